"""Reads every computed instance of the pipeline in the current directory with the `rlmflow`
package, checks what each reader reads against what `rlmflow show` records for the instance,
and prints, per instance, the facts the Rust test compares with rlmflow's own readers."""

import json
import sys
import tomllib

import numpy as np
import rlmflow

pipeline = sys.argv[1]
with open(pipeline, "rb") as f:
    stages = list(tomllib.load(f)["stages"])

facts = {}
for stage in stages:
    for artifact in rlmflow.instances(pipeline, stage):
        metrics, reader = artifact.metrics, artifact.read()
        assert type(reader).__name__ == artifact.type, (artifact.label, artifact.type)
        # A Files artifact is marked by no file: it reads as its type only when named.
        if artifact.type != "Files":
            assert rlmflow.open(artifact.dir).__class__ is reader.__class__, artifact.label
        fact = {"type": artifact.type, "dir": str(artifact.dir), "key": artifact.record["key"]}
        if artifact.type == "Scenes":
            actors, images = reader.actors(), reader.images()
            assert len(actors) == images.shape[0] == metrics["frames"], artifact.label
            fact.update(frames=len(actors), shape=list(images.shape), pixels=int(images.astype(np.int64).sum()))
        elif artifact.type == "Labels":
            assert len(reader.frames) == metrics["frames"] and int((reader.split == "test").sum()) == metrics["test"], artifact.label
            assert reader.masks().shape[0] == len(reader.frames)
            fact.update(counts=int(reader.counts.sum()), test=int((reader.split == "test").sum()), ids=reader.ids)
        elif artifact.type == "Captions":
            assert len(reader.captions) == metrics["captions"], artifact.label
            fact.update(captions=[c["caption"] for c in reader.captions])
        elif artifact.type == "Tokens":
            ids = reader.ids()
            assert ids.shape[0] == metrics["captions"] and reader.tokenizer().get_vocab_size() == metrics["vocab"], artifact.label
            assert len(reader.frames()) == ids.shape[0]
            fact.update(shape=list(ids.shape), sum=int(ids.astype(np.int64).sum()))
        elif artifact.type == "Encoder":
            assert reader.summary["last"] == metrics["last"], artifact.label
            last = {k: v for k, v in reader.log[-1].items() if not k.startswith("batch_")} if reader.log else None
            assert last is None or last == metrics["last"], (artifact.label, last)
            weights = reader.weights()
            assert any(n.startswith("visual.") for n in weights) and "text_projection" in weights, sorted(weights)[:5]
            fact.update(tensors=len(weights), trained=len(reader.trained_frames()))
        elif artifact.type == "Embeddings":
            cls, mean = reader.cls(), reader.mean_patch()
            assert cls.shape[0] == mean.shape[0] == len(reader.frames) == reader.summary["frames"], artifact.label
            assert [list(cls.shape), list(mean.shape)] == [reader.summary["arrays"]["cls.npy"], reader.summary["arrays"]["mean_patch.npy"]]
            fact.update(shape=list(cls.shape), sum=float(cls.astype(np.float64).sum()), test=int((reader.split == "test").sum()))
        elif artifact.type == "ProbeReport":
            for row in reader.summary["rows"]:
                assert row["scores"]["overall"]["f1"] == metrics[row["features"]]["f1"], (artifact.label, row["features"])
            fact.update(predictions=len(reader.predictions), rows=[r["features"] for r in reader.summary["rows"]])
        elif artifact.type == "SegReport":
            for name in ("iou", "dice", "ap", "peak_iou"):
                assert reader.summary["metrics"][name] == metrics[name], (artifact.label, name)
            assert len(reader.frames) == reader.summary["test_frames"] and reader.samples().ndim == 3
            fact.update(frames=[f["frame"] for f in reader.frames], iou=[f["iou"] for f in reader.frames])
        elif artifact.type == "Files":
            fact.update(files=reader.files)
        elif artifact.type == "Report":
            assert reader.html.is_file() and reader.metrics, artifact.label
            fact.update(sections=sorted(reader.metrics))
        facts[artifact.label] = fact

try:
    rlmflow.load(pipeline, "pretrain")
    raise AssertionError("`pretrain` names several instances; load must refuse it")
except LookupError as e:
    assert "name one" in str(e), e
json.dump(facts, sys.stdout)
