"""Stage 7, export: the model files, ``summary.json`` and the recording, written into the staging folder."""

from __future__ import annotations

import os
from pathlib import Path

from ..cameras_io import write_cameras
from .frames import frame_files


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
