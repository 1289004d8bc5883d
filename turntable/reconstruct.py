"""The main job: photos of an object on the turntable -> coloured mesh + recording.

Stages (each a module of :mod:`turntable.stages` over library functions in
``calib``/``recon``; this module is the list of them, in order):

1. frames      load the folder/video, check sizes, note unreadable files
2. cameras     sequence calibration (``cameras.json``) or ``--cameras``
3. silhouettes automatic (``recon.silhouettes``) or ``--masks``
4. hull        visual-hull carving (``recon.carving``)
5. fusion      per-view stereo depth and fused points (``recon.stereo``, ``recon.fusion``)
6. mesh        watertight mesh, decimation, vertex colours (``recon.meshing``, ``recon.colorize``)
7. export      model.glb/.ply/.obj, cameras.json, points.ply, recording.rrd, summary.json

OUT is a transaction (:mod:`turntable.outdir`): one run at a time; the new
files are built in ``OUT/.turntable/staging.<pid>`` and switched in only when
every one is written, so a failed, interrupted or killed run leaves the
previous outputs as they were. Finished stages are cached in ``OUT/.turntable``
and reused on a re-run unless ``overwrite``.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .cameras_io import atomic_write_text
from .errors import UserError
from .frames import Frame
from .outdir import DISK_FULL_ERRNOS, OutputFolder, write_error
from .progress import Progress
from .recording import RecordedModels, RecordedViews, record_reconstruction
from .stages import cameras, export, silhouettes
from .stages import frames as frames_stage
from .stages import hull as hull_stage
from .stages import summary as summary_stage
from .stages.cache import StageCache, file_digest, files_digest, stage_key
from .stages.options import MIN_VIEWS, ReconstructOptions
from .stages.silhouettes import GREY  # noqa: F401  (kept importable from here)
from .stages.summary import ReconstructSummary

log = logging.getLogger(__name__)

__all__ = ["ReconstructOptions", "ReconstructResult", "reconstruct"]


@dataclass
class ReconstructResult:
    out: Path
    files: dict[str, Path]
    frames_used: list[str]
    frames_skipped: dict[str, str]
    summary: ReconstructSummary | None = None  # also OUT/summary.json; None only before a run finishes
    exit_code: int = 0  # see EXIT_* below
    failed_checks: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)  # input images that could not be read

EXIT_OK = 0
EXIT_UNREADABLE = 1  # finished, but some input images could not be read (the rest were used)
EXIT_CHECK_FAILED = 3  # finished and wrote everything, but the model failed a check (summary: failed_checks)


def reconstruct(opts: ReconstructOptions, progress: Progress | None = None, recorder=None) -> ReconstructResult:
    """Run every stage; see the module docstring. Raises ``UserError`` on bad input.

    ``recorder`` (a :class:`turntable.recording.Recorder`) is written to
    ``OUT/recording.rrd`` with the other outputs. OUT changes only if the run
    finishes (exit code 0, 1 or 3); an error, Ctrl-C or SIGTERM leaves it as it
    was, and a full disk ends the run with a ``UserError`` naming the file.
    """
    progress = progress or Progress(enabled=False)
    out = Path(opts.out)
    t0 = time.perf_counter()
    with OutputFolder(out) as folder:
        for line in folder.cleaned:
            progress.note(f"out: {line}")
        try:
            res = _run(opts, progress, recorder, folder, t0)
            folder.publish()
        except OSError as exc:
            if exc.errno in DISK_FULL_ERRNOS or _under(exc.filename, out):
                raise write_error(exc, out, folder.staging) from None
            raise
    return res


def _under(filename, folder: Path) -> bool:
    try:
        return filename is not None and Path(os.fsdecode(filename)).resolve().is_relative_to(folder.resolve())
    except (OSError, ValueError, TypeError):
        return False


def _run(opts: ReconstructOptions, progress: Progress, recorder, folder: OutputFolder, t0: float) -> ReconstructResult:
    out, staging = folder.out, folder.staging
    cache = StageCache(out, enabled=not opts.overwrite, note=progress.note)
    if opts.overwrite:
        cache.clear()
    skipped: dict[str, str] = {}

    # every stage key starts from this one: the frames' bytes, the target, the options the calibration reads
    # (the angle marks are read on the work images) and the bytes of --intrinsics and --cameras
    cam_key = stage_key(frames_stage.input_key(opts), None if opts.spec is None else opts.spec.__dict__, opts.step_deg,
                        opts.work_size, file_digest(opts.intrinsics), file_digest(opts.cameras))
    seq, conics = cameras.known_cameras(opts, progress, cam_key, cache)
    loaded = frames_stage.load(opts, progress, seq)  # every frame decoded once; only the work size is kept
    ws = loaded.work
    frames = [Frame(n, im, "" if im is not None else why) for n, im, why in
              zip(loaded.names, loaded.images, loaded.failures, strict=True)]
    for f in frames:
        if f.bgr is None:
            skipped[f.name] = f.error
            progress.note(f"skipping {f.name}: {f.error}")
    good = [f for f in frames if f.bgr is not None]
    unreadable = [f.name for f in frames if f.bgr is None]
    if seq is None:
        seq, conics = cameras.calibrate(loaded, opts, progress, cam_key, cache)
    else:
        cameras.check_given(seq, good, opts, ws)
    exif = cameras.exif_focal(good, seq, opts, progress)
    by_name = {fp.image: fp for fp in seq.frames}
    used: list[Frame] = []
    for f in good:
        fp = by_name.get(f.name)
        if fp is None:
            skipped[f.name] = "no camera"
        elif not fp.ok:
            skipped[f.name] = fp.status
        else:
            used.append(f)
    if len(used) < 3:
        why = "; ".join(f"{k}: {v}" for k, v in list(skipped.items())[:4])
        raise UserError(f"{opts.input}: only {len(used)} frame(s) could be calibrated; need at least 3"
                        + (f" ({why})" if why else ""))
    names = [f.name for f in used]
    K = ws.K(seq.intrinsics.K)  # the work images' camera (cameras.json keeps the photos')
    Ts = np.stack([by_name[n].T_cam_table for n in names])
    images_rgb = [cv2.cvtColor(im, cv2.COLOR_BGR2RGB) for im in frames_stage.undistort([f.bgr for f in used], seq, ws)]
    del frames, good, used, loaded  # the work BGR copies go; images_rgb holds the pixels from here on

    masks_used = None if opts.masks_dir is None else files_digest(silhouettes.mask_files(opts.masks_dir, names))
    # "masks undistorted", "label masks": what given masks mean changed with these keys (older caches recompute)
    sil_key = stage_key(cam_key, masks_used, "masks undistorted", "label masks", names, K, seq.intrinsics.dist, Ts,
                        list(ws.work))
    carved = hull_stage.silhouettes_and_hull(images_rgb, names, K, Ts, opts, cache, sil_key, progress, ws,
                                             seq.intrinsics)
    keep, rejected, conservative, hull = carved.keep, carved.rejected, carved.conservative, carved.hull
    for n, why in rejected.items():
        skipped[n] = f"silhouette rejected: {why}"
        progress.note(f"silhouettes: frame {n} rejected: {why}")
    for n, why in conservative.items():
        progress.note(f"silhouettes: frame {n} kept with a conservative mask: {why}")
    if len(keep) < MIN_VIEWS:
        listed = "; ".join(f"{n}: {why}" for n, why in list(rejected.items())[:6])
        more = f"; and {len(rejected) - 6} more" if len(rejected) > 6 else ""
        raise UserError(f"{opts.input}: only {len(keep)} of {len(names)} silhouettes usable, need at least "
                        f"{MIN_VIEWS}; rejected: {listed}{more}")
    names = [names[i] for i in keep]
    images_rgb = [images_rgb[i] for i in keep]
    masks, Ts, unknown = carved.silhouettes.masks[keep], Ts[keep], carved.silhouettes.unknown[keep]

    def hull_note(note: str) -> None:  # on screen and in the summary's working-volume notes
        progress.note(f"hull: {note}")
        carved.report.setdefault("notes", []).append(note)

    from recon.shadows import GUARD_DEPTH_MM, SKIRT_MM, carve_cast_shadows

    if opts.masks_dir is None:  # automatic silhouettes: the cast shadow they held, where every view held some
        with progress.stage("cast shadows"):
            hull, skirt = carve_cast_shadows(hull, images_rgb, masks, unknown, K, Ts)
        if skirt is not None:
            hull_note(f"a cast shadow ({skirt.ratio:.2f} of the lit paper's grey, seen in {skirt.views} views) held "
                      f"in the silhouettes: the skirt it left within {SKIRT_MM:.0f} mm of the table carved "
                      f"({hull_stage.volume_text(skirt.volume_mm3)})")
    from recon.faces import carve_above_faces, same_top, sweep

    with progress.stage("flat tops"):  # the roof no silhouette carves over a plinth's or a box's top
        # the views' edges over horizontal planes. The openings read them where the views may show the object:
        # a round object's top seen against the room turns alike in every view, the room's plate holds it and
        # the silhouettes leave it unknown (a cup's rim, in 27 of 36 views of a dark room). The flat tops read
        # them in the sure silhouettes only: the doubt also holds what stands on a top (a white figure's leg,
        # unknown in some views), whose outline a few mm up falls inside the top, which is then not flat
        swept = sweep(images_rgb, masks | unknown, K, Ts, hull)
        hull, roofs = carve_above_faces(hull, images_rgb, masks, K, Ts,
                                        None if swept is None else swept.within(masks))
    tops: list[list] = []  # [face, mm3]: a top found again half a mm higher is noted once, with both volumes
    for face, mm3 in roofs:
        same = next((t for t in tops if same_top(face, t[0])), None)
        if same is None:
            tops.append([face, mm3])
        else:
            same[1] += mm3
    for face, mm3 in tops:
        hull_note(f"a flat top {face.height_mm:.1f} mm above the table ({face.area_mm2:.0f} mm²): the roof the "
                  f"silhouettes leave over it carved ({hull_stage.volume_text(mm3)})")
    if roofs:
        from recon.faces import carve_under_slabs, space_under

        tops_found = [face for face, _ in roofs]
        roofed = hull
        with progress.stage("under slabs"):  # the wedge the silhouettes leave under a seat, which no view sees
            hull, unders = carve_under_slabs(hull, tops_found, masks, K, Ts)
        for slab, mm3 in unders:
            hull_note(f"a slab under the flat top {slab.top.height_mm:.1f} mm above the table, its underside at "
                      f"{slab.underside_mm:.1f} mm: the space under it that no view sees, between what the views "
                      f"do see there, carved ({hull_stage.volume_text(mm3)})")
        if unders and opts.masks_dir is None:  # the skirt under the slab, seen now that the wedge over it is gone,
            # looked for up to the underside: the paper between the legs, held (doubt or mask), lit or in the seat's
            # shadow; the legs, standing on the table, stay what hides the paper (recon.faces.space_under)
            with progress.stage("cast shadows"):
                hull, skirt = carve_cast_shadows(hull, images_rgb, masks, unknown, K, Ts,
                                                 guard_depth_mm=GUARD_DEPTH_MM,
                                                 under=space_under([slab for slab, _ in unders], roofed))
            if skirt is not None:
                hull_note(f"under the slab, the cast shadow's skirt carved up to the underside, where the views "
                          f"see the paper between the legs ({hull_stage.volume_text(skirt.volume_mm3)})")
                with progress.stage("under slabs"):  # the wedge again: what hung under it is gone
                    hull, again = carve_under_slabs(hull, tops_found, masks, K, Ts)
                for slab, mm3 in again:
                    hull_note(f"under the slab at {slab.underside_mm:.1f} mm, the rest of the space no view sees, "
                              f"above the skirt carved, carved ({hull_stage.volume_text(mm3)})")

    from recon.sides import flatten_sides

    with progress.stage("flat sides"):  # the tent the silhouettes leave over a box's plain sides
        hull, sides = flatten_sides(hull, images_rgb, masks, K, Ts)
    if sides:
        lo, hi = min(s.lo_mm for s in sides), max(s.hi_mm for s in sides)
        hull_note(f"flat sides between corners from {lo:.1f} to {hi:.1f} mm above the table: the tent the "
                  f"silhouettes leave over them carved ({hull_stage.volume_text(sum(s.volume_mm3 for s in sides))})")

    from recon.meshing import clip_to_hull, mesh_from_hull

    with progress.stage("hull mesh"):  # smoothing moves vertices up to ~0.3 mm out: back inside the hull
        hull_mesh = clip_to_hull(mesh_from_hull(hull, max_faces=opts.max_faces), hull)
    mesh, fused, fusion_note = hull_mesh, None, "disabled (--no-fusion)"
    if opts.fusion:
        from .stages.fusion import run_fusion

        mesh, fused, fusion_note = run_fusion(images_rgb, masks, K, Ts, hull, hull_mesh, opts, progress, swept)

    from recon.colorize import color_vertices

    with progress.stage("colour"):
        mesh = color_vertices(mesh, images_rgb, K, Ts, masks=masks)
    textured = None
    if opts.texture:  # the UV atlas and photo texture (and --lods), cached: stages/texture.py
        from .stages.texture import texture_key, textured_model

        textured = textured_model(mesh, images_rgb, K, Ts, masks, opts, cache,
                                  texture_key(sil_key, names, mesh, opts), progress)

    from recon.meshing import mesh_stats

    stats = mesh_stats(mesh)
    failed = summary_stage.failed_checks(stats, carved.report)
    files = export.write_outputs(staging, opts, seq, names, mesh, fused, progress, textured=textured)
    if recorder is not None:
        with progress.stage("recording"):
            record_reconstruction(recorder, opts.spec, seq,
                                  RecordedViews(names, images_rgb, masks, K, Ts, conics, ws),
                                  RecordedModels(hull_mesh, fused, mesh, textured))
            files["recording"] = recorder.save(staging / "recording.rrd")
    files = {k: out / p.relative_to(staging) for k, p in files.items()}  # where they will be once published
    files["summary"] = out / "summary.json"
    times = {**progress.times_s, "total": time.perf_counter() - t0}
    summary = summary_stage.summarise(out=out, seq=seq, names=names, skipped=skipped, mesh=mesh, stats=stats,
                                      fusion_note=fusion_note, carved=carved, failed=failed, exif=exif,
                                      work_size=ws.report(), times_s=times, files=files, textured=textured)
    atomic_write_text(staging / "summary.json", json.dumps(summary.to_json(), indent=1) + "\n")
    exit_code = EXIT_CHECK_FAILED if failed else EXIT_UNREADABLE if unreadable else EXIT_OK
    return ReconstructResult(out=out, files=files, frames_used=names, frames_skipped=skipped,
                             summary=summary, exit_code=exit_code, failed_checks=failed,
                             unreadable=unreadable)
