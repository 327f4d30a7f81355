//! Signed records and trusted keys, as Nix's binary caches sign `narinfo`s: a pusher signs each
//! action record it uploads with its ed25519 secret key; a reader configured with trusted public
//! keys uses a record only if one of them signed it. Anyone who can write to the bucket can then
//! still delete or damage records, but not make a key name an output no trusted pusher computed.
//!
//! Keys are text, `NAME:BASE64`: a secret key's base64 is its PKCS#8 document, a public key's its
//! 32 bytes. `rlmflow key generate NAME` makes a pair.

use anyhow::{Context as _, bail};
use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use ring::signature::{ED25519, Ed25519KeyPair, KeyPair as _, UnparsedPublicKey};
use rlmflow_cache::{ActionRecord, RecordSignature, SIGNED_FORMAT};

/// A pusher's secret key.
pub struct SigningKey {
    name: String,
    pair: Ed25519KeyPair,
}

/// A new key pair named `name`: (the secret key's text, the public key's text).
pub fn generate(name: &str) -> anyhow::Result<(String, String)> {
    check_name(name)?;
    let document = Ed25519KeyPair::generate_pkcs8(&ring::rand::SystemRandom::new()).map_err(|_| anyhow::anyhow!("generating an ed25519 key"))?;
    let pair = Ed25519KeyPair::from_pkcs8(document.as_ref()).map_err(|e| anyhow::anyhow!("reading the generated key: {e}"))?;
    Ok((format!("{name}:{}", BASE64.encode(document.as_ref())), format!("{name}:{}", BASE64.encode(pair.public_key().as_ref()))))
}

fn check_name(name: &str) -> anyhow::Result<()> {
    if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c)) {
        bail!("key name `{name}`: use letters, digits, `-`, `_` and `.`");
    }
    Ok(())
}

/// `NAME:BASE64` split, the name checked and the base64 decoded.
fn split(text: &str, what: &str) -> anyhow::Result<(String, Vec<u8>)> {
    let (name, data) = text.trim().split_once(':').with_context(|| format!("a {what} is NAME:BASE64"))?;
    check_name(name)?;
    let bytes = BASE64.decode(data).with_context(|| format!("the {what} `{name}` is not base64"))?;
    Ok((name.to_owned(), bytes))
}

impl SigningKey {
    /// A secret key from its text (`rlmflow key generate`'s `NAME.secret`).
    pub fn parse(text: &str) -> anyhow::Result<SigningKey> {
        let (name, document) = split(text, "secret key")?;
        let pair = Ed25519KeyPair::from_pkcs8(&document).map_err(|e| anyhow::anyhow!("the secret key `{name}` is not an ed25519 key ({e})"))?;
        Ok(SigningKey { name, pair })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// `record` with this key's signature (replacing an earlier one of the same name).
    pub fn sign(&self, record: &ActionRecord) -> ActionRecord {
        let signature = BASE64.encode(self.pair.sign(&record.signed_message()).as_ref());
        let mut signed = record.clone();
        signed.signatures.retain(|s| s.key != self.name);
        signed.signatures.push(RecordSignature { key: self.name.clone(), signature, format: SIGNED_FORMAT });
        signed
    }
}

/// The public keys whose signatures a reader accepts.
#[derive(Clone, Debug, Default)]
pub struct TrustedKeys(Vec<(String, Vec<u8>)>);

/// Whether a record may be used, by the trusted keys. A key is named by its name and its
/// fingerprint (the first characters of its public key's base64): several keys may share a name
/// while one is rotated.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Trust {
    /// A trusted key signed it.
    Signed { name: String, fingerprint: String },
    /// No signature at all.
    Unsigned,
    /// Signed only by keys not trusted here (their names).
    Untrusted(Vec<String>),
    /// A signature under a trusted key's name that none of the trusted keys of that name (their
    /// fingerprints) made of this record: forged or altered.
    Forged { name: String, fingerprints: Vec<String> },
    /// A trusted key's name with a signature in an earlier format, which left fields of the
    /// record unsigned: not used, whether genuine or not.
    Outdated(String),
}

impl TrustedKeys {
    /// `NAME:BASE64` public keys; an error names the first that is not one.
    pub fn parse(keys: &[String]) -> anyhow::Result<TrustedKeys> {
        let mut trusted = Vec::new();
        for text in keys {
            let (name, bytes) = split(text, "public key")?;
            if bytes.len() != 32 {
                bail!("the public key `{name}` has {} bytes; an ed25519 public key has 32", bytes.len());
            }
            trusted.push((name, bytes));
        }
        Ok(TrustedKeys(trusted))
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Whether `record` carries a valid signature by a trusted key.
    pub fn check(&self, record: &ActionRecord) -> Trust {
        if record.signatures.is_empty() {
            return Trust::Unsigned;
        }
        let message = record.signed_message();
        let (mut forged, mut outdated) = (None, None);
        for s in &record.signatures {
            // Every trusted key of the signature's name: while a key is rotated, the old and the
            // new are trusted side by side under one name, as Nix's `trusted-public-keys` allows.
            let mut keys = self.0.iter().filter(|(name, _)| *name == s.key).map(|(_, key)| key).peekable();
            if keys.peek().is_none() {
                continue;
            }
            if s.format != SIGNED_FORMAT {
                outdated = Some(s.key.clone());
                continue;
            }
            let signature = BASE64.decode(&s.signature).ok();
            if let Some(sig) = signature
                && let Some(key) = keys.find(|key| UnparsedPublicKey::new(&ED25519, key).verify(&message, &sig).is_ok())
            {
                return Trust::Signed { name: s.key.clone(), fingerprint: fingerprint(key) };
            }
            let fingerprints = self.0.iter().filter(|(name, _)| *name == s.key).map(|(_, key)| fingerprint(key)).collect();
            forged = Some(Trust::Forged { name: s.key.clone(), fingerprints });
        }
        match (forged, outdated) {
            (Some(forged), _) => forged,
            (None, Some(name)) => Trust::Outdated(name),
            (None, None) => Trust::Untrusted(record.signatures.iter().map(|s| s.key.clone()).collect()),
        }
    }
}

/// A public key's fingerprint: the first 12 characters of its base64.
pub fn fingerprint(key: &[u8]) -> String {
    BASE64.encode(key).chars().take(12).collect()
}

/// Who vouched for `record`, for a person reading a warning: `unsigned` or `signed by ci, laptop`.
pub fn signers(record: &ActionRecord) -> String {
    if record.signatures.is_empty() {
        return "unsigned".to_owned();
    }
    format!("signed by {}", record.signatures.iter().map(|s| s.key.as_str()).collect::<Vec<_>>().join(", "))
}

impl std::fmt::Display for Trust {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Trust::Signed { name, fingerprint } => write!(f, "signed by `{name}` (key {fingerprint})"),
            Trust::Unsigned => f.write_str("unsigned"),
            Trust::Untrusted(names) => write!(f, "signed only by keys not trusted here ({})", names.join(", ")),
            Trust::Forged { name, fingerprints } => {
                write!(f, "its signature by `{name}` does not match it (forged or altered); trusted keys named `{name}`: {}", fingerprints.join(", "))
            }
            Trust::Outdated(name) => write!(
                f,
                "signed by `{name}` in record format 1, which leaves its metrics, summary, times and platform unsigned (push it again to sign it whole)"
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rlmflow_cache::{Digest, Preimage};

    fn record(output: &[u8]) -> ActionRecord {
        let preimage =
            Preimage { operator: "clip".into(), operator_version: 3, config: serde_json::json!({}), seed: 1, inputs: vec![], platform: None };
        ActionRecord {
            key: preimage.key(),
            preimage,
            output: Digest::of(output),
            files: 1,
            bytes: 10,
            started: String::new(),
            duration_s: 0.0,
            metrics: serde_json::Value::Null,
            summary: String::new(),
            platform: None,
            signatures: Vec::new(),
            pulled: None,
        }
    }

    #[test]
    fn only_a_trusted_keys_signature_of_this_very_record_is_trusted() {
        let (ci_secret, ci_public) = generate("ci").unwrap();
        let (other_secret, _) = generate("laptop").unwrap();
        let ci = SigningKey::parse(&ci_secret).unwrap();
        let trusted = TrustedKeys::parse(std::slice::from_ref(&ci_public)).unwrap();
        let ci_key = fingerprint(&BASE64.decode(ci_public.split_once(':').unwrap().1).unwrap());
        let signed = |key: &str| Trust::Signed { name: "ci".into(), fingerprint: key.to_owned() };
        let forged = |keys: &[&str]| Trust::Forged { name: "ci".into(), fingerprints: keys.iter().map(|k| k.to_string()).collect() };
        let good = ci.sign(&record(b"trained"));
        assert_eq!(trusted.check(&good), signed(&ci_key));
        assert_eq!(trusted.check(&record(b"trained")), Trust::Unsigned);
        assert_eq!(trusted.check(&SigningKey::parse(&other_secret).unwrap().sign(&record(b"trained"))), Trust::Untrusted(vec!["laptop".into()]));
        // The same signature on a record naming another output: forged.
        let mut forged_record = record(b"random init");
        forged_record.signatures = good.signatures.clone();
        assert_eq!(trusted.check(&forged_record), forged(&[&ci_key]));
        // Every field a reader is shown is signed: metrics, summary, times, platform.
        let alterations: [fn(&mut ActionRecord); 5] = [
            |r| r.metrics = serde_json::json!({"top1": 0.99}),
            |r| r.summary = "FORGED".into(),
            |r| r.duration_s = 1.0,
            |r| r.started = "2020-01-01T00:00:00Z".into(),
            |r| r.platform = Some(serde_json::json!({"cpu": "forged"})),
        ];
        for alter in alterations {
            let mut altered = good.clone();
            alter(&mut altered);
            assert_eq!(trusted.check(&altered), forged(&[&ci_key]), "{altered:?}");
        }
        // A signature of the first format, which covered the output only: named as old, not used.
        let mut old = good.clone();
        old.signatures[0].format = 1;
        assert_eq!(trusted.check(&old), Trust::Outdated("ci".into()));
        let parsed: RecordSignature = serde_json::from_str(r#"{"key": "ci", "signature": "AAAA"}"#).unwrap();
        assert_eq!(parsed.format, 1, "a signature without its format is of the first");
        // Signing again replaces the signer's own signature.
        assert_eq!(ci.sign(&good).signatures.len(), 1);
        assert!(TrustedKeys::parse(&["ci:AAAA".into()]).unwrap_err().to_string().contains("has 3 bytes"));
        // Rotation: the old and the new key trusted under one name, each one's records trusted; a
        // third key of that name, not trusted, is still a forgery.
        let (new_secret, new_public) = generate("ci").unwrap();
        let new_key = fingerprint(&BASE64.decode(new_public.split_once(':').unwrap().1).unwrap());
        let both = TrustedKeys::parse(&[ci_public, new_public]).unwrap();
        assert_eq!(both.check(&good), signed(&ci_key));
        assert_eq!(both.check(&SigningKey::parse(&new_secret).unwrap().sign(&record(b"trained"))), signed(&new_key));
        let (impostor, _) = generate("ci").unwrap();
        let impostor_signed = both.check(&SigningKey::parse(&impostor).unwrap().sign(&record(b"trained")));
        assert_eq!(impostor_signed, forged(&[&ci_key, &new_key]));
        assert!(impostor_signed.to_string().ends_with(&format!("trusted keys named `ci`: {ci_key}, {new_key}")), "{impostor_signed}");
        assert!(SigningKey::parse("no colon").is_err());
    }
}
