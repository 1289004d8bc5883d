"""Input frames: a folder of images (natural order) or a video; every N-th frame or N spread evenly."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import UserError
from .images import IMAGE_SUFFIXES, list_images, read_image

__all__ = ["Frame", "load_frames", "iter_frames", "select_indices", "VIDEO_SUFFIXES", "frame_name", "frame_paths"]

VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}


def frame_name(file_name: str) -> str:
    """A file name as the text a frame is known by: any valid name unchanged.

    File names are bytes on Linux; bytes that are not UTF-8 reach Python as lone
    surrogates, which strict JSON (``cameras.json``, ``summary.json``) and a
    UTF-8 terminal cannot carry. They become the text ``\\xNN`` here.
    """
    return os.fsencode(file_name).decode("utf-8", "backslashreplace")


def frame_paths(folder: str | Path) -> dict[str, Path]:
    """Frame name -> image file of ``folder`` (:func:`frame_name` of each file name)."""
    return {frame_name(p.name): p for p in list_images(folder)}


@dataclass(frozen=True)
class Frame:
    """One input frame: ``name`` (file name or ``video#index``), BGR pixels or the reason it is unusable."""

    name: str
    bgr: np.ndarray | None
    error: str = ""


def select_indices(n: int, every: int = 1, count: int | None = None) -> list[int]:
    """Which of ``n`` frames to use: every ``every``-th (0, N, 2N, ...), or ``count`` spread evenly.

    ``count`` frames are ``floor(i * n / count)`` for i = 0..count-1: equal steps
    that start at the first frame and stop one step short of the end, so a
    video of one full turn gives equal angles without repeating the start.
    ``count >= n`` takes every frame. Giving both is a ``UserError``.
    """
    if every < 1:
        raise UserError(f"--every must be >= 1, got {every}")
    if count is not None:
        if count < 1:
            raise UserError(f"--frames must be >= 1, got {count}")
        if every != 1:
            raise UserError("give --every or --frames, not both")
        if count >= n:
            return list(range(n))
        return [i * n // count for i in range(count)]
    return list(range(0, n, every))


def _count_video_frames(path: Path) -> int:
    cap = cv2.VideoCapture(str(path))
    n = 0
    try:
        while cap.grab():
            n += 1
    finally:
        cap.release()
    return n


def _read_video(path: Path, n: int, every: int, count: int | None) -> Iterator[Frame]:
    """The selected frames (rotation metadata applied), decoded one at a time as they are reached."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise UserError(f"{path}: cannot open video (unsupported format or corrupt)")
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # phones film portrait as landscape + a rotation: show it upright
    wanted = set(select_indices(n, every, count)) if count is not None else None
    i = 0
    try:
        while cap.grab():  # grab every frame (cheap), convert only those used
            if (i in wanted) if wanted is not None else (i % every == 0):
                ok, img = cap.retrieve()
                if ok and img is not None:
                    yield Frame(name=frame_name(f"{path.stem}_{i:05d}.png"), bgr=img)
            i += 1
    finally:
        cap.release()


def _video_frames(path: Path, every: int, count: int | None = None) -> Iterator[Frame]:
    """Frames of a video, upright, one at a time: every ``every``-th, or ``count`` evenly spread (see
    :func:`select_indices`). Never more than one decoded frame is held here (a phone's 4K video of a
    turn has hundreds). For ``count``, the frames are counted by reading first: containers' frame
    counts can be wrong."""
    select_indices(1, every, count)  # argument errors before any decoding
    n = _count_video_frames(path) if count is not None else 0
    if count is not None and n == 0:
        raise UserError(f"{path}: no frame could be decoded from the video")
    got = 0
    for f in _read_video(path, n, every, count):
        got += 1
        yield f
    if not got:
        raise UserError(f"{path}: no frame could be decoded from the video")


def iter_frames(input_path: str | Path, every: int = 1, count: int | None = None) -> Iterator[Frame]:
    """The frames of ``input_path`` one at a time, each image decoded when it is reached.

    Same frames, order, names and errors as :func:`load_frames` (which see),
    but at most one photo of a folder is held at a time: callers that keep a
    reduced copy (``reconstruct``) never hold every frame at full resolution.
    Video frames too are decoded one at a time. Frames of different sizes raise ``UserError`` when the
    first odd one is reached; no readable frame at all raises it at the end.
    """
    p = Path(input_path)
    select_indices(1, every, count)  # argument errors first
    if not p.exists():
        raise UserError(f"{p}: not found")
    if p.is_file():
        if p.suffix.lower() in VIDEO_SUFFIXES:
            source: Iterator[Frame] = _video_frames(p, every, count)
        elif p.suffix.lower() in IMAGE_SUFFIXES:
            raise UserError(f"{p}: INPUT must be a folder of images or a video, not a single image")
        else:
            raise UserError(f"{p}: not a folder of images nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})")
    else:
        files = list_images(p)
        source = (_read_one(f) for f in (files[i] for i in select_indices(len(files), every, count)))
    first: Frame | None = None
    n = 0
    for f in source:
        n += 1
        if f.bgr is not None:
            if first is None:
                first = f
            elif f.bgr.shape[:2] != first.bgr.shape[:2]:
                h, w = first.bgr.shape[:2]
                raise UserError(f"{p}: images have different sizes: {first.name} is {w}x{h}, "
                                f"{f.name} is {f.bgr.shape[1]}x{f.bgr.shape[0]}; all frames must come from one "
                                f"camera setting")
        yield f
    if first is None:
        raise UserError(f"{p}: none of the {n} images could be read")


def _read_one(path: Path) -> Frame:
    try:
        return Frame(name=frame_name(path.name), bgr=read_image(path))
    except UserError as exc:
        return Frame(name=frame_name(path.name), bgr=None, error=str(exc).split(": ", 1)[-1])


def load_frames(input_path: str | Path, every: int = 1, count: int | None = None) -> list[Frame]:
    """The frames of ``input_path`` (a folder of images or a video); unreadable images come back with ``error`` set.

    Every ``every``-th frame, or ``count`` frames spread evenly (:func:`select_indices`).
    Images come upright (EXIF orientation, :func:`turntable.images.read_image`),
    and so do video frames (the container's rotation metadata).

    Raises ``UserError`` for an empty folder, a missing path, an undecodable
    video, or images of different sizes (naming the first odd one).
    """
    return list(iter_frames(input_path, every, count))
