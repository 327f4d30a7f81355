//! What a run shows on a terminal: one line per event, a bar per running stage and per artifact
//! moving to or from the remote cache; plain lines when stdout is not a terminal, nothing but the
//! event log with `--json`.

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use rlmflow_cache::Store;

/// Progress bars on a terminal; plain lines otherwise.
#[derive(Clone)]
pub(crate) struct Ui {
    multi: MultiProgress,
    quiet: bool,
}

impl Ui {
    pub(crate) fn new(json: bool) -> Ui {
        let multi = MultiProgress::new();
        if json {
            multi.set_draw_target(ProgressDrawTarget::hidden());
        }
        Ui { multi, quiet: json }
    }

    pub(crate) fn say(&self, line: String) {
        if self.quiet {
            return;
        }
        if self.multi.is_hidden() {
            println!("{line}");
        } else {
            let _ = self.multi.println(line);
        }
    }

    /// A running stage's spinner, until the stage reports a length.
    pub(crate) fn bar(&self, label: &str) -> ProgressBar {
        let bar = self.multi.add(ProgressBar::new_spinner());
        bar.set_style(ProgressStyle::with_template("  {spinner} {prefix} {elapsed} {msg}").unwrap());
        bar.set_prefix(label.to_owned());
        bar.enable_steady_tick(std::time::Duration::from_millis(120));
        bar
    }

    pub(crate) fn bar_style() -> ProgressStyle {
        ProgressStyle::with_template("  {prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed}, eta {eta})").unwrap().progress_chars("=> ")
    }

    /// A bar for `label`'s artifact moving to or from the remote cache (`verb`: "pulling",
    /// "pushing"), drawn once its bytes move (a miss, or an object the other side has, draws
    /// none) and cleared when dropped.
    pub(crate) fn transfer(&self, label: &str, verb: &str) -> TransferBar {
        TransferBar { ui: self.clone(), label: format!("{label} {verb}"), bar: None }
    }
}

/// See [`Ui::transfer`].
pub(crate) struct TransferBar {
    ui: Ui,
    label: String,
    bar: Option<ProgressBar>,
}

impl TransferBar {
    /// `done` of `total` bytes have moved.
    pub(crate) fn moved(&mut self, done: u64, total: u64) {
        let bar = self.bar.get_or_insert_with(|| {
            let bar = self.ui.multi.add(ProgressBar::new(total));
            let style = ProgressStyle::with_template("  {prefix} [{bar:30}] {bytes}/{total_bytes} ({bytes_per_sec}, eta {eta})").unwrap();
            bar.set_style(style.progress_chars("=> "));
            bar.set_prefix(self.label.clone());
            bar
        });
        bar.set_position(done);
    }
}

impl Drop for TransferBar {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// What the store met and treated as absent (damaged records, refs, plans), on stderr.
pub(crate) fn print_store_warnings(store: Option<&Store>) {
    for warning in store.map(Store::take_warnings).unwrap_or_default() {
        eprintln!("warning: {warning}");
    }
}
