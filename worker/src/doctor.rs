//! `rlmflow-torch doctor`: which devices the worker can compute on and, where CUDA is out of
//! reach, the first cause (`rlmflow_nn::cuda::Status`); with the numeric platform classes its
//! actions would be keyed by.

use std::process::ExitCode;

use rlmflow_engine::cli::ExtraCommand;
use rlmflow_stages::numerics::{Cpu, Gpu, Numerics, Target, class};

pub fn command() -> ExtraCommand {
    ExtraCommand {
        command: clap::Command::new("doctor").about("Which devices the torch worker can compute on, and why not CUDA where it cannot"),
        run: |_| run(),
    }
}

fn run() -> anyhow::Result<ExitCode> {
    let status = rlmflow_nn::cuda::status();
    println!("{status}");
    let cpu = Cpu::detect();
    println!("cpu            {} ({})", cpu.model, cpu.extensions.join(" "));
    println!(
        "classes        {} (numerics = \"portable\"), {}",
        class(Numerics::Portable, &cpu, Target::Cpu, None),
        class(Numerics::Native, &cpu, Target::Cpu, None)
    );
    for n in 0..status.devices {
        let gpu = Gpu::detect(n as usize);
        println!("cuda:{n}         {}", class(Numerics::Portable, &cpu, Target::Cuda(n as usize), gpu.as_ref()));
    }
    Ok(ExitCode::SUCCESS)
}
