"""What a reconstruction is asked to do: :class:`ReconstructOptions` and the rules derived from it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from calib.target import TargetSpec


@dataclass(frozen=True)
class ReconstructOptions:
    input: Path
    out: Path
    spec: TargetSpec | None  # None only with ``cameras``: no ring target in the photos
    step_deg: float | None = None
    masks_dir: Path | None = None
    cameras: Path | None = None
    intrinsics: Path | None = None
    resolution: int = 256
    max_faces: int = 50_000  # a standalone headset's budget for one object
    every: int = 1
    frames: int | None = None  # use this many frames spread evenly over the input (instead of ``every``)
    fusion: bool = True
    overwrite: bool = False
    spawn: bool = False
    export_colmap: bool = False
    export_nerfstudio: bool = False
    copy_images: bool = False  # the exports' photos under OUT/images: copies, not hard links
    max_rejections: int | None = None  # None: 0 with masks_dir (trusted), 1 with automatic silhouettes
    work_size: int | None = None  # long side of the work images, pixels; 0: full size; None: the default policy
    texture: bool = True  # a UV atlas and a baked photo texture (False: vertex colours only)
    texture_size: int = 2048  # texture side, texels
    lods: tuple[int, ...] = ()  # face counts of coarser levels of detail sharing the texture (model_lod1, ...)


MIN_VIEWS = 3


# --------------------------------------------------------------------------- helpers


def max_rejections(opts: ReconstructOptions) -> int:
    """Views that may reject a voxel before it is carved: the user's masks are trusted (0); automatic
    silhouettes may err in a view (1), their doubtful pixels are carried by ``unknown`` besides."""
    if opts.max_rejections is not None:
        return int(opts.max_rejections)
    return 0 if opts.masks_dir is not None else 1
