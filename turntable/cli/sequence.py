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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from calib.types import SequenceCalibration, SequenceDiagnostics

from ..cameras_io import write_cameras
from ..errors import UserError
from ..frames import VIDEO_SUFFIXES, iter_frames, select_indices
from ..images import exif_focal_report, focal_warning, list_images
from ..progress import Progress, fit_reporter
from ..stages.calibration import calibrate_folder, calibrate_stream
from .args import add_target_arguments, target_from_args

__all__ = ["add_arguments", "run", "summary_table"]


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






def _fmt(x, spec: str, none: str = "-") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _exif_text(exif: Mapping[str, Any] | None) -> str:
    if not exif:
        return ""
    return (f"   (EXIF: {exif['focal_35mm']:g} mm equivalent = {exif['focal_px']:.1f} px; "
            f"calibrated {exif['calibrated_vs_exif_pct']:+.1f} %)")


def summary_table(seq: SequenceCalibration) -> str:
    """Human summary: per-frame lines, then the shared camera with 1-sigma."""
    m = seq.diagnostics if seq.diagnostics is not None else SequenceDiagnostics()
    lines = [f"{'image':<28} {'angle°':>8} {'rms px':>7}  status", "-" * 60]
    for f in seq.frames:
        lines.append(f"{Path(f.image).name[:28]:<28} {_fmt(f.angle_deg, '8.2f'):>8} "
                     f"{_fmt(f.rms_px, '7.3f'):>7}  {f.status}")
    K = seq.intrinsics.K
    pp_std = m.principal_point_std_px
    used = "?" if m.frames_used is None else m.frames_used
    skipped = "?" if m.frames_skipped is None else m.frames_skipped
    lines += ["",
              f"mode            {seq.mode} ({m.mode_reason})",
              f"frames          {used} used, {skipped} skipped",
              f"focal length    {K[0, 0]:.2f} px ± {_fmt(m.focal_std_px, '.2f', 'fixed')}"
              + _exif_text(m.exif_focal),
              f"principal point ({K[0, 2]:.2f}, {K[1, 2]:.2f}) px ± "
              f"({_fmt(pp_std[0], '.2f', 'fixed')}, {_fmt(pp_std[1], '.2f', 'fixed')})"]
    dist = seq.intrinsics.dist
    if dist.size:
        ds = m.dist_std
        lines.append("distortion      " + ", ".join(
            f"{n} {dist[i]:+.4f} ± {_fmt(ds.get(n), '.4f', 'fixed')}" for i, n in enumerate(("k1", "k2"))
            if i < dist.size))
    if m.stroke_mm is not None:
        lines.append(f"stroke width    {m.stroke_mm:.3f} mm ± {_fmt(m.stroke_std_mm, '.3f')}")
    lines.append(f"RMS             {_fmt(m.rms_px, '.3f')} px "
                 f"(single views {_fmt(m.single_view_rms_px, '.3f')} px)")
    tt = m.turntable
    if tt:
        off = tt.pattern_offset_from_axis_mm
        lines.append(f"turntable       camera {tt.camera_radius_mm:.1f} mm from the axis, "
                     f"{tt.camera_height_mm:.1f} mm above the table; pattern off the axis by "
                     f"({off[0]:.2f}, {off[1]:.2f}) mm")
    exif = dict(m.exif_focal or {})
    for line in (exif.get("note"), focal_warning(K[0, 0], exif or None)):
        if line:
            lines.append(f"warning         {line}")
    for name, why in m.not_estimated.items():
        lines.append(f"note            {name}: {why}")
    for w in m.warnings:
        lines.append(f"warning         {w}")
    for c in m.angle_checks:
        lines.append(f"warning         {c.image}: marks and --step-deg disagree by "
                     f"{c.marks_minus_step_deg:+.2f}°")
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
        from ..intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(args.intrinsics)
    if args.step_deg is not None and not (math.isfinite(args.step_deg) and args.step_deg != 0):
        raise UserError(f"--step-deg must be a non-zero number, got {args.step_deg}")
    pp = tuple(args.principal_point) if args.principal_point else None
    kw = dict(step_deg=args.step_deg, intrinsics=intr, mode=args.mode, principal_point_px=pp,
              distortion="none" if args.no_distortion else "auto")
    progress = Progress(sys.stderr)
    kw["fit_progress"] = fit_reporter(progress, "joint fit")
    with progress.stage("frames") as tick:  # each frame twice: rings, then its own calibration
        if paths is not None:
            seq = calibrate_folder(paths, spec, progress=tick, **kw)
        else:  # the video's frames decoded one at a time, never all held at full resolution
            seq = calibrate_stream(((f.name, f.bgr, f.error) for f in iter_frames(src, args.every, args.frames)),
                                   0, spec, progress=tick, **kw)
    if paths is not None:
        exif = exif_focal_report(paths, seq.intrinsics.width, seq.intrinsics.height, seq.intrinsics.focal_px)
        if exif is not None:
            diagnostics = seq.diagnostics if seq.diagnostics is not None else SequenceDiagnostics()
            seq = dataclasses.replace(seq, diagnostics=dataclasses.replace(diagnostics, exif_focal=exif))
    for f in seq.frames:
        if not f.ok:
            where = src / f.image if paths is not None else f"{src} (frame {f.image})"
            print(f"turntable calibrate-sequence: {where}: {f.status}", file=sys.stderr)
    write_cameras(out, seq)
    print(summary_table(seq))
    print(f"wrote {out}")
    return 0 if all(f.ok for f in seq.frames) else 1
