"""Meshing (hull -> watertight outward mesh) and vertex colouring, on synthetic ground truth."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from recon.colorize import color_vertices, visible_vertices
from recon.meshing import clip_to_hull, finalize_mesh, hull_excess_mm, mesh_from_hull, mesh_stats, remesh_watertight
from recon.types import TableMesh, VoxelHull

VOLUME_REL_TOL = 0.01  # relative volume error
RADIUS_TOL_VOXELS = 0.2  # |r - R| of every vertex, in voxels
SHRINK_TOL_VOXELS = 0.02  # change of the mean radius by smoothing, in voxels


def sphere_hull(radius_mm: float, voxel_mm: float, centre_table=(0.0, 0.0, 0.0), margin: int = 3) -> VoxelHull:
    """Exact signed distance ``R - |p - c|`` of a sphere sampled at voxel centres."""
    centre = np.asarray(centre_table, float)
    n = int(np.ceil(2 * radius_mm / voxel_mm)) + 2 * margin
    origin = centre - (n - 1) / 2 * voxel_mm + 0.37 * voxel_mm  # grid not centred on the sphere
    ax = [origin[i] + voxel_mm * np.arange(n) for i in range(3)]
    P = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1)
    values = (radius_mm - np.linalg.norm(P - centre, axis=-1)).astype(np.float32)
    return VoxelHull(values=values, origin_table=origin, voxel_mm=voxel_mm)


def radii(mesh: TableMesh, centre) -> np.ndarray:
    return np.linalg.norm(mesh.vertices_table - np.asarray(centre), axis=1)


@pytest.mark.parametrize("voxel_mm", [0.5, 2.0])
def test_sphere_hull_meshes_watertight_outward_with_true_volume(voxel_mm):
    R, centre = 20.0, (3.0, 25.0, -7.0)
    mesh = mesh_from_hull(sphere_hull(R, voxel_mm, centre), max_faces=10**7, smooth_iters=0)
    stats = mesh_stats(mesh)
    assert stats.watertight and stats.n_bodies == 1
    assert stats.volume_mm3 > 0
    assert abs(stats.volume_mm3 / (4 / 3 * np.pi * R**3) - 1) < VOLUME_REL_TOL
    assert np.max(np.abs(radii(mesh, centre) - R)) < RADIUS_TOL_VOXELS * voxel_mm
    # faces counter-clockwise from outside: face normals point away from the centre
    tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    assert np.all(np.einsum("ij,ij->i", tm.face_normals, tm.triangles_center - centre) > 0)
    radial = (mesh.vertices_table - centre) / radii(mesh, centre)[:, None]
    assert np.min(np.einsum("ij,ij->i", mesh.normals_table, radial)) > 0.95
    assert np.allclose(np.linalg.norm(mesh.normals_table, axis=1), 1.0)


def test_taubin_smoothing_does_not_shrink():
    R, voxel, centre = 20.0, 1.0, (0.0, 0.0, 0.0)
    hull = sphere_hull(R, voxel, centre)
    raw = mesh_from_hull(hull, max_faces=10**7, smooth_iters=0)
    calls = []
    smooth = mesh_from_hull(hull, max_faces=10**7, smooth_iters=20, progress=lambda d, t: calls.append((d, t)))
    assert calls[-1][0] == calls[-1][1] and [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert not np.allclose(raw.vertices_table, smooth.vertices_table)  # it did smooth
    assert abs(radii(smooth, centre).mean() - radii(raw, centre).mean()) < SHRINK_TOL_VOXELS * voxel
    assert abs(mesh_stats(smooth).volume_mm3 / (4 / 3 * np.pi * R**3) - 1) < VOLUME_REL_TOL


@pytest.mark.parametrize("max_faces", [20_000, 3_000, 500])
def test_decimation_respects_max_faces_and_stays_watertight(max_faces):
    R = 20.0
    mesh = mesh_from_hull(sphere_hull(R, 0.5, (0, 0, 0)), max_faces=max_faces)
    stats = mesh_stats(mesh)
    assert stats.n_faces <= max_faces
    assert stats.n_faces >= 0.5 * max_faces
    assert stats.watertight and stats.volume_mm3 > 0
    assert abs(stats.volume_mm3 / (4 / 3 * np.pi * R**3) - 1) < 0.03


def blob_hull(seed: int) -> VoxelHull:
    """Union of random balls on an integer grid with integer radii (exact zeros on nodes)."""
    rng = np.random.default_rng(seed)
    n = 64
    P = np.stack(np.meshgrid(*[np.arange(n, dtype=float)] * 3, indexing="ij"), axis=-1)
    values = np.full((n, n, n), -1.0, np.float32)
    for _ in range(8):
        c = np.round(rng.uniform(12, 52, 3))
        r = float(rng.integers(3, 10))
        values = np.maximum(values, (r - np.linalg.norm(P - c, axis=-1)).astype(np.float32))
    values[:, :, :3] = np.maximum(values[:, :, :3], 1.0)  # a slab touching the first z border
    values[-2:, 20:40, 20:40] = 1.0  # a block touching the last x border
    return VoxelHull(values=values, origin_table=np.array([-32.0, 0.0, -32.0]), voxel_mm=1.0)


@pytest.mark.parametrize("seed, max_faces", [(0, 4000), (1, 4000), (1, 600)])
def test_blobs_with_exact_zero_samples_and_border_contact_mesh_watertight(seed, max_faces):
    hull = blob_hull(seed)
    assert np.any(hull.values == 0)  # the degenerate case the nudge exists for
    mesh = mesh_from_hull(hull, max_faces=max_faces, min_body_fraction=0.0)
    stats = mesh_stats(mesh)
    assert stats.watertight and stats.volume_mm3 > 0 and stats.n_faces <= max_faces
    # both border bodies are capped, at most a (coarse) voxel beyond the outermost samples
    lo, hi = mesh.vertices_table.min(axis=0), mesh.vertices_table.max(axis=0)
    assert lo[2] >= -32.0 - 4.0 and hi[0] <= -32.0 + 63 + 4.0
    assert hi[0] > -32.0 + 61  # the block at the x border survived


def test_small_bodies_are_dropped():
    big = sphere_hull(15.0, 1.0, (0, 0, 0), margin=12)
    P = big.centres_table(np.indices(big.values.shape).reshape(3, -1).T).reshape(*big.values.shape, 3)
    speck = (1.5 - np.linalg.norm(P - np.array([19.0, 19.0, 19.0]), axis=-1)).astype(np.float32)
    hull = VoxelHull(np.maximum(big.values, speck), big.origin_table, big.voxel_mm)
    assert mesh_stats(mesh_from_hull(hull, min_body_fraction=0.0)).n_bodies == 2
    assert mesh_stats(mesh_from_hull(hull, min_body_fraction=0.01)).n_bodies == 1


def test_finalize_mesh_fixes_inward_winding_and_holes():
    tm = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    faces = tm.faces[:, ::-1][1:]  # inside out, one triangle missing
    mesh = finalize_mesh(tm.vertices, faces, max_faces=10**6)
    stats = mesh_stats(mesh)
    assert stats.watertight and stats.volume_mm3 > 0


def test_finalize_mesh_orients_each_body_outward():
    a = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    b = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    V = np.vstack([a.vertices, b.vertices + (40.0, 0.0, 0.0)])
    F = np.vstack([a.faces, b.faces[:, ::-1] + len(a.vertices)])  # second body inside out
    mesh = finalize_mesh(V, F, max_faces=10**6)
    tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    centres = np.where(tm.triangles_center[:, :1] > 20.0, (40.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert np.all(np.einsum("ij,ij->i", tm.face_normals, tm.triangles_center - centres) > 0)
    assert abs(mesh_stats(mesh).volume_mm3 - (a.volume + b.volume)) < 1e-6 * a.volume


def test_remesh_watertight_fallback_is_closed_and_small():
    tm = trimesh.creation.annulus(r_min=10.0, r_max=25.0, height=12.0, sections=64)
    mesh = remesh_watertight(tm.vertices, tm.faces, max_faces=3000)
    stats = mesh_stats(mesh)
    assert stats.watertight and 1000 < stats.n_faces <= 3000
    assert abs(stats.volume_mm3 / tm.volume - 1) < 0.05


def test_mesh_from_hull_rejects_empty_hull():
    hull = VoxelHull(np.full((4, 4, 4), -1.0, np.float32), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="no inside voxel"):
        mesh_from_hull(hull)


# --- colouring ---------------------------------------------------------------------------------


def look_at(K_unused, centre_table, target_table=(0.0, 0.0, 0.0), up_table=(0.0, 1.0, 0.0)) -> np.ndarray:
    """``T_cam_table`` of an OpenCV camera at ``centre_table`` looking at ``target_table``."""
    c = np.asarray(centre_table, float)
    z = np.asarray(target_table, float) - c
    z /= np.linalg.norm(z)
    up = np.asarray(up_table, float)
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R_cam_table = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3] = R_cam_table
    T[:3, 3] = -R_cam_table @ c
    return T


def render_face_colors(mesh: TableMesh, face_rgb: np.ndarray, K, T_cam_table, wh=(160, 120)) -> np.ndarray:
    """Image (H, W, 3) uint8 of ``mesh`` with flat per-face colours; black background.

    Rays pass through pixel centres at integer (u, v), independently of the code under test.
    """
    W, H = wh
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices_table.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    dirs_cam = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ np.linalg.inv(K).T
    R = T_cam_table[:3, :3]
    dirs_table = dirs_cam @ R  # R^T d for row vectors
    centre = -R.T @ T_cam_table[:3, 3]
    rays = np.hstack([np.broadcast_to(centre, dirs_table.shape), dirs_table]).astype(np.float32)
    ids = scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().astype(np.int64)
    img = np.zeros((H * W, 3), np.uint8)
    hit = ids != scene.INVALID_ID
    img[hit] = face_rgb[ids[hit]]
    return img.reshape(H, W, 3)


K_TEST = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
OCTANT_RGB = np.array([[230, 20, 20], [20, 200, 30], [30, 40, 220], [240, 220, 10],
                       [200, 30, 200], [20, 210, 210], [250, 250, 250], [90, 60, 30]], np.uint8)


def octant(p: np.ndarray) -> np.ndarray:
    return (p[:, 0] > 0) * 1 + (p[:, 1] > 0) * 2 + (p[:, 2] > 0) * 4


def test_colors_come_from_the_rendered_face_pattern():
    rng = np.random.default_rng(3)
    mesh = mesh_from_hull(sphere_hull(20.0, 1.0, (0, 0, 0)), max_faces=8000)
    tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
    face_rgb = OCTANT_RGB[octant(tm.triangles_center)]
    poses = []
    for az in np.radians(np.arange(0, 360, 30)):
        for el in (-0.6, 0.6):
            c = 120.0 * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
            poses.append(look_at(K_TEST, c + rng.normal(0, 2.0, 3)))
    images = [render_face_colors(mesh, face_rgb, K_TEST, T) for T in poses]
    calls = []
    out = color_vertices(mesh, images, K_TEST, np.array(poses), progress=lambda d, t: calls.append((d, t)))
    assert calls[-1] == (len(poses), len(poses))
    assert out.colors_rgb.shape == (len(mesh.vertices_table), 3) and out.colors_rgb.dtype == np.uint8
    p = mesh.vertices_table
    interior = np.min(np.abs(p), axis=1) > 0.2 * 20.0  # away from the octant borders
    assert interior.sum() > 500
    err = np.abs(out.colors_rgb[interior].astype(int) - OCTANT_RGB[octant(p[interior])].astype(int))
    assert np.percentile(err.max(axis=1), 99) <= 2
    assert np.allclose(out.vertices_table, mesh.vertices_table) and out.normals_table is not None


def test_occluded_vertex_takes_no_colour_from_a_view_that_cannot_see_it():
    green = mesh_from_hull(sphere_hull(20.0, 1.0, (0, 0, 0)), max_faces=6000)
    red = mesh_from_hull(sphere_hull(15.0, 1.0, (0, 0, 45.0)), max_faces=4000)
    V = np.vstack([green.vertices_table, red.vertices_table])
    F = np.vstack([green.faces, red.faces + len(green.vertices_table)])
    N = np.vstack([green.normals_table, red.normals_table])
    mesh = TableMesh(V, F, normals_table=N)
    face_rgb = np.zeros((len(F), 3), np.uint8)
    face_rgb[: len(green.faces)] = (0, 255, 0)
    face_rgb[len(green.faces):] = (255, 0, 0)
    T_front = look_at(K_TEST, (0.0, 0.0, 200.0))  # sees the red ball in front of the green one's pole
    T_side = look_at(K_TEST, (200.0, 0.0, 120.0))  # sees the green pole past the red ball
    images = [render_face_colors(mesh, face_rgb, K_TEST, T) for T in (T_front, T_side)]
    pole = np.flatnonzero((np.arange(len(V)) < len(green.vertices_table))
                          & (V[:, 2] > 20.0 * np.cos(np.radians(8))))
    assert len(pole) >= 3
    assert not visible_vertices(mesh, K_TEST, T_front, images[0].shape[:2])[pole].any()
    assert visible_vertices(mesh, K_TEST, T_side, images[1].shape[:2])[pole].all()
    out = color_vertices(mesh, images, K_TEST, np.array([T_front, T_side]))
    assert np.all(out.colors_rgb[pole] == (0, 255, 0))


def test_highlight_in_one_view_is_rejected_and_unseen_vertices_are_filled():
    mesh = mesh_from_hull(sphere_hull(20.0, 1.0, (0, 0, 0)), max_faces=6000)
    face_rgb = np.full((len(mesh.faces), 3), (60, 90, 150), np.uint8)
    poses = [look_at(K_TEST, 150.0 * np.array([np.cos(a), 0.3, np.sin(a)])) for a in np.radians([0, 25, 50])]
    images = [render_face_colors(mesh, face_rgb, K_TEST, T) for T in poses]
    images[1][55:65, 75:85] = 255  # a specular blob in the middle of the middle view
    out = color_vertices(mesh, images, K_TEST, np.array(poses))
    assert np.abs(out.colors_rgb.astype(int) - (60, 90, 150)).max() <= 2  # everywhere, seen or not


def test_decimation_that_opens_the_mesh_falls_back_to_a_watertight_remesh(monkeypatch):
    import recon.meshing as meshing

    real = o3d.geometry.TriangleMesh.simplify_quadric_decimation
    calls = []

    def leaky(self, target_number_of_triangles):  # a decimator that loses one triangle
        calls.append(target_number_of_triangles)
        out = real(self, target_number_of_triangles=target_number_of_triangles)
        out.triangles = o3d.utility.Vector3iVector(np.asarray(out.triangles)[1:])
        return out

    monkeypatch.setattr(o3d.geometry.TriangleMesh, "simplify_quadric_decimation", leaky)
    hull = sphere_hull(20.0, 1.0, (0, 0, 0))
    mesh = meshing.mesh_from_hull(hull, max_faces=2000)
    stats = mesh_stats(mesh)
    assert calls == [2000]
    assert stats.watertight and 500 < stats.n_faces <= 2000
    assert abs(stats.volume_mm3 / (4 / 3 * np.pi * 20.0**3) - 1) < 0.03


CLIP_TOL_MM = 0.01  # how far outside the hull a clipped vertex may stay (exact sphere distance)


def test_clip_to_hull_pulls_decimated_vertices_back_inside():
    R, centre, voxel = 15.0, (1.0, 20.0, -2.0), 1.0
    hull = sphere_hull(R, voxel, centre)
    mesh = mesh_from_hull(hull, max_faces=800)  # coarse decimation: vertices leave the sphere
    assert hull_excess_mm(mesh, hull) > 5 * CLIP_TOL_MM
    clipped = clip_to_hull(mesh, hull)
    assert hull_excess_mm(clipped, hull) < CLIP_TOL_MM
    np.testing.assert_array_equal(clipped.faces, mesh.faces)
    assert mesh_stats(clipped).watertight
    # only vertices that were outside moved, and by less than a voxel
    move = np.linalg.norm(clipped.vertices_table - mesh.vertices_table, axis=1)
    assert move.max() < voxel
    assert np.all(move[radii(mesh, centre) <= R - 1e-6] == 0)


def test_remesh_watertight_rejects_wrong_shapes():
    with pytest.raises(ValueError, match=r"vertices_table must be \(N, 3\), got \(4, 2\)"):
        remesh_watertight(np.zeros((4, 2)), np.array([[0, 1, 2], [0, 2, 3]]), 100)
    with pytest.raises(ValueError, match=r"faces must be \(M, 3\), got \(6,\)"):
        remesh_watertight(np.zeros((4, 3)), np.arange(6), 100)
