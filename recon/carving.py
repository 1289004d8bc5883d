"""Visual hull from silhouettes, carved coarse-to-fine as a signed distance.

Each view ``i`` gives a signed distance to its silhouette boundary, in pixels,
from two Euclidean distance transforms of the mask (positive inside, negative
outside, zero on the boundary between a foreground and a background pixel)::

    s_i(u, v) = dt_in(u, v) - 1/2     for mask pixels
    s_i(u, v) = 1/2 - dt_out(u, v)    for background pixels

A table point ``X`` (mm) projecting to ``(u, v)`` at depth ``z`` gets the view's
vote ``d_i(X) = s_i(u, v) * z / f`` (bilinear lookup, pixels converted to mm
at the point's depth). The hull is the set where every view votes "inside";
tolerating up to ``k`` wrong silhouettes, the voxel's value is the
``(k + 1)``-th smallest vote (``k = max_rejections``)::

    D(X) = min( d_(k+1)(X), region(X) )

where ``region`` is the signed distance to the carving region (a cylinder on
the table plane ``Y = 0`` or a box), so the hull closes flat on the table.
For ``k = 0``, ``D`` is the min over views: a signed distance to the
intersection of the viewing cones up to the cone's slant, so its zero level
set is a sub-voxel surface (no staircase) and ``|D|`` bounds how far the
surface can be, which is what makes the coarse-to-fine refinement safe: a cell
whose ``|D|`` exceeds its half-diagonal (times a margin) cannot contain the
surface, its children inherit its value, and only cells near the zero level
set are evaluated at the next, twice finer, level.

With automatic silhouettes one wrong view is tolerated (``k = 1``), but the
background a view sees *round* the object is not a wrong silhouette: given
``outer_masks`` (each view's silhouette grown over what its outline may have
missed, :func:`held_past_edges`, its holes and narrow bays filled), each view
also votes against those, and ``D`` is the smaller of the above and the
``k``-th smallest of these votes.

Out-of-image policy: a view in which a point projects outside the image (or
behind the camera) cannot reject it (the object may overhang the frame edge
in a few views); a point must however be seen by at least half of the views
(and by more than ``k``), otherwise it is outside.

Memory: the result is a dense float32 grid (``4 N`` bytes for ``N`` voxels:
2.7 GB at resolution 1024 around a vase). Each level is refined in slabs of
about ``_SLAB_VOXELS`` fine voxels (the previous level, 1/8 of the size, is
the only other grid alive) and the result is clipped in place, so the peak
is about ``4.5 N`` bytes plus the views' distance maps and fixed slab
buffers (:func:`hull_peak_bytes`); before the fine grid is allocated it is
compared with the memory available (Linux ``MemAvailable``) and refused
(:class:`HullTooLarge`) when it cannot fit.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable
from dataclasses import replace

import cv2
import numpy as np

from calib.camera import as_K, as_poses

from .image_edges import EDGE_HI, EDGE_LO, edges, smoothed_grey
from .types import VoxelHull

__all__ = ["carve_hull", "silhouette_sdf_px", "fill_enclosed", "held_past_edges", "outer_band_px",
           "largest_visible_radius_mm", "largest_visible_height_mm",
           "largest_carvable_radius_mm", "hull_peak_bytes", "HullTooLarge", "drop_floating_bodies",
           "rejoin_cut_off", "keep_seen_inside"]

_UNSEEN_PX = 1.0e6  # distance-map value that means "this view has no opinion"
_BAND = 1.25 * math.sqrt(3.0) / 2.0  # refine when |D| < _BAND * cell edge (half diagonal + 25 %)
_CHUNK = 1 << 16  # points per evaluation chunk (memory: 3 x views x chunk x 4 B)
_COARSE = 32  # voxels along the longest axis of the coarsest level
_SLAB_VOXELS = 1 << 20  # fine voxels refined per slab (index, point and value buffers: up to ~120 B per voxel)
_SLAB_BYTES = 300 << 20  # one slab's temporaries, an evaluation chunk and allocator slack (measured: 263 MB at 1024)


class HullTooLarge(ValueError):
    """The hull grid at this resolution would not fit in the memory available.

    ``resolution``, ``shape`` (the grid, voxels), ``needed_bytes`` (the
    carve's estimated peak, :func:`hull_peak_bytes`) and ``available_bytes``.
    """

    def __init__(self, resolution: int, shape: Iterable[int], needed_bytes: int, available_bytes: int):
        self.resolution, self.shape = resolution, tuple(int(n) for n in shape)
        self.needed_bytes, self.available_bytes = int(needed_bytes), int(available_bytes)
        super().__init__(
            f"resolution {resolution} needs a {' x '.join(map(str, self.shape))} voxel grid: about "
            f"{needed_bytes / 2**30:.1f} GB to carve and mesh, more than the {available_bytes / 2**30:.1f} GB of "
            f"memory available; use a lower resolution (each halving divides it by 8)")


def memory_available_bytes() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` (Linux), bytes; None where it cannot be read."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


OUTER_BAND = 0.0025  # a view's silhouette outline is doubtful within this share of the image diagonal ...
OUTER_BAND_MIN_PX = 2.0  # ... and this many pixels at least (4 px at 1280 x 960, 2 px at 640 x 480)


def outer_band_px(width: int, height: int) -> float:
    """The band (pixels) round a silhouette of a ``width`` x ``height`` image in which its outline is doubtful."""
    return max(OUTER_BAND_MIN_PX, OUTER_BAND * math.hypot(width, height))


def fill_enclosed(mask: np.ndarray, bay_px: float = 0.0) -> np.ndarray:
    """(H, W) bool: ``mask`` with its enclosed holes filled: the background components (4-connected) that do not
    reach the image's border; first closed with a disc of radius ``bay_px`` (a bay whose mouth is narrower than
    twice that is a hole too)."""
    m = np.asarray(mask, bool)
    if bay_px >= 1.0:
        r = int(round(bay_px))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        pad = cv2.copyMakeBorder(m.astype(np.uint8), r, r, r, r, cv2.BORDER_CONSTANT, value=0)
        m = m | (cv2.morphologyEx(pad, cv2.MORPH_CLOSE, disc)[r:-r, r:-r] > 0)
    from scipy import ndimage

    return ndimage.binary_fill_holes(m)  # the background 4-connected (its default structure)


def held_past_edges(held: np.ndarray, image_rgb: np.ndarray, band_px: float,
                    thresholds: tuple[float, float] = (EDGE_LO, EDGE_HI)) -> np.ndarray:
    """(H, W) bool: ``held`` grown by up to ``band_px`` pixels (4-connected steps) without crossing an edge of
    the image (:func:`recon.image_edges.edges` at ``thresholds``, the sequence's
    :func:`recon.image_edges.edge_thresholds`); the edge pixels it reaches are held too.

    Where a silhouette's outline stops short of the object's (a pixel or two inside it: the edge is still
    ahead), this takes the rest up to the edge; where the outline sits on an edge, or stops on an edge
    beyond the object (doubtful paper ending at the target's printed ring), nothing is added: past it is
    the background the view sees round the object (:func:`carve_hull`'s ``outer_masks``).
    """
    edge = edges(smoothed_grey(image_rgb), thresholds)
    held = np.asarray(held, bool)
    free = ~edge
    reach = held & free
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for _ in range(int(math.ceil(band_px))):
        reach = (cv2.dilate(reach.astype(np.uint8), cross) > 0) & free
    grown = held | reach
    return grown | ((cv2.dilate(grown.astype(np.uint8), cross) > 0) & edge)


def silhouette_sdf_px(mask: np.ndarray, margin_px: int = 64) -> np.ndarray:
    """Signed distance (pixels) to the boundary of a binary silhouette.

    Parameters
    ----------
    mask : (H, W) bool
        True on the object.
    margin_px : int
        The distance transforms run on the mask's bounding box grown by this
        margin (exact there); farther pixels get ``-margin_px`` + 1/2, a lower
        bound of their distance, which is all carving needs that far out.

    Returns
    -------
    (H, W) float32
        Positive inside, negative outside, zero half-way between a foreground
        and a background pixel. An all-foreground mask is +``1e6`` everywhere,
        an all-background one -``1e6`` (no boundary in the image).
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"mask: expected (H, W), got {m.shape}")
    m = m.astype(bool, copy=False)
    if not m.any():
        return np.full(m.shape, -_UNSEEN_PX, np.float32)
    if m.all():
        return np.full(m.shape, _UNSEEN_PX, np.float32)
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    r0, r1 = max(rows[0] - margin_px, 0), min(rows[-1] + margin_px + 1, m.shape[0])
    c0, c1 = max(cols[0] - margin_px, 0), min(cols[-1] + margin_px + 1, m.shape[1])
    crop = np.ascontiguousarray(m[r0:r1, c0:c1], dtype=np.uint8)
    out = np.full(m.shape, 0.5 - margin_px, np.float32)
    if crop.all():  # the object fills its whole box: no background inside it
        out[r0:r1, c0:c1] = np.float32(_UNSEEN_PX)
        return out
    # the crop touches the image border where the mask does: distances stay inside the image
    # The precise transform's distances are between pixel centres, square roots of integers; OpenCV
    # computes them with IPP on one thread (or a crop under 2^14 px) and with its own code on more,
    # equal to an ulp, not to the bit. Snapped to sqrt(round(d^2)), a hull (and everything after it)
    # no longer depends on the thread count (`--threads 1`, a batch job on one core).
    d_in = _exact(cv2.distanceTransform(crop, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    d_out = _exact(cv2.distanceTransform(1 - crop, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    out[r0:r1, c0:c1] = np.where(crop > 0, d_in - 0.5, 0.5 - d_out)
    return out


def _exact(d: np.ndarray) -> np.ndarray:
    """Distances between pixel centres snapped to ``sqrt`` of their integer square (float32)."""
    return np.sqrt(np.rint(d.astype(np.float64) ** 2)).astype(np.float32)


def _check_inputs(masks, K, T_cam_table, max_rejections):
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise ValueError(f"masks: expected (V, H, W), got {masks.shape}")
    K, T = as_K(K), as_poses(T_cam_table, masks.shape[0])
    k = int(max_rejections)
    if not 0 <= k < masks.shape[0]:
        raise ValueError(f"max_rejections must be in [0, {masks.shape[0] - 1}] for {masks.shape[0]} views, got {k}")
    return masks.astype(bool, copy=False), K, T, k


def _visible(K, T, pts_table, width, height):
    """(V, N) bool: point n projects inside image v, in front of the camera."""
    pts_cam = np.einsum("vij,nj->vni", T[:, :3, :3], pts_table) + T[:, None, :3, 3]
    z = pts_cam[..., 2]
    uvw = pts_cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[..., 0] / uvw[..., 2], uvw[..., 1] / uvw[..., 2]
    return (z > 0) & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)


def largest_visible_radius_mm(K, T_cam_table, width: int, height: int) -> float:
    """Radius (mm) of the largest table circle about the origin seen whole in every view.

    ``K`` (3, 3) pixels, ``T_cam_table`` (V, 4, 4); 0 when even the centre is unseen.
    """
    T = np.asarray(T_cam_table, float).reshape(-1, 4, 4)
    th = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    best = 0.0
    for r in np.linspace(0.0, np.linalg.norm(T[:, :3, 3], axis=1).max(), 257):
        circle = np.column_stack([r * np.cos(th), np.zeros_like(th), r * np.sin(th)])
        if not _visible(K, T, circle, width, height).all():
            break
        best = float(r)
    return best


def largest_visible_height_mm(K, T_cam_table, width: int, height: int) -> float:
    """Height (mm) up the table axis that at least half of the views still see.

    The highest point ``(0, h, 0)`` projecting inside the image in most views:
    an object taller than that cannot be carved from these views anyway.
    """
    T = np.asarray(T_cam_table, float).reshape(-1, 4, 4)
    hs = np.linspace(0.0, 2.0 * np.linalg.norm(T[:, :3, 3], axis=1).max(), 513)
    axis = np.column_stack([np.zeros_like(hs), hs, np.zeros_like(hs)])
    frac = _visible(K, T, axis, width, height).mean(axis=0)
    below = np.flatnonzero(frac < 0.5)
    return float(hs[below[0] - 1] if below.size and below[0] > 0 else (0.0 if below.size else hs[-1]))


def largest_carvable_radius_mm(K, T_cam_table, width: int, height: int, height_mm: float) -> float:
    """Radius (mm) of the largest cylinder on the table that carving can still decide.

    Carving needs a point inside at least half of the views (see the module
    docstring): this is the largest ``r`` for which every point of the
    cylinder's wall is (sampled every 5 deg at ``Y = 0, h/4, h/2, 3h/4`` for
    ``h = height_mm``; the top, where ``largest_visible_height_mm`` puts it, is
    at that limit already on the axis). The working volume can grow up to
    this radius, no further; 0 when the axis itself is not seen.
    """
    K, T = as_K(K), as_poses(T_cam_table)
    th = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    ys = np.linspace(0.0, 0.75 * max(float(height_mm), 0.0), 4)
    need = (len(T) + 1) // 2
    best = 0.0
    for r in np.linspace(0.0, 2.0 * np.linalg.norm(T[:, :3, 3], axis=1).max(), 513):
        wall = np.array([[r * math.cos(a), y, r * math.sin(a)] for y in ys for a in th])
        if (_visible(K, T, wall, width, height).sum(axis=0) < need).any():
            break
        best = float(r)
    return best


class _Region:
    """Carving region: a vertical cylinder on the table, or an axis-aligned box (table frame, mm)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, radius_mm: float | None):
        self.lo = np.asarray(lo, float)
        self.hi = np.asarray(hi, float)
        self.radius_mm = radius_mm

    def sdf(self, pts: np.ndarray) -> np.ndarray:
        """Signed distance (N,) mm, positive inside (exact for the box faces and the cylinder wall)."""
        d_lo = pts - self.lo.astype(np.float32)
        d_hi = self.hi.astype(np.float32) - pts
        if self.radius_mm is None:
            return np.minimum(d_lo, d_hi).min(axis=1)
        wall = np.float32(self.radius_mm) - np.hypot(pts[:, 0], pts[:, 2])
        return np.minimum(wall, np.minimum(d_lo[:, 1], d_hi[:, 1]))

    def touching(self, pts: np.ndarray, tol_mm: float) -> tuple[int, int]:
        """How many of ``pts`` (N, 3) lie within ``tol_mm`` of the side wall and of the top.

        For a box region the side is its four vertical faces. The bottom
        (the table, ``Y = lo``) is where an object stands: never counted.
        """
        if self.radius_mm is None:
            side = np.minimum(pts[:, [0, 2]] - self.lo[[0, 2]], self.hi[[0, 2]] - pts[:, [0, 2]]).min(axis=1)
        else:
            side = self.radius_mm - np.hypot(pts[:, 0], pts[:, 2])
        top = self.hi[1] - pts[:, 1]
        return int(np.count_nonzero(side < tol_mm)), int(np.count_nonzero(top < tol_mm))


def _make_region(bounds_table, radius_mm, height_mm, K, T, width, height) -> _Region:
    if bounds_table is not None:
        b = np.asarray(bounds_table, dtype=np.float64)
        if b.shape != (2, 3) or not np.all(b[1] > b[0]):
            raise ValueError(f"bounds_table: expected (2, 3) [min, max] with max > min, got {b.tolist()}")
        return _Region(b[0], b[1], None)
    r = largest_visible_radius_mm(K, T, width, height) if radius_mm is None else float(radius_mm)
    if not r > 0:
        raise ValueError(f"carving radius must be positive, got {r} mm")
    h = largest_visible_height_mm(K, T, width, height) if height_mm is None else float(height_mm)
    if not h > 0:
        raise ValueError(f"carving height must be positive, got {h} mm")
    return _Region(np.array([-r, 0.0, -r]), np.array([r, h, r]), r)


class _Views:
    """Projection matrices and silhouette distance maps of all views."""

    def __init__(self, masks: np.ndarray, K: np.ndarray, T: np.ndarray, max_rejections: int,
                 outer_masks: np.ndarray | None = None):
        self.P = (K @ T[:, :3, :]).astype(np.float32)  # (V, 3, 4)
        self.inv_f = np.float32(1.0 / math.sqrt(K[0, 0] * K[1, 1]))
        self.sdf_px = [silhouette_sdf_px(m) for m in masks]
        self.height, self.width = masks.shape[1:]
        # the outer silhouettes, enclosed holes and narrow bays filled: one rejection fewer suffices outside them
        bay = 2.0 * outer_band_px(self.width, self.height)
        self.outer_px = [silhouette_sdf_px(fill_enclosed(m, bay)) for m in outer_masks] \
            if outer_masks is not None and max_rejections > 0 else []
        self.k = max_rejections
        self.min_seen = max(max_rejections + 1, (len(masks) + 1) // 2)

    def evaluate(self, pts_table: np.ndarray) -> np.ndarray:
        """Order-statistic signed distance (N,) float32 mm at table points (N, 3)."""
        pts = np.asarray(pts_table, dtype=np.float32)
        out = np.empty(len(pts), np.float32)
        for a in range(0, len(pts), _CHUNK):
            out[a:a + _CHUNK] = self._evaluate_chunk(pts[a:a + _CHUNK])
        return out

    def _evaluate_chunk(self, pts: np.ndarray) -> np.ndarray:
        n, cols = len(pts), 1024
        rows = -(-n // cols)
        pts_h = np.zeros((4, rows * cols), np.float32)
        pts_h[:3, :n] = pts.T
        pts_h[3] = 1.0
        proj = self.P.reshape(-1, 4) @ pts_h  # (3 V, n): u w, v w, w of every view
        best = [np.full(rows * cols, np.inf, np.float32) for _ in range(self.k + 1)]  # k+1 smallest votes, sorted
        outer = [np.full(rows * cols, np.inf, np.float32) for _ in range(self.k if self.outer_px else 0)]
        seen = np.zeros(rows * cols, np.uint16)
        inv_w, u, v, vote = (np.empty(rows * cols, np.float32) for _ in range(4))
        for i, sdf in enumerate(self.sdf_px):
            w = proj[3 * i + 2]
            np.divide(1.0, w, out=inv_w)
            np.multiply(proj[3 * i], inv_w, out=u)
            np.multiply(proj[3 * i + 1], inv_w, out=v)
            u[w <= 0] = -4.0  # behind the camera: off the image
            np.clip(u, -4.0, self.width + 3.0, out=u)
            np.clip(v, -4.0, self.height + 3.0, out=v)
            s = cv2.remap(sdf, u.reshape(rows, cols), v.reshape(rows, cols), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=_UNSEEN_PX).ravel()
            seen += s < 0.5 * _UNSEEN_PX
            np.multiply(s, w, out=vote)
            vote *= self.inv_f
            for j in range(self.k + 1):  # insert the vote into the sorted k+1 smallest
                lo = np.minimum(best[j], vote)
                np.maximum(best[j], vote, out=vote)
                best[j] = lo
            if outer:  # the same vote against the outer silhouette, into its sorted k smallest
                s = cv2.remap(self.outer_px[i], u.reshape(rows, cols), v.reshape(rows, cols), cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=_UNSEEN_PX).ravel()
                np.multiply(s, w, out=vote)
                vote *= self.inv_f
                for j in range(self.k):
                    lo = np.minimum(outer[j], vote)
                    np.maximum(outer[j], vote, out=vote)
                    outer[j] = lo
        value = best[self.k] if not outer else np.minimum(best[self.k], outer[self.k - 1])
        value[seen < self.min_seen] = -np.float32(_UNSEEN_PX)
        return value[:n]


def _centres(origin: np.ndarray, voxel_mm: float, idx: np.ndarray) -> np.ndarray:
    return (origin + idx * voxel_mm).astype(np.float32)


def _dense_idx(dims) -> np.ndarray:
    return np.indices(dims).reshape(3, -1).T


def _evaluate_dense(views, region, origin, voxel_mm, dims) -> np.ndarray:
    pts = _centres(origin, voxel_mm, _dense_idx(dims))
    return np.minimum(views.evaluate(pts), region.sdf(pts)).reshape(dims)


def _tight_box(views: _Views, region: _Region) -> tuple[np.ndarray, np.ndarray]:
    """Box (lo, hi) mm around what survives a coarse carve of the region."""
    ext = region.hi - region.lo
    h = ext.max() / _COARSE
    dims = np.maximum(np.ceil(ext / h).astype(int), 1)
    origin = region.lo + 0.5 * (ext - (dims - 1) * h)
    vals = _evaluate_dense(views, region, origin, h, dims)
    occupied = np.argwhere(vals > -_BAND * h)
    if len(occupied) == 0:
        raise ValueError("the silhouettes carve the whole region away: no point is inside enough views")
    lo = origin + occupied.min(axis=0) * h - _BAND * h
    hi = origin + occupied.max(axis=0) * h + _BAND * h
    return np.maximum(lo, region.lo), np.minimum(hi, region.hi)


def _slab_planes(plane_voxels: int) -> int:
    """x-planes of the coarser grid per slab, for ``plane_voxels`` voxels in one of its planes."""
    return max(1, _SLAB_VOXELS // (8 * max(plane_voxels, 1)))


def _refine(vals, views, region, origin, voxel_mm) -> tuple[np.ndarray, int]:
    """One level finer: children of cells near the zero level set are evaluated, others inherit.

    Slab by slab along x (the new grid is the only full-size allocation).
    Returns the finer grid and how many parents were refined.
    """
    nx, ny, nz = vals.shape
    child = np.empty((2 * nx, 2 * ny, 2 * nz), np.float32)
    offsets = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    band = _BAND * 2.0 * voxel_mm
    step = _slab_planes(ny * nz)
    refined = 0
    for a in range(0, nx, step):
        part = vals[a:a + step]
        m = len(part)
        child[2 * a:2 * (a + m)] = np.broadcast_to(part[:, None, :, None, :, None],
                                                   (m, 2, ny, 2, nz, 2)).reshape(2 * m, 2 * ny, 2 * nz)
        parents = np.argwhere(np.abs(part) < band)
        if len(parents) == 0:
            continue
        parents[:, 0] += a
        refined += len(parents)
        idx = (2 * parents[:, None, :] + offsets[None]).reshape(-1, 3)
        pts = _centres(origin, voxel_mm, idx)
        child[idx[:, 0], idx[:, 1], idx[:, 2]] = np.minimum(views.evaluate(pts), region.sdf(pts))
    return child, refined


def _touching(vals, region, origin, voxel_mm) -> tuple[int, int]:
    """``region.touching`` of the inside voxels within a voxel of the region's boundary, slab by slab.

    Such a voxel has a value below a voxel (``D <= region``).
    """
    side = top = 0
    step = _slab_planes(vals.shape[1] * vals.shape[2] // 8)
    for a in range(0, vals.shape[0], step):
        part = vals[a:a + step]
        near = np.argwhere((part > 0) & (part < voxel_mm))
        near[:, 0] += a
        s, t = region.touching(origin + near * voxel_mm, voxel_mm)
        side, top = side + s, top + t
    return side, top


def _grid(views: _Views, region: _Region, resolution: int) -> tuple[tuple, np.ndarray]:
    """The fine grid around what the coarse carve keeps: ``(lo, hi, voxel_mm, levels)`` and its ``dims``."""
    levels = max(0, int(round(math.log2(int(resolution) / _COARSE))))
    lo, hi = _tight_box(views, region)
    voxel = float((hi - lo).max()) / int(resolution)
    step = 2 ** levels
    dims = step * np.ceil(((hi - lo) + 4.0 * voxel) / (voxel * step)).astype(int)
    return (lo, hi, voxel, levels), dims


def _peak_bytes(dims, n_views: int, image_hw: tuple[int, int]) -> int:
    """Estimated peak (bytes) of carving a grid of ``dims`` and meshing it.

    Carving: the grid, the level before it (1/8), the views' float32 distance
    maps, and the bounded slab and chunk buffers. Meshing the grid afterwards
    (``recon.meshing``: the grid, its padded copy and marching cubes' own
    buffers) takes more: measured 6.5 GB peak RSS for a 2.9 GB grid
    (``reconstruct --resolution 1024``, data/sample), about 2.2 grids; the
    larger of the two is what a run needs.
    """
    n = int(np.prod(np.asarray(dims, dtype=np.int64)))
    carve = 4 * n * 9 // 8 + 4 * n_views * image_hw[0] * image_hw[1] + _SLAB_BYTES
    mesh = int(2.3 * 4 * n) + _SLAB_BYTES
    return int(max(carve, mesh))


def hull_peak_bytes(masks: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, *,
                    bounds_table: np.ndarray | None = None, radius_mm: float | None = None,
                    height_mm: float | None = None, resolution: int = 256, max_rejections: int = 1,
                    outer: bool = False) -> int:
    """Estimated peak memory (bytes) of :func:`carve_hull` with these arguments (``outer``: with
    ``outer_masks``), beyond its inputs.

    Computes the views' distance maps and the coarse carve (``32^3`` points)
    to find the grid; the fine grid is not allocated.
    """
    masks, K, T, k = _check_inputs(masks, K, T_cam_table, max_rejections)
    V, H, W = masks.shape
    views = _Views(masks, K, T, k)
    _, dims = _grid(views, _make_region(bounds_table, radius_mm, height_mm, K, T, W, H), resolution)
    return _peak_bytes(dims, 2 * V if outer else V, (H, W))


def carve_hull(masks: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray, *,
               bounds_table: np.ndarray | None = None, radius_mm: float | None = None,
               height_mm: float | None = None, resolution: int = 256, max_rejections: int = 1,
               outer_masks: np.ndarray | None = None,
               progress: Callable[[int, int], None] | None = None) -> VoxelHull:
    """Carve the visual hull of the silhouettes as a sub-voxel signed distance grid.

    Parameters
    ----------
    masks : (V, H, W) bool
        Silhouettes, True on the object; undistorted images.
    K : (3, 3) float
        Shared pinhole intrinsics, pixels.
    T_cam_table : (V, 4, 4) float
        Per-view pose, table (mm) to camera (mm).
    bounds_table : (2, 3) float, optional
        Carving box ``[min, max]`` in the table frame, mm. When omitted the
        region is the cylinder of ``radius_mm`` on the table (``0 <= Y <=
        height_mm``).
    radius_mm, height_mm : float, optional
        Cylinder radius and height, mm (typically the target's ring radius).
        Defaults: the largest table circle every view sees whole, and the
        highest point of the turntable axis that most views see.
    resolution : int
        Voxels along the longest side of the (tightened) box.
    max_rejections : int
        ``k``: a voxel survives if at most ``k`` views reject it.
    outer_masks : (V, H, W) bool, optional
        With ``k >= 1``: each view's silhouette grown over what its outline
        may have missed (:func:`held_past_edges`); a voxel is also carved
        where ``k`` views (one fewer) see it outside this, once its enclosed
        holes and its bays narrower than four :func:`outer_band_px` are
        filled (:func:`fill_enclosed`). Tolerating one view's rejection keeps
        a hole in its silhouette from boring a tunnel through what every
        other view holds (a patch of a white teapot's shoulder that looks
        like the paper behind it); it also left the paper round a white box's
        foot (its shadow, its doubtful lit paper) in the hull wherever a
        single view saw it beside the box. The background a view sees round
        the object, past the outline's edge, is what it sees past it.
    progress : callable(done, total), optional
        Called after each refinement level.

    Returns
    -------
    VoxelHull
        ``values`` (Nx, Ny, Nz) float32 mm, > 0 inside; the grid is the box
        around what the coarse carve keeps plus two voxels of margin, so the
        zero level set is closed (flat on the table plane ``Y = 0``).
        ``meta`` holds ``max_rejections``, ``views``, ``region_lo``/``region_hi``
        (mm), ``evaluated`` (voxel centres projected, a cost measure) and
        ``touches_side``/``touches_top``: how many inside voxels lie within a
        voxel of the region's side wall / top, i.e. where the silhouettes
        would have let the hull go further (> 0: the region clipped it).
    """
    masks, K, T, k = _check_inputs(masks, K, T_cam_table, max_rejections)
    if int(resolution) < 4:
        raise ValueError(f"resolution must be at least 4, got {resolution}")
    V, H, W = masks.shape
    region = _make_region(bounds_table, radius_mm, height_mm, K, T, W, H)
    if outer_masks is not None and np.shape(outer_masks) != masks.shape:
        raise ValueError(f"outer_masks must have the masks' shape {masks.shape}, got {np.shape(outer_masks)}")
    views = _Views(masks, K, T, k, None if outer_masks is None else np.asarray(outer_masks, bool))
    (lo, hi, voxel, levels), dims = _grid(views, region, resolution)
    total = levels + 2
    if progress is not None:
        progress(1, total)
    needed, available = _peak_bytes(dims, V + len(views.outer_px), (H, W)), memory_available_bytes()
    if available is not None and needed > available:
        raise HullTooLarge(int(resolution), dims, needed, available)
    step = 2 ** levels
    centre = 0.5 * (lo + hi)
    h = voxel * step
    vals = _evaluate_dense(views, region, centre - 0.5 * (dims // step - 1) * h, h, dims // step)
    evaluated = vals.size
    if progress is not None:
        progress(2, total)
    for level in range(1, levels + 1):
        h = voxel * 2 ** (levels - level)
        n = dims // 2 ** (levels - level)
        vals, refined = _refine(vals, views, region, centre - 0.5 * (n - 1) * h, h)
        evaluated += 8 * refined
        if progress is not None:
            progress(2 + level, total)
    cap = np.float32(np.linalg.norm(region.hi - region.lo))
    origin = centre - 0.5 * (dims - 1) * voxel
    side, top = _touching(vals, region, origin, voxel)
    np.clip(vals, -cap, cap, out=vals)
    meta = {"max_rejections": k, "outer": bool(views.outer_px), "views": V,
            "region_lo": region.lo.tolist(), "region_hi": region.hi.tolist(),
            "evaluated": int(evaluated), "touches_side": side, "touches_top": top}
    return VoxelHull(values=vals, origin_table=origin, voxel_mm=voxel, meta=meta)


def drop_floating_bodies(hull: VoxelHull, ground_tol_mm: float = 3.0,
                         keep_fraction: float = 0.5) -> tuple[VoxelHull, list[float]]:
    """The hull without its bodies that float: ``(hull, dropped volumes in mm^3, largest first)``.

    An object standing on the turntable is connected and rests on the table,
    so its visual hull holds it in a body that reaches down to the table. A
    body (26-connected inside voxels) whose lowest voxel stays more than
    ``ground_tol_mm`` (at least 3 voxels) above the hull's lowest one is a
    phantom of the silhouettes (a patch of doubt between a chair's slats that
    every view leaves uncarved) unless it is large: bodies of at least
    ``keep_fraction`` of the largest one's volume stay (two objects, one on a
    stand the silhouettes lost). Dropped voxels are set just outside.
    """
    lab, n, vol, above = _body_labels(hull.values > 0, ground_tol_mm, hull.voxel_mm)
    if n <= 1:
        return hull, []
    idx = np.arange(1, n + 1)
    floating = above & (vol < keep_fraction * vol.max())
    if not floating.any():
        return hull, []
    drop = np.isin(lab, idx[floating])
    vals = hull.values.copy()
    vals[drop] = np.minimum(vals[drop], np.float32(-1e-3))
    dropped = sorted((float(v) * hull.voxel_mm ** 3 for v in vol[floating]), reverse=True)
    return replace(hull, values=vals, meta={**hull.meta, "floating_dropped": len(dropped)}), dropped


def _body_labels(inside: np.ndarray, ground_tol_mm: float, voxel_mm: float, faces_only: bool = False):
    """26-connected bodies of ``inside`` (6-connected: ``faces_only``): ``(labels, n, volumes (n,), above (n,)
    bool)``, ``above``: the body's lowest layer is more than ``ground_tol_mm`` (at least 3 voxels) above the
    lowest body's."""
    from scipy import ndimage

    lab, n = ndimage.label(inside, structure=None if faces_only else np.ones((3, 3, 3), bool))
    if n == 0:
        return lab, 0, np.zeros(0, np.int64), np.zeros(0, bool)
    vol = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    low = np.array([box[1].start for box in ndimage.find_objects(lab)])  # each body's lowest layer (axis 1 is up)
    return lab, n, vol, low > low.min() + max(ground_tol_mm / voxel_mm, 3.0)


SEEN_INSIDE_RATIO = 2.0  # keep_seen_inside: a voxel comes back where more views see it inside than this x the views
# whose dropped pixels hold it
SEEN_ONE_SIDE = 0.75  # ... (with one_side) and those views lie on one side of the turn: their azimuths' mean
# resultant length is this or more
SEEN_DEEP_MM = 4.0  # ... (with min_depth_mm) in parts reaching this far from what the split kept


def keep_seen_inside(after: VoxelHull, before: VoxelHull, masks, dropped, K, T_cam_table, radius_mm: float,
                     height_mm: float, ratio: float = SEEN_INSIDE_RATIO,
                     one_side: float | None = None, held=None,
                     min_depth_mm: float | None = None) -> tuple[VoxelHull, float]:
    """``before`` less what ``after`` carved, except the voxels the views see inside the object: ``(hull, mm^3 kept)``.

    ``after`` was carved from the silhouettes of ``before`` less each view's ``dropped`` pixels (a guess: doubt
    that ran to the working volume's outline, taken for the wall behind the object). Where the object and the
    wall share a colour, a view's dropped piece may hold a part of the object with the wall (a white chair's
    back on a light wall, seen from behind: the back went with the wall in 8 views of 36 and 18 % of a front
    view's silhouette lost its hull). A voxel ``after`` carved comes back when more views see it inside their
    sure silhouette (``masks``) than ``ratio`` times the views whose dropped pixels hold it: the object's back,
    inside every front view's silhouette, and not the fin of wall behind it, which only the views that see it
    against the object hold as sure. A voxel within two voxels of the working volume's side (``radius_mm``)
    or top (``height_mm``) never comes back: the result touches them where ``after`` does, and keeps its
    ``meta``. Returned on ``before``'s grid (``after`` sampled trilinearly at its voxel centres, in chunks).

    With ``one_side`` (e.g. ``SEEN_ONE_SIDE``), a voxel comes back only where, besides, the views whose dropped
    pixels hold it lie on one side of the turn (their azimuths' mean resultant length is ``one_side`` or
    more). Any voxel near a body lies inside most views' silhouettes, the views that see it in front of the
    body or behind it; only the views that see it at the body's outline can carve it. Doubt that the wall
    joined along one side of the object, its shaded side (the light stays with the camera), is dropped by the
    views that see that part at their outline on that side: a white vase's shaded shoulder, the wall's very
    grey, went with the wall in all 36 views of a light wall and was carved 7 mm deep all round. The wall's
    doubt round the object's outline is dropped on both sides of it, by the views at either end of the turn
    that see it there: the ratio alone gave back the wall round the vase's neck too (1.5 mm all round).
    ``held`` ((V, H, W) bool, what each view held before the split: its mask and doubt): a voxel that a view
    held as neither never comes back: that view saw past it (``before`` kept it, one view short of carving it),
    so it is not a part of the object that only the wall's grey hid. (It does not stop the sleeve of wall round
    a white snowman's nose, which comes back with the nose, held by every view before the split.)
    ``min_depth_mm``: what comes back, in parts (6-connected) of which none reaches that far from the voxels
    ``after`` keeps, does not: a part of the object lost with the wall is deep (the vase's shoulder: 7 mm),
    while the split's shaving of the outline is a sliver (the rim of a noisy vase's flat top, a millimetre or
    two, which came back one-sided and hid the top from :mod:`recon.faces`: 0.34 -> 0.40 % of the diagonal).
    """
    from scipy import ndimage

    from calib.camera import values_at_points

    from .silhouette_checks import camera_azimuths_deg

    K, Ts = as_K(K), as_poses(T_cam_table)
    az = np.deg2rad(camera_azimuths_deg(Ts))
    masks, dropped = np.asarray(masks, bool), np.asarray(dropped, bool)
    held = None if held is None else np.asarray(held, bool)
    vals = np.asarray(before.values, np.float32).copy()
    ijk = np.argwhere(vals > 0)
    after_vals = np.asarray(after.values, np.float32)
    kept = 0
    given: list[np.ndarray] = []  # the indices of what comes back
    for lo in range(0, len(ijk), 1_000_000):
        idx = ijk[lo:lo + 1_000_000]
        pts = before.centres_table(idx)
        after_at = ndimage.map_coordinates(after_vals, ((pts - after.origin_table) / after.voxel_mm).T, order=1,
                                           mode="constant", cval=-1.0)
        lost = after_at <= 0
        if not lost.any():
            continue
        pts, idx, after_at = pts[lost], idx[lost], after_at[lost]
        sure = np.zeros(len(pts), np.int32)
        wall = np.zeros(len(pts), np.int32)
        side = np.zeros((len(pts), 2))  # the sum of the unit azimuths of the views whose dropped pixels hold it
        free = np.zeros(len(pts), bool)  # a view that held it as neither the object nor doubt saw past it
        for j, (m, d, T, a) in enumerate(zip(masks, dropped, Ts, az, strict=True)):
            at = values_at_points(K, T, pts, m.astype(np.uint8) | (d.astype(np.uint8) << 1)
                                  | (0 if held is None else (~held[j]).astype(np.uint8) << 2))
            free |= (at >> 2) > 0
            at &= 3
            sure += at & 1
            held_as_wall = (at >> 1) > 0
            wall += held_as_wall
            side[held_as_wall] += (math.cos(a), math.sin(a))
        margin = 2.0 * before.voxel_mm
        back = (sure > ratio * wall) & (np.hypot(pts[:, 0], pts[:, 2]) < radius_mm - margin) \
            & (pts[:, 1] < height_mm - margin)
        if one_side is not None:
            back &= np.hypot(side[:, 0], side[:, 1]) >= one_side * np.maximum(wall, 1)
        back &= ~free
        kept += int(back.sum())
        given.append(idx[back])
        gone = tuple(idx[~back].T)
        vals[gone] = np.minimum(vals[gone], np.minimum(after_at[~back], np.float32(-1e-3)))
    if min_depth_mm is not None and kept:
        kept -= _drop_shallow(vals, np.concatenate(given), min_depth_mm / before.voxel_mm)
    return replace(before, values=vals, meta=dict(after.meta)), kept * before.voxel_mm ** 3


def _drop_shallow(vals: np.ndarray, given: np.ndarray, depth_vox: float) -> int:
    """Carve (in place, in ``vals``, > 0 inside) the parts of the ``given`` voxels (indices (N, 3)) that no voxel
    of them reaches ``depth_vox`` voxels from the rest of the inside; returns how many were carved."""
    from scipy import ndimage

    pad = int(math.ceil(depth_vox)) + 1
    lo = np.maximum(given.min(axis=0) - pad, 0)
    hi = np.minimum(given.max(axis=0) + pad + 1, vals.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    back = np.zeros(tuple(int(n) for n in hi - lo), bool)
    back[tuple((given - lo).T)] = True
    rest = (vals[box] > 0) & ~back
    depth = ndimage.distance_transform_edt(~rest)
    lab, n = ndimage.label(back)
    reach = np.asarray(ndimage.maximum(depth, lab, index=np.arange(1, n + 1)))
    shallow = np.concatenate([[False], reach < depth_vox])[lab]
    sub = vals[box]
    sub[shallow] = np.float32(-1e-3)
    return int(shallow.sum())


def rejoin_cut_off(hull: VoxelHull, before: VoxelHull, gap_mm: float = 4.0, min_fraction: float = 0.05,
                   ground_tol_mm: float = 3.0) -> tuple[VoxelHull, int]:
    """``hull`` with its large floating bodies joined again to the body standing on the table, where ``before``
    joined them: ``(hull, bodies joined)``.

    ``hull`` was carved from silhouettes that lost doubtful pixels which ``before`` (carved from the same
    views before that) still held. Where that cut a part of at least ``min_fraction`` of the volume off the
    standing body (:func:`drop_floating_bodies` would drop it), across a gap of at most ``gap_mm``, the
    voxels that ``before`` holds within ``gap_mm`` of both come back (a white figure's static head on a grey
    wall: the split of the doubt off the volume's outline gave the shaded neck, the wall's grey, to the wall
    in half the views, and the head floated 3 mm above the torso). The two grids may differ: ``before`` is
    sampled (trilinearly) at ``hull``'s voxel centres.

    Bodies are 6-connected here, as the mesh's surface joins voxels: a part that touches the standing body
    only along a voxel's edge or corner is a piece of its own in the mesh (the same figure's head, soft and
    noisy photos: its neck thinned to a diagonal step 86 mm up, one body of the hull, two of the mesh).
    """
    from scipy import ndimage

    inside = hull.values > 0
    lab, n, vol, floating = _body_labels(inside, ground_tol_mm, hull.voxel_mm, faces_only=True)
    if n <= 1 or not floating.any() or floating.all():
        return hull, 0
    standing = np.flatnonzero(~floating)
    main = lab == standing[np.argmax(vol[standing])] + 1
    big = np.flatnonzero(floating & (vol >= min_fraction * vol.sum()))
    if not len(big):
        return hull, 0
    r = gap_mm / hull.voxel_mm
    d_main = ndimage.distance_transform_edt(~main)
    before_vals = np.asarray(before.values, np.float32)
    vals = hull.values.copy()
    joined = 0
    for b in big:
        part = lab == b + 1
        if d_main[part].min() > r + 1.0:
            continue
        near = (ndimage.distance_transform_edt(~part) <= r) & (d_main <= r) & ~inside
        if not near.any():
            continue
        # ``before`` sampled only there (every voxel of a 256^3 grid would take ~1 GB of coordinates)
        ijk = np.argwhere(near)
        coords = (hull.centres_table(ijk) - before.origin_table) / before.voxel_mm
        held = ndimage.map_coordinates(before_vals, coords.T, order=1, mode="constant", cval=-1.0)
        near[tuple(ijk[held <= 0].T)] = False
        if not near.any():
            continue
        trial = inside | near
        tl, _ = ndimage.label(trial)
        if tl[part].max() != tl[main].max():  # each is one body of ``trial``: the same one, or still apart
            continue
        vals[near] = held[held > 0]
        inside = vals > 0
        joined += 1
    if not joined:
        return hull, 0
    return replace(hull, values=vals.astype(np.float32), meta={**hull.meta, "rejoined": joined}), joined
