"""Reading OpenCV intrinsics files: cv2.FileStorage YAML/XML and JSON round trips, bad files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calib.types import Intrinsics
from turntable.errors import UserError
from turntable.intrinsics_io import read_opencv_intrinsics, write_opencv_intrinsics

K = np.array([[1500.0, 0.0, 650.25], [0.0, 1510.0, 470.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.1, 0.02, 0.001, -0.0005, 0.003])


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json"])
def test_round_trip(tmp_path, suffix):
    intr = Intrinsics(K=K, width=1280, height=960, dist=DIST)
    path = tmp_path / f"cam{suffix}"
    write_opencv_intrinsics(path, intr)
    got = read_opencv_intrinsics(path)
    assert np.array_equal(got.K, K) and np.array_equal(got.dist, DIST)
    assert (got.width, got.height) == (1280, 960)


def test_reads_what_cv2_filestorage_writes_with_other_key_names(tmp_path):
    path = tmp_path / "calib.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("K", K)
    fs.write("D", DIST[:4].reshape(-1, 1))
    fs.write("width", 640)
    fs.write("height", 480)
    fs.release()
    got = read_opencv_intrinsics(path)
    assert np.array_equal(got.K, K) and np.array_equal(got.dist, DIST[:4]) and got.width == 640


def test_ros_camera_info_yaml(tmp_path):
    path = tmp_path / "ros.yaml"
    path.write_text("%YAML:1.0\nimage_width: 640\nimage_height: 480\n"
                    "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n"
                    "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.2, 0.05, 0, 0, 0]\n")
    got = read_opencv_intrinsics(path)
    assert got.K[0, 0] == 500 and got.dist[0] == -0.2


def test_json_without_distortion(tmp_path):
    path = tmp_path / "k.json"
    path.write_text(json.dumps({"K": K.tolist(), "image_size": [1280, 960]}))
    got = read_opencv_intrinsics(path)
    assert got.dist.size == 0 and not got.has_distortion and got.height == 960


@pytest.mark.parametrize("content, reason", [
    ({"image_width": 640, "image_height": 480}, "no camera matrix"),
    ({"K": [[1, 2], [3, 4]], "image_width": 640, "image_height": 480}, "3x3"),
    ({"K": [[500, 0, 1], [0, 500, 1], [1, 0, 1]], "width": 640, "height": 480}, "not a camera matrix"),
    ({"K": K.tolist(), "D": [0.1, 0.2, 0.3], "width": 640, "height": 480}, "4, 5 or 8"),
    ({"K": K.tolist()}, "image size missing"),
    ({"K": K.tolist(), "width": -3, "height": 480}, "positive integers"),
    ({"K": "abc", "width": 640, "height": 480}, "numeric"),
])
def test_bad_json_names_file_and_reason(tmp_path, content, reason):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    with pytest.raises(UserError, match=reason) as exc:
        read_opencv_intrinsics(path)
    assert str(path) in str(exc.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(UserError, match="file not found"):
        read_opencv_intrinsics(tmp_path / "missing.yml")
    broken = tmp_path / "broken.yml"
    broken.write_text("camera_matrix: [1, 2\n")
    with pytest.raises(UserError, match="broken.yml"):
        read_opencv_intrinsics(broken)
    notjson = tmp_path / "x.json"
    notjson.write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        read_opencv_intrinsics(notjson)
