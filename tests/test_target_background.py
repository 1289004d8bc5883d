"""A target printed on a coloured ground (``pattern --background``, ``synth --target-background``)."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from calib.calibrate import calibrate_view
from calib.camera import plane_homography, project_points
from calib.marks import align_pose_to_marks, read_turntable_angle
from calib.rings import detect_rings
from calib.target import TargetSpec
from turntable.cli import main
from turntable.pattern import (
    BACKGROUND_COLOURS,
    MIN_BACKGROUND_LUMINANCE,
    SHEET_MARGIN_MM,
    parse_background,
    relative_luminance,
    sheet_layout,
    write_pattern,
)

SPEC = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
GREEN = BACKGROUND_COLOURS["green"]


def test_named_colours_are_light_enough_and_hex_parses():
    for name, rgb in BACKGROUND_COLOURS.items():
        assert relative_luminance(rgb) >= MIN_BACKGROUND_LUMINANCE, name
        assert parse_background(name.upper()) == rgb
    assert parse_background("#5BC85B") == (91, 200, 91)
    assert relative_luminance((255, 255, 255)) == pytest.approx(1.0)
    assert relative_luminance((0, 0, 0)) == 0.0
    for text in ("black", "#000080", "#595959"):          # navy, a mid-dark grey (Y 0.10)
        with pytest.raises(ValueError, match="too dark|not a colour"):
            parse_background(text)
    for text in ("#12345", "#gg0000", "0x5bc85b", ""):
        with pytest.raises(ValueError, match="not a colour"):
            parse_background(text)


def test_png_ground_is_the_colour_under_black_ink(tmp_path):
    dpi = 40.0
    img = np.asarray(Image.open(write_pattern(tmp_path / "t.png", SPEC, dpi=dpi, background="green")))
    assert img.ndim == 3 and img.shape[2] == 3
    px = dpi / 25.4
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    at = lambda x_mm, y_mm: tuple(img[int(round(y_mm * px - 0.5)), int(round(x_mm * px - 0.5))])  # noqa: E731
    assert at(cx, cy) == GREEN                            # inside the inner ring
    assert at(cx + 65.0, cy) == GREEN                     # between the rings
    assert at(15.0, 200.0) == GREEN                       # far from the target, still the printable area
    assert at(cx + 80.0, cy) == (0, 0, 0)                 # the outer ring stays black
    assert at(1.0, 1.0) == (255, 255, 255)                # the unprintable margin stays paper
    assert 1.0 + 1.0 / px < SHEET_MARGIN_MM


def test_svg_and_pdf_fill_the_printable_area(tmp_path):
    root = ET.parse(write_pattern(tmp_path / "t.svg", SPEC, background="#6ea8ff")).getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    rects = root.findall("s:rect", ns)
    ground = [r for r in rects if r.get("fill") == "#6ea8ff"]
    assert len(ground) == 1 and rects.index(ground[0]) == 1      # right over the white sheet, under all ink
    g = ground[0]
    assert [float(g.get(k)) for k in ("x", "y", "width", "height")] == [5.0, 5.0, 200.0, 287.0]
    assert all(c.get("stroke") == "#000000" for c in root.findall("s:circle", ns))
    plain = ET.parse(write_pattern(tmp_path / "w.svg", SPEC)).getroot()
    assert [r.get("fill") for r in plain.findall("s:rect", ns)][0] == "#ffffff"
    assert not [r for r in plain.findall("s:rect", ns) if r.get("id") == "ground"]

    data = Path(write_pattern(tmp_path / "t.pdf", SPEC, background="green")).read_bytes()
    stream = re.search(rb"stream\n(.*)\nendstream", data, re.S).group(1)
    ops = zlib.decompress(stream).decode("latin-1").splitlines()
    r, gg, b = (v / 255 for v in GREEN)
    assert ops[1] == f"{r:.4f} {gg:.4f} {b:.4f} rg 5.0000 5.0000 200.0000 287.0000 re f"
    assert ops[2].startswith("0 g 0 G")                   # ink is black again before the rings
    plain_pdf = Path(write_pattern(tmp_path / "w.pdf", SPEC)).read_bytes()
    assert b" rg " not in zlib.decompress(re.search(rb"stream\n(.*)\nendstream", plain_pdf, re.S).group(1))


@pytest.mark.parametrize("colour, message", [("#202020", "too dark"), ("navy", "not a colour")])
def test_cli_refuses_a_ground_the_rings_would_vanish_on(tmp_path, capsys, colour, message):
    out = tmp_path / "t.pdf"
    assert main(["pattern", str(out), "--background", colour]) == 2
    err = capsys.readouterr().err
    assert "--background" in err and message in err and colour in err and "Traceback" not in err
    assert not out.exists()
    assert main(["synth", str(tmp_path / "s"), "--frames", "1", "--size", "64x48",
                 "--target-background", colour]) == 2
    err = capsys.readouterr().err
    assert "--target-background" in err and message in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_photographed_green_sheet_calibrates(tmp_path):
    """The green sheet as printed, photographed at 35 deg: rings, focal length and marks as on white paper."""
    from synthetic_images import look_at_T

    dpi = 150.0
    sheet = np.asarray(Image.open(write_pattern(tmp_path / "t.png", SPEC, dpi=dpi, background="green")))
    px = dpi / 25.4
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    M_table_sheet = np.array([[1 / px, 0, 0.5 / px - cx], [0, 1 / px, 0.5 / px - cy], [0, 0, 1.0]])
    W, H, f = 1280, 960, 1400.0
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    T_true = look_at_T(35.0, 50.0, 450.0)
    S2 = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])
    big = cv2.warpPerspective(np.ascontiguousarray(sheet[..., ::-1]), S2 @ plane_homography(K, T_true) @ M_table_sheet,
                              (2 * W, 2 * H), flags=cv2.INTER_LINEAR, borderValue=(60, 60, 60))
    photo = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)                 # BGR
    photo = cv2.imdecode(cv2.imencode(".jpg", photo, [cv2.IMWRITE_JPEG_QUALITY, 95])[1], cv2.IMREAD_COLOR)
    centre = project_points(K, T_true, np.array([[0.0, 0.0, 65.0]]))[0]
    assert photo[int(round(centre[1])), int(round(centre[0]))][1] > 150   # the photo does show green paper

    cal = calibrate_view(detect_rings(photo, SPEC, gamma=1.0), SPEC)  # the warp mixes grey levels linearly
    assert abs(cal.intrinsics.focal_px / f - 1) < 0.003
    reading = read_turntable_angle(photo, cal.intrinsics.K, cal.T_cam_table, SPEC)
    assert reading.coverage > 0.5
    dR = align_pose_to_marks(cal.T_cam_table, reading.angle_deg)[:3, :3].T @ T_true[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1


def test_synth_renders_the_ground_colour_on_the_paper(tmp_path):
    """The same scene on white and on green paper: between the rings each channel scales by the ground's."""
    from turntable.synth.sequence import SynthOptions, make_sequence

    base = dict(frames=1, width=160, height=120, focal_px=190.0, supersample=1, noise=0.0, jpeg=0, vignette=0.0)
    white = make_sequence(tmp_path / "w", SynthOptions(**base))
    green = make_sequence(tmp_path / "g", SynthOptions(**base, target_background="green"))
    scene = json.loads((green / "scene.json").read_text())
    assert scene["options"]["target_background"] == "green" and scene["target_background_rgb"] == list(GREEN)
    assert json.loads((white / "scene.json").read_text())["target_background_rgb"] == [255, 255, 255]
    from turntable.cameras_io import read_cameras

    seq = read_cameras(green / "cameras_gt.json")
    pts = np.array([[0.0, 0.0, 65.0], [65.0, 0.0, 0.0], [-65.0, 0.0, 0.0]])  # between the rings, in front
    uv = np.round(project_points(seq.intrinsics.K, seq.frames[0].T_cam_table, pts)).astype(int)
    a = cv2.imread(str(white / "images/frame_000.png"))[..., ::-1].astype(float)[uv[:, 1], uv[:, 0]]
    b = cv2.imread(str(green / "images/frame_000.png"))[..., ::-1].astype(float)[uv[:, 1], uv[:, 0]]
    assert np.all(a > 120), a                             # lit paper on the white target
    ratio = b / a                                         # sRGB ratios survive the shading
    tol = 0.05
    np.testing.assert_allclose(ratio, np.broadcast_to(np.array(GREEN) / 255.0, ratio.shape), atol=tol)
    u, v = np.round(project_points(seq.intrinsics.K, seq.frames[0].T_cam_table, np.array([[0.0, 0.0, 80.0]]))[0])
    near = cv2.imread(str(green / "images/frame_000.png"))[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2]
    assert near.max(axis=2).min() < 60                    # the outer ring's ink stays dark on green
