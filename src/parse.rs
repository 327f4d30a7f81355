//! `rlmflow parse`: the LLM-free caption parser on the command line.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context as _, bail};
use clap::{Args, FromArgMatches as _};
use rlmflow_engine::cli::ExtraCommand;

/// Parse captions into the paper's grid JSON with the LLM-free parser: one caption per line,
/// or JSON lines with a `caption` field; writes one grid JSON per line. Warnings go to stderr.
#[derive(Args)]
struct Parse {
    /// Default: standard input.
    file: Option<PathBuf>,
}

pub fn command() -> ExtraCommand {
    ExtraCommand { command: Parse::augment_args(clap::Command::new("parse")), run: |args| run(Parse::from_arg_matches(args)?) }
}

fn run(args: Parse) -> anyhow::Result<ExitCode> {
    let file = args.file.as_deref();
    let name = file.map_or("<stdin>".to_string(), |f| f.display().to_string());
    let input: Box<dyn BufRead> = match file {
        Some(f) => Box::new(std::io::BufReader::new(std::fs::File::open(f).with_context(|| format!("reading {}", f.display()))?)),
        None => Box::new(std::io::stdin().lock()),
    };
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    for (i, line) in input.lines().enumerate() {
        let line = line.with_context(|| format!("{name}:{}", i + 1))?;
        let caption = if line.trim_start().starts_with('{') {
            let value: serde_json::Value = serde_json::from_str(&line).with_context(|| format!("{name}:{}: not JSON", i + 1))?;
            match value.get("caption").and_then(|c| c.as_str()) {
                Some(c) => c.to_string(),
                None => bail!("{name}:{}: a JSON line needs a string field `caption`", i + 1),
            }
        } else {
            line
        };
        let parsed = rlmflow_parser::parse(&caption);
        for warning in &parsed.warnings {
            eprintln!("{name}:{}: warning: {warning}", i + 1);
        }
        if let Err(e) = writeln!(out, "{}", parsed.grid.to_json()) {
            return quiet_on_closed_pipe(e);
        }
    }
    out.flush().map_or_else(quiet_on_closed_pipe, |()| Ok(ExitCode::SUCCESS))
}

/// A reader that stops early (`rlmflow parse ... | head`) is not an error.
fn quiet_on_closed_pipe(e: std::io::Error) -> anyhow::Result<ExitCode> {
    if e.kind() == std::io::ErrorKind::BrokenPipe { Ok(ExitCode::SUCCESS) } else { Err(e.into()) }
}
