//! `cargo bench --bench engine`: the engine's speed targets, each printed with its ratio to the
//! target (above 1.00 meets it).
//!
//! * warm no-op run (every stage cached), as a user runs it: a new `rlmflow-test run` process
//!   each time, its run history and results links written; 22 instances (`examples/ci.toml`'s
//!   count) target <= 10 ms, 100 instances target <= 50 ms
//! * planning 10,000 stage instances: parse, validate, fan out, compute every action key;
//!   target <= 1 s
//! * hashing throughput on one core, in memory and from a file; target >= 1 GB/s
//! * an unchanged tracked recording (4,000 files, 1 GiB) checked against the digests the store
//!   recorded, against hashing every file: target >= 3x faster
//! * dispatch through HyperQueue (a local cluster: one worker, two cores) against the local
//!   executor on the same 20-action pipeline, fresh stores: the cold run's extra time per
//!   action, target <= 100 ms; the warm no-op run (nothing submitted), target <= 1.25x local

use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use rlmflow_cache::{Digest, hash_file};

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

fn report(name: &str, value: f64, unit: &str, target: f64, higher_is_better: bool) {
    let ratio = if higher_is_better { value / target } else { target / value };
    let verdict = if ratio >= 1.0 { "meets" } else { "MISSES" };
    println!("{name:<42} {value:>10.3} {unit:<5} target {target} {unit}: {ratio:.2}x ({verdict})");
}

/// A warm no-op run of `pairs` source and map stages, against `target_ms`.
fn warm_noop(dir: &Path, pairs: usize, target_ms: f64) {
    let dir = &dir.join(format!("noop-{pairs}"));
    std::fs::create_dir_all(dir).unwrap();
    let mut text = format!("[pipeline]\nname = \"noop{pairs}\"\n");
    for i in 0..pairs {
        write!(text, "[stages.s{i}]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"t{i}\"\n").unwrap();
        write!(text, "[stages.m{i}]\nkind = \"map\"\noperator = \"shout\"\ninputs = {{ text = \"s{i}\" }}\n").unwrap();
    }
    std::fs::write(dir.join("p.toml"), text).unwrap();
    // In a git work tree with a commit, as a user's pipeline is (where git is installed).
    let git =
        |args: &[&str]| Command::new("git").current_dir(dir).args(["-c", "user.name=bench", "-c", "user.email=bench@localhost"]).args(args).output();
    let _ = (git(&["init", "-q"]), git(&["add", "p.toml"]), git(&["commit", "-q", "-m", "bench"]));
    let run = || {
        let t0 = Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_rlmflow-test")).current_dir(dir).args(["run", "p.toml", "--json"]).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        (t0.elapsed().as_secs_f64() * 1e3, String::from_utf8_lossy(&out.stdout).into_owned())
    };
    run(); // cold: computes every stage
    let times: Vec<f64> = (0..21)
        .map(|_| {
            let (ms, out) = run();
            assert!(out.contains(&format!(r#""reused":{}"#, 2 * pairs)), "the warm run reused everything");
            ms
        })
        .collect();
    report(&format!("warm no-op run, {} stages (median of 21)", 2 * pairs), median(times), "ms", target_ms, false);
}

fn planning() {
    let mut text =
        String::from("[pipeline]\nname = \"plan10k\"\nmax_instances = 10100\n[stages.source]\noperator = \"write-text\"\n[stages.source.variants]\n");
    for i in 0..100 {
        writeln!(text, "v{i} = {{ text = \"t{i}\" }}").unwrap();
    }
    text.push_str("[stages.map]\noperator = \"shout\"\n[stages.map.variants]\n");
    for i in 0..100 {
        writeln!(text, "w{i} = {{ suffix = \"{i}\" }}").unwrap();
    }
    let registry = rlmflow_e2e::registry();
    let times: Vec<f64> = (0..5)
        .map(|_| {
            let t0 = Instant::now();
            let pipeline = rlmflow_engine::config::parse(Path::new("plan10k.toml"), &text, &registry).unwrap();
            let plan = rlmflow_engine::plan::plan(&pipeline);
            // Every instance's key, with every upstream output known.
            let outputs: Vec<Option<Digest>> = (0..plan.instances.len()).map(|i| Some(Digest::of(&i.to_le_bytes()))).collect();
            let keys: Vec<Digest> = (0..plan.instances.len()).map(|i| plan.preimage(i, &registry, &outputs).unwrap().unwrap().key()).collect();
            assert_eq!(keys.len(), 10_100);
            t0.elapsed().as_secs_f64()
        })
        .collect();
    report("planning 10,100 stage instances (median of 5)", median(times), "s", 1.0, false);
}

fn hashing(dir: &Path) {
    let size = 256 << 20;
    let data: Vec<u8> = (0..size).map(|i| ((i * 2654435761usize) >> 13) as u8).collect();
    let times: Vec<f64> = (0..5)
        .map(|_| {
            let t0 = Instant::now();
            std::hint::black_box(blake3::Hasher::new().update(&data).finalize());
            t0.elapsed().as_secs_f64()
        })
        .collect();
    report("BLAKE3 in memory, one core (256 MiB)", size as f64 / median(times) / 1e9, "GB/s", 1.0, true);
    let file = dir.join("blob");
    std::fs::write(&file, &data).unwrap();
    let times: Vec<f64> = (0..5)
        .map(|_| {
            let t0 = Instant::now();
            std::hint::black_box(hash_file(&file).unwrap());
            t0.elapsed().as_secs_f64()
        })
        .collect();
    report("hash_file, one core (256 MiB, page cache)", size as f64 / median(times) / 1e9, "GB/s", 1.0, true);
}

/// A tracked path's fingerprint with recorded digests (a stat per file) against hashing every
/// file, both from the page cache.
fn tracked(dir: &Path) {
    let recording = dir.join("recording");
    std::fs::create_dir_all(&recording).unwrap();
    let written = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
    for i in 0..4000u32 {
        let path = recording.join(format!("{i:06}.npy"));
        let mut bytes = vec![0u8; 256 << 10];
        bytes[..4].copy_from_slice(&i.to_le_bytes());
        std::fs::write(&path, bytes).unwrap();
        // Written long before it is hashed, so the racy rule does not hash it again.
        std::fs::File::options().write(true).open(&path).unwrap().set_modified(written).unwrap();
    }
    let store = rlmflow_cache::Store::open(&dir.join("tracked-store")).unwrap();
    let time = |store: Option<&rlmflow_cache::Store>| {
        let t0 = Instant::now();
        std::hint::black_box(rlmflow_cache::external::fingerprint(store, &rlmflow_cache::external::Source::Path(recording.clone())).unwrap());
        t0.elapsed().as_secs_f64()
    };
    let hashing = median((0..5).map(|_| time(None)).collect());
    time(Some(&store));
    let recorded = median((0..5).map(|_| time(Some(&store))).collect());
    report("unchanged recording, recorded vs hashed (1 GiB)", hashing / recorded, "x", 3.0, true);
}

/// Milliseconds of one `rlmflow-test run` in `dir`, which must report `expect`.
fn timed_run(dir: &Path, extra: &[&str], expect: &str) -> f64 {
    let t0 = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow-test")).current_dir(dir).args(["run", "p.toml", "--json"]).args(extra).output().unwrap();
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success() && stdout.contains(expect), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    ms
}

fn dispatch(dir: &Path) {
    let mut text = String::from("[pipeline]\nname = \"dispatch\"\n\n[pipeline.hyperqueue]\nworkers = 1\ncores = 2\n");
    for i in 0..10 {
        write!(text, "[stages.s{i}]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"t{i}\"\n").unwrap();
        write!(text, "[stages.m{i}]\nkind = \"map\"\noperator = \"shout\"\ninputs = {{ text = \"s{i}\" }}\n").unwrap();
    }
    let mut cold = [Vec::new(), Vec::new()];
    let mut warm = [Vec::new(), Vec::new()];
    for round in 0..3 {
        for (e, executor) in ["local", "hyperqueue"].into_iter().enumerate() {
            let run_dir = dir.join(format!("dispatch-{executor}-{round}"));
            std::fs::create_dir_all(&run_dir).unwrap();
            std::fs::write(run_dir.join("p.toml"), &text).unwrap();
            cold[e].push(timed_run(&run_dir, &["--executor", executor], r#""ran":20"#));
            warm[e].extend((0..5).map(|_| timed_run(&run_dir, &["--executor", executor], r#""reused":20"#)));
        }
    }
    let (local, hq) = (median(cold[0].clone()), median(cold[1].clone()));
    println!("cold, 20 actions: local {local:.0} ms, HyperQueue {hq:.0} ms (medians of 3; HyperQueue's includes starting its cluster)");
    report("HyperQueue extra time per action, cold", (hq - local) / 20.0, "ms", 100.0, false);
    let (local, hq) = (median(warm[0].clone()), median(warm[1].clone()));
    println!("warm no-op, 20 actions: local {local:.1} ms, HyperQueue {hq:.1} ms (medians of 15)");
    report("warm no-op, HyperQueue / local", hq / local, "x", 1.25, false);
}

fn main() {
    let dir = std::env::temp_dir().join(format!("rlmflow-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    warm_noop(&dir, 11, 10.0);
    warm_noop(&dir, 50, 50.0);
    planning();
    hashing(&dir);
    tracked(&dir);
    dispatch(&dir);
    let _ = std::fs::remove_dir_all(&dir);
}
