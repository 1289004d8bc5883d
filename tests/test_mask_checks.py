"""Sense checks for --masks: inverted and all-white masks are refused before any work."""

from pathlib import Path

import numpy as np
import pytest

from turntable.errors import UserError
from turntable.mask_checks import check_masks

NAMES = [f"frame_{k:03d}.jpg" for k in range(8)]
DIR = Path("masks")


def _discs(n=8, h=60, w=80, r=15):
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([(yy - 30) ** 2 + (xx - 40 - k) ** 2 <= r * r for k in range(n)])


def test_plausible_masks_pass():
    m = _discs()
    m[3] = False  # one frame with the object out of view: left to the later, per-frame checks
    check_masks(m, NAMES, DIR)


def test_inverted_masks_are_refused_naming_folder_and_frames():
    inverted = r"--masks masks: 8 of 8 masks .*\(frame_000.jpg, .*\): they look inverted"
    with pytest.raises(UserError, match=inverted) as e:
        check_masks(~_discs(), NAMES, DIR)
    assert "white (> 127) on black" in str(e.value)


def test_an_all_white_mask_is_refused():
    m = _discs()
    m[5] = True
    with pytest.raises(UserError, match=r"1 of 8 masks cover more than 90 % .*\(frame_005.jpg\)"):
        check_masks(m, NAMES, DIR)


def test_a_large_object_touching_the_borders_is_not_called_inverted():
    m = _discs()
    yy, xx = np.mgrid[0:60, 0:80]
    m[:3] = ((yy - 30) / 31.0) ** 2 + ((xx - 40) / 41.0) ** 2 <= 1.0  # close up: cut by every border
    assert np.all(m[:3].reshape(3, -1).mean(axis=1) > 0.5) and m.reshape(8, -1).mean(axis=1).max() < 0.9
    check_masks(m, NAMES, DIR)
