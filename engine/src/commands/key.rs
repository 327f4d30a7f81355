//! `rlmflow key generate`: an ed25519 key pair for signing remote cache records.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::config;

#[derive(clap::Args)]
pub(crate) struct Args {
    #[command(subcommand)]
    action: KeyAction,
}

#[derive(clap::Subcommand)]
pub(crate) enum KeyAction {
    /// A new key pair named NAME (letters, digits, `-`, `_`, `.`).
    Generate {
        name: String,
        /// Where to write NAME.secret and NAME.public.
        #[arg(long, default_value = ".")]
        dir: PathBuf,
    },
}

pub(crate) fn exec(args: Args) -> anyhow::Result<ExitCode> {
    let Args { action: KeyAction::Generate { name, dir } } = args;
    let (secret, public) = rlmflow_remote::signing::generate(&name)?;
    let (secret_file, public_file) = (dir.join(format!("{name}.secret")), dir.join(format!("{name}.public")));
    if secret_file.exists() {
        anyhow::bail!("{} exists; a key is never overwritten", secret_file.display());
    }
    use std::os::unix::fs::OpenOptionsExt as _;
    let mut file = std::fs::OpenOptions::new().write(true).create_new(true).mode(0o600).open(&secret_file)?;
    std::io::Write::write_all(&mut file, format!("{secret}\n").as_bytes())?;
    std::fs::write(&public_file, format!("{public}\n"))?;
    println!("secret key: {} (for the pusher: {}={})", secret_file.display(), config::SIGNING_KEY_VARIABLE, secret_file.display());
    println!("public key: {public}");
    println!("readers trust it with: remote_trusted_keys = [\"{public}\"]");
    Ok(ExitCode::SUCCESS)
}
