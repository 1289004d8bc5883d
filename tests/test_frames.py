"""Input frames: natural order, unreadable files, mixed sizes, videos, bad paths."""

import cv2
import numpy as np
import pytest

from turntable.errors import UserError
from turntable.frames import load_frames, select_indices
from turntable.images import natural_key


def _write(path, w=64, h=48, value=128):
    cv2.imwrite(str(path), np.full((h, w, 3), value, np.uint8))


def test_natural_order_and_every(tmp_path):
    for i in (10, 2, 1):
        _write(tmp_path / f"frame_{i}.png")
    assert [f.name for f in load_frames(tmp_path)] == ["frame_1.png", "frame_2.png", "frame_10.png"]
    assert [f.name for f in load_frames(tmp_path, every=2)] == ["frame_1.png", "frame_10.png"]
    assert sorted(["a10", "a9", "A1"], key=natural_key) == ["A1", "a9", "a10"]


def test_corrupt_file_is_reported_not_fatal(tmp_path):
    _write(tmp_path / "a.png")
    (tmp_path / "b.jpg").write_bytes(b"not a jpeg at all")
    frames = load_frames(tmp_path)
    bad = [f for f in frames if f.bgr is None]
    assert [f.name for f in bad] == ["b.jpg"] and "cannot decode" in bad[0].error


def test_mixed_sizes_name_the_odd_file(tmp_path):
    _write(tmp_path / "a.png")
    _write(tmp_path / "b.png", w=32)
    with pytest.raises(UserError, match=r"b\.png is 32x48"):
        load_frames(tmp_path)


@pytest.mark.parametrize("make,reason", [
    (lambda p: p.mkdir(), "no images found"),
    (lambda p: None, "not found"),
    (lambda p: p.write_text("hello"), "not a folder of images nor a video"),
])
def test_bad_inputs(tmp_path, make, reason):
    p = tmp_path / "input"
    make(p)
    with pytest.raises(UserError, match=reason):
        load_frames(p)


def test_all_unreadable(tmp_path):
    (tmp_path / "x.png").write_bytes(b"garbage")
    with pytest.raises(UserError, match="none of the 1 images"):
        load_frames(tmp_path)


def _grey_video(path, n: int, size: tuple[int, int], step: int):
    """An MJPG video of ``n`` flat grey frames (frame i at grey ``step * i``), or skip the test."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    if not vw.isOpened():
        pytest.skip("no video writer in this OpenCV build")
    for i in range(n):
        vw.write(np.full((size[1], size[0], 3), step * i, np.uint8))
    vw.release()
    return path


def test_video_frames_and_undecodable_video(tmp_path):
    path = _grey_video(tmp_path / "clip.avi", 6, (64, 48), 40)
    frames = load_frames(path, every=2)
    assert len(frames) == 3 and frames[0].bgr.shape == (48, 64, 3)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00" * 100)
    with pytest.raises(UserError, match="broken.mp4"):
        load_frames(broken)


def _write_mp4(path, frames_bgr, fps=10):
    h, w = frames_bgr[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not vw.isOpened():
        pytest.skip("no mp4v writer in this OpenCV build")
    for f in frames_bgr:
        vw.write(f)
    vw.release()


def _set_mp4_rotation(path, degrees_cw):
    """Write a display rotation into the MP4 track header, as phones do (ffmpeg's ``rotate=`` metadata).

    The tkhd matrix (a b u / c d v / x y w, 16.16 fixed point) of a clockwise
    display rotation by 90° is (0 1 0 / -1 0 0 / 0 0 1).
    """
    import struct

    c = {0: 1, 90: 0, 180: -1, 270: 0}[degrees_cw]
    s = {0: 0, 90: 1, 180: 0, 270: -1}[degrees_cw]
    data = bytearray(path.read_bytes())
    k = data.find(b"tkhd")
    assert k > 0
    version = data[k + 4]
    off = k + 8 + (20 if version == 0 else 32) + 8 + 8  # times, track id, duration; reserved; layer..volume
    assert struct.unpack(">9i", data[off:off + 36])[8] == 1 << 30  # the identity matrix's w: right place
    data[off:off + 36] = struct.pack(">9i", c << 16, s << 16, 0, -s << 16, c << 16, 0, 0, 0, 1 << 30)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("degrees_cw", [90, 270, 180])
def test_phone_video_rotation_metadata_applied(tmp_path, degrees_cw):
    rng = np.random.default_rng(degrees_cw)
    blocks = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    stored = np.kron(blocks, np.ones((8, 8, 1), np.uint8))  # 48 x 64 landscape, as the sensor recorded it
    path = tmp_path / "phone.mp4"
    _write_mp4(path, [stored] * 4)
    _set_mp4_rotation(path, degrees_cw)
    frames = load_frames(path)
    shown = np.rot90(stored, -degrees_cw // 90)  # np.rot90 turns counter-clockwise
    assert len(frames) == 4
    for f in frames:
        assert f.bgr.shape == shown.shape
        assert np.abs(f.bgr.astype(float) - shown).mean() < 12  # mp4v at a tiny size
        assert np.abs(f.bgr.astype(float) - np.rot90(shown, 2)).mean() > 40  # a wrong turn would show


def test_select_indices_every_and_evenly():
    assert select_indices(10, every=3) == [0, 3, 6, 9]
    assert select_indices(360, count=36) == list(range(0, 360, 10))  # one turn: equal steps, no repeat
    assert select_indices(10, count=4) == [0, 2, 5, 7]
    assert select_indices(5, count=9) == [0, 1, 2, 3, 4]
    with pytest.raises(UserError, match="not both"):
        select_indices(10, every=2, count=3)
    with pytest.raises(UserError, match="--frames must be >= 1"):
        select_indices(10, count=0)


def test_video_frames_spread_evenly(tmp_path):
    path = _grey_video(tmp_path / "turn.avi", 20, (32, 24), 10)
    frames = load_frames(path, count=5)
    assert [f.name for f in frames] == [f"turn_{i:05d}.png" for i in (0, 4, 8, 12, 16)]
    assert [round(float(f.bgr.mean()) / 10) for f in frames] == [0, 4, 8, 12, 16]  # the frames named
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(6):
        _write(folder / f"f{i}.png")
    assert [f.name for f in load_frames(folder, count=3)] == ["f0.png", "f2.png", "f4.png"]


@pytest.mark.parametrize("count", [None, 3])
def test_truncated_video_names_the_file(tmp_path, count):
    path = tmp_path / "cut.mp4"
    _write_mp4(path, [np.full((48, 64, 3), 20 * i, np.uint8) for i in range(8)])
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])  # the index (moov) is written last: it is gone
    with pytest.raises(UserError, match=r"cut\.mp4: (cannot open video|no frame could be decoded)"):
        load_frames(path, count=count)
