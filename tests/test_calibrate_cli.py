"""``turntable calibrate`` end to end: JSON contract, overlays, and bad inputs.

Two good photos are made once per module: a 640x480 frame rendered by
``turntable.synth`` (ray-cast vase on the printed target, JPEG 95, exact ground
truth in ``cameras_gt.json``) and a warped-sheet photo from
``synthetic_images.render_target_photo`` (another pose, light backdrop). The bad
inputs sit beside them in the same call, so every failure is also a check that
the good images are still processed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from synthetic_images import look_at_T, render_target_photo

from calib.camera import angle_between_deg
from calib.target import TargetSpec
from turntable.cameras_io import read_cameras
from turntable.cli import main

R_OUTER, R_INNER, STROKE = 80.0, 50.0, 3.0
SPEC = TargetSpec(R_OUTER, R_INNER, STROKE)
TARGET_ARGS = ["--r-outer", "80", "--r-inner", "50", "--stroke", "3"]

# 640x480, f 800 px, ~450 mm away: the rings' outer diameter is ~280 px.
F_TOL_REL = 0.01        # relative focal error allowed on these small frames
NORMAL_TOL_DEG = 0.5
T_TOL_REL = 0.01
PP_TOL_PX = 1e-9


@dataclass(frozen=True)
class Photo:
    """An image file and the camera that took it (K (3, 3) px, T_cam_table (4, 4) mm)."""

    path: Path
    K: np.ndarray
    T_cam_table: np.ndarray


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> dict[str, Photo]:
    from turntable.synth.sequence import SynthOptions, make_sequence

    root = tmp_path_factory.mktemp("calibrate_cli")
    seq_dir = make_sequence(root / "synth", SynthOptions(
        object="vase", frames=1, width=640, height=480, focal_px=800.0, elevation_deg=40.0,
        distance_mm=450.0, backdrop="clutter", jpeg=95, seed=3, supersample=2))
    gt = read_cameras(seq_dir / "cameras_gt.json")
    out = {"synth": Photo(seq_dir / gt.frames[0].image, gt.intrinsics.K, gt.frames[0].T_cam_table)}

    rng = np.random.default_rng(11)
    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1.0]])
    T = look_at_T(35.0, 120.0, 420.0, look_at_table=(5.0, 0.0, -8.0), roll_deg=6.0)
    p = render_target_photo(SPEC, K, T, (640, 480), rng=rng, backdrop="light", jpeg_quality=95)
    cv2.imwrite(str(root / "warped.png"), p.image)
    out["warped"] = Photo(root / "warped.png", K, T)

    one = render_target_photo(SPEC, K, T, (640, 480), rng=rng, backdrop="dark", occluder=False,
                              rings_mm=[(0.0, 0.0, R_OUTER)], jpeg_quality=None)
    cv2.imwrite(str(root / "one_ring.png"), one.image)
    out["one_ring"] = Photo(root / "one_ring.png", K, T)

    cv2.imwrite(str(root / "blank.png"), np.full((480, 640, 3), 255, np.uint8))
    out["blank"] = Photo(root / "blank.png", K, T)
    (root / "notes.jpg").write_text("this is not a photo\n")
    out["text"] = Photo(root / "notes.jpg", K, T)
    out["missing"] = Photo(root / "no_such_photo.jpg", K, T)
    return out


def _run(capsys, argv):
    rc = main(["calibrate", *map(str, argv)])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _check_against_gt(rec: dict, photo: Photo) -> None:
    assert rec["status"] == "ok", rec
    f_gt = photo.K[0, 0]
    assert abs(rec["focal_px"] - f_gt) / f_gt < F_TOL_REL, (rec["focal_px"], f_gt)
    R = np.array(rec["R_cam_table"])
    t = np.array(rec["t_cam_table_mm"])
    assert R.shape == (3, 3) and t.shape == (3,)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    # second column: the table normal, on the camera's side of the plane (towards -t)
    assert angle_between_deg(R[:, 1], photo.T_cam_table[:3, 1]) < NORMAL_TOL_DEG
    assert R[:, 1] @ -t > 0
    t_gt = photo.T_cam_table[:3, 3]
    assert np.linalg.norm(t - t_gt) / np.linalg.norm(t_gt) < T_TOL_REL, (t, t_gt)


def test_json_single_image_matches_ground_truth(photos, capsys):
    ph = photos["synth"]
    rc, out, err = _run(capsys, [ph.path, *TARGET_ARGS, "--json"])
    assert rc == 0, err
    rec = json.loads(out)
    assert isinstance(rec, dict)
    for key in ("image", "focal_px", "principal_point_px", "R_cam_table", "t_cam_table_mm", "std", "rms_px", "solver"):
        assert key in rec, key
    assert rec["image"] == str(ph.path)
    assert rec["solver"] == "refine"
    np.testing.assert_allclose(rec["principal_point_px"], [319.5, 239.5], atol=PP_TOL_PX)
    _check_against_gt(rec, ph)
    std = rec["std"]
    assert set(std) >= {"focal_px", "normal_deg", "t_mm"}
    assert 0 < std["focal_px"] < 0.05 * rec["focal_px"]
    assert 0 < std["normal_deg"] < 1.0
    assert len(std["t_mm"]) == 3 and all(0 < v < 20.0 for v in std["t_mm"])
    assert 0 < rec["rms_px"] < 1.0


def test_json_list_for_several_images_in_order(photos, capsys):
    names = ("warped", "synth")
    rc, out, err = _run(capsys, [*(photos[n].path for n in names), *TARGET_ARGS, "--json"])
    assert rc == 0, err
    recs = json.loads(out)
    assert isinstance(recs, list) and [r["image"] for r in recs] == [str(photos[n].path) for n in names]
    for r, n in zip(recs, names, strict=True):
        _check_against_gt(r, photos[n])


@pytest.mark.parametrize("solver", ["paper", "pencil"])
def test_closed_form_solvers_and_given_principal_point(photos, capsys, solver):
    ph = photos["warped"]
    rc, out, err = _run(capsys, [ph.path, *TARGET_ARGS, "--json", "--solver", solver,
                                 "--principal-point", "319.5", "239.5"])
    assert rc == 0, err
    rec = json.loads(out)
    assert rec["solver"] == solver
    np.testing.assert_allclose(rec["principal_point_px"], [319.5, 239.5], atol=PP_TOL_PX)
    _check_against_gt(rec, ph)


def test_table_output_without_json(photos, capsys):
    ph = photos["synth"]
    rc, out, err = _run(capsys, [ph.path, *TARGET_ARGS])
    assert rc == 0, err
    assert ph.path.name in out and "ok" in out
    with pytest.raises(json.JSONDecodeError):
        json.loads(out)


def test_overlay_png_per_image(photos, capsys, tmp_path):
    names = ("synth", "warped", "blank")
    rc, out, err = _run(capsys, [*(photos[n].path for n in names), *TARGET_ARGS, "--overlay", tmp_path / "ov"])
    assert rc == 1  # the blank image fails; its overlay is still written (with the reason)
    for n in names:
        p = tmp_path / "ov" / f"{photos[n].path.stem}_overlay.png"
        assert p.is_file(), p
        img = cv2.imread(str(p))
        assert img is not None and img.shape[:2] == (480, 640)
    # an overlay of a calibrated image differs from the photo (the rings are drawn)
    drawn = cv2.imread(str(tmp_path / "ov" / f"{photos['synth'].path.stem}_overlay.png")).astype(int)
    photo = cv2.imread(str(photos["synth"].path)).astype(int)
    assert np.mean(np.abs(drawn - photo).sum(axis=2) > 60) > 0.002


# bad input -> a word its reason must contain
BAD = {
    "missing": "not found",
    "text": "cannot decode",
    "blank": "ring",
    "one_ring": "ring",
}


@pytest.mark.parametrize("bad", sorted(BAD))
def test_bad_image_is_reported_and_others_still_processed(photos, capsys, bad):
    good = photos["synth"]
    rc, out, err = _run(capsys, [photos[bad].path, good.path, *TARGET_ARGS, "--json"])
    assert rc != 0
    assert "Traceback" not in err and "internal error" not in err
    lines = [ln for ln in err.splitlines() if str(photos[bad].path) in ln]
    assert len(lines) == 1, err
    reason = lines[0].split(f"{photos[bad].path}:", 1)[1].strip()
    assert len(reason) > 5, lines[0]
    assert BAD[bad] in reason
    assert str(good.path) not in err
    recs = json.loads(out)
    assert [r["image"] for r in recs] == [str(photos[bad].path), str(good.path)]
    assert recs[0]["status"] != "ok" and recs[0]["error"]
    _check_against_gt(recs[1], good)


def test_wrong_inner_radius_is_a_per_image_failure(photos, capsys):
    ph = photos["synth"]
    rc, out, err = _run(capsys, [ph.path, "--r-outer", "80", "--r-inner", "35", "--json"])
    assert rc != 0
    assert "Traceback" not in err and "internal error" not in err
    assert str(ph.path) in err
    rec = json.loads(out)
    assert rec["status"] != "ok" and rec["error"]


def test_wrong_inner_radius_message_names_the_ratio(photos, capsys):
    ph = photos["synth"]
    rc, out, err = _run(capsys, [ph.path, "--r-outer", "80", "--r-inner", "35"])
    assert rc != 0
    assert "ratio" in err.lower()
    listed = [float(x) for x in err.split("radius ratios ")[1].split(";")[0].split(", ")]
    assert min(abs(r / 1.6 - 1) for r in listed) < 0.02  # the printed rings' ratio is among them


@pytest.mark.parametrize("r_inner", ["49", "49.6", "50.4", "51"])
def test_slightly_wrong_inner_radius_is_refused_not_silently_wrong(photos, capsys, r_inner):
    ph = photos["synth"]
    rc, out, err = _run(capsys, [ph.path, "--r-outer", "80", "--r-inner", r_inner, "--json"])
    rec = json.loads(out)
    if rec["status"] == "ok":  # accepted: then it must still be right
        assert abs(rec["focal_px"] / ph.K[0, 0] - 1.0) < F_TOL_REL, rec["focal_px"]
    else:
        assert rc != 0 and "ratio" in rec["error"]


@pytest.mark.parametrize("r_inner", ["80", "90"])
def test_inner_not_smaller_than_outer_is_a_clean_error(photos, capsys, r_inner):
    rc, out, err = _run(capsys, [photos["synth"].path, "--r-outer", "80", "--r-inner", r_inner])
    assert rc == 2
    assert "Traceback" not in err
    assert "--r-inner" in err and "--r-outer" in err
    assert out == ""


def test_unexpected_error_on_one_image_keeps_the_others(photos, capsys, monkeypatch):
    import calib.rings

    real = calib.rings.detect_rings
    bad = photos["warped"]

    def detect(image, spec, **kw):
        if image.shape == (480, 640, 3) and np.array_equal(image, cv2.imread(str(bad.path))):
            raise RuntimeError("simulated bug")
        return real(image, spec, **kw)

    monkeypatch.setattr(calib.rings, "detect_rings", detect)
    rc, out, err = _run(capsys, [bad.path, photos["synth"].path, *TARGET_ARGS, "--json"])
    assert rc == 1
    assert "Traceback" not in err
    assert f"{bad.path}: internal error: RuntimeError: simulated bug" in err
    recs = json.loads(out)
    assert recs[0]["status"] == "error"
    _check_against_gt(recs[1], photos["synth"])
