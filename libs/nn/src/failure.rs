//! A libtorch error inside an operator as the operator's error. tch's infallible methods panic
//! on a libtorch error (`called Result::unwrap() on an Err value: Torch("...")`, with a C++
//! backtrace); [`catching`] turns that panic into an error holding libtorch's message alone, so
//! the engine reports the stage as failed, with its name and device, instead of a panic.

use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};

/// Runs an operator's body; a libtorch error it panicked with becomes its error. Any other
/// panic (a bug in rlmflow's own code) goes on as a panic.
pub fn catching<T>(body: impl FnOnce() -> anyhow::Result<T>) -> anyhow::Result<T> {
    match catch_unwind(AssertUnwindSafe(body)) {
        Ok(result) => result,
        Err(payload) => {
            let text = payload.downcast_ref::<String>().map(String::as_str).or_else(|| payload.downcast_ref::<&str>().copied());
            match text.and_then(libtorch_message) {
                Some(message) => Err(anyhow::anyhow!("libtorch: {message}")),
                None => resume_unwind(payload),
            }
        }
    }
}

/// libtorch's message in a panic's text, without the C++ backtrace it carries.
fn libtorch_message(panic: &str) -> Option<String> {
    let start = panic.find("Torch(\"")? + "Torch(\"".len();
    let quoted = &panic[start..];
    // The error is Debug-printed: escaped newlines, the backtrace after the first.
    let end = [quoted.find("\\n"), quoted.rfind("\")")].into_iter().flatten().min().unwrap_or(quoted.len());
    Some(quoted[..end].replace("\\\"", "\"").trim().to_owned())
}

#[cfg(test)]
mod tests {
    use tch::{Device, Kind, Tensor};

    use super::*;

    #[test]
    fn a_libtorch_error_is_an_error_with_its_message_and_no_backtrace() {
        let a = Tensor::zeros([2, 3], (Kind::Float, Device::Cpu));
        let b = Tensor::zeros([4, 5], (Kind::Float, Device::Cpu));
        let err = catching(|| Ok(a.matmul(&b))).unwrap_err().to_string();
        assert!(err.starts_with("libtorch: mat1 and mat2 shapes cannot be multiplied (2x3 and 4x5)"), "{err}");
        assert!(!err.contains("Exception raised from"), "{err}");
    }

    #[test]
    fn other_panics_stay_panics() {
        let outcome = catch_unwind(|| catching(|| -> anyhow::Result<()> { panic!("a bug") }));
        assert!(outcome.is_err());
    }
}
