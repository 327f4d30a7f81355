//! Model stages placed on a machine's GPUs and packed by their memory estimates, on an
//! inventory the tests declare (`RLMFLOW_GPU_INVENTORY`): the scheduler's decisions, and what
//! each stage's worker is shown, without a GPU.

use crate::harness::*;

/// Two H100s of 80 GiB, as `nvidia-smi` numbers them.
const TWO: &str = "0:H100:81559,1:H100:81559";

/// Source stages named `names`, each asking for a GPU with a peak estimate of `mib` (0: none).
fn gpu_stages(names: &[&str], mib: u64) -> String {
    let mut text = "[pipeline]\nname = \"g\"\n".to_owned();
    for name in names {
        text += &format!(
            "[stages.{name}]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"{name}\"\nsteps = 2\nstep_ms = 100\ngpu = true\nmemory_mib = {mib}\n"
        );
    }
    text
}

/// `run --json` with the inventory `gpus`.
fn run_on(s: &Scratch, gpus: &str, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["run", "p.toml", "--json"];
    args.extend_from_slice(extra);
    s.command(&args).env("RLMFLOW_GPU_INVENTORY", gpus).output().unwrap()
}

fn events_of(out: &std::process::Output) -> Events {
    assert_eq!(out.status.code(), Some(0), "stdout:\n{}\nstderr:\n{}", text(&out.stdout), text(&out.stderr));
    Events::parse(&out.stdout)
}

/// `start` and `finish` in the order the run wrote them.
fn order(events: &Events) -> Vec<&'static str> {
    events
        .0
        .iter()
        .filter_map(|e| match e["event"].as_str() {
            Some("stage_started") => Some("start"),
            Some("stage_finished") => Some("finish"),
            _ => None,
        })
        .collect()
}

/// Each started stage and the device its event names.
fn devices(events: &Events) -> Vec<(String, String)> {
    let started = events.of("stage_started");
    started.iter().map(|e| (e["stage"].as_str().unwrap().to_owned(), e["device"].as_str().unwrap_or("none").to_owned())).collect()
}

/// Each stage and the `CUDA_VISIBLE_DEVICES` its worker saw.
fn shown(s: &Scratch) -> Vec<(String, String)> {
    let starts = s.trace().into_iter().filter_map(|l| {
        let rest = l.strip_prefix("start write-text ")?.to_owned();
        let stage = rest.split(' ').next()?.to_owned();
        let gpu = rest.split(" gpu=").nth(1)?.split(' ').next()?.to_owned();
        Some((stage, gpu))
    });
    let mut found: Vec<(String, String)> = starts.collect();
    found.sort();
    found
}

#[test]
fn two_gpus_run_two_stages_at_once_each_worker_seeing_its_own() {
    let s = Scratch::new("two-gpus");
    s.pipeline(&gpu_stages(&["a", "b"], 30_000));
    let events = events_of(&run_on(&s, TWO, &["--jobs", "2"]));
    assert_eq!(order(&events), ["start", "start", "finish", "finish"]);
    let mut placed = devices(&events);
    placed.sort();
    assert_eq!(placed, [("a".into(), "cuda:0".into()), ("b".into(), "cuda:1".into())]);
    assert_eq!(shown(&s), [("a".into(), "0".into()), ("b".into(), "1".into())], "each worker sees exactly its GPU");

    // A person's run names the device on each stage's line.
    s.pipeline(&gpu_stages(&["a2", "b2"], 30_000));
    let out = s.command(&["run", "p.toml", "--jobs", "2"]).env("RLMFLOW_GPU_INVENTORY", TWO).output().unwrap();
    let stdout = text(&out.stdout);
    assert!(stdout.contains("gpus     cuda:0 (H100, 79.6 GiB), cuda:1 (H100, 79.6 GiB)"), "{stdout}");
    assert!(stdout.lines().any(|l| l.contains("ran      a2") && l.contains(" cuda:0")), "{stdout}");
    assert!(stdout.lines().any(|l| l.contains("ran      b2") && l.contains(" cuda:1")), "{stdout}");
}

#[test]
fn small_stages_share_one_gpu_by_their_estimates_and_a_large_or_unestimated_one_waits_for_it_whole() {
    let s = Scratch::new("pack");
    let one = "0:H100:81559";
    s.pipeline(&gpu_stages(&["a", "b", "c"], 20_000));
    let three = events_of(&run_on(&s, one, &["--jobs", "3"]));
    assert_eq!(order(&three), ["start", "start", "start", "finish", "finish", "finish"], "3 x 20 GiB fit in 80 GiB");
    assert!(devices(&three).iter().all(|(_, d)| d == "cuda:0"));
    assert!(shown(&s).iter().all(|(_, gpu)| gpu == "0"));

    // Two that do not fit beside each other (within the headroom) run one after the other.
    s.pipeline(&gpu_stages(&["d", "e"], 50_000));
    assert_eq!(order(&events_of(&run_on(&s, one, &["--jobs", "2"]))), ["start", "finish", "start", "finish"]);
    // Without an estimate a stage holds its GPU whole.
    s.pipeline(&gpu_stages(&["f", "g"], 0));
    assert_eq!(order(&events_of(&run_on(&s, one, &["--jobs", "2"]))), ["start", "finish", "start", "finish"]);
}

#[test]
fn gpus_restrict_the_inventory_and_name_what_is_there_when_wrong() {
    let s = Scratch::new("restrict");
    s.pipeline(&gpu_stages(&["a", "b"], 0));
    let events = events_of(&run_on(&s, TWO, &["--jobs", "2", "--gpus", "1"]));
    assert_eq!(order(&events), ["start", "finish", "start", "finish"], "one GPU left, each stage holds it whole");
    assert!(devices(&events).iter().all(|(_, d)| d == "cuda:1"));
    assert!(shown(&s).iter().all(|(_, gpu)| gpu == "1"));

    // The file's `gpus`, and the dry run's inventory.
    s.pipeline(&gpu_stages(&["c", "d"], 0).replace("name = \"g\"", "name = \"g\"\ngpus = [0]"));
    let dry = s.command(&["run", "p.toml", "--dry-run"]).env("RLMFLOW_GPU_INVENTORY", TWO).output().unwrap();
    let listed = text(&dry.stdout);
    assert!(listed.contains("gpu       cuda:0 (H100, 79.6 GiB)") && !listed.contains("cuda:1"), "{listed}");
    let events = events_of(&run_on(&s, TWO, &["--jobs", "2"]));
    assert!(devices(&events).iter().all(|(_, d)| d == "cuda:0"));

    let out = run_on(&s, TWO, &["--gpus", "5"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("gpus: there is no GPU 5 here (this machine's, as CUDA_VISIBLE_DEVICES shows them: 0, 1)"), "{}", text(&out.stderr));
    s.pipeline(&gpu_stages(&["c"], 0).replace("name = \"g\"", "name = \"g\"\ngpus = \"all\""));
    let out = run_on(&s, TWO, &[]);
    assert!(text(&out.stderr).contains("p.toml:3: pipeline.gpus: must be a list of GPU indices, not \"all\""), "{}", text(&out.stderr));
}

#[test]
fn a_stage_out_of_memory_beside_others_is_retried_alone_and_says_so() {
    let s = Scratch::new("oom");
    s.pipeline(&format!("{}oom_once = true\n", gpu_stages(&["a", "b"], 20_000)).replace("text = \"a\"\nsteps = 2", "text = \"a\"\nsteps = 3"));
    let events = events_of(&run_on(&s, "0:H100:81559", &["--jobs", "2"]));
    // Both started on the one GPU; b (its `oom_once` is last in the file) ran out of memory.
    let retry = events.of("stage_retry");
    assert_eq!(retry.len(), 1, "{:?}", events.0);
    assert_eq!(retry[0]["stage"], "b");
    let error = retry[0]["error"].as_str().unwrap();
    assert!(error.starts_with("CUDA out of memory") && error.ends_with("(out of memory on cuda:0, which it shared: retried alone on a GPU)"), "{error}");
    // Its second attempt started with the GPU to itself: after a finished.
    let seq: Vec<(String, String)> = events
        .0
        .iter()
        .filter_map(|e| Some((e["event"].as_str()?.to_owned(), e["stage"].as_str()?.to_owned())))
        .filter(|(name, _)| name == "stage_started" || name == "stage_finished")
        .collect();
    let second_b = seq.iter().rposition(|(name, stage)| name == "stage_started" && stage == "b").unwrap();
    let a_done = seq.iter().position(|(name, stage)| name == "stage_finished" && stage == "a").unwrap();
    assert!(a_done < second_b, "{seq:?}");
    assert_eq!((events.status_of("a"), events.status_of("b")), ("ran".to_owned(), "ran".to_owned()));
}
