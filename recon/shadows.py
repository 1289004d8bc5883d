"""Cast shadows: the skirt a shadow held in the silhouettes leaves round an object's foot.

A white object on white paper casts its key light's shadow on the paper, and
the shadow has the object's own grey: the automatic silhouettes hold it where
the object's shaded side shows the same colour. Where every view holds some
of it (under a teapot's overhanging belly, under a chair's seat), the hull
keeps a slab of it: a skirt up to ~20 mm high round the foot (1.23 % of a
teapot's diagonal against 0.37 % from the true silhouettes).

A cast shadow is recognisable all the same:

* **It lies on the plane.** A pixel of it sees the table through no part of
  the hull above ``SKIRT_MM`` (the ray meets the hull, if at all, low down,
  and it only runs lower from there).
* **It is the paper, darker by one factor.** A key light's shadow on the
  paper is the lit paper times one ratio (the ambient light's share) all
  over; shaded parts of the object take every ratio their normals give. The
  ratio is read from the pixels above (grey over the lit paper's grey round
  the object in that view, in the paper's own chromaticity); the sequence's
  most common ratio between ``RATIO_LO`` and ``RATIO_HI`` is the shadow's, if
  it is common enough (``MIN_PEAK_SHARE``).
* **The paper under it stays paper as the table turns.** The plane point
  behind the pixel is the object's own (held, under no high part, neither the
  shadow's grey nor the lit paper's) in at most ``MAX_OWN_SHARE`` of the views
  that see it under no high part: a low part of the object standing on that
  point shows its own shading in most of them (a white box's lower sides, lit
  one way or another as it turns, whose shade matches the shadow's in a few
  views). And in one of the neighbouring views (up to ``NEIGHBOUR_DEG`` of the
  turn away) at least, it is not the object's own.
* **It does not rise.** A pixel of the shadow's grey in an unbroken run of it
  up its image column into the hull above ``SKIRT_MM`` is a face of the
  object (a box's side turned from the light, where the ambient light gives
  a side as much as the paper), not the plane.

A hull voxel below ``SKIRT_MM`` whose pixel is such a shadow in at least
``MIN_VOTES`` views is carved. Then a guard: a silhouette pixel of the
object's own (not the shadow's grey or the lit paper's, nor the penumbra
beside a released shadow) that loses every voxel behind it gets back the
carved voxels on its ray; pieces the carving cut loose that are small, not
counting what the guard gave back (streaks along its rays under a seat), or
that rest on the table wholly under the body (the skirt's centre under a
seat), or float wholly under it where no silhouette pixel of the object's own
needs them (the skirt's rest under a seat, its foot carved), are dropped, and a
carving that would cut the object in two (a piece in the open, or floating
where the masks hold it), or lift it off the table, is not made.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from calib.camera import plane_homography, project_points, values_at_points

from .silhouette_checks import camera_azimuths_deg
from .silhouette_doubt import channel_max
from .silhouette_plates import raster_to_table
from .types import VoxelHull

__all__ = ["Skirt", "carve_cast_shadows", "drop_cut_pieces", "SKIRT_MM", "GUARD_DEPTH_MM"]

SKIRT_MM = 20.0  # the heights a skirt is looked for in
RATIO_LO, RATIO_HI = 0.3, 0.85  # a shadow's grey over the lit paper's, the range searched ...
RATIO_BIN = 0.01  # ... in bins this wide
RATIO_TOL = 0.04  # a pixel is in the shadow within this of the shadow's ratio ...
LIT_TOL = 0.05  # ... and the lit paper within this of 1
MIN_PEAK_SHARE = 0.08  # the shadow's bin holds at least this share of the candidate pixels, ...
MIN_SHADOW_PX = 500  # ... at least this many
CHROMA_TOL = 0.012  # the paper's chromaticity (r, g, b over their sum) within this
PAPER_MARGIN_MM = 30.0  # the lit paper is read on the plane this far round the hull's foot
MIN_VOTES = 3  # a voxel is carved where this many views see a shadow through it
MAX_OWN_SHARE = 0.4  # ... and the plane point under it is the object's own in at most this share of the views
PLANE_PX_PER_MM = 1.0  # (judged on a raster of the plane this fine)
NEIGHBOUR_DEG = 30.0  # the views that check the plane point under a shadow pixel
PENUMBRA_PX = 8  # a shade of the paper this near a released shadow is its penumbra
SMALL_PIECE = 0.02  # a piece cut loose smaller than this share of the largest is dropped (the guard's voxels aside)
UNDER_SHARE = 0.9  # ... and a larger one resting on the table with the body above this share of its columns
UNHELD_PX = 10  # ... or floating there, leaving at most this many of any view's own pixels without a voxel
GUARD_DEPTH_MM = 3.0  # the guard's voxels on a ray, after a slab's wedge is carved: this deep past the first


@dataclass(frozen=True)
class Skirt:
    """What :func:`carve_cast_shadows` carved: the shadow's ratio to the lit paper, the volume (mm^3)
    and the number of views that saw the shadow."""

    ratio: float
    volume_mm3: float
    views: int


def _splat(pts: np.ndarray, K, T, shape, grow: bool = True) -> np.ndarray:
    """(h, w) bool: the pixels of the points with the gaps between voxel centres closed, and grown by a pixel
    all round where ``grow``."""
    cov = np.zeros(shape, np.uint8)
    if len(pts):
        uv = np.rint(project_points(K, T, pts)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] < shape[0])
        cov[uv[ok, 1], uv[ok, 0]] = 1
    if grow:
        cov = cv2.dilate(cov, np.ones((3, 3), np.uint8))
    return cv2.morphologyEx(cov, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)) > 0


def _plane_radius(K, T, shape, step: int = 4) -> np.ndarray:
    """(h, w) float32: the distance from the table's axis of the plane point each pixel's ray meets (1e9 where
    it meets none in front of the camera); computed every ``step`` pixels and interpolated (it is smooth)."""
    H, W = shape
    T = np.asarray(T, float)
    u, v = np.meshgrid(np.arange(0, W + step, step, dtype=np.float64), np.arange(0, H + step, step, dtype=np.float64))
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ T[:3, :3]  # ray directions, table frame
    c = -T[:3, :3].T @ T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -c[1] / d[..., 1]
        r = np.hypot(c[0] + lam * d[..., 0], c[2] + lam * d[..., 2])
    r = np.where((lam > 0) & np.isfinite(r), np.minimum(r, 1e9), 1e9).astype(np.float32)
    full = cv2.resize(r, (r.shape[1] * step, r.shape[0] * step), interpolation=cv2.INTER_LINEAR)
    return full[:H, :W]


@dataclass
class _View:
    held: np.ndarray  # mask | unknown
    high: np.ndarray  # the hull above SKIRT_MM covers the pixel
    paperlike: np.ndarray  # the paper's chromaticity
    ratio: np.ndarray  # grey over the lit paper's
    near: np.ndarray  # the plane point lies on the paper round the foot
    cover: np.ndarray  # the hull covers the pixel


def _view(img, held, high, cover, K, T, radius_mm) -> _View | None:
    r = _plane_radius(K, T, held.shape)
    near = r < radius_mm
    f = img.astype(np.float32)
    grey = f.mean(axis=-1)
    bg = near & ~(cv2.dilate(held.astype(np.uint8), np.ones((11, 11), np.uint8)) > 0)
    if bg.sum() < 100:
        return None
    lit = bg & (grey >= np.percentile(grey[bg], 60))
    paper = f[lit].mean(axis=0)
    if paper.mean() < 20.0:
        return None
    chroma = channel_max(np.abs(f / np.maximum(f.sum(axis=-1, keepdims=True), 1.0) - paper / paper.sum()))
    ratio = cv2.medianBlur(grey, 3) / float(paper.mean())
    return _View(held, high, chroma < CHROMA_TOL, ratio, near, cover)


def _shadow_ratio(views: list[_View]) -> float | None:
    """The sequence's shadow ratio: the most common ratio of the held pixels the hull left without a voxel
    behind them (a shadow one view held, which the others carved: not the object for sure), if common enough;
    failing that, of the held pixels low down (under no part of the hull above ``SKIRT_MM``).

    The held pixels low down come second: a white box's side turned from the light has one grey in every view
    (the ambient light's alone), as common there as a shadow's (the tests that follow keep such a side: it
    rises, and the plane behind it is the box's own). But a soft image's shadow is held by every view alike
    and the hull covers it all: the pixels left uncovered are its penumbra, every ratio from the shadow's to
    the lit paper's (a teapot rendered 1 px out of focus: their best window 0.03 wide held 5.7 %, 8 % asked, while
    the shadow's own held pixels peaked at 0.58 with a third of the low ones)."""
    for held in ((w.held & ~w.cover & w.near & w.paperlike for w in views),
                 (w.held & ~w.high & w.near & w.paperlike for w in views)):
        vals = np.concatenate([w.ratio[h] for w, h in zip(views, held, strict=True)])
        if len(vals) < MIN_SHADOW_PX:
            continue
        hist, edges = np.histogram(vals, bins=np.arange(RATIO_LO, RATIO_HI + 0.5 * RATIO_BIN, RATIO_BIN))
        near3 = np.convolve(hist, np.ones(3), mode="same")  # a peak split between two bins counts whole
        k = int(np.argmax(near3))
        if near3[k] < MIN_PEAK_SHARE * len(vals):
            continue
        centre = edges[k] + 0.5 * RATIO_BIN
        return float(np.median(vals[np.abs(vals - centre) <= 1.5 * RATIO_BIN]))
    return None


def _rising(grey: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels of ``grey`` in an unbroken vertical run of it (an image column) that reaches a
    pixel of ``high``: a face of that grey rising past the skirt's height (a side, not the plane)."""
    H, W = grey.shape
    start = grey.copy()
    start[1:] &= ~grey[:-1]
    run = np.cumsum(start, axis=0) + np.arange(W)[None, :] * (H + 1)  # a label per run of each column
    run = np.where(grey, run, 0)
    hit = np.zeros(W * (H + 1) + H + 2, bool)
    hit[run[grey & high]] = True
    hit[0] = False
    return hit[run]


def _neighbours(az: np.ndarray) -> list[list[int]]:
    """For each view, the views just before and after it in the turn within ``NEIGHBOUR_DEG``."""
    order = np.argsort(az)
    n = len(az)
    out: list[list[int]] = [[] for _ in range(n)]
    for p, i in enumerate(order):
        for q in (order[(p - 1) % n], order[(p + 1) % n]):
            gap = abs((az[q] - az[i] + 180.0) % 360.0 - 180.0)
            if q != i and gap <= NEIGHBOUR_DEG and int(q) not in out[i]:
                out[i].append(int(q))
    return out


def carve_cast_shadows(hull: VoxelHull, images_rgb, masks: np.ndarray, unknown: np.ndarray, K: np.ndarray,
                       Ts: np.ndarray, guard_depth_mm: float | None = None,
                       under: np.ndarray | None = None) -> tuple[VoxelHull, Skirt | None]:
    """The hull without the skirt its silhouettes' held cast shadow left (see the module's docstring).

    ``masks``, ``unknown``: (V, H, W) bool, the automatic silhouettes and their unknown pixels of the views
    ``images_rgb`` (V of (H, W, 3) uint8), cameras ``K``, ``Ts`` (V, 4, 4). ``guard_depth_mm``: the guard gives
    back, on the ray of each pixel it keeps, only the carved voxels this far behind the nearest (None: all of
    them). Returns the hull (the same object where nothing is carved) and what was carved, or None.

    Once the wedge under a slab is carved (:func:`recon.faces.carve_under_slabs`), the skirt under the slab is
    seen: its pixels no longer meet the hull above ``SKIRT_MM``, and a second pass takes it, with the guard
    ``GUARD_DEPTH_MM`` deep. From 20 deg a ray runs ~35 mm through a skirt 12 mm high: the ~10 pixels a view of
    the shadow's soft edge between a chair's legs (0.63-0.85 of the lit paper, counted as the object's own)
    gave the whole skirt back with their whole rays (a white chair from 20 deg: 1.74 % of the diagonal as it
    was, 0.53 % with a voxel 3 mm deep kept behind each).

    ``under`` (bool, the hull's grid; :func:`recon.faces.space_under`): the space under a slab, where the skirt
    is looked for up to the underside; it is low, and its part of the hull hides no pixel (the legs, standing
    from the table up to the underside, are not in it, and stay high). On a light wall a white chair's views
    hold the paper under its seat, lit or in the seat's shadow, as doubt or in the mask, and the hull keeps a
    blob hanging from the seat down to 20-25 mm, below the wedge no view sees (seed 23: 0.68 of its 1.30 % of
    the diagonal); the views see that paper only in strips a few pixels wide between the legs. There a voxel
    takes the votes of every pixel of the shadow's grey or the lit paper's, held, under no high part and not
    rising into one, without the erosion (which left 12-43 % of the blob with three votes, the lit paper
    none); the guard and the cut pieces' checks are the same. Seed 23: 1.30 -> 0.65 %, seed 3 2.19 -> 0.50 %,
    the wedge carved after it.
    """
    vals = np.asarray(hull.values, np.float32)
    inside = vals > 0
    V = len(Ts)
    if not inside.any() or V < MIN_VOTES:
        return hull, None
    o, v = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    Ts = np.asarray(Ts, float)
    idx = np.argwhere(inside)
    y = o[1] + idx[:, 1] * v
    low = y <= SKIRT_MM
    if under is not None:
        low |= under[tuple(idx.T)]
    if not low.any():
        return hull, None
    shell = inside & ~ndimage.binary_erosion(inside)
    sidx = np.argwhere(shell)
    shell_pts = o + sidx * v
    high_sel = shell_pts[:, 1] > SKIRT_MM
    if under is not None:
        high_sel &= ~under[tuple(sidx.T)]
    high_pts = shell_pts[high_sel]
    foot = o + idx[y <= y.min() + 2.0 * v] * v
    radius = float(np.hypot(foot[:, 0], foot[:, 2]).max()) + PAPER_MARGIN_MM
    shape = masks[0].shape
    views: list[_View] = []
    for img, m, u, T in zip(images_rgb, masks, unknown, Ts, strict=True):
        # the high part's image is not grown: from high up, the skirt against the foot under an overhang (a belly,
        # a spout) shows only in the pixel or two just below the overhang's outline
        high = _splat(high_pts, K, T, shape, grow=False)
        w = _view(np.asarray(img), m | u, high, _splat(shell_pts, K, T, shape), K, T, radius)
        if w is None:
            return hull, None
        views.append(w)
    k = _shadow_ratio(views)
    if k is None:
        return hull, None
    shade = [w.paperlike & (w.ratio >= k - RATIO_TOL) for w in views]  # a shade of the paper: shadow to lit
    # the object's own pixels where it stands low: held, under no high part, not a shade of the paper
    own = [w.held & ~w.high & ~(w.paperlike & ((np.abs(w.ratio - k) <= RATIO_TOL) | (np.abs(w.ratio - 1.0) <= LIT_TOL)))
           for w in views]
    Hs = [plane_homography(K, T) for T in Ts]
    nbrs = _neighbours(camera_azimuths_deg(Ts))
    # every view's verdict on each plane point, on a raster of the plane round the foot
    n = int(2 * np.ceil(radius * PLANE_PX_PER_MM) + 1)
    to_plane = [Hm @ raster_to_table(n, PLANE_PX_PER_MM) for Hm in Hs]
    own_n = np.zeros((n, n), np.float32)
    seen_n = np.zeros((n, n), np.float32)
    for w, ow, M in zip(views, own, to_plane, strict=True):
        flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
        own_n += cv2.warpPerspective(ow.astype(np.uint8), M, (n, n), flags=flags, borderValue=0)
        seen_n += cv2.warpPerspective((~w.high).astype(np.uint8), M, (n, n), flags=flags, borderValue=0)
    # a shadow's plane point is the object's own in few of the views that see it; a low part's, in many
    plain = ((own_n <= MAX_OWN_SHARE * seen_n) & (seen_n > 0)).astype(np.uint8)
    low_idx = idx[low]
    low_pts = o + low_idx * v
    votes = np.zeros(len(low_pts), np.int32)
    in_under = np.zeros(len(low_pts), bool) if under is None else under[tuple(low_idx.T)]
    k3 = np.ones((3, 3), np.uint8)
    released = []
    for i, w in enumerate(views):
        grey = w.held & w.paperlike & (np.abs(w.ratio - k) <= RATIO_TOL)
        R = grey & ~w.high & w.near
        grey_rises = _rising(grey, w.high)
        R &= ~grey_rises  # a face of the shadow's grey rising past SKIRT_MM is the object's
        R = cv2.erode(R.astype(np.uint8), k3) > 0
        R &= cv2.warpPerspective(plain, np.linalg.inv(to_plane[i]), (shape[1], shape[0]),
                                 flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0) > 0
        if not nbrs[i]:
            R[:] = False
        both = np.ones(shape, bool)
        for j in nbrs[i]:  # the plane point behind each pixel, in the view next to it: the object's own there?
            M = Hs[j] @ np.linalg.inv(Hs[i])
            both &= cv2.warpPerspective(own[j].astype(np.uint8), M, (shape[1], shape[0]),
                                        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
        R &= ~both
        released.append(R)
        if in_under.any():  # under a slab: the shadow's grey and the lit paper, held, not eroded
            lit = w.held & w.paperlike & (np.abs(w.ratio - 1.0) <= LIT_TOL)
            free = (grey & ~grey_rises) | (lit & ~_rising(lit, w.high))
            free = (free & ~w.high & w.near) | R
            if free.any():
                votes[in_under] += values_at_points(K, Ts[i], low_pts[in_under], free)
        if R.any():
            votes[~in_under] += values_at_points(K, Ts[i], low_pts[~in_under], R)
    carve = votes >= MIN_VOTES
    if not carve.any():
        return hull, None
    cidx = low_idx[carve]
    new = vals.copy()
    new[tuple(cidx.T)] = -0.5 * v
    # the guard: the object's own silhouette pixels must keep a voxel behind them
    forgive = []
    for i, (w, s, o_) in enumerate(zip(views, shade, own, strict=True)):
        beside = cv2.dilate(released[i].astype(np.uint8), np.ones((2 * PENUMBRA_PX + 1,) * 2, np.uint8)) > 0
        forgive.append((cv2.dilate(released[i].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
                       | (w.near & ~o_) | (beside & s))

    def lost_pixels(after: np.ndarray) -> list[np.ndarray]:
        """Per view, the object's own silhouette pixels left with no voxel of ``after`` behind them."""
        after_shell = o + np.argwhere(after & ~ndimage.binary_erosion(after)) * v
        return [masks[i] & ~forgive[i] & w.cover & ~_splat(after_shell, K, T, shape)
                for i, (w, T) in enumerate(zip(views, Ts, strict=True))]

    cpts = o + cidx * v
    restore = np.zeros(len(cidx), bool)
    for lost, T in zip(lost_pixels(new > 0), Ts, strict=True):
        if lost.any():
            back = values_at_points(K, T, cpts, cv2.dilate(lost.astype(np.uint8), k3) > 0)
            if guard_depth_mm is not None and back.any():
                back[back] = _nearest_on_rays(K, T, cpts[back], guard_depth_mm)
            restore |= back
    restored = np.zeros(vals.shape, bool)
    if restore.any():
        r = cidx[restore]
        new[tuple(r.T)] = vals[tuple(r.T)]
        restored[tuple(r.T)] = True
        cidx = cidx[~restore]
        if not len(cidx):
            return hull, None
    def unheld(piece: np.ndarray) -> bool:  # no silhouette pixel of the object's own needs the piece
        return all(int(lost.sum()) <= UNHELD_PX for lost in lost_pixels((new > 0) & ~piece))

    kept = drop_cut_pieces(new, inside, restored, v, unheld)
    if kept is None:
        return hull, None
    carved_n = int(inside.sum() - (kept > 0).sum())
    if carved_n <= 0:
        return hull, None
    out = VoxelHull(values=kept.astype(np.float32), origin_table=hull.origin_table, voxel_mm=hull.voxel_mm,
                    meta=dict(hull.meta))
    return out, Skirt(ratio=k, volume_mm3=carved_n * v ** 3, views=int(sum(r.any() for r in released)))


def _nearest_on_rays(K, T, pts: np.ndarray, depth_mm: float) -> np.ndarray:
    """(N,) bool: the points (N, 3) within ``depth_mm`` (camera z) of the nearest point on the same pixel."""
    T = np.asarray(T, float)
    z = pts @ T[2, :3] + T[2, 3]
    uv = np.rint(project_points(K, T, pts)).astype(np.int64)
    _, pixel = np.unique(uv, axis=0, return_inverse=True)
    pixel = pixel.ravel()
    nearest = np.full(int(pixel.max()) + 1, np.inf)
    np.minimum.at(nearest, pixel, z)
    return z <= nearest[pixel] + depth_mm


def drop_cut_pieces(new: np.ndarray, inside: np.ndarray, restored: np.ndarray, voxel_mm: float,
                    unheld: Callable[[np.ndarray], bool] | None = None) -> np.ndarray | None:
    """The carved grid without the pieces the carving cut loose from the object, or None where it cut off a part.

    ``new``: the carved values (> 0 inside); ``inside``: the hull before carving (bool, the same shape);
    ``restored``: the voxels the guard gave back. A piece cut loose is a crumb when it is smaller than
    ``SMALL_PIECE`` of the largest, not counting the voxels the guard gave back: streaks along the guard's rays
    under a seat, which the skirt's rest joins, are what the rays left of the skirt, not a part (a white chair at
    1280 x 960: five such pieces, 3.7 % of the hull, kept the whole skirt, 2.86 % of the diagonal). A larger piece
    that rests on the table wholly under the body (:func:`_under_the_body`) is the skirt's rest too: the
    centre under a chair's seat, in a shade darker than the shadow's (seed 14: 2.94 % kept whole). So is one
    floating wholly under the body that no silhouette pixel of the object's own needs (``unheld``, given the
    piece: dropped, it leaves none without a voxel behind it): the skirt's rest under a chair's seat whose foot
    the carving took, darker still higher up, which the views hold only as doubt (a white chair on a light wall,
    seed 8: 3.12 % of the diagonal kept whole); a bar between the legs is in the masks. Any other returns
    None: a part the carving cut off. None also where nothing is left, or where the largest piece no longer
    reaches the table (its foot was taken for the shadow).
    """
    lab, n = ndimage.label(new > 0)
    if n == 0:
        return None  # an object lower than SKIRT_MM, all of it taken for the shadow
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    sizes[0] = 0
    big = int(np.argmax(sizes))
    low = int(np.flatnonzero(inside.any(axis=(0, 2)))[0])  # the hull's lowest layer: the table
    out = new.copy()
    if n > 1:
        lab0, _ = ndimage.label(inside)
        labels, first = np.unique(lab.ravel(), return_index=True)
        parent = np.zeros(n + 1, np.int64)
        parent[labels] = lab0.ravel()[first]  # carving only removes: each piece lies in one piece of before
        cut = (parent == parent[big]) & (np.arange(n + 1) != big) & (np.arange(n + 1) > 0)
        own = sizes - np.bincount(lab.ravel(), weights=restored.ravel(), minlength=n + 1).astype(np.int64)
        body_cols = (lab == big).any(axis=1)
        for p in np.flatnonzero(cut & (own >= SMALL_PIECE * sizes[big])):
            piece = lab == p
            if not _under_the_body(piece, body_cols):
                return None  # a part standing in the open (a block beside a post): the carving cut it
            if piece[:, : low + 2, :].any():
                continue  # resting on the table under the body: the skirt's rest
            if unheld is not None and unheld(piece):
                continue  # floating under the body where no silhouette pixel of the object's own needs it
            return None  # floating where the masks hold it (a bar between legs): a part the carving cut off
        crumbs = cut[lab]
        out[crumbs] = np.minimum(out[crumbs], -0.5 * voxel_mm)
    if not (lab[:, : low + 2, :] == big).any():
        return None  # the object no longer stands on the table: its foot was taken for the shadow
    return out


def _under_the_body(piece: np.ndarray, body_cols: np.ndarray) -> bool:
    """Whether the piece (a bool grid) lies wholly under the body: at least ``UNDER_SHARE`` of its columns (x, z)
    hold a voxel of the body (``body_cols``, (x, z) bool), as the rest of a skirt under an overhang does (the
    centre under a chair's seat, in a shade darker than the shadow's, which no rule releases), not a part
    standing on its own (a block beside a post, open to the sky above)."""
    return bool(body_cols[piece.any(axis=1)].mean() >= UNDER_SHARE)
