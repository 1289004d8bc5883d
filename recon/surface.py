"""A surface from the visual hull and the fused stereo points together.

Truncated signed distance fusion on the hull's own voxel grid, inside
positive like :class:`~recon.types.VoxelHull`. Each view ``i`` renders the
fused points that face it into a z-buffer ``Z_i`` (on every ``stride``-th
pixel), kept where the view's own stereo depth agrees (a z-buffer can show
points through pinholes between splats; a depth map cannot); a voxel centre
at camera depth ``z`` projecting to ``x`` gets

    phi_i = clip(z - Z_i(x), -tau, tau)        if z - Z_i(x) < tau,

(free space in front of the seen surface, unknown far behind it). With the
hull value ``h`` clipped to the same band and a small prior weight ``w_h``:

    D = (w_h clip(h, -tau, tau) + sum_i phi_i) / (w_h + n),
    F = D  where D < h - delta,   h  elsewhere,

``n`` the number of views that updated the voxel. Hull space is emptied
(``F < 0 < h``) only on evidence: at least ``min_free_views`` views saw the
voxel (or a neighbour) as free, ``phi_i < -delta``; elsewhere the hull value
stands, so a single view's stereo, or no stereo at all, never carves. Where
stereo agrees with the hull within ``delta`` (stereo noise, a few tenths of a
mm) the hull stands too, so a tight hull (convex parts, measured: ~0.13 mm
Chamfer on a vase) is not traded for noisier stereo; where several views see
deeper than the hull (a cup's inside, a dent, the roof a limited elevation
leaves) the free space is carved. ``F <= h``: nothing is added outside the
hull. The surface is the zero level set (marching cubes). ``D`` is computed
on every ``tsdf_step``-th voxel and interpolated trilinearly (concavities are
mm-sized or larger; the fine detail comes from the hull).

Where stereo is silent because no camera can look there, the hull would
stand wrongly: from a camera 30 deg above the table no ray reaches the lower
inside of a cup, so carving stops at a lid about 20 mm under its rim. A
gravity prior fills that gap (``cavity_prior``): unobserved hull voxels below
an *observed opening* (free space reaching up to the hull's outside, at
least ``min_opening_mm`` deep, seen as free by ``min_free_views`` cameras
above it), down each column, are empty too, keeping a wall and a floor as
thick as the wall (see :func:`_unseen_cavity`). It is silent where free space
was seen only from below (the top of a head above every camera) or only as a
thin layer of surface noise: on real photographs that is what had cut
narrow slots from the top of solid objects down to the table. Measured (36
views, 1280x960, 30 deg, integrating the 18 even views): cup fused/hull
Chamfer 0.27.

Which carved regions are kept is decided on views not integrated here:
:func:`recon.regions.choose_regions`.

:func:`compare_to_hull` (a whole-mesh comparison with the confident stereo
depth, see its docstring) is no longer used by ``reconstruct``, which decides
region by region; it is kept for callers comparing two meshes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from calib.camera import camera_centre_table

from .raycast import render_depth
from .types import DepthMap, FusedPoints, TableMesh, VoxelHull

__all__ = ["SurfaceOptions", "fused_field", "fused_surface", "splat_depth", "compare_to_hull", "HullComparison"]


@dataclass(frozen=True)
class SurfaceOptions:
    """Settings of :func:`fused_field` (and :func:`fused_surface`).

    Attributes
    ----------
    trunc_mm : float, optional
        TSDF truncation ``tau``; None: ``max(2 TSDF voxels, 1.5 mm)`` (cup:
        1.5 mm gave Chamfer 1.09 mm, 2.5 mm 1.11, 4 mm 1.13).
    hull_weight : float
        Weight of the hull prior, in views.
    delta_mm : float
        Stereo must put the surface this far inside the hull to move it; a
        view sees a voxel as free when the voxel lies this far in front of
        the surface it sees.
    tsdf_step : int, optional
        TSDF on every ``tsdf_step``-th hull voxel; None: the step that makes
        its voxel about 1 mm (at least 1).
    stride : int
        Pixel step of the per-view z-buffers.
    min_confidence, agree_mm : float
        A z-buffer pixel counts only where the view's own depth (confidence
        at least ``min_confidence``) agrees with it within ``agree_mm``.
    min_free_views : int
        Hull space is carved only where at least this many views saw it as
        free; the cavity prior needs as many views from above its opening.
    cavity_prior : bool
        Treat unobserved hull voxels under an observed opening as empty (a
        cavity no camera could look into; see :func:`_unseen_cavity`).
    min_cavity_mm2 : float
        Smallest horizontal extent of such a cavity's top; smaller ones
        (gaps in the observed surface of a solid object) are left alone.
    min_opening_mm : float
        Depth of observed free space the cavity's opening must show.
    """

    trunc_mm: float | None = None
    hull_weight: float = 0.1
    delta_mm: float = 1.0
    tsdf_step: int | None = None
    stride: int = 2
    min_confidence: float = 0.2
    agree_mm: float = 2.0
    min_free_views: int = 2
    cavity_prior: bool = True
    min_cavity_mm2: float = 100.0
    min_opening_mm: float = 5.0


def splat_depth(points: FusedPoints, K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int],
                stride: int = 2, fill_iters: int = 2) -> np.ndarray:
    """Z-buffer (h, w) float32 of the points facing the camera, on every ``stride``-th pixel.

    Empty pixels are filled ``fill_iters`` times with the nearest depth of
    their 3x3 neighbourhood, so that pinholes between points do not let
    surfaces behind show through. 0 where no point lands.
    """
    W, H = size
    w, h = (W + stride - 1) // stride, (H + stride - 1) // stride
    T = np.asarray(T_cam_table, float)
    centre = camera_centre_table(T)
    p = np.asarray(points.pts_table, float)
    facing = np.sum(np.asarray(points.normals_table) * (centre - p), axis=1) > 0
    pc = p[facing] @ T[:3, :3].T + T[:3, 3]
    uvw = pc @ (np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(K, float)).T
    z = uvw[:, 2]
    ok = z > 1e-6
    x = np.rint(uvw[ok, 0] / z[ok]).astype(np.intp)
    y = np.rint(uvw[ok, 1] / z[ok]).astype(np.intp)
    z = z[ok]
    inb = (x >= 0) & (y >= 0) & (x < w) & (y < h)
    zbuf: np.ndarray = np.full(h * w, np.inf)
    np.minimum.at(zbuf, y[inb] * w + x[inb], z[inb])
    zbuf = zbuf.reshape(h, w)
    for _ in range(fill_iters):
        zbuf = np.where(np.isfinite(zbuf), zbuf, ndimage.minimum_filter(zbuf, size=3))
    return np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)


def _agreeing(zbuf: np.ndarray, dm: DepthMap, stride: int, min_confidence: float, agree_mm: float) -> np.ndarray:
    """The z-buffer where the view's own confident stereo depth agrees with it, else 0.

    A z-buffer pixel can show a point from behind the first surface (a
    pinhole between splatted points); the view's own depth map cannot, so
    agreement with it keeps only first-surface observations.
    """
    own = np.where(dm.confidence >= min_confidence, dm.depth_mm, 0.0)[::stride, ::stride]
    h, w = zbuf.shape
    own = own[:h, :w]
    return np.where((own > 0) & (np.abs(zbuf - own) <= agree_mm), zbuf, 0.0).astype(np.float32)


def lateral_mm(inside_slice: np.ndarray, voxel_mm: float) -> np.ndarray:
    """Per voxel of one horizontal slice (axes x, z) of a grid: its distance to the slice's outside, mm (the
    grid's edge counts as outside)."""
    return ndimage.distance_transform_edt(np.pad(inside_slice, 1))[1:-1, 1:-1] * voxel_mm


def _unseen_cavity(h: np.ndarray, D: np.ndarray, C: np.ndarray, down: np.ndarray, voxel_mm: float,
                   min_area_mm2: float, min_views: int, min_opening_mm: float) -> np.ndarray:
    """Unobserved hull voxels under an observed opening: a cavity no camera could look into.

    ``h`` hull values, ``D`` fused TSDF, ``C`` number of views that updated
    each voxel, ``down`` number of views *above* the voxel that saw it as
    free space, all on one grid whose axis 1 is table +Y (up). A voxel is
    *free* where views carved it (``C > 0``, ``D < 0``) inside the hull and
    *unseen* where no view updated it.

    The prior acts only where an opening is actually observed: a seed is an
    unseen voxel directly under free space; a connected set of seeds acts
    only if at least half of its footprint, and ``min_area_mm2`` of it, lies
    under a free column that (1) reaches up to the hull's outside (the
    opening), (2) is at least ``min_opening_mm`` deep and (3) whose lowest
    voxel at least ``min_views`` cameras above it saw as free (they looked
    down into it; the most over its lowest ~2 mm, which the opening's depth
    covers: the lowest voxel alone lies within the surface's depth noise). A
    few voxels of noisy carving at a surface, or free space
    seen only from below (the top of a head above every camera), start
    nothing. Going down each column from a seed, unseen
    voxels are cavity voxels as long as their horizontal distance to the
    hull's outside and their height above the hull's floor both exceed the
    wall thickness ``t`` (a low percentile of that horizontal distance over
    the seeds), so the cavity keeps a wall and a floor of that thickness.
    Solid tops stop the descent: under an observed surface the voxels within
    ``tau`` behind it were updated (``C > 0``, ``D >= 0``). Seed components
    whose footprint covers less than ``min_area_mm2`` are dropped. Returns a
    bool mask of the voxels to treat as empty.
    """
    inside = h > 0
    free = inside & (C > 0) & (D < 0)
    unseen = inside & (C == 0)
    ny = h.shape[1]
    run = np.zeros(h.shape, np.int32)     # free voxels in a row from here up
    opens = np.zeros(h.shape, bool)       # ... and the run reaches the hull's outside
    run[:, -1, :] = free[:, -1, :]
    opens[:, -1, :] = free[:, -1, :]
    for j in range(ny - 2, -1, -1):
        run[:, j, :] = np.where(free[:, j, :], run[:, j + 1, :] + 1, 0)
        opens[:, j, :] = free[:, j, :] & (opens[:, j + 1, :] | ~inside[:, j + 1, :])
    seed = np.zeros_like(unseen)
    seed[:, :-1, :] = unseen[:, :-1, :] & free[:, 1:, :]
    # views from above that saw the bottom of the free column free: the most over its lowest ~2 mm. The very
    # lowest voxel lies within the depth noise of the surface under it and is seen free by fewer views the finer
    # the grid (the rendered cup: 46 % of its cavity's footprint passed at 0.81 mm voxels, and the cavity
    # stayed full, fused/hull 0.27 -> 0.66; most of it at 1.14 mm); the opening is deeper than that anyway.
    low = np.asarray(down).copy()
    for s in range(1, max(1, int(round(2.0 / voxel_mm)))):
        low[:, :-s, :] = np.maximum(low[:, :-s, :], down[:, s:, :])
    good = np.zeros_like(unseen)  # seeds under an observed opening
    good[:, :-1, :] = opens[:, 1:, :] & (run[:, 1:, :] * voxel_mm >= min_opening_mm) & (low[:, 1:, :] >= min_views)
    good &= seed
    E = np.zeros_like(unseen)
    if not good.any():
        return E
    lab, n = ndimage.label(seed, structure=np.ones((3, 3, 3), bool))
    ii, jj, kk = np.nonzero(seed)
    # footprint: distinct (x, z) columns per seed component, and those under an observed opening
    key = np.unique(np.stack([lab[ii, jj, kk], ii, kk], 1), axis=0)
    cols = np.bincount(key[:, 0], minlength=n + 1)
    sel = good[ii, jj, kk]
    key_g = np.unique(np.stack([lab[ii, jj, kk], ii, kk], 1)[sel], axis=0)
    cols_g = np.bincount(key_g[:, 0], minlength=n + 1)
    # a component acts when most of its footprint lies under an observed opening of enough area
    big = (cols_g * voxel_mm ** 2 >= min_area_mm2) & (cols_g >= 0.5 * cols)
    big[0] = False
    seed &= big[lab]
    if not seed.any():
        return E
    # lateral distance to the hull's outside, slice by slice (the grid edge counts as outside)
    lateral = np.stack([lateral_mm(inside[:, j, :], voxel_mm) for j in range(ny)], axis=1)
    t = float(np.percentile(lateral[seed], 2))
    # height above the hull's floor in each column
    j_idx = np.arange(ny)[None, :, None]
    floor = np.where(inside, j_idx, ny).min(axis=1, keepdims=True)
    above = (j_idx - floor + 0.5) * voxel_mm
    ok = unseen & (lateral > t) & (above > t)
    for j in range(ny - 2, -1, -1):
        E[:, j, :] = ok[:, j, :] & (seed[:, j, :] | E[:, j + 1, :])
    return E


def _integrate(pts, zbufs, K_sub, Ts, tau, delta, progress):
    """TSDF sums at ``pts`` (N, 3): sum of clipped phi, views that updated, saw free, saw free from above."""
    acc = np.zeros(len(pts), np.float32)
    cnt = np.zeros(len(pts), np.float32)
    n_free = np.zeros(len(pts), np.int16)
    n_down = np.zeros(len(pts), np.int16)
    for i, (zb, T) in enumerate(zip(zbufs, Ts, strict=True)):
        P = (K_sub @ T[:3, :]).astype(np.float32)
        uvw = pts @ P[:, :3].T
        uvw += P[:, 3]
        z = uvw[:, 2]  # > 0: the hull is in front of every camera
        h, w = zb.shape
        inv = np.float32(1.0) / np.maximum(z, np.float32(1e-6))
        x = (uvw[:, 0] * inv + np.float32(0.5)).astype(np.int32)  # rounding; negatives fail the bounds test
        y = (uvw[:, 1] * inv + np.float32(0.5)).astype(np.int32)
        inb = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (uvw[:, 0] > -0.5 * z) & (uvw[:, 1] > -0.5 * z)
        sel = np.flatnonzero(inb)
        obs = zb[y[sel], x[sel]]
        phi = z[sel] - obs
        upd = (obs > 0) & (phi < tau)
        fr = upd & (phi < -delta)
        sel_u, sel_f = sel[upd], sel[fr]
        acc[sel_u] += np.maximum(phi[upd], -tau)
        cnt[sel_u] += 1.0
        n_free[sel_f] += 1
        cam_y = float(camera_centre_table(T)[1])
        n_down[sel_f[pts[sel_f, 1] < cam_y]] += 1
        if progress is not None:
            progress(i + 1, len(Ts))
    return acc, cnt, n_free, n_down


def _tsdf(hull: VoxelHull, zbufs, K_sub, Ts, tau: float, step: int, o: SurfaceOptions, progress):
    """The fused grid ``F`` on the hull's grid: the TSDF on every ``step``-th voxel, carving only on evidence."""
    hull_weight, delta, min_free_views = o.hull_weight, float(o.delta_mm), int(o.min_free_views)
    vals = np.asarray(hull.values, np.float32)
    coarse = vals[::step, ::step, ::step]
    idx = np.nonzero(coarse > -tau)
    pts = (np.asarray(hull.origin_table, float) + np.stack(idx, 1) * step * float(hull.voxel_mm)).astype(np.float32)
    acc, cnt, n_free, n_down = _integrate(pts, zbufs, K_sub, Ts, tau, delta, progress)
    D = np.clip(coarse, -tau, tau)
    D[idx] = (hull_weight * D[idx] + acc) / (hull_weight + cnt)
    # carve only on evidence: free space that min_free_views views saw as free (counted over
    # a voxel and its neighbours, so that z-buffer gaps do not leave specks standing in it)
    NF = np.zeros(coarse.shape, np.int16)
    NF[idx] = n_free
    weak = (D < 0) & (coarse > 0) & (ndimage.maximum_filter(NF, size=3) < min_free_views)
    D[weak] = np.clip(coarse[weak], -tau, tau)
    if o.cavity_prior:
        # "seen": some view saw a surface at or in front of the voxel (free-only sightings do not count)
        C = np.zeros(coarse.shape, np.float32)
        C[idx] = cnt - n_free
        C[(D < 0) & (coarse > 0)] = 1.0
        down = np.zeros(coarse.shape, np.int16)
        down[idx] = n_down
        E = _unseen_cavity(coarse, D, C, down, step * float(hull.voxel_mm), float(o.min_cavity_mm2), min_free_views,
                           float(o.min_opening_mm))
        D[E] = -tau
    fine = np.nonzero(vals > -tau)
    if step > 1:
        Df = ndimage.map_coordinates(D, np.stack(fine).astype(np.float32) / step, order=1, mode="nearest")
    else:
        Df = D[fine]
    F = vals.copy()
    F[fine] = np.where(Df < vals[fine] - delta, Df, vals[fine])
    return F


def fused_field(points: FusedPoints, hull: VoxelHull, K: np.ndarray, T_cam_table: Sequence[np.ndarray] | np.ndarray,
                depths: Sequence[DepthMap] | None = None, *, size: tuple[int, int] | None = None,
                options: SurfaceOptions | None = None, progress: Callable[[int, int], None] | None = None,
                **overrides) -> np.ndarray:
    """The hull's signed grid carved by the fused stereo points (``F <= h``).

    Parameters
    ----------
    points : FusedPoints
        From :func:`recon.fusion.fuse_depths` (table mm, normals towards cameras).
    hull : VoxelHull
        The visual hull; its grid is the TSDF grid.
    K : (3, 3) float64
        Intrinsics of the (H, W) images.
    T_cam_table : (V, 4, 4) float64
        Poses of the views to integrate (any subset of those that saw the points).
    depths : sequence of V DepthMap, optional
        Those views' own stereo depth: a z-buffer pixel counts only where the
        view's depth agrees with it (see :class:`SurfaceOptions`), which
        removes points seen through pinholes of the splat. Also gives the
        image size when ``size`` is not given.
    size : (W, H), optional
        Image size.
    options : SurfaceOptions, optional
        The fusion's settings; default ``SurfaceOptions()``.
    **overrides
        Fields of :class:`SurfaceOptions` by name (``cavity_prior=False``),
        replacing those of ``options``.

    Returns
    -------
    (Nx, Ny, Nz) float32
        Values on the hull's grid, > 0 inside, ``<= hull.values`` everywhere.
    """
    o = replace(options or SurfaceOptions(), **overrides)
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    if size is None:
        if not depths:
            raise ValueError("give size=(W, H) or the depth maps")
        H, W = depths[0].depth_mm.shape
        size = (W, H)
    if len(points.pts_table) == 0:
        return np.asarray(hull.values, np.float32).copy()
    stride = o.stride
    zbufs = [splat_depth(points, K, T, size, stride) for T in Ts]
    if depths is not None:
        if len(depths) != len(Ts):
            raise ValueError(f"{len(depths)} depth maps but {len(Ts)} poses")
        zbufs = [_agreeing(zb, dm, stride, o.min_confidence, o.agree_mm) for zb, dm in zip(zbufs, depths, strict=True)]
    K_sub = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(K, float)
    step = int(o.tsdf_step) if o.tsdf_step is not None else max(1, int(round(1.0 / float(hull.voxel_mm))))
    tau = float(o.trunc_mm) if o.trunc_mm is not None else max(2.0 * step * float(hull.voxel_mm), 1.5)
    return _tsdf(hull, zbufs, K_sub, Ts, tau, step, o, progress)


def fused_surface(points: FusedPoints, hull: VoxelHull, K: np.ndarray, T_cam_table: Sequence[np.ndarray] | np.ndarray,
                  depths: Sequence[DepthMap] | None = None, **kwargs) -> TableMesh:
    """Raw mesh (marching cubes, no clean-up) of :func:`fused_field`; same arguments.

    Returns
    -------
    TableMesh
        ``vertices_table`` (N, 3) float64 mm, ``faces`` (M, 3) int64
        counter-clockwise seen from outside; no normals or colours.
    """
    from .stereo import hull_mesh

    F = fused_field(points, hull, K, T_cam_table, depths, **kwargs)
    V, faces = hull_mesh(VoxelHull(values=F, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm))
    return TableMesh(vertices_table=V, faces=faces)


# --------------------------------------------------------------------------- decision
@dataclass(frozen=True)
class HullComparison:
    """Agreement of two meshes with the confident stereo depth where they differ.

    ``*_err_mm``: mean of ``min(|D_mesh - D_stereo|, cap_mm)`` over the
    confident stereo pixels where the two rendered depths differ by more than
    ``delta_mm``; ``n_pixels``: how many; ``use_fused``: the decision.
    """

    hull_err_mm: float
    fused_err_mm: float
    n_pixels: int
    use_fused: bool


def compare_to_hull(hull_mesh_vf: tuple[np.ndarray, np.ndarray], fused_mesh_vf: tuple[np.ndarray, np.ndarray],
                    depths: Sequence[DepthMap], K: np.ndarray, T_cam_table: Sequence[np.ndarray] | np.ndarray, *,
                    min_confidence: float = 0.5, delta_mm: float = 1.0, cap_mm: float = 10.0,
                    margin: float = 0.8, min_pixels: int = 50, stride: int = 4) -> HullComparison:
    """Should the fused mesh replace the hull mesh?

    Both meshes are ray-cast into each given view (every ``stride``-th
    pixel). Only pixels where they *differ* (rendered depths more than
    ``delta_mm`` apart) and stereo is confident decide: there, the error of a
    mesh is ``min(|D_mesh - D_stereo|, cap_mm)`` (the cap bounds stereo
    outliers and pixels a mesh misses). The fused mesh wins when at least
    ``min_pixels`` such pixels exist and its mean error is below ``margin``
    times the hull's. Where the meshes agree the choice does not matter, and
    comparing there would only measure stereo noise (which the fused mesh,
    built from it, would fit). Stereo depth is evidence that silhouettes do
    not use; pass depth maps of views not used to build the fused mesh (e.g.
    odd frames when even frames were fused) for a held-out test.
    """
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    if len(depths) != len(Ts):
        raise ValueError(f"{len(depths)} depth maps but {len(Ts)} poses")
    Ks = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(K, float)
    parts_h: list[np.ndarray] = []
    parts_f: list[np.ndarray] = []
    for dm, T in zip(depths, Ts, strict=True):
        d = np.where(dm.confidence >= min_confidence, dm.depth_mm, 0.0)[::stride, ::stride]
        size = (d.shape[1], d.shape[0])
        r_h = render_depth(*hull_mesh_vf, Ks, T, size)
        r_f = render_depth(*fused_mesh_vf, Ks, T, size)
        sel = (d > 0) & (np.abs(r_h - r_f) > delta_mm)
        for out, r in ((parts_h, r_h[sel]), (parts_f, r_f[sel])):
            out.append(np.where(r > 0, np.minimum(np.abs(r - d[sel]), cap_mm), cap_mm))
    e_h = np.concatenate(parts_h) if parts_h else np.zeros(0)
    e_f = np.concatenate(parts_f) if parts_f else np.zeros(0)
    if len(e_h) < min_pixels:
        return HullComparison(float(e_h.mean()) if len(e_h) else float("nan"),
                              float(e_f.mean()) if len(e_f) else float("nan"), int(len(e_h)), False)
    mh, mf = float(e_h.mean()), float(e_f.mean())
    return HullComparison(hull_err_mm=mh, fused_err_mm=mf, n_pixels=int(len(e_h)), use_fused=mf < margin * mh)
