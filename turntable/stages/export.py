"""Stage 7, export: the model files, ``summary.json`` and the recording, written into the staging folder."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..cameras_io import write_cameras
from .frames import frame_files


def failed_checks(stats, vol_report: dict) -> list[str]:
    """What is wrong with the finished model, one line each (empty: it passed)."""
    failed = []
    if not stats.watertight:
        failed.append("the mesh is not watertight")
    if stats.n_bodies != 1:
        failed.append(f"the mesh is {stats.n_bodies} separate pieces, not one")
    failed += vol_report["clipped"]
    return failed


def write_outputs(staging: Path, opts, seq, names, mesh, fused, progress) -> dict[str, Path]:
    """Write the model, cameras and exports into ``staging`` (the folder that becomes OUT's new set)."""
    from recon.export import export_mesh

    out = staging
    with progress.stage("export"):
        files = dict(export_mesh(mesh, out))
        write_cameras(out / "cameras.json", seq)
        files["cameras"] = out / "cameras.json"
        if fused is not None and len(fused.pts_table):
            from ..pointsio import write_points_ply

            write_points_ply(out / "points.ply", fused)
            files["points"] = out / "points.ply"
        T_by_name = {fp.image: fp.T_cam_table for fp in seq.frames}
        intr = seq.intrinsics  # the original photos: their distortion, not the undistorted copies'
        if opts.export_colmap:
            from recon.export import export_colmap

            col = [(n, T_by_name[n]) for n in names]
            files["colmap"] = out / "colmap"
            export_colmap(intr.K, intr.width, intr.height, col, files["colmap"], dist=intr.dist,
                          points_table=None if fused is None else fused.pts_table,
                          colors_rgb=None if fused is None else fused.colors_rgb)
        if opts.export_nerfstudio:
            from recon.export import export_nerfstudio

            from ..frames import frame_name

            # file paths relative to OUT (where transforms.json is published), pointing at the user's photos
            rel = [(frame_name(os.path.relpath(p, opts.out)), T_by_name[n])
                   for n, p in zip(names, frame_files(opts, names), strict=True)]
            files["nerfstudio"] = export_nerfstudio(intr.K, intr.width, intr.height, rel, out, dist=intr.dist,
                                                    ply_file_path="model.ply")
    return files


def summary(seq, names, skipped, mesh, progress, fusion_note, files) -> dict:
    import trimesh

    from ..frames import frame_name

    tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    meta = seq.meta
    std_f = meta.get("focal_std_px")

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
        "warnings": list(meta.get("warnings", [])),
        "time_s": {k: round(v, 2) for k, v in progress.times_s.items()},
        "files": {k: frame_name(str(v)) for k, v in files.items()},  # strict JSON whatever the path
    }


def record(rec, opts, seq, names, images_rgb, masks, K, Ts, hull_mesh, fused, mesh, conics, ws) -> None:
    """The recording shows the work images with their camera ``K`` and the rings mapped onto them."""
    if opts.spec is not None:
        rec.log_target(opts.spec.r_outer_mm, opts.spec.r_inner_mm)
    W, H = ws.work
    for i, n in enumerate(names):
        rec.log_camera(i, K, W, H, Ts[i], image_rgb=images_rgb[i])
        if n in conics:
            rec.log_conics(i, {k: ws.conic(C) for k, C in conics[n].items()})
        rec.log_silhouette(i, masks[i])
    rec.log_mesh("hull", hull_mesh.vertices_table, hull_mesh.faces, hull_mesh.normals_table)
    if fused is not None and len(fused.pts_table):
        rec.log_points("points", fused.pts_table, fused.colors_rgb)
    rec.log_mesh("mesh", mesh.vertices_table, mesh.faces, mesh.normals_table, mesh.colors_rgb)
