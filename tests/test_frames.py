"""Input frames: natural order, unreadable files, mixed sizes, videos, bad paths."""

import cv2
import numpy as np
import pytest

from turntable.errors import UserError
from turntable.frames import load_frames
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


def test_video_frames_and_undecodable_video(tmp_path):
    path = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    if not vw.isOpened():
        pytest.skip("no video writer in this OpenCV build")
    for i in range(6):
        vw.write(np.full((48, 64, 3), 40 * i, np.uint8))
    vw.release()
    frames = load_frames(path, every=2)
    assert len(frames) == 3 and frames[0].bgr.shape == (48, 64, 3)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00" * 100)
    with pytest.raises(UserError, match="broken.mp4"):
        load_frames(broken)
