"""The working resolution: K scaled with the pixel-centre convention, the default policy, ``--work-size``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.conics import fit_conic
from turntable.errors import UserError
from turntable.worksize import (
    MAX_DEFAULT_PIXELS,
    MIN_RING_PX,
    WorkSize,
    choose_work_size,
    parse_work_size,
    scale_matrix,
)

PX_TOL = 1e-9  # exact maps: pixels
CENTROID_TOL_PX = 0.02  # a blob's centroid after cv2.resize, work pixels


def _project(K, pts_cam):
    uv = (K @ pts_cam.T).T
    return uv[:, :2] / uv[:, 2:]


@pytest.mark.parametrize("full, work", [((4032, 3024), (1316, 987)), ((8064, 6048), (1000, 750)),
                                        ((3024, 4032), (960, 1280)), ((1280, 960), (1280, 960))])
def test_scaled_K_projects_where_the_pixel_centre_convention_says(full, work):
    rng = np.random.default_rng(0)
    K = np.array([[3.1 * 1500, 0, 2000.3], [0, 3.1 * 1500, 1510.8], [0, 0, 1]])
    pts = np.column_stack([rng.uniform(-200, 200, (50, 2)), rng.uniform(300, 900, 50)])
    ws = WorkSize(full, work, "test")
    uv_full, uv_work = _project(K, pts), _project(ws.K(K), pts)
    s = np.array(work, float) / np.array(full, float)
    np.testing.assert_allclose(uv_work, s * (uv_full + 0.5) - 0.5, atol=PX_TOL)
    np.testing.assert_allclose(ws.to_work(uv_full), uv_work, atol=PX_TOL)
    np.testing.assert_allclose(ws.to_full(uv_work), uv_full, atol=1e-6)
    Kw = ws.K(K)
    assert Kw[0, 0] == pytest.approx(s[0] * K[0, 0]) and Kw[0, 2] == pytest.approx(s[0] * (K[0, 2] + 0.5) - 0.5)


def test_conic_maps_with_the_points():
    rng = np.random.default_rng(1)
    t = rng.uniform(0, 2 * np.pi, 40)
    uv_full = np.column_stack([2000 + 900 * np.cos(t), 1500 + 400 * np.sin(t)])
    ws = WorkSize((4032, 3024), (1344, 1008), "test")
    Cw = ws.conic(fit_conic(uv_full))
    x = np.column_stack([ws.to_work(uv_full), np.ones(len(t))])
    resid = np.einsum("ij,jk,ik->i", x, Cw / np.linalg.norm(Cw), x)
    assert np.max(np.abs(resid)) < 1e-9


@pytest.mark.parametrize("factor", [3, 4])
def test_the_map_is_the_one_cv2_resize_samples_with(factor):
    """A bright blob at a sub-pixel position lands where to_work says after INTER_AREA reduction."""
    H, W = 240, 320
    u0, v0 = 141.3, 97.8
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.exp(-((xx - u0) ** 2 + (yy - v0) ** 2) / (2 * 6.0 ** 2)).astype(np.float32)
    ws = WorkSize((W, H), (W // factor, H // factor), "test")
    small = ws.reduce(img)
    ys, xs = np.mgrid[0:small.shape[0], 0:small.shape[1]]
    c = np.array([(xs * small).sum(), (ys * small).sum()]) / small.sum()
    np.testing.assert_allclose(c, ws.to_work(np.array([[u0, v0]]))[0], atol=CENTROID_TOL_PX)
    assert np.abs(c - np.array([u0, v0]) / factor).max() > 0.2  # a map without the half pixels would fail


def test_default_policy_keeps_small_photos_and_reduces_large_ones():
    assert choose_work_size((1280, 960), ring_px=540).is_full
    assert choose_work_size((1280, 960)).is_full
    ws = choose_work_size((4032, 3024), ring_px=1700)
    assert abs(ws.work[0] * ws.work[1] / MAX_DEFAULT_PIXELS - 1) < 0.01
    assert ws.work[0] / ws.work[1] == pytest.approx(4 / 3, abs=2e-3)
    small_ring = choose_work_size((8064, 6048), ring_px=2000)  # the object a small part of a 48 MP photo
    assert 2000 * small_ring.scale == pytest.approx(MIN_RING_PX, rel=0.01)
    assert "ring" in small_ring.why


def test_work_size_option():
    assert parse_work_size(None) is None and parse_work_size("full") == 0 and parse_work_size("1600") == 1600
    for bad in ("big", "12", "-5"):
        with pytest.raises(UserError, match="--work-size"):
            parse_work_size(bad)
    ws = choose_work_size((4032, 3024), ring_px=1700, requested=2016)
    assert ws.work == (2016, 1512) and ws.why == "--work-size 2016"
    assert choose_work_size((4032, 3024), requested=0).is_full
    assert choose_work_size((1280, 960), requested=4000).is_full
    assert np.allclose(scale_matrix((100, 50), (100, 50)), np.eye(3))
    with pytest.raises(ValueError, match="expected 4032x3024"):
        ws.reduce(np.zeros((10, 10), np.uint8))


# --------------------------------------------------------------------------- end to end
SAMPLE = __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "sample"
FOCAL_AGREE_REL = 0.002  # f of the x2 photos / 2 against the native f
VOLUME_AGREE_REL = 0.05  # model volume, upscaled vs native
CHAMFER_AGREE_MM = 0.3  # each model's Chamfer distance to the true object, upscaled minus native


@pytest.fixture(scope="module")
def upscaled_runs(tmp_path_factory):
    """6 frames of data/sample as they are (1280x960) and upscaled x2 (2560x1920, INTER_CUBIC, JPEG 92)."""
    import contextlib
    import io
    import json

    from turntable.cli import main

    root = tmp_path_factory.mktemp("worksize")
    files = sorted((SAMPLE / "images").iterdir())[::6]
    native, big = root / "native", root / "big"
    native.mkdir(), big.mkdir()
    for f in files:
        img = cv2.imread(str(f))
        cv2.imwrite(str(native / f.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        cv2.imwrite(str(big / f.name), cv2.resize(img, (2560, 1920), interpolation=cv2.INTER_CUBIC),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
    common = ["--r-outer", "80", "--r-inner", "50", "--resolution", "64", "--max-faces", "5000", "--no-fusion",
              "--quiet"]
    runs = {}
    for key, src, extra in (("native", native, []), ("big", big, []), ("big800", big, ["--work-size", "800"])):
        out = root / f"out_{key}"
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            code = main(["reconstruct", str(src), "--out", str(out), *common, *extra])
        runs[key] = (code, out, json.loads((out / "summary.json").read_text()), printed.getvalue())
    return runs


def _chamfer_to_truth_mm(glb) -> float:
    import trimesh
    from scipy.spatial import cKDTree

    a = trimesh.load(glb, force="mesh", skip_materials=True).sample(20000, seed=0) * 1000
    b = trimesh.load(SAMPLE / "object_gt.ply").sample(20000, seed=0)
    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def test_upscaled_photos_give_the_same_frames_and_model(upscaled_runs):
    (c0, o0, s0, _), (c1, o1, s1, _) = upscaled_runs["native"], upscaled_runs["big"]
    assert c0 == 0 and c1 == 0
    assert s0["work_size"]["width"] == 1280 and s0["work_size"]["scale"] == 1.0
    assert s1["work_size"]["full_width"] == 2560 and s1["work_size"]["width"] * s1["work_size"]["height"] <= 1.31e6
    assert s1["frames_used"] == s0["frames_used"] == 6 and s1["frames_skipped"] == s0["frames_skipped"] == {}
    assert abs(s1["focal_px"] / 2 / s0["focal_px"] - 1) < FOCAL_AGREE_REL  # calibrated at 2560x1920
    assert abs(s1["mesh"]["volume_cm3"] / s0["mesh"]["volume_cm3"] - 1) < VOLUME_AGREE_REL
    assert _chamfer_to_truth_mm(o1 / "model.glb") < _chamfer_to_truth_mm(o0 / "model.glb") + CHAMFER_AGREE_MM


def test_work_size_is_honoured_and_reported(upscaled_runs):
    from turntable.cameras_io import read_cameras

    code, out, s, printed = upscaled_runs["big800"]
    assert code == 0
    assert (s["work_size"]["width"], s["work_size"]["height"]) == (800, 600)
    assert s["work_size"]["why"] == "--work-size 800"
    assert read_cameras(out / "cameras.json").intrinsics.width == 2560  # cameras stay in the photos' pixels
    assert "work size       800 x 600 px (0.312 of 2560 x 1920; --work-size 800)" in printed
