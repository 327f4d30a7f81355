//! Child processes on this machine, which die with the engine.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};

use anyhow::Context as _;
use rlmflow_stages::Device;

use super::{Dispatch, Exit, Launch, Report, Reports, forward_lines};
use crate::gpus::Gpu;

pub struct Local {
    /// The GPUs a stage that can use one is placed on; empty where it may get none here (such
    /// stages then share the CPUs like any other).
    gpus: Vec<Gpu>,
    /// Whether a stage's worker is shown its GPU alone (`CUDA_VISIBLE_DEVICES`): not where the
    /// run names one device (`--device cuda:N`), which the worker then opens itself.
    expose: bool,
}

impl Local {
    /// With `--device cuda:N` that GPU; otherwise (a stage's own `device = "auto"` finds
    /// CUDA where there is one) every GPU of the inventory (`gpus`: `[pipeline] gpus` or
    /// `--gpus`), or where the driver's device nodes are but the driver lists none, one of
    /// unknown memory.
    pub fn new(device: Device, gpus: Option<&[usize]>) -> anyhow::Result<Local> {
        let unknown = |index| Gpu { index, uuid: None, model: "unknown GPU".into(), memory: None };
        if let Device::Cuda(n) = device {
            let gpu = crate::gpus::inventory(None)?.gpus.into_iter().find(|g| g.index == n);
            return Ok(Local { gpus: vec![gpu.unwrap_or_else(|| unknown(n))], expose: false });
        }
        let inventory = crate::gpus::inventory(gpus)?;
        Ok(match inventory.gpus.is_empty() && crate::platform::cuda_present() {
            true => Local { gpus: vec![unknown(0)], expose: false },
            false => Local { gpus: inventory.gpus, expose: true },
        })
    }
}

impl Dispatch for Local {
    fn start(&mut self, launch: Launch, reports: Reports) -> anyhow::Result<()> {
        // Appending, so the engine's note of how the attempt ended lands after the last line.
        File::create(&launch.log).with_context(|| format!("creating {}", launch.log.display()))?;
        let log = std::fs::OpenOptions::new().append(true).open(&launch.log).with_context(|| format!("opening {}", launch.log.display()))?;
        let log = Arc::new(Mutex::new(log));
        let mut cmd = Command::new(&launch.exe);
        cmd.args(&launch.args).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        if let Some(gpu) = launch.placed.as_ref().filter(|_| self.expose) {
            cmd.envs(gpu.visible());
        }
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
        let timer = launch.timeout.map(|limit| Timer::start(child.id(), limit));
        std::thread::spawn(move || {
            forward_lines(BufReader::new(stdout), &reports, &log);
            let timed_out = timer.is_some_and(|t| {
                wait_unreaped(child.id());
                t.stop()
            });
            let status = child.wait();
            let exit = match status {
                Ok(_) if timed_out => Exit::TimedOut(launch.timeout.unwrap().as_secs_f64()),
                Ok(status) => exit_of(status),
                Err(e) => Exit::Lost(format!("could not wait for the child: {e}")),
            };
            reports(Report::Exited(exit));
        });
        Ok(())
    }

    fn gpus(&self) -> Option<Vec<Gpu>> {
        Some(self.gpus.clone())
    }

    fn cuda_possible(&self) -> bool {
        !self.gpus.is_empty()
    }

    fn describe(&self) -> String {
        "local".into()
    }
}

/// Kills a child that runs past its limit. The child's pid is signalled only until the child is
/// seen to have exited ([`wait_unreaped`], before it is reaped), so a reused pid is never hit.
struct Timer {
    state: Arc<Mutex<TimerState>>,
    stop: std::sync::mpsc::Sender<()>,
}

#[derive(Default)]
struct TimerState {
    stopped: bool,
    fired: bool,
}

impl Timer {
    fn start(pid: u32, limit: std::time::Duration) -> Timer {
        let state = Arc::new(Mutex::new(TimerState::default()));
        let (stop, stopped) = std::sync::mpsc::channel::<()>();
        let watched = state.clone();
        std::thread::spawn(move || {
            if stopped.recv_timeout(limit).is_err() {
                let mut s = watched.lock().unwrap();
                if !s.stopped {
                    // SAFETY: kill(2) on the pid of our child, which has not been reaped.
                    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
                    s.fired = true;
                }
            }
        });
        Timer { state, stop }
    }

    /// Called once the child was waited for: whether the limit stopped it.
    fn stop(self) -> bool {
        let mut s = self.state.lock().unwrap();
        s.stopped = true;
        let _ = self.stop.send(());
        s.fired
    }
}

/// Blocks until child `pid` has exited, leaving it unreaped: until `wait` reaps it, its pid
/// stays its own.
fn wait_unreaped(pid: u32) {
    loop {
        // SAFETY: waitid(2) on our own child, into a zeroed siginfo_t.
        let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
        let r = unsafe { libc::waitid(libc::P_PID, pid as libc::id_t, &mut info, libc::WEXITED | libc::WNOWAIT) };
        if r == 0 || std::io::Error::last_os_error().raw_os_error() != Some(libc::EINTR) {
            return;
        }
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
        use crate::platform::cuda_device_nodes;
        let dev = std::env::temp_dir().join(format!("rlmflow-dev-{}", std::process::id()));
        std::fs::create_dir_all(&dev).unwrap();
        assert!(!cuda_device_nodes(&dev), "an empty /dev has no CUDA device");
        std::fs::write(dev.join("nvidiactl"), "").unwrap();
        assert!(cuda_device_nodes(&dev));
        std::fs::remove_dir_all(&dev).unwrap();
        let one = Local::new(Device::Cuda(0), None).unwrap();
        assert_eq!(one.gpus().map(|g| g.len()), Some(1), "a run that names CUDA places on that GPU");
        assert!(!one.expose, "its worker opens the device it names");
        if std::env::var_os(crate::gpus::DECLARED).is_none() && !crate::platform::cuda_present() {
            assert_eq!(Local::new(Device::Cpu, None).unwrap().gpus(), Some(Vec::new()), "no GPU here");
        }
    }

    #[test]
    fn a_gpu_that_cuda_visible_devices_hides_is_no_gpu() {
        use crate::platform::cuda_visible;
        assert!(cuda_visible(None), "unset: every device");
        for visible in ["0", "1,0", " 2", "GPU-8f3c", "MIG-1a2b/0", "0,-1"] {
            assert!(cuda_visible(Some(visible)), "{visible:?}");
        }
        for hidden in ["", "-1", "none", "NoDevFiles", "-1,0", "GPU-"] {
            assert!(!cuda_visible(Some(hidden)), "{hidden:?}");
        }
    }
}
