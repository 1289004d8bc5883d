"""Reading input images and listing image folders, with errors that name the file."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from .errors import UserError

__all__ = ["IMAGE_SUFFIXES", "read_image", "list_images", "natural_key"]

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}


def natural_key(name: str) -> list:
    """Sort key so that ``frame_2`` comes before ``frame_10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def read_image(path: str | Path) -> np.ndarray:
    """BGR uint8 image (H, W, 3); ``UserError`` naming the file if unreadable."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    if path.is_dir():
        raise UserError(f"{path}: is a folder, not an image")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise UserError(f"{path}: cannot decode image (not an image file, or corrupt)")
    return img


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` in natural order; ``UserError`` if none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise UserError(f"{folder}: no images found (looked for {', '.join(sorted(IMAGE_SUFFIXES))})")
    return files
