"""The report's Rerun recording, written with the rerun-sdk package (embedded by rlmflow).

The file must be the same bytes for the same report, so: every chunk gets row and chunk ids
numbered in logging order instead of time-based random ones; recording properties (a start
time) are not sent; no footer is written (its manifest is ordered by a hash map); and the two
store-info messages' random ids are set to fixed values after writing. Rerun reads the result
as it reads any footer-less `.rrd` (a whole-file scan).
"""

import json
import struct

import numpy as np
import pyarrow as pa
import rerun as rr
from rerun.chunk import Chunk


class _Ids:
    """Row and chunk ids in logging order."""

    def __init__(self):
        self.next = 1

    def take(self, n):
        first = self.next
        self.next += n
        return first

    def fix(self, chunk):
        batch = chunk.to_record_batch()
        first = self.take(batch.num_rows + 1)
        rows = pa.array([struct.pack(">QQ", 1, first + i) for i in range(batch.num_rows)], type=pa.binary(16))
        row_type = batch.column(0).type
        if isinstance(row_type, pa.ExtensionType):
            rows = pa.ExtensionArray.from_storage(row_type, rows)
        meta = dict(batch.schema.metadata)
        meta[b"rerun:id"] = ("chunk_" + struct.pack(">QQ", 1, first + batch.num_rows).hex().upper()).encode()
        fixed = pa.RecordBatch.from_arrays([rows] + batch.columns[1:], schema=batch.schema.with_metadata(meta))
        return Chunk.from_record_batch(fixed)


def _fix_store_info(path):
    """Sets the random ids of the store-info messages (kind 1) to fixed values, in place."""
    data = bytearray(open(path, "rb").read())
    if data[:4] != b"RRF2":
        raise ValueError(f"{path}: not an RRF2 file")
    pos = 12
    while pos + 16 <= len(data):
        kind, length = struct.unpack_from("<QQ", data, pos)
        body = pos + 16
        # SetStoreInfo: field 1 is the row id, a Tuid {fixed64 time_ns = 1; fixed64 inc = 2}.
        if kind == 1 and data[body : body + 3] == b"\x0a\x12\x09" and data[body + 11] == 0x11:
            data[body + 3 : body + 11] = struct.pack("<Q", 0)
            data[body + 12 : body + 20] = struct.pack("<Q", 1)
        pos = body + length
    if pos != len(data):
        raise ValueError(f"{path}: message framing ended at byte {pos} of {len(data)}")
    open(path, "wb").write(bytes(data))


def record(path, recording_id, scalars_json, frames, contrasts):
    """Writes `path`.

    scalars_json: {"entity/path": [[epoch, value], ...]}, training curves on the `epoch` timeline.
    frames: one dict per test frame on the `frame` timeline: "frame", "side", "heatmap" and
    "truth" (side*side bytes), "masks" ({name: bytes}), "actors" ([[col, row], ...] pixel
    centres), "true_grid" (text), "captions" ({name: text}).
    contrasts: per claim, its most different test frames on the `rank` timeline under
    `claims/<claim>/`: "claim", "rank", "frame", "side", "heatmap", "true_grid", "outputs"
    ({instance: text}), "masks" ({instance: bytes}) and, for segmenters, "truth_mask".
    """
    rec = rr.RecordingStream("rlmflow-report", recording_id=recording_id, send_properties=False)
    rec.save(path, write_footer=False)
    ids = _Ids()
    chunks = []
    for entity, points in sorted(json.loads(scalars_json).items()):
        epochs = [int(p[0]) for p in points]
        values = [float(p[1]) for p in points]
        chunks.append(Chunk.from_columns(entity, indexes=[rr.TimeColumn("epoch", sequence=epochs)], columns=rr.Scalars.columns(scalars=values)))

    def image(entity, frame, side, pixels, timeline="frame"):
        fmt = rr.components.ImageFormat(width=side, height=side, color_model="L", channel_datatype="U8")
        buffer = np.frombuffer(pixels, dtype=np.uint8)
        chunks.append(
            Chunk.from_columns(entity, indexes=[rr.TimeColumn(timeline, sequence=[frame])], columns=rr.Image.columns(buffer=[buffer], format=[fmt]))
        )

    def text(entity, frame, body, timeline="frame"):
        chunks.append(Chunk.from_columns(entity, indexes=[rr.TimeColumn(timeline, sequence=[frame])], columns=rr.TextDocument.columns(text=[body])))

    for f in frames:
        frame, side = int(f["frame"]), int(f["side"])
        image("radar/heatmap", frame, side, f["heatmap"])
        image("radar/truth", frame, side, f["truth"])
        for name, mask in sorted(f["masks"].items()):
            image(f"radar/predicted/{name}", frame, side, mask)
        if f["actors"]:
            chunks.append(
                Chunk.from_columns(
                    "radar/actors",
                    indexes=[rr.TimeColumn("frame", sequence=[frame])],
                    columns=rr.Points2D.columns(positions=np.array(f["actors"], dtype=np.float32)).partition([len(f["actors"])]),
                )
            )
        text("captions/true", frame, f["true_grid"])
        for name, caption in sorted(f["captions"].items()):
            text(f"captions/{name}", frame, caption)
    for c in contrasts:
        at, rank, side = f"claims/{c['claim']}", int(c["rank"]), int(c["side"])
        image(f"{at}/heatmap", rank, side, c["heatmap"], "rank")
        text(f"{at}/true_grid", rank, f"frame {int(c['frame'])}: {c['true_grid']}", "rank")
        if "truth_mask" in c:
            image(f"{at}/truth", rank, side, c["truth_mask"], "rank")
        for i, (name, output) in enumerate(sorted(c["outputs"].items())):
            text(f"{at}/output{i}", rank, f"{name}: {output}", "rank")
        for i, (name, mask) in enumerate(sorted(c["masks"].items())):
            image(f"{at}/predicted{i}", rank, side, mask, "rank")
    rec.send_chunks([ids.fix(c)[0] for c in chunks])
    rec.flush()
    del rec
    _fix_store_info(path)
    return len({c.entity_path for c in chunks})
