"""Automatic object silhouettes for a turntable sequence with a fixed camera.

What calibration knows replaces a global threshold:

* **Where the object can be.** It stands on the table, inside the vertical
  cylinder of radius ``spec.extent_mm`` (+ a margin) above the table, or the
  working volume the caller gives (``radius_mm``, ``height_mm``: real photos
  have no target). The cylinder's image is the convex hull of its projected
  bottom and top circles; every pixel outside it is background for sure.
* **Two background plates.** The camera does not move, so the room (backdrop,
  table top, surroundings) is static in the image: the per-pixel median over
  frames is a *room plate*. The turntable disc and the printed target turn
  with the table, so they are static in the table frame: every frame is
  rectified onto the plane ``Y = 0`` with the plane homography and the median
  over frames there is a *table plate* (angle marks, paper, disc), warped back
  into each frame (near the object, from the views that see each point from
  its own side where the others disagree: see :func:`recon.silhouette_plates.table_plate`). A
  textured object is static in neither: above the plane it moves in the
  rectified frames by parallax, and it turns in the image. A
  plate is trusted at a pixel where most frames agree with it. A plain body of
  revolution is static in the image too (the same picture in every frame):
  when many frames fail their checks, a second pass trusts the room plate
  inside the volume only where it shows colours the room shows outside it.
* **Per-frame evidence.** Where the table plate is trusted it alone decides
  (an object covering the same pixels in most frames makes the room plate
  look like itself, but not the plane behind it); the room plate decides
  elsewhere. A pixel agreeing with a trusted plate (or with a darker copy of
  it: a shadow) is background, one far from it is object (unless a plain
  room shows its colour elsewhere); pixels no plate explains are left to the
  colour models. A darker copy of the paper is a sure shadow only in a colour
  the object's sure pixels do not show (the shaded side of a white object is
  one too), and in a plain room the room plate is sure only in the room's
  colours (a static plain object is part of it); the rest is left to the
  colour models and the outline's edges, and a shadow left in a mask is
  carved by the views that see that part of the paper lit.
* **Refinement.** GrabCut (colour GMMs + graph cut) starts from that labelling
  on the cylinder's bounding box at reduced resolution; back at full
  resolution the outline pixels are decided by their coverage ``alpha`` between
  the plate's colour and the object's colour nearby (``alpha >= 1/2``, the
  ground truth's convention for blended pixels). Then the big components that
  touch the base region are kept and small holes filled.

**Three states.** Besides the mask, each frame has *unknown* pixels: not
confidently background. Confident background is only what the object cannot
fake: a colour the object does not show that a trusted plate matches closely,
or the printed ink of the table plate reproduced (normalised cross-correlation
of its texture). A colour of the object's that matches a plate (a white
object on the white paper), a plate matched only as a shadow or only within
the colour range of a plate edge is doubtful. The unknown pixels are the
doubtful ones joined to the mask without crossing an edge
(:func:`recon.silhouette_doubt.doubt_joined`): the part of a white object
the mask missed joins it through smooth shading, while the wall or paper
of its colour lies beyond its outline's edge (a whole wall left unknown was
never carved above the object). Beyond an edge, doubtful pixels that no
plate vouches for (a static part over the axis: a vase's lip, a figure's
head, which the room plate holds in every frame) are unknown too where they
reach the object (within 0.5 % of the image diagonal) in a fifth of the
views or more, or in four fifths counting the views whose mask holds them
(then within 1.5 times that distance: a head beyond a shaded neck), or,
in a sequence in doubt and once every view has grown so, within 2.5 times
that distance where a fifth of the views hold them (the upper spheres of a
snowman beyond the shaded crease under them)
(:func:`recon.silhouette_doubt.doubt_across`; a poster behind the object
reaches it only while the object turns past), with the doubtful gaps
between them and the object closed; and only where the frame shows the
room plate's colour, as a static part does in every frame (the paper
beside a white box seen edge-on, which the box covers in most frames,
was held as a static part of it). Last, doubtful pixels unlike the
background's own colour (a thin arm whose shading turns across it, all
edge) join where they touch what the frame holds
(:func:`recon.silhouette_doubt.doubt_unlike`), and holes in what the frame
holds that are doubtful throughout and joined to it through smooth shading
on half their rim or more are closed (a white belly's lit side in front of
the paper, :func:`recon.silhouette_doubt.doubt_enclosed`; a view between an
arm and the body is ringed by an edge). Of a static object (a body of
revolution), a pixel that most views show in the room plate's colour and
a fifth of them hold (their masks; their unknown too off the paper) is
unknown in every view that shows it so (:func:`held_alike`): which views
set a white vase's lit foot off from the paper behind it, or its shaded
neck off from a wall of its grey, is chance, and the others carved it.
Of a turning object, a static part that no plate vouches for (a head over
the axis, a plinth's top) and that a fifth of the views alike hold in their
masks is unknown in the views alike that left it out, where it lies within
the wider reach of what they hold (:func:`held_static`).
Last of all, a small hole in what a frame holds that is doubtful throughout
(:func:`recon.silhouette_doubt.doubt_pinholes`) is unknown where its rays
run through what every other view holds (:func:`carved_alone`: a few pixels
of a white belly like the paper behind it, whose ray would carve a thread
through the body); a view between a turning figure's legs, seen through by
the views beside it too, stays open. So is a larger notch of doubtful
pixels, mostly ringed by what the frame holds, whose rays carve (with a
few views on the same side of the turn only) space at least 4 mm inside what
every other view holds (:func:`carved_deep_alone`: a white teapot's lit
shoulder beside its lid, left out across the crease under it in up to seven
neighbouring views, carved hollows through the body); free space shows in
the silhouettes from both sides of the turn. Lower down, where a cast
shadow's skirt is carved by the views that see the paper lit, such a notch
counts only in pixels darker than the lit paper, doubtful or not, and only
as large as a foot (a white teapot's shaded foot on a light wall, 20 deg
up: three neighbouring views took it for its own shadow). Then, where the
hull carved with all views leaves a hole in a view's mask with no voxel
behind it, the voxels on its rays that a sixth of the views or fewer carve are given back to the
views that carved them (:func:`explained_back`: a white plinth's top, taken
for the paper by views on both sides of the turn).
These rules grow by whole pixels, and the pixel past an edge blends both
sides: at the very end, each pixel of the outer layer of what a frame holds
beyond its mask goes to the side that covers most of it, where the object's
colour at the outline and the background's differ
(:func:`recon.silhouette_doubt.blend_behind`).
In a ``"conservative"`` frame,
and in every frame of a sequence with two or more conservative frames,
the doubtful pixels are judged without trusting the mask's colours or a room
plate the object may have polluted. Carving with ``mask | unknown`` rejects a voxel
only where a view is sure. Each frame is checked (empty, touching the image
border along a long stretch, area jumping against its neighbours, outline
support: the ring just outside the outline must sit on an edge and match a
trusted plate where there is one) and kept as ``"ok"``, kept as
``"conservative: ..."``, or ``"rejected: ..."`` (see
:mod:`recon.silhouette_checks`, which also keeps rejected frames where
dropping them would leave more than 30 deg of the turn without a view).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from skimage.morphology import remove_small_objects

from calib.camera import as_K, as_poses, camera_centre_table, project_points, values_at_points
from calib.target import TargetSpec

from .silhouette_checks import area_shortfall, camera_azimuths_deg, camera_spread, camera_still, fill_gaps, frame_status
from .silhouette_doubt import (
    Evidence,
    Plate,
    blend_alpha,
    blend_behind,
    channel_max,
    colour_dist,
    colour_set,
    doubt_across,
    doubt_enclosed,
    doubt_joined,
    doubt_pinholes,
    doubt_unlike,
    doubtful_pixels,
    in_set,
    major_colours,
    range_dist,
    reach,
    rim_counts,
    shadow_dist,
    texture_match,
    window_mean,
)
from .silhouette_plates import (
    PLATE_BORDER_MM,
    STRONG,
    Plates,
    ground_match,
    median_frames,
    moved_pixels,
    moved_window_px,
    rectify_to_table,
    room_off_masks,
)

__all__ = ["SilhouetteResult", "estimate_silhouettes", "paper_pixels", "cylinder_region", "rectify_to_table",
           "worker_threads", "carved_alone"]

_MARGIN_MM = 5.0  # the object may overhang the target's outermost ink by this much
_MIN_TAU = 6.0  # colour distance (0..255 units) below which a pixel agrees with a plate, at least
_WORK_PX = 360_000  # GrabCut runs on at most this many pixels (the region's box, downscaled)
_GRABCUT_SEED = 0  # OpenCV's random generator is seeded with this before every GrabCut: same photos, same masks


@dataclass(frozen=True)
class SilhouetteResult:
    """Silhouettes of a sequence, in three states: object, background, unknown.

    Attributes
    ----------
    masks : (V, H, W) bool
        True on the object.
    unknown : (V, H, W) bool
        Pixels neither confidently object nor background (never overlapping
        ``masks``). Carve with ``masks | unknown``: a view rejects a voxel only
        where it says background with confidence: the doubtful pixels joined
        to the mask without crossing an edge (in a ``"conservative"`` frame
        judged without trusting the mask's colours).
    quality : (V,) float64
        In [0, 1]: the outline support (fraction of a ring two pixels outside
        the outline that looks like background) times an area-consistency
        factor (``min(r, 1/r)``, ``r`` the area over its neighbours' median).
    status : tuple of str
        Per frame ``"ok"``, ``"conservative: <reason>"`` (kept, with a widened
        ``unknown``) or ``"rejected: <reason>"`` (leave the frame out). No gap
        of more than 30 deg of the turn between kept frames is opened by a
        rejection (see :mod:`recon.silhouette_checks`).
    ground : (3,) tuple of float or None
        The chromaticity (``rgb / (r + g + b)``) of the target's printed ground
        where it is coloured (``turntable pattern --background green``) and was
        recognised on the paper; the silhouettes then tell paper from object by
        it next to the object. None on a white or grey ground.
    moved : (V, H, W) bool or None
        Off the turning disc, the pixels where a frame is not the still room
        (:func:`recon.silhouette_plates.moved_pixels`): the object (or its
        shadow) before a static backdrop, whatever its colour. The split of a
        wall's doubt (:func:`turntable.stages.volume.doubt_off_the_outline`)
        never gives them to the wall.
    """

    masks: np.ndarray
    unknown: np.ndarray
    quality: np.ndarray
    status: tuple[str, ...]
    ground: tuple[float, float, float] | None = None
    moved: np.ndarray | None = None


def cylinder_region(K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int], radius_mm: float,
                    height_mm: float) -> np.ndarray:
    """Image (H, W) bool of the cylinder ``r <= radius_mm``, ``0 <= Y <= height_mm`` (table frame).

    The projection of a convex body is the convex hull of its projected
    extreme points: here the bottom and top circles. Points behind the camera
    are dropped (the caller keeps the height below the camera).
    """
    W, H = size
    th = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    ring = np.column_stack([radius_mm * np.cos(th), np.zeros_like(th), radius_mm * np.sin(th)])
    pts = np.vstack([ring, ring + [0.0, height_mm, 0.0]])
    z = pts @ T_cam_table[2, :3] + T_cam_table[2, 3]
    uv = project_points(K, T_cam_table, pts[z > 1e-3])
    uv = np.clip(uv, -4.0 * (W + H), 4.0 * (W + H))
    out = np.zeros((H, W), np.uint8)
    hull = cv2.convexHull(np.round(uv * 16).astype(np.int32))
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def worker_threads(limit: int = 8) -> int:
    """Threads for per-frame work: the cores, at most ``OMP_NUM_THREADS`` where set (``turntable
    --threads N`` sets it), at most ``limit``."""
    n = os.cpu_count() or 1
    omp = os.environ.get("OMP_NUM_THREADS", "")
    if omp.isdigit() and int(omp) > 0:
        n = min(n, int(omp))
    return max(1, min(n, limit))


def _check_inputs(images_rgb, K, T_cam_table):
    imgs = np.asarray(images_rgb)
    if imgs.ndim != 4 or imgs.shape[-1] != 3 or imgs.shape[0] < 1:
        raise ValueError(f"images_rgb: expected (V, H, W, 3), got {imgs.shape}")
    if imgs.dtype != np.uint8:
        raise ValueError(f"images_rgb: expected uint8, got {imgs.dtype}")
    return imgs, as_K(K), as_poses(T_cam_table, imgs.shape[0])


def check_camera_still(T_cam_table: np.ndarray) -> None:
    """Raise ``ValueError`` when the camera moves between frames rather than the table turning under it.

    The background plates assume a camera that stays put while the table
    turns: the room is then the same in every photo and the table's print
    turns with it. Seen from the table, such a camera's centres lie on one
    circle about the axis: a constant height and distance from the axis. A
    camera carried round a still table (``turntable synth --handheld``) breaks both, and
    the automatic silhouettes came out empty (a coloured vase: an error in
    carving) or wrong (a white vase: 20 of 36 frames rejected, the model 22 %
    of its diagonal off, exit 0).
    """
    if len(T_cam_table) < 3 or camera_still(T_cam_table):
        return
    dy, dr, d = camera_spread(T_cam_table)
    raise ValueError(
        f"the camera moves between frames (seen from the table its height varies by {dy:.0f} mm and its "
        f"distance from the axis by {dr:.0f} mm, std, at {d:.0f} mm): automatic silhouettes need a camera "
        "that stays put while the table turns; give --masks")


SEQUENCE_DOUBT = 2  # this many frames conservative: judge every frame's doubt strictly
ACROSS_SHARE = 0.2  # doubt_across: kept where at least this share of the views holds it
ACROSS_HELD = 0.8  # ... or, with the views whose mask holds it, at least this share
ACROSS_FAR = 1.5  # ... and, where the masks hold them in four views of five, within this many times that distance
ACROSS_GAP = 0.005  # ... and reaching the object within this share of the image diagonal (4 px at 640 x 480)
ACROSS_WIDE = 2.5  # ... and, where a fifth of the views hold them by then, within this many times that distance
ALIKE_STATIC = 0.9  # held_alike: an object is static where this share of its masks' core is
TURN_NEAR_DEG = 25.0  # held_between: frames this near in the turn bracket a turning part ...
TURN_SHADE_DN = 60  # ... in a shade this near the frame's own (8-bit, each channel) ...
TURN_MIN_SHARE = 0.02  # ... held where it is a piece beside the mask of at least this share of the mask (a side, not
# the sliver a leg sweeping past leaves)
_PLAIN_ROOM = 0.05  # a room whose colours fill less than this share of the RGB cube is "plain"


def _room_alike_full(plates: Plates, i: int, box, size_hw) -> np.ndarray:
    """(H, W) bool: where frame ``i`` shows the room plate's colour (``plates.room_alike``, on the whole image).

    A static part looks the same in every frame, so it is the room plate there; a pixel beside a turning
    object that its masks hold in most frames (a white box seen edge-on: the paper beside it, which the box
    covers whenever it is turned) shows the paper in this frame, not the plate's box."""
    full = np.zeros(size_hw, bool)
    full[box] = plates.room_alike[i]
    return full


def static_votes(across: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(H, W) bool: where :func:`recon.silhouette_doubt.doubt_across` candidates (V, H, W) are kept.

    A static part reaches the object in every view: across in a fifth of the
    views or more, or across or in the mask in four fifths (a head that
    the mask holds wherever it turns off the axis and that is across, beyond
    the shaded neck, only in the views where it does not); a poster behind
    the object reaches it only while the object turns past.
    """
    return (across.mean(axis=0) >= ACROSS_SHARE) | held_votes(across, masks)


def wide_votes(across: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(H, W) bool: where the wider reach's :func:`recon.silhouette_doubt.doubt_across` candidates (V, H, W) are
    kept: a fifth of the views or more hold the pixel (``held``: mask or unknown) or reach it across.

    A static head whose shade runs through the wall's grey is the room plate's
    in no view and so no view holds it by then; it is across in every view
    whose neck gap is narrow enough (a white figure on a light wall, 640 x 480,
    seed 4: the head missing from the model, 1.75 -> 1.11 % of the diagonal).
    """
    return (across | held).mean(axis=0) >= ACROSS_SHARE


def held_votes(across: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(H, W) bool: across (V, H, W) or in the mask in at least ``ACROSS_HELD`` of the views."""
    return (across | masks).mean(axis=0) >= ACROSS_HELD


ALONE_SAMPLES = 2048  # carved_alone: samples along each ray (at most), a pixel's footprint at the axis apart
ALONE_MIN_SAMPLES = 3  # ... a ray carves alone where this many of them lie in what every other view holds
_ALONE_CHUNK = 1 << 20  # ... samples per pass (24 MiB of points)


def carved_alone(cands: np.ndarray, held: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float,
                 height_mm: float) -> np.ndarray:
    """(V, H, W) bool: the holes ``cands`` (V, H, W) bool through which a view would carve what every other
    view holds.

    ``held`` (V, H, W) bool: what each view holds (mask and unknown). Each
    4-connected component of ``cands[i]`` is tested on its pixels' rays,
    sampled a pixel's footprint at the axis apart (``ALONE_SAMPLES`` at most)
    over the camera's depth range of the working volume (the cylinder
    ``radius_mm``, ``height_mm``): a ray carves alone
    where ``ALONE_MIN_SAMPLES`` of its samples in the volume project into what
    every other view holds (a view not seeing the sample holds it). A
    component is returned where half of its pixels or more carve alone.

    A few pixels of a white vase's lit belly that look exactly like the paper
    behind them leave a pinhole in what a view holds (~25 px at 640 x 480);
    its ray carved a thread through the body, which every other view holds,
    and the threads of 36 views a hollow sheet inside it (a vase on a light
    wall: 1.22 % of the bounding-box diagonal). A view between a turning
    figure's legs is a hole as small in some views, but the views beside
    them see through the same gap and carve it too: not alone, it stays
    open (closing every small doubtful hole raised a mound between the legs).
    """
    V, H, W = held.shape
    out = np.zeros_like(cands)
    Kinv = np.linalg.inv(K)
    span = math.hypot(radius_mm, height_mm)
    azimuth = camera_azimuths_deg(T_cam_table)
    for i in range(V):
        if not cands[i].any():
            continue
        ys, xs = np.nonzero(cands[i])
        apart = np.abs((azimuth - azimuth[i] + 180.0) % 360.0 - 180.0)
        order = [int(j) for j in np.argsort(-apart, kind="stable") if j != i]
        centre = camera_centre_table(T_cam_table[i])
        rays = np.column_stack([xs, ys, np.ones_like(xs)]).astype(float) @ Kinv.T @ T_cam_table[i][:3, :3]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        dist = float(np.linalg.norm(centre))
        step = dist / float(K[0, 0])  # a pixel's footprint at the axis
        depth = np.arange(max(dist - span, 1.0), dist + span, step)[:ALONE_SAMPLES]
        count = np.zeros(len(xs), np.int64)
        chunk = max(1, _ALONE_CHUNK // len(depth))  # rays per pass: bounded memory, however many candidates
        for a in range(0, len(xs), chunk):
            pts = centre + rays[a:a + chunk, None, :] * depth[None, :, None]  # (n, S, 3) table mm
            inside = (np.hypot(pts[..., 0], pts[..., 2]) <= radius_mm) & (pts[..., 1] >= 0.0) \
                & (pts[..., 1] <= height_mm)
            sel = np.nonzero(inside.ravel())[0]
            flat = pts.reshape(-1, 3)[sel]
            for j in order:  # the samples every view so far holds; the opposite views first (they carve most)
                if not len(sel):
                    break
                uv = np.rint(project_points(K, T_cam_table[j], flat)).astype(np.int64)
                seen = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
                hold = np.ones(len(sel), bool)
                hold[seen] = held[j][uv[seen, 1], uv[seen, 0]]
                sel, flat = sel[hold], flat[hold]
            count[a:a + chunk] = np.bincount(sel // len(depth), minlength=inside.shape[0])
        alone = count >= ALONE_MIN_SAMPLES
        n, lab = cv2.connectedComponents(cands[i].astype(np.uint8), connectivity=4)
        comp = lab[ys, xs]
        share = np.bincount(comp, weights=alone, minlength=n) / np.maximum(np.bincount(comp, minlength=n), 1)
        keep = share >= 0.5
        keep[0] = False
        out[i] = keep[lab]
    return out


DEEP_VOXEL_CELLS = 48  # carved_deep_alone: voxels across the working volume's radius
DEEP_VIEW_SHARE = 1 / 6  # ... carved by this share of the views at most (neighbours leave the same part out)
DEEP_STEP_MM = 1.0  # ... then voxels this fine round what all views but those few hold
DEEP_ONE_SIDE = 0.75  # ... and those views on one side of the turn: their azimuths' mean resultant length
DEEP_FLOOR_MM = 20.0  # ... above this height (lower down, a held cast shadow's skirt: recon.shadows)
DEEP_MM = 4.0  # ... a voxel this deep inside what every other view holds (2 mm closed a teapot's handle loop)
DEEP_RIM_HELD = 0.65  # ... drawn where this share of a part's rim is held: a notch, not a sliver
DEEP_LOW_SHARE = 0.03  # ... below DEEP_FLOOR_MM, a notch this share of the view's mask or larger: a foot, not a sliver
DEEP_LOST_SHARE = 0.5  # ... and, in a view whose area dropped against its neighbours', a part joined to what it
# holds that makes up this share of what it lacks, doubtful or not: the part of the object it lost
_DEEP_MAX_VOXELS = 2_000_000  # ... the finer voxels: at most this many (coarser than DEEP_STEP_MM if need be)


def _not_held_counts(held: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, pts: np.ndarray):
    """For points ``pts`` (n, 3) table mm: how many views see them and do not hold them (``held``, V, H, W), and
    the mean resultant length of those views' azimuths round the turn (1: all at one azimuth, 0 for none or
    for views evenly round it)."""
    az = np.deg2rad(camera_azimuths_deg(T_cam_table))
    count = np.zeros(len(pts), np.int16)
    resultant = np.zeros((len(pts), 2))
    for j in range(len(held)):
        free = values_at_points(K, T_cam_table[j], pts, ~held[j])  # a view not seeing a point holds it
        count += free
        resultant[free] += (math.cos(az[j]), math.sin(az[j]))
    return count, np.hypot(resultant[:, 0], resultant[:, 1]) / np.maximum(count, 1)


def _cylinder_cells(lo: np.ndarray, hi: np.ndarray, step: float, radius_mm: float, height_mm: float):
    """Voxel centres (X, Y, Z, 3) table mm, ``step`` apart from ``lo + step / 2`` to below ``hi``, and which of them
    lie in the working volume's cylinder (X, Y, Z) bool; None where the box holds no voxel."""
    axes = [np.arange(lo[k] + step / 2, hi[k], step) for k in range(3)]
    if min(len(a) for a in axes) == 0:
        return None
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    inside = (np.hypot(grid[..., 0], grid[..., 2]) <= radius_mm) & (grid[..., 1] >= 0.0) & (grid[..., 1] <= height_mm)
    return grid, inside


def _enclosed_parts(cand: np.ndarray, held: np.ndarray, thick: bool = False) -> np.ndarray:
    """The 8-connected parts of ``cand`` (h, w) bool whose outer rim (the pixels next to them, not theirs) lies in
    ``held`` (h, w) bool for ``DEEP_RIM_HELD`` of its length or more: a notch into what a view holds, not a
    sliver along its outline. With ``thick``, also the parts whose rim is held for ``THICK_RIM_HELD`` of its
    length and whose area is ``THICK_AREA_PER_RIM`` times that length or more (a disc 8 pixels across): a
    part whose one side is the object's outline, not a sliver."""
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(cand)
    inner, total = rim_counts(lab, n, cand, held)
    keep = inner >= DEEP_RIM_HELD * np.maximum(total, 1)
    if thick:
        area = np.bincount(lab.ravel(), minlength=n)
        keep |= (inner >= THICK_RIM_HELD * np.maximum(total, 1)) & (area >= THICK_AREA_PER_RIM * np.maximum(total, 1))
    keep[0] = False
    return keep[lab]


def _lost_parts(cand: np.ndarray, held: np.ndarray, shortfall_px: float) -> np.ndarray:
    """The 8-connected parts of ``cand`` (h, w) bool next to ``held`` (h, w) bool, each of at least
    ``DEEP_LOST_SHARE`` times ``shortfall_px`` pixels (none where that is 0)."""
    if shortfall_px <= 0:
        return np.zeros_like(cand)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
    beside = np.zeros(n, bool)
    beside[np.unique(lab[(cv2.dilate(held.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & cand])] = True
    keep = beside & (stats[:, cv2.CC_STAT_AREA] >= DEEP_LOST_SHARE * shortfall_px)
    keep[0] = False
    return keep[lab]


def carved_deep_alone(held: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float,
                      height_mm: float, lit: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(high, low)``, each (V, H, W) bool: the pixels of each view whose rays carve, with a few views on the
    same side of the turn, space deep inside what every other view holds; ``high`` from ``DEEP_FLOOR_MM``
    above the table up, ``low`` below it (only with ``lit``).

    ``held`` (V, H, W) bool: what each view holds (mask and unknown). The working volume (the cylinder
    ``radius_mm``, ``height_mm``) is cut into voxels (``DEEP_VOXEL_CELLS`` across its radius, then
    ``DEEP_STEP_MM`` round what all views but a few hold). A voxel is carved from one side where
    ``DEEP_VIEW_SHARE`` of the views or fewer see it and do not hold it, and their azimuths' mean resultant length is
    ``DEEP_ONE_SIDE`` or more. Free space shows in a silhouette from both sides of the turn: a body's outline
    seen from the opposite side is nearly its mirror image, so a tunnel, a handle's loop or the gap between two
    legs is carved by the views at both ends (a resultant near 0). Of the voxels carved from one side, those at
    least ``DEEP_MM`` inside what the other views hold are drawn into each view that carves them (a disc a
    voxel wide round each centre), from ``DEEP_FLOOR_MM`` above the table up into ``high``. Below, a cast
    shadow that the other views hold is carved by the views that see the paper lit (:mod:`recon.shadows` weighs
    it): with ``lit`` ((V, H, W) bool, pixels as bright as each view's lit paper), the voxels there are drawn
    into ``low`` where the view does not see them lit. A white object's shaded foot has its own shadow's grey
    on the paper; a view that took it for the shadow left out a part that the other views hold (a white
    teapot on a light wall, 20 deg up: its shaded foot in three neighbouring views of 35, hollowed 4 mm deep
    under the belly on their side; 1.12 -> 0.94 % of the diagonal given back). The caller keeps of these the
    doubtful pixels (of ``low``: all, in parts of at least ``DEEP_LOW_SHARE`` of the view's mask, a foot and not
    the sliver of shaded paper under a belly) in parts mostly ringed by what the view holds
    (:func:`_enclosed_parts`): beside a white box's top, slivers along the outline through the roof the other
    views leave over it (carved later: ``recon.faces``) were held as well.

    A white teapot's lit shoulder beside its lid has the paper's very grey, across the shaded crease under the
    lid from what the mask holds. At 640 x 480 under some lights a notch of ~500 pixels was left out in seven
    neighbouring views of 36, at the same place, and their rays carved hollows through the body, which every
    other view holds (1.5 % of the diagonal; 0.4 % from the true silhouettes). Of the voxels inside the true
    hull that the views carved, every one was carved by five views or fewer, all on one side (restored:
    0.78 %). The rim a view shapes beside an object (the other views' hull is a polygon round a round body
    there) is a lens about a millimetre thick, not deep. The teapot's handle loop is seen
    through from both sides, but at the loop's inner rim by a few views on one side only: 2 mm deep closed
    the loop in the model, 4 mm leaves it open as before.
    """
    from scipy import ndimage

    V = len(held)
    out = np.zeros_like(held), np.zeros_like(held)
    few_views = int(DEEP_VIEW_SHARE * V)
    if few_views < 1:  # too few views to tell a side that carves alone
        return out
    step = float(radius_mm) / DEEP_VOXEL_CELLS
    lo = np.array([-radius_mm, 0.0, -radius_mm])
    hi = np.array([radius_mm, height_mm, radius_mm])
    for fine in (False, True):
        cells = _cylinder_cells(lo, hi, step, radius_mm, height_mm)
        if cells is None:
            return out
        grid, inside = cells
        pts = grid[inside]
        count, resultant = _not_held_counts(held, K, T_cam_table, pts)
        few = (count >= 1) & (count <= few_views) & (resultant >= DEEP_ONE_SIDE)
        if not few.any():
            return out
        if fine:
            break
        # round what a few views on one side carve, finer
        lo = np.maximum(pts[few].min(axis=0) - step, lo)
        hi = np.minimum(pts[few].max(axis=0) + step, hi)
        step = min(step, max(DEEP_STEP_MM, float(np.prod(hi - lo) / _DEEP_MAX_VOXELS) ** (1.0 / 3.0)))
    others = np.zeros(inside.shape, bool)
    others[inside] = (count == 0) | few
    depth = max(1, int(math.ceil(DEEP_MM / step)))
    deep = ndimage.binary_erosion(others, iterations=depth)[inside] & few
    high = deep & (pts[:, 1] >= DEEP_FLOOR_MM)
    low = deep & ~high
    return (_draw_voxels(pts[high], step, held, K, T_cam_table, only_free=True) if high.any() else out[0],
            _draw_voxels(pts[low], step, held, K, T_cam_table, only_free=True) & ~lit
            if lit is not None and low.any() else out[1])


EXPLAIN_REJECTIONS = 1  # explained_back: the hull keeps a voxel that this many views reject (--max-rejections)
EXPLAIN_OPEN_PX = 3  # ... a mask's pixels with no hull behind them, opened this wide (the outline's blend is not one)
EXPLAIN_SHARE = 1 / 6  # ... get back the voxels their rays meet that this share of the views or fewer carve
EXPLAIN_SEEN = 3 / 4  # ... and that this share of the views or more see (a blob the other views do not see)
EXPLAIN_RIM_HELD = 0.75  # ... from parts of those pixels whose rim the view holds this much: a hole, not a fringe
EXPLAIN_LIT_SHARE = 0.85  # ... and only mask pixels this bright against the lit paper (a cast shadow is darker)
THICK_RIM_HELD = 0.4  # ... and, kept as well, parts of what it draws whose rim the view holds this much ...
THICK_AREA_PER_RIM = 2.0  # ... with this much area per pixel of rim (the blurred plinth's front edge is the outline)
_EXPLAIN_COARSE_CELLS = 24  # (the hull found first on voxels this many across the volume's radius)


def _draw_voxels(pts: np.ndarray, step: float, held: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray,
                 grow: float = 0.5, only_free: bool = False) -> np.ndarray:
    """(V, H, W) bool: the voxels (centres ``pts``, n x 3, edge ``step`` mm) drawn, as discs ``grow`` voxels in
    radius round their centres (the radius of the nearest voxel, for speed), into each view (``held``: V, H, W),
    or with ``only_free`` into each view that does not hold a voxel's centre."""
    V = len(T_cam_table)
    H, W = held.shape[1:]
    out = np.zeros((V, H, W), bool)
    for i in range(V):
        mine = values_at_points(K, T_cam_table[i], pts, ~held[i]) if only_free else np.ones(len(pts), bool)
        if not mine.any():
            continue
        uv = np.rint(project_points(K, T_cam_table[i], pts[mine])).astype(int)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        if not inside.any():
            continue
        dist = np.linalg.norm(pts[mine] - camera_centre_table(T_cam_table[i]), axis=1)
        r = int(math.ceil(grow * step * float(K[0, 0]) / float(dist.min())))
        canvas = np.zeros((H, W), np.uint8)
        canvas[uv[inside, 1], uv[inside, 0]] = 1
        out[i] = cv2.dilate(canvas, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0
    return out


def explained_back(masks: np.ndarray, held: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float,
                   height_mm: float, lit: np.ndarray | None = None) -> np.ndarray:
    """(V, H, W) bool: the pixels of each view whose rays carve what another view's mask needs.

    ``masks``, ``held`` (V, H, W) bool: each view's sure object pixels, and what it holds (mask and unknown).
    The hull keeps a voxel that ``EXPLAIN_REJECTIONS`` views or fewer reject. A mask's pixel (opened by
    ``EXPLAIN_OPEN_PX``: not the outline's blend) with no hull voxel behind it is a sure object pixel that
    other views carved, where it lies in a part of such pixels whose rim the view holds for
    ``EXPLAIN_RIM_HELD`` of its length: a hole the others cut into what the view holds, not a fringe along
    its outline (a cast shadow the mask kept beside a white teapot's belly, whose rays gave back a lens of
    air beside it: 0.68 -> 0.72 % of the diagonal without this), and, with ``lit`` (V, H, W bool), where it is
    as bright as the lit paper (``EXPLAIN_LIT_SHARE``, judged by the caller): a cast shadow under a white
    snowman's lowest sphere, held in its masks, gave back a skirt round its foot (0.44 -> 0.61 %), and under
    a blurred teapot's belly (0.90 -> 1.13 %). Along its ray, the voxels that
    ``EXPLAIN_SHARE`` of the views or fewer carve, and ``EXPLAIN_SEEN`` or more see, are given back: a held
    cast shadow's paper is carved by the many views that see it lit, a blob beside the object by every view
    that sees it. Those voxels are drawn into each view that carves them; the caller keeps the doubtful
    pixels among them, in parts mostly ringed by what the view holds (:func:`_enclosed_parts`). Unlike
    :func:`carved_deep_alone`, the views that carve may stand on both sides of the turn, and the voxels may
    lie low: a mask that needs them is the evidence.

    A white figure's plinth top, 5 mm above the paper and of the paper's very grey: with twice the usual
    noise, or blurred by a pixel (``white_e2e.py --noise 4``, ``--blur 1``), 7 to 12 views of 36 on both
    sides of the turn took it for the paper and carved it away, where up to 14 views' masks held it, the
    hull left behind none of their pixels there. Given back: 1.03 -> 0.71 % (noise, light wall) and
    1.14 / 1.22 -> 0.98 / 1.11 % (blur, dark / light room) of the diagonal.
    """
    V, H, W = held.shape
    out = np.zeros_like(held)
    few_views = int(EXPLAIN_SHARE * V)
    if few_views <= EXPLAIN_REJECTIONS:
        return out
    step = float(radius_mm) / _EXPLAIN_COARSE_CELLS
    lo = np.array([-radius_mm, 0.0, -radius_mm])
    hi = np.array([radius_mm, height_mm, radius_mm])
    for fine in (False, True):  # the hull coarse, then finer round it
        cells = _cylinder_cells(lo, hi, step, radius_mm, height_mm)
        if cells is None:
            return out
        grid, inside = cells
        pts = grid[inside]
        free, seen = np.zeros(len(pts), np.int16), np.zeros(len(pts), np.int16)
        for j in range(V):  # one projection per view: 0 off the image, 1 held, 2 not held
            code = values_at_points(K, T_cam_table[j], pts, np.where(held[j], 1, 2).astype(np.uint8))
            free += code == 2
            seen += code > 0
        count = np.full(inside.shape, V + 1, np.int16)
        count[inside] = free
        hull = count <= EXPLAIN_REJECTIONS
        if not hull.any():
            return out
        if fine:
            break
        near = pts[hull[inside]]
        lo = np.maximum(near.min(axis=0) - 2 * step, lo)
        hi = np.minimum(near.max(axis=0) + 2 * step, hi)
        step = min(step, max(DEEP_STEP_MM, float(np.prod(hi - lo) / _DEEP_MAX_VOXELS) ** (1.0 / 3.0)))
    shape = np.array(count.shape)
    count[inside] = np.where(seen >= EXPLAIN_SEEN * V, free, V + 1)  # too few views see it to tell
    covered = _draw_voxels(grid[hull], step, held, K, T_cam_table, grow=0.75)
    k = np.ones((EXPLAIN_OPEN_PX, EXPLAIN_OPEN_PX), np.uint8)
    back = np.zeros(count.shape, bool)
    Kinv = np.linalg.inv(K)
    for i in range(V):
        lone = masks[i] & ~covered[i] if lit is None else masks[i] & ~covered[i] & lit[i]
        lone = cv2.morphologyEx(lone.astype(np.uint8), cv2.MORPH_OPEN, k) > 0
        n, lab = cv2.connectedComponents(lone.astype(np.uint8), connectivity=8)
        if n <= 1:
            continue
        inner, total = rim_counts(lab, n, lone, held[i])
        enclosed = inner >= EXPLAIN_RIM_HELD * np.maximum(total, 1)
        enclosed[0] = False
        lone = enclosed[lab]
        vs, us = np.nonzero(lone)
        if len(us) == 0:
            continue
        R, C = T_cam_table[i][:3, :3], camera_centre_table(T_cam_table[i])
        d = (R.T @ (Kinv @ np.stack([us, vs, np.ones_like(us)]).astype(np.float64))).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        # the ray's stretch through the grid's box, in half voxels
        far = float(np.linalg.norm(np.maximum(np.abs(lo - C), np.abs(hi - C))))
        near_s = max(0.0, float(np.linalg.norm(C - np.clip(C, lo, hi))))
        s = np.arange(near_s, far, step / 2)
        for rows in np.array_split(np.arange(len(us)), max(1, len(us) * len(s) // 2_000_000 + 1)):
            p = C + s[None, :, None] * d[rows, None, :]
            idx = np.floor((p - lo) / step).astype(int)
            ok = np.all((idx >= 0) & (idx < shape), axis=-1)
            c = np.full(ok.shape, V + 1, np.int16)
            c[ok] = count[tuple(idx[ok].T)]
            take = (c > EXPLAIN_REJECTIONS) & (c <= few_views) & ok
            back[tuple(idx[take].T)] = True
    if not back.any():
        return out
    drawn = _draw_voxels(grid[back], step, held, K, T_cam_table, only_free=True)
    for i in range(V):  # the discs round the voxels' centres leave pinholes between them
        drawn[i] = cv2.morphologyEx(drawn[i].astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    return drawn


def held_between(masks: np.ndarray, azimuths_deg: np.ndarray, images: np.ndarray | None = None) -> np.ndarray:
    """(V, H, W) bool: the pixels that ``masks`` hold both in a frame up to ``TURN_NEAR_DEG`` before each frame and
    in one up to that after it, in the turn (frames ordered by their cameras' azimuths); with ``images`` (V, H, W, 3),
    only where those frames show a colour within ``TURN_SHADE_DN`` of this frame's.

    A turning object's side passes through the room's colour for a frame or two as it turns (a white box's
    shaded side, the wall's very grey, two frames in every half turn: taken for the wall, it was carved
    from the box 42 pixels deep, 3.5 % of the diagonal); the frames either side show it in a shade near it.
    The background behind an object is held by its neighbours only where the object sweeps over it and back,
    and then in the object's colour, not the background's (the dark room between a bunny's two ears)."""
    a = np.mod(np.asarray(azimuths_deg, float), 360.0)
    out = np.zeros_like(masks)
    for i in range(len(masks)):
        d = (a - a[i] + 180.0) % 360.0 - 180.0
        own = None if images is None else images[i].astype(np.int16)
        sides = []
        for near in ((d < 0) & (d >= -TURN_NEAR_DEG), (d > 0) & (d <= TURN_NEAR_DEG)):
            held = masks[near]
            if images is not None:
                shade = channel_max(np.abs(images[near].astype(np.int16) - own))
                held = held & (shade <= TURN_SHADE_DN)
            sides.append(held.any(axis=0))
        out[i] = sides[0] & sides[1]
    return out


def _large_beside(cand: np.ndarray, mask: np.ndarray, min_px: float) -> np.ndarray:
    """The connected parts of ``cand`` of at least ``min_px`` pixels that touch ``mask``."""
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(cand)
    size = np.bincount(lab.ravel(), minlength=n)
    near = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    touch = np.zeros(n, bool)
    touch[lab[near & cand]] = True
    keep = (size >= min_px) & touch
    keep[0] = False
    return keep[lab]


def held_alike(alike: np.ndarray, masks: np.ndarray, doubt: np.ndarray | None = None) -> np.ndarray:
    """(V, H, W) bool: what to hold (unknown) in each view of a static object because other views hold it.

    ``alike``: (V, H, W) bool, where a view shows the pixel's static colour (the room plate's, within the
    noise); ``masks``: (V, H, W) bool, each view's mask; ``doubt``: (V, H, W) bool, unknown pixels that vote
    as the masks do, or None. Of a static object (a body of revolution: ``ALIKE_STATIC`` of the pixels its
    masks hold in half the views or more are static, ``STRONG`` of the views alike), every view shows the
    same picture, and which views set a part off from a backdrop of its colour is chance: a pixel alike in
    ``STRONG`` of the views that a fifth of those views hold (``ACROSS_SHARE``) is held in every view alike
    there. Such a view has the same evidence as they, and carving on it ate what they kept (a white vase
    on a light wall, seed 4: its lit foot in front of the white paper in the masks of 11 views of 36, its
    shaded neck against the wall unknown in as many, both carved by the others: 3.48 % of the diagonal at
    640 x 480; 2.01 % holding what the masks hold, 1.22 % with the unknown off the paper). The caller
    passes the unknown off the table plate's disc only: holding the doubt over the paper added a skirt of
    paper round a 1280 x 960 vase's foot (two pieces). Nothing of a turning object: what a fifth of the
    views left unknown there may be what it passed (the wall behind a white figure's head, 0.97 -> 1.10 %).
    """
    steady = alike.sum(axis=0) >= STRONG * len(alike)
    core = masks.mean(axis=0) >= 0.5
    if (steady & core).sum() < ALIKE_STATIC * max(int(core.sum()), 1):
        return np.zeros_like(alike)
    return alike & _voted_alike(alike, masks if doubt is None else masks | doubt)[None]


def _voted_alike(alike: np.ndarray, votes: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels alike (V, H, W) in ``STRONG`` of the views, a fifth (``ACROSS_SHARE``) of which
    hold them (``votes``, V, H, W) (:func:`held_alike`, :func:`held_static`)."""
    n = alike.sum(axis=0)
    return (n >= STRONG * len(alike)) & ((alike & votes).sum(axis=0) >= ACROSS_SHARE * n)


def held_static(alike: np.ndarray, masks: np.ndarray, cands: np.ndarray) -> np.ndarray:
    """(V, H, W) bool: the candidates ``cands`` (V, H, W: doubtful pixels no plate vouches for) at a static
    part of the object, which other views' masks hold.

    ``alike``: (V, H, W) bool, where a view shows the pixel's static colour (the room plate's, within the
    noise); ``masks``: (V, H, W) bool. A pixel alike in ``STRONG`` of the views shows the same thing in all of
    them: where a fifth of those views (``ACROSS_SHARE``) hold it in their masks, it is a static part of
    the object (a head over the axis), and a view alike there that left it out, across an edge that kept
    it from the mask, has the same evidence. :func:`held_alike` does this for a wholly static object; here
    a turning one's static part is held where no plate vouches for it (a white figure's head over a dark
    wall seen from 20 deg: in its mask in 12 views of 36, beyond its shaded neck in the other 20, which
    carved it off). A poster behind a turning object is what its masks hold only while the
    object covers it, in the object's colours, not alike; the wall or paper of the object's colour is
    vouched for by its plate.
    """
    return cands & alike & _voted_alike(alike, masks)[None]


def _hold_across(base: np.ndarray, cands, doubtful_box: np.ndarray, box) -> np.ndarray:
    """(H, W) bool: ``base`` (a frame's mask and unknown) with the components of each ``(cand, gap_px)``
    within ``gap_px`` of it (:func:`recon.silhouette_doubt.reach`), one pixel further (their outline is an
    edge, its blended pixels are neither side's: doubt_joined), and the doubtful pixels (``doubtful_box``,
    in the slices ``box``) of the gaps between them and the object closed."""
    k3 = np.ones((3, 3), np.uint8)
    grown = base.copy()
    gaps = np.zeros_like(base)
    dk = np.zeros_like(base)
    dk[box] = doubtful_box
    for cand, g in cands:
        if not cand.any():
            continue
        kept = reach(cand, base, g)
        kc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1))
        more = base | (cv2.dilate(kept.astype(np.uint8), k3) > 0)
        closed = cv2.morphologyEx(more.astype(np.uint8), cv2.MORPH_CLOSE, kc) > 0
        gaps |= dk & closed & (cv2.dilate(kept.astype(np.uint8), kc) > 0)
        grown |= more
    return grown | gaps


def _plate_distances(img, room: Plate, table: Plate) -> tuple[np.ndarray, ...]:
    """Each pixel's colour distances to the room and table plates: (range, shadow, own colour) for each.

    They depend on the plates' colours only, not on where a plate is trusted, so
    :func:`_initial_labels` can judge one frame under two trust maps of the room plate
    (``room`` and ``room_verified`` share their colours) at the cost of one.
    """
    return (range_dist(img, room.lo, room.hi), range_dist(img, table.lo, table.hi),
            shadow_dist(img, room.mid), shadow_dist(img, table.mid),
            colour_dist(img, room.mid), colour_dist(img, table.mid))


def _initial_labels(img, region, room: Plate, table: Plate, tau, room_colours,
                    dist: tuple[np.ndarray, ...] | None = None, room_hard: np.ndarray | None = None,
                    ground: tuple[np.ndarray, np.ndarray] | None = None) -> Evidence:
    """GrabCut labels from the plates, and what each pixel's plates say (:class:`Evidence`).

    ``dist``: :func:`_plate_distances` of these plates' colours, when already computed.
    ``ground``: two (h, w) bool, the pixels on the table plate's disc with a coloured printed ground's
    chromaticity (:func:`recon.silhouette_plates.ground_match`), loose (``noise=3``) and strict
    (``noise=1``); None on a white or grey ground.

    Where the table plate is trusted it alone decides: it shows the plane point
    behind the pixel as other views saw it, so an object that covers the same
    pixels in every frame (and makes the room plate look like itself) cannot
    explain itself away there. The room plate decides elsewhere; its
    explanations are only hard where it is background in nearly every frame.
    """
    if dist is None:
        dist = _plate_distances(img, room, table)
    r_range, t_range, r_shadow, t_shadow, r_mid, t_mid = dist
    d_room = np.where(room.trust & ~table.trust, r_range, np.inf)
    d_tab = np.where(table.trust, t_range, np.inf)
    d = np.minimum(d_room, d_tab)
    s_room = np.where(room.trust & ~table.trust, r_shadow, np.inf)
    s_tab = np.where(table.trust, t_shadow, np.inf)
    shadow = np.minimum(s_room, s_tab) < tau
    explained = d < tau
    trusted = room.trust | table.trust
    # A sure object seed must not have a colour a plain room shows elsewhere: a plate polluted by
    # the object in many frames disagrees with the plain backdrop it hides (real photos). A room
    # of many colours (clutter) says little by its colours; an unknown one (the volume fills the
    # image) is taken as all colours.
    sure = trusted & (d > 3.0 * tau) & ~shadow
    if room_colours.mean() < _PLAIN_ROOM or room_colours.all():
        sure &= ~in_set(img, room_colours)
    # A darker copy of the table plate is a shadow on the paper for sure only in a colour the object
    # does not show: the shaded side of a grey or white object on white paper is a darker copy of
    # the paper too (white vase: the whole body below the horizon was taken for shadow).
    if ground is not None:  # a coloured ground where the table plate is trusted: paper in a deep shadow
        sure &= ~(ground[0] & table.trust)
    sure_colours = major_colours(img, sure)
    table_shadow = s_tab < tau
    if sure_colours is not None:
        table_shadow &= ~in_set(img, sure_colours)
    hard = (d_tab < tau) | table_shadow | ((d_room < tau) & (room.strong if room_hard is None else room_hard))
    if ground is not None:
        # where the table plate cannot say (the object hides the paper in most frames), the printed
        # ground's colour can, unless the object shows it: the green disc round a white vase's foot went
        # to the vase (2.3 % of the diagonal). Hard only where the colour is the ground's within the
        # strict tolerance: a looser one took blends along a vase's shaded foot, and GrabCut the side.
        like, strict = (g & ~table.trust & ~sure for g in ground)
        if sure_colours is not None:
            object_like = in_set(img, sure_colours)
            like, strict = like & ~object_like, strict & ~object_like
        explained = explained | like
        hard = hard | strict
    k3 = np.ones((3, 3), np.uint8)
    labels = np.full(img.shape[:2], cv2.GC_PR_FGD, np.uint8)
    labels[explained | shadow] = cv2.GC_PR_BGD
    labels[cv2.erode(hard.astype(np.uint8), k3) > 0] = cv2.GC_BGD  # a plate explains the whole neighbourhood
    labels[sure] = cv2.GC_FGD
    labels[~region] = cv2.GC_BGD
    background = np.where(table.trust[..., None], table.mid, room.mid)
    usable = table.trust | (room.trust & ~table.trust)
    d_mid = np.where(table.trust, t_mid, np.where(room.trust, r_mid, np.inf))
    tight = explained & (d_mid < 2.0 * tau)
    return Evidence(labels, explained, tight, shadow, trusted, trusted & (d > tau) & ~shadow, background, usable)


def _grabcut(img, labels, iterations: int = 2) -> np.ndarray:
    """Foreground probability-like map (h, w) float32 in {0, 1} from GrabCut at reduced resolution."""
    h, w = labels.shape
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not fg.any() or fg.all():
        return fg.astype(np.float32)
    s = min(1.0, math.sqrt(_WORK_PX / (h * w)))
    if s < 1.0:
        size = (max(int(round(w * s)), 8), max(int(round(h * s)), 8))
        small = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        lab = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
    else:
        small, lab = img, labels.copy()
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    # GrabCut starts its colour GMMs with k-means++ drawn from OpenCV's random generator, one per
    # thread: unseeded, a frame's mask depended on which frames its worker thread had cut before.
    cv2.setRNGSeed(_GRABCUT_SEED)
    try:
        # OpenCV's stubs want a rect; None is accepted (and the rect unused) with GC_INIT_WITH_MASK
        cv2.grabCut(np.ascontiguousarray(small[..., ::-1]), lab, None,  # type: ignore[call-overload]
                    bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # a class without samples at this scale
        return fg.astype(np.float32)
    out = ((lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)).astype(np.float32)
    if s < 1.0:
        out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
    return out


def _refine_outline(prob, explained, disagrees, band_px: int) -> np.ndarray:
    """Full-resolution mask: GrabCut's upsampled answer, the plates' near its outline."""
    mask = prob >= 0.5
    k = np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)
    m8 = mask.astype(np.uint8)
    band = (cv2.dilate(m8, k) > 0) & (cv2.erode(m8, k) == 0)
    mask[band & explained] = False
    mask[band & disagrees] = True
    return mask


def _alpha_outline(img, mask, background, usable, tau) -> np.ndarray:
    """Decide the outline pixels by their coverage: ``alpha = (I - B).(F - B) / |F - B|^2 >= 1/2``.

    ``B`` is the plate's background colour, ``F`` the object's colour nearby
    (mean of the mask pixels at least two pixels inside, within 7 x 7); used
    where a plate is trusted and the two colours differ by more than ``3 tau``.
    A blended edge pixel then goes to the side that covers most of it.
    """
    m8 = mask.astype(np.uint8)
    k3 = np.ones((3, 3), np.uint8)
    band = (cv2.dilate(m8, k3) > 0) & (cv2.erode(m8, k3) == 0)
    F, has_F = _object_colour_near(img, mask, 7)
    alpha, decidable = blend_alpha(img.astype(np.float32), F, background.astype(np.float32), tau)
    ok = band & usable & has_F & decidable
    out = mask.copy()
    out[ok] = alpha[ok] >= 0.5
    return out


def _clean(mask: np.ndarray, base: np.ndarray, explained: np.ndarray) -> np.ndarray:
    """Keep the largest component touching the base region (and any a tenth its size) and fill holes.

    An enclosed hole is filled when it is small, or when no trusted plate says
    it shows the background (``explained``, the per-pixel plate match, covers
    less than half of it): a true opening (between a chair's legs, inside a
    handle) shows the room or the table behind, which a plate explains, while a
    patch of the object's texture that merely resembles the backdrop does not.
    """
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask
    touching = np.unique(lab[base & mask])
    touching = touching[touching > 0]
    cand = touching if len(touching) else np.arange(1, n)
    big = stats[cand, cv2.CC_STAT_AREA].max()
    keep = [k for k in cand if stats[k, cv2.CC_STAT_AREA] >= 0.1 * big]
    out = np.isin(lab, keep)
    nh, hl, hs, _ = cv2.connectedComponentsWithStats((~out).astype(np.uint8), connectivity=4)
    if nh <= 1:
        return out
    area = hs[:, cv2.CC_STAT_AREA]
    explained_n = np.bincount(hl.ravel(), weights=explained.ravel().astype(float), minlength=nh)
    explained_share = explained_n / np.maximum(area, 1)
    small = area < max(16, 0.002 * out.sum())
    H, W = out.shape
    for h in range(1, nh):
        x, y, w, hh = hs[h, :4]
        enclosed = x > 0 and y > 0 and x + w < W and y + hh < H  # not the outside
        if enclosed and (small[h] or explained_share[h] < 0.5):
            out[hl == h] = True
    return out


def _object_colour_near(img: np.ndarray, mask: np.ndarray, size: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour (h, w, 3) float32 of the mask pixels at least two pixels inside, within ``size`` x
    ``size``, and where that mean exists (h, w) bool."""
    return window_mean(img, cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0, size)


def _outline_support(img, mask, ev: Evidence, tau) -> float:
    """Fraction of the ring two pixels outside the outline that is clearly background.

    A ring pixel supports the outline when it differs by more than ``3 tau``
    from the object's colour just inside (the outline sits on an edge) and,
    where a plate is trusted, also matches it (or a shadow of it). A pixel
    like the object next to it is ambiguous even where it matches a plate: a
    white object on white paper matches the paper. Where no plate is trusted
    (the object covers those pixels in most frames, so no plate knows what
    lies behind them: typical right next to the object on real photos), the
    edge alone decides: "no plate knows" is no evidence against the outline.
    """
    m8 = mask.astype(np.uint8)
    ring = (cv2.dilate(m8, np.ones((5, 5), np.uint8)) > 0) & (cv2.dilate(m8, np.ones((3, 3), np.uint8)) == 0)
    if not ring.any():
        return 0.0
    F, has_F = _object_colour_near(img, mask)
    edge = has_F & (channel_max(np.abs(img.astype(np.float32) - F)) > 3.0 * tau)
    supported = edge & (ev.explained | ev.shadow | ~ev.trusted)
    return float(supported[ring].mean())


@dataclass(frozen=True)
class _FrameOut:
    mask: np.ndarray  # (h, w) bool
    doubtful: np.ndarray  # (h, w) bool, see doubtful_pixels
    doubtful_strict: np.ndarray  # (h, w) bool, the same with plates_only (for a conservative frame)
    support: float  # see _outline_support
    paper: np.ndarray  # (h, w) bool: the table plate matches closely (see doubt_joined)
    unvouched: np.ndarray  # (h, w) bool: no plate is trusted there, the room's only in the room's colours
    unlike: np.ndarray  # (h, w) bool: not the background's colour (see doubt_unlike)
    on_plate: np.ndarray  # (h, w) bool: the ray meets the plane on the table plate's disc
    background: np.ndarray  # (h, w, 3) uint8: the trusted plate's colour (Evidence.background, verified plates)
    usable: np.ndarray  # (h, w) bool: where ``background`` is meaningful


def _lit_paper(trust: np.ndarray, d_range: np.ndarray, d_mid: np.ndarray, tau: float) -> np.ndarray:
    """Where the trusted table plate explains a pixel as the lit paper: within ``tau`` of its 3 x 3 range and
    ``2 tau`` of its own colour (``d_range``, ``d_mid``: the pixel's distances to them)."""
    return trust & (d_range < tau) & (d_mid < 2.0 * tau)


def _without(plate: Plate, pixels: np.ndarray) -> Plate:
    """``plate`` not trusted at ``pixels``."""
    if not pixels.any():
        return plate
    return dataclasses.replace(plate, trust=plate.trust & ~pixels, strong=plate.strong & ~pixels)


def _frame_mask(img, region, base, plates: Plates, T, tau, verified: bool) -> _FrameOut:
    """Mask of one frame inside the box, the doubtful pixels, and how well its outline is supported.

    ``verified``: trust the room plate inside the volume's image only where its
    colour is one of the room's (see :class:`Plates`).
    """
    h, w = img.shape[:2]
    table = plates.table_in_frame(T, (h, w))
    island = plates.island_in_frame(T, (h, w))
    # An untrusted island of the table plate (recon.silhouette_plates.untrust_enclosed) keeps the plate of the
    # views on its points' own side: for those views it is the paper as they see it (a white vase's foot,
    # hidden from the far side by the belly, ringed by its shadow's sweep on a light wall: no plate vouched
    # for the paper inside the inner ring, and the mask took it whole, 2.3 % of the diagonal at 1280 x 960,
    # seed 2). A raised plain top turning with the table (a plinth) is one plate in every view, not an arc's.
    # For the doubt too: judged untrusted there, the island's paper was doubtful in the views that see it lit,
    # and the hull of that seed's vase kept a skirt round its foot (0.84 -> 1.63 %). Trusted, the shadow by the
    # textured cup's foot turns unknown (~1300 pixels a frame at 1280 x 960), which the cup's fusion keeps
    # (fused/hull 0.29 either way).
    arc_island = island & plates.in_arc_in_frame(T, (h, w)) if island.any() else island
    table_arc = table if not arc_island.any() else \
        dataclasses.replace(table, trust=table.trust | arc_island, strong=table.strong | arc_island)
    room_v = _without(plates.room_verified, island)
    room = room_v if verified else _without(plates.room, island)
    dist = _plate_distances(img, room, table)  # the same for plates.room and plates.room_verified
    on_plate = plates.plate_in_frame(T, (h, w))
    ground = None if plates.ground is None else \
        tuple(on_plate & ground_match(img, plates.ground, tau, noise) for noise in (3.0, 1.0))
    # In a plain room the room plate's explanations are hard only in the room's own colours: inside
    # the volume's image a static object (a plain body of revolution) is part of the plate. (A
    # cluttered room shows too many colours to tell; there the second pass below handles it.)
    plain = plates.room_colours.mean() < _PLAIN_ROOM
    ev = _initial_labels(img, region, room, table_arc, tau, plates.room_colours, dist,
                         room_v.strong if plain else None, ground)
    prob = _grabcut(img, ev.labels)
    scale = math.sqrt(h * w / _WORK_PX)
    mask = _refine_outline(prob, ev.explained, ev.disagrees, band_px=max(2, int(math.ceil(scale)) + 1)) & region
    mask = _alpha_outline(img, mask, ev.background, ev.usable, tau) & region
    mask = _clean(mask, base, ev.explained)
    # For a frame in doubt, the room plate explains only with the room's own colours: it may be
    # the object itself where that covers the same pixels in most frames.
    ev_v = ev if verified else \
        _initial_labels(img, region, room_v, table_arc, tau, plates.room_colours, dist, ground=ground)
    ink = texture_match(img, table_arc, tau)
    if ground is not None and (seen := major_colours(img, mask)) is not None:
        # confident too, as the ink: the printed ground's colour lit or in a shadow, where the mask does not
        # show it (the figure's cast shadow on the green paper was doubtful, not the paper's own colour
        # there, and the unknown took it: a mound round the feet, 1.06 -> 0.97 % on a light wall)
        ink = ink | (ground[1] & ~in_set(img, seen))
    # trusted, not vouched for (a static object?), in a colour the room shows nowhere
    static = plates.room.trust & ~island & ~room_v.trust & ~in_set(img, plates.room_colours)
    return _FrameOut(mask, doubtful_pixels(img, mask, region, ev_v, ink, False, static),
                     doubtful_pixels(img, mask, region, ev_v, ink, True), _outline_support(img, mask, ev, tau),
                     # (on an island too, where its plate comes from the views on the point's own side and
                     # this is one of them: paper round a vase's foot, seen from in front of it; see above)
                     _lit_paper(table_arc.trust, dist[1], dist[5], tau),
                     # off the table plate's disc, or on it where the plate's colour (or a shadow of it) is not
                     # the pixel's (a head above the plane, seen against the table behind the turntable)
                     region & ~(room_v.trust | table.trust)
                     & ~(on_plate & ((dist[1] < tau) | (dist[3] < tau))),
                     (ev_v.trusted & ~ev_v.tight) | (~ev_v.trusted & (dist[4] > 2.0 * tau)), on_plate,
                     ev_v.background.astype(np.uint8), ev_v.usable)


def _moved_joined(held: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """(h, w) bool: the parts of ``cand`` (8-connected) that touch ``held`` (or lie in it), less ``held``
    (:func:`recon.silhouette_doubt.reach`, one pixel, one round, as :func:`~recon.silhouette_doubt.doubt_unlike`)."""
    return reach(cand, held, 1, rounds=1) & ~held


def _keep_joined(held: np.ndarray, mask: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """``drop`` (h, w) bool less the pixels next to a part of ``held`` that dropping them would cut off from
    the mask (a part joined to it through a blended pixel stays joined)."""
    if not drop.any():
        return drop
    n0, lab0 = cv2.connectedComponents(held.astype(np.uint8), connectivity=8)
    joined0 = np.zeros(n0, bool)
    joined0[lab0[mask & held]] = True
    after = held & ~drop
    n1, lab1 = cv2.connectedComponents(after.astype(np.uint8), connectivity=8)
    joined1 = np.zeros(n1, bool)
    joined1[lab1[mask & after]] = True
    was = np.zeros(n1, bool)
    was[lab1[after]] = joined0[lab0[after]]
    cut = after & (was & ~joined1)[lab1]
    if not cut.any():
        return drop
    return drop & (cv2.dilate(cut.astype(np.uint8), np.ones((3, 3), np.uint8)) == 0)


def _noise_tau(samples: np.ndarray) -> float:
    """Agreement threshold from pixels that are background for sure (V, N, 3): 1.5 x the 95th
    percentile of their distance to the median, per frame, median over frames (a bad frame cannot
    inflate it), at least ``_MIN_TAU``."""
    far = colour_dist(samples, median_frames(samples))
    return max(_MIN_TAU, 1.5 * float(np.median(np.percentile(far, 95, axis=1))))


def room_colour_set(imgs: np.ndarray, K: np.ndarray, T: np.ndarray, radius: float, union: np.ndarray) -> np.ndarray:
    """(32, 32, 32) bool: the room's colours (:func:`recon.silhouette_doubt.colour_set`), seen outside the
    working volume's image ``union`` (H, W) and off the table top round it (the paper is the table's); every
    colour where fewer than 100 pixels are left."""
    V, H, W = imgs.shape[:3]
    room = ~union & ~np.any([cylinder_region(K, t, (W, H), radius + PLATE_BORDER_MM, 0.0) for t in T], axis=0)
    return colour_set(imgs[:, room][:, ::7]) if room.sum() >= 100 else np.ones((32, 32, 32), bool)


def plain_room(room_colours: np.ndarray) -> bool:
    """Whether a room's colour set (:func:`room_colour_set`) is plain: its colours say what is not the room."""
    return bool(room_colours.mean() < _PLAIN_ROOM and not room_colours.all())


def _plates(imgs: np.ndarray, K: np.ndarray, T: np.ndarray, radius: float, regions: list[np.ndarray]):
    """The room and table plates of a sequence, or None where the working volume is out of view.

    ``regions``: each view's image of the working volume (:func:`cylinder_region`). Returns ``(box, crops,
    tau, plates, union)``: the box (two slices) round the union of the regions, the frames cropped to it,
    the noise threshold (:func:`_noise_tau`), the :class:`~recon.silhouette_plates.Plates` and the union.
    """
    V, H, W = imgs.shape[:3]
    union = np.any(regions, axis=0)
    if not union.any():
        return None
    rows, cols = np.flatnonzero(union.any(axis=1)), np.flatnonzero(union.any(axis=0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    crops = imgs[:, y0:y1, x0:x1]
    outside = ~union
    samples = imgs[:, outside][:, ::7]
    tau = _noise_tau(samples) if outside.sum() >= 100 else _MIN_TAU
    room_colours = room_colour_set(imgs, K, T, radius, union)
    plates = Plates(crops, imgs, K, T, (y0, x0), radius, tau, union[y0:y1, x0:x1], room_colours)
    return (slice(y0, y1), slice(x0, x1)), crops, tau, plates, union


def paper_pixels(images_rgb: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float,
                 height_mm: float) -> np.ndarray:
    """(V, H, W) bool: the pixels where the photo shows the paper as the other views saw it.

    That is, where the table plate (the target's paper in the table frame, from
    the frames that see each point of it) is trusted and explains the pixel's
    colour closely: the paper lit, not an object in front of it nor a shadow on
    it. The working volume (``radius_mm``, ``height_mm``) is the one
    :func:`estimate_silhouettes` ran in. What a doubtful region of a silhouette
    would give the object is weighed with it (``turntable.stages.volume``): the
    paper is never the object's.
    """
    imgs, K, T = _check_inputs(images_rgb, K, T_cam_table)
    V, H, W = imgs.shape[:3]
    out = np.zeros((V, H, W), bool)
    setup = _plates(imgs, K, T, float(radius_mm), [cylinder_region(K, t, (W, H), float(radius_mm),
                                                                   float(height_mm)) for t in T])
    if setup is None:
        return out
    box, crops, tau, plates, _ = setup
    for i in range(V):
        table = plates.table_in_frame(T[i], crops[i].shape[:2])
        out[(i, *box)] = _lit_paper(table.trust, range_dist(crops[i], table.lo, table.hi),
                                    colour_dist(crops[i], table.mid), tau)
    return out


def estimate_silhouettes(images_rgb: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray,
                         spec: TargetSpec | None = None, *, radius_mm: float | None = None,
                         height_mm: float | None = None,
                         progress: Callable[[int, int], None] | None = None) -> SilhouetteResult:
    """Object silhouettes of a turntable sequence (fixed camera, table turning).

    Parameters
    ----------
    images_rgb : (V, H, W, 3) uint8
        Undistorted RGB frames (denoised first where the camera is noisy:
        :func:`recon.image_edges.quieted`).
    K : (3, 3) float
        Shared intrinsics, pixels.
    T_cam_table : (V, 4, 4) float
        Per-frame pose, table (mm) to camera (mm); the table frame turns with
        the turntable.
    spec : TargetSpec, optional
        The printed target: the object stands inside ``spec.extent_mm`` (+ a
        margin). Not needed when ``radius_mm`` is given.
    radius_mm, height_mm : float, optional
        The working volume: a cylinder about the table +Y axis, ``r <=
        radius_mm``, ``0 <= Y <= height_mm`` (table frame, mm). Default radius:
        the target's extent + 5 mm; default height: the largest height most
        views see.
    progress : callable(done, total), optional
        Called after each frame.

    Returns
    -------
    SilhouetteResult
        Masks, unknown pixels, quality, per-frame status and whether each mask
        reaches the volume's boundary (see :class:`SilhouetteResult`).

    Raises
    ------
    ValueError
        Malformed inputs, or a camera that moves between frames
        (:func:`check_camera_still`).
    """
    imgs, K, T = _check_inputs(images_rgb, K, T_cam_table)
    check_camera_still(T)
    from .carving import largest_visible_height_mm
    from .image_edges import quieted

    imgs = quieted(imgs, T)  # a noisy camera's photos denoised (the outline kept sharp)

    V, H, W = imgs.shape[:3]
    if radius_mm is None and spec is None:
        raise ValueError("estimate_silhouettes: give the target spec or radius_mm")
    # spec is given when radius_mm is not (checked just above)
    radius = float(radius_mm) if radius_mm is not None else float(spec.extent_mm) + _MARGIN_MM  # type: ignore[union-attr]
    height = float(height_mm) if height_mm is not None else largest_visible_height_mm(K, T, W, H)
    regions = [cylinder_region(K, t, (W, H), radius, height) for t in T]
    setup = _plates(imgs, K, T, radius, regions)
    unknown = np.zeros((V, H, W), bool)
    if setup is None:
        return SilhouetteResult(unknown.copy(), unknown, np.zeros(V),
                                ("rejected: the working volume is not in view",) * V, moved=unknown.copy())
    box, crops, tau, plates, union = setup
    bases = [cylinder_region(K, t, (W, H), radius, 0.0)[box] for t in T]
    regions_box = [r[box] for r in regions]
    region_px = np.array([r.sum() for r in regions], float)

    def run(verified: bool, report):
        out: list[_FrameOut] = [None] * V  # type: ignore[list-item]  # one() sets every item

        def one(i: int) -> int:
            out[i] = _frame_mask(crops[i], regions_box[i], bases[i], plates, T[i], tau, verified)
            return i

        # Frames are independent and OpenCV (GrabCut, distance transforms, warps)
        # releases the GIL: one thread per core.
        with ThreadPoolExecutor(max_workers=worker_threads()) as pool:
            for done, _ in enumerate(pool.map(one, range(V)), start=1):
                if report is not None:
                    report(done, V)
        m = np.zeros((V, H, W), bool)
        for i, o in enumerate(out):
            m[(i, *box)] = o.mask
        border = np.array([f[0].sum() + f[-1].sum() + f[:, 0].sum() + f[:, -1].sum() for f in m])
        quality, status = frame_status(m.reshape(V, -1).sum(axis=1), np.array([o.support for o in out]), border,
                                       region_px, (W, H))
        return m, out, quality, status

    masks, outs, quality, status = run(False, progress)
    # A static object (a plain body of revolution: the same image in every frame) is part of the
    # room plate. When many frames fail their checks, try again trusting the room plate inside
    # the volume only where it shows the room's colours, and keep per frame the better result.
    if sum(s != "ok" for s in status) >= max(2, 0.1 * V):
        masks2, outs2, quality2, _ = run(True, None)
        better = quality2 > quality
        masks[better] = masks2[better]
        outs = [o2 if b else o for o, o2, b in zip(outs, outs2, better, strict=True)]
        border = np.array([f[0].sum() + f[-1].sum() + f[:, 0].sum() + f[:, -1].sum() for f in masks])
        quality, status = frame_status(masks.reshape(V, -1).sum(axis=1), np.array([o.support for o in outs]),
                                       border, region_px, (W, H))
    status = fill_gaps(status, camera_azimuths_deg(T))
    used = [i for i in range(V) if status[i].startswith("conservative") or status[i] == "ok"]
    # what turns with the table against the still room, off the disc (which turns too). The room from the frames
    # whose masks leave the pixel (room_off_masks): against the plain median, which shows a white snowman's
    # off-axis head where it stands in most frames, a ring ~5 px wide through which some frames showed the wall
    # had moved, was held, and made the head 4 mm fat on one side (0.41 -> 0.68 % of the diagonal)
    disc = np.any([cylinder_region(K, t, (W, H), radius + PLATE_BORDER_MM, 0.0)[box] for t in T], axis=0)
    room_ref, room_known = room_off_masks(crops, masks[(slice(None), *box)])
    moved = np.zeros((V, H, W), bool)
    moved[(slice(None), *box)] = moved_pixels(crops, room_ref, ~union[box] & ~disc, moved_window_px((W, H))) \
        & ~disc & room_known
    across = np.zeros_like(unknown)
    across_far = np.zeros_like(unknown)
    gap = max(2, round(ACROSS_GAP * math.hypot(W, H)))  # doubt_across: reach across a neck's shaded gap
    far = round(ACROSS_FAR * gap)
    wide = round(ACROSS_WIDE * gap)
    # a sequence with frames in doubt is in doubt as a whole: which of its frames pass the check is chance
    # (a static white vase on a light wall: 2, 12 or 33 of 36 frames under 50 % outline support, from a
    # 0.1 % change of the focal length or of a table-plate texel's trust), and where an ok frame's doubt
    # trusts its mask's colours, the vase's shaded base, missing from them, was carved hollow
    in_doubt = sum(s.startswith("conservative") for s in status) >= SEQUENCE_DOUBT
    across_wide = np.zeros_like(unknown) if in_doubt else None  # the wider reach: only in a sequence in doubt
    doubtful = {i: outs[i].doubtful_strict if in_doubt or status[i].startswith("conservative") else outs[i].doubtful
                for i in used}
    for i in used:
        o = outs[i]
        unknown[(i, *box)] = doubt_joined(crops[i], o.mask, doubtful[i], o.paper, tau, o.background, o.usable,
                                          o.on_plate)
        # and the doubtful pixels that moved against the still room, in parts touching what the view holds: an edge
        # between a chair's seat and the back it joins (the back and the wall both its grey) stopped the doubt's
        # flood, and views that did not hold the back carved it (seed 4 on a light wall: 1.27 % of the diagonal;
        # with this alone 1.03, with the split's use of the same pixels as well 0.64)
        unknown[(i, *box)] |= _moved_joined(o.mask | unknown[(i, *box)], doubtful[i] & moved[(i, *box)])
        across[(i, *box)] = doubt_across(o.mask, unknown[(i, *box)], doubtful[i], o.unvouched, gap)
        across_far[(i, *box)] = doubt_across(o.mask, unknown[(i, *box)], doubtful[i], o.unvouched, far)
        if across_wide is not None:
            across_wide[(i, *box)] = doubt_across(o.mask, unknown[(i, *box)], doubtful[i], o.unvouched, wide)
    if used:  # static parts across an edge: where they reach the object in enough views (doubt_across)
        often = static_votes(across[used], masks[used])
        # further from the object only what the masks hold in nearly every view: a head beyond a neck whose
        # shaded side has the wall's grey for more than the near gap (a poster never gets that far)
        held = held_votes(across_far[used], masks[used])
        for i in used:
            alike = _room_alike_full(plates, i, box, (H, W))
            unknown[i] |= _hold_across(masks[i] | unknown[i], ((across[i] & often & alike, gap),
                                                               (across_far[i] & held & alike, far)),
                                       doubtful[i], box) & union & ~masks[i]
        # then, up to a wider gap, what a fifth of the views hold by now (mask or unknown): a static body
        # shows the same pixels in every view, and whether its shading joins a part to what a view holds
        # is chance (a white snowman on a light wall: its upper spheres held in 16 views of 36, 4.4-6 px
        # beyond the shaded crease under them in the others, which carved them off). Only in a sequence in
        # doubt: run on the rendered textured cup, whose masks are sure, it cost the fusion the cup's carved
        # cavity (fused/hull 0.27 -> 0.65)
        if across_wide is not None:
            wide_ok = wide_votes(across_wide[used], masks[used] | unknown[used])
            for i in used:
                cand = across_wide[i] & wide_ok & ~unknown[i] & _room_alike_full(plates, i, box, (H, W))
                unknown[i] |= _hold_across(masks[i] | unknown[i], ((cand, wide),), doubtful[i], box) \
                    & union & ~masks[i]
    if used:  # static parts the masks of a fifth of the views alike hold (held_static), within the wide gap
        sub = (np.asarray(used), *box)
        cands = np.stack([doubtful[i] & outs[i].unvouched for i in used]) & ~(masks[sub] | unknown[sub])
        static_held = held_static(plates.room_alike[used], masks[sub], cands)
        for k, i in enumerate(used):
            if static_held[k].any():
                cand = np.zeros((H, W), bool)
                cand[box] = static_held[k]
                unknown[i] |= _hold_across(masks[i] | unknown[i], ((cand, wide),), doubtful[i], box) \
                    & union & ~masks[i]
    for i in used:  # thin parts beyond an edge, unlike the background (doubt_unlike); then doubtful holes
        u = unknown[(i, *box)]  # joined through smooth shading (doubt_enclosed)
        u |= doubt_unlike(outs[i].mask, u, doubtful[i], outs[i].unlike)
        u |= doubt_enclosed(crops[i], outs[i].mask | u, doubtful[i], tau, moved=moved[(i, *box)])
    if used:  # equal evidence, equal verdict: what the views showing the same colour hold (held_alike)
        sub = (np.asarray(used), *box)
        # the unknown off the table plate's disc counts as well: the paper round a foot is doubtful in many views
        off_paper = ~np.stack([outs[i].on_plate for i in used])
        hold = held_alike(plates.room_alike[used], masks[sub], unknown[sub] & off_paper)
        for k, i in enumerate(used):
            unknown[(i, *box)] |= hold[k] & regions_box[i] & ~masks[(i, *box)]
        # last, the pinholes in what a view holds (doubt_pinholes) through which it alone would carve (carved_alone):
        # the rays through a few doubtful pixels of a white vase's belly carved a hollow sheet inside it
        holds = masks[used] | unknown[used]
        pins = np.zeros_like(holds)
        for k, i in enumerate(used):
            doubt = np.zeros((H, W), bool)
            doubt[box] = outs[i].doubtful_strict
            pins[k] = doubt_pinholes(holds[k], doubt)
        unknown[used] |= carved_alone(pins, holds, K, T[used], radius, height)
        lit = np.zeros((len(used), H, W), bool)  # pixels as bright as the frame's lit paper, or brighter
        for k, i in enumerate(used):
            grey = crops[i].astype(np.float32).mean(axis=-1)
            paper = outs[i].paper & outs[i].on_plate & ~(masks[(i, *box)] | unknown[(i, *box)])
            if paper.sum() >= 100:
                lit[(k, *box)] = grey >= EXPLAIN_LIT_SHARE * float(np.median(grey[paper]))
        # and the doubtful pixels whose rays carve alone deep into what every other view holds (carved_deep_alone):
        # a notch in a white teapot's lit belly, left out across the crease under its lid; near the table, the
        # pixels darker than the lit paper, doubtful or not, in a notch as large as a foot: a shaded foot taken for
        # its own shadow (a white teapot 20 deg up: ~730 px, 9 % of its mask, in three views), not the sliver of
        # shaded paper under a belly's overhang that a few views on one side see (a bunny: up to 140 px, 1 %,
        # which gave back a skirt round its foot: 0.42 -> 0.47 % of the diagonal)
        # A view whose area dropped against its neighbours' (a conservative frame) may have lost a whole part that
        # it sees against the wall's grey, doubtful or not and not ringed by what it holds: a white figure's
        # torso, head and arm, in one view of 36 on a light wall (1588 px alone carved deep, of the 1800 its mask
        # lacked), carved from the hull (1.86 % of the diagonal). Where what it alone carves deep makes up half
        # of what it lacks, in a part joined to what it holds, that part is held too. Elsewhere such parts are a
        # few slivers beside a box's roof (<= 350 px, under 5 % of what the view lacked).
        deep, low = carved_deep_alone(masks[used] | unknown[used], K, T[used], radius, height, lit)
        shortfall = area_shortfall(masks.reshape(V, -1).sum(axis=1))
        for k, i in enumerate(used):
            d = np.zeros((H, W), bool)
            d[box] = doubtful[i]
            held_i = masks[i] | unknown[i]
            notch = _enclosed_parts(deep[k] & d & ~held_i, held_i) | _lost_parts(deep[k] & ~held_i, held_i,
                                                                                   float(shortfall[i]))
            foot = _enclosed_parts(low[k] & ~held_i, held_i)
            notch |= remove_small_objects(foot, max_size=max(1, int(DEEP_LOW_SHARE * masks[i].sum())), connectivity=2)
            unknown[i] |= notch
        # and, last, the voxels that a few views carve from behind a mask's pixels left with no hull (explained_back):
        # a white figure's plinth top, the paper's very grey, carved by seven views on both sides of the turn
        back = explained_back(masks[used], masks[used] | unknown[used], K, T[used], radius, height, lit)
        for k, i in enumerate(used):
            d = np.zeros((H, W), bool)
            d[box] = doubtful[i]
            unknown[i] |= _enclosed_parts(back[k] & d & ~masks[i] & ~unknown[i], masks[i] | unknown[i], thick=True)
    if used:  # a turning part in the room plate's colour for a frame or two, which the frames either side hold
        sub_used = np.asarray(used)
        between = held_between(masks[sub_used], camera_azimuths_deg(T[sub_used]), imgs[sub_used])
        for k, i in enumerate(used):
            cand = between[k] & _room_alike_full(plates, i, box, (H, W)) & union & ~masks[i] & ~unknown[i]
            unknown[i] |= _large_beside(cand, masks[i], TURN_MIN_SHARE * masks[i].sum())
    # Last, the outline's blended pixels that the rules above added (they grow a held region by whole pixels,
    # and the pixel past an edge blends both sides): each goes to the side that covers most of it
    # (recon.silhouette_doubt.blend_behind). One such pixel all round a thin white figure is ~0.6 mm at 640 x 480:
    # the truth's masks grown by one pixel made its hull 1.05 mm from the truth instead of 0.60 mm.
    for i in used:
        o = outs[i]
        held_i = masks[(i, *box)] | unknown[(i, *box)]
        ring = held_i & (cv2.erode(held_i.astype(np.uint8), np.ones((3, 3), np.uint8)) == 0) & ~o.mask
        # not round a pinhole (doubt_pinholes, which carved_alone weighs): widened, a crack in a body's shading
        # would carve a notch (the line under a static vase's lip, whose verified room plate is its own colour)
        ring &= cv2.dilate(doubt_pinholes(held_i).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0
        unknown[(i, *box)] &= ~_keep_joined(held_i, o.mask, blend_behind(crops[i], held_i & ~ring, ring,
                                                                        o.background, o.usable, tau))
    g = plates.ground
    ground = None if g is None else (float(g[0]), float(g[1]), float(g[2]))
    return SilhouetteResult(masks=masks, unknown=unknown, quality=quality, status=status, ground=ground, moved=moved)
