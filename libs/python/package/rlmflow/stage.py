"""What a `script` stage's program is told, and how it reports.

    from rlmflow import stage
    ctx = stage.context()
    labels = ctx.read("labels")              # a reader of the artifact bound to the slot
    k = ctx.settings.get("k", 10)
    stage.progress(3, 10, "folds")
    stage.event("fold", k=k, f1=0.41)
    stage.metrics(f1=0.41)
    stage.summary("k=10 F1 0.410")

The context comes from `$RLMFLOW_STAGE` (docs/guide/your-own-stage.md); each report is one
`@rlmflow {json}` line on stdout, which rlmflow shows as it shows its own stages' progress,
events and metrics. Print anything else freely: it goes to the stage's log.
"""

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Context", "context", "progress", "event", "metrics", "summary", "live"]


@dataclass(frozen=True)
class Input:
    label: str
    path: Path


@dataclass(frozen=True)
class Context:
    stage: str
    inputs: dict
    output: Path
    checkpoint: Path
    seed: int
    settings: dict
    device: str
    threads: int

    def input(self, slot):
        """The directory of the one artifact bound to `slot`."""
        found = self.inputs.get(slot) or []
        if len(found) != 1:
            raise KeyError(f"{self.stage}: slot `{slot}` holds {len(found)} artifacts; bound slots: {', '.join(self.inputs) or 'none'}")
        return found[0].path

    def read(self, slot):
        """The reader of the one artifact bound to `slot` (`rlmflow.open`)."""
        from . import open as open_artifact

        return open_artifact(self.input(slot))


def context():
    """This stage's context, read from `$RLMFLOW_STAGE`."""
    path = os.environ.get("RLMFLOW_STAGE")
    if not path:
        raise RuntimeError("not run by rlmflow: $RLMFLOW_STAGE is unset (a script stage's program is started by `rlmflow run`)")
    raw = json.loads(Path(path).read_text())
    inputs = {slot: [Input(i["label"], Path(i["path"])) for i in items] for slot, items in raw["inputs"].items()}
    return Context(
        stage=raw["stage"],
        inputs=inputs,
        output=Path(raw["output"]),
        checkpoint=Path(raw["checkpoint"]),
        seed=int(raw["seed"]),
        settings=raw["settings"],
        device=raw["device"],
        threads=int(raw["threads"]),
    )


def _send(message):
    sys.stdout.write("@rlmflow " + json.dumps(message, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def progress(position, length, message=""):
    _send({"progress": {"position": int(position), "length": int(length), "message": str(message)}})


def event(name, **data):
    _send({"event": str(name), "data": data})


def metrics(**values):
    _send({"metrics": values})


def summary(text):
    _send({"summary": str(text)})


def live(dir):
    """Says that `dir` (below the checkpoint directory) shows the work as it goes, TensorBoard
    event files say: `results/` links the stage there until its output is committed."""
    _send({"live": str(dir)})
