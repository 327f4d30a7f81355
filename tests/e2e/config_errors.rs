//! Every configuration error names the file, line and key, says what is valid, and suggests the
//! nearest name; nothing runs and nothing is written.

use crate::harness::*;

fn error_for(pipeline: &str) -> String {
    error_for_bytes(pipeline.as_bytes())
}

fn error_for_bytes(pipeline: &[u8]) -> String {
    let s = Scratch::new(&format!("cfg-{:x}", pipeline.len() * 31 + pipeline.iter().map(|&b| b as usize).sum::<usize>()));
    std::fs::write(s.dir.join("p.toml"), pipeline).unwrap();
    let out = s.cli(&["run", "p.toml"]);
    assert_eq!(out.status.code(), Some(2), "stdout: {}", text(&out.stdout));
    assert!(!s.store().exists(), "a config error writes nothing");
    assert!(s.trace().is_empty(), "a config error runs nothing");
    text(&out.stderr)
}

fn assert_has(err: &str, parts: &[&str]) {
    for p in parts {
        assert!(err.contains(p), "expected `{p}` in:\n{err}");
    }
}

#[test]
fn operator_typo_suggests_the_nearest() {
    let err = error_for("[stages.source]\noperator = \"write-txt\"\n");
    assert_has(
        &err,
        &[
            "p.toml:2: stages.source.operator: unknown operator `write-txt` for stage kind `source`",
            "valid: write-text",
            "did you mean `write-text`?",
        ],
    );
}

#[test]
fn operator_of_another_kind_is_named() {
    let err = error_for("[stages.source]\noperator = \"shout\"\n");
    assert_has(&err, &["p.toml:2:", "operator `shout` implements kind `map`, not `source`"]);
}

#[test]
fn unknown_setting_lists_valid_keys() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\n\ntxet = \"x\"\n");
    assert_has(&err, &["p.toml:4: stages.source.txet: unknown setting `txet`", "did you mean `text`?"]);
    let valid = err.lines().find_map(|l| l.trim().strip_prefix("valid keys: ")).unwrap_or_else(|| panic!("no valid keys in:\n{err}"));
    let valid: Vec<&str> = valid.split("; ").next().unwrap().split(", ").collect();
    assert!(["text", "steps", "repeat", "operator", "inputs"].iter().all(|k| valid.contains(k)), "{valid:?}");
}

#[test]
fn bad_setting_value_names_the_key() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\nsteps = \"many\"\n");
    assert_has(&err, &["p.toml:3: stages.source.steps: invalid type: string \"many\", expected u32"]);
    let err = error_for("[stages.source]\noperator = \"write-text\"\nthreads = 0\n");
    assert_has(&err, &["p.toml:3: stages.source.threads: must be at least 1"]);
}

#[test]
fn bad_variant_setting_points_at_the_variant() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\n[stages.source.variants]\nok = { text = \"a\" }\nbad = { step = 3 }\n");
    assert_has(&err, &["p.toml:5: stages.source.variants.bad.step: unknown setting `step`", "did you mean `steps`?"]);
}

#[test]
fn a_bad_setting_every_variant_inherits_is_one_error() {
    let err = error_for(
        "[stages.source]\noperator = \"write-text\"\nsteps = \"many\"\n[stages.source.variants]\na = { text = \"a\" }\nb = { text = \"b\" }\n",
    );
    assert_eq!(err.matches("stages.source.steps: invalid type").count(), 1, "{err}");
}

#[test]
fn a_stage_that_needs_cuda_is_refused_before_anything_runs_where_there_is_none() {
    let pipeline = "[stages.source]\noperator = \"write-text\"\ncuda = true\n";
    if std::path::Path::new("/dev/nvidiactl").exists() || std::path::Path::new("/dev/dxg").exists() {
        // A machine with the CUDA driver: the stage may run (the test operator uses no GPU).
        let s = Scratch::new("cuda-present");
        s.pipeline(pipeline);
        assert_eq!(s.run().status_of("source"), "ran");
        return;
    }
    let err = error_for(pipeline);
    assert_has(&err, &["p.toml:1: stages.source: needs a CUDA device", "valid here: device = \"auto\""]);
}

#[test]
fn unknown_pipeline_key_and_executor() {
    let err = error_for("[pipeline]\nnmae = \"x\"\nexecutor = \"hyperqeue\"\n[stages.source]\noperator = \"write-text\"\n");
    assert_has(
        &err,
        &[
            "p.toml:2: pipeline.nmae: unknown key `nmae`",
            "did you mean `name`?",
            "p.toml:3: pipeline.executor: unknown executor `hyperqeue`",
            "valid executors: local",
        ],
    );
    assert!(err.contains("2 problems"), "{err}");
}

#[test]
fn unknown_kind() {
    let err = error_for("[stages.src]\noperator = \"write-text\"\n");
    assert_has(&err, &["p.toml:1: stages.src: `src` is not a stage kind", "valid kinds: source, map, measure, remap, join, collect"]);
    let err = error_for("[stages.x]\nkind = \"mesure\"\noperator = \"count\"\n");
    assert_has(&err, &["p.toml:2: stages.x.kind: unknown stage kind `mesure`", "did you mean `measure`?"]);
}

#[test]
fn missing_input() {
    let err = error_for("[stages.map]\noperator = \"shout\"\n");
    assert_has(&err, &["p.toml:1: stages.map: missing input `text`: no stage produces Text", "add a stage of kind source"]);
}

#[test]
fn ambiguous_input() {
    let err = error_for(
        "[stages.a]\nkind = \"source\"\noperator = \"write-text\"\n[stages.b]\nkind = \"source\"\noperator = \"write-text\"\n[stages.map]\noperator = \"shout\"\n",
    );
    assert_has(&err, &["p.toml:7: stages.map: ambiguous input `text`: stages a, b all produce Text", "inputs = { text = \"a\" }"]);
}

#[test]
fn artifact_type_mismatch() {
    let err = error_for(
        "[stages.source]\noperator = \"write-text\"\n[stages.m]\nkind = \"map\"\noperator = \"shout\"\n[stages.map]\noperator = \"shout\"\ninputs = { text = \"m\" }\n",
    );
    assert_has(&err, &["p.toml:8: stages.map.inputs.text: stage `m` produces Mapped, but slot `text` takes Text"]);
}

#[test]
fn unknown_input_stage_and_slot() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\n[stages.map]\noperator = \"shout\"\ninputs = { txt = \"source\" }\n");
    assert_has(&err, &["p.toml:5: stages.map.inputs.txt: unknown input slot `txt`", "did you mean `text`?"]);
    let err = error_for("[stages.source]\noperator = \"write-text\"\n[stages.map]\noperator = \"shout\"\ninputs = { text = \"sorce\" }\n");
    assert_has(&err, &["p.toml:5: stages.map.inputs.text: no stage named `sorce`", "did you mean `source`?"]);
}

#[test]
fn cycles_are_caught_before_anything_runs() {
    let err = error_for(
        "[stages.a]\nkind = \"remap\"\noperator = \"echo\"\ninputs = { mapped = \"b\" }\n[stages.b]\nkind = \"remap\"\noperator = \"echo\"\ninputs = { mapped = \"a\" }\n",
    );
    assert_has(&err, &["p.toml:1: stages.a: the stages form a cycle: a -> b -> a", "break it by changing one stage's `inputs`"]);
}

#[test]
fn invalid_toml_names_the_line() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\ntext = \n");
    assert_has(&err, &["p.toml:3: invalid TOML"]);
}

#[test]
fn a_file_that_is_not_utf8_is_reported_at_its_line() {
    let err = error_for_bytes(b"[pipeline]\nname = \"x\"\n# caf\xe9\n[stages.source]\noperator = \"write-text\"\n");
    assert_has(&err, &["p.toml:3: not UTF-8 text: byte 0xE9 at column 6"]);
}

#[test]
fn a_table_nested_thousands_deep_is_reported_at_its_line() {
    let deep = format!("[stages.source]\noperator = \"write-text\"\n\n[{}]\n", vec!["a"; 5000].join("."));
    let err = error_for(&deep);
    assert_has(&err, &["p.toml:4: nested more than 32 levels deep"]);
    let arrays = format!("[stages.source]\noperator = \"write-text\"\ntext = {}\n", "[".repeat(5000));
    assert_has(&error_for(&arrays), &["p.toml:3: nested more than 32 levels deep"]);
}

#[test]
fn numbers_and_dots_in_values_are_not_nesting() {
    // 40 floats on one line, and a multi-line string of 40 dots: values, not 40 levels.
    let floats = (1..=40).map(|i| format!("{i}.5")).collect::<Vec<_>>().join(", ");
    let err = error_for(&format!("[pipeline]\nseeds = [{floats}]\n[stages.source]\noperator = \"write-text\"\n"));
    assert_has(&err, &["p.toml:2: pipeline.seeds: must be a list of non-negative integers"]);
    assert!(!err.contains("nested"), "{err}");
    let s = Scratch::new("cfg-dots");
    s.pipeline(&format!("[stages.source]\noperator = \"write-text\"\ntext = \"\"\"\n{}\n{}\"\"\"\n", ".".repeat(40), "a.b.".repeat(20)));
    let out = s.cli(&["run", "p.toml", "--dry-run"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    // Nesting is still counted where it is: inline tables and dotted keys inside them.
    let inline = format!("[stages.source]\noperator = \"write-text\"\nvariants = {}{}\n", "{ a = ".repeat(40), "}".repeat(40));
    assert_has(&error_for(&inline), &["p.toml:3: nested more than 32 levels deep"]);
}

#[test]
fn variants_that_multiply_past_the_instance_bound_are_refused_before_expanding() {
    // 20 variants on each of four chained stages: 160,000 instances.
    let variants = (0..20).map(|v| format!("v{v} = {{}}")).collect::<Vec<_>>().join(", ");
    let pipeline = format!(
        "[stages.source]\noperator = \"write-text\"\nvariants = {{ {variants} }}\n\n\
         [stages.map]\noperator = \"shout\"\nvariants = {{ {variants} }}\n\n\
         [stages.again]\nkind = \"remap\"\noperator = \"echo\"\ninputs = {{ mapped = \"map\" }}\nvariants = {{ {variants} }}\n\n\
         [stages.measure]\noperator = \"count\"\ninputs = {{ mapped = \"again\" }}\nvariants = {{ {variants} }}\n"
    );
    let started = std::time::Instant::now();
    let err = error_for(&pipeline);
    assert_has(
        &err,
        &[
            "p.toml:15: stages.measure: the plan would have more than 10000 instances (`[pipeline] max_instances`): this stage makes 160000 (20 variants of `again` x 20 variants of `map` x 20 variants of `measure` x 20 variants of `source`), 168420 with the stages before it",
            "raise `[pipeline] max_instances`",
        ],
    );
    assert!(started.elapsed() < std::time::Duration::from_secs(20), "refused in {:?}", started.elapsed());
    // Raised past what a plan can hold in memory (the largest integer TOML has, or just past the
    // ceiling): refused as a setting, never an allocation failure.
    for max in ["9223372036854775807", "100001", "0"] {
        let err = error_for(&format!("[pipeline]\nmax_instances = {max}\n{pipeline}"));
        assert_has(&err, &[&format!("p.toml:2: pipeline.max_instances: must be a positive integer up to 100000, not {max}")]);
    }
    // The bound is a setting: raised, 8,000 of one stage's variants plan (and are listed).
    let many = (0..8000).map(|v| format!("v{v} = {{}}")).collect::<Vec<_>>().join(", ");
    let s = Scratch::new("cfg-many-variants");
    s.pipeline(&format!("[pipeline]\nmax_instances = 8000\n[stages.source]\noperator = \"write-text\"\nvariants = {{ {many} }}\n"));
    let out = s.cli(&["run", "p.toml", "--dry-run"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains("source[v7999]"), "{}", text(&out.stdout));
}

#[test]
fn a_chain_of_stages_longer_than_the_bound_is_refused_and_a_long_one_plans() {
    let chain = |n: usize| {
        let mut p = String::from(
            "[stages.s0]\nkind = \"map\"\noperator = \"shout\"\ninputs = { text = \"t\" }\n[stages.t]\nkind = \"source\"\noperator = \"write-text\"\n",
        );
        for i in 1..n {
            p.push_str(&format!("[stages.s{i}]\nkind = \"remap\"\noperator = \"echo\"\ninputs = {{ mapped = \"s{}\" }}\n", i - 1));
        }
        p
    };
    let err = error_for(&chain(200_000));
    assert_has(&err, &["stages: 200001 stages, and each makes at least one instance; at most 10000 (`[pipeline] max_instances`)"]);
    // Ordered without recursion: a chain of 50,000 (raised bound) plans in a dry run.
    let s = Scratch::new("cfg-long-chain");
    s.pipeline(&format!("[pipeline]\nmax_instances = 60000\n{}", chain(50_000)));
    let out = s.cli(&["run", "p.toml", "--dry-run"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(!s.store().exists(), "a dry run writes nothing");
}

#[test]
fn an_empty_list_for_a_required_input_is_a_config_error() {
    let err = error_for("[stages.source]\noperator = \"write-text\"\n[stages.map]\noperator = \"shout\"\ninputs = { text = [] }\n");
    assert_has(&err, &["p.toml:5: stages.map.inputs.text: names no stage, but `shout` needs its `text` input", "name a stage that produces Text"]);
}

#[test]
fn a_toml_datetime_is_no_setting_value() {
    let err = error_for("[pipeline]\nname = 1979-05-27\n[stages.source]\noperator = \"write-text\"\ntext = 07:32:00\n");
    assert_has(&err, &["p.toml:2: pipeline.name: a TOML date or time is not a valid value", "p.toml:5: stages.source.text: a TOML date or time"]);
}

#[test]
fn names_too_long_for_a_file_name_are_config_errors() {
    let long = "x".repeat(5000);
    let err = error_for(&format!("[pipeline]\nname = \"{long}\"\n[stages.source]\noperator = \"write-text\"\n"));
    assert_has(&err, &["p.toml:2: pipeline.name: the name is 5000 bytes long; at most 128"]);
    let err = error_for(&format!("[stages.{long}]\nkind = \"source\"\noperator = \"write-text\"\n"));
    assert_has(&err, &[&format!("p.toml:1: stages.{long}: the name is 5000 bytes long")]);
    let err = error_for(&format!("[stages.source]\noperator = \"write-text\"\n[stages.source.variants]\n{long} = {{ text = \"a\" }}\n"));
    assert_has(&err, &["the name is 5000 bytes long"]);
}

/// A name that would forge a provenance row or a label (a newline, a NUL, `|`, brackets), or
/// climb out of a results folder (`.`, `..`): refused with the character named, nothing run.
#[test]
fn names_that_could_forge_a_row_or_leave_a_folder_are_config_errors() {
    let cases = [
        ("[stages.\"s\\n| forged | ran |\"]\nkind = \"source\"\noperator = \"write-text\"\n", "holds '\\n'"),
        ("[stages.\"s\\u0000\"]\nkind = \"source\"\noperator = \"write-text\"\n", "holds '\\0'"),
        ("[stages.\"p[x=y]\"]\nkind = \"source\"\noperator = \"write-text\"\n", "holds '['"),
        ("[stages.source]\noperator = \"write-text\"\n[stages.source.variants]\n\".\" = { text = \"a\" }\n", "begins with \".\""),
        ("[stages.source]\noperator = \"write-text\"\n[stages.source.variants]\n\"..\" = { text = \"a\" }\n", "begins with \".\""),
        ("[pipeline]\nname = \"a/b\"\n[stages.source]\noperator = \"write-text\"\n", "holds '/'"),
    ];
    for (pipeline, problem) in cases {
        assert_has(&error_for(pipeline), &[problem, "valid: ASCII letters, digits, `-`, `_` and `.`"]);
    }
}

#[test]
fn a_pipeline_without_stages_is_an_error() {
    let err = error_for("[pipeline]\nname = \"empty\"\n");
    assert_has(&err, &["the pipeline has no stages"]);
}

#[test]
fn a_pin_name_too_long_for_a_file_name_is_refused() {
    let s = Scratch::new("pin-long");
    s.pipeline(CHAIN);
    s.run();
    let out = s.cli(&["pin", "p.toml", &"x".repeat(5000)]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("the pin name is 5000 bytes long"), "{}", text(&out.stderr));
}
