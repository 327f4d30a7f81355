//! `cargo xtask bench -p rlmflow --bench script`: what a `script` stage costs over its program
//! alone. A no-op program (`sh -c 'echo > out'`, and `python -c` writing a file in rlmflow's own
//! environment) is run directly and as a stage of a pipeline whose other stage is cached, the
//! stage's key changed each time (`--set x.settings.i=N`) so it computes; the median of 21 of
//! each. Printed: the program alone, the whole `rlmflow run` and the action (the stage's
//! `duration_s`: its process, the program and the output's check and commit), and the overhead
//! of each over the program alone.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

const RUNS: usize = 21;

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

fn ms(f: impl FnOnce()) -> f64 {
    let t0 = Instant::now();
    f();
    t0.elapsed().as_secs_f64() * 1e3
}

/// The program `run` (a TOML array) alone and as a stage, medians in ms.
fn overhead(dir: &Path, name: &str, run: &[&str], alone: &mut dyn FnMut(&Path)) {
    let dir = dir.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    let run_toml: Vec<String> = run.iter().map(|a| serde_json::json!(a).to_string()).collect();
    let pipeline = format!(
        "[pipeline]\nname = \"bench\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 4\nradar = {{ image = 16 }}\n\
         [stages.x]\nkind = \"files\"\noperator = \"script\"\ninputs = {{ scenes = \"scenes\" }}\nrun = [{}]\n",
        run_toml.join(", ")
    );
    std::fs::write(dir.join("p.toml"), pipeline).unwrap();
    let rlmflow = |i: usize| {
        let out = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
            .current_dir(&dir)
            .args(["run", "p.toml", "--json", "--set", &format!("x.settings.i={i}")])
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        text
    };
    rlmflow(0); // the scenes, and the environment where the program is Python
    let scratch = dir.join("alone");
    std::fs::create_dir_all(&scratch).unwrap();
    let program: Vec<f64> = (0..RUNS).map(|_| ms(|| alone(&scratch))).collect();
    let (mut wall, mut action) = (Vec::new(), Vec::new());
    for i in 1..=RUNS {
        let t0 = Instant::now();
        let events = rlmflow(i);
        wall.push(t0.elapsed().as_secs_f64() * 1e3);
        let finished = events.lines().find(|l| l.contains("\"stage_finished\"") && l.contains("\"stage\":\"x\"")).expect("x ran");
        let finished: serde_json::Value = serde_json::from_str(finished).unwrap();
        assert_eq!(finished["status"], "ran", "{finished}");
        action.push(finished["duration_s"].as_f64().unwrap() * 1e3);
    }
    let (program, wall, action) = (median(program), median(wall), median(action));
    println!(
        "{name:<8} program alone {program:>7.1} ms | rlmflow run {wall:>7.1} ms (+{:.1} ms) | action {action:>7.1} ms (+{:.1} ms) | run/program {:.2}x",
        wall - program,
        action - program,
        wall / program
    );
}

fn main() {
    let dir = std::env::temp_dir().join(format!("rlmflow-bench-script-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    overhead(&dir, "sh", &["sh", "-c", "echo x > $RLMFLOW_OUTPUT/x"], &mut |out| {
        let status = Command::new("sh").args(["-c", "echo x > $OUT/x"]).env("OUT", out).status().unwrap();
        assert!(status.success());
    });
    let python = rlmflow_python::ensure(&mut |note| eprintln!("{note}")).unwrap().python;
    let code = "import os, pathlib; pathlib.Path(os.environ['RLMFLOW_OUTPUT'], 'x').write_text('x')";
    overhead(&dir, "python", &["python", "-c", code], &mut |out| {
        let status = Command::new(&python).args(["-c", code]).env("RLMFLOW_OUTPUT", out).status().unwrap();
        assert!(status.success());
    });
    let _ = std::fs::remove_dir_all(&dir);
}
