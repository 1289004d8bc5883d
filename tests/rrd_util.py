"""Reading a .rrd back for tests: which components were logged where, how often, and the default blueprint."""

from __future__ import annotations

from collections import defaultdict

import numpy as np


def _chunks(path, store: str = "recording"):
    """The chunks of the file's first ``store`` ("recording" or "blueprint")."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    entries = reader.recordings() if store == "recording" else reader.blueprints()
    if not entries:
        raise AssertionError(f"{path}: no {store} store")
    return reader.stream(store=entries[0]).to_chunks()


def rrd_rows(path, store: str = "recording") -> dict[str, dict[str, int]]:
    """{entity_path: {component column: number of rows}} over all chunks."""
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for ch in _chunks(path, store):
        rb = ch.to_record_batch()
        for name in rb.schema.names:
            if ":" in name:
                col = rb.column(name)
                counts[ch.entity_path][name] += rb.num_rows - col.null_count
    return {k: dict(v) for k, v in counts.items()}


def rrd_column(path, entity: str, column: str, store: str = "recording") -> list:
    """All non-null values of one component column of one entity, as Python lists."""
    out = []
    for ch in _chunks(path, store):
        if ch.entity_path != entity:
            continue
        rb = ch.to_record_batch()
        if column in rb.schema.names:
            out.extend(v for v in rb.column(column).to_pylist() if v is not None)
    return out


def static_entities(path, column: str | None = None) -> set[str]:
    """Entities that have static data (no timeline), of ``column`` if given."""
    return {ch.entity_path for ch in _chunks(path)
            if ch.is_static and (column is None or column in ch.to_record_batch().schema.names)}


def blueprint_values(path) -> dict[str, dict[str, list]]:
    """{blueprint entity path: {component column: its non-null values}}: views, containers, overrides."""
    out: dict[str, dict[str, list]] = defaultdict(dict)
    for ch in _chunks(path, "blueprint"):
        rb = ch.to_record_batch()
        for name in rb.schema.names:
            if ":" in name:
                out[ch.entity_path].setdefault(name, []).extend(
                    v for v in rb.column(name).to_pylist() if v is not None)
    return dict(out)


def blueprint_views(path) -> dict[str, dict]:
    """The views of the default blueprint by their path: class ("3D", "2D", "TimeSeries"), name, origin."""
    def last(cols, name):  # each row holds a list of one value
        rows = cols.get(name) or [[None]]
        return rows[-1][0]

    views = {}
    for entity, cols in blueprint_values(path).items():
        if "ViewBlueprint:class_identifier" in cols:
            views[entity] = {"class": last(cols, "ViewBlueprint:class_identifier"),
                             "name": last(cols, "ViewBlueprint:display_name"),
                             "origin": last(cols, "ViewBlueprint:space_origin")}
    return views


def pinhole_K(value) -> np.ndarray:
    """Rerun stores Pinhole matrices column-major (LIBRARIES.md)."""
    flat = np.asarray(value, float).ravel()
    return flat.reshape(3, 3).T
