//! CUDA for the torch worker. The PyPI wheel's libtorch splits CUDA into `libtorch_cuda.so`,
//! whose own dependencies (cuBLAS, cuDNN, NCCL, ...) come as separate packages of several GB: a
//! binary that named it as a needed library would not start on a machine without them (CI, any
//! laptop). So the worker links the CPU half and loads the CUDA half at start ([`load`]) from
//! the directory of the libtorch it runs with, before anything asks libtorch about CUDA
//! (libtorch decides once, at its first question, whether it has CUDA). [`status`] says which
//! devices libtorch can use and, where CUDA is out of reach, exactly why: `rlmflow-torch
//! doctor` prints it, and a stage asked to compute on CUDA fails with it.

use std::ffi::{CStr, CString, c_int, c_void};
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// What this process can compute on, and why not CUDA.
#[derive(Clone, Debug)]
pub struct Status {
    /// The directory of the libtorch this process runs with.
    pub libtorch: Option<PathBuf>,
    /// The CUDA version the libtorch was built for (`13.0`); `None`: a CPU build.
    pub built_for: Option<String>,
    /// The NVIDIA driver's CUDA version (`13.0`), or why there is none.
    pub driver: Result<String, String>,
    /// Whether `libtorch_cuda.so` is loaded, or why not.
    pub library: Result<(), String>,
    /// CUDA devices libtorch sees.
    pub devices: i64,
}

impl Status {
    /// Why CUDA is out of reach, first cause first; `None` when libtorch has a CUDA device.
    pub fn why_not(&self) -> Option<String> {
        if self.devices > 0 {
            return None;
        }
        let Some(dir) = &self.libtorch else { return Some("libtorch is not loaded from a file this process can name".into()) };
        let Some(built_for) = &self.built_for else {
            return Some(format!(
                "the libtorch at {} is a CPU build (no lib/libtorch_cuda.so): use the CUDA wheel's (`cargo xtask` installs it)",
                dir.display()
            ));
        };
        let driver = match &self.driver {
            Err(why) => return Some(format!("no NVIDIA driver: {why}")),
            Ok(driver) => driver,
        };
        if version_number(driver) < version_number(built_for) {
            return Some(format!("the NVIDIA driver supports CUDA {driver}, and this libtorch needs CUDA {built_for}: update the driver"));
        }
        if let Err(why) = &self.library {
            return Some(format!(
                "libtorch's CUDA library cannot be loaded: {why} (`cargo xtask libtorch --cuda` installs the CUDA packages the torch wheel needs)"
            ));
        }
        Some(format!("the driver (CUDA {driver}) and libtorch_cuda are loaded, but no CUDA device is visible (CUDA_VISIBLE_DEVICES?)"))
    }
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let dir = self.libtorch.as_ref().map_or("unknown".to_owned(), |d| d.display().to_string());
        writeln!(f, "libtorch       {dir} ({})", self.built_for.as_ref().map_or("CPU build".to_owned(), |v| format!("built for CUDA {v}")))?;
        match &self.driver {
            Ok(v) => writeln!(f, "NVIDIA driver  supports CUDA {v}")?,
            Err(why) => writeln!(f, "NVIDIA driver  none: {why}")?,
        }
        match (&self.built_for, &self.library) {
            (None, _) => writeln!(f, "libtorch_cuda  none in this libtorch")?,
            (Some(_), Ok(())) => writeln!(f, "libtorch_cuda  loaded")?,
            (Some(_), Err(why)) => writeln!(f, "libtorch_cuda  not loaded: {why}")?,
        }
        writeln!(f, "devices        cpu{}", (0..self.devices).map(|n| format!(", cuda:{n}")).collect::<String>())?;
        match self.why_not() {
            None => write!(f, "CUDA           usable"),
            Some(why) => write!(f, "CUDA           not usable: {why}"),
        }
    }
}

/// `13.0` as 13000, the driver API's encoding; 0 where it does not parse.
fn version_number(version: &str) -> i64 {
    let mut parts = version.split('.').map(|p| p.parse::<i64>().unwrap_or(0));
    parts.next().unwrap_or(0) * 1000 + parts.next().unwrap_or(0) * 10
}

/// The last `dlerror()` message.
fn dl_error() -> String {
    // SAFETY: dlerror returns null or a NUL-terminated message owned by libc.
    let message = unsafe { libc::dlerror() };
    if message.is_null() { "unknown error".into() } else { unsafe { CStr::from_ptr(message) }.to_string_lossy().into_owned() }
}

fn dlopen(path: &str, flags: c_int) -> Result<*mut c_void, String> {
    let name = CString::new(path).map_err(|_| format!("{path}: a NUL in the path"))?;
    // SAFETY: a valid C string; the handle is never closed (libraries stay for the process).
    let handle = unsafe { libc::dlopen(name.as_ptr(), flags) };
    if handle.is_null() { Err(dl_error()) } else { Ok(handle) }
}

/// The directory of the `libtorch_cpu.so` this process has mapped (its run path or
/// `LD_LIBRARY_PATH` chose it).
fn libtorch_lib_dir() -> Option<PathBuf> {
    let maps = std::fs::read_to_string("/proc/self/maps").ok()?;
    maps.lines()
        .filter_map(|line| line.split_whitespace().nth(5))
        .find(|path| path.ends_with("/libtorch_cpu.so"))
        .map(|p| Path::new(p).parent().expect("a file in a directory").to_path_buf())
}

/// The CUDA version a libtorch at `lib` (its `lib/` directory) was built for, from the wheel's
/// `version.py` (`cuda = '13.0'`); `None` for a CPU build.
fn built_for(lib: &Path) -> Option<String> {
    if !lib.join("libtorch_cuda.so").is_file() {
        return None;
    }
    let version = std::fs::read_to_string(lib.join("../version.py")).unwrap_or_default();
    let recorded = version
        .lines()
        .find_map(|l| l.strip_prefix("cuda").and_then(|rest| rest.split_once('=')).map(|(_, v)| v.trim().trim_matches(['\'', '"']).to_owned()));
    Some(recorded.filter(|v| v != "None").unwrap_or_else(|| "an unrecorded version".into()))
}

/// The driver's CUDA version through `cuDriverGetVersion` in `libcuda.so.1`.
fn driver_version() -> Result<String, String> {
    let handle = dlopen("libcuda.so.1", libc::RTLD_NOW | libc::RTLD_GLOBAL).map_err(|e| format!("libcuda.so.1 cannot be loaded ({e})"))?;
    let symbol = CString::new("cuDriverGetVersion").expect("no NUL");
    // SAFETY: a handle dlopen returned and a C string.
    let function = unsafe { libc::dlsym(handle, symbol.as_ptr()) };
    if function.is_null() {
        return Err("libcuda.so.1 has no cuDriverGetVersion".into());
    }
    // SAFETY: cuDriverGetVersion(int*) -> CUresult, as the driver API declares it.
    let get: extern "C" fn(*mut c_int) -> c_int = unsafe { std::mem::transmute(function) };
    let mut version: c_int = 0;
    match get(&mut version) {
        0 => Ok(format!("{}.{}", version / 1000, (version % 1000) / 10)),
        code => Err(format!("cuDriverGetVersion failed with CUDA error {code}")),
    }
}

/// The outcome of loading libtorch_cuda: `None` until tried.
static LOADED: Mutex<Option<Result<(), String>>> = Mutex::new(None);
const NO_DRIVER: &str = "not tried: no NVIDIA driver";

/// Loads `libtorch_cuda.so` beside the libtorch this process runs with, once, where the
/// libtorch is a CUDA build and an NVIDIA driver is present (so a CPU machine loads nothing);
/// `force` tries even without a driver (for [`status`]'s report). Call before anything asks
/// libtorch about CUDA: the worker does, first thing.
pub fn load(force: bool) -> Result<(), String> {
    let mut loaded = LOADED.lock().expect("the CUDA load's outcome");
    if let Some(outcome) = loaded.as_ref().filter(|o| !(force && o.as_ref().err().is_some_and(|e| e == NO_DRIVER))) {
        return outcome.clone();
    }
    let outcome = match libtorch_lib_dir().filter(|lib| built_for(lib).is_some()) {
        None => Err("this libtorch has no libtorch_cuda.so".into()),
        Some(_) if !force && driver_version().is_err() => Err(NO_DRIVER.into()),
        Some(lib) => dlopen(&lib.join("libtorch_cuda.so").to_string_lossy(), libc::RTLD_NOW | libc::RTLD_GLOBAL).map(|_| ()),
    };
    *loaded = Some(outcome.clone());
    outcome
}

/// What this process can compute on; loads libtorch_cuda first if it can ([`load`]).
pub fn status() -> Status {
    let library = load(true);
    let libtorch = libtorch_lib_dir();
    let built_for = libtorch.as_deref().and_then(built_for);
    let devices = if library.is_ok() { tch::Cuda::device_count() } else { 0 };
    Status {
        libtorch: libtorch.map(|lib| lib.parent().map_or(lib.clone(), Path::to_path_buf)),
        built_for,
        driver: driver_version(),
        library,
        devices,
    }
}

/// Whether libtorch can compute on CUDA in this process.
pub fn available() -> bool {
    load(false).is_ok() && tch::Cuda::is_available()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(built_for: Option<&str>, driver: Result<&str, &str>, library: Result<(), &str>, devices: i64) -> Status {
        Status {
            libtorch: Some("/opt/torch".into()),
            built_for: built_for.map(str::to_owned),
            driver: driver.map(str::to_owned).map_err(str::to_owned),
            library: library.map_err(str::to_owned),
            devices,
        }
    }

    #[test]
    fn the_reason_cuda_is_out_of_reach_is_its_first_cause() {
        let why = |s: Status| s.why_not().unwrap_or_default();
        assert!(why(status(None, Ok("13.0"), Ok(()), 0)).contains("is a CPU build"));
        assert!(why(status(Some("13.0"), Err("libcuda.so.1 cannot be loaded"), Err("x"), 0)).starts_with("no NVIDIA driver: libcuda.so.1"));
        assert!(
            why(status(Some("13.0"), Ok("12.8"), Ok(()), 0)).contains("supports CUDA 12.8, and this libtorch needs CUDA 13.0: update the driver")
        );
        let missing = why(status(Some("13.0"), Ok("13.1"), Err("libcudnn.so.9: cannot open shared object file"), 0));
        assert!(missing.contains("libcudnn.so.9") && missing.contains("cargo xtask libtorch --cuda"), "{missing}");
        assert!(why(status(Some("13.0"), Ok("13.0"), Ok(()), 0)).contains("no CUDA device is visible"));
        assert_eq!(status(Some("13.0"), Ok("13.0"), Ok(()), 1).why_not(), None);
        assert_eq!(version_number("13.0"), 13000);
        assert!(version_number("12.9") < version_number("13.0"));
    }

    #[test]
    fn this_process_runs_with_the_libtorch_it_was_built_against() {
        let lib = libtorch_lib_dir().expect("libtorch_cpu.so is mapped");
        let expected = std::path::Path::new(env!("RLMFLOW_LIBTORCH")).join("lib");
        assert_eq!(lib.canonicalize().unwrap(), expected.canonicalize().unwrap());
        assert_eq!(built_for(&lib).is_some(), lib.join("libtorch_cuda.so").is_file());
    }
}
