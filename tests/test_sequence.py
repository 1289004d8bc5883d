"""Joint sequence calibration on edge observations synthesised from known cameras.

Edges are exact points on the projected (and distorted) edge circles plus
Gaussian noise; the angle marks are simulated by a reader that returns the
true rotation about the table normal plus noise. The single-view stage is
replaced by a perturbed ground truth where a test is about the joint maths
alone (``single_view`` monkeypatched), and run for real in the end-to-end tests.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import calib.sequence as cs
import calib.sequence_model as sm
from calib.camera import camera_centre_table, circle_points_table, look_at, make_T, project_points
from calib.conics import conic_center
from calib.distortion import distort_px
from calib.target import TargetSpec
from calib.types import CalibrationError, EdgePoints, Intrinsics, TargetObservation

W, H = 1280, 960
SPEC = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
CENTRE_TOL_MM = 0.5
TRUE_STROKE_MM = 3.3  # printers spread ink: the truth differs from the nominal width


def camera_position(elev_deg: float, azim_deg: float, dist_mm: float) -> np.ndarray:
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    return dist_mm * np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])


def synth_observation(K, dist, T, rng, noise_px=0.15, n_per_edge=1000, hide_deg=60.0) -> TargetObservation:
    """Both edges of both rings, an arc of ``hide_deg`` hidden (the object), noisy pixels."""
    edges = []
    start = rng.uniform(0, 360)
    for R in (SPEC.r_outer_mm, SPEC.r_inner_mm):
        for side in (-1, 1):
            r = R + side * TRUE_STROKE_MM / 2
            pts = circle_points_table(r, n_per_edge)
            phi = np.degrees(np.arctan2(pts[:, 2], pts[:, 0])) % 360
            keep = (phi - start) % 360 > hide_deg
            uv = project_points(K, T, pts[keep])
            uv = distort_px(uv, K, dist)
            uv = uv + rng.normal(0, noise_px, uv.shape)
            edges.append(EdgePoints(uv, R, side))
    return TargetObservation(edges=tuple(edges), width=W, height=H)


def turntable_truth(rng, n=36, step=10.0, jitter=0.0, offset=(2.0, -1.5), f=1500.0, elev=30.0, dist=450.0):
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    T_cam_axis = look_at(camera_position(elev, 0.0, dist), np.array([0.0, 30.0, 0.0]))
    theta = np.radians(np.arange(n) * step + rng.uniform(-jitter, jitter, n))
    d = np.array([offset[0], 0.0, offset[1]])
    Ts = [T_cam_axis @ make_T(cs.rot_y(th), np.zeros(3)) @ make_T(np.eye(3), d) for th in theta]
    return K, theta, Ts


def handheld_truth(rng, n=8, f=1400.0, pp=(20.0, -12.0)):
    K = np.array([[f, 0, (W - 1) / 2 + pp[0]], [0, f, (H - 1) / 2 + pp[1]], [0, 0, 1.0]])
    Ts = []
    for k in range(n):
        C = camera_position(rng.uniform(25, 70), 360.0 * k / n + rng.uniform(-20, 20), rng.uniform(380, 520))
        aim = np.array([rng.uniform(-40, 40), 0.0, rng.uniform(-40, 40)])
        Ts.append(look_at(C, aim, math.radians(rng.uniform(-15, 15))))
    return K, Ts


def fake_reader(Ts_true, rng, std_deg=0.05):
    def read(k, K, T, dist=None):
        psi = sm.yaw_of(T[:3, :3].T @ Ts_true[k][:3, :3]) + math.radians(rng.normal(0, std_deg))
        return make_T(T[:3, :3] @ cs.rot_y(psi), T[:3, 3]), std_deg

    return read


def perturbed_single_view(Ts_true, K_true, rng):
    """Stand-in for calib.calibrate: truth off by 1 % in f, 0.5 deg in the normal, 3 mm, random yaw."""
    lookup = []  # frame index of each call, in order (calls come in frame order)

    def single(obs, spec, pp, max_per_edge):
        k = lookup.pop(0)
        T = Ts_true[k]
        w = rng.normal(0, math.radians(0.5), 3)
        R = sm.exp_so3(w) @ T[:3, :3] @ cs.rot_y(rng.uniform(-np.pi, np.pi))
        return cs.SingleView(edges=sm.FrameEdges.from_observation(obs, max_per_edge),
                             T=make_T(R, T[:3, 3] + rng.normal(0, 3.0, 3)),
                             focal_px=K_true[0, 0] * (1 + rng.normal(0, 0.01)), rms_px=0.15, stroke_mm=3.0)

    return single, lookup


def run_synthetic(monkeypatch, rng, K, dist, Ts, n_per_edge=400, **kw):
    obs = [synth_observation(K, dist, T, rng, n_per_edge=n_per_edge) for T in Ts]
    single, lookup = perturbed_single_view(Ts, K, rng)
    lookup.extend(range(len(obs)))
    monkeypatch.setattr(cs, "single_view", single)
    return cs.calibrate_sequence(obs, None, SPEC, angle_reader=fake_reader(Ts, rng), **kw)


def centre_errors_mm(seq, Ts):
    return np.array([np.linalg.norm(camera_centre_table(f.T_cam_table) - camera_centre_table(T))
                     for f, T in zip(seq.frames, Ts, strict=True) if f.ok])


def angle_errors_deg(seq, theta_true):
    est = np.radians([f.angle_deg for f in seq.frames])
    d = sm.wrap_angle(est - cs.TURN_SIGN * theta_true)
    d = sm.wrap_angle(d - math.atan2(np.sin(d).mean(), np.cos(d).mean()))  # common offset: a gauge
    return np.degrees(np.abs(d))


# --------------------------------------------------------------------------- distortion model
@pytest.mark.parametrize("dist", [[-0.1, 0.0, 0.0, 0.0], [-0.1, 0.05, 0.001, -0.0005, 0.01],
                                  [0.05, -0.02, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0]])
def test_distortion_matches_opencv_and_inverts(dist):
    import cv2

    from calib.distortion import undistort_px

    rng = np.random.default_rng(9)
    K = np.array([[1400.0, 0, 650.0], [0, 1400.0, 470.0], [0, 0, 1.0]])
    uv = rng.uniform([0, 0], [W, H], (500, 2))
    rays = np.column_stack([(uv - K[:2, 2]) / K[0, 0], np.ones(len(uv))])
    ref = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.asarray(dist))[0][:, 0]
    assert np.max(np.abs(distort_px(uv, K, dist) - ref)) < 1e-9  # px
    assert np.max(np.abs(undistort_px(ref, K, dist) - uv)) < 1e-9  # px, Newton to convergence
    with pytest.raises(ValueError):
        distort_px(uv, K, [0.1, 0.2, 0.3])


# --------------------------------------------------------------------------- turntable
def test_turntable_joint_fit_recovers_camera_axis_and_angles(monkeypatch):
    rng = np.random.default_rng(1)
    K, theta, Ts = turntable_truth(rng, n=18, step=20.0, jitter=3.0)
    seq = run_synthetic(monkeypatch, rng, K, np.zeros(5), Ts, distortion="none")
    assert seq.mode == "turntable"
    assert all(f.ok for f in seq.frames)
    f_rel_err = abs(seq.intrinsics.focal_px / K[0, 0] - 1)
    assert f_rel_err < 1e-3
    # the camera centre's azimuth error is the angle error (0.05 deg marks noise at ~390 mm: 0.34 mm),
    # its height and distance from the pattern centre come from the rings
    assert np.median(centre_errors_mm(seq, Ts)) < CENTRE_TOL_MM
    c_est = np.array([camera_centre_table(f.T_cam_table) for f in seq.frames])
    c_true = np.array([camera_centre_table(T) for T in Ts])
    assert np.max(np.abs(c_est[:, 1] - c_true[:, 1])) < CENTRE_TOL_MM
    assert np.max(np.abs(np.linalg.norm(c_est, axis=1) - np.linalg.norm(c_true, axis=1))) < CENTRE_TOL_MM
    err = angle_errors_deg(seq, theta)
    assert np.median(err) < 0.05 and np.max(err) < 0.2
    off = seq.diagnostics.turntable.pattern_offset_from_axis_mm
    assert np.allclose(off, [2.0, -1.5], atol=0.3)
    assert "unobservable" in seq.diagnostics.not_estimated["principal_point"]
    assert seq.diagnostics.not_estimated["distortion"]
    assert abs(seq.diagnostics.stroke_mm - TRUE_STROKE_MM) < 0.05


def test_turntable_step_fixes_angles_and_flags_disagreeing_marks(monkeypatch):
    rng = np.random.default_rng(2)
    K, theta, Ts = turntable_truth(rng, n=12, step=30.0)
    # the table slipped by 4 deg in frame 5: the marks see it, the step does not
    D = make_T(np.eye(3), [2.0, 0.0, -1.5])  # turntable_truth's pattern offset
    Ts_bad = list(Ts)
    Ts_bad[5] = Ts[5] @ np.linalg.inv(D) @ make_T(cs.rot_y(math.radians(4.0)), np.zeros(3)) @ D
    obs = [synth_observation(K, np.zeros(5), T, rng, n_per_edge=200) for T in Ts_bad]
    single, lookup = perturbed_single_view(Ts_bad, K, rng)
    lookup.extend(range(len(obs)))
    monkeypatch.setattr(cs, "single_view", single)
    seq = cs.calibrate_sequence(obs, None, SPEC, step_deg=30.0, mode="turntable",
                                angle_reader=fake_reader(Ts_bad, rng))
    assert [f.angle_deg for f in seq.frames][:3] == pytest.approx([0.0, 30.0, 60.0])
    flagged = [c.image for c in seq.diagnostics.angle_checks]
    assert flagged == ["frame_005"]


def test_a_step_the_marks_contradict_is_not_used_and_the_warning_says_so(monkeypatch):
    """--step-deg 10 on a 30-degree table: the marks' angles are used (turntable mode kept), and it is said."""
    rng = np.random.default_rng(2)
    K, theta, Ts = turntable_truth(rng, n=12, step=30.0)
    obs = [synth_observation(K, np.zeros(5), T, rng, n_per_edge=200) for T in Ts]
    single, lookup = perturbed_single_view(Ts, K, rng)
    lookup.extend(range(len(obs)))
    monkeypatch.setattr(cs, "single_view", single)
    seq = cs.calibrate_sequence(obs, None, SPEC, step_deg=10.0, angle_reader=fake_reader(Ts, rng))
    assert seq.mode == "turntable"
    [warning] = seq.diagnostics.warnings
    assert "--step-deg 10 contradicts the angle marks" in warning and "30.0° per frame" in warning
    assert warning in seq.diagnostics.mode_reason
    assert [f.angle_deg for f in seq.frames][:3] == pytest.approx([0.0, 30.0, 60.0], abs=0.2)  # the marks' 30
    assert not seq.diagnostics.angle_checks  # the step was dropped, so nothing is checked against it


# --------------------------------------------------------------------------- handheld
def test_handheld_sweep_estimates_principal_point_and_k1(monkeypatch):
    rng = np.random.default_rng(3)
    K, Ts = handheld_truth(rng, n=8, pp=(20.0, -12.0))
    dist = np.array([-0.1, 0.0, 0.0, 0.0, 0.0])
    seq = run_synthetic(monkeypatch, rng, K, dist, Ts, n_per_edge=1000, max_points_per_edge=400)
    assert seq.mode == "handheld"
    assert abs(seq.intrinsics.focal_px / K[0, 0] - 1) < 0.005
    assert np.all(np.abs(seq.intrinsics.principal_point_px - K[:2, 2]) < 2.0)  # px
    assert abs(seq.intrinsics.dist[0] - dist[0]) < 0.01
    assert seq.diagnostics.dist_std["k1"] < 0.005
    assert np.isnan(seq.frames[0].angle_deg)
    assert np.max(centre_errors_mm(seq, Ts)) < 2.0


def test_same_tilt_views_refuse_the_principal_point(monkeypatch):
    """Forced handheld on a fixed camera: every view shares the circular points, so the principal point
    is free along the line perpendicular to the horizon (here: cy, the camera has no roll) and is refused."""
    rng = np.random.default_rng(4)
    K, theta, Ts = turntable_truth(rng, n=6, step=60.0, offset=(0.0, 0.0))
    seq = run_synthetic(monkeypatch, rng, K, np.zeros(5), Ts, mode="handheld", distortion="none",
                        max_points_per_edge=100)
    assert seq.mode == "handheld"
    assert "unconstrained" in seq.diagnostics.not_estimated["cy"]
    assert seq.intrinsics.principal_point_px[1] == (H - 1) / 2
    assert abs(seq.intrinsics.focal_px / K[0, 0] - 1) < 2e-3


def test_failed_frames_are_reported_and_the_rest_calibrate(monkeypatch):
    rng = np.random.default_rng(5)
    K, theta, Ts = turntable_truth(rng, n=8, step=45.0)
    obs = [synth_observation(K, np.zeros(5), T, rng, n_per_edge=200) for T in Ts]
    obs[2] = None
    single, lookup = perturbed_single_view(Ts, K, rng)
    lookup.extend(k for k, o in enumerate(obs) if o is not None)
    monkeypatch.setattr(cs, "single_view", single)
    good = fake_reader(Ts, rng)

    def reader(k, K_, T, dist=None):
        if k == 5:
            raise CalibrationError("angle marks unreadable: 3 edges visible")
        return good(k, K_, T)

    seq = cs.calibrate_sequence(obs, None, SPEC, failures=[""] * 2 + ["inner ring not found"] + [""] * 5,
                                angle_reader=reader)
    status = [f.status for f in seq.frames]
    assert status[2] == "inner ring not found"
    assert status[5].startswith("angle marks unreadable")
    assert sum(f.ok for f in seq.frames) == 6 and seq.mode == "turntable"
    assert seq.diagnostics.frames_skipped == 2


def test_nothing_calibrates_raises():
    with pytest.raises(CalibrationError, match="no frame could be calibrated"):
        cs.calibrate_sequence([None, None], None, SPEC, failures=["no rings", "no rings"])
    with pytest.raises(ValueError):
        cs.calibrate_sequence([None], None, SPEC, mode="sideways")


def test_given_intrinsics_are_kept_and_undistort_the_edges(monkeypatch):
    rng = np.random.default_rng(6)
    K, theta, Ts = turntable_truth(rng, n=8, step=45.0)
    dist = np.array([-0.08, 0.01, 0.0, 0.0, 0.0])
    intr = Intrinsics(K=K, width=W, height=H, dist=dist)
    seq = run_synthetic(monkeypatch, rng, K, dist, Ts, intrinsics=intr, max_points_per_edge=100)
    assert np.array_equal(seq.intrinsics.K, K) and np.array_equal(seq.intrinsics.dist, dist)
    assert seq.diagnostics.intrinsics_source == "given"
    assert seq.diagnostics.rms_px < 0.2  # the distortion was removed: the model fits to the noise level


# --------------------------------------------------------------------------- CLI
def _cli(argv):
    from turntable.cli import main

    return main(["calibrate-sequence", *argv])


def test_cli_empty_folder(tmp_path, capsys):
    (tmp_path / "imgs").mkdir()
    rc = _cli([str(tmp_path / "imgs"), "--r-outer", "80", "--r-inner", "50", "--out", str(tmp_path / "c.json")])
    assert rc == 2
    assert "no images found" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_cli_no_rings_anywhere(tmp_path, capsys):
    import cv2

    d = tmp_path / "imgs"
    d.mkdir()
    rng = np.random.default_rng(7)
    for k in range(2):
        cv2.imwrite(str(d / f"frame_{k}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    (d / "frame_2.png").write_bytes(b"not a png")
    rc = _cli([str(d), "--r-outer", "80", "--r-inner", "50", "--out", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "no frame could be calibrated" in err and "cannot decode image" in err
    assert not (tmp_path / "c.json").exists()


def test_cli_bad_intrinsics_file(tmp_path, capsys):
    import cv2

    d = tmp_path / "imgs"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), np.zeros((10, 10, 3), np.uint8))
    rc = _cli([str(d), "--r-outer", "80", "--r-inner", "50", "--intrinsics", str(tmp_path / "nope.yml"),
               "--out", str(tmp_path / "c.json")])
    assert rc == 2 and "nope.yml: file not found" in capsys.readouterr().err


# --------------------------------------------------------------------------- end to end
def test_rendered_turntable_sequence_end_to_end(tmp_path, capsys):
    """Five small rendered photos (marks, occluder, JPEG) through the CLI: detection, marks, joint fit."""
    import cv2
    from synthetic_images import render_target_photo

    from turntable.cameras_io import read_cameras

    rng = np.random.default_rng(8)
    size, f = (800, 600), 950.0
    K = np.array([[f, 0, (size[0] - 1) / 2], [0, f, (size[1] - 1) / 2], [0, 0, 1.0]])
    T_cam_world = look_at(camera_position(35.0, 0.0, 420.0), np.zeros(3))
    theta = np.radians([0.0, 47.0, 95.0, 141.0, 190.0])
    Ts = [T_cam_world @ make_T(cs.rot_y(th), np.zeros(3)) for th in theta]
    (tmp_path / "imgs").mkdir()
    for k, T in enumerate(Ts):
        cv2.imwrite(str(tmp_path / "imgs" / f"frame_{k}.png"), render_target_photo(SPEC, K, T, size, rng=rng).image)
    rc = _cli([str(tmp_path / "imgs"), "--r-outer", "80", "--r-inner", "50", "--out", str(tmp_path / "cams.json")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "focal length" in out.out
    # off a terminal, one line per stage of the joint fit, with its iterations and cost
    fit_lines = [line for line in out.err.splitlines() if line.startswith("  joint fit ")]
    assert fit_lines[0].startswith("  joint fit turntable, robust: ") and "iterations, cost" in fit_lines[0]
    assert any(line.startswith("  joint fit turntable: ") for line in fit_lines), fit_lines
    seq = read_cameras(tmp_path / "cams.json")
    assert seq.mode == "turntable" and all(fr.ok for fr in seq.frames)
    assert abs(seq.intrinsics.focal_px / f - 1) < 0.005
    err = np.abs(sm.wrap_angle(np.radians([fr.angle_deg for fr in seq.frames]) - theta))
    assert np.degrees(err).max() < 0.3
    assert np.max(centre_errors_mm(seq, Ts)) < 3.0



def test_expected_pose_predicts_a_frame_between_and_before_the_calibrated_ones():
    from calib.types import FramePose

    rng = np.random.default_rng(21)
    _, _, Ts = turntable_truth(rng, n=8, step=30.0, offset=(7.0, -4.0))  # paper far off the axis
    lost = {0, 3, 4}
    frames = [FramePose(image=f"f{k}", angle_deg=30.0 * k, T_cam_table=T, status="lost" if k in lost else "ok")
              for k, T in enumerate(Ts)]
    for k in lost:  # between two (3 and 4: two steps apart), and before the first (extrapolated)
        T = cs.expected_pose(frames, k)
        assert T is not None
        assert np.allclose(T, Ts[k], atol=1e-9), k
    one = [fr if k == 5 else FramePose(fr.image, fr.angle_deg, fr.T_cam_table, status="lost")
           for k, fr in enumerate(frames)]
    assert cs.expected_pose(one, 2) is None


def test_a_frame_the_coarse_search_missed_is_found_where_the_others_put_its_rings():
    """The frame whose rings the first search missed (here: its observation thrown away, as the object
    hiding the inner ring does) is searched again on the reduced work image, mapped back to full
    pixels and calibrated with the rest; a frame without the target stays out, with both reasons."""
    import cv2
    from synthetic_images import render_target_photo

    from turntable.stages.calibration import calibrate_detected, detect_all
    from turntable.worksize import scale_matrix

    rng = np.random.default_rng(22)
    size, work, f = (800, 600), (400, 300), 950.0
    K = np.array([[f, 0, (size[0] - 1) / 2], [0, f, (size[1] - 1) / 2], [0, 0, 1.0]])
    T_cam_axis = look_at(camera_position(35.0, 0.0, 420.0), np.zeros(3))
    d = make_T(np.eye(3), np.array([9.0, 0.0, -6.0]))  # the paper off the axis: the rings move as it turns
    Ts = [T_cam_axis @ make_T(cs.rot_y(math.radians(40.0 * k)), np.zeros(3)) @ d for k in range(6)]
    photos = [render_target_photo(SPEC, K, T, size, rng=rng).image for T in Ts]
    photos[4] = np.full_like(photos[4], 120)  # no target at all
    names = [f"frame_{k}.png" for k in range(6)]
    obs, failures = detect_all([(n, p, "") for n, p in zip(names, photos, strict=True)], SPEC)
    assert obs[2] is not None and obs[4] is None
    full_obs2 = obs[2]
    obs[2], failures[2] = None, "radius ratio 1.32 does not match the target's 1.60"
    S = scale_matrix(size, work)
    small = [cv2.resize(p, work, interpolation=cv2.INTER_AREA) for p in photos]
    out: list = []
    seq = calibrate_detected(obs, failures, names, small, SPEC, marks_map=S, observations_out=out)
    assert seq.mode == "turntable"
    assert seq.frames[2].ok and not seq.frames[4].ok
    assert "radius ratio" not in seq.frames[2].status
    assert "no ring found" in seq.frames[4].status and "not found either where" in seq.frames[4].status
    assert "frame_2.png" in seq.diagnostics.mode_reason
    # the rings found on the half-size image, in full-image pixels, are where the full-size search put them
    for C_new, C_old in ((out[2].conics.outer, full_obs2.conics.outer), (out[2].conics.inner, full_obs2.conics.inner)):
        assert np.linalg.norm(conic_center(C_new) - conic_center(C_old)) < 0.5
    assert (out[2].width, out[2].height) == size
    assert np.max(centre_errors_mm(seq, Ts)) < 3.0


def test_a_frame_that_does_not_fit_the_shared_camera_is_dropped(monkeypatch):
    rng = np.random.default_rng(10)
    K, theta, Ts = turntable_truth(rng, n=8, step=45.0)
    obs = [synth_observation(K, np.zeros(5), T, rng, n_per_edge=300) for T in Ts]
    # frame 3 was taken with a zoomed lens: its rings are 10 % larger about the image centre
    c = K[:2, 2]
    obs[3] = TargetObservation(edges=tuple(EdgePoints(c + 1.1 * (e.uv_px - c), e.ring_radius_mm, e.side)
                                           for e in obs[3].edges), width=W, height=H)
    single, lookup = perturbed_single_view(Ts, K, rng)
    lookup.extend(range(len(obs)))
    monkeypatch.setattr(cs, "single_view", single)
    seq = cs.calibrate_sequence(obs, None, SPEC, angle_reader=fake_reader(Ts, rng), distortion="none")
    assert seq.frames[3].status.startswith("does not fit the shared camera")
    assert sum(f.ok for f in seq.frames) == 7 and seq.mode == "turntable"
    assert abs(seq.intrinsics.focal_px / K[0, 0] - 1) < 1e-3


def test_stage_rejects_mixed_sizes_and_mismatched_intrinsics():
    from turntable.errors import UserError
    from turntable.stages.calibration import calibrate_frames

    a, b = np.zeros((60, 80, 3), np.uint8), np.zeros((60, 90, 3), np.uint8)
    with pytest.raises(UserError, match="different sizes"):
        calibrate_frames([("a", a, ""), ("b", b, "")], SPEC)
    intr = Intrinsics.from_focal(100.0, 640, 480)
    with pytest.raises(UserError, match="640x480"):
        calibrate_frames([("a", a, "")], SPEC, intrinsics=intr)
    with pytest.raises(UserError, match="no frames"):
        calibrate_frames([], SPEC)


def test_one_upside_down_frame_is_left_out_not_a_switch_to_handheld(monkeypatch):
    """One photo of a turntable sequence stored upside down (EXIF 180 deg lost): its camera is rolled
    half a turn about the optical axis, so its pose breaks the fixed camera. Auto mode used to take
    the whole sequence for hand-held ('camera centres do not lie on one circle'); now that frame is
    left out, named, with the reason, and the rest is the turntable it is."""
    rng = np.random.default_rng(12)
    K, theta, Ts = turntable_truth(rng, n=12, step=30.0)
    flip = make_T(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))  # 180 deg about the camera's z axis
    Ts[5] = flip @ Ts[5]
    seq = run_synthetic(monkeypatch, rng, K, np.zeros(5), Ts, distortion="none")
    assert seq.mode == "turntable", seq.diagnostics.mode_reason
    assert seq.frames[5].status.startswith("does not fit the turntable"), seq.frames[5].status
    assert [k for k, f in enumerate(seq.frames) if not f.ok] == [5]
    assert abs(seq.intrinsics.focal_px / K[0, 0] - 1) < 1e-3
    assert "off the turntable circle left out" in seq.diagnostics.mode_reason


# --------------------------------------------------------------------------- the joint fit's linear algebra
def _problems(rng, n):
    """A turntable problem (marks on all frames but one, the first angle fixed) and a handheld one, n frames,
    10 edge points per edge, started off the truth; and a parameter vector off zero."""
    from calib.sequence_model import FitState, FrameEdges, JointProblem

    K, theta, Ts = turntable_truth(rng, n=n, step=360.0 / n)
    frames = [FrameEdges.from_observation(synth_observation(K, np.zeros(5), T, rng), 10) for T in Ts]
    d = np.array([2.0, 0.0, -1.5])
    T_ca = Ts[0] @ np.linalg.inv(make_T(cs.rot_y(theta[0]), cs.rot_y(theta[0]) @ d))
    st = sm.FitState(K=K * [[1.01], [1.01], [1]], dist=np.array([-0.01, 0, 0, 0, 0.0]), stroke=3.0,
                      R_cam_axis=T_ca[:3, :3], t_cam_axis=T_ca[:3, 3] + 1.0, d_xz=np.zeros(2), theta=theta + 0.01)
    free = np.arange(n) > 0
    mark_R = [None] + [T[:3, :3] for T in Ts[1:]]
    tt = JointProblem(frames, st, ("f", "k1"), True, "turntable", free_theta=free, mark_R=mark_R,
                      mark_w=np.full(n, 50.0))
    sh = FitState(K=st.K, dist=st.dist, stroke=3.0, R=[T[:3, :3] for T in Ts], t=[T[:3, 3] + 1.0 for T in Ts])
    hh = JointProblem(frames, sh, ("f", "cx", "cy", "k1"), True, "handheld")
    return [(p, rng.normal(0, 1e-3, p.n_params)) for p in (tt, hh)]


def test_joint_fit_jacobian_is_blocked_and_costs_the_same_evaluations_for_any_number_of_frames(monkeypatch):
    """The joint fit's cost is linear in the frames: its Jacobian holds the global columns and each
    frame's own (at most 5) for every row -- never a dense (rows, parameters) array whose width grows
    with the frames -- and is built from a fixed number of residual evaluations of all rows (every
    frame's c-th parameter is stepped at once), not one per frame's parameter."""
    from calib.sequence_model import JointProblem

    calls = []
    evaluate = JointProblem.residuals
    monkeypatch.setattr(JointProblem, "residuals", lambda self, x: calls.append(1) or evaluate(self, x))
    per_jacobian, expected = {}, {}
    for n in (4, 12):
        for p, x in _problems(np.random.default_rng(20), n):
            calls.clear()
            J = p.jacobian(x)
            assert J.glob.shape == (p.n_rows, p.n_global)
            assert J.local.shape == (p.n_rows, int(p.n_local.max()))
            per_jacobian.setdefault(p.model, set()).add(len(calls))
            expected[p.model] = {p.n_global + int(p.n_local.max()) + 1}  # globals + local columns + r0
    assert per_jacobian == expected


def test_blocked_normal_equations_match_the_dense_solve():
    """The Schur-complement step and covariance equal the dense ``(J^T J + lam D)^-1 J^T r`` and ``(J^T J)^-1``."""
    from calib.lm import DIAGONAL_FLOOR
    from calib.sequence_model import dense_jacobian, global_std, param_std

    REL_TOL = 1e-8  # the steps
    STD_REL_TOL = 1e-6  # 1 sigma: both computations lose ~cond(M) eps, cond ~ 4e9 here (10 points per edge)
    rng = np.random.default_rng(21)
    for p, x in _problems(rng, 7):
        J, r = p.jacobian(x), p.residuals(x)
        w = rng.uniform(0.5, 1.0, p.n_rows)
        Jd = dense_jacobian(p, J) * w[:, None]
        A, g = Jd.T @ Jd, Jd.T @ (w * r)
        for lam in (1e-6, 1e-2, 10.0):
            D = np.maximum(np.diag(A), DIAGONAL_FLOOR * np.diag(A).max())
            dx = -np.linalg.solve(A + lam * np.diag(D), g)
            step = -p.normal_equations(x, r, w**2).solve(lam * D)  # what calib.lm takes for this lam
            assert np.linalg.norm(step - dx) < REL_TOL * np.linalg.norm(dx), (p.model, lam)
        std = global_std(p, J, 0.02)
        np.testing.assert_allclose(std, param_std(dense_jacobian(p, J), 0.02)[:p.n_global], rtol=STD_REL_TOL)
