"""Read an rlmflow pipeline's artifacts from Python.

    import rlmflow
    encoder = rlmflow.load("pipeline.toml", "pretrain[alpha4]")
    encoder.dir, encoder.record["key"], encoder.metrics["last"]["top1"]
    weights = encoder.read().weights()          # numpy arrays by open_clip's names

`load` and `instances` ask the `rlmflow` binary (`rlmflow show --json`: `$RLMFLOW_BIN`, else
`rlmflow` on the PATH) where an instance's artifact is; `open` reads an artifact directory
directly (a script stage's inputs). Everything here is read-only: it never computes, and an
instance the store does not hold is an error saying why (`rlmflow run` computes it).

The readers follow docs/reference/artifacts.md. Each imports what it needs when called (numpy
always; scenes through `mcap`, tokens through `tokenizers`, weights through `safetensors`, an
encoder into open_clip through `torch` and `open_clip`), so reading a probe's scores needs
nothing but numpy.
"""

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Artifact", "NotComputed", "instances", "load", "open", "binary"]


class NotComputed(LookupError):
    """The store holds no output for the instance (yet)."""


def binary():
    """The rlmflow binary this package asks: `$RLMFLOW_BIN`, else `rlmflow` on the PATH."""
    found = os.environ.get("RLMFLOW_BIN") or shutil.which("rlmflow")
    if not found:
        raise FileNotFoundError("no rlmflow binary: set RLMFLOW_BIN to one (target/release/rlmflow) or put it on the PATH")
    return found


@dataclass(frozen=True)
class Artifact:
    """One instance's output as the store records it."""

    label: str
    stage: str
    type: str
    dir: Path
    record: dict

    @property
    def metrics(self):
        return self.record.get("metrics") or {}

    @property
    def summary(self):
        return self.record.get("summary", "")

    def read(self):
        """The reader of this artifact's type (`Scenes`, `Labels`, ... `Report`)."""
        return open(self.dir, self.type)


def _show(pipeline, stage, store=None):
    command = [binary(), "show", os.fspath(pipeline), stage, "--json"]
    if store is not None:
        command += ["--cache", os.fspath(store)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"`{' '.join(command)}` failed: {done.stderr.strip()}")
    return json.loads(done.stdout)["instances"]


def _artifact(shown):
    if shown["state"] != "cached":
        raise NotComputed(f"{shown['label']}: not computed yet ({shown['why']}); `rlmflow run` computes it")
    return Artifact(
        label=shown["label"],
        stage=shown["stage"],
        type=shown["type"],
        dir=Path(shown["output"]),
        record=shown["record"],
    )


def instances(pipeline, stage, store=None):
    """Every computed instance of `stage` (a stage name, or one instance's label)."""
    return [_artifact(s) for s in _show(pipeline, stage, store) if s["state"] == "cached"]


def load(pipeline, instance, store=None):
    """The artifact of one instance, named as a run prints it: `pretrain[alpha4]`,
    `clipcap[pretrain=alpha1,seed=2]`, `report`."""
    shown = _show(pipeline, instance, store)
    if len(shown) != 1:
        labels = ", ".join(s["label"] for s in shown)
        raise LookupError(f"`{instance}` names {len(shown)} instances ({labels}): name one")
    return _artifact(shown[0])


def _lines(path):
    with path.open() as f:
        return [json.loads(line) for line in f if line.strip()]


def _json(path):
    with path.open() as f:
        return json.load(f)


def _numpy():
    import numpy

    return numpy


class _Reader:
    """An artifact directory and the file that marks its type, read as `summary`."""

    MARKER = ""

    def __init__(self, dir):
        self.dir = Path(dir)
        self.summary = _json(self.dir / self.MARKER)


class Scenes(_Reader):
    """`scenes.mcap` (a `foxglove.RawImage` channel per radar view, `/actors` as JSON) and
    `scenes.json`."""

    MARKER = "scenes.json"
    ACTORS = "/actors"

    @property
    def topics(self):
        return [image["topic"] for image in self.summary["images"]]

    def _messages(self):
        from mcap.reader import make_reader

        with (self.dir / "scenes.mcap").open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                yield schema, channel, message

    def actors(self):
        """Per frame, its identity, episode and every actor's state, in frame order."""
        return [json.loads(m.data) for _, c, m in self._messages() if c.topic == self.ACTORS]

    def images(self, topic=None):
        """One view's frames as a `(frames, height, width)` uint8 array (the first view by default)."""
        from mcap_protobuf.decoder import DecoderFactory

        np = _numpy()
        topic = topic or self.topics[0]
        if topic not in self.topics:
            raise KeyError(f"{self.dir}: no view `{topic}`; the views are {', '.join(self.topics)}")
        decoders = DecoderFactory()
        frames = []
        for schema, channel, message in self._messages():
            if channel.topic == topic:
                image = decoders.decoder_for(channel.message_encoding, schema)(message.data)
                frames.append(np.frombuffer(image.data, dtype=np.uint8).reshape(image.height, image.width))
        return np.stack(frames)


class Labels(_Reader):
    """`labels.jsonl` (per frame its identity, split, 48 counts and grid), `masks.npy`, `labels.json`."""

    MARKER = "labels.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.frames = _lines(self.dir / "labels.jsonl")

    @property
    def ids(self):
        return [f["id"] for f in self.frames]

    @property
    def split(self):
        """Each frame's split (`train` or `test`), in frame order."""
        return _numpy().array([f["split"] for f in self.frames])

    @property
    def counts(self):
        """The 48 cell counts of every frame, `(frames, 48)`."""
        return _numpy().array([f["counts"] for f in self.frames], dtype=_numpy().int64)

    def masks(self):
        return _numpy().load(self.dir / "masks.npy")


class Captions(_Reader):
    """`captions.jsonl`: one `{frame, id, split, caption}` per caption."""

    MARKER = "captions.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.captions = _lines(self.dir / "captions.jsonl")


class Tokens(_Reader):
    """`tokens.npy` (a caption a row), `frames.npy` (each row's frame), `tokenizer.json`."""

    MARKER = "tokens.json"

    def ids(self):
        return _numpy().load(self.dir / "tokens.npy")

    def frames(self):
        return _numpy().load(self.dir / "frames.npy")

    def learnt_frames(self):
        return (self.dir / "learnt_frames.txt").read_text().split()

    def tokenizer(self):
        from tokenizers import Tokenizer

        return Tokenizer.from_file(os.fspath(self.dir / "tokenizer.json"))


def _weights(path):
    from safetensors.numpy import load_file

    return load_file(os.fspath(path))


class Encoder(_Reader):
    """`model.safetensors` (open_clip's names), `config.json`, `train.jsonl`, `encoder.json`."""

    MARKER = "encoder.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.config = _json(self.dir / "config.json")
        self.log = _lines(self.dir / "train.jsonl")

    def trained_frames(self):
        return (self.dir / "trained_frames.txt").read_text().split()

    def weights(self):
        return _weights(self.dir / "model.safetensors")

    def open_clip(self):
        """The encoder as an `open_clip.CLIP` in eval mode (torch and open_clip_torch installed
        by the caller), loaded as docs/guide/paper-scale.md says; where open_clip cannot build
        it, an error saying why."""
        config = self.dir / "open_clip.json"
        if not config.is_file():
            why = self.config.get("open_clip", "its config.json says nothing")
            raise ValueError(f"{self.dir}: open_clip cannot build this encoder: {why}")
        import open_clip
        import safetensors.torch
        from open_clip.transformer import QuickGELU

        model = open_clip.CLIP(**_json(config))
        weights = safetensors.torch.load_file(os.fspath(self.dir / "model.safetensors"))
        weights["visual.conv1.weight"] = weights["visual.conv1.weight"].repeat(1, 3, 1, 1) / 3
        model.load_state_dict(weights)
        for block in model.transformer.resblocks:
            block.mlp.gelu = QuickGELU()
        return model.eval()


class Embeddings(_Reader):
    """A frozen encoder's features: `cls.npy`, `mean_patch.npy`, `patches.npy` (float32, frames
    first), `frames.jsonl` (each frame's identity and split) and the encoder's learnt sets."""

    MARKER = "embed.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.frames = _lines(self.dir / "frames.jsonl")

    @property
    def split(self):
        """Each frame's split (`train` or `test`), in frame order."""
        return _numpy().array([f["split"] for f in self.frames])

    def cls(self):
        return _numpy().load(self.dir / "cls.npy")

    def mean_patch(self):
        return _numpy().load(self.dir / "mean_patch.npy")

    def patches(self):
        return _numpy().load(self.dir / "patches.npy")

    def trained_frames(self):
        return (self.dir / "trained_frames.txt").read_text().split()


class ProbeReport(_Reader):
    """`probe.json` (scored rows, per bin and cell) and `predictions.jsonl` (each test frame's grid)."""

    MARKER = "probe.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.predictions = _lines(self.dir / "predictions.jsonl")


class SegReport(_Reader):
    """`segment.json`, `frames.jsonl` (each test frame's IoU and Dice), `samples.npy`."""

    MARKER = "segment.json"

    def __init__(self, dir):
        super().__init__(dir)
        self.frames = _lines(self.dir / "frames.jsonl")

    def samples(self):
        return _numpy().load(self.dir / "samples.npy")

    def weights(self):
        return _weights(self.dir / "head.safetensors")


class Report(_Reader):
    """`metrics.json` (every number of the tables), `report.md`, `report.html`, `report.rrd`."""

    MARKER = "metrics.json"

    @property
    def metrics(self):
        return self.summary

    @property
    def html(self):
        return self.dir / "report.html"


class Files:
    """A `files` stage's output (a script's): whatever its program wrote, marked by no file, so
    only read as this type when the type is named (`Artifact.read`, `open(dir, "Files")`)."""

    def __init__(self, dir):
        self.dir = Path(dir)

    @property
    def files(self):
        """Every file, by its path below the artifact, sorted."""
        return sorted(str(p.relative_to(self.dir)) for p in self.dir.rglob("*") if p.is_file())


READERS = {reader.__name__: reader for reader in (Scenes, Labels, Captions, Tokens, Encoder, Embeddings, ProbeReport, SegReport, Report)}


def open(dir, type=None):
    """The reader of the artifact in `dir`: of `type` where given, else the type its files mark."""
    dir = Path(dir)
    if type is None:
        marked = [name for name, reader in READERS.items() if (dir / reader.MARKER).is_file()]
        if len(marked) != 1:
            raise ValueError(f"{dir}: not an artifact this package reads (it marks {marked or 'no type'}); types: {', '.join(READERS)}")
        type = marked[0]
    if type == "Files":
        return Files(dir)
    if type not in READERS:
        raise ValueError(f"{dir}: no reader for `{type}`; types: {', '.join(READERS)}, Files")
    if not (dir / READERS[type].MARKER).is_file():
        raise ValueError(f"{dir}: holds no `{READERS[type].MARKER}`: it is not a {type} artifact")
    return READERS[type](dir)
