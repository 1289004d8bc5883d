"""Reading camera intrinsics calibrated elsewhere (OpenCV YAML/XML, or JSON).

Accepted keys (the first present wins):

* camera matrix: ``camera_matrix``, ``K``, ``cameraMatrix``, ``intrinsic_matrix``
* distortion: ``distortion_coefficients``, ``dist_coeffs``, ``D``, ``distCoeffs``, ``dist``
  (optional; 4, 5 or 8 values)
* size: ``image_width`` + ``image_height``, or ``width`` + ``height``, or
  ``image_size``/``size`` as ``[W, H]``

YAML/XML as ``cv2.FileStorage`` writes them (``!!opencv-matrix`` nodes); JSON
with the same keys and plain (nested) lists. OpenCV's pixel convention (pixel
centres at integer coordinates) is ours, so ``K`` is used as written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib.types import Intrinsics

from .errors import UserError

__all__ = ["read_opencv_intrinsics", "write_opencv_intrinsics"]

_K_KEYS = ("camera_matrix", "K", "cameraMatrix", "intrinsic_matrix")
_D_KEYS = ("distortion_coefficients", "dist_coeffs", "D", "distCoeffs", "dist")


def _from_filestorage(path: Path) -> dict:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV raises SystemError on some parse errors
        msg = str(getattr(exc, "__cause__", None) or exc).strip().splitlines()
        raise UserError(f"{path}: not a readable OpenCV YAML/XML file ({msg[-1] if msg else 'parse error'})") from None
    if not fs.isOpened():
        raise UserError(f"{path}: cannot open as an OpenCV YAML/XML file")
    try:
        out = {}
        for key in _K_KEYS + _D_KEYS + ("image_width", "image_height", "width", "height", "image_size", "size"):
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                continue
            if node.isMap():
                try:
                    m = node.mat()
                except cv2.error:
                    m = None
                if m is None:  # ROS camera_info style: {rows, cols, data: [...]}
                    data = node.getNode("data")
                    m = [data.at(i).real() for i in range(data.size())] if data.isSeq() else None
                out[key] = m
            elif node.isSeq():
                out[key] = [node.at(i).real() for i in range(node.size())]
            elif node.isReal() or node.isInt():
                out[key] = node.real()
            else:
                out[key] = node.mat()
        return out
    finally:
        fs.release()


def _from_json(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(d, dict):
        raise UserError(f"{path}: expected a JSON object with the camera matrix")
    return d


def _first(d: dict, keys) -> tuple[str | None, object]:
    for k in keys:
        if k in d and d[k] is not None:
            return k, d[k]
    return None, None


def _size(d: dict, path: Path) -> tuple[int, int]:
    for wk, hk in (("image_width", "image_height"), ("width", "height")):
        if wk in d and hk in d:
            w, h = d[wk], d[hk]
            break
    else:
        _, s = _first(d, ("image_size", "size"))
        if s is None:
            raise UserError(f"{path}: image size missing (image_width/image_height)")
        s = np.asarray(s, dtype=float).ravel()
        if s.size != 2:
            raise UserError(f"{path}: image_size must be [width, height], got {s.tolist()}")
        w, h = s
    try:
        w, h = float(w), float(h)
    except (TypeError, ValueError):
        raise UserError(f"{path}: image width/height must be numbers, got {w!r}, {h!r}") from None
    if not (w >= 1 and h >= 1 and w == int(w) and h == int(h)):
        raise UserError(f"{path}: image size must be positive integers, got {w} x {h}")
    return int(w), int(h)


def read_opencv_intrinsics(path: str | Path) -> Intrinsics:
    """Camera matrix, distortion and image size from an OpenCV calibration file.

    Parameters
    ----------
    path : str or Path
        ``.yml``/``.yaml``/``.xml`` (``cv2.FileStorage``) or ``.json``.

    Returns
    -------
    Intrinsics
        ``K`` (3, 3) pixels, ``dist`` (0, 4, 5 or 8 OpenCV coefficients).

    Raises
    ------
    UserError
        Missing file, unreadable format, missing or malformed keys; the message
        names the file and the reason.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: file not found")
    d = _from_json(path) if path.suffix.lower() == ".json" else _from_filestorage(path)
    kk, K = _first(d, _K_KEYS)
    if K is None:
        raise UserError(f"{path}: no camera matrix (looked for {', '.join(_K_KEYS)})")
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: {kk} is not a numeric matrix") from None
    if K.size == 9:
        K = K.reshape(3, 3)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise UserError(f"{path}: {kk} must be a finite 3x3 matrix, got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise UserError(f"{path}: {kk} is not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    dk, D = _first(d, _D_KEYS)
    try:
        D = np.zeros(0) if D is None else np.asarray(D, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise UserError(f"{path}: {dk} is not a list of numbers") from None
    if D.size not in (0, 4, 5, 8) or not np.all(np.isfinite(D)):
        raise UserError(f"{path}: {dk} must hold 4, 5 or 8 finite coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), "
                        f"got {D.size}")
    w, h = _size(d, path)
    return Intrinsics(K=K, width=w, height=h, dist=D)


def write_opencv_intrinsics(path: str | Path, intr: Intrinsics) -> None:
    """Write ``intr`` as ``cv2.FileStorage`` YAML/XML (by suffix) or JSON, readable by the function above."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        from .cameras_io import atomic_write_text

        d = {"camera_matrix": intr.K.tolist(), "distortion_coefficients": intr.dist.tolist(),
             "image_width": int(intr.width), "image_height": int(intr.height)}
        atomic_write_text(path, json.dumps(d, indent=1) + "\n")
        return
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(intr.width))
        fs.write("image_height", int(intr.height))
        fs.write("camera_matrix", intr.K)
        fs.write("distortion_coefficients", intr.dist.reshape(1, -1) if intr.dist.size else np.zeros((1, 5)))
    finally:
        fs.release()
