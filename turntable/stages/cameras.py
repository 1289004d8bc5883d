"""Stage 2, cameras: the sequence calibration from the rings, ``--cameras``, or the cached one."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from calib.types import RingConics, SequenceCalibration, SequenceDiagnostics

from ..cameras_io import read_cameras, write_cameras
from ..errors import UserError
from ..frames import Frame
from ..progress import Progress, fit_reporter
from ..worksize import WorkSize
from .cache import StageCache, file_digest
from .frames import frame_files
from .options import ReconstructOptions


def known_cameras(opts: ReconstructOptions, progress: Progress, key: str,
                   cache: StageCache) -> tuple[SequenceCalibration | None, dict]:
    """Cameras that need no ring detection: ``--cameras``, or the cached calibration of an earlier run."""
    cam_path = cache.dir / "cameras.json"
    if opts.cameras is not None:
        seq = read_cameras(opts.cameras)
        # cameras.json may name frames with a folder ("images/frame_000.jpg"): match by file name
        seq = replace(seq, frames=tuple(replace(fp, image=Path(fp.image).name) for fp in seq.frames))
        return seq, {}
    if cam_path.is_file() and not opts.overwrite:
        # cameras.json is this stage's result only with the detections saved beside it, which name its bytes
        hit = cache.load("detections", key, DETECTIONS)
        if hit is None or str(hit["cameras_json"]) != file_digest(cam_path):
            return None, {}
        try:
            seq = read_cameras(cam_path)
        except UserError:
            return None, {}
        if seq.diagnostics is not None and seq.diagnostics.stage_key == key:
            progress.note("cameras: reusing cameras.json")
            return seq, conics_from_arrays(hit)
    return None, {}


DETECTIONS = {"names": ("U", ("N",)), "conics": ("f", ("N", 2, 3, 3)), "cameras_json": ("U", ())}


def calibrate(loaded, opts: ReconstructOptions, progress: Progress, key: str,
                   cache: StageCache) -> tuple[SequenceCalibration, dict]:
    """The sequence calibration from the rings found at full resolution, and the ring conics per frame name."""
    from .calibration import calibrate_detected

    intr = None
    if opts.intrinsics is not None:
        from ..intrinsics_io import read_opencv_intrinsics

        intr = read_opencv_intrinsics(opts.intrinsics)
    observations: list = []
    with progress.stage("cameras") as tick:
        try:  # the angle marks are read on the work images (they are sampled in millimetres)
            seq = calibrate_detected(loaded.observations, loaded.failures, loaded.names, loaded.images, opts.spec,
                                     marks_map=loaded.work.S, step_deg=opts.step_deg, intrinsics=intr,
                                     progress=tick, fit_progress=fit_reporter(progress, "cameras: joint fit"),
                                     observations_out=observations)
        except UserError as exc:
            raise UserError(f"{opts.input}: {exc}") from None
    again = [n for n, o, o0 in zip(loaded.names, observations, loaded.observations, strict=True)
             if o is not None and o0 is None]
    if again:
        progress.note(f"cameras: rings of {len(again)} frame(s) ({', '.join(again[:5])}) found by searching "
                      f"where the frames beside them put them (the first search was misled)")
    diagnostics = seq.diagnostics if seq.diagnostics is not None else SequenceDiagnostics()
    for warning in diagnostics.warnings:
        progress.note(f"cameras: WARNING: {warning}")
    seq = replace(seq, diagnostics=replace(diagnostics, stage_key=key))
    found = [(n, o.conics) for n, o in zip(loaded.names, observations, strict=True)
             if o is not None and o.conics is not None]
    names = [n for n, _ in found]
    conics = np.array([[c.outer, c.inner] for _, c in found])
    conics = conics.reshape(-1, 2, 3, 3)
    cam_path = cache.dir / "cameras.json"
    write_cameras(cam_path, seq)
    cache.save("detections", key, names=np.array(names, dtype=str), conics=conics,
               cameras_json=np.array(str(file_digest(cam_path))))
    return seq, conics_from_arrays({"names": np.array(names, dtype=str), "conics": conics})


def conics_from_arrays(d: dict) -> dict[str, RingConics]:
    """Each frame's ring centre lines by frame name, from the detections' saved arrays."""
    if "names" not in d:
        return {}
    return {str(n): RingConics(outer=c[0], inner=c[1]) for n, c in zip(d["names"], d["conics"], strict=True)}


def check_given(seq: SequenceCalibration, good: list[Frame], opts: ReconstructOptions,
                         ws: WorkSize) -> None:
    """``--cameras`` must be for photos of this size and name every readable frame."""
    if opts.cameras is None:
        return
    intr = seq.intrinsics
    if (intr.width, intr.height) != tuple(ws.full):
        raise UserError(f"--cameras {opts.cameras}: the cameras are for {intr.width}x{intr.height} images, "
                        f"the frames are {ws.full[0]}x{ws.full[1]}")
    names = {fp.image for fp in seq.frames}
    missing = [f.name for f in good if f.name not in names]
    if missing:
        raise UserError(f"--cameras {opts.cameras}: no camera for frame(s) {', '.join(missing[:5])}")


def exif_focal(frames: list[Frame], seq: SequenceCalibration, opts: ReconstructOptions,
                progress: Progress) -> dict | None:
    """The photos' EXIF focal length against the calibrated one (None: a video, or no EXIF focal length)."""
    from ..images import exif_focal_report, focal_warning

    if not Path(opts.input).is_dir():
        return None
    intr = seq.intrinsics
    report = exif_focal_report(frame_files(opts, [f.name for f in frames]), intr.width, intr.height, intr.focal_px)
    for line in ((report or {}).get("note"), focal_warning(intr.focal_px, report)):
        if line:
            progress.note(f"cameras: {line}")
    return report
