//! Child processes on this machine, which die with the engine.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};

use anyhow::Context as _;
use rlmflow_stages::Device;

use super::{Dispatch, Exit, Launch, Report, forward_lines};

pub struct Local {
    /// Whether a stage that can use a GPU may get one here, so such stages run one at a time.
    gpu: bool,
}

impl Local {
    /// A stage that can use a GPU gets one when the run names a CUDA device, or (`device =
    /// "auto"`) when libtorch sees one, which needs the CUDA driver's device nodes. On a machine
    /// without them such stages share the CPUs like any other.
    pub fn new(device: Device) -> Local {
        Local { gpu: device != Device::Cpu || crate::platform::cuda_present() }
    }
}

impl Dispatch for Local {
    fn start(&mut self, id: usize, launch: Launch, tx: Sender<(usize, Report)>) -> anyhow::Result<()> {
        let log = Arc::new(Mutex::new(File::create(&launch.log).with_context(|| format!("creating {}", launch.log.display()))?));
        let mut cmd = Command::new(&launch.exe);
        cmd.args(&launch.args).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        die_with_parent(&mut cmd);
        let mut child = cmd.spawn().with_context(|| format!("starting {}", launch.exe.display()))?;
        let stdout = child.stdout.take().unwrap();
        let stderr = child.stderr.take().unwrap();
        let err_log = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let _ = writeln!(err_log.lock().unwrap(), "{line}");
            }
        });
        std::thread::spawn(move || {
            forward_lines(BufReader::new(stdout), id, &tx, &log);
            let exit = match child.wait() {
                Ok(status) => exit_of(status),
                Err(e) => Exit::Lost(format!("could not wait for the child: {e}")),
            };
            let _ = tx.send((id, Report::Exited(exit)));
        });
        Ok(())
    }

    fn serialises_gpu(&self) -> bool {
        self.gpu
    }

    fn cuda_possible(&self) -> bool {
        self.gpu
    }

    fn describe(&self) -> String {
        "local".into()
    }
}

fn exit_of(status: std::process::ExitStatus) -> Exit {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (_, Some(sig)) => Exit::Signal(sig),
        (Some(code), _) => Exit::Code(code),
        _ => Exit::Lost("the stage process ended abnormally".into()),
    }
}

/// The child dies with the engine (Linux), so a killed run leaves no stage computing alone.
fn die_with_parent(cmd: &mut Command) {
    #[cfg(target_os = "linux")]
    unsafe {
        use std::os::unix::process::CommandExt;
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gpu_stages_run_one_at_a_time_only_where_a_gpu_can_be() {
        use std::path::Path;

        use crate::platform::cuda_device_nodes;
        let dev = std::env::temp_dir().join(format!("rlmflow-dev-{}", std::process::id()));
        std::fs::create_dir_all(&dev).unwrap();
        assert!(!cuda_device_nodes(&dev), "an empty /dev has no CUDA device");
        std::fs::write(dev.join("nvidiactl"), "").unwrap();
        assert!(cuda_device_nodes(&dev));
        std::fs::remove_dir_all(&dev).unwrap();
        assert!(Local::new(Device::Cuda(0)).serialises_gpu(), "a run that names CUDA shares one GPU");
        assert_eq!(Local::new(Device::Cpu).serialises_gpu(), cuda_device_nodes(Path::new("/dev")));
    }
}
