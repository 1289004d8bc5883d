"""Reading a .rrd back for tests: which components were logged where, how often."""

from __future__ import annotations

from collections import defaultdict

import numpy as np


def rrd_rows(path) -> dict[str, dict[str, int]]:
    """{entity_path: {component column: number of rows}} over all chunks."""
    from rerun.chunk import RrdReader

    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for ch in RrdReader(str(path)).stream().to_chunks():
        rb = ch.to_record_batch()
        for name in rb.schema.names:
            if ":" in name:
                col = rb.column(name)
                counts[ch.entity_path][name] += rb.num_rows - col.null_count
    return {k: dict(v) for k, v in counts.items()}


def rrd_column(path, entity: str, column: str) -> list:
    """All non-null values of one component column of one entity, as Python lists."""
    from rerun.chunk import RrdReader

    out = []
    for ch in RrdReader(str(path)).stream().to_chunks():
        if ch.entity_path != entity:
            continue
        rb = ch.to_record_batch()
        if column in rb.schema.names:
            out.extend(v for v in rb.column(column).to_pylist() if v is not None)
    return out


def pinhole_K(value) -> np.ndarray:
    """Rerun stores Pinhole matrices column-major (LIBRARIES.md)."""
    flat = np.asarray(value, float).ravel()
    return flat.reshape(3, 3).T
