"""Input frames: a folder of images (natural order) or a video (every N-th frame)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import UserError
from .images import IMAGE_SUFFIXES, list_images, read_image

__all__ = ["Frame", "load_frames", "VIDEO_SUFFIXES"]

VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}


@dataclass(frozen=True)
class Frame:
    """One input frame: ``name`` (file name or ``video#index``), BGR pixels or the reason it is unusable."""

    name: str
    bgr: np.ndarray | None
    error: str = ""


def _video_frames(path: Path, every: int) -> list[Frame]:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise UserError(f"{path}: cannot open video (unsupported format or corrupt)")
    frames, i = [], 0
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if i % every == 0:
                frames.append(Frame(name=f"{path.stem}_{i:05d}.png", bgr=img))
            i += 1
    finally:
        cap.release()
    if not frames:
        raise UserError(f"{path}: no frame could be decoded from the video")
    return frames


def load_frames(input_path: str | Path, every: int = 1) -> list[Frame]:
    """All frames of ``input_path``; unreadable images come back with ``error`` set.

    Raises ``UserError`` for an empty folder, a missing path, an undecodable
    video, or images of different sizes (naming the first odd one).
    """
    p = Path(input_path)
    if every < 1:
        raise UserError(f"--every must be >= 1, got {every}")
    if not p.exists():
        raise UserError(f"{p}: not found")
    if p.is_file():
        if p.suffix.lower() in VIDEO_SUFFIXES:
            frames = _video_frames(p, every)
        elif p.suffix.lower() in IMAGE_SUFFIXES:
            raise UserError(f"{p}: INPUT must be a folder of images or a video, not a single image")
        else:
            raise UserError(f"{p}: not a folder of images nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})")
    else:
        frames = []
        for f in list_images(p)[::every]:
            try:
                frames.append(Frame(name=f.name, bgr=read_image(f)))
            except UserError as exc:
                frames.append(Frame(name=f.name, bgr=None, error=str(exc).split(": ", 1)[-1]))
    good = [f for f in frames if f.bgr is not None]
    if not good:
        raise UserError(f"{p}: none of the {len(frames)} images could be read")
    h, w = good[0].bgr.shape[:2]
    for f in good:
        if f.bgr.shape[:2] != (h, w):
            raise UserError(f"{p}: images have different sizes: {good[0].name} is {w}x{h}, "
                            f"{f.name} is {f.bgr.shape[1]}x{f.bgr.shape[0]}; all frames must come from one camera setting")
    return frames
