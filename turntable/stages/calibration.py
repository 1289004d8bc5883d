"""The sequence-calibration stage: detection in every frame, then the joint fit.

Shared by ``turntable calibrate-sequence`` and the ``reconstruct`` orchestrator.
Frames whose rings cannot be found are kept with their reason; the library
(:func:`calib.sequence.calibrate_sequence`) does the rest.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.target import TargetSpec
from calib.types import CalibrationError, Intrinsics, RingConics, SequenceCalibration, TargetObservation

from ..errors import UserError
from ..images import read_image
from ..worksize import WorkSize

log = logging.getLogger(__name__)

__all__ = ["calibrate_folder", "calibrate_stream", "calibrate_frames", "calibrate_detected", "detect_all",
           "detect_and_reduce", "DetectedFrames", "scaled_marks_reader", "look_again"]


def detect_all(frames: Sequence[tuple[str, np.ndarray | None, str]], spec: TargetSpec,
               principal_point_px=None, progress: Callable[[int, int], None] | None = None
               ) -> tuple[list[TargetObservation | None], list[str]]:
    """Ring observations of every frame (None and the reason where not found)."""
    from calib.rings import detect_rings

    obs: list[TargetObservation | None] = []
    failures: list[str] = []
    for k, (_name, img, error) in enumerate(frames):
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


@dataclass
class DetectedFrames:
    """Frames read one by one: ring observations at full resolution, pixels kept at the work size only."""

    names: list[str] = field(default_factory=list)
    images: list = field(default_factory=list)  # (h, w, 3) uint8 at ``work.work``, or None (unreadable)
    observations: list = field(default_factory=list)  # TargetObservation in full-image pixels, or None
    failures: list[str] = field(default_factory=list)  # why a frame has no observation ("" where it has one)
    work: WorkSize | None = None  # None until a readable frame was seen


def detect_and_reduce(frames: Iterable[tuple[str, np.ndarray | None, str]], spec: TargetSpec | None,
                      choose: Callable[[tuple[int, int], float | None, str], WorkSize], *,
                      principal_point_px=None, expected_size: tuple[int, int] | None = None,
                      progress: Callable[[int, int], None] | None = None, total: int = 0) -> DetectedFrames:
    """Find the rings in each frame at full resolution (``spec`` None: don't) and keep it reduced.

    ``frames`` may be a generator that decodes each image when it is reached:
    no full-resolution frame is held past its own turn. ``choose(full_size,
    ring_px, name)`` gives the work size on the first readable frame
    (``ring_px``: long axis of its outer ring in pixels, None where not found).
    ``expected_size`` (width, height): the size ``--intrinsics`` are for; another
    is a ``UserError``.
    """
    from calib.conics import conic_to_ellipse
    from calib.rings import detect_rings

    out = DetectedFrames()
    for name, img, error in frames:
        obs, why = None, error or ""
        if img is not None and not error:
            h, w = img.shape[:2]
            if expected_size is not None and (w, h) != tuple(expected_size):
                raise UserError(f"--intrinsics are for {expected_size[0]}x{expected_size[1]} images, "
                                f"the frames are {w}x{h}")
            if spec is not None:
                try:
                    obs = detect_rings(img, spec, principal_point_px=principal_point_px)
                except (CalibrationError, ValueError) as exc:  # one bad frame does not stop the sequence
                    why = str(exc)
            if out.work is None:
                ring = None
                if obs is not None and obs.conics is not None:
                    ring = 2.0 * conic_to_ellipse(obs.conics.outer).a
                out.work = choose((w, h), ring, name)
            img = out.work.reduce(img)
        elif not why:
            why = "image unreadable"
        out.names.append(name)
        out.images.append(img)
        out.observations.append(obs)
        out.failures.append("" if obs is not None else why)
        if progress is not None:
            progress(len(out.names), max(total, len(out.names)))
    return out


def calibrate_frames(frames: Sequence[tuple[str, np.ndarray | None, str]], spec: TargetSpec, *,
                     step_deg: float | None = None, intrinsics: Intrinsics | None = None, mode: str = "auto",
                     principal_point_px=None, distortion: str = "auto",
                     progress: Callable[[int, int], None] | None = None,
                     observations_out: list | None = None, fit_progress=None) -> SequenceCalibration:
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
    fit_progress : callable(calib.sequence.FitStep), optional
        Told each iteration of the joint fit (:func:`turntable.progress.fit_reporter`).

    Raises
    ------
    UserError
        No frames, images of different sizes, intrinsics for another image size,
        or no frame could be calibrated (the message lists why).
    """
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
    return calibrate_detected(obs, failures, [f[0] for f in frames], [img for _, img, _ in frames], spec,
                              step_deg=step_deg, intrinsics=intrinsics, mode=mode,
                              principal_point_px=principal_point_px, distortion=distortion, progress=tick2,
                              fit_progress=fit_progress, observations_out=observations_out)


def calibrate_detected(observations: Sequence[TargetObservation | None], failures: Sequence[str],
                       names: Sequence[str], images: Sequence[np.ndarray | None], spec: TargetSpec, *,
                       marks_map: np.ndarray | None = None, step_deg: float | None = None,
                       intrinsics: Intrinsics | None = None, mode: str = "auto", principal_point_px=None,
                       distortion: str = "auto", progress: Callable[[int, int], None] | None = None,
                       fit_progress=None, observations_out: list | None = None) -> SequenceCalibration:
    """The sequence calibration from ring observations already made (:func:`detect_all`).

    ``images`` are what the angle marks are read from: the photos, or copies
    reduced by ``marks_map`` (3, 3), the map of full-image pixel centres to
    theirs (:func:`turntable.worksize.scale_matrix`); the marks are read there
    with the camera matrix ``marks_map @ K``. The observations are always in
    full-image pixels. ``progress`` is told each frame's single-view calibration,
    ``fit_progress`` each iteration of the joint fit (:class:`calib.sequence.FitStep`).
    In turntable mode the rings of frames without an observation are searched
    again where the others put them (:func:`look_again`) and, where found, the
    sequence is calibrated again with them; ``observations_out`` receives the
    observations so completed. Raises ``UserError`` when no frame can be calibrated.
    """
    from calib.sequence import calibrate_sequence

    reader = None
    if marks_map is not None:
        reader = scaled_marks_reader(images, spec, marks_map, intrinsics.dist if intrinsics is not None else None)
    observations, failures = list(observations), list(failures)

    def run(tick) -> SequenceCalibration:
        try:
            return calibrate_sequence(observations, None if reader is not None else list(images), spec,
                                      names=list(names), failures=failures, step_deg=step_deg,
                                      intrinsics=intrinsics, mode=mode, principal_point_px=principal_point_px,
                                      distortion=distortion, angle_reader=reader, progress=tick,
                                      fit_progress=fit_progress)
        except CalibrationError as exc:
            raise UserError(str(exc)) from None

    seq = run(progress)
    found = look_again(seq, observations, failures, images, spec, marks_map) if seq.mode == "turntable" else []
    if found:
        seq = run(None)
        d = seq.diagnostics
        if d is not None:
            why = (f"the rings of {len(found)} frame(s) ({', '.join(names[k] for k in found[:5])}) were found by "
                   f"searching where the frames beside them put them")
            seq = replace(seq, diagnostics=replace(d, mode_reason=f"{d.mode_reason}; {why}"))
    if observations_out is not None:
        observations_out.extend(observations)
    return seq


def look_again(seq: SequenceCalibration, observations: list, failures: list[str],
               images: Sequence[np.ndarray | None], spec: TargetSpec, marks_map: np.ndarray | None = None) -> list[int]:
    """Search the rings of each frame that has none where a fixed camera puts them, and return those found.

    A turntable sequence's frames all see the rings in nearly the same place
    (exactly, when the pattern is centred on the axis): the pose the calibrated
    frames beside it predict (:func:`calib.sequence.expected_pose`) gives the
    centre-line conics, and :func:`calib.rings.detect_rings_near` searches
    around them, on ``images[k]`` (full-image pixels mapped by ``marks_map``,
    or the photo itself). This recovers frames whose coarse ellipse search was
    misled, mostly by an object hiding much of the inner ring. ``observations``
    and ``failures`` are updated in place; a frame still not found keeps its
    reason, with the second search's added.
    """
    from calib.camera import circle_points_table, project_points
    from calib.conics import fit_conic, normalize_conic
    from calib.distortion import distort_px
    from calib.rings import detect_rings_near
    from calib.sequence import expected_pose

    S = np.eye(3) if marks_map is None else np.asarray(marks_map, np.float64)
    Sinv = np.linalg.inv(S)

    def full(C):  # a conic in work pixels -> full-image pixels: C_full = S^T C S
        return None if C is None else normalize_conic(S.T @ C @ S)

    K, dist = seq.intrinsics.K, seq.intrinsics.dist
    found: list[int] = []
    for k, (obs, img) in enumerate(zip(observations, images, strict=True)):
        if obs is not None or img is None:
            continue
        T = expected_pose(seq.frames, k)
        if T is None:
            return found
        conics = []
        for r in (spec.r_outer_mm, spec.r_inner_mm):
            uv = project_points(K, T, circle_points_table(r, 180))
            if dist is not None and np.any(dist):
                uv = distort_px(uv, K, dist)
            conics.append(fit_conic(uv @ S[:2, :2].T + S[:2, 2]))
        try:
            near = detect_rings_near(img, spec, conics[0], conics[1])
        except (CalibrationError, ValueError) as exc:
            failures[k] = f"{failures[k]}; not found either where the frames beside it put the rings: {exc}"
            continue
        edges = tuple(replace(e, uv_px=e.uv_px @ Sinv[:2, :2].T + Sinv[:2, 2]) for e in near.edges)
        c = near.conics
        if c is not None:
            c = RingConics(outer=full(c.outer), inner=full(c.inner), outer_plus=full(c.outer_plus),
                           outer_minus=full(c.outer_minus), inner_plus=full(c.inner_plus),
                           inner_minus=full(c.inner_minus))
        observations[k] = replace(near, edges=edges, conics=c, width=seq.intrinsics.width,
                                  height=seq.intrinsics.height)
        failures[k] = ""
        found.append(k)
    return found


def scaled_marks_reader(images: Sequence[np.ndarray | None], spec: TargetSpec, S: np.ndarray,
                        dist: np.ndarray | None = None):
    """An angle reader (:data:`calib.sequence.AngleReader`) on images reduced by ``S`` (full -> reduced pixels).

    The marks are sampled in table millimetres (``calib.marks``), so reading
    them on a reduced copy changes the camera matrix only: ``K' = S K``; the
    distortion coefficients act on normalised coordinates and are unchanged.
    """
    from calib.sequence import marks_angle_reader

    base = marks_angle_reader(images, spec, dist)
    S = np.asarray(S, np.float64)

    def read(k: int, K: np.ndarray, T: np.ndarray, dist_now: np.ndarray | None = None):
        return base(k, S @ np.asarray(K, np.float64), T, dist_now)

    return read


def calibrate_folder(paths, spec: TargetSpec, *, step_deg=None, intrinsics=None, mode="auto",
                     principal_point_px=None, distortion="auto", progress=None,
                     fit_progress=None) -> SequenceCalibration:
    """Read ``paths`` (unreadable ones are reported as skipped frames) and calibrate them.

    One photo at a time: its rings are found at full resolution, and only a
    copy at the default work size (:func:`turntable.worksize.choose_work_size`;
    photos up to 1.3 MP whole) is kept to read the angle marks from.
    ``UserError`` when nothing can be calibrated or the photos differ in size;
    see :func:`turntable.stages.calibration.calibrate_frames` for the rest.
    """
    def frames():
        size = None
        for p in map(Path, paths):
            try:
                img = read_image(p)
            except UserError as exc:
                yield p.name, None, str(exc).split(": ", 1)[-1]
                continue
            if size is not None and img.shape[:2] != size:
                raise UserError(f"frames have different sizes: {p} is {img.shape[1]}x{img.shape[0]}, "
                                f"the first is {size[1]}x{size[0]}")
            size = img.shape[:2]
            yield p.name, img, ""

    if not paths:
        raise UserError("no frames to calibrate")
    return calibrate_stream(frames(), len(paths), spec, step_deg=step_deg, intrinsics=intrinsics, mode=mode,
                            principal_point_px=principal_point_px, distortion=distortion, progress=progress,
                            fit_progress=fit_progress)


def calibrate_stream(frames, n: int, spec: TargetSpec, *, step_deg=None, intrinsics=None, mode="auto",
                     principal_point_px=None, distortion="auto", progress=None,
                     fit_progress=None) -> SequenceCalibration:
    """Calibrate frames ``(name, BGR image or None, error)`` given one at a time (a generator that decodes
    each when it is reached: a folder's photos, a video's frames), ``n`` of them (0: not known ahead).

    Each frame's rings are found at full resolution and only a copy at the
    default work size is kept, for the angle marks. ``progress(done, total)``
    counts the frames twice (detection, then single-view calibration);
    ``fit_progress`` is told each iteration of the joint fit after them.
    """
    from ..worksize import choose_work_size

    tick = (lambda done, total: progress(done, 2 * max(n, total))) if progress is not None else None
    pp = intrinsics.principal_point_px if intrinsics is not None else principal_point_px
    det = detect_and_reduce(frames, spec, lambda size, ring, name: choose_work_size(size, ring),
                            principal_point_px=pp, progress=tick, total=n,
                            expected_size=None if intrinsics is None else (intrinsics.width, intrinsics.height))
    if not det.names:
        raise UserError("no frames to calibrate")
    m = len(det.names)
    tick2 = (lambda done, total: progress(m + done, 2 * m)) if progress is not None else None
    return calibrate_detected(det.observations, det.failures, det.names, det.images, spec,
                              marks_map=None if det.work is None else det.work.S, step_deg=step_deg,
                              intrinsics=intrinsics, mode=mode, principal_point_px=principal_point_px,
                              distortion=distortion, progress=tick2, fit_progress=fit_progress)
