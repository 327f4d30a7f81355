//! The worker and `rlmflow` register the same definition of each torch operator.

use std::process::Command;

use crate::common::rlmflow_exe;

fn operators(exe: &std::path::Path) -> Vec<serde_json::Value> {
    let out = Command::new(exe).args(["operators", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

#[test]
fn the_worker_registers_the_operators_rlmflow_plans_with_the_same_spec_and_settings() {
    let worker = operators(std::path::Path::new(env!("CARGO_BIN_EXE_rlmflow-torch")));
    let planner = operators(&rlmflow_exe());
    let names: Vec<&str> = worker.iter().filter_map(|op| op["name"].as_str()).collect();
    assert_eq!(names, ["clip", "linear", "clipcap", "pup", "unet", "frozen"]);
    for op in &worker {
        let planned = planner.iter().find(|p| p["name"] == op["name"]).unwrap_or_else(|| panic!("rlmflow lacks {}", op["name"]));
        assert_eq!(op, planned, "one definition: name, kind, version, defaults, non-result and tracked keys");
    }
}
