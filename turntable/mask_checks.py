"""Sense checks for user-given silhouettes (``--masks``): refuse masks that cannot be the object's.

A mask shows the object in white (> 127) on black. Inverted masks (the
background in white) or all-white ones still carve "a" model: a block the
size of the working volume, with exit 0, or an internal error.
These checks catch them when the masks are read, before any work; empty
masks are named frame by frame by the silhouette checks later.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import UserError

__all__ = ["check_masks"]

_FULL = 0.9  # a mask covering more than this share of its image is no object's silhouette
_INVERTED = 0.5  # more than half the image white and touching all four borders: the background


def _touches_all_borders(m: np.ndarray) -> bool:
    return bool(m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any())


def check_masks(masks: np.ndarray, names: list[str], masks_dir: Path) -> None:
    """``UserError`` naming the folder, the frames and the reason when the masks are implausible.

    ``masks`` (V, h, w) bool, object True, one per frame ``names``. Refused:
    masks of most frames (more than half) that cover more than half of the
    image while touching all four image borders (inverted: the background is
    white), and any single mask covering more than 90 % of its image (all
    white). Empty masks are left to the silhouette checks, which reject them
    frame by frame and name each one (and stop the run when too few remain).
    """
    V = len(masks)
    if V == 0:
        return
    share = masks.reshape(V, -1).mean(axis=1)
    full = share > _FULL
    inverted = np.array([s > _INVERTED and _touches_all_borders(m) for s, m in zip(share, masks, strict=True)])

    def listed(sel: np.ndarray) -> str:
        idx = np.flatnonzero(sel)
        shown = ", ".join(names[i] for i in idx[:5])
        return shown + (f" and {len(idx) - 5} more" if len(idx) > 5 else "")

    hint = "the object must be white (> 127) on black"
    if inverted.sum() > V / 2:
        raise UserError(f"--masks {masks_dir}: {int(inverted.sum())} of {V} masks are white over more than half the "
                        f"image and touch all four borders ({listed(inverted)}): they look inverted; {hint}")
    if full.any():
        raise UserError(f"--masks {masks_dir}: {int(full.sum())} of {V} masks cover more than 90 % of their image "
                        f"({listed(full)}): no object's silhouette; {hint}")
