"""A UV atlas for a mesh: projection charts packed into one texture, shared by levels of detail.

**Atlas** (:func:`uv_atlas`): every face goes to the axis direction (±X, ±Y, ±Z
of the table frame) its normal is closest to; connected faces of one direction
form a chart (charts under ``MIN_CHART_FACES`` faces join a neighbour whose
direction their normals also face, ``cos > MIN_JOIN_COS``), projected
orthographically onto that direction's plane (a face's area shrinks at most by
``cos 54.7° = 0.58``; +Y up stays up in the image), and the charts' boxes are
packed on shelves at one common scale with a gutter of ``padding`` texels.
Vertices on chart borders are split, one copy per chart.

Why not a library: measured on this 2-core machine (2026-12-02, other jobs
running), on 50 000 faces. ``xatlas`` (PyPI): 9-14 s on the smooth true vase
(6 charts, 66 % of the texture used), but **48 s of CPU** on the pipeline's own
50k hull mesh (marching cubes, smoothed, decimated: 246 charts). open3d's
``compute_uvatlas`` (no new dependency): 14-18 s on the smooth vase (57-60 %
used). Either alone breaks the bar (texturing 36 views in 15 s). The
projection atlas takes **0.2 s of CPU** on the same hull mesh (36 charts), with
the area stretch between the 5th and 95th percentile 0.73-1.14 of the mean
(xatlas 0.82-1.27), but fills only ~42 % of the texture (box packing):
:func:`recon.texture.texture_side` budgets for that (``ATLAS_FILL``), so the texel density is
what the photos resolve. Cost: more seams than an optimised atlas (they are
invisible in the bake: a texel's colour is a function of its 3D point).

**Levels of detail** (:func:`uv_atlas_levels`, :func:`recon.texture.texture_mesh` ``lods``):
coarser meshes (quadric decimation) in the same atlas, sharing the one texture.
The charts are made on the coarsest level; a finer face joins the chart of the
closest coarse face, so every chart's projection covers the same region of the
surface on every level, and the texel at a chart-plane position stands for the
same surface point on all of them: the coarse levels show the fine texture's
detail (sample, held out: 50k 27.26 dB, its 10k level 27.26, its 2k level 27.22).

The texels the charts cover (:func:`rasterize_faces`, :func:`texel_barycentrics`) are the surface
points :mod:`recon.texture` bakes.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .raycast import raycasting_scene

__all__ = ["uv_atlas", "uv_atlas_levels", "rasterize_faces", "texel_barycentrics", "closest_faces"]

#: Gutter between charts, texels; half of it is baked outward from the chart edges.
PADDING_TEXELS = 4
#: Share of the texture the packed charts cover (measured 0.41-0.42 on the vase's hull and true meshes).
ATLAS_FILL = 0.4


def uv_atlas(vertices_table: np.ndarray, faces: np.ndarray, size: int,
             padding: int = PADDING_TEXELS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Charts of a mesh packed into a ``size`` x ``size`` texture (see the module docstring).

    Parameters
    ----------
    vertices_table : (N, 3) float, mm
    faces : (M, 3) int
    size : int
        Texture side, texels.
    padding : int
        Gutter between charts, texels.

    Returns
    -------
    source_vertex : (N',) int64
        Source vertex of each atlas vertex (vertices on seams appear once per chart).
    faces : (M, 3) int64
        The same faces, in the same order, indexing atlas vertices.
    texcoords : (N', 2) float32
        In [0, 1]; ``texcoords * size - 0.5`` is the position in texel-centre coordinates (column, row).
    """
    return uv_atlas_levels([(vertices_table, faces)], size, padding)[0]


def uv_atlas_levels(levels: Sequence[tuple[np.ndarray, np.ndarray]], size: int, padding: int = PADDING_TEXELS
                    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One atlas shared by several levels of detail of one surface, finest first (``(vertices_table, faces)``).

    The charts are made on the **coarsest** level (:func:`uv_atlas`'s rule); a face of a finer level joins
    the chart of the coarsest face closest to its centroid and is projected along that chart's direction.
    Every chart's box holds all levels' projections, so a texel at a chart-plane position stands for the
    same surface point on every level (up to the levels' distance along the projection direction): the
    texture baked on the finest level is the coarser levels' texture too. Returns :func:`uv_atlas`'s
    triple for each level. With one level it is :func:`uv_atlas`.
    """
    lv = [(np.asarray(V, np.float64), np.asarray(F, np.int64)) for V, F in levels]
    for V, F in lv:
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or not len(F):
            raise ValueError(f"expected vertices (N, 3) and faces (M, 3), got {V.shape} and {F.shape}")
    Vc, Fc = lv[-1]
    chart_c, direction = _charts(Vc, Fc)
    n_charts = int(chart_c.max()) + 1
    chart_dir = np.zeros(n_charts, np.int64)
    chart_dir[chart_c] = direction
    charts = [chart_c]
    if len(lv) > 1:
        coarse = raycasting_scene(Vc, Fc)
        charts = [chart_c[closest_faces(coarse, V[F].mean(axis=1))[0]] for V, F in lv[:-1]] + charts
    parts, xys, vcharts = [], [], []
    for (V, F), chart in zip(lv, charts, strict=True):
        key = F * n_charts + chart[:, None]  # one atlas vertex per (vertex, chart) it belongs to
        uniq, inverse = np.unique(key.ravel(), return_inverse=True)
        src, vchart = uniq // n_charts, uniq % n_charts
        axes = _PLANE_AXES[chart_dir[vchart]]  # (N', 2, 3)
        xys.append(np.einsum("nkd,nd->nk", axes, V[src]))  # mm in each chart's projection plane
        vcharts.append(vchart)
        parts.append((src.astype(np.int64), inverse.reshape(F.shape).astype(np.int64)))
    uv = _pack(np.concatenate(xys), np.concatenate(vcharts), n_charts, int(size), int(padding)).astype(np.float32)
    out, at = [], 0
    for (src, faces), xy in zip(parts, xys, strict=True):
        out.append((src, faces, uv[at:at + len(xy)]))
        at += len(xy)
    return out


#: Projection directions of the charts (±X, ±Y, ±Z, table frame) and an orthonormal basis of each plane.
_DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
_PLANE_AXES = np.array([[[0, 0, -1], [0, -1, 0]], [[0, 0, 1], [0, -1, 0]], [[1, 0, 0], [0, 0, 1]],
                        [[1, 0, 0], [0, 0, -1]], [[1, 0, 0], [0, -1, 0]], [[-1, 0, 0], [0, -1, 0]]], np.float64)
#: Charts of fewer faces join a neighbouring chart that their normals also face (``MIN_JOIN_COS``).
MIN_CHART_FACES = 24
MIN_JOIN_COS = 0.2


def _charts(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chart id (M,) and projection direction (M,) of every face (module docstring)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    score = n @ _DIRECTIONS.T  # (M, 6): cos between each face normal and each direction
    label = np.argmax(score, axis=1)
    # faces sharing an edge: sort the (min, max) vertex pairs of every face edge, equal neighbours share it
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(F)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, owner = e[order], owner[order]
    same_edge = np.flatnonzero(np.all(e[1:] == e[:-1], axis=1))
    fa, fb = owner[same_edge], owner[same_edge + 1]
    fa, fb = np.concatenate([fa, fb]), np.concatenate([fb, fa])
    M = len(F)
    for _ in range(4):  # small charts join a neighbouring chart their normals face too
        keep = label[fa] == label[fb]
        _, comp = connected_components(coo_matrix((np.ones(int(keep.sum())), (fa[keep], fb[keep])), shape=(M, M)),
                                       directed=False)
        small = np.bincount(comp)[comp] < MIN_CHART_FACES
        cand = np.flatnonzero(small[fa] & ~small[fb])
        if not len(cand):
            break
        a, lab = fa[cand], label[fb[cand]]
        s = score[a, lab]
        best = np.lexsort((s, a))  # per face a: its candidates by score, the best last
        last = np.r_[a[best][1:] != a[best][:-1], True]
        a, lab, s = a[best][last], lab[best][last], s[best][last]
        ok = s > MIN_JOIN_COS
        if not ok.any():
            break
        label[a[ok]] = lab[ok]
    keep = label[fa] == label[fb]
    _, comp = connected_components(coo_matrix((np.ones(int(keep.sum())), (fa[keep], fb[keep])), shape=(M, M)),
                                   directed=False)
    return comp.astype(np.int64), label


def closest_faces(scene, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest face of a ray-casting scene's mesh to each point, and the barycentrics of the closest point.

    Parameters
    ----------
    scene : open3d.t.geometry.RaycastingScene
        Holding one mesh (:func:`recon.raycast.raycasting_scene`).
    pts : (n, 3) float, mm, the scene's frame

    Returns
    -------
    faces : (n,) int64
        Index of the closest face.
    bary : (n, 3) float32
        Barycentrics of the closest point on it (clipped to >= 0, summing to 1).
    """
    import open3d as o3d

    q = scene.compute_closest_points(o3d.core.Tensor(np.asarray(pts, np.float32)))  # type: ignore[call-overload]
    b12 = q["primitive_uvs"].numpy().astype(np.float32)
    bary = np.clip(np.column_stack([1.0 - b12.sum(axis=1), b12]), 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)
    return q["primitive_ids"].numpy().astype(np.int64), bary


def _pack(xy: np.ndarray, vchart: np.ndarray, n_charts: int, size: int, padding: int) -> np.ndarray:
    """Texture coordinates (N', 2) in [0, 1]: every chart's bounding box placed on shelves, one scale for all.

    The scale (texels per mm) starts where the boxes would fill 80 % of the texture and shrinks by 5 % until
    every box fits with ``padding`` texels between boxes and around the edge.
    """
    lo = np.full((n_charts, 2), np.inf)
    hi = np.full((n_charts, 2), -np.inf)
    np.minimum.at(lo, vchart, xy)
    np.maximum.at(hi, vchart, xy)
    ext = np.maximum(hi - lo, 1e-6)
    order = np.argsort(-ext[:, 1], kind="stable")  # tallest first: shelves waste least
    usable = size - 2 * padding
    scale = min(np.sqrt(0.8 * usable**2 / float(np.prod(ext, axis=1).sum())), (usable - 2) / float(ext.max()))
    for _ in range(200):
        w = np.ceil(ext[:, 0] * scale).astype(np.int64) + 1
        h = np.ceil(ext[:, 1] * scale).astype(np.int64) + 1
        origin = _shelves(w[order], h[order], size, padding)
        if origin is not None:
            break
        scale *= 0.95
    else:  # pragma: no cover - the scale shrinks geometrically: a few dozen steps at most
        raise ValueError("could not pack the charts")
    at = np.empty((n_charts, 2), np.float64)
    at[order] = origin
    px = at[vchart] + 0.5 + (xy - lo[vchart]) * scale  # texel-corner units: a box of w texels spans w - 1 inside
    return px / size


def _shelves(w: np.ndarray, h: np.ndarray, size: int, padding: int) -> np.ndarray | None:
    """Top-left texel (n, 2) of boxes ``w`` x ``h`` placed left to right on shelves, or None if they overflow."""
    out = np.empty((len(w), 2), np.float64)
    x = y = padding
    shelf = 0
    for i, (wi, hi) in enumerate(zip(w.tolist(), h.tolist(), strict=True)):
        if x + wi + padding > size:
            x, y, shelf = padding, y + shelf + padding, 0
        if y + hi + padding > size or wi + 2 * padding > size:
            return None
        out[i] = (x, y)
        x += wi + padding
        shelf = max(shelf, hi)
    return out


def rasterize_faces(texcoords: np.ndarray, faces: np.ndarray, size: int, grow: int) -> np.ndarray:
    """The face covering each texel of a ``size`` x ``size`` texture, the charts grown by ``grow`` texels.

    Parameters
    ----------
    texcoords : (N, 2) float
        In [0, 1] (:func:`uv_atlas`); ``texcoords * size - 0.5`` is the texel-centre position.
    faces : (M, 3) int
        Indexing ``texcoords``.
    size : int
        Texture side, texels.
    grow : int
        Rings of empty texels around the charts that take a neighbouring face.

    Returns
    -------
    (S, S) int32
        Face id of each texel (row = ``v``), -1 outside every (grown) chart.
    """
    S = int(size)
    face_id = np.full((S, S), -1, np.int32)
    pts = np.rint((texcoords[faces] * S - 0.5) * 256.0).astype(np.int32)  # 8 fractional bits (shift=8)
    for i in range(len(faces)):  # ~5 µs a triangle: 0.25 s for 50 000
        cv2.fillPoly(face_id, [pts[i]], i, lineType=cv2.LINE_8, shift=8)
    if grow > 0:  # the gutter's first rings take a neighbouring face (its edge point after clamping)
        kernel = np.ones((3, 3), np.uint8)
        ids = face_id.astype(np.float32)  # exact below 2**24 faces; OpenCV dilates no int32
        for _ in range(int(grow)):
            ids = np.where(ids < 0, cv2.dilate(ids, kernel), ids)
        face_id = ids.astype(np.int32)
    return face_id


def texel_barycentrics(texcoords, faces, size, face_id) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface coordinates of the texels :func:`rasterize_faces` gave a face.

    Parameters
    ----------
    texcoords : (N, 2) float
        In [0, 1], as for :func:`rasterize_faces`.
    faces : (M, 3) int
        Indexing ``texcoords``.
    size : int
        Texture side, texels.
    face_id : (S, S) int
        :func:`rasterize_faces`' output.

    Returns
    -------
    flat : (P,) int64
        Indices of the covered texels into the flat (S * S) texture.
    face : (P,) int64
        Their faces.
    bary : (P, 3) float32
        Barycentrics of their centres in those faces, clamped to the face (>= 0, summing to 1).
    """
    S = int(size)
    flat = np.flatnonzero(face_id.ravel() >= 0)
    f = face_id.ravel()[flat].astype(np.int64)
    p = np.column_stack([flat % S, flat // S]).astype(np.float64) + 0.5  # texel centres, texel units
    tri = texcoords[faces[f]].astype(np.float64) * S
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) > 1e-12, den, 1e-12)
    l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.column_stack([1.0 - l1 - l2, l1, l2]), 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)
    return flat, f, bary.astype(np.float32)
