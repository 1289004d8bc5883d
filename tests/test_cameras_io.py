"""cameras.json: schema round trip and bad input."""

import json

import numpy as np
import pytest

from calib.camera import make_T, rotation_from_normal
from calib.types import FramePose, Intrinsics, SequenceCalibration
from turntable.cameras_io import cameras_to_dict, read_cameras, write_cameras
from turntable.errors import UserError


def _seq():
    intr = Intrinsics.from_focal(1500.0, 1280, 960, dist=[-0.1, 0.01, 0, 0, 0])
    frames = []
    for k in range(3):
        T = make_T(rotation_from_normal([0, -0.8, -0.6]), [0, 20, 450 + k])
        frames.append(FramePose(image=f"frame_{k:03d}.jpg", angle_deg=10.0 * k, T_cam_table=T, rms_px=0.1 * k))
    frames.append(FramePose(image="bad.jpg", angle_deg=float("nan"), T_cam_table=np.eye(4),
                            status="inner ring not found"))
    return SequenceCalibration(intrinsics=intr, frames=tuple(frames), extra={"object": "vase"})


def test_round_trip(tmp_path):
    seq = _seq()
    p = tmp_path / "cameras.json"
    write_cameras(p, seq)
    d = json.loads(p.read_text())
    assert d["units"] == "mm" and d["intrinsics"]["width"] == 1280 and d["object"] == "vase"
    assert d["frames"][3]["angle_deg"] is None  # NaN is written as null, valid JSON
    back = read_cameras(p)
    np.testing.assert_allclose(back.intrinsics.K, seq.intrinsics.K)
    np.testing.assert_allclose(back.intrinsics.dist, seq.intrinsics.dist)
    assert [f.image for f in back.ok_frames()] == [f"frame_{k:03d}.jpg" for k in range(3)]
    assert back.frames[3].status == "inner ring not found"
    for a, b in zip(back.frames, seq.frames, strict=True):
        np.testing.assert_allclose(a.T_cam_table, b.T_cam_table)
    assert back.extra["object"] == "vase"


@pytest.mark.parametrize("content,reason", [
    ("not json", "cannot read"),
    ("[1, 2]", "top level"),
    ('{"units": "m", "intrinsics": {}, "frames": []}', "units"),
    ('{"intrinsics": {"K": [[1]]}, "frames": []}', "not a valid"),
])
def test_bad_files_name_the_file_and_reason(tmp_path, content, reason):
    p = tmp_path / "cams.json"
    p.write_text(content)
    with pytest.raises(UserError, match=reason) as exc:
        read_cameras(p)
    assert str(p) in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(UserError, match="not found"):
        read_cameras(tmp_path / "nope.json")


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["frames"][1]["T_cam_table"][0].__setitem__(3, float("nan")), r"frame 1 \(frame_001.jpg\).*non-finite"),
    (lambda d: d["frames"][0].__setitem__("T_cam_table", np.eye(4).tolist()), r"frame 0 \(frame_000.jpg\).*in front"),
    (lambda d: d["frames"][2]["T_cam_table"][0].__setitem__(0, 2.0), r"frame 2 .*not a rotation"),
    (lambda d: d["frames"][2]["T_cam_table"][3].__setitem__(2, 1.0), r"frame 2 .*last row"),
    (lambda d: d["intrinsics"]["K"][0].__setitem__(0, -1500.0), r"focal lengths must be positive.*fx = -1500"),
    (lambda d: d["intrinsics"]["K"][1].__setitem__(1, float("nan")), r"finite 3x3"),
    (lambda d: d["intrinsics"]["K"][2].__setitem__(0, 0.5), r"last row must be \[0, 0, 1\]"),
    (lambda d: d["intrinsics"].__setitem__("width", 0), r"width and height must be positive"),
    (lambda d: d["intrinsics"]["dist"].__setitem__(0, float("inf")), r"dist must be finite"),
])
def test_implausible_cameras_are_refused_naming_file_and_frame(tmp_path, edit, match):
    p = tmp_path / "cameras.json"
    write_cameras(p, _seq())
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))  # Python writes NaN / Infinity literals, as a hand-edited file might have
    with pytest.raises(UserError, match=match) as e:
        read_cameras(p)
    assert str(p) in str(e.value)


def test_a_failed_frame_keeps_its_placeholder_pose(tmp_path):
    p = tmp_path / "cameras.json"
    write_cameras(p, _seq())  # frame 3 failed: identity pose, status says why
    assert read_cameras(p).frames[3].status == "inner ring not found"


def _calibrated_dict() -> dict:
    """A cameras.json as calibrate-sequence wrote it before diagnostics were typed (keys in that order)."""
    d = cameras_to_dict(_seq())
    del d["object"]
    d.update({
        "mode_reason": "fixed camera", "rms_px": 0.066, "single_view_rms_px": 0.067, "frames_used": 3,
        "frames_skipped": 1, "focal_std_px": 0.11, "principal_point_std_px": [None, None], "dist_std": {"k1": 0.001},
        "stroke_mm": 3.05, "stroke_std_mm": None, "not_estimated": {"principal_point": "not estimated: ..."},
        "intrinsics_source": "estimated",
        "turntable": {"pattern_offset_from_axis_mm": [0.1, -0.2], "camera_height_mm": 225.0,
                      "camera_radius_mm": 389.8, "camera_centres_off_circle_median_mm": 0.03,
                      "marks_residual_deg": {"median_abs": 0.01, "max_abs": 0.05}},
        "angle_checks": [{"image": "frame_001.jpg", "marks_minus_step_deg": 1.5}],
        "warnings": ["--step-deg 10 contradicts the angle marks"],
        "exif_focal": {"focal_35mm": 26.0, "focal_px": 1000.0, "disagrees": True},
        "stage_key": "abc123",
        "object": "vase",
    })
    return d


def test_diagnostics_are_typed_and_written_back_byte_for_byte(tmp_path):
    """An older cameras.json (diagnostics as plain keys) reads into SequenceDiagnostics and writes back the
    same bytes; a file without them (synth's ground truth) has no diagnostics."""
    p = tmp_path / "cameras.json"
    text = json.dumps(_calibrated_dict(), indent=1) + "\n"
    p.write_text(text)
    seq = read_cameras(p)
    diag = seq.diagnostics
    assert diag.mode_reason == "fixed camera" and diag.focal_std_px == 0.11 and diag.frames_skipped == 1
    assert diag.turntable.pattern_offset_from_axis_mm == (0.1, -0.2)
    assert diag.turntable.marks_residual_deg == (0.01, 0.05)
    assert diag.angle_checks[0].image == "frame_001.jpg" and diag.angle_checks[0].marks_minus_step_deg == 1.5
    assert diag.warnings == ("--step-deg 10 contradicts the angle marks",)
    assert diag.exif_focal["disagrees"] and diag.stage_key == "abc123"
    assert seq.extra == {"object": "vase"}
    q = tmp_path / "again.json"
    write_cameras(q, seq)
    assert q.read_text() == text
    write_cameras(p, _seq())
    assert read_cameras(p).diagnostics is None


def test_an_older_file_without_some_diagnostics_still_reads(tmp_path):
    d = _calibrated_dict()
    for key in ("single_view_rms_px", "turntable", "intrinsics_source", "warnings", "stage_key"):
        del d[key]
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps(d))
    diag = read_cameras(p).diagnostics
    assert diag.single_view_rms_px is None and diag.turntable is None and diag.intrinsics_source is None
    assert diag.warnings == () and diag.stage_key is None and diag.rms_px == 0.066
