"""The sequence-calibration stage: detection in every frame, then the joint fit.

Shared by ``turntable calibrate-sequence`` and the ``reconstruct`` orchestrator.
Frames whose rings cannot be found are kept with their reason; the library
(:func:`calib.sequence.calibrate_sequence`) does the rest.
"""

from __future__ import annotations

import logging
from typing import Callable, Sequence

import numpy as np

from calib.target import TargetSpec
from calib.types import CalibrationError, Intrinsics, SequenceCalibration, TargetObservation

from .errors import UserError

log = logging.getLogger(__name__)

__all__ = ["calibrate_frames", "detect_all"]


def detect_all(frames: Sequence[tuple[str, np.ndarray | None, str]], spec: TargetSpec,
               principal_point_px=None, progress: Callable[[int, int], None] | None = None
               ) -> tuple[list[TargetObservation | None], list[str]]:
    """Ring observations of every frame (None and the reason where not found)."""
    from calib.rings import detect_rings

    obs: list[TargetObservation | None] = []
    failures: list[str] = []
    for k, (name, img, error) in enumerate(frames):
        o, why = None, error or ""
        if img is not None and not error:
            try:
                o = detect_rings(img, spec, principal_point_px=principal_point_px)
            except (CalibrationError, ValueError) as exc:  # one bad frame does not stop the sequence
                why = str(exc)
        elif not why:
            why = "image unreadable"
        obs.append(o)
        failures.append(why)
        if progress is not None:
            progress(k + 1, len(frames))
    return obs, failures


def calibrate_frames(frames: Sequence[tuple[str, np.ndarray | None, str]], spec: TargetSpec, *,
                     step_deg: float | None = None, intrinsics: Intrinsics | None = None, mode: str = "auto",
                     principal_point_px=None, distortion: str = "auto",
                     progress: Callable[[int, int], None] | None = None,
                     observations_out: list | None = None) -> SequenceCalibration:
    """Detect the rings in every frame and calibrate the sequence.

    Parameters
    ----------
    frames : list of (name, BGR image (H, W, 3) uint8 or None, error message)
        In turntable order; an image of None (or an error) is reported as skipped.
    spec : TargetSpec
    step_deg, intrinsics, mode, principal_point_px, distortion
        See :func:`calib.sequence.calibrate_sequence`.
    progress : callable(done, total), optional
    observations_out : list, optional
        Receives each frame's ``TargetObservation`` (None where not detected),
        for callers that show what was detected.

    Raises
    ------
    UserError
        No frames, images of different sizes, intrinsics for another image size,
        or no frame could be calibrated (the message lists why).
    """
    from calib.sequence import calibrate_sequence

    if not frames:
        raise UserError("no frames to calibrate")
    sizes = {img.shape[:2] for _, img, _ in frames if img is not None}
    if len(sizes) > 1:
        raise UserError(f"frames have different sizes: {sorted(sizes)}")
    if intrinsics is not None and sizes:
        (h, w), = sizes
        if (w, h) != (intrinsics.width, intrinsics.height):
            raise UserError(f"--intrinsics are for {intrinsics.width}x{intrinsics.height} images, "
                            f"the frames are {w}x{h}")
    n = len(frames)
    tick = (lambda done, total: progress(done, 2 * n)) if progress is not None else None
    tick2 = (lambda done, total: progress(n + done, 2 * n)) if progress is not None else None
    pp = intrinsics.principal_point_px if intrinsics is not None else principal_point_px
    obs, failures = detect_all(frames, spec, principal_point_px=pp, progress=tick)
    if observations_out is not None:
        observations_out.extend(obs)
    try:
        return calibrate_sequence(obs, [img for _, img, _ in frames], spec, names=[f[0] for f in frames],
                                  failures=failures, step_deg=step_deg, intrinsics=intrinsics, mode=mode,
                                  principal_point_px=principal_point_px, distortion=distortion,
                                  progress=tick2)
    except CalibrationError as exc:
        raise UserError(str(exc)) from None
