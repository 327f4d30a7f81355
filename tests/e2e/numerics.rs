//! The numeric platform of actions whose bytes depend on their kernels (the test operator with
//! `numerics` set writes every kernel variable it sees): the class enters the key, the pins win
//! over the caller's environment, `native` is keyed by the CPU, and the record names it.

use std::fs;

use rlmflow_stages::numerics::{Cpu, Numerics, Target, class};

use crate::harness::*;

const PORTABLE: &str = r#"
[pipeline]
name = "kernels"
seed = 1

[stages.source]
operator = "write-text"
text = "weights"
numerics = "portable"
"#;

fn written(s: &Scratch) -> String {
    fs::read_to_string(output_dir(&s.store(), "kernels", "source").join("text.txt")).unwrap()
}

#[test]
fn the_pins_win_over_the_callers_kernel_choices() {
    let s = Scratch::new("pins");
    s.pipeline(PORTABLE);
    let out = s
        .command(&["run", "p.toml"])
        .env("ATEN_CPU_CAPABILITY", "avx512")
        .env("ONEDNN_MAX_CPU_ISA", "AVX512_CORE")
        .env("MKL_CBWR", "AUTO")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    let seen = written(&s);
    let cpu = Cpu::detect();
    let pins = rlmflow_stages::numerics::pins(Numerics::Portable, &cpu, Target::Cpu);
    for (var, value) in &pins {
        assert!(seen.contains(&format!("\n{var}={}", value.unwrap_or(""))), "{var} should be {value:?}:\n{seen}");
    }
    // The binary's kernel pin ran once, after the pins were set and before the operator.
    let trace = s.trace();
    let gemm = pins.get(rlmflow_stages::numerics::GEMM_VARIABLE).copied().flatten().unwrap_or("");
    let pinned: Vec<usize> = (0..trace.len()).filter(|&i| trace[i].starts_with("kernel pin ")).collect();
    let started = trace.iter().position(|l| l.starts_with("start write-text")).expect("the operator ran");
    assert!(pinned.len() == 1 && pinned[0] < started, "{trace:#?}");
    assert!(trace[pinned[0]].starts_with(&format!("kernel pin RLMFLOW_GEMM={gemm} ")), "{trace:#?}");
    // Native removes every choice, the caller's too: the fastest kernels the machine has.
    s.pipeline(&PORTABLE.replace("portable", "native"));
    let out = s.command(&["run", "p.toml"]).env("ATEN_CPU_CAPABILITY", "default").output().unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(written(&s).contains("\nATEN_CPU_CAPABILITY=\n"), "{}", written(&s));
}

#[test]
fn the_numeric_platform_is_in_the_key_and_native_names_the_cpu() {
    let s = Scratch::new("platform");
    s.pipeline(PORTABLE);
    s.run();
    let cpu = Cpu::detect();
    let portable = class(Numerics::Portable, &cpu, Target::Cpu, None);
    let show = text(&s.cli(&["show", "p.toml", "source"]).stdout);
    assert!(show.contains(&format!("platform {portable}")), "{show}");
    assert!(show.contains(&format!("cpu {}", cpu.model)), "{show}");
    assert!(show.contains("kernels portable"), "{show}");
    // `native` is another class: the key changes, explain and status say why, and the record names the CPU.
    s.pipeline(&PORTABLE.replace("numerics = \"portable\"", "numerics = \"native\""));
    let native = class(Numerics::Native, &cpu, Target::Cpu, None);
    assert!(native.contains(&cpu.model), "{native}");
    let explain = text(&s.cli(&["explain", "p.toml", "source"]).stdout);
    assert!(explain.contains(&format!("numeric platform {portable} -> {native}")), "{explain}");
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.contains(&format!("numeric platform {portable} -> {native}")), "{status}");
    assert_eq!(s.run().with_status("ran"), ["source"]);
    let show = text(&s.cli(&["show", "p.toml", "source"]).stdout);
    assert!(show.contains(&format!("platform {native}")) && show.contains("kernels native"), "{show}");
    let provenance = fs::read_dir(s.store().join("runs"))
        .unwrap()
        .map(|r| fs::read_to_string(r.unwrap().path().join("provenance.md")).unwrap_or_default())
        .collect::<String>();
    assert!(provenance.contains(&format!("| {native} |")), "{provenance}");
    // An operator whose bytes do not follow kernels has no platform in its key.
    s.pipeline(&PORTABLE.replace("numerics = \"portable\"\n", ""));
    s.run();
    let show = text(&s.cli(&["show", "p.toml", "source"]).stdout);
    assert!(!show.contains("\n  platform "), "{show}");
}

#[test]
fn an_action_keyed_for_another_platform_refuses_to_run_here() {
    let s = Scratch::new("foreign");
    s.pipeline(PORTABLE);
    s.run();
    let store = rlmflow_cache::Store::open_existing(&s.store()).unwrap().unwrap();
    let key = rlmflow_test_support::cli::last_keys(&store, "kernels")["source"];
    let mut request = store.request(&key).unwrap().unwrap();
    request.preimage.platform = Some("cpu/aarch64/portable".into());
    store.write_request(&request).unwrap();
    let out = s.cli(&["exec", &key.to_string(), "--store", ".rlmflow", "--scratch", "scratch"]);
    let err = text(&out.stderr);
    assert!(!out.status.success(), "{err}");
    let here = class(Numerics::Portable, &Cpu::detect(), Target::Cpu, None);
    assert!(err.contains("numeric platform `cpu/aarch64/portable`") && err.contains(&format!("this machine computes `{here}`")), "{err}");
}
