"""Stage 1, frames: decode the input once (rings at full size, pixels at the work size), undistort."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calib.target import TargetSpec
from calib.types import SequenceCalibration

from ..errors import UserError
from ..frames import iter_frames
from ..progress import Progress
from ..worksize import WorkSize, choose_work_size
from .cache import files_digest, stage_key
from .options import ReconstructOptions


def frame_files(opts: ReconstructOptions, names: list[str]) -> list[Path]:
    """Where each frame lives on disk (video frames: the video itself)."""
    from ..frames import frame_paths

    p = Path(opts.input)
    if not p.is_dir():
        return [p] * len(names)
    files = frame_paths(p)
    return [files.get(n, p / n) for n in names]


# --------------------------------------------------------------------------- stages


def load(opts: ReconstructOptions, progress: Progress, seq: SequenceCalibration | None):
    """Decode every frame once: the rings at full resolution (when ``seq`` is None), the pixels at the work size.

    The work size is chosen on the first readable frame, from its size and the
    outer ring's size in it (:func:`turntable.worksize.choose_work_size`; the
    pixel count alone where its rings are not found).
    Returns :class:`turntable.stages.calibration.DetectedFrames`.
    """
    from .calibration import detect_and_reduce

    intr = None
    if seq is None and opts.intrinsics is not None:
        from ..intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(opts.intrinsics)

    def choose(size, ring_px, name):
        if ring_px is None and seq is not None:
            ring_px = ring_px_from_camera(seq, name, opts.spec)
        ws = choose_work_size(size, ring_px, opts.work_size)
        progress.note(f"work size: {ws.describe()}")
        return ws

    frames = ((f.name, f.bgr, f.error) for f in iter_frames(opts.input, opts.every, opts.frames))
    with progress.stage("frames" if seq is not None else "frames and rings") as tick:
        return detect_and_reduce(frames, opts.spec if seq is None else None, choose,
                                 principal_point_px=None if intr is None else intr.principal_point_px,
                                 expected_size=None if intr is None else (intr.width, intr.height),
                                 progress=tick, total=count_inputs(opts))


def count_inputs(opts: ReconstructOptions) -> int:
    """How many frames will be read (a folder: known; a video: 0, unknown until read)."""
    from ..frames import select_indices
    from ..images import list_images

    p = Path(opts.input)
    if not p.is_dir():
        return 0
    return len(select_indices(len(list_images(p)), opts.every, opts.frames))


def input_key(opts: ReconstructOptions) -> str:
    """What the inputs are: the selected files' names and the hashes of their bytes (a video: the whole file)."""
    from ..frames import select_indices
    from ..images import list_images

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


def undistort(images: list[np.ndarray], seq: SequenceCalibration, ws: WorkSize) -> list[np.ndarray]:
    """Work images without lens distortion (same camera matrix ``ws.K(K)``; the coefficients are scale-free)."""
    return undistort_with(images, seq.intrinsics, ws)


def undistort_with(images: list[np.ndarray], intr, ws: WorkSize) -> list[np.ndarray]:
    if not intr.has_distortion:
        return images
    K = ws.K(intr.K)
    m1, m2 = cv2.initUndistortRectifyMap(K, intr.dist, None, K, tuple(ws.work), cv2.CV_32FC1)
    return [cv2.remap(im, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for im in images]


def ring_px_from_camera(seq: SequenceCalibration, name: str, spec: TargetSpec | None) -> float | None:
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
