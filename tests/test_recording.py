"""The Rerun recorder and `turntable view`: what a person opening the file will find, and how it opens."""

import importlib.util
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rrd_util import blueprint_values, blueprint_views, pinhole_K, rrd_column, rrd_rows, static_entities

from calib.camera import invert_T, make_T, rotation_from_normal
from calib.types import FramePose
from turntable.cli import main
from turntable.cli.view import no_display_reason, web_command, web_url
from turntable.recording import (
    HIDDEN_BY_DEFAULT,
    SCALARS,
    RecordedModels,
    RecordedViews,
    Recorder,
    camera_entity,
    eye_for,
    record_reconstruction,
)

ROOT = Path(__file__).resolve().parents[1]


def test_cameras_images_and_meshes_are_recorded(tmp_path):
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 159.5], [0, 800.0, 119.5], [0, 0, 1]])
    p = tmp_path / "r.rrd"
    with Recorder(p) as rec:
        rec.log_target(80, 50)
        for i in range(3):
            T = make_T(rotation_from_normal([0, -0.8, -0.6]), [0, 20, 450])
            rec.log_camera(i, K, 320, 240, T, image_rgb=rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
            rec.log_silhouette(i, np.pad(np.ones((100, 100), bool), 70)[:240, :320])
        V = rng.normal(size=(4, 3))
        rec.log_mesh("mesh", V, [[0, 1, 2], [0, 2, 3]], normals=V, colors_rgb=np.full((4, 3), 200, np.uint8))
    rows = rrd_rows(p)
    assert rows["/world/camera"]["Pinhole:image_from_camera"] == 3
    assert rows["/world/camera/image"]["EncodedImage:blob"] == 3
    assert rows["/world/mesh"]["Mesh3D:vertex_colors"] == 1
    assert "LineStrips3D:strips" in rows["/world/target"]
    # our pixel-centre principal point is shifted by half a pixel into Rerun's corner convention
    K_rr = pinhole_K(rrd_column(p, "/world/camera", "Pinhole:image_from_camera")[0])
    np.testing.assert_allclose(K_rr[:2, 2], K[:2, 2] + 0.5)
    assert K_rr[0, 0] == 800.0


def _turntable_poses(n: int, distance_mm: float = 430.0, elevation_deg: float = 35.0) -> np.ndarray:
    """Cameras on a circle around the table, looking at its centre (table frame, mm)."""
    Ts = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        e = np.radians(elevation_deg)
        C = distance_mm * np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
        z = -C / np.linalg.norm(C)
        x = np.cross([0.0, -1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R_cam_table = np.stack([x, np.cross(z, x), z])  # rows: the camera's axes in the table frame
        Ts.append(make_T(R_cam_table, -R_cam_table @ C))
    return np.array(Ts)


def _record_small_scan(path: Path, n: int = 6, rms=None) -> SimpleNamespace:
    """record_reconstruction on a made-up scan: a box on the table, n cameras all round, as reconstruct calls it."""
    rng = np.random.default_rng(1)
    W, H = 320, 240
    K = np.array([[380.0, 0, 159.5], [0, 380.0, 119.5], [0, 0, 1]])
    Ts = _turntable_poses(n)
    names = [f"frame_{i}.png" for i in range(n)]
    rms = [0.2 + 0.01 * i for i in range(n)] if rms is None else rms
    seq = SimpleNamespace(frames=tuple(FramePose(image=nm, angle_deg=30.0 * i, T_cam_table=T, rms_px=r)
                                       for i, (nm, T, r) in enumerate(zip(names, Ts, rms, strict=True))))
    V = np.array([[x, y, z] for x in (-30, 30) for y in (0, 100) for z in (-30, 30)], float)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    hull = SimpleNamespace(vertices_table=V, faces=F, normals_table=V / np.linalg.norm(V, axis=1, keepdims=True))
    mesh = SimpleNamespace(vertices_table=V, faces=F, normals_table=hull.normals_table,
                           colors_rgb=np.tile([[220, 40, 190]], (len(V), 1)).astype(np.uint8))
    fused = SimpleNamespace(pts_table=rng.uniform(-30, 30, (50, 3)), colors_rgb=np.full((50, 3), 128, np.uint8))
    ws = SimpleNamespace(work=(W, H), conic=lambda C: C)
    opts = SimpleNamespace(spec=SimpleNamespace(r_outer_mm=80.0, r_inner_mm=50.0))
    images = [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(n)]
    masks = [np.pad(np.ones((80, 60), bool), ((80, 80), (130, 130))) for _ in range(n)]
    rec = Recorder()
    record_reconstruction(rec, opts.spec, seq, RecordedViews(names, images, masks, K, Ts, {}, ws),
                          RecordedModels(hull, fused, mesh))
    rec.save(path)
    return SimpleNamespace(Ts=Ts, V=V, n=n, rms=rms, W=W, H=H)


def test_every_camera_is_static_with_a_small_photo(tmp_path):
    p = tmp_path / "r.rrd"
    scan = _record_small_scan(p)
    rows, static = rrd_rows(p), static_entities(p)
    for i in range(scan.n):
        e = "/" + camera_entity(i)
        assert e in static and e + "/image" in static
        assert rows[e]["Pinhole:image_from_camera"] == 1 and rows[e]["Transform3D:translation"] == 1
        assert rows[e + "/image"]["EncodedImage:blob"] == 1
        # the frustum is where the camera is: table-from-camera translation = the camera centre
        t = np.ravel(rrd_column(p, e, "Transform3D:translation")[0]).astype(float)
        np.testing.assert_allclose(t, invert_T(scan.Ts[i])[:3, 3], atol=1e-3)
        # a thumbnail's pinhole has the same field of view as the photo's
        K_small = pinhole_K(rrd_column(p, e, "Pinhole:image_from_camera")[0])
        w, h = np.ravel(rrd_column(p, e, "Pinhole:resolution")[0])
        assert max(w, h) <= 160
        np.testing.assert_allclose(K_small[0, 0] / w, 380.0 / scan.W, rtol=1e-3)
    # the current frame keeps its full photo on the timeline
    assert "/world/camera" not in static_entities(p, "Pinhole:image_from_camera")
    assert rows["/world/camera"]["Pinhole:image_from_camera"] == scan.n
    assert rows["/world/camera/image"]["EncodedImage:blob"] == scan.n
    assert {"/world/mesh", "/world/hull", "/world/points", "/world/target"} <= static


def test_default_blueprint_shows_the_mesh_and_hides_hull_and_points(tmp_path):
    p = tmp_path / "r.rrd"
    scan = _record_small_scan(p)
    views = blueprint_views(p)
    by_class: dict[str, list] = {}
    for path, v in views.items():
        by_class.setdefault(v["class"], []).append({**v, "path": path})
    (v3d,) = by_class["3D"]
    assert v3d["origin"] == "world"
    assert [v["origin"] for v in by_class["2D"]] == ["world/camera/image"]
    assert sorted(v["origin"] for v in by_class["TimeSeries"]) == sorted(SCALARS)
    bp = blueprint_values(p)
    hidden = {e.split("/ViewContents/overrides/")[1].removesuffix("/visualizers")
              for e, cols in bp.items() if e.startswith(v3d["path"] + "/ViewContents/overrides/")
              and cols.get("EntityBehavior:visible") == [[False]]}
    assert hidden == set(HIDDEN_BY_DEFAULT) == {"world/hull", "world/points"}
    # the eye looks at the middle of the object, from outside every camera, with the object and every camera
    # within 30 degrees of its axis (the viewer's field of view is wider)
    eye = bp[v3d["path"] + "/EyeControls3D"]
    pos = np.asarray(eye["EyeControls3D:position"][-1][0], float)
    target = np.asarray(eye["EyeControls3D:look_target"][-1][0], float)
    np.testing.assert_allclose(target, [0.0, 50.0, 0.0], atol=1e-3)
    axis = (target - pos) / np.linalg.norm(target - pos)
    centres = np.array([invert_T(T)[:3, 3] for T in scan.Ts])
    for q in np.vstack([scan.V, centres]):
        d = (q - pos) / np.linalg.norm(q - pos)
        assert np.degrees(np.arccos(np.clip(d @ axis, -1, 1))) < 30.0
    assert np.linalg.norm(pos - target) > np.linalg.norm(centres - target, axis=1).max()
    assert pos[1] > centres[:, 1].max()  # from above the cameras: they do not hide the object


def test_eye_looks_from_the_side_of_an_arc_of_cameras():
    """Cameras over 70 degrees only (a partial turn): the eye stands behind their arc, not across the table."""
    Ts = _turntable_poses(36)[:8]  # 0..70 degrees
    V = np.array([[-30.0, 0, -30], [30, 100, 30]])
    eye, target = eye_for(V, Ts)
    centres = np.array([invert_T(T)[:3, 3] for T in Ts])
    az_eye = np.degrees(np.arctan2(eye[0] - target[0], eye[2] - target[2]))
    az_arc = np.degrees(np.arctan2(*(centres - target).mean(axis=0)[[0, 2]]))
    assert abs(az_eye - az_arc) < 1.0  # degrees
    assert 40.0 < np.degrees(np.arcsin((eye - target)[1] / np.linalg.norm(eye - target))) < 50.0


def test_per_frame_calibration_is_plotted(tmp_path):
    p = tmp_path / "r.rrd"
    rms = [0.2, float("nan"), 0.3, 0.25]  # a frame without a value has no point, not a NaN
    _record_small_scan(p, n=4, rms=rms)
    got_rms = rrd_column(p, "/calibration/edge_rms_px", "Scalars:scalars")
    got_angle = rrd_column(p, "/calibration/angle_deg", "Scalars:scalars")
    np.testing.assert_allclose(np.ravel(got_rms), [0.2, 0.3, 0.25])
    np.testing.assert_allclose(np.ravel(got_angle), [0.0, 30.0, 60.0, 90.0])
    assert "/calibration/angle_deg" not in static_entities(p)  # on the frame timeline


# -- turntable view --------------------------------------------------------------------------------------------


def test_no_display_is_detected_on_linux_only():
    assert "no display" in no_display_reason({}, "linux")
    assert no_display_reason({"DISPLAY": ":0"}, "linux") is None
    assert no_display_reason({"WAYLAND_DISPLAY": "wayland-0"}, "linux") is None
    assert no_display_reason({}, "darwin") is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="DISPLAY decides only on Linux")
def test_view_without_a_display_points_to_web(tmp_path, monkeypatch, capsys):
    p = tmp_path / "recording.rrd"
    Recorder(p).save(p)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)

    def no_viewer(*a, **k):
        raise AssertionError("the native viewer was started without a display")

    monkeypatch.setattr(subprocess, "call", no_viewer)
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no display found" in err and f"turntable view {tmp_path} --web" in err


def test_web_serves_on_localhost_only():
    cmd = web_command(Path(__file__), 9090, 9091)
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1"
    assert cmd[cmd.index("--web-viewer-port") + 1] == "9090" and cmd[cmd.index("--port") + 1] == "9091"
    assert web_url(9090, 9091) == "http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9091%2Fproxy"


def test_web_port_in_use_is_a_clear_error(tmp_path, capsys):
    p = tmp_path / "recording.rrd"
    Recorder(p).save(p)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["view", str(p), "--web", "--port", str(port)]) == 2
    assert f"--port {port}" in capsys.readouterr().err


def _web_view_module():
    spec = importlib.util.spec_from_file_location("web_view", ROOT / "benchmarks" / "web_view.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_web_serves_the_viewer_until_ctrl_c(tmp_path):
    """The page and the recording's gRPC port answer on 127.0.0.1; Ctrl-C ends it with 130, no traceback."""
    web_view = _web_view_module()
    p = tmp_path / "recording.rrd"
    Recorder(p).save(p)
    port = web_view.free_port()
    proc, url = web_view.start_view(p, port)
    try:
        assert url.startswith(f"http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A")
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as r:
            assert b"<html" in r.read().lower()
        grpc_port = int(url.rsplit("%3A", 1)[1].split("%2F")[0])
        socket.create_connection(("127.0.0.1", grpc_port), timeout=10).close()
    finally:
        code, err = web_view.stop_view(proc)
    assert code == 130, err
    assert "Traceback" not in err
    time.sleep(0.5)
    with pytest.raises(OSError):  # the server went with it
        socket.create_connection(("127.0.0.1", grpc_port), timeout=2).close()


@pytest.mark.skipif(not Path("/usr/bin/chromium").exists(), reason="needs /usr/bin/chromium (apt-get install chromium)")
def test_web_view_draws_the_mesh_in_chromium(tmp_path):
    """A real browser: headless Chromium on `turntable view R --web` draws the reconstructed mesh."""
    web_view = _web_view_module()
    out, _ = web_view.make_reconstruction(tmp_path)
    port = web_view.free_port()
    proc, url = web_view.start_view(out, port)
    try:
        count, _ = web_view.shoot_until_drawn(url, tmp_path / "shot.png", timeout=300)
    finally:
        code, err = web_view.stop_view(proc)
    assert count >= web_view.MIN_MESH_PIXELS, f"mesh not drawn: {count} mesh pixels, see {tmp_path / 'shot.png'}"
    assert code == 130 and "Traceback" not in err
