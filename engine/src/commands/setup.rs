//! `rlmflow setup`: the managed Python environment, made if missing.

use std::process::ExitCode;

pub(crate) fn exec() -> anyhow::Result<ExitCode> {
    let env = rlmflow_python::ensure(&mut |note| eprintln!("{note}"))?;
    println!("Python {} environment: {}", env.version, env.root.display());
    println!("site-packages: {}", env.site_packages.display());
    Ok(ExitCode::SUCCESS)
}
