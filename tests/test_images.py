"""Reading what phones and cameras produce: EXIF orientation, HEIC, 16 bit, EXIF focal length.

Every test writes a small synthetic image with known upright content and
checks that :func:`turntable.images.read_image` gives it back upright, in
BGR uint8, within the codec's error.
"""

import io
import math

import cv2
import numpy as np
import pytest
from PIL import Image

from turntable.errors import UserError
from turntable.images import exif_focal_35mm, exif_focal_px, focal_px_from_35mm, list_images, read_image

# mean |difference|, 8-bit levels, that lossy codecs leave on the blocky test image (chroma subsampling at
# block edges); a wrong orientation of the same image is off by ~80
JPEG_TOL = 12.0
HEIC_TOL = 12.0
WRONG_MIN = 40.0

# Stored pixels for EXIF orientation o are inverse_o(upright); applying o gives upright back.
# (EXIF 6: "rotate 90 CW to view" -> stored = upright rotated 90 CCW.)
_STORED = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: np.rot90(a, 2), 4: lambda a: a[::-1],
           5: lambda a: np.rot90(a, 1)[::-1], 6: lambda a: np.rot90(a, 1), 7: lambda a: np.rot90(a, -1)[::-1],
           8: lambda a: np.rot90(a, -1)}


def _upright(rng, h=72, w=48):
    """A portrait BGR test image with no symmetry: coloured blocks (8x8, JPEG-friendly) and a top band."""
    blocks = rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    img = np.kron(blocks, np.ones((8, 8, 1), np.uint8))
    img[:8] = (0, 0, 255)  # red band on top: a wrong rotation cannot match
    return np.ascontiguousarray(img)


def _exif(orientation=None, f35=None):
    ex = Image.Exif()
    if orientation is not None:
        ex[0x0112] = orientation
    if f35 is not None:
        ex.get_ifd(0x8769)[0xA405] = f35
    return ex


def _write_pil(path, bgr, fmt, exif=None, **kw):
    Image.fromarray(np.ascontiguousarray(bgr[..., ::-1])).save(path, fmt, exif=exif or Image.Exif(), **kw)


def _mean_err(a, b):
    assert a.shape == b.shape, f"shape {a.shape} != {b.shape}"
    return float(np.abs(a.astype(float) - b.astype(float)).mean())


@pytest.mark.parametrize("orientation", [1, 2, 3, 4, 5, 6, 7, 8])
@pytest.mark.parametrize("fmt,suffix,tol", [("JPEG", ".jpg", JPEG_TOL), ("PNG", ".png", 0.0),
                                            ("TIFF", ".tif", 0.0), ("WEBP", ".webp", JPEG_TOL)])
def test_exif_orientation_gives_the_upright_image(tmp_path, orientation, fmt, suffix, tol):
    rng = np.random.default_rng(orientation)
    up = _upright(rng)
    path = tmp_path / f"photo{suffix}"
    kw = {"quality": 95} if fmt in ("JPEG", "WEBP") else {}
    _write_pil(path, np.ascontiguousarray(_STORED[orientation](up)), fmt, _exif(orientation), **kw)
    img = read_image(path)
    assert img.dtype == np.uint8 and img.shape == up.shape  # portrait, as seen
    assert _mean_err(img, up) <= tol + 1e-9


def test_portrait_jpeg_orientation_6_and_8_differ_from_the_stored_pixels(tmp_path):
    """The check above can fail: without orientation, the stored pixels are landscape."""
    rng = np.random.default_rng(3)
    up = _upright(rng)
    for o in (6, 8):
        path = tmp_path / f"p{o}.jpg"
        _write_pil(path, np.ascontiguousarray(_STORED[o](up)), "JPEG", _exif(o), quality=95)
        stored = cv2.imdecode(np.fromfile(str(path), np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        assert stored.shape == (up.shape[1], up.shape[0], 3)
        img = read_image(path)
        assert _mean_err(img, up) <= JPEG_TOL
        assert _mean_err(img, np.rot90(up, 2)) >= WRONG_MIN  # upside down would be seen


def _write_heic(path, bgr, exif=None, quality=92):
    import pillow_heif

    rgb = np.ascontiguousarray(bgr[..., ::-1])
    mode = "RGB;16" if rgb.dtype == np.uint16 else "RGB"
    pillow_heif.from_bytes(mode, (rgb.shape[1], rgb.shape[0]), rgb.tobytes()).save(  # ultrafast: 7x quicker
        path, quality=quality, exif=exif.tobytes() if exif is not None else None, enc_params={"preset": "ultrafast"})


@pytest.mark.parametrize("orientation", [1, 6, 8, 3])
def test_heic_round_trip_upright(tmp_path, orientation):
    """pillow-heif stores the EXIF orientation as HEIF irot/imir; the stored pixels are not upright."""
    rng = np.random.default_rng(10 + orientation)
    up = _upright(rng, 80, 64)
    path = tmp_path / "photo.HEIC"
    _write_heic(path, np.ascontiguousarray(_STORED[orientation](up)), _exif(orientation))
    img = read_image(path)
    assert img.dtype == np.uint8
    assert _mean_err(img, up) <= HEIC_TOL


def test_heic_ten_bit_is_scaled_not_truncated(tmp_path):
    ramp = np.linspace(0, 65535, 64).round().astype(np.uint16)
    img16 = np.ascontiguousarray(np.broadcast_to(ramp[None, :, None], (32, 64, 3)))
    path = tmp_path / "ramp.heif"
    _write_heic(path, img16, quality=-1)  # lossless-ish 10 bit
    got = read_image(path)
    want = np.round(img16 / 257.0)
    assert got.dtype == np.uint8 and np.abs(got.astype(float) - want).max() <= 2  # codec + 10-bit step


@pytest.mark.parametrize("suffix", [".png", ".tif"])
@pytest.mark.parametrize("channels", [1, 3])
def test_sixteen_bit_scaled_by_257_with_rounding(tmp_path, suffix, channels):
    rng = np.random.default_rng(5)
    img16 = rng.integers(0, 65536, (40, 56, channels), dtype=np.uint16)
    img16.reshape(-1)[:6] = [0, 1, 128, 129, 65406, 65535]  # the ends and both sides of a rounding step
    path = tmp_path / f"deep{suffix}"
    assert cv2.imwrite(str(path), img16 if channels == 3 else img16[..., 0])
    got = read_image(path)
    want = np.round(img16.astype(np.float64) / 257.0).astype(np.uint8)  # round(v / 257)
    if channels == 1:
        want = np.repeat(want, 3, axis=2)
    assert got.dtype == np.uint8 and got.shape == (40, 56, 3)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got.reshape(-1, 3)[:6, 0] if channels == 1 else got.reshape(-1)[:6],
                                  [0, 0, 0, 1, 254, 255])


def test_sixteen_bit_png_with_orientation(tmp_path):
    rng = np.random.default_rng(7)
    up8 = _upright(rng)
    up16 = up8.astype(np.uint16) * 257
    path = tmp_path / "deep.png"
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(_STORED[6](up16)))
    # insert an eXIf chunk with orientation 6 after IHDR (33 bytes: signature 8 + IHDR 25)
    import zlib

    payload = _exif(6).tobytes()[6:]  # eXIf holds the TIFF structure without the "Exif\0\0" prefix Pillow adds
    chunk = len(payload).to_bytes(4, "big") + b"eXIf" + payload + zlib.crc32(b"eXIf" + payload).to_bytes(4, "big")
    path.write_bytes(buf.tobytes()[:33] + chunk + buf.tobytes()[33:])
    np.testing.assert_array_equal(read_image(path), up8)


def test_float_tiff_refused_naming_the_file(tmp_path):
    path = tmp_path / "hdr.tif"
    assert cv2.imwrite(str(path), np.full((8, 8, 3), 0.5, np.float32))
    with pytest.raises(UserError, match=r"hdr\.tif: float32 pixels are not supported"):
        read_image(path)


@pytest.mark.parametrize("name,content,reason", [
    ("truncated.heic", None, "cannot decode HEIC/HEIF image"),
    ("empty.heic", b"", "cannot decode image"),
    ("notheic.heic", b"\xff\xd8 this is not an image", "content is neither HEIC/HEIF nor"),
    ("text.png", b"hello", "cannot decode image"),
])
def test_bad_files_give_user_error_naming_the_file(tmp_path, name, content, reason):
    path = tmp_path / name
    if content is None:  # a real HEIC cut in half
        full = tmp_path / "full.heic"
        _write_heic(full, _upright(np.random.default_rng(0)))
        data = full.read_bytes()
        content = data[:len(data) // 2]
    path.write_bytes(content)
    with pytest.raises(UserError, match=rf"{name}: .*{reason}"):
        read_image(path)


def test_heic_listed_in_folders(tmp_path):
    for n in ("b.heic", "a.HEIF", "c.txt"):
        (tmp_path / n).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == ["a.HEIF", "b.heic"]


# --------------------------------------------------------------------------- EXIF focal length
def test_focal_px_from_35mm_uses_the_diagonal():
    # 26 mm equivalent on a 4032 x 3024 phone image: 26 / 43.267 * 5040 = 3028.6 px
    assert focal_px_from_35mm(26, 4032, 3024) == pytest.approx(26 / math.hypot(36, 24) * 5040, rel=1e-12)
    assert focal_px_from_35mm(26, 4032, 3024) == pytest.approx(3028.6, abs=0.1)
    assert focal_px_from_35mm(26, 3024, 4032) == focal_px_from_35mm(26, 4032, 3024)  # portrait: same
    # a 36 x 24 mm image 3600 x 2400 px (100 px/mm): a 50 mm lens is 5000 px
    assert focal_px_from_35mm(50, 3600, 2400) == pytest.approx(5000.0, rel=1e-12)
    with pytest.raises(ValueError):
        focal_px_from_35mm(0, 10, 10)


@pytest.mark.parametrize("fmt,suffix", [("JPEG", ".jpg"), ("HEIC", ".heic")])
def test_exif_focal_read_from_jpeg_and_heic(tmp_path, fmt, suffix):
    up = _upright(np.random.default_rng(1))
    path = tmp_path / f"f{suffix}"
    ex = _exif(6, f35=26)
    if fmt == "HEIC":
        _write_heic(path, np.ascontiguousarray(_STORED[6](up)), ex)
    else:
        _write_pil(path, np.ascontiguousarray(_STORED[6](up)), "JPEG", ex, quality=90)
    assert exif_focal_35mm(path) == 26
    h, w = read_image(path).shape[:2]
    assert exif_focal_px(path, w, h) == pytest.approx(26 / 43.2666 * math.hypot(48, 72), rel=1e-4)


def test_no_exif_focal_is_none(tmp_path):
    path = tmp_path / "plain.png"
    cv2.imwrite(str(path), np.zeros((8, 8, 3), np.uint8))
    assert exif_focal_35mm(path) is None and exif_focal_px(path, 8, 8) is None
    (tmp_path / "junk.jpg").write_bytes(b"junk")
    assert exif_focal_35mm(tmp_path / "junk.jpg") is None


# --------------------------------------------------------------------------- through the CLI
F_TRUE_PX = 950.0
SIZE_PORTRAIT = (600, 800)  # W, H of the upright photos


@pytest.fixture(scope="module")
def upright_photos():
    """Five rendered portrait photos of the target (BGR, upright), a turning table, and the true f."""
    from synthetic_images import render_target_photo

    from calib.camera import look_at, make_T
    from calib.target import TargetSpec

    spec = TargetSpec(r_outer_mm=80.0, r_inner_mm=50.0, stroke_mm=3.0)
    rng = np.random.default_rng(8)
    (w, h), f = SIZE_PORTRAIT, F_TRUE_PX
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    el = np.radians(35.0)
    eye = 420.0 * np.array([np.cos(el), np.sin(el), 0.0])
    T_cam_world = look_at(eye, np.zeros(3))
    photos = []
    for th in np.radians([0.0, 47.0, 95.0, 141.0, 190.0]):
        c, s = np.cos(th), np.sin(th)
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        photos.append(render_target_photo(spec, K, T_cam_world @ make_T(R, np.zeros(3)), (w, h), rng=rng).image)
    return photos


def _calibrate_cli(folder, out, capsys, *extra):
    from turntable.cameras_io import read_cameras
    from turntable.cli import main

    rc = main(["calibrate-sequence", str(folder), "--r-outer", "80", "--r-inner", "50", "--out", str(out), *extra])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return read_cameras(out), cap.out


def test_portrait_jpeg_and_heic_calibrate_like_the_upright_png(tmp_path, upright_photos, capsys):
    """The issue's bar on a small scale: orientation 6/8 JPEG and HEIC give the PNG's f; EXIF f is reported."""
    diag = math.hypot(*SIZE_PORTRAIT)
    f35 = round(F_TRUE_PX / diag * 43.2666)  # what a phone would write (an integer, mm)
    dirs = {k: tmp_path / k for k in ("png", "jpeg6", "jpeg8", "heic6")}
    for d in dirs.values():
        d.mkdir()
    for k, up in enumerate(upright_photos):
        cv2.imwrite(str(dirs["png"] / f"frame_{k}.png"), up)
        for o in (6, 8):
            _write_pil(dirs[f"jpeg{o}"] / f"IMG_{k}.JPG", np.ascontiguousarray(_STORED[o](up)), "JPEG",
                       _exif(o, f35=f35), quality=95)
        _write_heic(dirs["heic6"] / f"IMG_{k}.HEIC", np.ascontiguousarray(_STORED[6](up)), _exif(6, f35=f35),
                    quality=95)
    f = {}
    for name, d in dirs.items():
        seq, out = _calibrate_cli(d, tmp_path / f"{name}.json", capsys)
        assert (seq.intrinsics.width, seq.intrinsics.height) == SIZE_PORTRAIT
        f[name] = seq.intrinsics.focal_px
        if name != "png":
            assert f"EXIF: {f35} mm equivalent" in out and "disagree" not in out
            exif = seq.diagnostics.exif_focal
            assert exif["focal_35mm"] == f35 and not exif["disagrees"]
        else:
            assert "EXIF" not in out and seq.diagnostics.exif_focal is None
    assert abs(f["png"] / F_TRUE_PX - 1) < 0.005
    for name in ("jpeg6", "jpeg8", "heic6"):
        assert abs(f[name] / f["png"] - 1) < 0.0005, (name, f)  # 0.05 %: the bar


def test_exif_focal_disagreement_is_reported(tmp_path, upright_photos, capsys):
    d = tmp_path / "wrong"
    d.mkdir()
    f35_wrong = 26  # a phone's main camera; these photos were taken at ~41 mm equivalent
    for k, up in enumerate(upright_photos):
        _write_pil(d / f"IMG_{k}.jpg", np.ascontiguousarray(_STORED[6](up)), "JPEG", _exif(6, f35=f35_wrong),
                   quality=95)
    seq, out = _calibrate_cli(d, tmp_path / "c.json", capsys)
    f_exif = focal_px_from_35mm(f35_wrong, *SIZE_PORTRAIT)
    pct = 100 * (seq.intrinsics.focal_px / f_exif - 1)
    assert pct > 50
    assert f"disagree by {pct:+.1f} % (more than 5 %)" in out
    assert seq.diagnostics.exif_focal["disagrees"]


def test_calibrate_sequence_takes_a_video(tmp_path, upright_photos, capsys):
    path = tmp_path / "turn.avi"
    w, h = SIZE_PORTRAIT
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 5, (w, h))
    if not vw.isOpened():
        pytest.skip("no video writer in this OpenCV build")
    for up in upright_photos:  # each photo twice: --frames 5 takes every other frame
        vw.write(up)
        vw.write(up)
    vw.release()
    seq, out = _calibrate_cli(path, tmp_path / "c.json", capsys, "--frames", "5")
    assert [fr.image for fr in seq.frames] == [f"turn_{i:05d}.png" for i in (0, 2, 4, 6, 8)]
    assert all(fr.ok for fr in seq.frames) and abs(seq.intrinsics.focal_px / F_TRUE_PX - 1) < 0.01


def test_reconstruct_summary_carries_the_exif_check(tmp_path):
    """The orchestrator's hook: a folder of photos with EXIF focal -> summary entry and a progress note."""
    from types import SimpleNamespace

    from turntable.frames import Frame
    from turntable.reconstruct import ReconstructOptions
    from turntable.stages.cameras import exif_focal

    up = _upright(np.random.default_rng(2))
    for k in range(2):
        _write_pil(tmp_path / f"IMG_{k}.jpg", up, "JPEG", _exif(1, f35=26), quality=90)
    frames = [Frame(name=f"IMG_{k}.jpg", bgr=up) for k in range(2)]
    f_exif = focal_px_from_35mm(26, 48, 72)
    notes = []
    progress = SimpleNamespace(note=notes.append)
    opts = ReconstructOptions(input=tmp_path, out=tmp_path / "out", spec=None)
    for f_cal, warned in ((f_exif * 1.02, False), (f_exif * 1.08, True)):
        notes.clear()
        seq = SimpleNamespace(intrinsics=SimpleNamespace(width=48, height=72, focal_px=f_cal))
        rep = exif_focal(frames, seq, opts, progress)
        assert rep["photos"] == 2 and rep["focal_px"] == pytest.approx(f_exif, abs=0.01)
        assert rep["disagrees"] is warned and bool(notes) is warned
        if warned:
            assert "disagree by +8.0 %" in notes[0]
    video_opts = ReconstructOptions(input=tmp_path / "clip.mp4", out=tmp_path / "out", spec=None)
    assert exif_focal(frames, seq, video_opts, progress) is None


def test_calibrate_single_photo_reports_exif_focal(tmp_path, upright_photos, capsys):
    import json

    from turntable.cli import main

    for name, f35 in (("right.jpg", round(F_TRUE_PX / math.hypot(*SIZE_PORTRAIT) * 43.2666)), ("wrong.jpg", 26)):
        _write_pil(tmp_path / name, np.ascontiguousarray(_STORED[8](upright_photos[0])), "JPEG", _exif(8, f35=f35),
                   quality=95)
    rc = main(["calibrate", str(tmp_path / "right.jpg"), str(tmp_path / "wrong.jpg"), "--r-outer", "80",
               "--r-inner", "50", "--json"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    right, wrong = json.loads(cap.out)
    assert right["exif_focal_px"] == pytest.approx(F_TRUE_PX, rel=0.01)
    assert wrong["exif_focal_px"] == pytest.approx(focal_px_from_35mm(26, *SIZE_PORTRAIT), abs=0.01)
    assert "wrong.jpg: warning: calibrated focal length" in cap.err and "right.jpg" not in cap.err


def test_reconstruct_prints_the_exif_check():
    from types import SimpleNamespace

    from turntable.cli.reconstruct import print_summary
    from turntable.stages.summary import ReconstructSummary

    summary = {"frames_used": 3, "focal_px": 1100.0, "mode": "turntable",
               "exif_focal": {"focal_35mm": 26.0, "focal_px": 1000.0, "photos": 3, "calibrated_vs_exif_pct": 10.0,
                              "disagrees": True},
               "mesh": {"vertices": 8, "faces": 12, "watertight": True, "volume_cm3": 1.0, "extent_mm": [1, 1, 1]},
               "fusion": "off", "time_s": {}, "files": {}}
    out = io.StringIO()
    print_summary(SimpleNamespace(summary=ReconstructSummary.from_json(summary, out="OUT")), out)
    text = out.getvalue()
    assert "EXIF focal      26 mm equivalent = 1000.0 px (calibrated +10.0 %)" in text
    assert "warning         calibrated focal length 1100.0 px and the EXIF focal length" in text


def test_a_huge_image_is_refused_from_its_header(tmp_path):
    """A 20000 x 20000 PNG (400 MP) is refused by its header, naming the file and the size, before
    decoding 1.2 GB of pixels; the file itself is small (one colour compresses well)."""
    import tracemalloc

    from PIL import Image

    from turntable.images import MAX_PIXELS

    p = tmp_path / "huge.png"
    Image.new("L", (20000, 20000)).save(p)  # grey, 400 MP: a few hundred kB on disk
    q = tmp_path / "big.png"
    Image.new("L", (13000, 12000)).save(q)  # 156 MP: under Pillow's own limit, over ours
    with pytest.raises(UserError, match=r"big.png: 13000x12000 pixels \(156 MP\) is more than turntable reads"):
        read_image(q)
    tracemalloc.start()
    with pytest.raises(UserError, match=r"huge.png: 400 MP is more than turntable reads \(150 MP\)"):
        read_image(p)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 100e6, peak  # the header only
    assert MAX_PIXELS > 8064 * 6048  # 48 MP phone photos still pass


@pytest.mark.parametrize("orientation", [1, 6, 3])
def test_read_alpha_gives_a_cutouts_transparency_upright(tmp_path, orientation):
    from turntable.images import read_alpha

    rng = np.random.default_rng(20 + orientation)
    up = _upright(rng)
    alpha = np.zeros(up.shape[:2], np.uint8)
    alpha[10:40, 5:30] = 255  # no symmetry: a wrong rotation cannot match
    rgba = np.dstack([up[..., ::-1], alpha])
    path = tmp_path / "cut.png"
    Image.fromarray(np.ascontiguousarray(_STORED[orientation](rgba))).save(path, "PNG", exif=_exif(orientation))
    got = read_alpha(path)
    assert got is not None and got.shape == alpha.shape
    np.testing.assert_array_equal(got, alpha)
    assert read_image(path).shape == up.shape  # the colours upright the same way


def test_read_alpha_is_none_without_transparency(tmp_path):
    from turntable.images import read_alpha

    m = np.zeros((32, 48), np.uint8)
    m[8:20, 10:30] = 255
    Image.fromarray(m).save(tmp_path / "grey.png")
    Image.fromarray(np.dstack([m, m, m, np.full_like(m, 255)])).save(tmp_path / "opaque.png")  # alpha, all opaque
    cv2.imwrite(str(tmp_path / "mask.jpg"), m)
    Image.fromarray(np.dstack([m, m, m, np.zeros_like(m)])).save(tmp_path / "clear.png")  # all transparent
    for name in ("grey.png", "opaque.png", "mask.jpg", "clear.png"):
        assert read_alpha(tmp_path / name) is None, name
    p = Image.fromarray(m).convert("P")  # a palette image whose black is transparent: a cut-out too
    p.save(tmp_path / "pal.png", transparency=0)
    got = read_alpha(tmp_path / "pal.png")
    assert got is not None and np.array_equal(got > 127, m > 127)
