"""``turntable reconstruct``: a folder of turntable photos (or a video) -> VR-ready mesh."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from ..errors import UserError
from ..progress import Progress
from ..reconstruct import ReconstructOptions, reconstruct
from ..worksize import parse_work_size
from .args import add_target_arguments, target_from_args


def add_arguments(parser) -> None:
    parser.add_argument("input", metavar="INPUT", help="folder of images (natural sort) or a video file")
    add_target_arguments(parser, required=False, optional_note="; optional with --cameras")  # see options_from_args
    parser.add_argument("--out", required=True, metavar="OUT", help="output folder")
    add_job_arguments(parser)
    parser.add_argument("--spawn", action="store_true", help="open the Rerun viewer on the recording")
    parser.add_argument("--overwrite", action="store_true", help="recompute every stage")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output")


def add_job_arguments(parser) -> None:
    """What one reconstruction is asked to do beyond INPUT, OUT and the target: shared with ``batch``
    (read back by :func:`options_from_args`)."""
    parser.add_argument("--step-deg", type=float, metavar="D",
                        help="known turntable step per frame (motorised tables); checked against the marks")
    parser.add_argument("--masks", metavar="DIR", help="use these silhouettes (matched to frames by file stem)")
    parser.add_argument("--cameras", metavar="JSON", help="use this cameras.json instead of calibrating")
    parser.add_argument("--intrinsics", metavar="FILE",
                        help="OpenCV calibration (YAML/JSON) to use as known intrinsics")
    parser.add_argument("--resolution", type=int, default=256, metavar="N",
                        help="carving grid resolution (default 256)")
    parser.add_argument("--max-faces", type=int, default=50_000, metavar="N", help="decimate to at most N faces")
    parser.add_argument("--texture-size", type=int, default=2048, metavar="N",
                        help="side of the baked photo texture, texels (power of two, 256-8192)")
    parser.add_argument("--lods", metavar="N,N,...", default="none",
                        help="coarser levels of detail, as face counts below --max-faces (e.g. 10000,2000): "
                             "OUT/model_lod1.glb/.obj, model_lod2... in the same atlas as model.glb, sharing "
                             "model_albedo.png (default: none)")
    parser.add_argument("--no-texture", action="store_true",
                        help="vertex colours only: no UV atlas, no texture (the model before 2026-12)")
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="use every N-th frame (videos, dense folders)")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="use N frames spread evenly over the input (not with --every)")
    parser.add_argument("--max-rejections", type=int, default=None, metavar="K",
                        help="a voxel survives if at most K silhouettes reject it (default: 0 with --masks, whose "
                             "silhouettes are trusted; 1 with automatic ones, so that a hole in one view's "
                             "silhouette cannot bore through the object; the background a view sees round the object, "
                             "past the edge its outline sits on, rejects with K-1)")
    parser.add_argument("--work-size", metavar="N|full",
                        help="long side in pixels of the images silhouettes, stereo and colour work on (rings and "
                             "calibration always use the full photos); 'full' for no reduction (default: photos "
                             "up to 1.3 MP whole, larger ones reduced to about 1.3 MP, keeping the outer ring at "
                             "least 480 px across)")
    parser.add_argument("--no-fusion", action="store_true", help="keep the visual hull only (no stereo)")
    parser.add_argument("--export-colmap", action="store_true", help="also write a COLMAP text model to OUT/colmap")
    parser.add_argument("--export-nerfstudio", action="store_true", help="also write OUT/transforms.json")
    parser.add_argument("--copy-images", action="store_true",
                        help="with the exports: copy the photos used into OUT/images (default: hard links where OUT "
                             "is on the photos' filesystem, copies elsewhere; video frames are always written)")


def options_from_args(args) -> ReconstructOptions:
    if args.resolution < 16 or args.resolution > 1024:
        raise UserError(f"--resolution must be between 16 and 1024, got {args.resolution}")
    if args.max_rejections is not None and args.max_rejections < 0:
        raise UserError(f"--max-rejections must be 0 or more, got {args.max_rejections}")
    if args.max_faces < 100:
        raise UserError(f"--max-faces must be at least 100, got {args.max_faces}")
    texture_size = getattr(args, "texture_size", 2048)
    if texture_size not in {2**k for k in range(8, 14)}:
        raise UserError(f"--texture-size must be a power of two from 256 to 8192, got {texture_size}")
    lods = parse_lods(getattr(args, "lods", None), args.max_faces, texture=not getattr(args, "no_texture", False))
    # fail before the long stages, not after them
    work_size = parse_work_size(getattr(args, "work_size", None))
    if args.step_deg is not None and not (math.isfinite(args.step_deg) and args.step_deg != 0):
        raise UserError(f"--step-deg must be a non-zero number of degrees, got {args.step_deg}")
    if args.r_outer is None or args.r_inner is None:
        if args.cameras is None:
            raise UserError("--r-outer and --r-inner are required: the printed rings calibrate the cameras "
                            "(they may be left out only with --cameras)")
        if (args.r_outer is None) != (args.r_inner is None):
            raise UserError("give both --r-outer and --r-inner, or neither (with --cameras)")
        spec = None
    else:
        spec = target_from_args(args)
    if args.masks and not Path(args.masks).is_dir():
        raise UserError(f"--masks {args.masks}: not a folder")
    for flag, value in (("--cameras", args.cameras), ("--intrinsics", args.intrinsics)):
        if value and not Path(value).is_file():
            raise UserError(f"{flag} {value}: file not found")
    return ReconstructOptions(
        input=Path(args.input), out=Path(args.out), spec=spec, step_deg=args.step_deg,
        masks_dir=Path(args.masks) if args.masks else None, cameras=Path(args.cameras) if args.cameras else None,
        intrinsics=Path(args.intrinsics) if args.intrinsics else None, resolution=args.resolution,
        max_faces=args.max_faces, every=args.every, frames=args.frames, fusion=not args.no_fusion,
        overwrite=args.overwrite,
        spawn=args.spawn, export_colmap=args.export_colmap, export_nerfstudio=args.export_nerfstudio,
        copy_images=args.copy_images,
        max_rejections=args.max_rejections, work_size=work_size,
        texture=not getattr(args, "no_texture", False), texture_size=texture_size, lods=lods)


def parse_lods(value, max_faces: int, texture: bool = True) -> tuple[int, ...]:
    """``--lods``: 'none' (or empty) or comma-separated face counts, each at least 100 and below
    ``max_faces``, returned largest first without repeats."""
    text = "" if value is None else str(value).strip().lower()
    if text in ("", "none", "0"):
        return ()
    try:
        counts = [int(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise UserError(f"--lods must be 'none' or face counts separated by commas (e.g. 10000,2000), "
                        f"got {value!r}") from None
    bad = [n for n in counts if n < 100 or n >= max_faces]
    if bad:
        raise UserError(f"--lods: every level needs at least 100 faces and fewer than --max-faces {max_faces}, "
                        f"got {', '.join(map(str, bad))}")
    if not texture:
        raise UserError("--lods needs the texture: the levels share it (leave out --no-texture)")
    return tuple(sorted(set(counts), reverse=True))


def print_summary(res, stream=None) -> None:
    """Print the run's summary (the same fields as ``OUT/summary.json``)."""
    (stream or sys.stdout).write("\n" + "\n".join(res.summary.lines()) + "\n")


def run(args) -> int:
    opts = options_from_args(args)
    out = opts.out
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is a file, not a folder")
    from ..recording import Recorder

    progress = Progress(enabled=not args.quiet)
    rec = Recorder()  # in memory; reconstruct writes it to OUT/recording.rrd with the other outputs
    try:
        res = reconstruct(opts, progress=progress, recorder=rec)
    finally:
        rec.close()
    print_summary(res)
    if res.failed_checks:
        print(f"turntable reconstruct: FINISHED, BUT THE MODEL FAILED {len(res.failed_checks)} CHECK(S): "
              f"{'; '.join(res.failed_checks)} (every output was written; exit code {res.exit_code})",
              file=sys.stderr)
    if res.unreadable:
        print("turntable reconstruct: some input files could not be read (listed above); "
              "the model was built from the others", file=sys.stderr)
    if opts.spawn:  # the viewer runs on its own; this command does not wait for it
        import subprocess

        from .view import viewer_command

        try:
            subprocess.Popen(viewer_command(out), start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        except (UserError, OSError) as exc:
            print(f"turntable reconstruct: --spawn: could not open the viewer ({exc}); "
                  f"the recording is {out / 'recording.rrd'}", file=sys.stderr)
    return res.exit_code
