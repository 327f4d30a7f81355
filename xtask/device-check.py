"""The GPU check of issue 48, for a short GPU loan: one command, no build on the GPU machine.

    python3 xtask/device-check.py --bin DIR [--torch-python PY] [--out DIR] [--dry]

DIR holds the release binaries `cargo xtask device-check --build-only` leaves in
target/device-check/ (rlmflow and rlmflow-torch, each may be xz-compressed as `NAME.xz`, and
the libpython3 rlmflow embeds, put on the library path here).
It runs, each part in its own processes, with the GPU's memory sampled by nvidia-smi:

1. `rlmflow-torch doctor`: CUDA loads, which devices, the class an action is keyed by.
2. examples/paper-smoke.toml with every model stage on `cuda` (precision `auto`: bf16), through
   the report, into a fresh store.
3. Pretraining of that pipeline twice more, into two fresh stores: the output digests must be
   equal (same key, same bytes on one GPU).
4. Memory: pretraining at a batch of 160 in chunks of 80 (the paper's per-GPU batch) against the
   dry run's estimate.
5. The paper's training step, `rlmflow-torch step` against PyTorch
   (`worker/benches/step_reference.py` under --torch-python), batch 64 and 160, fp32 and bf16,
   each measurement in its own process.

and prints one Markdown table (also written to --out). Without a CUDA device (or with --dry) it
checks its inputs (binaries run, the pipeline and its overrides validate, the reference script
is there), says so and exits 0: the test suite runs it that way, so it cannot rot between loans.
"""

import argparse
import json
import lzma
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PIPELINE = ROOT / "examples/paper-smoke.toml"
REFERENCE = ROOT / "worker/benches/step_reference.py"
BINARIES = ("rlmflow", "rlmflow-torch")
MODEL_STAGES = ("pretrain", "clipcap", "pup", "unet")
# The report's Rerun recording needs the managed Python environment, which a GPU machine without
# a network cannot install; the report's other files are made all the same.
CUDA = [f'{stage}.device="cuda"' for stage in MODEL_STAGES] + ["report.rerun=false"]
# The paper's per-GPU batch, embedded in chunks as examples/paper.toml does.
MEMORY = ["scenes.frames=400", "pretrain.batch=160", "pretrain.chunk=80", "--only", "pretrain"]


def binaries(directory):
    """Each binary's path, decompressed from NAME.xz beside it where only that was carried."""
    found = {}
    for name in BINARIES:
        path = directory / name
        packed = directory / f"{name}.xz"
        if not path.is_file() and packed.is_file():
            with lzma.open(packed) as source, open(path, "wb") as target:
                shutil.copyfileobj(source, target)
        if not path.is_file():
            sys.exit(f"device-check: {path} (or {packed}) is missing: `cargo xtask device-check --build-only` builds it")
        path.chmod(0o755)
        found[name] = path
    return found


def run(command, **kwargs):
    """Runs `command`; its stdout, or exits naming the command and its stderr's tail."""
    out = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    if out.returncode != 0:
        tail = "\n".join((out.stderr or out.stdout).strip().splitlines()[-15:])
        sys.exit(f"device-check: {' '.join(map(str, command))} failed ({out.returncode}):\n{tail}")
    return out.stdout


def overrides(sets):
    """Command-line arguments for `sets`: `stage.key=value` items as `--set`, `--only STAGE` kept."""
    args, items = [], iter(sets)
    for item in items:
        args += ["--only", next(items)] if item == "--only" else ["--set", item]
    return args


class MemorySampler:
    """The largest `memory.used` nvidia-smi reports for GPU 0 while it runs (MiB)."""

    def __init__(self):
        self.peak, self.running = 0, True
        self.thread = threading.Thread(target=self.sample, daemon=True)

    def sample(self):
        while self.running:
            out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits", "--id=0"], capture_output=True, text=True)
            if out.returncode == 0 and out.stdout.strip():
                self.peak = max(self.peak, int(out.stdout.split()[0]))
            time.sleep(0.2)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.running = False
        self.thread.join()


def outputs(rlmflow, store, sets):
    """Each instance's output digest in `store`, from `status --json`."""
    lines = run([rlmflow, "status", PIPELINE, "--json", "--store", store] + overrides([s for s in sets if "=" in s]))
    return {line["stage"]: line.get("output") for line in map(json.loads, lines.splitlines()) if line.strip()}


def pipeline(rlmflow, store, sets):
    """Runs the pipeline with `sets` into `store`: seconds and the GPU's peak MiB."""
    start = time.time()
    with MemorySampler() as memory:
        run([rlmflow, "run", PIPELINE, "--store", store, "--device", "cuda"] + overrides(sets), cwd=ROOT)
    return time.time() - start, memory.peak


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bin", type=Path, default=ROOT / "target/device-check")
    parser.add_argument("--torch-python", default=os.environ.get("RLMFLOW_TORCH_PYTHON", "/opt/torch/.venv/bin/python"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--dry", action="store_true", help="check the inputs only, even on a GPU")
    args = parser.parse_args()

    bins = binaries(args.bin)
    rlmflow, worker = bins["rlmflow"], bins["rlmflow-torch"]
    # The libpython rlmflow embeds, where it was carried beside the binaries.
    if list(args.bin.glob("libpython3*.so*")):
        os.environ["LD_LIBRARY_PATH"] = f"{args.bin}:{os.environ.get('LD_LIBRARY_PATH', '')}"
    doctor = run([worker, "doctor"])
    print(doctor)
    for path in (PIPELINE, REFERENCE):
        if not path.is_file():
            sys.exit(f"device-check: {path} is missing")
    # The overrides every part uses validate as the file does (dag checks every setting).
    for sets in (CUDA, CUDA + [s for s in MEMORY if "=" in s]):
        run([rlmflow, "dag", PIPELINE] + overrides(sets))
    usable = "CUDA           usable" in doctor
    if args.dry or not usable:
        why = "--dry" if args.dry else "no CUDA device (the doctor's report above says why)"
        print(f"device-check: dry mode, {why}: inputs checked (binaries run, {PIPELINE.name} and its overrides validate, the reference is there); nothing measured")
        return

    rows, scratch = [], Path(tempfile.mkdtemp(prefix="rlmflow-device-check-"))
    seconds, peak = pipeline(rlmflow, scratch / "smoke", CUDA)
    rows.append(("paper-smoke, every model stage on cuda, through the report", f"{seconds:.0f} s", f"peak {peak} MiB"))

    first = pipeline(rlmflow, scratch / "a", CUDA + ["--only", "pretrain"])
    second = pipeline(rlmflow, scratch / "b", CUDA + ["--only", "pretrain"])
    a = outputs(rlmflow, scratch / "a", CUDA)
    b = outputs(rlmflow, scratch / "b", CUDA)
    same = a.get("pretrain") is not None and a.get("pretrain") == b.get("pretrain")
    rows.append(("pretrain twice, two fresh stores", f"{first[0]:.0f} s / {second[0]:.0f} s", f"{'same bytes' if same else 'OTHER BYTES'}: {a.get('pretrain')} / {b.get('pretrain')}"))

    dry = run([rlmflow, "run", PIPELINE, "--dry-run", "--json", "--store", scratch / "memory", "--device", "cuda"] + overrides(CUDA + MEMORY))
    estimate = next((line["memory"]["peak_bytes"] for line in map(json.loads, dry.splitlines()) if line.get("stage") == "pretrain" and line.get("memory")), None)
    seconds, peak = pipeline(rlmflow, scratch / "memory", CUDA + MEMORY)
    estimate_mib = estimate / 2**20 if estimate else float("nan")
    rows.append(("memory: pretrain, batch 160 in chunks of 80", f"{seconds:.0f} s", f"peak {peak} MiB (with the CUDA context) against the estimate {estimate_mib:.0f} MiB: {peak / estimate_mib:.2f}x"))

    config = run([worker, "step", "--model", "paper", "--config"]).strip()
    for batch in ("64", "160"):
        for precision in ("fp32", "bf16"):
            ours = float(run([worker, "step", "--model", "paper", "--batch", batch, "--steps", "6", "--threads", "16", "--device", "cuda", "--precision", precision]))
            theirs = float(run([args.torch_python, REFERENCE, config, batch, "6", "16", "cuda", precision]))
            rate = lambda ms: int(batch) / ms * 1000
            rows.append((f"step, paper model, batch {batch}, {precision}", f"{ours:.1f} / {theirs:.1f} ms", f"rlmflow {rate(ours):.0f} samples/s, PyTorch {rate(theirs):.0f}: samples/s ratio {theirs / ours:.3f}"))

    table = "| check | time | result |\n|---|---|---|\n" + "\n".join(f"| {a} | {b} | {c} |" for a, b, c in rows)
    print(table)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "device-check.md").write_text(doctor + "\n" + table + "\n")
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
