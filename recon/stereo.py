"""Per-view depth by multi-view plane-sweep stereo, searched inside the hull.

For a reference view ``r`` and a neighbour ``n`` the pixel ``p = (u, v, 1)`` at
z-depth ``z`` in ``r`` lands in ``n`` at

    x_n ~ z * K R_nr K^-1 p + K t_nr,      T_n_r = T_n_table @ T_table_r,

so a sweep over ``z`` warps each neighbour onto the reference pixel grid
(``cv2.remap``) and scores photo-consistency by zero-mean normalised
cross-correlation over a square window (``cv2.boxFilter`` of I, J, J^2, IJ).
The sweep is *per pixel*: ``z = near + s (far - near)`` with ``s`` in [0, 1]
sampled uniformly, ``near``/``far`` the entry and exit of the pixel's ray in
the visual hull (:func:`hull_depth_range`), so only the hull's thickness is
searched. Scores of the neighbours are averaged over the best half of them
(robust to one occluded neighbour); the best sample is refined by a parabola
through it and its two neighbours.

Confidence in [0, 1] is the product of four terms, each a clipped ramp:
the NCC peak (``ncc_lo`` -> 0, ``ncc_hi`` -> 1), its uniqueness (gap to the
second local maximum of the score along the ray), its gap to the score of
the neighbours *unwarped* (the same pixels: see below) and the texture
strength (local grey-level standard deviation of the reference window).
Flat, blank or saturated regions therefore come out with low confidence
instead of a confident wrong depth.

A pattern that does not turn with the table is no evidence of depth: the
shading of a turning body of revolution under a fixed light, a shadow, a
reflection stay put in the image. Matched between views such a pattern
looks like a surface where the warp is the identity (near the axis, far
behind the object's front), and carving the free space in front of it cut
a white snowman (1.6 % of its diagonal; 0.8 % without). So the peak must
beat the unmoved image by the uniqueness gap (``uniq_gap``): a surface
that really lies where the image does not move (a face through the axis,
facing the camera) loses its depth in that view, and the views that see it
turned keep it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.camera import camera_centre_table

from .raycast import first_hits, pixel_rays_table, raycasting_scene
from .types import DepthMap, TableMesh, VoxelHull

__all__ = ["StereoOptions", "depth_maps", "hull_depth_range", "hull_mesh", "select_neighbours", "pixel_rays_table"]


@dataclass(frozen=True)
class StereoOptions:
    """Settings of :func:`depth_maps`.

    Attributes
    ----------
    neighbours : int
        Views on each side (by camera angle) matched against each view.
    scale : float
        Resolution of the sweep relative to the images (0.5: half); depth is
        upsampled back to (H, W).
    window : int
        NCC window edge, pixels at the sweep resolution (odd, >= 3).
    step_px : float
        Largest image motion per depth sample in the farthest neighbour.
        (A coarse-to-fine variant, 1.5 px then 0.5 px around a smoothed
        coarse surface, halved the time but raised the 90th-percentile depth
        error from 0.58 to 0.74 mm on the vase: every pixel of an NCC window
        must be warped with a coherent depth, which the hull's own surface
        gives the single sweep for free.)
    ncc_lo, ncc_hi, uniq_gap, texture_lo, texture_hi : float
        Confidence ramps: NCC peak, gap to the second local maximum and to the
        score of the unwarped neighbours, grey-level standard deviation of the
        reference window (0-255 scale).
    seed : int
        Seed of the pixel sample that sizes each view's sweep.
    """

    neighbours: int = 2
    scale: float = 0.5
    window: int = 7
    step_px: float = 0.75
    ncc_lo: float = 0.4
    ncc_hi: float = 0.85
    uniq_gap: float = 0.15
    texture_lo: float = 1.0
    texture_hi: float = 5.0
    seed: int = 0


# --------------------------------------------------------------------------- hull range
def hull_mesh(hull: VoxelHull) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a :class:`VoxelHull` as ``(vertices_table (N, 3) mm, faces (M, 3))``."""
    from skimage import measure

    vals = np.asarray(hull.values, dtype=np.float32)
    if vals.ndim != 3 or min(vals.shape) < 2:
        raise ValueError(f"hull.values: expected a 3-D grid, got shape {vals.shape}")
    if not (vals.max() > 0 > vals.min()):
        raise ValueError("hull.values: no zero crossing (hull empty or fills the grid)")
    padded = np.pad(vals, 1, constant_values=min(float(vals.min()), -1.0))
    verts, faces, _, _ = measure.marching_cubes(padded, level=0.0)
    verts = (verts - 1.0) * float(hull.voxel_mm) + np.asarray(hull.origin_table, float)
    # skimage orients faces towards increasing values (the inside); flip to outward
    return verts.astype(np.float64), faces[:, ::-1].astype(np.int64)


def _as_mesh(hull_or_mesh) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(hull_or_mesh, VoxelHull):
        return hull_mesh(hull_or_mesh)
    if isinstance(hull_or_mesh, TableMesh):
        return np.asarray(hull_or_mesh.vertices_table, float), np.asarray(hull_or_mesh.faces, np.int64)
    if isinstance(hull_or_mesh, tuple) and len(hull_or_mesh) == 2:
        return np.asarray(hull_or_mesh[0], float), np.asarray(hull_or_mesh[1], np.int64)
    raise ValueError("expected a VoxelHull, a TableMesh or (vertices_table, faces)")


def hull_depth_range(hull_or_mesh, K: np.ndarray, T_cam_table: Sequence[np.ndarray] | np.ndarray,
                     size: tuple[int, int], *, margin_mm: float = 0.0,
                     scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit z-depth of each pixel's ray in the hull, for every view.

    Parameters
    ----------
    hull_or_mesh : VoxelHull | TableMesh | (vertices_table, faces)
        The visual hull (table frame, mm).
    K : (3, 3) float64
        Intrinsics for images of ``size``.
    T_cam_table : (V, 4, 4) float64
        Per-view poses (table mm -> camera mm).
    size : (W, H)
        Image size in pixels.
    margin_mm : float
        Widening of each interval on both sides (discretisation of the hull).
    scale : float
        Cast rays on an image ``scale`` times the size and upsample (nearest)
        to (H, W): 0.5 matches a half-resolution sweep at a quarter of the cost.

    Returns
    -------
    near, far : (V, H, W) float32
        z-depth (mm, camera frame) of the first entry into and the last exit
        from the hull; 0 for rays that miss it.
    """
    K = np.asarray(K, dtype=np.float64)
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    verts, faces = _as_mesh(hull_or_mesh)
    scene = raycasting_scene(verts, faces)
    if not 0.0 < scale <= 1.0:
        raise ValueError(f"scale must be in (0, 1], got {scale}")
    W, H = int(size[0]), int(size[1])
    Ws, Hs = int(round(W * scale)), int(round(H * scale))
    Ks = _scaled_K(K, scale)
    near = np.zeros((len(Ts), H, W), np.float32)
    far = np.zeros_like(near)
    corners = np.array(np.meshgrid(*zip(verts.min(0), verts.max(0), strict=True))).reshape(3, -1).T
    v_sub = verts[:: max(1, len(verts) // 20000)]
    for i, T in enumerate(Ts):
        n_i = np.zeros((Hs, Ws), np.float32)
        f_i = np.zeros((Hs, Ws), np.float32)
        win = _projected_window(Ks, T, v_sub, (Ws, Hs))
        if win is not None:
            ys, xs = win
            u, v = np.meshgrid(np.arange(xs.start, xs.stop, dtype=np.float64),
                               np.arange(ys.start, ys.stop, dtype=np.float64))
            dirs = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(Ks).T @ T[:3, :3]
            centre = camera_centre_table(T)
            # farthest possible depth: bounding-box corners in the camera frame
            t_far = float((corners @ T[:3, :3].T + T[:3, 3])[:, 2].max()) + 10.0
            rays = np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], axis=-1).astype(np.float32)
            t1 = first_hits(scene, rays)
            back = np.concatenate([centre + dirs * t_far, -dirs], axis=-1).astype(np.float32)
            t2 = first_hits(scene, back)
            hit = np.isfinite(t1) & np.isfinite(t2)
            n_i[ys, xs] = np.where(hit, np.maximum(t1 - margin_mm, 1e-3), 0.0)
            f_i[ys, xs] = np.where(hit, t_far - t2 + margin_mm, 0.0)
        near[i] = _resize_nearest(n_i, (W, H)) if scale != 1.0 else n_i
        far[i] = _resize_nearest(f_i, (W, H)) if scale != 1.0 else f_i
    return near, far


def _projected_window(K, T, pts_table, size, pad: int = 4) -> tuple[slice, slice] | None:
    """Pixel window (rows, cols) holding the projection of ``pts_table``, padded; None if empty."""
    pc = pts_table @ T[:3, :3].T + T[:3, 3]
    W, H = size
    if np.any(pc[:, 2] <= 1e-6):  # the mesh straddles the camera plane: whole image
        return slice(0, H), slice(0, W)
    uv = pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    x0, y0 = np.floor(uv.min(0)).astype(int) - pad
    x1, y1 = np.ceil(uv.max(0)).astype(int) + pad + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if x1 <= x0 or y1 <= y0:
        return None
    return slice(y0, y1), slice(x0, x1)


# --------------------------------------------------------------------------- neighbours
def select_neighbours(T_cam_table: np.ndarray, neighbours: int, *, min_angle_deg: float = 2.0) -> list[list[int]]:
    """The ``2 * neighbours`` views whose camera centres are angularly closest.

    Angles are measured between camera centres seen from the table origin
    (turntable steps); views closer than ``min_angle_deg`` (no baseline) are
    skipped. Returns one index list per view, nearest first.
    """
    Ts = np.asarray(T_cam_table, float).reshape(-1, 4, 4)
    centres = camera_centre_table(Ts)
    dirs = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0)))
    out = []
    for i in range(len(Ts)):
        order = [j for j in np.argsort(ang[i]) if j != i and ang[i, j] >= min_angle_deg]
        out.append([int(j) for j in order[: 2 * neighbours]])
    return out


# --------------------------------------------------------------------------- sweep
def _scaled_K(K: np.ndarray, s: float) -> np.ndarray:
    """Intrinsics of an image resized by ``s`` (pixel centres at integers)."""
    S = np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])
    return S @ K


def _grey(img: np.ndarray, s: float) -> np.ndarray:
    img = np.asarray(img)
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    g = g.astype(np.float32)
    if s != 1.0:
        g = cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return g


def _resize_nearest(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.resize(a, size, interpolation=cv2.INTER_NEAREST)


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def _roi(valid: np.ndarray, pad: int) -> tuple[slice, slice] | None:
    ys, xs = np.nonzero(valid)
    if len(ys) == 0:
        return None
    H, W = valid.shape
    return (slice(max(ys.min() - pad, 0), min(ys.max() + pad + 1, H)),
            slice(max(xs.min() - pad, 0), min(xs.max() + pad + 1, W)))


class _Ref:
    """Reference view quantities restricted to its ROI (processing resolution)."""

    def __init__(self, grey, K, T, near, far, valid, win):
        self.roi = _roi(valid, win)
        ys, xs = self.roi
        self.I = grey[ys, xs]
        self.valid = valid[ys, xs]
        self.near, self.far = near[ys, xs], far[ys, xs]
        self.K, self.T, self.win = K, T, win
        box = (win, win)
        self.mI = cv2.boxFilter(self.I, -1, box)
        self.sI = np.sqrt(np.maximum(cv2.boxFilter(self.I * self.I, -1, box) - self.mI ** 2, 0.0))
        v, u = np.mgrid[ys, xs]
        self.pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(np.float64)


def _warp_setup(ref: _Ref, K_n: np.ndarray, T_n: np.ndarray):
    """Per-pixel terms of ``x_n ~ z a + b`` for the neighbour (a: (3, h, w) planes, b: (3,))."""
    T_nr = T_n @ np.linalg.inv(ref.T)
    a = ref.pix @ (K_n @ T_nr[:3, :3] @ np.linalg.inv(ref.K)).T
    b = K_n @ T_nr[:3, 3]
    return np.ascontiguousarray(np.moveaxis(a, -1, 0), dtype=np.float32), b.astype(np.float32)


def _ncc(ref: _Ref, J: np.ndarray, inside: np.ndarray) -> np.ndarray:
    box = (ref.win, ref.win)
    mJ = cv2.boxFilter(J, -1, box)
    sJ2 = cv2.boxFilter(J * J, -1, box) - mJ * mJ
    cov = cv2.boxFilter(ref.I * J, -1, box) - ref.mI * mJ
    den = ref.sI * np.sqrt(np.maximum(sJ2, 0.0)) + 1e-3
    ncc = cov / den
    ncc[~inside] = -1.0
    return ncc


def _sweep(ref: _Ref, neigh: list[tuple[np.ndarray, np.ndarray, np.ndarray]], z0: np.ndarray, dz: np.ndarray,
           n_samples: int) -> np.ndarray:
    """Aggregated score volume (D, h, w) float32 at depths ``z0 + k dz``, k < D (per pixel, mm)."""
    setups = [(g, *_warp_setup(ref, K_n, T_n)) for g, K_n, T_n in neigh]
    h, w = ref.I.shape
    vol = np.empty((n_samples, h, w), np.float32)
    for d in range(n_samples):
        z = z0 + np.float32(d) * dz
        view_scores = []
        for g, a, b in setups:
            wz = np.maximum(z * a[2] + b[2], np.float32(1e-6))  # > 0: the hull is in front of every camera
            mx = (z * a[0] + b[0]) / wz
            my = (z * a[1] + b[1]) / wz
            inside = (mx > 0) & (my > 0) & (mx < g.shape[1] - 1) & (my < g.shape[0] - 1)
            J = cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            view_scores.append(_ncc(ref, J, inside))
        vol[d] = _best_half_mean(np.stack(view_scores))
    return vol


def _best_half_mean(scores: np.ndarray) -> np.ndarray:
    """(h, w) mean of the best half (rounded up) of the neighbours' scores (n, h, w): one occluded
    neighbour does not sink a match.

    The best half is sorted out by compare-exchanges of whole (h, w) planes (odd-even transposition:
    n rounds), not by ``np.partition`` along the first axis, which strides across the planes and took a
    third of the stereo stage (2 x 2 neighbours, 1280 x 960: ~12 ms a call against ~1 ms)."""
    n = len(scores)
    k_best = max(1, (n + 1) // 2)
    if k_best >= n:
        return scores.mean(axis=0)
    rows = [np.array(r, copy=True) for r in scores]
    for r in range(n):
        for j in range(r % 2, n - 1, 2):
            hi = np.maximum(rows[j], rows[j + 1])
            np.minimum(rows[j], rows[j + 1], out=rows[j + 1])
            rows[j] = hi
    total = rows[0].copy()
    for row in rows[1:k_best]:
        total += row
    return total / np.asarray(k_best, dtype=total.dtype)


def _static_score(ref: _Ref, neigh: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """(h, w) NCC of the reference against its neighbours at the same pixels (no warp: what does not move
    as the table turns), aggregated as in :func:`_sweep`."""
    ys, xs = ref.roi
    inside = np.ones_like(ref.valid)
    return _best_half_mean(np.stack([_ncc(ref, np.ascontiguousarray(g[ys, xs]), inside) for g, _, _ in neigh]))


def _auto_samples(ref: _Ref, neigh, step_px: float, rng: np.random.Generator) -> int:
    """Samples along the ray so the farthest neighbour moves ``step_px`` per sample."""
    vy, vx = np.nonzero(ref.valid)
    pick = rng.choice(len(vy), size=min(300, len(vy)), replace=False)
    vy, vx = vy[pick], vx[pick]
    shift = 0.0
    for _, K_n, T_n in neigh:
        a, b = _warp_setup(ref, K_n, T_n)
        a = a[:, vy, vx].T.astype(np.float64)
        x0 = ref.near[vy, vx, None] * a + b
        x1 = ref.far[vy, vx, None] * a + b
        d = np.linalg.norm(x0[:, :2] / x0[:, 2:] - x1[:, :2] / x1[:, 2:], axis=1)
        shift = max(shift, float(np.percentile(d, 95)))
    return int(np.clip(np.ceil(shift / step_px) + 1, 8, 256))


def _pick_peak(vol: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-sample peak position (h, w), peak score and second local maximum."""
    D = vol.shape[0]
    best = np.argmax(vol, axis=0)
    c1 = np.take_along_axis(vol, best[None], 0)[0]
    lo = np.take_along_axis(vol, np.maximum(best - 1, 0)[None], 0)[0]
    hi = np.take_along_axis(vol, np.minimum(best + 1, D - 1)[None], 0)[0]
    curv = lo - 2.0 * c1 + hi
    inner = (best > 0) & (best < D - 1) & (curv < -1e-6)
    off = np.where(inner, 0.5 * (lo - hi) / np.where(inner, curv, -1.0), 0.0)
    pos = best + np.clip(off, -0.5, 0.5)
    # second-highest local maximum, away from the main peak (depth by depth: no temporaries the size of
    # the volume)
    c2 = np.full(best.shape, -1.0, dtype=vol.dtype)
    for d in range(D):
        m = vol[d]
        ok = np.abs(d - best) > 1
        if d > 0:
            ok &= m >= vol[d - 1]
        if d < D - 1:
            ok &= m >= vol[d + 1]
        np.maximum(c2, np.where(ok, m, vol.dtype.type(-1.0)), out=c2)
    return pos.astype(np.float32), c1, c2


def _upsample(depth: np.ndarray, conf: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear upsampling where all four parents are known, nearest elsewhere."""
    known = (depth > 0).astype(np.float32)
    lin = cv2.resize(depth, size, interpolation=cv2.INTER_LINEAR)
    full = cv2.resize(known, size, interpolation=cv2.INTER_LINEAR) > 0.999
    near = _resize_nearest(depth, size)
    return np.where(full, lin, near).astype(np.float32), _resize_nearest(conf, size)


def depth_maps(images_rgb: Sequence[np.ndarray], K: np.ndarray, T_cam_table: Sequence[np.ndarray] | np.ndarray,
               depth_range: tuple[np.ndarray, np.ndarray], *, masks: Sequence[np.ndarray] | None = None,
               options: StereoOptions | None = None, progress: Callable[[int, int], None] | None = None,
               **overrides) -> list[DepthMap]:
    """Depth and confidence for every view by plane-sweep NCC inside the hull.

    Parameters
    ----------
    images_rgb : sequence of V (H, W, 3) uint8
        Undistorted images (or (H, W) grey).
    K : (3, 3) float64
        Shared intrinsics of the full-resolution images.
    T_cam_table : (V, 4, 4) float64
        Poses, table mm -> camera mm.
    depth_range : (near, far), each (V, H, W) float
        z-depth interval (mm) to search per pixel, e.g. from
        :func:`hull_depth_range`; pixels with ``far <= near`` or ``near <= 0``
        are skipped. Scalars are broadcast to every pixel.
    masks : sequence of V (H, W) bool, optional
        Silhouettes; only pixels inside are computed.
    options : StereoOptions, optional
        The sweep's settings; default ``StereoOptions()``.
    **overrides
        Fields of :class:`StereoOptions` by name (``neighbours=3``), replacing
        those of ``options``.

    Returns
    -------
    list of DepthMap
        One per view, (H, W): z-depth (mm, 0 unknown) and confidence in [0, 1].
    """
    o = replace(options or StereoOptions(), **overrides)
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    V = len(Ts)
    if len(images_rgb) != V:
        raise ValueError(f"{len(images_rgb)} images but {V} poses")
    if not 0.0 < o.scale <= 1.0:
        raise ValueError(f"scale must be in (0, 1], got {o.scale}")
    if o.window < 3 or o.window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {o.window}")
    H, W = np.asarray(images_rgb[0]).shape[:2]
    near_all = np.broadcast_to(np.asarray(depth_range[0], np.float32), (V, H, W))
    far_all = np.broadcast_to(np.asarray(depth_range[1], np.float32), (V, H, W))
    K = np.asarray(K, dtype=np.float64)
    Ks = _scaled_K(K, o.scale)
    greys = [_grey(im, o.scale) for im in images_rgb]
    rng = np.random.default_rng(o.seed)
    nb = select_neighbours(Ts, o.neighbours)
    out = []
    for r in range(V):
        valid_full = (near_all[r] > 0) & (far_all[r] > near_all[r])
        if masks is not None:
            valid_full &= np.asarray(masks[r], bool)
        out.append(_one_view(r, greys, Ks, Ts, (near_all[r], far_all[r]), valid_full, nb[r], (W, H), o, rng))
        if progress is not None:
            progress(r + 1, V)
    return out


def _one_view(r, greys, Ks, Ts, near_far, valid_full, nb, size, o: StereoOptions, rng) -> DepthMap:
    """Depth map of view ``r`` (full size (W, H)) from the sweep at ``o.scale`` against views ``nb``."""
    W, H = size
    size_s = (int(round(W * o.scale)), int(round(H * o.scale)))
    near, far = near_far
    empty = DepthMap(view=r, depth_mm=np.zeros((H, W), np.float32), confidence=np.zeros((H, W), np.float32))
    valid_s = _resize_nearest(valid_full.astype(np.uint8), size_s) > 0
    if not valid_s.any() or not nb:
        return empty
    near_s = _resize_nearest(np.ascontiguousarray(near), size_s)
    far_s = _resize_nearest(np.ascontiguousarray(far), size_s)
    ref = _Ref(greys[r], Ks, Ts[r], near_s, far_s, valid_s, o.window)
    neigh = [(greys[j], Ks, Ts[j]) for j in nb]
    span = (ref.far - ref.near).astype(np.float32)
    D = _auto_samples(ref, neigh, o.step_px, rng)
    dz = span / max(D - 1, 1)
    pos, c1, c2 = _pick_peak(_sweep(ref, neigh, ref.near, dz, D))
    depth = ref.near + pos * dz
    conf = _ramp(c1, o.ncc_lo, o.ncc_hi) * _ramp(c1 - c2, 0.0, o.uniq_gap) * _ramp(ref.sI, o.texture_lo, o.texture_hi)
    conf *= _ramp(c1 - _static_score(ref, neigh), 0.0, o.uniq_gap)  # better than nothing moving at all
    keep = ref.valid & (conf > 0)
    depth_s = np.zeros(size_s[::-1], np.float32)
    conf_s = np.zeros(size_s[::-1], np.float32)
    depth_s[ref.roi] = np.where(keep, depth, 0.0)
    conf_s[ref.roi] = np.where(keep, conf, 0.0)
    if size_s != (W, H):
        depth_s, conf_s = _upsample(depth_s, conf_s, (W, H))
    depth_s[~valid_full] = 0.0
    conf_s[depth_s <= 0] = 0.0
    return DepthMap(view=r, depth_mm=depth_s, confidence=conf_s)
