"""The printable sheet: PDF/SVG/PNG at true scale, readable by our own reader."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from calib.camera import make_T
from calib.marks import read_turntable_angle, turntable_rotation
from calib.target import TargetSpec, mark_cells, mark_edges
from turntable.cli import main
from turntable.pattern import sheet_layout, write_pattern

SPEC = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
PT_TOL = 0.01        # PDF MediaBox, points
MM_TOL = 1e-3        # SVG geometry, mm


def test_pdf_is_a4_with_a_valid_xref(tmp_path):
    path = write_pattern(tmp_path / "t.pdf", SPEC, paper="a4")
    data = Path(path).read_bytes()
    assert data.startswith(b"%PDF-1.") and data.rstrip().endswith(b"%%EOF")
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", data).group(1).split()]
    assert np.allclose(box, [0, 0, 595.28, 841.89], atol=PT_TOL)
    # every xref offset points at its object
    start = int(re.search(rb"startxref\s+(\d+)", data).group(1))
    assert data[start:start + 4] == b"xref"
    rows = re.findall(rb"(\d{10}) 00000 n", data[start:])
    assert len(rows) >= 5
    for k, off in enumerate(rows, start=1):
        assert data[int(off):].startswith(b"%d 0 obj" % k)


def test_pdf_letter_media_box(tmp_path):
    data = Path(write_pattern(tmp_path / "t.pdf", SPEC, paper="letter")).read_bytes()
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", data).group(1).split()]
    assert np.allclose(box, [0, 0, 612.0, 792.0], atol=PT_TOL)


def test_svg_is_millimetre_true_scale_with_rings_marks_and_scale_bar(tmp_path):
    path = write_pattern(tmp_path / "t.svg", SPEC, paper="a4")
    root = ET.parse(path).getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    assert root.get("width") == "210mm" and root.get("height") == "297mm"
    assert root.get("viewBox") == "0 0 210 297"
    circles = root.findall("s:circle", ns)
    assert sorted(float(c.get("r")) for c in circles) == [50.0, 80.0]
    assert all(float(c.get("stroke-width")) == 3.0 for c in circles)
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    assert all(abs(float(c.get("cx")) - cx) < MM_TOL and abs(float(c.get("cy")) - cy) < MM_TOL for c in circles)
    paths = root.findall("s:path", ns)
    assert len(paths) == len(mark_cells(SPEC))
    # the first sector starts on the outer mark radius at its start angle
    t0, _, _, r1 = mark_cells(SPEC)[0]
    x, y = (float(v) for v in re.match(r"M([-\d.]+),([-\d.]+)", paths[0].get("d")).groups())
    assert np.hypot(x - cx, y - cy) == pytest.approx(r1, abs=MM_TOL)
    assert abs((np.arctan2(y - cy, x - cx) - t0 + np.pi) % (2 * np.pi) - np.pi) < 1e-4
    assert any(float(r.get("width")) == 50.0 for r in root.findall("s:rect", ns))
    text = " ".join(t.text for t in root.findall("s:text", ns))
    assert "100 %" in text and "50 mm" in text and "outer radius 80 mm" in text and "stroke 3 mm" in text


def test_png_has_the_paper_size_at_its_dpi_and_a_50_mm_bar(tmp_path):
    dpi = 300.0
    path = write_pattern(tmp_path / "t.png", SPEC, paper="a4", dpi=dpi)
    im = Image.open(path)
    assert im.size == (2480, 3508)                       # 210 x 297 mm at 300 dpi
    assert np.allclose(im.info["dpi"], (dpi, dpi), atol=0.01)
    img = np.asarray(im.convert("L"), dtype=np.float64)
    px = dpi / 25.4
    x0, y0, length = sheet_layout(SPEC, "a4").scale_bar_mm
    row = img[int(round((y0 + 0.75) * px - 0.5))]
    cols = slice(int((x0 - 1.0) * px), int((x0 + length + 1.5) * px))
    ink_mm = (1.0 - row[cols] / 255.0).sum() / px
    assert ink_mm == pytest.approx(50.0, abs=0.5 / px * 2)
    # rings where the spec says, with table +X along the sheet's x
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    def at(x_mm, z_mm):
        return img[int(round((cy + z_mm) * px - 0.5)), int(round((cx + x_mm) * px - 0.5))]

    assert at(80.0, 0.0) == 0 and at(-50.0, 0.0) == 0 and at(0.0, 80.0) == 0
    assert at(83.5, 0.0) == 255 and at(65.0, 0.0) == 255 and at(0.0, 0.0) == 255


def test_printed_png_read_back_gives_its_own_angle(tmp_path):
    dpi = 100.0
    path = write_pattern(tmp_path / "t.png", SPEC, paper="letter", dpi=dpi)
    img = np.asarray(Image.open(path).convert("L"))
    px = dpi / 25.4
    cx, cy = sheet_layout(SPEC, "letter").centre_mm
    d = 500.0                                             # a camera straight above the sheet
    K = np.array([[px * d, 0, cx * px - 0.5], [0, px * d, cy * px - 0.5], [0, 0, 1.0]])
    T_printed = make_T(np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [0, 0, d])
    rng = np.random.default_rng(5)
    alpha = rng.uniform(0, 360)
    reading = read_turntable_angle(img, K, T_printed @ turntable_rotation(-alpha), SPEC)
    assert abs((reading.angle_deg - alpha + 180) % 360 - 180) < 0.05
    assert reading.coverage == 1.0 and reading.n_edges == mark_edges(SPEC)[0].size


def test_no_marks_leaves_the_mark_annulus_white(tmp_path):
    dpi = 60.0
    plain = TargetSpec(80.0, 50.0, 3.0, marks=False)
    img = np.asarray(Image.open(write_pattern(tmp_path / "p.png", plain, dpi=dpi)).convert("L"))
    px = dpi / 25.4
    cx, cy = sheet_layout(plain, "a4").centre_mm
    th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    th = th[np.abs(np.cos(th)) > 0.8]                     # left and right: the text is above and below
    u = np.round((cx + 92.0 * np.cos(th)) * px - 0.5).astype(int)
    v = np.round((cy + 92.0 * np.sin(th)) * px - 0.5).astype(int)
    assert img[v, u].min() == 255
    marked = np.asarray(Image.open(write_pattern(tmp_path / "m.png", SPEC, dpi=dpi)).convert("L"))
    assert (marked[v, u] == 0).mean() > 0.3


def test_refuses_bad_format_and_patterns_that_do_not_fit(tmp_path):
    with pytest.raises(ValueError, match="unsupported output format"):
        write_pattern(tmp_path / "t.jpg", SPEC)
    with pytest.raises(ValueError, match="does not fit"):
        write_pattern(tmp_path / "t.pdf", TargetSpec(120.0, 60.0, 3.0), paper="a4")
    write_pattern(tmp_path / "t.pdf", TargetSpec(120.0, 60.0, 3.0), paper="a3")
    write_pattern(tmp_path / "t.svg", SPEC, paper=(220.0, 320.0))
    with pytest.raises(ValueError, match="paper"):
        write_pattern(tmp_path / "t.svg", SPEC, paper="b5x")


def test_cli_writes_the_sheet_and_reports_user_errors(tmp_path, capsys):
    out = tmp_path / "target.svg"
    assert main(["pattern", str(out), "--r-outer", "70", "--r-inner", "45", "--stroke", "2.5"]) == 0
    assert 'r="70.0000"' in out.read_text() and "outer radius 70 mm" in out.read_text()
    assert main(["pattern", str(tmp_path / "target.txt")]) == 2
    assert "unsupported format" in capsys.readouterr().err
    assert main(["pattern", str(tmp_path / "big.pdf"), "--r-outer", "130", "--r-inner", "60"]) == 2
    assert "does not fit" in capsys.readouterr().err
    assert main(["pattern", str(tmp_path / "x.pdf"), "--paper", "huge"]) == 2
    assert main(["pattern", str(tmp_path / "x.png"), "--paper", "300x400", "--dpi", "20", "--no-marks"]) == 0
    assert Image.open(tmp_path / "x.png").size == (236, 315)


def test_printed_png_photographed_calibrates_back_to_its_own_geometry(tmp_path):
    """The sheet as printed, photographed at 40 deg: our detector, solver and mark
    reader give back the camera that took the photo, the printed radii's ratio
    and the printed 0 deg mark (the sheet's table frame)."""
    import cv2
    from synthetic_images import look_at_T

    from calib.calibrate import calibrate_view
    from calib.camera import camera_centre_table, plane_homography
    from calib.marks import align_pose_to_marks
    from calib.rings import detect_rings, pencil_ratio

    dpi = 150.0
    sheet = np.asarray(Image.open(write_pattern(tmp_path / "t.png", SPEC, paper="a4", dpi=dpi)).convert("L"))
    px = dpi / 25.4
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    # sheet pixel (u, v) -> table (X, Z): pixel centres at (u + 0.5) / px mm from the sheet's corner
    M_table_sheet = np.array([[1 / px, 0, 0.5 / px - cx], [0, 1 / px, 0.5 / px - cy], [0, 0, 1.0]])
    W, H, f = 1280, 960, 1400.0
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    T_true = look_at_T(40.0, 30.0, 450.0)
    S2 = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])  # 2x supersampling, pixel centres kept
    big = cv2.warpPerspective(sheet, S2 @ plane_homography(K, T_true) @ M_table_sheet, (2 * W, 2 * H),
                              flags=cv2.INTER_LINEAR, borderValue=90)
    photo = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
    photo = cv2.imdecode(cv2.imencode(".jpg", photo, [cv2.IMWRITE_JPEG_QUALITY, 95])[1], cv2.IMREAD_GRAYSCALE)

    obs = detect_rings(photo, SPEC, gamma=1.0)  # the warp mixes grey levels linearly
    _, ratio, _ = pencil_ratio(obs.conics.outer, obs.conics.inner)
    assert abs(ratio / SPEC.radius_ratio - 1) < 1e-3
    cal = calibrate_view(obs, SPEC)
    assert abs(cal.intrinsics.focal_px / f - 1) < 0.003
    reading = read_turntable_angle(photo, cal.intrinsics.K, cal.T_cam_table, SPEC)
    T = align_pose_to_marks(cal.T_cam_table, reading.angle_deg)
    assert np.linalg.norm(camera_centre_table(T) - camera_centre_table(T_true)) < 1.0  # mm at 450 mm
    dR = T[:3, :3].T @ T_true[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
