"""The run's verdict and ``summary.json``: what failed and what was made, as the screen shows it."""

from __future__ import annotations

import math

import numpy as np


def failed_checks(stats, vol_report: dict) -> list[str]:
    """What is wrong with the finished model, one line each (empty: it passed)."""
    failed = []
    if not stats.watertight:
        failed.append("the mesh is not watertight")
    if stats.n_bodies != 1:
        failed.append(f"the mesh is {stats.n_bodies} separate pieces, not one")
    failed += vol_report["clipped"]
    return failed



def summary(seq, names, skipped, mesh, progress, fusion_note, files) -> dict:
    import trimesh

    from ..frames import frame_name

    tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    diagnostics = seq.diagnostics
    std_f = diagnostics.focal_std_px if diagnostics is not None else None

    def num(x):
        return None if x is None or (isinstance(x, float) and math.isnan(x)) else x

    rms = [fp.rms_px for fp in seq.frames if fp.ok and not math.isnan(fp.rms_px)]
    return {
        "frames_used": len(names),
        "frames_skipped": skipped,
        "focal_px": seq.intrinsics.focal_px,
        "focal_std_px": num(std_f),
        "principal_point_px": seq.intrinsics.principal_point_px.tolist(),
        "mode": seq.mode,
        "rms_px": float(np.sqrt(np.mean(np.square(rms)))) if rms else None,
        "mesh": {"vertices": int(len(tm.vertices)), "faces": int(len(tm.faces)),
                 "watertight": bool(tm.is_watertight), "volume_cm3": float(tm.volume) / 1000.0,
                 "extent_mm": (tm.bounds[1] - tm.bounds[0]).tolist()},
        "fusion": fusion_note,
        "warnings": list(diagnostics.warnings) if diagnostics is not None else [],
        "time_s": {k: round(v, 2) for k, v in progress.times_s.items()},
        "files": {k: frame_name(str(v)) for k, v in files.items()},  # strict JSON whatever the path
    }
