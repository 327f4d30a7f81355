//! The remote cache as one run uses it: opened on the first local miss (a warm run never contacts
//! it), each instance asked at most once, a bounded number of pulls under way at once, and the
//! actions whose remote copy was corrupt or untrusted, which this run's push replaces.

use std::cell::OnceCell;
use std::collections::BTreeSet;
use std::sync::Arc;

use rlmflow_cache::Digest;
use rlmflow_remote::Remote;

use crate::config::RemoteSettings;
use crate::ui::Ui;

/// The most pulls from the remote cache under way at once.
const MAX_PULLS: usize = 4;

pub struct Pulls<'a> {
    settings: Option<&'a RemoteSettings>,
    remote: OnceCell<Option<Arc<Remote>>>,
    under_way: usize,
    /// Instances asked already this run (a miss is not asked again).
    asked: Vec<bool>,
    /// Actions whose remote copy was found corrupt or untrusted.
    replace: BTreeSet<Digest>,
}

/// What to do about an instance missing from the local store.
pub enum Ask {
    /// Pull it now, from this remote.
    Now(Arc<Remote>),
    /// Wait: as many pulls as allowed are under way.
    Later,
    /// Compute it: there is no usable remote, or it was asked already.
    No,
}

impl<'a> Pulls<'a> {
    pub fn new(settings: Option<&'a RemoteSettings>, instances: usize) -> Pulls<'a> {
        Pulls { settings, remote: OnceCell::new(), under_way: 0, asked: vec![false; instances], replace: BTreeSet::new() }
    }

    /// The remote cache, opened once; `None` when there is none or it cannot be opened (which
    /// warns once).
    pub fn remote(&self, ui: &Ui) -> Option<&Arc<Remote>> {
        self.remote
            .get_or_init(|| match self.settings?.open() {
                Ok(remote) => {
                    if !remote.verified() {
                        ui.say(format!("  note     remote cache {}: its records are used unverified (no `remote_trusted_keys`)", remote.url()));
                    }
                    Some(Arc::new(remote))
                }
                Err(e) => {
                    ui.say(format!("  warning  remote cache not used: {e:#}"));
                    None
                }
            })
            .as_ref()
    }

    /// Whether instance `i`, missing locally, is pulled now (counted as under way), later, or
    /// not at all. A remote that went down answers every pull at once with a miss: not asked.
    pub fn ask(&mut self, i: usize, ui: &Ui) -> Ask {
        if self.asked[i] {
            return Ask::No;
        }
        let Some(remote) = self.remote(ui).filter(|r| r.down().is_none()).cloned() else { return Ask::No };
        if self.under_way == MAX_PULLS {
            return Ask::Later;
        }
        self.asked[i] = true;
        self.under_way += 1;
        Ask::Now(remote)
    }

    pub fn ended(&mut self) {
        self.under_way -= 1;
    }

    pub fn any_under_way(&self) -> bool {
        self.under_way > 0
    }

    /// The remote copy of `key` was corrupt or untrusted: this run's push replaces it.
    pub fn replace(&mut self, key: Digest) {
        self.replace.insert(key);
    }

    pub fn replaces(&self, key: &Digest) -> bool {
        self.replace.contains(key)
    }
}
