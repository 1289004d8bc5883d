"""``turntable synth OUT``: render a synthetic turntable sequence with ground truth.

Writes ``OUT/images/``, ``OUT/masks/``, ``OUT/cameras_gt.json``,
``OUT/object_gt.ply`` and ``OUT/scene.json`` (see
:mod:`turntable.synth.sequence`), all at once or not at all.
"""

from __future__ import annotations

import argparse
import logging
import time

from ..errors import UserError

log = logging.getLogger(__name__)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH (e.g. 1280x960), got {text!r}") from None


def _albedo(text: str) -> tuple[float, float, float]:
    named = {"white": (0.85, 0.84, 0.82)}
    if text.lower() in named:
        return named[text.lower()]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise argparse.ArgumentTypeError(f"expected R,G,B in [0, 1] (e.g. 0.85,0.84,0.82) or 'white', got {text!r}")
    return rgb


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT", help="output folder (must not exist or be empty, unless --overwrite)")
    p.add_argument("--object", default="vase",
                   help="built-in object (vase, cup, chair, figure) or a mesh file (+Y up; scaled to fit)")
    p.add_argument("--frames", type=int, default=36, help="number of frames (default 36)")
    p.add_argument("--step-deg", type=float, default=10.0, help="turntable step per frame, degrees (default 10)")
    p.add_argument("--jitter-deg", type=float, default=0.0,
                   help="random error of each frame's turntable angle (std, degrees; default 0)")
    p.add_argument("--size", type=_size, default=(1280, 960), metavar="WxH", help="image size (default 1280x960)")
    p.add_argument("--focal-px", type=float, default=1500.0, help="focal length, pixels (default 1500)")
    p.add_argument("--elevation-deg", type=float, default=30.0,
                   help="camera elevation above the table plane, degrees (default 30)")
    p.add_argument("--distance-mm", type=float, default=450.0,
                   help="camera distance to the table centre, mm (default 450)")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise std at mid-grey, 8-bit DN (default 2)")
    p.add_argument("--blur", type=float, default=0.0, help="Gaussian optical blur sigma, pixels (default 0)")
    p.add_argument("--vignette", type=float, default=0.15,
                   help="fraction of light lost in the image corners (default 0.15)")
    p.add_argument("--jpeg", type=int, default=95, help="JPEG quality 1-100, 0 writes PNG (default 95)")
    p.add_argument("--png", action="store_true", help="write lossless PNG images (same as --jpeg 0)")
    p.add_argument("--backdrop", default="dark", choices=["dark", "light", "colour", "clutter"],
                   help="wall behind the turntable (default dark)")
    p.add_argument("--handheld", action="store_true",
                   help="still table, the camera moves around it (varying azimuth, elevation, distance, roll)")
    p.add_argument("--k1", type=float, default=0.0, help="radial distortion k1 (OpenCV model)")
    p.add_argument("--k2", type=float, default=0.0, help="radial distortion k2 (OpenCV model)")
    p.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"), default=None,
                   help="principal point, pixels (default: image centre)")
    p.add_argument("--r-outer", type=float, default=80.0, help="outer ring centre-line radius, mm (default 80)")
    p.add_argument("--r-inner", type=float, default=50.0, help="inner ring centre-line radius, mm (default 50)")
    p.add_argument("--stroke", type=float, default=3.0, help="ring stroke width, mm (default 3)")
    p.add_argument("--albedo", type=_albedo, default=None, metavar="R,G,B",
                   help="colour the object uniformly with this sRGB albedo in [0, 1] ('white' = 0.85,0.84,0.82) "
                        "instead of the procedural texture")
    p.add_argument("--target-background", default="white", metavar="COLOUR",
                   help="ground colour of the printed target, as `turntable pattern --background` prints it: "
                        "white (default), green, blue, grey or #RRGGBB")
    p.add_argument("--supersample", type=int, default=3, help="rays per pixel per axis at edges (default 3)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT")


def options_from_args(args: argparse.Namespace):
    """:class:`~turntable.synth.sequence.SynthOptions` from parsed arguments; UserError when invalid."""
    from ..synth.sequence import SynthOptions

    w, h = args.size
    try:
        return SynthOptions(
            object=args.object, frames=args.frames, step_deg=args.step_deg, jitter_deg=args.jitter_deg,
            width=w, height=h, focal_px=args.focal_px, elevation_deg=args.elevation_deg,
            distance_mm=args.distance_mm, noise=args.noise, blur_px=args.blur, vignette=args.vignette,
            jpeg=0 if args.png else args.jpeg,
            backdrop=args.backdrop, handheld=args.handheld, k1=args.k1, k2=args.k2,
            principal_point=None if args.principal_point is None else tuple(args.principal_point),
            r_outer=args.r_outer, r_inner=args.r_inner, stroke=args.stroke, seed=args.seed,
            supersample=args.supersample, albedo=args.albedo, target_background=args.target_background)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    opts = options_from_args(args)
    from ..synth.sequence import make_sequence

    t0 = time.perf_counter()
    try:
        out = make_sequence(args.out, opts, overwrite=args.overwrite)
    except FileExistsError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:  # e.g. an unreadable mesh file
        raise UserError(f"{args.object}: {exc}") from None
    log.info("wrote %d frames to %s in %.1f s", opts.frames, out, time.perf_counter() - t0)
    print(f"{out}: {opts.frames} frames, ground truth in cameras_gt.json, masks/, object_gt.ply")
    return 0
