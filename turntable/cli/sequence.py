"""``turntable calibrate-sequence``: one camera and one pose per frame -> cameras.json.

Detects the rings in every image of a folder (or frame of a video), calibrates them jointly
(:func:`calib.sequence.calibrate_sequence`: a fixed camera and a turning table,
or a hand-held camera), prints a summary table and writes ``cameras.json``
atomically. Frames that cannot be used are listed with their reason; the exit
code is 0 when every frame calibrated, 1 when some were skipped.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

from calib.target import TargetSpec
from calib.types import SequenceCalibration

from .cameras_io import write_cameras
from .cmd_calibrate import add_target_arguments, target_from_args
from .errors import UserError
from .frames import VIDEO_SUFFIXES, iter_frames, select_indices
from .images import exif_focal_report, focal_warning, list_images, read_image
from .progress import Progress, fit_reporter

__all__ = ["add_arguments", "run", "calibrate_folder", "summary_table"]


def add_arguments(parser) -> None:
    parser.add_argument("input", metavar="INPUT", help="folder of photos in turntable order (natural sort), or a video")
    add_target_arguments(parser)
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="use every N-th frame (videos, dense folders)")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="use N frames spread evenly over the input (not with --every)")
    parser.add_argument("--step-deg", type=float, metavar="D",
                        help="motorised table: frame k is at k*D degrees (the marks are checked against it)")
    parser.add_argument("--intrinsics", metavar="FILE",
                        help="known camera (OpenCV YAML/XML or JSON: camera_matrix, distortion_coefficients, "
                             "image_width, image_height); K is kept, the edges are undistorted with it")
    parser.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"),
                        help="known principal point, pixels (default: estimated where the views allow, "
                             "else the image centre)")
    parser.add_argument("--mode", choices=("auto", "turntable", "handheld"), default="auto",
                        help="fixed camera and turning table, or a moving camera (default: decided from the data)")
    parser.add_argument("--no-distortion", action="store_true", help="do not estimate radial distortion")
    parser.add_argument("--out", required=True, metavar="cameras.json", help="output file")


def _progress_printer(stream, label: str):
    """``tick(done, total)``: a live line on a terminal, a line per quarter otherwise."""
    t0 = time.perf_counter()
    last = [0.0, -1]
    tty = bool(getattr(stream, "isatty", lambda: False)())

    def tick(done: int, total: int) -> None:
        now = time.perf_counter()
        if tty:
            if now - last[0] < 0.2 and done < total:
                return
            end = "\n" if done >= total else ""
            stream.write(f"\r{label}: {done}/{total} ({now - t0:.1f} s){end}")
        else:
            quarter = 4 * done // max(total, 1)
            if quarter == last[1]:
                return
            last[1] = quarter
            stream.write(f"{label}: {done}/{total} ({now - t0:.1f} s)\n")
        last[0] = now
        stream.flush()

    return tick


def calibrate_folder(paths, spec: TargetSpec, *, step_deg=None, intrinsics=None, mode="auto",
                     principal_point_px=None, distortion="auto", progress=None,
                     fit_progress=None) -> SequenceCalibration:
    """Read ``paths`` (unreadable ones are reported as skipped frames) and calibrate them.

    One photo at a time: its rings are found at full resolution, and only a
    copy at the default work size (:func:`turntable.worksize.choose_work_size`;
    photos up to 1.3 MP whole) is kept to read the angle marks from.
    ``UserError`` when nothing can be calibrated or the photos differ in size;
    see :func:`turntable.sequence_stage.calibrate_frames` for the rest.
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
    from .sequence_stage import calibrate_detected, detect_and_reduce
    from .worksize import choose_work_size

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


def _fmt(x, spec: str, none: str = "-") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _exif_text(exif: dict | None) -> str:
    if not exif:
        return ""
    return (f"   (EXIF: {exif['focal_35mm']:g} mm equivalent = {exif['focal_px']:.1f} px; "
            f"calibrated {exif['calibrated_vs_exif_pct']:+.1f} %)")


def summary_table(seq: SequenceCalibration) -> str:
    """Human summary: per-frame lines, then the shared camera with 1-sigma."""
    m = seq.meta
    lines = [f"{'image':<28} {'angle°':>8} {'rms px':>7}  status", "-" * 60]
    for f in seq.frames:
        lines.append(f"{Path(f.image).name[:28]:<28} {_fmt(f.angle_deg, '8.2f'):>8} "
                     f"{_fmt(f.rms_px, '7.3f'):>7}  {f.status}")
    K = seq.intrinsics.K
    pp_std = m.get("principal_point_std_px") or [None, None]
    lines += ["",
              f"mode            {seq.mode} ({m.get('mode_reason', '')})",
              f"frames          {m.get('frames_used', '?')} used, {m.get('frames_skipped', '?')} skipped",
              f"focal length    {K[0, 0]:.2f} px ± {_fmt(m.get('focal_std_px'), '.2f', 'fixed')}"
              + _exif_text(m.get("exif_focal")),
              f"principal point ({K[0, 2]:.2f}, {K[1, 2]:.2f}) px ± "
              f"({_fmt(pp_std[0], '.2f', 'fixed')}, {_fmt(pp_std[1], '.2f', 'fixed')})"]
    dist = seq.intrinsics.dist
    if dist.size:
        ds = m.get("dist_std", {})
        lines.append("distortion      " + ", ".join(
            f"{n} {dist[i]:+.4f} ± {_fmt(ds.get(n), '.4f', 'fixed')}" for i, n in enumerate(("k1", "k2"))
            if i < dist.size))
    if m.get("stroke_mm") is not None:
        lines.append(f"stroke width    {m['stroke_mm']:.3f} mm ± {_fmt(m.get('stroke_std_mm'), '.3f')}")
    lines.append(f"RMS             {_fmt(m.get('rms_px'), '.3f')} px "
                 f"(single views {_fmt(m.get('single_view_rms_px'), '.3f')} px)")
    tt = m.get("turntable")
    if tt:
        off = tt["pattern_offset_from_axis_mm"]
        lines.append(f"turntable       camera {tt['camera_radius_mm']:.1f} mm from the axis, "
                     f"{tt['camera_height_mm']:.1f} mm above the table; pattern off the axis by "
                     f"({off[0]:.2f}, {off[1]:.2f}) mm")
    exif = m.get("exif_focal") or {}
    for line in (exif.get("note"), focal_warning(K[0, 0], exif or None)):
        if line:
            lines.append(f"warning         {line}")
    for name, why in m.get("not_estimated", {}).items():
        lines.append(f"note            {name}: {why}")
    for c in m.get("angle_checks", []):
        lines.append(f"warning         {c['image']}: marks and --step-deg disagree by "
                     f"{c['marks_minus_step_deg']:+.2f}°")
    return "\n".join(lines)


def run(args) -> int:
    spec = target_from_args(args)
    src = Path(args.input)
    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"--out {out}: is a folder; give a file name such as {out / 'cameras.json'}")
    select_indices(1, args.every, args.frames)  # argument errors before any reading
    if src.is_dir():
        files = list_images(src)
        paths = [files[i] for i in select_indices(len(files), args.every, args.frames)]
    else:  # a video (iter_frames names what else it is: missing, a single image, unknown)
        paths = None
        if not src.exists() or src.suffix.lower() not in VIDEO_SUFFIXES:
            next(iter_frames(src, args.every, args.frames))  # raises UserError saying what it is
    intr = None
    if args.intrinsics:
        from .intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(args.intrinsics)
    if args.step_deg is not None and not (math.isfinite(args.step_deg) and args.step_deg != 0):
        raise UserError(f"--step-deg must be a non-zero number, got {args.step_deg}")
    pp = tuple(args.principal_point) if args.principal_point else None
    kw = dict(step_deg=args.step_deg, intrinsics=intr, mode=args.mode, principal_point_px=pp,
              distortion="none" if args.no_distortion else "auto",
              progress=_progress_printer(sys.stderr, "calibrate-sequence"),
              fit_progress=fit_reporter(Progress(sys.stderr), "joint fit"))
    if paths is not None:
        seq = calibrate_folder(paths, spec, **kw)
        exif = exif_focal_report(paths, seq.intrinsics.width, seq.intrinsics.height, seq.intrinsics.focal_px)
        if exif is not None:
            seq = dataclasses.replace(seq, meta={**seq.meta, "exif_focal": exif})
    else:  # the video's frames decoded one at a time, never all held at full resolution
        seq = calibrate_stream(((f.name, f.bgr, f.error) for f in iter_frames(src, args.every, args.frames)), 0,
                               spec, **kw)
    for f in seq.frames:
        if not f.ok:
            where = src / f.image if paths is not None else f"{src} (frame {f.image})"
            print(f"turntable calibrate-sequence: {where}: {f.status}", file=sys.stderr)
    write_cameras(out, seq)
    print(summary_table(seq))
    print(f"wrote {out}")
    return 0 if all(f.ok for f in seq.frames) else 1
