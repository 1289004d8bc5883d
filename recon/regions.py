"""Hull or fused surface, decided region by region on views the fusion did not use.

The fused grid ``F`` (:func:`recon.surface.fused_field`) differs from the hull
``h`` only where stereo carved hull space. That carved space is split into
*regions*: connected components (26-neighbourhood) of carved voxels
(``h > 0 >= F``), cut further into vertical prisms of ``region_mm`` square
footprint so one long shell of surface noise is not judged as a whole (prisms,
not cubes: the unseen lower part of a cavity, emptied by the cavity prior,
is judged with the opening it hangs from). Each region is judged on held-out
views (views whose depth was not integrated into ``F``): both surfaces are
ray-cast there, and on every confident stereo pixel whose ray meets the hull
at a point of the region and where the two surfaces differ by more than
``delta_mm``, the error of a surface is

    e = min(|D_surface - D_stereo|, cap_mm)     (cap_mm where the ray misses it).

A region stays carved when at least ``min_pixels`` such pixels judged it,
its mean fused error is below ``margin`` times the hull's, and hardly any
held-out pixel sees through it where its silhouette or its stereo saw the
object (a cut through the object); everywhere else
the hull stands (``F = h``), so stereo that cannot be judged never carves.

:func:`supported_field` then keeps only what the silhouettes support: space
that carving enclosed inside the model (no camera can see into a closed
bubble) is filled back, and of the pieces carving cut a hull body into only
the largest is kept (the others float free of the body the silhouettes saw as
one).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .raycast import pixel_rays_table, render_depth
from .types import DepthMap, VoxelHull

__all__ = ["RegionOptions", "RegionChoice", "choose_regions", "supported_field"]


@dataclass(frozen=True)
class RegionChoice:
    """Outcome of :func:`choose_regions`.

    Attributes
    ----------
    values : (Nx, Ny, Nz) float32
        The fused grid with every rejected region set back to the hull.
    n_regions, n_kept, n_unjudged : int
        Carved regions; regions kept; regions too little seen to judge
        (these keep the hull).
    kept_mm3, rejected_mm3 : float
        Carved volume kept / given back to the hull.
    fused_err_mm, hull_err_mm : float
        Mean capped error over the judged pixels of the kept regions (NaN
        when none is kept).
    n_pixels : int
        Judged pixels of the kept regions.
    """

    values: np.ndarray
    n_regions: int
    n_kept: int
    n_unjudged: int
    kept_mm3: float
    rejected_mm3: float
    fused_err_mm: float
    hull_err_mm: float
    n_pixels: int


@dataclass(frozen=True)
class RegionOptions:
    """Settings of :func:`choose_regions` (see the module docstring for the test).

    Attributes
    ----------
    region_mm : float
        Edge of the vertical prisms that cut carved components into regions.
    min_confidence : float
        Stereo pixels below this confidence do not judge.
    delta_mm : float
        The two surfaces must differ by more than this at a pixel for it to judge.
    cap_mm : float
        Cap of a pixel's error (stereo outliers, pixels a surface misses).
    margin : float
        A region stays carved when its mean fused error is below ``margin``
        times the hull's.
    min_pixels : int
        Judged pixels a region needs to be judged at all.
    max_through : float
        A region is rejected when, in the held-out views, more pixels than
        this fraction of its judged ones see through it where their
        silhouette or their stereo saw the object: carving must not cut the
        object through where a camera saw it whole.
    smooth_vox : float
        Gaussian sigma (voxels) smoothing the kept fused surface against
        stereo noise (the field clipped to two voxels each side of its zero
        level, never above the hull); 0: none.
    stride : int
        Pixel step of the test.
    """

    region_mm: float = 15.0
    min_confidence: float = 0.5
    delta_mm: float = 1.0
    cap_mm: float = 10.0
    margin: float = 0.8
    min_pixels: int = 20
    max_through: float = 0.01
    smooth_vox: float = 1.0
    stride: int = 4


def _region_labels(carved: np.ndarray, voxel_mm: float, region_mm: float) -> tuple[np.ndarray, int]:
    """Connected components of ``carved`` cut into vertical prisms (axis 1 is up) of ``region_mm``; 0: not carved."""
    comp, n = ndimage.label(carved, structure=np.ones((3, 3, 3), bool))
    if n == 0:
        return comp, 0
    b = max(1, int(round(region_mm / voxel_mm)))
    idx = np.nonzero(comp)
    nb = int(carved.shape[2] // b) + 1
    key = (comp[idx].astype(np.int64) * (int(carved.shape[0] // b) + 1) + idx[0] // b) * nb + idx[2] // b
    _, lab = np.unique(key, return_inverse=True)
    out = np.zeros(carved.shape, np.int32)
    out[idx] = lab.ravel() + 1
    return out, int(lab.max()) + 1


def _judge(labels, n, hull, meshes_vf: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]], depths,
           masks, K, Ts, o: RegionOptions):
    """Per region (arrays of n + 1): summed hull error, summed fused error, judged pixels, see-through pixels.

    ``meshes_vf``: the hull's and the fused grid's meshes, each (vertices_table, faces).
    """
    hull_vf, fused_vf = meshes_vf
    stride, delta_mm, cap_mm = o.stride, o.delta_mm, o.cap_mm
    near = ndimage.maximum_filter(labels, size=5)  # a hull hit lies within a voxel or two of its region
    Ks = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(K, float)
    origin, vox = np.asarray(hull.origin_table, float), float(hull.voxel_mm)
    e_h, e_f, cnt, n_through = (np.zeros(n + 1) for _ in range(4))
    for dm, T, m in zip(depths, Ts, masks if masks is not None else [None] * len(Ts), strict=True):
        d = np.where(dm.confidence >= o.min_confidence, dm.depth_mm, 0.0)[::stride, ::stride]
        size = (d.shape[1], d.shape[0])
        r_h = render_depth(*hull_vf, Ks, T, size)
        r_f = render_depth(*fused_vf, Ks, T, size)
        # the fused surface lets this view see through where its silhouette or its stereo saw the
        # object (the hull alone is no proof: it can be larger than every silhouette)
        seen = d > 0
        if m is not None:
            seen = seen | np.asarray(m, bool)[::stride, ::stride][:seen.shape[0], :seen.shape[1]]
        through = seen & (r_h > 0) & (r_f == 0)
        sel = ((d > 0) & (r_h > 0) & (r_f - r_h > delta_mm)) | through
        if not sel.any():
            continue
        centre, dirs = pixel_rays_table(Ks, T, size)
        dirs = dirs[sel]
        p = centre + (r_h[sel] + 0.5 * vox / np.linalg.norm(dirs, axis=1))[:, None] * dirs
        ijk = np.rint((p - origin) / vox).astype(np.intp)
        ok = np.all((ijk >= 0) & (ijk < np.array(labels.shape)), axis=1)
        lab = np.zeros(len(p), np.intp)
        lab[ok] = near[tuple(ijk[ok].T)]
        dd, rh, rf, th = d[sel], r_h[sel], r_f[sel], through[sel]
        np.add.at(n_through, lab[th], 1)
        np.add.at(e_h, lab, np.minimum(np.abs(rh - dd), cap_mm))
        np.add.at(e_f, lab, np.where(rf > 0, np.minimum(np.abs(rf - dd), cap_mm), cap_mm))
        np.add.at(cnt, lab, 1)
    return e_h, e_f, cnt, n_through


def _blend_kept(h: np.ndarray, F: np.ndarray, labels: np.ndarray, keep: np.ndarray, voxel_mm: float,
                region_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The fused grid ``F`` in the kept regions, the hull's ``h`` elsewhere, and the kept voxels.

    Voxels the fusion changed belong to the region they touch (a voxel's
    dilation). Between a kept region and a rejected one of the same carved
    piece the two surfaces differ, and a hard switch leaves a step wall along
    the prism's side (box-shaped seams on the model): there the switch is a
    ramp, half way at the border and over about a third of a region each
    side. Away from rejected regions (a cavity's walls) the kept surface stays
    as fused, and away from kept ones the hull stays; ``F <= h``, so the blend
    never leaves the hull.
    """
    kept_vox = ndimage.maximum_filter(np.where(keep[labels], labels, 0), size=3) > 0
    rejected_vox = (ndimage.maximum_filter(np.where(keep[labels], 0, labels), size=3) > 0) & ~kept_vox
    if not (kept_vox.any() and rejected_vox.any()):  # no border between the two: nothing to ramp
        return np.where(kept_vox, F, h).astype(np.float32), kept_vox
    sigma = max(1.0, region_mm / 6.0 / voxel_mm)
    s_k = ndimage.gaussian_filter(kept_vox.astype(np.float32), sigma)
    s_r = ndimage.gaussian_filter(rejected_vox.astype(np.float32), sigma)
    w = kept_vox.astype(np.float32)
    ramp = (kept_vox | rejected_vox) & (s_k > 1e-3) & (s_r > 1e-3)
    w[ramp] = s_k[ramp] / (s_k[ramp] + s_r[ramp])
    return (w * F + (1.0 - w) * h).astype(np.float32), kept_vox


def choose_regions(hull: VoxelHull, values: np.ndarray, depths: Sequence[DepthMap], K: np.ndarray,
                   T_cam_table: Sequence[np.ndarray] | np.ndarray, masks: Sequence[np.ndarray] | None = None, *,
                   options: RegionOptions | None = None, **overrides) -> RegionChoice:
    """Keep the fused grid only in the carved regions that held-out stereo confirms.

    Parameters
    ----------
    hull : VoxelHull
    values : (Nx, Ny, Nz) float
        Fused grid on the hull's grid, ``<= hull.values``.
    depths : sequence of V DepthMap
        Stereo depth of views *not* integrated into ``values``.
    K : (3, 3) float64
        Intrinsics of the depth maps' (H, W) images.
    T_cam_table : (V, 4, 4) float64
        Their poses.
    masks : sequence of V (H, W) bool, optional
        Those views' silhouettes (see ``RegionOptions.max_through``).
    options : RegionOptions, optional
        The test's settings; default ``RegionOptions()``.
    **overrides
        Fields of :class:`RegionOptions` by name (``min_pixels=10``),
        replacing those of ``options``.

    Returns
    -------
    RegionChoice
    """
    o = replace(options or RegionOptions(), **overrides)
    from .stereo import hull_mesh

    h = np.asarray(hull.values, np.float32)
    F = np.asarray(values, np.float32)
    if F.shape != h.shape:
        raise ValueError(f"values: expected the hull's shape {h.shape}, got {F.shape}")
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    if len(depths) != len(Ts):
        raise ValueError(f"{len(depths)} depth maps but {len(Ts)} poses")
    vox3 = float(hull.voxel_mm) ** 3
    labels, n = _region_labels((h > 0) & (F <= 0), float(hull.voxel_mm), o.region_mm)
    nan = float("nan")
    if n == 0:
        return RegionChoice(h.copy(), 0, 0, 0, 0.0, 0.0, nan, nan, 0)
    fused = VoxelHull(values=F, origin_table=hull.origin_table, voxel_mm=hull.voxel_mm)
    if masks is not None and len(masks) != len(Ts):
        raise ValueError(f"{len(masks)} masks but {len(Ts)} poses")
    e_h, e_f, cnt, n_through = _judge(labels, n, hull, (hull_mesh(hull), hull_mesh(fused)), depths, masks, K, Ts, o)
    judged = cnt >= o.min_pixels
    keep = judged & (e_f < o.margin * e_h) & (n_through <= o.max_through * np.maximum(cnt, 1.0))
    keep[0] = False
    size = np.bincount(labels.ravel(), minlength=n + 1) * vox3
    out, kept_vox = _blend_kept(h, F, labels, keep, float(hull.voxel_mm), o.region_mm)
    if o.smooth_vox > 0 and kept_vox.any():
        # stereo noise: smooth the kept surface (the field clipped to a band, so deep values
        # do not bleed through thin walls), never above the hull
        band = 2.0 * float(hull.voxel_mm)
        near = ndimage.maximum_filter(kept_vox, size=5)
        sm = ndimage.gaussian_filter(np.clip(out, -band, band), o.smooth_vox)
        out = np.where(near, np.minimum(np.where(np.abs(out) < band, sm, out), h), out).astype(np.float32)
    k = np.flatnonzero(keep)
    ph, pf, pc = e_h[k].sum(), e_f[k].sum(), cnt[k].sum()
    return RegionChoice(values=out, n_regions=n, n_kept=int(len(k)), n_unjudged=int((~judged[1:]).sum()),
                        kept_mm3=float(size[k].sum()), rejected_mm3=float(size[1:].sum() - size[k].sum()),
                        fused_err_mm=float(pf / pc) if pc else nan, hull_err_mm=float(ph / pc) if pc else nan,
                        n_pixels=int(pc))


def supported_field(hull_values: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` with enclosed voids filled back to the hull and carved-off fragments dropped.

    Parameters
    ----------
    hull_values : (Nx, Ny, Nz) float
        The hull's grid (> 0 inside).
    values : (Nx, Ny, Nz) float
        A grid carved from it (``<= hull_values``).

    Returns
    -------
    (Nx, Ny, Nz) float32
        Within each hull body (6-connected inside), only the largest
        6-connected piece of ``values > 0`` stays inside; voids that no
        outside space reaches are inside again, at the hull's value.
    """
    h = np.asarray(hull_values, np.float32)
    F = np.asarray(values, np.float32).copy()
    if F.shape != h.shape:
        raise ValueError(f"values: expected shape {h.shape}, got {F.shape}")
    inside = F > 0
    void = ndimage.binary_fill_holes(inside) & ~inside & (h > 0)
    F[void] = h[void]
    inside = F > 0
    body, nb = ndimage.label(h > 0)
    piece, npc = ndimage.label(inside)
    if npc <= 1:
        return F
    vol = np.bincount(piece.ravel(), minlength=npc + 1)
    vol[0] = 0
    # each piece lies in exactly one hull body (F <= h); keep the biggest piece per body
    first = ndimage.labeled_comprehension(body, piece, np.arange(1, npc + 1), np.max, np.int64, 0)
    best = np.zeros(nb + 1, np.int64)
    order = np.argsort(vol[1:])
    for p in order:  # ascending: the largest piece of a body is written last
        best[first[p]] = p + 1
    keep = np.zeros(npc + 1, bool)
    keep[best[best > 0]] = True
    drop = inside & ~keep[piece]
    F[drop] = np.minimum(F[drop], -1e-3 * np.float32(1.0))
    return F
