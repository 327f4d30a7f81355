//! ARCHITECTURE.md's invariants name the tests that enforce them: each invariant (a bullet of
//! its `## Invariants`, or a bullet or paragraph opening `Invariant:` in a crate's section)
//! names at least one, and every test it names exists.

use std::path::Path;

/// Each invariant of `architecture`, its lines joined: the bullets of `## Invariants`, and every
/// bullet or paragraph elsewhere that opens `Invariant:` (up to the next invariant, blank line or
/// heading).
pub fn invariants(architecture: &str) -> Vec<String> {
    let mut found: Vec<String> = Vec::new();
    let mut open = false;
    let mut in_section = false;
    for line in architecture.lines() {
        if line.starts_with("## ") {
            in_section = line == "## Invariants";
            open = false;
            continue;
        }
        let start =
            if in_section { line.strip_prefix("- ") } else { line.strip_prefix("- Invariant: ").or_else(|| line.strip_prefix("Invariant: ")) };
        match start {
            Some(start) => {
                found.push(start.to_owned());
                open = true;
            }
            None if line.trim().is_empty() || (in_section && !line.starts_with("  ")) => open = false,
            None if open => *found.last_mut().expect("an open invariant") += &format!(" {}", line.trim()),
            None => {}
        }
    }
    found
}

/// The backticked names in `text` that look like test names (snake case, four words or more).
pub fn named_tests(text: &str) -> Vec<&str> {
    let quoted = text.split('`').skip(1).step_by(2);
    quoted.filter(|q| q.matches('_').count() >= 3 && q.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')).collect()
}

/// Every `#[test]` function's name in the Rust files under `root` (build output aside).
pub fn test_functions(root: &Path) -> std::collections::BTreeSet<String> {
    let mut names = std::collections::BTreeSet::new();
    let mut dirs = vec![root.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            let name = entry.file_name();
            if path.is_dir() && name != "target" && !name.to_string_lossy().starts_with('.') {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).unwrap_or_default();
                let mut lines = text.lines().map(str::trim);
                while let Some(line) = lines.next() {
                    if line == "#[test]" {
                        let signature = lines.by_ref().find(|l| l.starts_with("fn ") || l.starts_with("pub fn "));
                        if let Some(name) = signature.and_then(|l| l.split("fn ").nth(1)?.split('(').next()) {
                            names.insert(name.to_owned());
                        }
                    }
                }
            }
        }
    }
    names
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_invariant_names_a_test_that_exists() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let architecture = std::fs::read_to_string(root.join("ARCHITECTURE.md")).unwrap();
        let tests = test_functions(&root);
        assert!(tests.contains("every_invariant_names_a_test_that_exists"), "the tests are read: {}", tests.len());
        let bullets = invariants(&architecture);
        assert!(bullets.len() >= 30, "{bullets:#?}");
        for bullet in &bullets {
            let named = named_tests(bullet);
            assert!(!named.is_empty(), "an invariant names no test: {bullet}");
            for test in named {
                assert!(tests.contains(test), "`{test}` is named for an invariant and is no test: {bullet}");
            }
        }
    }
}
