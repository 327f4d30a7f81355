//! Which remotes a client can use, and opening one: the URL and the `AWS_*` variables checked
//! before any client is built (a malformed endpoint would otherwise panic inside the S3 client).

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context as _, bail};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::{ClientOptions, ObjectStore, RetryConfig};

use crate::Remote;
use crate::link::{self, Watch, WatchedConnector};
use crate::signing::TrustedKeys;

/// `Ok` for a remote URL this client can use, else what is wrong with it and what is valid:
/// checked before any client is built (a malformed endpoint would otherwise panic inside the S3
/// client), for `[pipeline] remote` at validation and for `--remote` before a run.
pub fn check_url(url: &str) -> Result<(), BadRemote> {
    const VALID: &str = "valid: s3://bucket/prefix, https://host/path (WebDAV), file:///path";
    let bad = |problem: String| Err(BadRemote { variable: None, problem });
    if let Some(rest) = url.strip_prefix("s3://") {
        if rest.split('/').next().is_none_or(str::is_empty) {
            return bad(format!("`{url}` names no bucket; {VALID}"));
        }
        // Every variable the S3 client reads, and the endpoint it names.
        s3_from_env()?;
        for var in ["AWS_ENDPOINT_URL", "AWS_ENDPOINT"] {
            if let Ok(endpoint) = std::env::var(var) {
                let in_variable = |problem| BadRemote { variable: Some(var.to_owned()), problem };
                check_endpoint(&format!("the environment variable {var}"), &aws_value(var, &endpoint)?).map_err(in_variable)?;
            }
        }
        Ok(())
    } else if url.starts_with("http://") || url.starts_with("https://") {
        check_endpoint("the remote", url).or_else(bad)
    } else if let Some(path) = url.strip_prefix("file://") {
        match path {
            "" => bad(format!("`{url}` names no directory; {VALID}")),
            p if !Path::new(p).is_absolute() => bad(format!("`{url}` is not an absolute path; {VALID}")),
            _ => Ok(()),
        }
    } else {
        bad(format!("`{url}`: unknown scheme; {VALID}"))
    }
}

/// A remote URL, or an `AWS_*` variable the S3 client reads, that this client cannot use:
/// [`check_url`]'s answer, before any client is built.
#[derive(Clone, Debug, PartialEq)]
pub struct BadRemote {
    /// The environment variable at fault; `None`: the URL.
    pub variable: Option<String>,
    /// What is wrong, and what would be valid (it names the variable, never its value).
    pub problem: String,
}

impl std::fmt::Display for BadRemote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.problem)
    }
}

impl std::error::Error for BadRemote {}

/// The S3 client's settings from the standard `AWS_*` variables, read as
/// `AmazonS3Builder::from_env` reads them, but each value without surrounding whitespace (a value
/// from a secrets file ends with a newline more often than not) and a control character inside a
/// value refused by the variable's name: the client panics on either.
fn s3_from_env() -> Result<AmazonS3Builder, BadRemote> {
    let mut builder = AmazonS3Builder::new();
    for (name, value) in std::env::vars_os().filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?))) {
        if let Some(key) = name.starts_with("AWS_").then(|| name.to_ascii_lowercase().parse::<AmazonS3ConfigKey>().ok()).flatten() {
            builder = builder.with_config(key, aws_value(&name, &value)?);
        }
    }
    Ok(builder)
}

/// The value of the environment variable `name` without surrounding whitespace; an error naming
/// the variable (never its value: it may be a secret) for a control character inside it.
fn aws_value(name: &str, value: &str) -> Result<String, BadRemote> {
    let trimmed = value.trim();
    match trimmed.char_indices().find(|(_, c)| c.is_control()) {
        Some((at, c)) => Err(BadRemote {
            variable: Some(name.to_owned()),
            problem: format!(
                "the environment variable {name} holds the control character {c:?} at byte {at} of its value; valid: a value without control characters (surrounding whitespace is dropped)"
            ),
        }),
        None => Ok(trimmed.to_owned()),
    }
}

/// `Ok` for an http(s) URL with a host (and a valid port).
fn check_endpoint(what: &str, endpoint: &str) -> Result<(), String> {
    let valid = "valid: http(s)://host[:port][/path]";
    let url = reqwest::Url::parse(endpoint).map_err(|e| format!("{what} `{endpoint}` is not a URL ({e}); {valid}"))?;
    if !matches!(url.scheme(), "http" | "https") || url.host_str().is_none_or(str::is_empty) {
        return Err(format!("{what} `{endpoint}` is not an http(s) URL with a host; {valid}"));
    }
    Ok(())
}

impl Remote {
    /// `s3://bucket/prefix` (endpoint and credentials from the standard `AWS_*` variables,
    /// `AWS_ENDPOINT_URL` for a non-AWS server), `http(s)://host/path` (WebDAV, a Bazel-style
    /// HTTP cache) or `file:///path`. A bad URL or endpoint is an error ([`check_url`]).
    pub fn open(url: &str, push: bool, timeout: Duration) -> anyhow::Result<Remote> {
        check_url(url).map_err(|problem| anyhow::anyhow!("remote {problem}"))?;
        // TLS on ring; an error only says a provider is installed already.
        let _ = rustls::crypto::ring::default_provider().install_default();
        // No whole-request timeout: it would cut off a large transfer that is still moving. The
        // link's client bounds the wait to connect; `call` bounds the wait for the next bytes
        // either way.
        let client = ClientOptions::new().with_timeout_disabled().with_allow_http(true);
        let retry = RetryConfig { max_retries: 1, retry_timeout: timeout, ..RetryConfig::default() };
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let objects: Arc<dyn ObjectStore> = if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            let store = s3_from_env()
                .map_err(|problem| anyhow::anyhow!("remote {problem}"))?
                .with_bucket_name(bucket)
                .with_client_options(client)
                .with_http_connector(WatchedConnector { timeout })
                .with_retry(retry)
                .build()
                .with_context(|| format!("remote `{url}`"))?;
            // A bucket that does not exist would read as an empty cache: asked once here. A
            // server that does not answer is not an error yet (the first request marks it down).
            let listed = runtime.block_on(link::bounded(&Watch::new(), timeout, store.list_with_delimiter(None), &mut |_| {}));
            if let Some(Err(e)) = listed
                && (matches!(e, object_store::Error::NotFound { .. }) || e.to_string().contains("NoSuchBucket"))
            {
                let endpoint = std::env::var("AWS_ENDPOINT_URL")
                    .or_else(|_| std::env::var("AWS_ENDPOINT"))
                    .map_or_else(|_| "AWS".into(), |e| e.trim().to_owned());
                bail!("remote `{url}`: bucket `{bucket}` does not exist at {endpoint}");
            }
            Arc::new(object_store::prefix::PrefixStore::new(store, prefix))
        } else if url.starts_with("http://") || url.starts_with("https://") {
            Arc::new(
                object_store::http::HttpBuilder::new()
                    .with_url(url)
                    .with_client_options(client)
                    .with_http_connector(WatchedConnector { timeout })
                    .with_retry(retry)
                    .build()
                    .with_context(|| format!("remote `{url}`"))?,
            )
        } else if let Some(path) = url.strip_prefix("file://") {
            std::fs::create_dir_all(path).with_context(|| format!("remote `{url}`: creating {path}"))?;
            Arc::new(object_store::local::LocalFileSystem::new_with_prefix(path).with_context(|| format!("remote `{url}`"))?)
        } else {
            bail!("remote `{url}`: unknown scheme; valid: s3://bucket/prefix, https://host/path (WebDAV), file:///path");
        };
        Ok(Remote {
            url: url.to_owned(),
            objects,
            runtime,
            timeout,
            push,
            down: Mutex::new(None),
            told: Default::default(),
            trusted: TrustedKeys::default(),
            signer: None,
            parts: !url.starts_with("http"),
        })
    }
}
