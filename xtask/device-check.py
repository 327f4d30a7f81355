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
4. The paper's training step, `rlmflow-torch step` against PyTorch
   (`worker/benches/step_reference.py` under --torch-python), batch 64 and 160, fp32 and bf16,
   each measurement in its own process.
5. Memory: pretraining at a batch of 160 in chunks of 80 (the paper's per-GPU batch) against the
   dry run's estimate.
6. This machine's CPU, another CPU model than the one that wrote docs/digests/: examples/ci.toml
   into fresh stores (portable numerics, the FMA-chain GEMM at the CPU's widest lanes, then at 8)
   against docs/digests/ci.toml.digests, and the laptop model's step, portable against native.
   Its highway-env scenes come from DIR/ci-seeds, a file remote `--build-only` fills (the GPU
   machine has no network to make the Python environment highway-env runs in).
7. Packed: paper-smoke's model stages with the GPU held whole by each (its memory declared
   unknown, `RLMFLOW_GPU_INVENTORY`), then packed onto it by their memory estimates, into two
   fresh stores: every output digest must be equal; the peak memory against the sum of the
   estimates, the wall time against the one-at-a-time run's.
8. Claims: examples/gpu-claims.toml cold into a fresh store on cuda (its placed scenes computed
   on this machine's cores), adding seeds until every claim is decided: the verdicts with their
   seeds and intervals (`rlmflow claims --json`), and the wall time against the 8 minutes the
   profile is meant to fit.

and prints one Markdown table, row by row (also written to --out after each row; a failed part
is a row saying why, and the check goes on). Without a CUDA device (or with --dry) it
checks its inputs (binaries run, the pipeline and its overrides validate, the reference script
is there), says so and exits 0: the test suite runs it that way, so it cannot rot between loans.
`--cpu` runs part 6 alone, on any machine.
"""

import argparse
import json
import lzma
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PIPELINE = ROOT / "examples/paper-smoke.toml"
CI = ROOT / "examples/ci.toml"
CI_DIGESTS = ROOT / "docs/digests/ci.toml.digests"
GPU_CLAIMS = ROOT / "examples/gpu-claims.toml"
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


def torch_libraries(python):
    """`torch/lib` of the torch `python` imports, found without importing it; None if none."""
    if not shutil.which(python) and not Path(python).is_file():
        return None
    query = "import importlib.util, os; s = importlib.util.find_spec('torch'); print(os.path.join(os.path.dirname(s.origin), 'lib') if s else '')"
    out = subprocess.run([python, "-c", query], capture_output=True, text=True)
    found = out.stdout.strip()
    return found if out.returncode == 0 and found and (Path(found) / "libtorch_cpu.so").is_file() else None


class Failed(Exception):
    """A command of the check failed: which, and its stderr's tail."""


def run(command, allowed=(0,), **kwargs):
    """Runs `command`; its stdout, or raises `Failed` naming the command and its stderr's tail
    when it exits with a status not `allowed`."""
    out = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    if out.returncode not in allowed:
        tail = "\n".join((out.stderr or out.stdout).strip().splitlines()[-15:])
        raise Failed(f"{' '.join(map(str, command))} failed ({out.returncode}):\n{tail}")
    return out.stdout


class Table:
    """The check's Markdown table, printed and written to `out` row by row: a loan that ends
    mid-check still leaves every figure measured so far, and a failed part is a row, not the end."""

    def __init__(self, out, doctor):
        self.out, self.doctor, self.rows, self.failed = out, doctor, [], 0

    def measure(self, check, part):
        start = time.time()
        try:
            time_taken, result = part()
        except Failed as failure:
            self.failed += 1
            print(failure, file=sys.stderr)
            time_taken, result = f"{time.time() - start:.0f} s", "FAILED: " + str(failure).splitlines()[-1][:300].replace("|", "/")
        self.rows.append((check, time_taken, result))
        print(f"| {check} | {time_taken} | {result} |", flush=True)
        if self.out:
            self.out.mkdir(parents=True, exist_ok=True)
            body = "\n".join(f"| {a} | {b} | {c} |" for a, b, c in self.rows)
            (self.out / "device-check.md").write_text(f"{self.doctor}\n| check | time | result |\n|---|---|---|\n{body}\n")


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
    lines = run([rlmflow, "status", PIPELINE, "--json", "--cache", store] + overrides([s for s in sets if "=" in s]))
    return {line["stage"]: line.get("output") for line in map(json.loads, filter(str.strip, lines.splitlines()))}


def pipeline(rlmflow, store, sets, env=None):
    """Runs the pipeline with `sets` into `store` (`env` added to the environment): seconds and
    the GPU's peak MiB."""
    start = time.time()
    with MemorySampler() as memory:
        run([rlmflow, "run", PIPELINE, "--cache", store, "--device", "cuda"] + overrides(sets), cwd=ROOT, env={**os.environ, **(env or {})})
    return time.time() - start, memory.peak


def cpu_checks(table, rlmflow, worker, bin_dir):
    """Part 6: this CPU's portable bytes against the shipped digests, and what the pins cost here."""
    model = cpu_model()
    seeds = bin_dir / "ci-seeds"
    # Every instance but the report, whose sample figures read nothing the others do not.
    stages = [re.split(r"[\[#]", row.split()[0])[0] for row in CI_DIGESTS.read_text().splitlines() if row.strip() and not row.startswith("#")]
    only = [a for stage in dict.fromkeys(stages) if stage != "report" for a in ("--only", stage)]
    for lanes in ("", "8"):
        def against(lanes=lanes):
            if not seeds.is_dir():
                raise Failed(f"{seeds} is missing: `cargo xtask device-check --build-only` makes it")
            store = Path(tempfile.mkdtemp(prefix="rlmflow-cpu-check-"))
            # No CUDA device is visible, or the stages set to `auto` (the probes) would compute there.
            env = dict(os.environ, CUDA_VISIBLE_DEVICES="", **({"RLMFLOW_GEMM_LANES": lanes} if lanes else {}))
            start = time.time()
            run([rlmflow, "run", CI, "--cache", store, "--remote", f"file://{seeds.resolve()}"] + only, cwd=ROOT, env=env)
            seconds = time.time() - start
            out = subprocess.run([rlmflow, "verify", CI, "--cache", store, "--against", CI_DIGESTS], capture_output=True, text=True)
            shutil.rmtree(store, ignore_errors=True)
            summary = next((line for line in out.stdout.splitlines() if line.startswith("verify --against")), out.stderr.strip()[-300:])
            differs = [line.split()[1] for line in out.stdout.splitlines() if line.strip().startswith("DIFFERS")]
            if differs:
                raise Failed(f"{summary.split(': ', 1)[-1]}; differ: {', '.join(differs)}")
            return f"{seconds:.0f} s", summary.split(": ", 1)[-1]

        width = f"{lanes} lanes" if lanes else "its widest lanes"
        table.measure(f"cpu: examples/ci.toml on {model} (GEMM at {width}) against {CI_DIGESTS.name}", against)

    def pins():
        times = {}
        for numerics in ("native", "portable"):
            times[numerics] = float(run([worker, "step", "--model", "laptop", "--batch", "128", "--steps", "8", "--numerics", numerics, "--threads", "2"]))
        return f"{times['portable']:.0f} / {times['native']:.0f} ms", f"portable {times['portable'] / times['native']:.2f}x native (laptop model, batch 128, 2 threads)"

    table.measure(f"cpu: step, portable against native, {model}", pins)


def cpu_model():
    """The CPU's model name, as /proc/cpuinfo says it."""
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "this CPU"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bin", type=Path, default=ROOT / "target/device-check")
    parser.add_argument("--torch-python", default=os.environ.get("RLMFLOW_TORCH_PYTHON", "/opt/torch/.venv/bin/python"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--dry", action="store_true", help="check the inputs only, even on a GPU")
    parser.add_argument("--cpu", action="store_true", help="only this CPU against the shipped digests (part 6)")
    args = parser.parse_args()

    bins = binaries(args.bin)
    rlmflow, worker = bins["rlmflow"], bins["rlmflow-torch"]
    # The libpython rlmflow embeds, where it was carried beside the binaries.
    if list(args.bin.glob("libpython3*.so*")):
        os.environ["LD_LIBRARY_PATH"] = f"{args.bin}:{os.environ.get('LD_LIBRARY_PATH', '')}"
    # The worker's run path names this machine's libtorch; a GPU machine has its own torch 2.11
    # (the one the reference runs on), whose libraries it then loads, CUDA's with them.
    libtorch = torch_libraries(args.torch_python)
    if libtorch:
        os.environ["LD_LIBRARY_PATH"] = ":".join(filter(None, [os.environ.get("LD_LIBRARY_PATH"), libtorch]))
    doctor = run([worker, "doctor"])
    print(doctor)
    for path in (PIPELINE, REFERENCE, CI, CI_DIGESTS, GPU_CLAIMS):
        if not path.is_file():
            sys.exit(f"device-check: {path} is missing")
    # The overrides every part uses validate as the file does (dag checks every setting).
    for sets in (CUDA, CUDA + [s for s in MEMORY if "=" in s]):
        run([rlmflow, "dag", PIPELINE] + overrides(sets))
    run([rlmflow, "dag", GPU_CLAIMS])
    usable = "CUDA           usable" in doctor
    if args.cpu:
        table = Table(args.out, doctor)
        cpu_checks(table, rlmflow, worker, args.bin)
        sys.exit(f"device-check: {table.failed} checks failed (the table says which and why)" if table.failed else 0)
    if args.dry or not usable:
        why = "--dry" if args.dry else "no CUDA device (the doctor's report above says why)"
        print(f"device-check: dry mode, {why}: inputs checked (binaries run, {PIPELINE.name} and its overrides validate, the reference is there); nothing measured")
        return

    table, scratch = Table(args.out, doctor), Path(tempfile.mkdtemp(prefix="rlmflow-device-check-"))

    def smoke():
        seconds, peak = pipeline(rlmflow, scratch / "smoke", CUDA)
        return f"{seconds:.0f} s", f"peak {peak} MiB"

    table.measure("paper-smoke, every model stage on cuda, through the report", smoke)

    def twice():
        first = pipeline(rlmflow, scratch / "a", CUDA + ["--only", "pretrain"])
        second = pipeline(rlmflow, scratch / "b", CUDA + ["--only", "pretrain"])
        digests = [outputs(rlmflow, scratch / store, CUDA).get("pretrain") for store in ("smoke", "a", "b")]
        same = None not in digests[1:] and len(set(filter(None, digests))) == 1
        return f"{first[0]:.0f} s / {second[0]:.0f} s", f"{'same bytes' if same else 'OTHER BYTES'} (smoke run, a, b): {' / '.join(map(str, digests))}"

    table.measure("pretrain twice more, two fresh stores, each its own process", twice)

    config = run([worker, "step", "--model", "paper", "--config"]).strip()
    for batch in ("64", "160"):
        for precision in ("fp32", "bf16"):
            def step(batch=batch, precision=precision):
                ours = float(run([worker, "step", "--model", "paper", "--batch", batch, "--steps", "6", "--threads", "16", "--device", "cuda", "--precision", precision]))
                theirs = float(run([args.torch_python, REFERENCE, config, batch, "6", "16", "cuda", precision]))
                rate = lambda ms: int(batch) / ms * 1000
                return f"{ours:.1f} / {theirs:.1f} ms", f"rlmflow {rate(ours):.0f} samples/s, PyTorch {rate(theirs):.0f}: samples/s ratio {theirs / ours:.3f}"

            table.measure(f"step, paper model, batch {batch}, {precision}", step)

    def memory():
        dry = run([rlmflow, "run", PIPELINE, "--dry-run", "--json", "--cache", scratch / "memory", "--device", "cuda"] + overrides(CUDA + MEMORY))
        estimate = next((line["memory"]["peak_bytes"] for line in map(json.loads, filter(str.strip, dry.splitlines())) if line.get("stage") == "pretrain" and line.get("memory")), None)
        seconds, peak = pipeline(rlmflow, scratch / "memory", CUDA + MEMORY)
        estimate_mib = estimate / 2**20 if estimate else float("nan")
        return f"{seconds:.0f} s", f"peak {peak} MiB (with the CUDA context) against the estimate {estimate_mib:.0f} MiB: {peak / estimate_mib:.2f}x"

    table.measure("memory: pretrain, batch 160 in chunks of 80", memory)

    def packed():
        model = run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader", "--id=0"]).strip()
        alone = pipeline(rlmflow, scratch / "alone", CUDA, env={"RLMFLOW_GPU_INVENTORY": f"0:{model}"})
        shared = pipeline(rlmflow, scratch / "packed", CUDA)
        a, b = outputs(rlmflow, scratch / "alone", CUDA), outputs(rlmflow, scratch / "packed", CUDA)
        same = a == b and None not in a.values()
        dry = run([rlmflow, "run", PIPELINE, "--dry-run", "--json", "--cache", scratch / "estimates", "--device", "cuda"] + overrides(CUDA))
        lines = [json.loads(line) for line in dry.splitlines() if line.strip()]
        estimates = sum(line["memory"]["peak_bytes"] for line in lines if line.get("memory")) / 2**20
        return (
            f"{shared[0]:.0f} s packed / {alone[0]:.0f} s one at a time",
            f"{'same bytes' if same else 'OTHER BYTES'} for {len(a)} instances; peak {shared[1]} MiB packed ({alone[1]} alone) against the estimates' sum {estimates:.0f} MiB; wall ratio {alone[0] / shared[0]:.2f}x",
        )

    table.measure("packed: paper-smoke's model stages on one GPU by their estimates, against one at a time", packed)

    def claims():
        store = scratch / "claims"
        start = time.time()
        # A required claim that fails exits 1 with every verdict printed: still a measurement.
        run([rlmflow, "run", GPU_CLAIMS, "--cache", store, "--device", "cuda", "--jobs", str(os.cpu_count() or 1)], allowed=(0, 1))
        seconds = time.time() - start
        line = json.loads(run([rlmflow, "claims", GPU_CLAIMS, "--json", "--cache", store, "--device", "cuda"], allowed=(0, 1)).strip().splitlines()[-1])
        said = [f"{v['claim']} {v['decision']} at {v['seeds']} seeds" for v in line["verdicts"]]
        return f"{seconds:.0f} s ({seconds / 60:.1f} min, target 8)", f"{line['seeds']} seeds: " + "; ".join(said)

    table.measure("claims: gpu-claims.toml cold on cuda, seeds until decided", claims)
    shutil.rmtree(scratch, ignore_errors=True)
    cpu_checks(table, rlmflow, worker, args.bin)
    if table.failed:
        sys.exit(f"device-check: {table.failed} checks failed (the table says which and why)")

if __name__ == "__main__":
    try:
        main()
    except Failed as failure:
        sys.exit(f"device-check: {failure}")
