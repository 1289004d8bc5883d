"""Stage 7, export: the model files, ``cameras.json`` and the exports for other tools, written into the staging folder.

The COLMAP and nerfstudio exports name the photos they describe, so the photos
used travel with them: they are placed in ``OUT/images/`` and every exported
path points there (COLMAP's image names are relative to ``OUT/images``,
nerfstudio's ``file_path`` to OUT), so OUT can be moved or copied as one
folder. A photo is **hard-linked** when OUT is on its filesystem (no extra
space; the link and the photo are one file), **copied** otherwise or with
``--copy-images``, and **written as PNG** (the decoded, upright 8-bit RGB
pixels that were calibrated) when the file is not a plain 8-bit RGB JPEG/PNG
without an EXIF rotation: other tools do not apply EXIF orientation
(nerfstudio's ``Image.open``, COLMAP's reader) or read HEIC, so the file
itself would not match the camera. Video frames are written as PNG, named as
in ``cameras.json``. When the input folder already is ``OUT/images`` (and not
one of this tool's outputs), the photos are used where they are.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cameras_io import write_cameras
from ..outdir import DISK_FULL_ERRNOS, OutputFolder
from .frames import frame_files

#: Points sampled on the mesh for COLMAP's tracks when there are no fused points (``--no-fusion``).
SURFACE_SAMPLES = 20_000
#: Fewer fused points than this seen by two views: the mesh is sampled instead.
MIN_TRACK_POINTS = 1_000
#: How far from the final mesh a fused point may lie and still be a COLMAP point (mm).
SURFACE_TOL_MM = 1.0
_IMAGE_DIRS = ("images", "turntable_images")


@dataclass(frozen=True)
class PlacedImages:
    """Where the exports find the photos: ``folder`` (relative to OUT), each frame's file name in it."""

    folder: str
    file_names: dict[str, str]  # frame name -> file name in ``folder``
    counts: dict[str, int]  # "hard-linked" / "copied" / "written as PNG" / "in place" -> how many
    staged: bool  # the folder is part of this run's outputs (False: the user's own, used in place)

    def describe(self) -> str:
        how = ", ".join(f"{n} {what}" for what, n in self.counts.items() if n)
        return f"photos for the exports in OUT/{self.folder}: {how}"


def write_outputs(staging: Path, opts, seq, names, mesh, fused, progress, textured=None) -> dict[str, Path]:
    """Write the model, cameras and exports into ``staging`` (the folder that becomes OUT's new set).

    ``textured`` (a :class:`recon.texture.TexturedMesh` of ``mesh``): the GLB and OBJ carry its texture
    (``model.mtl``, ``model_albedo.png``); the PLY keeps ``mesh``'s vertex colours."""
    from recon.export import export_mesh

    out = staging
    with progress.stage("export"):
        files = dict(export_mesh(mesh, out, textured=textured))
        from recon.export import export_usdz, usd_available

        if textured is not None and usd_available():  # the optional extra turntable[usd]
            files["usdz"] = export_usdz(textured, out / "model.usdz")
        write_cameras(out / "cameras.json", seq)
        files["cameras"] = out / "cameras.json"
        if fused is not None and len(fused.pts_table):
            from ..pointsio import write_points_ply

            write_points_ply(out / "points.ply", fused)
            files["points"] = out / "points.ply"
        if not (opts.export_colmap or opts.export_nerfstudio):
            return files
        placed = place_images(opts, names, staging)
        progress.note(placed.describe())
        if placed.staged:  # (the user's own OUT/images, used in place, is not this run's output)
            files["images"] = staging / placed.folder
        T_by_name = {fp.image: fp.T_cam_table for fp in seq.frames}
        intr = seq.intrinsics  # the original photos: their distortion, not the undistorted copies'
        if opts.export_colmap:
            from recon.export import export_colmap

            tracks = colmap_tracks(mesh, fused, intr, np.stack([T_by_name[n] for n in names]))
            col = [(placed.file_names[n], T_by_name[n]) for n in names]
            files["colmap"] = out / "colmap"
            export_colmap(intr.K, intr.width, intr.height, col, files["colmap"], dist=intr.dist, tracks=tracks)
            progress.note(f"colmap: {len(tracks.points_table)} points, {int(tracks.visible.sum())} observations "
                          f"(mean track length {tracks.visible.sum(1).mean() if len(tracks.visible) else 0:.1f})")
        if opts.export_nerfstudio:
            from recon.export import export_nerfstudio

            rel = [(f"{placed.folder}/{placed.file_names[n]}", T_by_name[n]) for n in names]
            files["nerfstudio"] = export_nerfstudio(intr.K, intr.width, intr.height, rel, out, dist=intr.dist,
                                                    ply_file_path="model.ply")
    return files


def colmap_tracks(mesh, fused, intr, Ts: np.ndarray):
    """COLMAP's 3D points with their observations: the fused points on the final mesh (at most
    ``MAX_TRACK_POINTS``), or points sampled on it without fusion (or too few fused points seen)."""
    from recon.export import MAX_TRACK_POINTS, sample_surface, surface_tracks

    def tracks_of(pts, cols):
        return surface_tracks(mesh.vertices_table, mesh.faces, pts, cols, intr.K, intr.dist,
                              (intr.width, intr.height), Ts, surface_tol_mm=SURFACE_TOL_MM)

    if fused is not None and len(fused.pts_table):
        pts, cols = np.asarray(fused.pts_table), np.asarray(fused.colors_rgb)
        if len(pts) > MAX_TRACK_POINTS:  # a deterministic, even subsample
            pick = np.sort(np.random.default_rng(0).choice(len(pts), MAX_TRACK_POINTS, replace=False))
            pts, cols = pts[pick], cols[pick]
        tracks = tracks_of(pts, cols)
        if len(tracks.points_table) >= MIN_TRACK_POINTS:
            return tracks
    return tracks_of(*sample_surface(mesh, SURFACE_SAMPLES))


# --------------------------------------------------------------------------- the photos under OUT


def place_images(opts, names: list[str], staging: Path) -> PlacedImages:
    """Put the frames ``names`` under ``staging/images`` (see the module docstring); where they went."""
    from ..frames import VIDEO_SUFFIXES

    inp = Path(opts.input)
    published = OutputFolder(opts.out).published_names()
    if inp.is_file() and inp.suffix.lower() in VIDEO_SUFFIXES:
        return _write_video_frames(opts, names, staging / _image_dir(opts.out, published))
    srcs = frame_files(opts, names)
    plain = [_plain_rgb(p) for p in srcs]
    own = Path(opts.out) / "images"
    if all(plain) and "images" not in published and own.is_dir() and inp.resolve() == own.resolve():
        return PlacedImages("images", {n: p.name for n, p in zip(names, srcs, strict=True)},
                            {"in place": len(names)}, staged=False)
    folder = _image_dir(opts.out, published)
    dst_dir = staging / folder
    dst_dir.mkdir()
    counts = {"hard-linked": 0, "copied": 0, "written as PNG": 0}
    file_names = _file_names(names, [not ok for ok in plain])
    for n, src, ok in zip(names, srcs, plain, strict=True):
        dst = dst_dir / file_names[n]
        if ok:
            counts[_link_or_copy(src, dst, opts.copy_images)] += 1
        else:
            from ..images import read_image

            _write_png(dst, read_image(src))
            counts["written as PNG"] += 1
    return PlacedImages(folder, file_names, counts, staged=True)


def _image_dir(out, published: set[str]) -> str:
    """``images``, unless OUT already holds an ``images`` of the user's (then ``turntable_images``)."""
    for name in _IMAGE_DIRS:
        if name in published or not (Path(out) / name).exists():
            return name
    from ..errors import UserError

    raise UserError(f"{out}: 'images' and 'turntable_images' are the user's folders, not outputs of turntable; "
                    f"the exports place the photos they name in one of them: choose another --out")


def _plain_rgb(path: Path) -> bool:
    """A file other tools read as we do: 8-bit RGB JPEG or PNG, no EXIF rotation (nor mirror)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.format in ("JPEG", "PNG") and im.mode == "RGB" and im.getexif().get(0x0112, 1) == 1
    except Exception:  # not something Pillow reads (HEIC without the plugin): decode it ourselves
        return False


def _file_names(names: list[str], as_png: list[bool]) -> dict[str, str]:
    """File names for the exports: no whitespace (COLMAP's text format), ``.png`` for re-encoded photos, unique."""
    out: dict[str, str] = {}
    taken: set[str] = set()
    for n, png in zip(names, as_png, strict=True):
        f = re.sub(r"\s", "_", n)
        if png and not f.lower().endswith(".png"):
            f += ".png"
        stem, dot, ext = f.rpartition(".")
        k = 1
        while f.lower() in taken:
            f = f"{stem}_{k}{dot}{ext}" if dot else f"{ext}_{k}"
            k += 1
        taken.add(f.lower())
        out[n] = f
    return out


def _link_or_copy(src: Path, dst: Path, copy: bool) -> str:
    if not copy:
        try:
            os.link(src, dst)
            return "hard-linked"
        except OSError as exc:  # another filesystem, no hard links there, not permitted: copy
            if exc.errno in DISK_FULL_ERRNOS:
                raise
    shutil.copyfile(src, dst)
    return "copied"


def _write_png(dst: Path, bgr: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(errno.EIO, "could not encode PNG", str(dst))
    with open(dst, "wb") as f:
        f.write(buf.tobytes())


def _write_video_frames(opts, names: list[str], dst_dir: Path) -> PlacedImages:
    """The video frames used, decoded again (upright, full size) and written as PNG under their frame names."""
    from ..frames import iter_frames

    wanted = set(names)
    file_names = _file_names(names, [True] * len(names))
    dst_dir.mkdir()
    done = 0
    for f in iter_frames(opts.input, opts.every, opts.frames):
        if f.name in wanted and f.bgr is not None:
            _write_png(dst_dir / file_names[f.name], f.bgr)
            done += 1
    if done != len(wanted):
        from ..errors import UserError

        raise UserError(f"{opts.input}: only {done} of the {len(wanted)} frames used could be decoded again for "
                        f"the exports")
    return PlacedImages(dst_dir.name, file_names, {"video frames written as PNG": done}, staged=True)
