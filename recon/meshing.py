"""Visual hull (signed voxel grid) -> watertight, outward, smoothed, decimated mesh.

The hull is a signed function ``f`` sampled at voxel centres
``p_ijk = origin_table + (i, j, k) * voxel_mm`` (> 0 inside, < 0 outside); the
surface is its zero level set ``f(p) = 0``, extracted by marching cubes
(Lewiner) with linear interpolation along grid edges: a crossing between
samples ``f_a > 0 > f_b`` lies at ``p_a + f_a / (f_a - f_b) (p_b - p_a)``.

When the full-resolution surface would exceed ``max_faces`` more than
fourfold, marching cubes runs on every ``step``-th sample instead (quadric
decimation time grows with its input; the hull is smooth at that scale).

Everything after extraction is shared with the fusion stage through
:func:`finalize_mesh`:

1. merge duplicate vertices, drop degenerate/duplicate faces, fill holes;
2. orient every closed body outward (signed volume > 0, faces counter-clockwise
   seen from outside);
3. drop specks (bodies smaller than a fraction of the largest);
4. Taubin λ|μ smoothing (λ = 0.5, μ = -0.53), which removes marching-cubes
   staircases without the shrinkage of plain Laplacian smoothing;
5. quadric decimation to ``max_faces`` (open3d). If the result is not
   watertight, :func:`remesh_watertight` re-extracts the surface from the
   mesh's own signed distance on a coarser grid, which is closed by
   construction;
6. area-weighted vertex normals.

Units are the table frame's millimetres throughout.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from skimage import measure

from calib.types import as_points

from .raycast import raycasting_scene
from .types import TableMesh, VoxelHull

__all__ = ["MeshStats", "mesh_from_hull", "finalize_mesh", "remesh_watertight", "mesh_stats", "clip_to_hull",
           "hull_excess_mm"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None] | None

# Taubin pass band: λ = 0.5, μ = -0.53 (k_PB = 1/λ + 1/μ ≈ 0.11).
_TAUBIN_LAMBDA = 0.5
_TAUBIN_NU = 0.53
# mesh_from_hull extracts on a coarser grid when full resolution would give more
# than this many times max_faces (quadric decimation time grows with its input).
_MAX_DECIMATION_RATIO = 4.0
# Marching-cubes faces per (surface area / voxel²), measured on spheres and blobs
# (≈ 3.0); used to pick the grid of the watertight remesh.
_MC_FACES_PER_AREA = 3.0


@dataclass(frozen=True)
class MeshStats:
    """Summary of a mesh in the table frame.

    Attributes
    ----------
    volume_mm3 : float
        Enclosed volume, mm³ (signed: > 0 for an outward-oriented closed mesh).
    area_mm2 : float
        Surface area, mm².
    watertight : bool
        Every edge shared by exactly two faces with consistent winding (trimesh).
    n_faces, n_vertices : int
    n_bodies : int
        Connected components.
    """

    volume_mm3: float
    area_mm2: float
    watertight: bool
    n_faces: int
    n_vertices: int
    n_bodies: int


def mesh_from_hull(
    hull: VoxelHull,
    *,
    max_faces: int = 100_000,
    smooth_iters: int = 10,
    min_body_fraction: float = 0.01,
    progress: Progress = None,
) -> TableMesh:
    """Watertight outward mesh of the hull's zero level set.

    Parameters
    ----------
    hull : VoxelHull
        ``values`` (Nx, Ny, Nz) float, > 0 inside, sampled at voxel centres.
    max_faces : int
        Upper bound on the number of triangles of the result.
    smooth_iters : int
        Taubin half-steps (λ and μ alternate; an odd count is rounded up);
        0 disables smoothing.
    min_body_fraction : float
        Bodies whose volume is below this fraction of the largest body's are
        dropped (carving specks); 0 keeps everything.
    progress : callable(done, total), optional
        Called after each stage.

    Returns
    -------
    TableMesh
        Vertices (N, 3) mm in the table frame, faces (M, 3) counter-clockwise
        seen from outside, unit outward vertex normals; no colours.

    Raises
    ------
    ValueError
        If the grid is not 3-D, has no inside sample, or the arguments are bad.
    """
    values = np.asarray(hull.values, dtype=np.float32)
    if values.ndim != 3 or min(values.shape) < 2:
        raise ValueError(f"hull.values: expected (Nx, Ny, Nz) with every size >= 2, got {values.shape}")
    voxel_mm = float(hull.voxel_mm)
    if not voxel_mm > 0:
        raise ValueError(f"hull.voxel_mm must be > 0, got {hull.voxel_mm}")
    origin = np.asarray(hull.origin_table, dtype=np.float64).reshape(3)
    if not np.any(values > 0):
        raise ValueError("hull has no inside voxel (all values <= 0): nothing to mesh")

    vertices_table, faces = _marching_cubes_closed(values, origin, voxel_mm)
    step = int(np.sqrt(len(faces) / (_MAX_DECIMATION_RATIO * max_faces)))
    if step > 1:  # far finer than asked: extract on every step-th sample instead of decimating it all
        vertices_table, faces = _marching_cubes_closed(values, origin, voxel_mm, step=step)
    if progress is not None:
        progress(1, 6)
    stage = (lambda d, t: progress(d + 1, t + 1)) if progress is not None else None
    return finalize_mesh(vertices_table, faces, max_faces, smooth_iters=smooth_iters,
                         min_body_fraction=min_body_fraction, assume_outward=True, progress=stage)


def _marching_cubes_closed(values: np.ndarray, origin_table: np.ndarray, voxel_mm: float, step: int = 1):
    """Zero level set of ``values`` as a closed, outward triangle soup (mm, table frame).

    The grid is padded with ``step`` outside layers so bodies touching the
    grid's border are capped (marching cubes samples every ``step``-th node,
    so the last one sampled lies in the padding). Samples that are exactly 0
    are nudged outside: marching cubes places a vertex on a grid node there,
    which several cubes share without merging, and the surface pinches into
    non-manifold edges.
    """
    eps = np.float32(1e-3 * voxel_mm)
    # the padded grid is allocated once and filled a slab at a time (a copy, then np.pad of it, held
    # three grids at once: 7.7 GB at resolution 1024)
    v = np.full([n + 2 * step for n in values.shape], -voxel_mm, dtype=values.dtype)
    for x0 in range(0, values.shape[0], 32):
        slab = values[x0:x0 + 32]
        v[step + x0:step + x0 + len(slab), step:step + values.shape[1], step:step + values.shape[2]] = \
            np.where(np.abs(slab) < eps, -eps, slab)
    verts, faces, _, _ = measure.marching_cubes(v, level=0.0, spacing=(voxel_mm,) * 3, step_size=step)
    # Padding shifts indices by ``step`` voxels. skimage winds triangles
    # clockwise seen from the side of larger values (our inside) for an
    # (x, y, z) grid, i.e. inward: reverse them.
    verts_table = verts.astype(np.float64) + (origin_table - step * voxel_mm)
    return verts_table, faces[:, ::-1].astype(np.int64)


def finalize_mesh(
    vertices_table: np.ndarray,
    faces: np.ndarray,
    max_faces: int = 100_000,
    *,
    smooth_iters: int = 0,
    min_body_fraction: float = 0.0,
    assume_outward: bool = False,
    progress: Progress = None,
) -> TableMesh:
    """Clean, orient, smooth, decimate and give normals to a triangle mesh.

    Parameters
    ----------
    vertices_table : (N, 3) float
        Vertex positions, mm, table frame.
    faces : (M, 3) int
        Vertex indices of the triangles (any winding; it is fixed here).
    max_faces : int
        Upper bound on the number of triangles of the result.
    smooth_iters : int
        Taubin half-steps (0: none; odd counts are rounded up so λ and μ pair).
    min_body_fraction : float
        Drop bodies whose |volume| is below this fraction of the largest's.
    assume_outward : bool
        The faces are known to be wound counter-clockwise from outside (as
        marching cubes of a signed grid gives, enclosed cavities included):
        skip re-orientation. Otherwise every closed body is turned to positive
        volume, which would also turn an enclosed cavity inside out.
    progress : callable(done, total), optional

    Returns
    -------
    TableMesh
        Outward-oriented mesh with unit vertex normals. Watertight whenever
        the input could be closed by filling holes; check :func:`mesh_stats`.

    Raises
    ------
    ValueError
        On bad shapes, out-of-range indices, or when nothing is left.
    """
    V = np.asarray(vertices_table, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices_table: expected (N, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces: expected (M, 3) integers, got {F.shape} {F.dtype}")
    if len(F) == 0:
        raise ValueError("faces: empty mesh")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"faces: indices must lie in [0, {len(V)}), got [{F.min()}, {F.max()}]")
    if int(max_faces) < 4:
        raise ValueError(f"max_faces must be >= 4, got {max_faces}")
    if smooth_iters < 0:
        raise ValueError(f"smooth_iters must be >= 0, got {smooth_iters}")

    def report(done: int) -> None:
        if progress is not None:
            progress(done, 5)

    mesh = _clean_and_orient(trimesh.Trimesh(V, F.astype(np.int64), process=True), assume_outward)
    report(1)
    if min_body_fraction > 0:
        mesh = _drop_small_bodies(mesh, min_body_fraction)
    report(2)
    if smooth_iters > 0:
        iters = int(smooth_iters) + (int(smooth_iters) % 2)
        trimesh.smoothing.filter_taubin(mesh, lamb=_TAUBIN_LAMBDA, nu=_TAUBIN_NU, iterations=iters)
    report(3)
    if len(mesh.faces) > max_faces:
        mesh = _decimate(mesh, int(max_faces))
    report(4)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    report(5)
    return TableMesh(vertices_table=np.asarray(mesh.vertices, dtype=np.float64),
                     faces=np.asarray(mesh.faces, dtype=np.int64), normals_table=normals)


def _clean_and_orient(mesh: trimesh.Trimesh, assume_outward: bool = False) -> trimesh.Trimesh:
    """Drop degenerate/duplicate faces, fill holes, orient each body outward."""
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no non-degenerate face")
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
        if not mesh.is_watertight:
            log.warning("mesh is not watertight after hole filling (%d faces)", len(mesh.faces))
    if assume_outward:
        return mesh
    if mesh.is_winding_consistent:
        labels, volumes = _body_volumes(mesh)
        faces = mesh.faces.copy()
        inverted = volumes[labels] < 0
        faces[inverted] = faces[inverted][:, ::-1]
        mesh.faces = faces
    else:
        trimesh.repair.fix_normals(mesh, multibody=True)
    return mesh


def _body_volumes(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Connected-body label of each face (M,) and signed volume of each body, mm³.

    A body's volume is the sum of its faces' signed tetrahedra with the
    origin, ``v0 . (v1 x v2) / 6`` (meaningful for closed bodies).
    """
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    tri = mesh.triangles
    tet = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    return labels, np.bincount(labels, weights=tet)


def _drop_small_bodies(mesh: trimesh.Trimesh, fraction: float) -> trimesh.Trimesh:
    labels, volumes = _body_volumes(mesh)
    if len(volumes) <= 1:
        return mesh
    size = np.abs(volumes)
    keep = size >= fraction * size.max()
    log.debug("kept %d of %d bodies", keep.sum(), len(keep))
    mesh.update_faces(keep[labels])
    mesh.remove_unreferenced_vertices()
    return mesh


def _decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """Quadric decimation to ``max_faces``; watertight remesh if that opens the mesh."""
    import open3d as o3d

    was_watertight = mesh.is_watertight
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    om = om.simplify_quadric_decimation(target_number_of_triangles=max_faces)
    out = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles, dtype=np.int64), process=True)
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    if not was_watertight or (out.is_watertight and out.volume > 0 and len(out.faces) <= max_faces):
        return out
    log.info("quadric decimation opened the mesh; remeshing its signed distance instead")
    rem = remesh_watertight(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_faces)
    return trimesh.Trimesh(rem.vertices_table, rem.faces, process=False)


def remesh_watertight(vertices_table: np.ndarray, faces: np.ndarray, max_faces: int) -> TableMesh:
    """Closed re-extraction of a watertight mesh with at most ``max_faces`` triangles.

    Samples the mesh's signed distance (open3d ``RaycastingScene``, sign by
    majority of 3 ray parities) on a grid whose voxel is chosen from the
    surface area so marching cubes yields about ``max_faces`` triangles, and
    coarsens the grid until it does not exceed it. Always watertight; detail
    below the voxel size is lost, so prefer quadric decimation when it works.

    Parameters
    ----------
    vertices_table : (N, 3) float, mm
    faces : (M, 3) int
        A closed mesh (the inside must be well defined).
    max_faces : int

    Returns
    -------
    TableMesh
        Outward mesh with vertex normals.
    """
    import open3d as o3d

    V = as_points(vertices_table, 3, "vertices_table")
    F = np.asarray(faces, dtype=np.int64)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"faces must be (M, 3), got {F.shape}")
    area = float(trimesh.Trimesh(V, F, process=False).area)
    scene = raycasting_scene(V, F)
    voxel = np.sqrt(_MC_FACES_PER_AREA * area / max_faces)
    lo, hi = V.min(axis=0), V.max(axis=0)
    for _ in range(20):
        origin = lo - 1.5 * voxel
        n = np.ceil((hi - lo) / voxel).astype(int) + 4
        axes = [origin[i] + voxel * np.arange(n[i]) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).astype(np.float32)
        # open3d's stubs make Tensor's dtype and device required; they are optional
        sd = scene.compute_signed_distance(o3d.core.Tensor(grid), nsamples=3).numpy()  # type: ignore[call-overload]
        Vr, Fr = _marching_cubes_closed(-sd, origin, voxel)  # inside: sd < 0
        if len(Fr) <= max_faces:
            mesh = _clean_and_orient(trimesh.Trimesh(Vr, Fr, process=True))
            return TableMesh(vertices_table=np.asarray(mesh.vertices, dtype=np.float64),
                             faces=np.asarray(mesh.faces, dtype=np.int64),
                             normals_table=np.asarray(mesh.vertex_normals, dtype=np.float64))
        voxel *= 1.1 * np.sqrt(len(Fr) / max_faces)
    raise ValueError(f"could not remesh below {max_faces} faces")  # pragma: no cover


def mesh_stats(mesh: TableMesh) -> MeshStats:
    """Volume (mm³), area (mm²), watertightness and sizes of ``mesh``."""
    tm = trimesh.Trimesh(np.asarray(mesh.vertices_table, float), np.asarray(mesh.faces), process=False)
    watertight = bool(tm.is_watertight)
    n_bodies = len(trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(tm.faces)),
                                                      min_len=1))
    return MeshStats(volume_mm3=float(tm.volume), area_mm2=float(tm.area), watertight=watertight,
                     n_faces=int(len(tm.faces)), n_vertices=int(len(tm.vertices)), n_bodies=n_bodies)


def _hull_at(hull: VoxelHull, pts_table: np.ndarray) -> np.ndarray:
    """Hull value (mm, > 0 inside) at table points, trilinear; outside the grid: the border's value."""
    from scipy import ndimage

    ijk = (np.asarray(pts_table, float) - np.asarray(hull.origin_table, float)) / float(hull.voxel_mm)
    return ndimage.map_coordinates(np.asarray(hull.values, np.float32), ijk.T, order=1, mode="nearest")


def hull_excess_mm(mesh: TableMesh, hull: VoxelHull) -> float:
    """How far (mm) the mesh's farthest vertex lies outside the hull; 0 when none does."""
    return float(max(0.0, -float(_hull_at(hull, mesh.vertices_table).min(initial=0.0))))


def clip_to_hull(mesh: TableMesh, hull: VoxelHull, iters: int = 8) -> TableMesh:
    """Move vertices that smoothing or decimation pushed outside the hull back into it.

    A vertex ``v`` with hull value ``h(v) < 0`` steps along the hull's
    gradient ``g`` (central differences of the trilinear ``h`` over half a
    voxel): ``v += s g / |g|^2`` with ``s = -h(v)`` plus a small margin,
    the step at most half a voxel, halved where it does not raise ``h``
    (the sampled hull is not smooth at sub-voxel scale). ``iters`` rounds.
    Steps are sub-voxel, so the faces are kept.

    Returns
    -------
    TableMesh
        Same faces and colours, moved vertices, recomputed normals.
    """
    V = np.asarray(mesh.vertices_table, float).copy()
    e = 0.5 * float(hull.voxel_mm)
    hv = _hull_at(hull, V)
    for _ in range(int(iters)):
        out = np.flatnonzero(hv < 0)
        if len(out) == 0:
            break
        P = V[out]
        g = np.stack([(_hull_at(hull, P + e * a) - _hull_at(hull, P - e * a)) / (2 * e) for a in np.eye(3)], 1)
        g2 = np.maximum(np.sum(g * g, 1), 1e-6)
        step = ((-hv[out] + 0.05 * e) / g2)[:, None] * g
        n = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, e / np.maximum(n, 1e-12))
        for _ in range(4):
            h_new = _hull_at(hull, P + step)
            better = h_new > hv[out]
            V[out[better]] = P[better] + step[better]
            hv[out[better]] = h_new[better]
            out, P, step = out[~better], P[~better], 0.5 * step[~better]
            if len(out) == 0:
                break
    tm = trimesh.Trimesh(V, np.asarray(mesh.faces), process=False)
    return TableMesh(vertices_table=V, faces=np.asarray(mesh.faces, np.int64),
                     normals_table=np.asarray(tm.vertex_normals, np.float64), colors_rgb=mesh.colors_rgb)
