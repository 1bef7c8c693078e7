"""Reading rerun recordings back in tests: chunks by entity, and a scalar series per frame."""

from __future__ import annotations

from pathlib import Path

import pandas as pd


def read_chunks(path: str | Path) -> dict[str, list]:
    """The chunks of a ``.rrd`` file, grouped by entity path."""
    from rerun.chunk import RrdReader

    chunks: dict[str, list] = {}
    for chunk in RrdReader(str(path)).stream().collect().stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk)
    return chunks


def scalar_series(chunks: dict[str, list], entity: str) -> pd.Series:
    """The scalars logged on ``entity`` on the ``frame`` timeline, indexed and sorted by frame."""
    frames, values = [], []
    for chunk in chunks[entity]:
        rb = chunk.to_record_batch()
        if "frame" not in rb.schema.names:
            continue
        frames += rb.column("frame").to_pylist()
        values += [v[0] for v in rb.column("Scalars:scalars").to_pylist()]
    return pd.Series(values, index=frames, dtype=float).sort_index()
