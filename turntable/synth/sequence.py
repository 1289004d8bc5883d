"""A whole synthetic sequence on disk, with its ground truth.

Turntable mode: the camera is fixed in the world (the room); the turntable, with
the paper target and the object on it, turns by ``step_deg`` per frame plus a
Gaussian error of ``jitter_deg`` (a hand-turned table). The world frame is the
table frame of frame 0. **Angle convention**: frame k's ``angle_deg`` θ_k is the
rotation of the table frame about its +Y axis relative to frame 0, right-handed
(θ > 0 turns the table counter-clockwise seen from above), so

    T_world_table_k = RotY(θ_k),   T_cam_table_k = T_cam_world @ RotY(θ_k),

``RotY(θ) = [[cos θ, 0, sin θ], [0, 1, 0], [-sin θ, 0, cos θ]]``, θ_0 = 0. The
printed target is fixed to the table frame (its 0 deg mark on table +X), so the
object has fixed table coordinates in every frame.

The key light comes from a random direction (per seed) 40-70 deg above the
table on the camera's side and stays fixed in the world, so shading and the
object's shadow on the target move as the table turns.

Hand-held mode: the table stands still (θ_k = 0, world = table frame) and the
camera walks around it: azimuth ``k * step_deg`` + N(0, max(jitter_deg, 2)),
elevation ``elevation_deg`` + N(0, 7) clipped to [12, 75], distance
``distance_mm`` x (1 + N(0, 0.08)) clipped to [0.8, 1.25], roll N(0, 6) (all
degrees), aim point moved by N(0, 5 mm) per axis.

Files written into the output folder (whole or not at all):

``images/frame_000.jpg`` (or ``.png``), ``masks/frame_000.png`` (object
silhouette, uint8 0/255), ``cameras_gt.json`` (schema of
:mod:`turntable.cameras_io`; rms_px NaN, status "ok"; scene facts as extra
top-level keys), ``object_gt.ply`` (GT mesh, table frame, mm, vertex colours),
``scene.json`` (every option and derived value).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.camera import invert_T, look_at, make_T
from calib.target import TargetSpec
from calib.types import FramePose, Intrinsics, SequenceCalibration
from turntable.cameras_io import write_cameras
from turntable.pattern import parse_background

from .objects import OBJECT_NAMES, load_object, make_object, with_uniform_albedo
from .render import render_view
from .scene import BACKDROPS, DISC_THICKNESS_MM, build_scene

__all__ = ["SynthOptions", "make_sequence", "camera_poses", "look_at", "rot_y"]

log = logging.getLogger(__name__)

_BACKDROP_BEHIND_MM = 120.0  # flat backdrop this far behind the turntable's rim (turntable mode)


@dataclass(frozen=True)
class SynthOptions:
    """Everything that defines a synthetic sequence (the CLI options).

    Lengths in mm, angles in degrees, image quantities in pixels. ``object`` is
    a built-in name or a mesh file path. ``jpeg`` is the JPEG quality (1-100),
    0 for PNG. ``noise`` is the sensor noise standard deviation (8-bit DN) at
    mid-grey: a read-noise floor of half of it plus shot noise growing with
    brightness. ``blur_px`` is a Gaussian optical blur (sigma, pixels).
    ``vignette`` is the fraction of light lost in the image corners (falls
    off with the squared distance from the principal point).
    """

    object: str = "vase"
    frames: int = 36
    step_deg: float = 10.0
    jitter_deg: float = 0.0
    width: int = 1280
    height: int = 960
    focal_px: float = 1500.0
    elevation_deg: float = 30.0
    distance_mm: float = 450.0
    noise: float = 2.0
    blur_px: float = 0.0
    vignette: float = 0.15
    jpeg: int = 95
    backdrop: str = "dark"
    handheld: bool = False
    k1: float = 0.0
    k2: float = 0.0
    principal_point: tuple[float, float] | None = None
    r_outer: float = 80.0
    r_inner: float = 50.0
    stroke: float = 3.0
    seed: int = 0
    supersample: int = 3
    albedo: tuple[float, float, float] | None = None  # one sRGB colour in [0, 1] instead of the texture
    target_background: str = "white"  # ground of the printed target: a name or #RRGGBB (turntable.pattern)

    def __post_init__(self) -> None:
        checks = [
            (self.frames >= 1, f"--frames must be >= 1, got {self.frames}"),
            (self.width >= 16 and self.height >= 16, f"--size must be at least 16x16, got {self.width}x{self.height}"),
            (self.focal_px > 0, f"--focal-px must be positive, got {self.focal_px}"),
            (0.0 < self.elevation_deg < 90.0, f"--elevation-deg must be in (0, 90), got {self.elevation_deg}"),
            (self.jitter_deg >= 0, f"--jitter-deg must be >= 0, got {self.jitter_deg}"),
            (self.noise >= 0, f"--noise must be >= 0, got {self.noise}"),
            (self.blur_px >= 0, f"--blur must be >= 0, got {self.blur_px}"),
            (0 <= self.vignette < 1, f"--vignette must be in [0, 1), got {self.vignette}"),
            (self.jpeg == 0 or 1 <= self.jpeg <= 100, f"--jpeg must be 1-100 (or 0 for PNG), got {self.jpeg}"),
            (self.backdrop in BACKDROPS, f"--backdrop must be one of {', '.join(BACKDROPS)}, got {self.backdrop!r}"),
            (1 <= self.supersample <= 8, f"--supersample must be 1-8, got {self.supersample}"),
            (all(math.isfinite(v) for v in (self.step_deg, self.k1, self.k2)), "angles and distortion must be finite"),
            (self.albedo is None or (len(self.albedo) == 3 and all(0.0 <= c <= 1.0 for c in self.albedo)),
             f"--albedo must be three values in [0, 1] (R,G,B), got {self.albedo}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)
        try:
            parse_background(self.target_background)
        except ValueError as exc:
            raise ValueError(f"--target-background {exc}") from None
        spec = self.target_spec()  # raises ValueError for radii that do not fit
        if self.distance_mm <= spec.r_outer_mm + 60.0:
            raise ValueError(f"--distance-mm {self.distance_mm} is too close: the camera must be farther "
                             f"than {spec.r_outer_mm + 60.0:g} mm from the table centre")
        if self.object not in OBJECT_NAMES and not Path(self.object).is_file():
            raise ValueError(f"--object {self.object!r} is neither a built-in ({', '.join(OBJECT_NAMES)}) "
                             "nor a mesh file")
        if self.k1 or self.k2:  # r_d = r (1 + k1 r^2 + k2 r^4) must grow out to the image corners
            cx, cy = self.principal_point or ((self.width - 1) / 2, (self.height - 1) / 2)
            corner = max(np.hypot(u - cx, v - cy) for u in (0, self.width - 1) for v in (0, self.height - 1))
            r2 = np.linspace(0.0, (1.5 * corner / self.focal_px) ** 2, 400)
            if np.any(np.diff(r2 ** 0.5 * (1 + self.k1 * r2 + self.k2 * r2 * r2)) <= 0):
                raise ValueError(f"--k1 {self.k1} --k2 {self.k2}: the distortion folds over inside the image")

    def target_spec(self) -> TargetSpec:
        return TargetSpec(r_outer_mm=float(self.r_outer), r_inner_mm=float(self.r_inner), stroke_mm=float(self.stroke))

    def intrinsics(self) -> Intrinsics:
        dist = [self.k1, self.k2, 0.0, 0.0, 0.0] if (self.k1 or self.k2) else []
        return Intrinsics.from_focal(self.focal_px, self.width, self.height,
                                     principal_point_px=self.principal_point, dist=dist)


def rot_y(theta_rad: float) -> np.ndarray:
    """4x4 rotation by ``theta_rad`` about +Y (right-handed)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return make_T(np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), np.zeros(3))


def camera_poses(opts: SynthOptions, object_height_mm: float, rng: np.random.Generator
                 ) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Per-frame ground truth: angles (deg), ``T_cam_table`` and ``T_world_table``.

    Returns ``angles_deg`` (F,), and two lists of F (4, 4) arrays. See the
    module docstring for the conventions.
    """
    n = opts.frames
    aim = np.array([0.0, float(np.clip(0.3 * object_height_mm, 0.0, 40.0)), 0.0])
    el, d = math.radians(opts.elevation_deg), opts.distance_mm
    if not opts.handheld:
        jitter = rng.normal(0.0, opts.jitter_deg, n) if opts.jitter_deg > 0 else np.zeros(n)
        jitter[0] = 0.0
        angles = np.arange(n) * opts.step_deg + jitter
        T_cam_world = look_at(d * np.array([0.0, math.sin(el), math.cos(el)]), aim)
        T_wt = [rot_y(math.radians(a)) for a in angles]
        return angles, [T_cam_world @ T for T in T_wt], T_wt
    az = np.radians(np.arange(n) * opts.step_deg + rng.normal(0.0, max(opts.jitter_deg, 2.0), n))
    els = np.radians(np.clip(opts.elevation_deg + rng.normal(0.0, 7.0, n), 12.0, 75.0))
    dists = d * np.clip(1.0 + rng.normal(0.0, 0.08, n), 0.8, 1.25)
    rolls = np.radians(rng.normal(0.0, 6.0, n))
    aims = aim + np.column_stack([rng.normal(0, 5, n), rng.normal(0, 5, n), rng.normal(0, 5, n)])
    poses = []
    for k in range(n):
        C = dists[k] * np.array([math.sin(az[k]) * math.cos(els[k]), math.sin(els[k]),
                                 math.cos(az[k]) * math.cos(els[k])])
        poses.append(look_at(C, aims[k], rolls[k]))
    return np.zeros(n), poses, [np.eye(4)] * n


def _light_direction(rng: np.random.Generator) -> np.ndarray:
    """A key light above the table on the camera's side (world frame; the camera of frame 0 is on +Z)."""
    az = math.radians(rng.uniform(-75.0, 75.0))
    el = math.radians(rng.uniform(40.0, 70.0))
    return np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])


def _sensor(rgb: np.ndarray, opts: SynthOptions, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Vignetting and optical blur, then Gaussian read noise plus brightness-dependent shot noise."""
    img = rgb.astype(np.float32)
    if opts.vignette > 0:
        h, w = img.shape[:2]
        du = np.arange(w, dtype=np.float32) - K[0, 2]
        dv = np.arange(h, dtype=np.float32) - K[1, 2]
        r2 = du[None, :] ** 2 + dv[:, None] ** 2
        r2c = max(du[0] ** 2, du[-1] ** 2) + max(dv[0] ** 2, dv[-1] ** 2)
        img *= np.power(1.0 - opts.vignette * r2 / r2c, 1.0 / 2.2)[..., None]  # linear loss, sRGB values
    if opts.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), opts.blur_px)
    if opts.noise > 0:
        read = 0.5 * opts.noise
        gain = (opts.noise ** 2 - read ** 2) / 128.0  # sigma = noise at mid-grey
        sigma = np.sqrt(read ** 2 + gain * img)
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _load_mesh(opts: SynthOptions, rng: np.random.Generator):
    if opts.object in OBJECT_NAMES:
        mesh = make_object(opts.object, rng)
    else:
        spec = opts.target_spec()
        mesh = load_object(opts.object, rng, max_radius_mm=0.85 * (spec.r_inner_mm - spec.stroke_mm / 2))
    return mesh if opts.albedo is None else with_uniform_albedo(mesh, opts.albedo)


def _publish(tmp: Path, out: Path, overwrite: bool) -> None:
    """Move the finished folder ``tmp`` to ``out`` (replacing it only if allowed)."""
    if out.exists():
        if out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        elif overwrite and out.is_dir():
            old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old."))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
            return
        else:
            raise FileExistsError(f"{out}: exists and is not an empty folder (use --overwrite)")
    os.replace(tmp, out)


def make_sequence(out_dir: str | os.PathLike, options: SynthOptions, overwrite: bool = False) -> Path:
    """Render a sequence with ground truth into ``out_dir`` (see the module docstring).

    Everything is written into a hidden temporary folder next to ``out_dir``
    and renamed at the end, so ``out_dir`` holds a whole sequence or nothing
    new. Raises ``FileExistsError`` when ``out_dir`` is a non-empty folder (or a
    file) and ``overwrite`` is false; ``ValueError`` for a mesh file that
    cannot be loaded. Deterministic for ``options.seed``.

    Returns
    -------
    pathlib.Path
        ``out_dir``.
    """
    out = Path(out_dir)
    if out.exists() and not overwrite and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out}: exists and is not an empty folder (use --overwrite)")
    seeds = np.random.SeedSequence(options.seed).spawn(5)
    mesh = _load_mesh(options, np.random.default_rng(seeds[0]))
    spec = options.target_spec()
    intr = options.intrinsics()
    ppm = float(np.clip(1.5 * options.focal_px / (options.distance_mm - spec.r_outer_mm), 2.0, 8.0))
    backdrop_mm = None if options.handheld else _BACKDROP_BEHIND_MM + spec.r_outer_mm + 40.0
    height = float(np.asarray(mesh.vertices)[:, 1].max())
    angles, T_cam_tables, T_world_tables = camera_poses(options, height, np.random.default_rng(seeds[2]))
    # the round wall stands well behind every camera (cameras in world coordinates)
    far = max(np.hypot(*(T_wt @ invert_T(T))[[0, 2], 3]) for T, T_wt in zip(T_cam_tables, T_world_tables, strict=True))
    room_mm = max(700.0, 1.3 * far + 100.0)
    light = _light_direction(np.random.default_rng(seeds[4]))
    scene = build_scene(mesh, spec, options.backdrop, rng=np.random.default_rng(seeds[1]), target_px_per_mm=ppm,
                        backdrop_distance_mm=backdrop_mm, room_radius_mm=room_mm, light_dir_world=light,
                        target_background=parse_background(options.target_background))
    noise_rngs = [np.random.default_rng(s) for s in seeds[3].spawn(options.frames)]
    ext = "png" if options.jpeg == 0 else "jpg"

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp."))
    tmp.chmod(0o755)  # mkdtemp makes it private; the result is an ordinary folder
    try:
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        frames = []
        for k in range(options.frames):
            rgb, mask = render_view(scene, intr.K, T_cam_tables[k], (intr.width, intr.height),
                                    dist=intr.dist if intr.has_distortion else None,
                                    supersample=options.supersample, T_world_table=T_world_tables[k])
            img = _sensor(rgb, options, intr.K, noise_rngs[k])
            name = f"frame_{k:03d}.{ext}"
            params = [cv2.IMWRITE_JPEG_QUALITY, int(options.jpeg)] if ext == "jpg" else []
            if not cv2.imwrite(str(tmp / "images" / name), img[..., ::-1], params):
                raise OSError(f"cannot write {tmp / 'images' / name}")
            cv2.imwrite(str(tmp / "masks" / f"frame_{k:03d}.png"), mask.astype(np.uint8) * 255)
            frames.append(FramePose(image=f"images/{name}", angle_deg=float(angles[k]),
                                    T_cam_table=T_cam_tables[k], rms_px=float("nan"), status="ok"))
            log.info("frame %d/%d rendered", k + 1, options.frames)
        meta = {
            "ground_truth": True,
            "object": options.object,
            "target": {"r_outer_mm": spec.r_outer_mm, "r_inner_mm": spec.r_inner_mm, "stroke_mm": spec.stroke_mm},
            "elevation_deg": options.elevation_deg,
            "distance_mm": options.distance_mm,
            "seed": options.seed,
            "angle_convention": "T_cam_table = T_cam_table0 @ RotY(angle_deg): table frame rotated by angle_deg "
                                "about +Y relative to frame 0 (counter-clockwise seen from above)",
        }
        seq = SequenceCalibration(intrinsics=intr, frames=tuple(frames),
                                  mode="handheld" if options.handheld else "turntable", extra=meta)
        write_cameras(tmp / "cameras_gt.json", seq)
        mesh.export(tmp / "object_gt.ply")
        scene_info = {
            "options": asdict(options),
            "angles_deg": [float(a) for a in angles],
            "target_background_rgb": list(parse_background(options.target_background)),
            "paper_radius_mm": scene.paper_radius_mm,
            "disc_radius_mm": scene.disc_radius_mm,
            "disc_thickness_mm": DISC_THICKNESS_MM,
            "backdrop_distance_mm": backdrop_mm,
            "room_radius_mm": room_mm,
            "target_px_per_mm": ppm,
            "light_dir_world": scene.light_dir_world.tolist(),
            "object_height_mm": height,
            "object_triangles": int(len(mesh.faces)),
            "T_world_table": [np.asarray(T).tolist() for T in T_world_tables],
        }
        (tmp / "scene.json").write_text(json.dumps(scene_info, indent=1) + "\n")
        _publish(tmp, out, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
