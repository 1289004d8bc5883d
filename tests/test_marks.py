"""Angle marks: the reader reads what the generator draws.

Synthetic photos: the target raster of ``turntable.pattern.render_target_image``
warped into a camera through the plane homography at 2x supersampling, on a
dark table, with an occluding object, a light gradient, blur, noise and JPEG-95.
The pose handed to the reader is the true one turned about the table normal by
a random angle (what a ring solver gives), sometimes with realistic errors.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from calib.camera import make_T, plane_homography, project_points
from calib.marks import AngleReading, align_pose_to_marks, read_turntable_angle, turntable_rotation
from calib.target import TargetSpec, ink_at, mark_cells, mark_edges, mark_halfcells, turntable_angle
from calib.types import CalibrationError
from turntable.pattern import render_target_image

SPEC = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
SIZE = (1280, 960)
RASTER_PX_PER_MM = 8.0
MEDIAN_BAR_DEG = 0.1
MAX_BAR_DEG = 0.3


@functools.lru_cache(maxsize=4)
def _raster(spec: TargetSpec) -> np.ndarray:
    return render_target_image(spec, RASTER_PX_PER_MM, supersample=2)


def look_at_pose(elevation_deg: float, azimuth_deg: float, distance_mm: float,
                 target_table=(0.0, 20.0, 0.0)) -> np.ndarray:
    """T_cam_table of a camera above the table (Y up) looking at ``target_table``."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    C = distance_mm * np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])
    z = np.asarray(target_table, float) - C
    z /= np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0])
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R_cam_table = np.column_stack([x, y, z]).T
    return make_T(R_cam_table, -R_cam_table @ C)


def object_outline(K, T_cam_table, radius_mm, height_mm) -> np.ndarray:
    """Image outline (N, 2) of an upright cylinder standing on the table centre."""
    th = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    ring = np.column_stack([radius_mm * np.cos(th), np.zeros_like(th), radius_mm * np.sin(th)])
    pts = np.vstack([ring, ring + [0.0, height_mm, 0.0]])
    return cv2.convexHull(project_points(K, T_cam_table, pts).astype(np.float32)).reshape(-1, 2)


def half_disc_outline(K, T_cam_table, theta0_deg) -> np.ndarray:
    """Image outline (N, 2) of the table half-disc theta0 .. theta0 + 180 deg, radius 140 mm."""
    th = np.radians(theta0_deg + np.linspace(0.0, 180.0, 91))
    pts = np.column_stack([140 * np.cos(th), np.zeros_like(th), 140 * np.sin(th)])
    return project_points(K, T_cam_table, np.vstack([[0.0, 0.0, 0.0], pts]))


def synthetic_photo(spec, K, T_cam_table, rng, *, occluders=(), occluder_grey=90.0, blur_px=0.7,
                    noise_sigma=2.0, jpeg_quality=95, size=SIZE) -> np.ndarray:
    """BGR uint8 photo of the printed target seen by (K, T_cam_table)."""
    W, H = size
    S = 2
    raster = _raster(spec).astype(np.float32)
    n = raster.shape[0]
    c = (n - 1) / 2.0
    A = np.array([[1 / RASTER_PX_PER_MM, 0, -c / RASTER_PX_PER_MM],
                  [0, 1 / RASTER_PX_PER_MM, -c / RASTER_PX_PER_MM], [0, 0, 1.0]])
    D = np.array([[S, 0, (S - 1) / 2.0], [0, S, (S - 1) / 2.0], [0, 0, 1.0]])
    M = D @ plane_homography(K, T_cam_table) @ A
    table = 45.0
    paper = cv2.warpPerspective(raster / 255.0, M, (W * S, H * S), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    img = np.where(paper < 0, table, 20.0 + 215.0 * np.clip(paper, 0, 1)).astype(np.float32)
    for outline in occluders:
        mask = np.zeros(img.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(outline * S + (S - 1) / 2.0).astype(np.int32)], 1)
        shade = occluder_grey + 20.0 * cv2.GaussianBlur(rng.standard_normal(img.shape).astype(np.float32), (0, 0), 6)
        img = np.where(mask > 0, shade, img)
    img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
    yy, xx = np.mgrid[0:H, 0:W]
    g = rng.uniform(-0.25, 0.25, 2)
    img *= 1.0 + g[0] * (xx / W - 0.5) + g[1] * (yy / H - 0.5)      # uneven light
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = img + rng.normal(0.0, noise_sigma, img.shape)
    bgr = np.clip(np.stack([img * 0.95, img, img * 1.05], axis=-1), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def _angle_err_deg(a, b) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _solver_pose(T_true, alpha_deg, rng=None, normal_err_deg=0.0):
    """What a ring solver returns: the true pose with table X turned to an arbitrary angle.

    The printed 0 deg mark then sits at solver angle ``alpha_deg``; optionally the
    plane normal is tilted by ``normal_err_deg`` about a random in-plane axis.
    """
    T = T_true @ turntable_rotation(-alpha_deg)
    if normal_err_deg:
        n = T[:3, 1]
        axis = rng.normal(size=3)
        axis -= n * (axis @ n)
        axis /= np.linalg.norm(axis)
        R = cv2.Rodrigues(axis * np.radians(normal_err_deg))[0]
        T = T.copy()
        T[:3, :3] = R @ T[:3, :3]
    return T


def _random_camera(rng, elevation_deg):
    f = rng.uniform(1300.0, 1700.0)
    K = np.array([[f, 0, (SIZE[0] - 1) / 2], [0, f, (SIZE[1] - 1) / 2], [0, 0, 1.0]])
    return K, look_at_pose(elevation_deg, rng.uniform(0, 360), rng.uniform(400.0, 550.0))


# ----------------------------------------------------------------------------- the code and its geometry

def test_default_code_windows_of_seven_sectors_are_unique():
    code = np.array([c == "1" for c in SPEC.mark_code])
    n = code.size
    for w, min_dist in ((7, 1), (12, 2), (18, 4), (36, 11)):
        win = code[(np.arange(n)[:, None] + np.arange(w)[None, :]) % n].astype(int)
        d = (win[:, None, :] != win[None, :, :]).sum(axis=-1)
        np.fill_diagonal(d, w + 1)
        assert d.min() >= min_dist, f"windows of {w} sectors differ in only {d.min()} sectors"


def test_manchester_track_has_an_edge_in_every_sector():
    ink = mark_halfcells(SPEC)
    assert ink.size == 2 * SPEC.n_sectors and ink.sum() == SPEC.n_sectors
    assert np.all(ink[0::2] != ink[1::2])            # the mid-sector edge, whatever the bit
    theta, to_ink = mark_edges(SPEC)
    half = np.pi / SPEC.n_sectors
    assert np.allclose(theta / half, np.round(theta / half))
    mids = np.round(theta / half).astype(int) % 2 == 1
    assert mids.sum() == SPEC.n_sectors
    assert np.all(to_ink[:-1] != to_ink[1:])          # polarities alternate along the track


def test_default_marks_sit_outside_the_outer_ring_with_a_white_gap():
    assert (SPEC.mark_r0_mm, SPEC.mark_r1_mm) == (86.0, 98.0)
    assert SPEC.mark_r0_mm - (SPEC.r_outer_mm + SPEC.stroke_mm / 2) >= 4.0
    assert TargetSpec(80, 50, 3, mark_r0_mm=86.0) == SPEC
    with pytest.raises(ValueError, match="white gap"):
        TargetSpec(80, 50, 3, mark_r0_mm=84.0)
    with pytest.raises(ValueError, match="periodic"):
        TargetSpec(80, 50, 3, mark_code="0011" * 18)
    with pytest.raises(ValueError, match="'0' and '1'"):
        TargetSpec(80, 50, 3, mark_code="01x" * 24)


# the default code, and one turned so that an ink run crosses angle 0 (sector 71 ends in ink, 0 starts in it)
WRAPPING_CODE = SPEC.mark_code[2:] + SPEC.mark_code[:2]


@pytest.mark.parametrize("spec", [SPEC, TargetSpec(80.0, 50.0, 3.0, mark_code=WRAPPING_CODE)])
def test_mark_cells_and_ink_at_describe_the_same_ink(spec):
    rng = np.random.default_rng(3)
    r = rng.uniform(spec.mark_r0_mm - 2, spec.mark_r1_mm + 2, 20000)
    th = np.concatenate([rng.uniform(0, 2 * np.pi, 19000), rng.uniform(-0.02, 0.02, 1000)])
    X, Z = r * np.cos(th), r * np.sin(th)
    cells = mark_cells(spec)
    t = turntable_angle(X, Z)
    in_cell = np.zeros(r.size, bool)
    for t0, t1, r0, r1 in cells:
        ang = (t >= t0) & (t < t1) | (t + 2 * np.pi < t1)
        in_cell |= ang & (r >= r0) & (r <= r1)
    assert np.array_equal(in_cell, ink_at(spec, X, Z))
    assert cells.shape[0] > spec.n_sectors // 2
    assert (cells[:, 1].max() > 2 * np.pi) == (spec.mark_code == WRAPPING_CODE)
    assert mark_cells(TargetSpec(80, 50, 3, marks=False)).shape == (0, 4)
    assert not ink_at(TargetSpec(80, 50, 3, marks=False), X, Z).any()


def test_raster_draws_the_marks_with_table_x_along_columns_and_z_along_rows():
    px = 4.0
    img = render_target_image(SPEC, px, supersample=2)
    n = img.shape[0]
    c = (n - 1) / 2.0
    j, i = np.meshgrid(np.arange(n), np.arange(n))
    X, Z = (j - c) / px, (i - c) / px
    ink = ink_at(SPEC, X, Z)
    # pixels whose whole neighbourhood agrees must be pure ink / pure paper
    solid = ((ink == np.roll(ink, 1, 0)) & (ink == np.roll(ink, -1, 0))
             & (ink == np.roll(ink, 1, 1)) & (ink == np.roll(ink, -1, 1)))
    assert np.all(img[solid & ink] == 0) and np.all(img[solid & ~ink] == 255)
    assert np.any(solid & ink & (np.hypot(X, Z) > SPEC.mark_r0_mm))


# ----------------------------------------------------------------------------- pose conventions

def test_turntable_rotation_turns_angles_forward_about_minus_y():
    T = turntable_rotation(90.0)
    assert np.allclose(T[:3, :3] @ [1.0, 0, 0], [0, 0, 1.0])     # theta 0 -> 90 deg (X -> Z)
    assert np.allclose(T[:3, :3], cv2.Rodrigues(np.array([0.0, -np.pi / 2, 0.0]))[0])
    pts = np.array([[80.0 * np.cos(0.3), 0.0, 80.0 * np.sin(0.3)]])
    out = pts @ turntable_rotation(25.0)[:3, :3].T
    assert np.isclose(np.degrees(turntable_angle(out[:, 0], out[:, 2]))[0], np.degrees(0.3) + 25.0)


def test_align_pose_undoes_the_solvers_arbitrary_rotation():
    rng = np.random.default_rng(7)
    T_true = look_at_pose(35.0, 20.0, 450.0)
    alpha = rng.uniform(0, 360)
    T_s = _solver_pose(T_true, alpha)
    assert np.allclose(align_pose_to_marks(T_s, alpha), T_true)
    assert np.allclose(T_s[:3, 1], T_true[:3, 1]) and np.allclose(T_s[:3, 3], T_true[:3, 3])
    with pytest.raises(ValueError):
        align_pose_to_marks(np.eye(3), 0.0)


# ----------------------------------------------------------------------------- reading synthetic photos

def test_reads_the_angle_within_bars_at_several_angles_and_elevations():
    rng = np.random.default_rng(11)
    errs = []
    for elevation in (20.0, 30.0, 40.0, 50.0, 60.0, 25.0):
        K, T = _random_camera(rng, elevation)
        grey = float(rng.choice([25.0, 120.0, 230.0]))   # dark, mid and paper-white objects
        img = synthetic_photo(SPEC, K, T, rng, occluders=[object_outline(K, T, 40.0, 140.0)], occluder_grey=grey)
        alpha = rng.uniform(0, 360)
        reading = read_turntable_angle(img, K, _solver_pose(T, alpha), SPEC)
        assert isinstance(reading, AngleReading)
        assert reading.n_edges >= 30 and 0.3 < reading.coverage < 1.0   # the object hides some
        errs.append(_angle_err_deg(reading.angle_deg, alpha))
    assert np.median(errs) <= MEDIAN_BAR_DEG and max(errs) <= MAX_BAR_DEG, errs


def test_reads_the_angle_through_realistic_pose_errors():
    rng = np.random.default_rng(12)
    errs = []
    for elevation in (22.0, 35.0, 55.0):
        K, T = _random_camera(rng, elevation)
        img = synthetic_photo(SPEC, K, T, rng, occluders=[object_outline(K, T, 35.0, 120.0)])
        alpha = rng.uniform(0, 360)
        K_est = K.copy()
        K_est[:2, :2] *= 1.001                                    # 0.1 % focal length error
        reading = read_turntable_angle(img, K_est, _solver_pose(T, alpha, rng, normal_err_deg=0.05), SPEC)
        errs.append(_angle_err_deg(reading.angle_deg, alpha))
    assert np.median(errs) <= MEDIAN_BAR_DEG and max(errs) <= MAX_BAR_DEG, errs


@pytest.mark.parametrize("occluder_grey", [30.0, 235.0])
def test_reads_the_angle_with_half_of_the_marks_hidden(occluder_grey):
    rng = np.random.default_rng(13 + int(occluder_grey))
    for elevation in (25.0, 45.0):
        K, T = _random_camera(rng, elevation)
        hide = [half_disc_outline(K, T, rng.uniform(0, 360))]
        img = synthetic_photo(SPEC, K, T, rng, occluders=hide, occluder_grey=occluder_grey)
        alpha = rng.uniform(0, 360)
        reading = read_turntable_angle(img, K, _solver_pose(T, alpha), SPEC)
        assert reading.coverage <= 0.5
        assert _angle_err_deg(reading.angle_deg, alpha) <= MAX_BAR_DEG


def test_aligned_pose_projects_printed_ink_onto_dark_pixels():
    rng = np.random.default_rng(21)
    K, T = _random_camera(rng, 35.0)
    img = synthetic_photo(SPEC, K, T, rng, occluders=[object_outline(K, T, 40.0, 120.0)])
    T_s = _solver_pose(T, rng.uniform(0, 360))
    T_aligned = align_pose_to_marks(T_s, read_turntable_angle(img, K, T_s, SPEC).angle_deg)
    # half-sector centres on the near side of the track (never behind the object)
    half = 180.0 / SPEC.n_sectors
    th = np.radians((np.arange(2 * SPEC.n_sectors) + 0.5) * half)
    r = 0.5 * (SPEC.mark_r0_mm + SPEC.mark_r1_mm)
    pts = np.column_stack([r * np.cos(th), np.zeros_like(th), r * np.sin(th)])
    near = (pts @ T_aligned[:3, :3].T + T_aligned[:3, 3])[:, 2] < T_aligned[2, 3]
    uv = np.round(project_points(K, T_aligned, pts)).astype(int)
    grey = img.mean(axis=2)[uv[:, 1], uv[:, 0]]
    ink = mark_halfcells(SPEC)
    assert grey[near & ink].max() < grey[near & ~ink].min()


def test_refuses_when_the_marks_are_mostly_hidden():
    rng = np.random.default_rng(31)
    K, T = _random_camera(rng, 40.0)
    th = np.radians(np.linspace(0.0, 335.0, 120))
    big = project_points(K, T, np.column_stack([140 * np.cos(th), 0 * th, 140 * np.sin(th)]))
    img = synthetic_photo(SPEC, K, T, rng, occluders=[np.vstack([project_points(K, T, np.zeros((1, 3))), big])])
    with pytest.raises(CalibrationError, match="angle marks unreadable"):
        read_turntable_angle(img, K, _solver_pose(T, 10.0), SPEC)


def test_refuses_a_target_without_marks():
    rng = np.random.default_rng(32)
    K, T = _random_camera(rng, 40.0)
    plain = TargetSpec(80.0, 50.0, 3.0, marks=False)
    img = synthetic_photo(plain, K, T, rng)
    with pytest.raises(CalibrationError, match="angle marks unreadable"):
        read_turntable_angle(img, K, T, SPEC)
    with pytest.raises(CalibrationError, match="no marks"):
        read_turntable_angle(img, K, T, plain)
    with pytest.raises(ValueError):
        read_turntable_angle(img, K[:2], T, SPEC)
    flipped = T @ np.diag([1.0, -1.0, -1.0, 1.0])        # right-handed, but +Y away from the camera
    with pytest.raises(ValueError, match="camera's side"):
        read_turntable_angle(img, K, flipped, SPEC)


def _distort(img, K, dist):
    """The photo a lens with OpenCV distortion ``dist`` would take of the same scene."""
    H, W = img.shape[:2]
    uv = np.stack(np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)), -1)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, P=K).reshape(H, W, 2).astype(np.float32)
    return cv2.remap(img, und[..., 0], und[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_reads_a_distorted_photo_through_the_distortion_model():
    rng = np.random.default_rng(41)
    K = np.array([[1200.0, 0, 639.5], [0, 1200.0, 479.5], [0, 0, 1]])
    T = look_at_pose(40.0, rng.uniform(0, 360), 420.0, target_table=(0.0, 0.0, 0.0))
    T[:3, :] = cv2.Rodrigues(np.array([0.12, 0.3, 0.0]))[0] @ T[:3, :]   # target off-centre, partly cut
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    img = _distort(synthetic_photo(SPEC, K, T, rng, occluders=[object_outline(K, T, 40.0, 120.0)]), K, dist)
    alpha = rng.uniform(0, 360)
    T_s = _solver_pose(T, alpha)
    err = _angle_err_deg(read_turntable_angle(img, K, T_s, SPEC, dist=dist).angle_deg, alpha)
    err_ignoring = _angle_err_deg(read_turntable_angle(img, K, T_s, SPEC).angle_deg, alpha)
    assert err <= 0.02 and err_ignoring > 3 * err, (err, err_ignoring)
