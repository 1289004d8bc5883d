"""The main job: photos of an object on the turntable -> coloured mesh + recording.

Stages (each a library function in ``calib``/``recon``; this module only wires
them, writes their artifacts and reports):

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
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from calib.target import TargetSpec
from calib.types import SequenceCalibration

from .cameras_io import atomic_write_text, read_cameras, write_cameras
from .errors import UserError
from .frames import Frame, iter_frames
from .outdir import DISK_FULL_ERRNOS, OutputFolder, write_error
from .progress import Progress
from .stagecache import StageCache, file_digest, files_digest, stage_key
from .worksize import WorkSize, choose_work_size

log = logging.getLogger(__name__)

__all__ = ["ReconstructOptions", "ReconstructResult", "reconstruct"]


@dataclass(frozen=True)
class ReconstructOptions:
    input: Path
    out: Path
    spec: TargetSpec | None  # None only with ``cameras``: no ring target in the photos
    step_deg: float | None = None
    masks_dir: Path | None = None
    cameras: Path | None = None
    intrinsics: Path | None = None
    resolution: int = 256
    max_faces: int = 100_000
    every: int = 1
    frames: int | None = None  # use this many frames spread evenly over the input (instead of ``every``)
    fusion: bool = True
    overwrite: bool = False
    spawn: bool = False
    export_colmap: bool = False
    export_nerfstudio: bool = False
    max_rejections: int | None = None  # None: 0 with masks_dir (trusted), 1 with automatic silhouettes
    work_size: int | None = None  # long side of the work images, pixels; 0: full size; None: the default policy


@dataclass
class ReconstructResult:
    out: Path
    files: dict[str, Path]
    frames_used: list[str]
    frames_skipped: dict[str, str]
    summary: dict = field(default_factory=dict)
    exit_code: int = 0  # see EXIT_* below
    failed_checks: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)  # input images that could not be read


EXIT_OK = 0
EXIT_UNREADABLE = 1  # finished, but some input images could not be read (the rest were used)
EXIT_CHECK_FAILED = 3  # finished and wrote everything, but the model failed a check (summary: failed_checks)
MIN_VIEWS = 3


# --------------------------------------------------------------------------- helpers
def _clear_cache(cache: StageCache) -> None:
    """``--overwrite``: forget every finished stage (the lock and the published set's record stay)."""
    for p in list(cache.dir.glob("*.npz")) + [cache.dir / "cameras.json"]:
        p.unlink(missing_ok=True)


def _read_masks(masks_dir: Path, names: list[str], ws: WorkSize,
                progress: Progress | None = None) -> tuple[np.ndarray, dict[str, str]]:
    """Masks matched to frames by file stem, as large as the photos; any image format; > 127 = object.

    A mask holding only 0 and one value up to 127 (a label image: 0/1, 0/100)
    takes that value as the object, with a note. Returned at the work size
    (V, h, w) bool: each mask is reduced (area average, then > 0.5) as it is
    read; and for each mask with no object pixel, why (its brightest value).
    """
    from .images import read_image
    from .mask_checks import check_masks

    if not masks_dir.is_dir():
        raise UserError(f"--masks {masks_dir}: not a folder")
    (W, H), (w, h) = ws.full, ws.work
    out = np.zeros((len(names), h, w), bool)
    empty: dict[str, str] = {}
    labels: list[str] = []
    for i, (n, p) in enumerate(zip(names, _mask_files(masks_dir, names))):
        if p is None:
            raise UserError(f"--masks {masks_dir}: no mask for frame {n} (expected {Path(n).stem}.png)")
        m = read_image(p)
        if m.shape[:2] != (H, W):
            raise UserError(f"{p}: mask is {m.shape[1]}x{m.shape[0]}, frame {n} is {W}x{H}")
        g = m.max(axis=2)
        top = int(g.max())
        if 0 < top <= 127 and not np.any((g != 0) & (g != top)):  # two values, 0 and a low one: a label image
            labels.append(n)
            threshold = 0
        else:
            threshold = 127
        out[i] = ws.reduce(np.where(g > threshold, np.uint8(255), np.uint8(0))) > 127
        if not out[i].any():
            empty[n] = (f"{p.name} has no pixel above 127, the brightest is {top}" if top <= threshold else
                        f"{p.name}: the object pixels vanish at the work size")
    if labels and progress is not None:
        progress.note(f"masks: {len(labels)} mask(s) hold only 0 and one value up to 127 (label images, "
                      f"e.g. {labels[0]}): that value is taken as the object")
    check_masks(out, names, masks_dir)  # inverted, all-white, mostly empty: refused before any work
    return out, empty


def _mask_files(masks_dir: Path, names: list[str]) -> list[Path | None]:
    """The mask file of each frame, matched by file stem (None: no mask; no folder: all None)."""
    from .frames import frame_name
    from .images import IMAGE_SUFFIXES

    try:
        by_stem = {frame_name(p.stem): p for p in sorted(masks_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    except OSError:
        by_stem = {}
    return [by_stem.get(Path(n).stem) for n in names]


def _undistort(images: list[np.ndarray], seq: SequenceCalibration, ws: WorkSize) -> list[np.ndarray]:
    """Work images without lens distortion (same camera matrix ``ws.K(K)``; the coefficients are scale-free)."""
    return _undistort_with(images, seq.intrinsics, ws)


def _undistort_masks(masks: np.ndarray, intr, ws: WorkSize) -> np.ndarray:
    """``--masks`` (V, h, w) bool drawn on the photos, undistorted like the work images (the hull is carved
    with the undistorted camera): coverage resampled bilinearly, > 1/2 is object."""
    if intr is None or not intr.has_distortion:
        return masks
    m8 = _undistort_with([m.astype(np.uint8) * 255 for m in masks], intr, ws)
    return np.stack([m > 127 for m in m8]) if len(m8) else masks


def _undistort_with(images: list[np.ndarray], intr, ws: WorkSize) -> list[np.ndarray]:
    if not intr.has_distortion:
        return images
    K = ws.K(intr.K)
    m1, m2 = cv2.initUndistortRectifyMap(K, intr.dist, None, K, tuple(ws.work), cv2.CV_32FC1)
    return [cv2.remap(im, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for im in images]


def _frame_paths(opts: ReconstructOptions, names: list[str]) -> list[Path]:
    """Where each frame lives on disk (video frames: the video itself)."""
    from .frames import frame_paths

    p = Path(opts.input)
    if not p.is_dir():
        return [p] * len(names)
    files = frame_paths(p)
    return [files.get(n, p / n) for n in names]


# --------------------------------------------------------------------------- stages
def _known_cameras(opts: ReconstructOptions, progress: Progress, key: str,
                   cache: StageCache) -> tuple[SequenceCalibration | None, dict]:
    """Cameras that need no ring detection: ``--cameras``, or the cached calibration of an earlier run."""
    cam_path = cache.dir / "cameras.json"
    if opts.cameras is not None:
        seq = read_cameras(opts.cameras)
        # cameras.json may name frames with a folder ("images/frame_000.jpg"): match by file name
        seq = replace(seq, frames=tuple(replace(fp, image=Path(fp.image).name) for fp in seq.frames))
        return seq, {}
    if cam_path.is_file() and not opts.overwrite:
        # cameras.json is this stage's result only with the detections saved beside it, which name its bytes
        hit = cache.load("detections", key, _DETECTIONS)
        if hit is None or str(hit["cameras_json"]) != file_digest(cam_path):
            return None, {}
        try:
            seq = read_cameras(cam_path)
        except UserError:
            return None, {}
        if seq.meta.get("stage_key") == key:
            progress.note("cameras: reusing cameras.json")
            return seq, _conics_from_arrays(hit)
    return None, {}


_DETECTIONS = {"names": ("U", ("N",)), "conics": ("f", ("N", 2, 3, 3)), "cameras_json": ("U", ())}


def _ring_px_from_camera(seq: SequenceCalibration, name: str, spec: TargetSpec | None) -> float | None:
    """Long axis (pixels) of the outer ring's image in frame ``name`` of known cameras (None: unknown)."""
    fp = next((fp for fp in seq.frames if fp.image == name and fp.ok), None)
    if fp is None or spec is None:
        return None
    th = np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False)
    r = spec.r_outer_mm
    pts = np.column_stack([r * np.cos(th), np.zeros_like(th), r * np.sin(th), np.ones_like(th)])
    pc = (fp.T_cam_table @ pts.T)[:3]
    if np.any(pc[2] <= 0):
        return None
    uv = (seq.intrinsics.K @ pc)[:2] / pc[2]
    return float(np.max(np.linalg.norm(uv[:, :180] - uv[:, 180:], axis=0)))


def _load(opts: ReconstructOptions, progress: Progress, seq: SequenceCalibration | None):
    """Decode every frame once: the rings at full resolution (when ``seq`` is None), the pixels at the work size.

    The work size is chosen on the first readable frame, from its size and the
    outer ring's size in it (:func:`turntable.worksize.choose_work_size`; the
    pixel count alone where its rings are not found).
    Returns :class:`turntable.sequence_stage.DetectedFrames`.
    """
    from .sequence_stage import detect_and_reduce

    intr = None
    if seq is None and opts.intrinsics is not None:
        from .intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(opts.intrinsics)

    def choose(size, ring_px, name):
        if ring_px is None and seq is not None:
            ring_px = _ring_px_from_camera(seq, name, opts.spec)
        ws = choose_work_size(size, ring_px, opts.work_size)
        progress.note(f"work size: {ws.describe()}")
        return ws

    frames = ((f.name, f.bgr, f.error) for f in iter_frames(opts.input, opts.every, opts.frames))
    with progress.stage("frames" if seq is not None else "frames and rings") as tick:
        return detect_and_reduce(frames, opts.spec if seq is None else None, choose,
                                 principal_point_px=None if intr is None else intr.principal_point_px,
                                 expected_size=None if intr is None else (intr.width, intr.height),
                                 progress=tick, total=_count_inputs(opts))


def _count_inputs(opts: ReconstructOptions) -> int:
    """How many frames will be read (a folder: known; a video: 0, unknown until read)."""
    from .frames import select_indices
    from .images import list_images

    p = Path(opts.input)
    if not p.is_dir():
        return 0
    return len(select_indices(len(list_images(p)), opts.every, opts.frames))


def _input_key(opts: ReconstructOptions) -> str:
    """What the inputs are: the selected files' names and the hashes of their bytes (a video: the whole file)."""
    from .frames import select_indices
    from .images import list_images

    p = Path(opts.input)
    try:
        if p.is_dir():
            listed = list_images(p)
            files = [listed[i] for i in select_indices(len(listed), opts.every, opts.frames)]
        else:
            files = [p]
    except (UserError, OSError):
        files = []  # iter_frames will say what is wrong with the input
    return stage_key(str(p.resolve()) if not p.is_dir() else "", files_digest(files), opts.every, opts.frames)


def _stage_cameras(loaded, opts: ReconstructOptions, progress: Progress, key: str,
                   cache: StageCache) -> tuple[SequenceCalibration, dict]:
    """The sequence calibration from the rings found at full resolution, and the ring conics per frame name."""
    from .sequence_stage import calibrate_detected

    intr = None
    if opts.intrinsics is not None:
        from .intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(opts.intrinsics)
    observations = loaded.observations
    with progress.stage("cameras") as tick:
        try:  # the angle marks are read on the work images (they are sampled in millimetres)
            seq = calibrate_detected(observations, loaded.failures, loaded.names, loaded.images, opts.spec,
                                     marks_map=loaded.work.S, step_deg=opts.step_deg, intrinsics=intr,
                                     progress=tick)
        except UserError as exc:
            raise UserError(f"{opts.input}: {exc}") from None
    seq = replace(seq, meta={**seq.meta, "stage_key": key})
    names = [n for n, o in zip(loaded.names, observations) if o is not None]
    conics = np.array([[o.conics["outer"], o.conics["inner"]] for o in observations if o is not None]).reshape(-1, 2, 3, 3)
    cam_path = cache.dir / "cameras.json"
    write_cameras(cam_path, seq)
    cache.save("detections", key, names=np.array(names, dtype=str), conics=conics,
               cameras_json=np.array(str(file_digest(cam_path))))
    return seq, _conics_from_arrays({"names": np.array(names, dtype=str), "conics": conics})


def _conics_from_arrays(d: dict) -> dict:
    if "names" not in d:
        return {}
    return {str(n): {"outer": c[0], "inner": c[1]} for n, c in zip(d["names"], d["conics"])}


@dataclass(frozen=True)
class _Silhouettes:
    masks: np.ndarray  # (V, H, W) bool: object
    unknown: np.ndarray  # (V, H, W) bool: neither object nor background for sure (carving keeps it)
    status: list[str]  # "ok", "conservative: <reason>" (kept) or "rejected: <reason>" (dropped)


def _stage_silhouettes(images_rgb, names, K, Ts, opts, cache, key, progress, vol, ws, intr=None) -> _Silhouettes:
    V, (w, h) = len(names), ws.work
    fields = {"masks": ("b", (V, h, w)), "unknown": ("b", (V, h, w)), "status": ("U", (V,))}
    hit = cache.load("silhouettes", key, fields)
    if hit is not None:
        progress.note("silhouettes: reused")
        return _Silhouettes(hit["masks"], hit["unknown"], [str(s) for s in hit["status"]])
    with progress.stage("silhouettes") as tick:
        if opts.masks_dir is not None:
            masks, empty = _read_masks(opts.masks_dir, names, ws, progress)
            masks = _undistort_masks(masks, intr, ws)
            unknown = np.zeros_like(masks)
            status = ["ok" if m.any() else f"rejected: the mask is empty ({empty.get(n, 'nothing left after undistortion')})"
                      for n, m in zip(names, masks)]
        else:
            from recon.silhouettes import estimate_silhouettes

            try:
                res = estimate_silhouettes(images_rgb, K, Ts, opts.spec, radius_mm=vol.radius_mm,
                                           height_mm=vol.height_mm, progress=tick)
            except ValueError as exc:
                raise UserError(f"{opts.input}: silhouettes: {exc}") from None
            masks, status = np.asarray(res.masks, bool), list(res.status)
            unknown = np.asarray(res.unknown, bool)
    cache.save("silhouettes", key, masks=masks, unknown=unknown, status=np.array(status))
    return _Silhouettes(masks, unknown, status)


_GREY = ("the photos are greyscale: automatic silhouettes tell the object from the table and the background "
         "mostly by colour; photograph in colour, or give --masks")


def _greyscale(images_rgb: list[np.ndarray]) -> bool:
    """Whether the (first few) photos carry no colour: R, G and B within 2 levels everywhere."""
    sample = images_rgb[:3]
    return bool(sample) and all(int(np.ptp(im.astype(np.int16), axis=2).max()) <= 2 for im in sample)


def _silhouettes_said(names: list[str], sil: "_Silhouettes", shown: int = 8) -> str:
    """Each view's silhouette, as its share of the image and its verdict (for an error that stops the run)."""
    share = sil.masks.reshape(len(names), -1).mean(axis=1)
    items = [f"{n} {100 * a:.1f} % {st}" for n, a, st in zip(names, share, sil.status)]
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return "silhouettes (share of the image, verdict): " + ", ".join(items[:shown]) + more


def _silhouette_verdicts(names, status) -> tuple[list[int], dict[str, str], dict[str, str]]:
    """Kept view indices, rejected frames and conservative (kept) frames, each with its reason."""
    keep, rejected, conservative = [], {}, {}
    for i, (n, s) in enumerate(zip(names, status)):
        if s == "ok":
            keep.append(i)
        elif s.startswith("conservative"):
            keep.append(i)
            conservative[n] = s.partition(":")[2].strip() or s
        else:  # "rejected: <reason>" (or a bare reason from an older silhouettes module)
            rejected[n] = s.partition(":")[2].strip() if s.startswith("rejected") else s
    return keep, rejected, conservative


def _max_rejections(opts: ReconstructOptions) -> int:
    """Views that may reject a voxel before it is carved: the user's masks are trusted (0); automatic
    silhouettes may err in a view (1), their doubtful pixels are carried by ``unknown`` besides."""
    if opts.max_rejections is not None:
        return int(opts.max_rejections)
    return 0 if opts.masks_dir is not None else 1


def _stage_hull(masks, K, Ts, opts, cache, key, progress, vol):
    from recon.types import VoxelHull

    fields = {"values": ("f", (None, None, None)), "origin": ("f", (3,)), "voxel_mm": ("f", ()),
              "touches": ("iu", (2,))}
    hit = cache.load("hull", key, fields)
    if hit is not None:
        progress.note("hull: reused")
        meta = {"touches_side": int(hit["touches"][0]), "touches_top": int(hit["touches"][1])}
        return VoxelHull(values=hit["values"], origin_table=hit["origin"], voxel_mm=float(hit["voxel_mm"]), meta=meta)
    from recon.carving import carve_hull

    with progress.stage("carving") as tick:
        try:
            hull = carve_hull(masks, K, Ts, radius_mm=vol.radius_mm, height_mm=vol.height_mm,
                              resolution=opts.resolution, max_rejections=min(_max_rejections(opts), len(masks) - 1),
                              progress=tick)
        except ValueError as exc:
            raise UserError(f"{opts.input}: carving: {exc}") from None
    cache.save("hull", key, values=hull.values, origin=hull.origin_table, voxel_mm=np.array(hull.voxel_mm),
               touches=np.array([hull.meta["touches_side"], hull.meta["touches_top"]]))
    return hull


def _silhouettes_and_hull(images_rgb, names, K, Ts, opts, cache, sil_key, progress, ws, intr=None):
    """Silhouettes and hull in a working volume grown until the object fits (or the view ends).

    Returns (silhouettes, kept indices, rejected, conservative, hull, volume, volume report).
    """
    from .volume_stage import MIN_TOUCH_VIEWS, initial_volume, mask_touches

    H, W = images_rgb[0].shape[:2]
    try:
        vol = initial_volume(K, Ts, (W, H), None if opts.spec is None else opts.spec.extent_mm)
    except ValueError as exc:
        raise UserError(f"{opts.cameras or opts.input}: {exc}") from None
    vol_key = stage_key(sil_key, vol.key(), opts.resolution, _max_rejections(opts))
    hit = cache.load("volume", vol_key, {"size": ("f", (2,)), "grown": ("U", (None,))})
    grown: list[str] = [str(g) for g in hit["grown"]] if hit is not None else []
    if hit is not None:
        vol = replace(vol, radius_mm=float(hit["size"][0]), height_mm=float(hit["size"][1]))
    automatic = opts.masks_dir is None
    clipped: list[str] = []
    doubtful_wall: list[str] = []

    grey = automatic and _greyscale(images_rgb)
    if grey:
        progress.note(f"silhouettes: {_GREY}")

    def carve(sil, keep, key, vol):
        hull_key = stage_key(key, keep, opts.resolution, _max_rejections(opts), vol.key())
        try:
            return _stage_hull(sil.masks[keep] | sil.unknown[keep], K, Ts[keep], opts, cache, hull_key, progress,
                               vol)
        except UserError as exc:  # nothing left: say what each view's silhouette was
            raise UserError(f"{exc}; {_silhouettes_said(names, sil)}" + (f"; {_GREY}" if grey else "")) from None

    sil, sil_for = None, None
    for _ in range(32):  # each pass grows the volume or ends the loop; the bound is a safety net
        key = stage_key(sil_key, vol.key()) if automatic else sil_key  # user masks do not depend on it
        if key != sil_for:
            sil, sil_for = _stage_silhouettes(images_rgb, names, K, Ts, opts, cache, key, progress, vol, ws,
                                              intr), key
        keep, rejected, conservative = _silhouette_verdicts(names, sil.status)
        if len(keep) < MIN_VIEWS:
            return sil, keep, rejected, conservative, None, vol, {}
        hull, why, touch = None, [], (False, False)
        if automatic:  # confined to the cylinder's image: an object larger than it touches that outline
            side, top = mask_touches(sil.masks[keep], K, Ts[keep], vol)
            touch = (len(side) >= MIN_TOUCH_VIEWS, len(top) >= MIN_TOUCH_VIEWS)
            why = [f"the silhouettes of {len(v)} views reach its {w}" for w, v, t in
                   zip(("side", "top"), (side, top), touch) if t]
        if not why:  # the silhouettes fit: carve, and ask the hull
            hull = carve(sil, keep, key, vol)
            touch = (hull.meta["touches_side"] > 0, hull.meta["touches_top"] > 0)
            why = [f"the carved hull reaches its {w}" for w, t in zip(("side", "top"), touch) if t]
            if automatic and why:
                # carved from masks | unknown: the doubtful pixels (carved only where a view is sure of the
                # background) reach the wall, not the object's own silhouette, which fits. Growing on them
                # would chase the doubt to the edge of the view: note it, and keep the volume.
                doubtful_wall = [f"doubtful silhouette pixels (not the object's sure silhouette) let the hull reach "
                                 f"its {w}" for w, t in zip(("side", "top"), touch) if t]
                progress.note(f"working volume: {'; '.join(doubtful_wall)}")
                why = []
        if not why:
            break
        bigger = vol.grown(*touch)
        if bigger is None:  # the cameras' view ends here: carve what there is, and say so
            clipped.append(f"the object reaches past the working volume ({vol.describe()}): {' and '.join(why)}; "
                           f"the cameras do not see further, so the model is cut there")
            progress.note(f"WARNING: {clipped[-1]}")
            break
        grown.append(f"{vol.describe()} -> {bigger.describe()}: {' and '.join(why)}")
        progress.note(f"working volume grows: {grown[-1]}")
        vol = bigger
    if hull is None:
        hull = carve(sil, keep, key, vol)
    cache.save("volume", vol_key, size=np.array([vol.radius_mm, vol.height_mm]), grown=np.array(grown, dtype=str))
    report = {"radius_mm": round(vol.radius_mm, 1), "height_mm": round(vol.height_mm, 1),
              "first_guess": vol.source, "max_radius_mm": round(vol.max_radius_mm, 1),
              "max_height_mm": round(vol.max_height_mm, 1), "grown": grown, "clipped": clipped,
              "notes": doubtful_wall}
    return sil, keep, rejected, conservative, hull, vol, report


# --------------------------------------------------------------------------- main
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
        _clear_cache(cache)
    skipped: dict[str, str] = {}

    # every stage key starts from this one: the frames' bytes, the target, the options the calibration reads
    # (the angle marks are read on the work images) and the bytes of --intrinsics and --cameras
    cam_key = stage_key(_input_key(opts), None if opts.spec is None else opts.spec.__dict__, opts.step_deg,
                        opts.work_size, file_digest(opts.intrinsics), file_digest(opts.cameras))
    seq, conics = _known_cameras(opts, progress, cam_key, cache)
    loaded = _load(opts, progress, seq)  # every frame decoded once; only the work size is kept
    ws = loaded.work
    frames = [Frame(n, im, "" if im is not None else why) for n, im, why in
              zip(loaded.names, loaded.images, loaded.failures)]
    for f in frames:
        if f.bgr is None:
            skipped[f.name] = f.error
            progress.note(f"skipping {f.name}: {f.error}")
    good = [f for f in frames if f.bgr is not None]
    unreadable = [f.name for f in frames if f.bgr is None]
    if seq is None:
        seq, conics = _stage_cameras(loaded, opts, progress, cam_key, cache)
    else:
        _check_known_cameras(seq, good, opts, ws)
    exif_focal = _exif_focal(good, seq, opts, progress)
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
        raise UserError(f"{opts.input}: only {len(used)} frame(s) could be calibrated; need at least 3 "
                        f"({'; '.join(f'{k}: {v}' for k, v in list(skipped.items())[:4])})")
    names = [f.name for f in used]
    K = ws.K(seq.intrinsics.K)  # the work images' camera (cameras.json keeps the photos')
    Ts = np.stack([by_name[n].T_cam_table for n in names])
    images_rgb = [cv2.cvtColor(im, cv2.COLOR_BGR2RGB) for im in _undistort([f.bgr for f in used], seq, ws)]
    del frames, good, used, loaded  # the work BGR copies go; images_rgb holds the pixels from here on

    masks_used = None if opts.masks_dir is None else files_digest(_mask_files(opts.masks_dir, names))
    # "masks undistorted", "label masks": what given masks mean changed with these keys (older caches recompute)
    sil_key = stage_key(cam_key, masks_used, "masks undistorted", "label masks", names, K, seq.intrinsics.dist, Ts, list(ws.work))
    sil, keep, rejected, conservative, hull, vol, vol_report = _silhouettes_and_hull(
        images_rgb, names, K, Ts, opts, cache, sil_key, progress, ws, seq.intrinsics)
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
    masks, Ts = sil.masks[keep], Ts[keep]

    from recon.meshing import clip_to_hull, mesh_from_hull

    with progress.stage("hull mesh"):  # smoothing moves vertices up to ~0.3 mm out: back inside the hull
        hull_mesh = clip_to_hull(mesh_from_hull(hull, max_faces=opts.max_faces), hull)
    mesh, fused, fusion_note = hull_mesh, None, "disabled (--no-fusion)"
    if opts.fusion:
        from .fusion_stage import run_fusion

        mesh, fused, fusion_note = run_fusion(images_rgb, masks, K, Ts, hull, hull_mesh, opts, progress)

    from recon.colorize import color_vertices

    with progress.stage("colour"):
        mesh = color_vertices(mesh, images_rgb, K, Ts, masks=masks)

    from recon.meshing import mesh_stats

    stats = mesh_stats(mesh)
    failed = _failed_checks(stats, vol_report)
    files = _export(staging, opts, seq, names, mesh, fused, progress)
    if recorder is not None:
        with progress.stage("recording"):
            _record(recorder, opts, seq, names, images_rgb, masks, K, Ts, hull_mesh, fused, mesh, conics, ws)
            files["recording"] = recorder.save(staging / "recording.rrd")
    files = {k: out / p.relative_to(staging) for k, p in files.items()}  # where they will be once published
    files["summary"] = out / "summary.json"
    summary = _summary(seq, names, skipped, mesh, progress, fusion_note, files)
    summary["mesh"]["pieces"] = stats.n_bodies
    summary["working_volume"] = vol_report
    summary["silhouettes"] = {"rejected": rejected, "conservative": conservative}
    summary["failed_checks"] = failed
    summary["exif_focal"] = exif_focal
    summary["work_size"] = ws.report()
    summary["time_s"]["total"] = round(time.perf_counter() - t0, 2)
    atomic_write_text(staging / "summary.json", json.dumps(summary, indent=1) + "\n")
    exit_code = EXIT_CHECK_FAILED if failed else EXIT_UNREADABLE if unreadable else EXIT_OK
    return ReconstructResult(out=out, files=files, frames_used=names, frames_skipped=skipped,
                             summary=summary, exit_code=exit_code, failed_checks=failed,
                             unreadable=unreadable)


def _check_known_cameras(seq: SequenceCalibration, good: list[Frame], opts: ReconstructOptions,
                         ws: WorkSize) -> None:
    """``--cameras`` must be for photos of this size and name every readable frame."""
    if opts.cameras is None:
        return
    intr = seq.intrinsics
    if (intr.width, intr.height) != tuple(ws.full):
        raise UserError(f"--cameras {opts.cameras}: the cameras are for {intr.width}x{intr.height} images, "
                        f"the frames are {ws.full[0]}x{ws.full[1]}")
    names = {fp.image for fp in seq.frames}
    missing = [f.name for f in good if f.name not in names]
    if missing:
        raise UserError(f"--cameras {opts.cameras}: no camera for frame(s) {', '.join(missing[:5])}")


def _exif_focal(frames: list[Frame], seq: SequenceCalibration, opts: ReconstructOptions,
                progress: Progress) -> dict | None:
    """The photos' EXIF focal length against the calibrated one (None: a video, or no EXIF focal length)."""
    from .images import exif_focal_report, focal_warning

    if not Path(opts.input).is_dir():
        return None
    intr = seq.intrinsics
    report = exif_focal_report(_frame_paths(opts, [f.name for f in frames]), intr.width, intr.height, intr.focal_px)
    for line in ((report or {}).get("note"), focal_warning(intr.focal_px, report)):
        if line:
            progress.note(f"cameras: {line}")
    return report


def _failed_checks(stats, vol_report: dict) -> list[str]:
    """What is wrong with the finished model, one line each (empty: it passed)."""
    failed = []
    if not stats.watertight:
        failed.append("the mesh is not watertight")
    if stats.n_bodies != 1:
        failed.append(f"the mesh is {stats.n_bodies} separate pieces, not one")
    failed += vol_report["clipped"]
    return failed


def _export(staging: Path, opts, seq, names, mesh, fused, progress) -> dict[str, Path]:
    """Write the model, cameras and exports into ``staging`` (the folder that becomes OUT's new set)."""
    from recon.export import export_mesh

    out = staging
    with progress.stage("export"):
        files = dict(export_mesh(mesh, out))
        write_cameras(out / "cameras.json", seq)
        files["cameras"] = out / "cameras.json"
        if fused is not None and len(fused.pts_table):
            from .pointsio import write_points_ply

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

            from .frames import frame_name

            # file paths relative to OUT (where transforms.json is published), pointing at the user's photos
            rel = [(frame_name(os.path.relpath(p, opts.out)), T_by_name[n])
                   for n, p in zip(names, _frame_paths(opts, names))]
            files["nerfstudio"] = export_nerfstudio(intr.K, intr.width, intr.height, rel, out, dist=intr.dist,
                                                    ply_file_path="model.ply")
    return files


def _summary(seq, names, skipped, mesh, progress, fusion_note, files) -> dict:
    import trimesh

    from .frames import frame_name

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
        "time_s": {k: round(v, 2) for k, v in progress.times_s.items()},
        "files": {k: frame_name(str(v)) for k, v in files.items()},  # strict JSON whatever the path
    }


def _record(rec, opts, seq, names, images_rgb, masks, K, Ts, hull_mesh, fused, mesh, conics, ws) -> None:
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
