"""A k-nearest-neighbour probe on a frozen encoder's features (`embed`'s arrays), in numpy.

Each test frame's 48 cell counts are predicted as the rounded mean of its k nearest training
frames' counts, by cosine (or euclidean) distance, for two rows: the CLS embedding and the mean
patch token. rlmflow scores the predictions with the paper's rule, beside `linear`'s rows.

Deterministic on every machine: distances are summed one feature column at a time (elementwise
operations only, so no BLAS kernel chooses the order of a sum), neighbours are ranked by a
stable sort, and nothing here draws a random number or reads the clock. Each row's predictions
are kept in the checkpoint directory as they are made, so a killed run resumes after its
finished rows.
"""

import json

import numpy as np

from rlmflow import stage

ROWS = [("cls-knn", "cls.npy"), ("mean-patch-knn", "mean_patch.npy")]


def distances(test, train, metric):
    """(test, train) distances, summed over the columns in order."""
    if metric == "cosine":
        test, train = test / norms(test), train / norms(train)
    d = np.zeros((len(test), len(train)))
    for j in range(test.shape[1]):
        if metric == "cosine":
            d -= test[:, j : j + 1] * train[:, j][None, :]
        else:
            d += (test[:, j : j + 1] - train[:, j][None, :]) ** 2
    return d


def norms(x):
    total = np.zeros((len(x), 1))
    for j in range(x.shape[1]):
        total[:, 0] += x[:, j] ** 2
    return np.maximum(np.sqrt(total), 1e-12)


def main():
    ctx = stage.context()
    k, metric = int(ctx.settings.get("k", 10)), ctx.settings.get("metric", "cosine")
    if metric not in ("cosine", "euclidean"):
        raise SystemExit(f"settings.metric must be cosine or euclidean, not {metric!r}")
    embeddings = ctx.input("embeddings")
    frames = [json.loads(line) for line in (embeddings / "frames.jsonl").read_text().splitlines()]
    split = np.array([f["split"] for f in frames])
    train, test = np.flatnonzero(split == "train"), np.flatnonzero(split == "test")
    counts = ctx.read("labels").counts
    k = min(k, len(train))
    lines = []
    for n, (row, file) in enumerate(ROWS):
        done = ctx.checkpoint / f"{row}.jsonl"
        if not done.exists():
            x = np.load(embeddings / file).astype(np.float64)
            nearest = np.argsort(distances(x[test], x[train], metric), axis=1, kind="stable")[:, :k]
            predicted = np.rint(counts[train][nearest].mean(axis=1)).astype(np.int64)
            text = "".join(json.dumps({"frame": int(f), "features": row, "counts": p.tolist()}) + "\n" for f, p in zip(test, predicted))
            partial = done.with_suffix(".part")
            partial.write_text(text)
            partial.rename(done)
        lines.append(done.read_text())
        stage.progress(n + 1, len(ROWS), "rows")
    (ctx.output / "predictions.jsonl").write_text("".join(lines))
    stage.metrics(k=k, train_frames=int(len(train)))
    stage.summary(f"k={k} {metric}")


if __name__ == "__main__":
    main()
