"""Per-frame checks of automatic silhouettes: keep, keep conservatively, or drop.

A silhouette that looks wrong is not simply dropped: a dropped frame is a
missing view, and a sequence that loses many neighbouring frames loses the
views that carve a whole side of the object. So a frame is

* ``"ok"``: its mask is used as it is (the doubtful pixels joined to it
  without crossing an edge are left unknown);
* ``"conservative: <reason>"``: kept, with its doubtful pixels judged without
  trusting the mask's colours, so carving with ``mask | unknown`` can make
  the hull larger there rather than eat the object;
* ``"rejected: <reason>"``: dropped (nothing usable: an empty or black
  frame, the volume out of view) — unless dropping it would leave more than
  ``max_gap_deg`` of the turn without a view, then it is kept conservatively.

Angles of the turn are those of the camera centres about the table's +Y axis,
``atan2(Z, X)`` of ``C_table = -R_cam_table^T t_cam_table``.
"""

from __future__ import annotations

import numpy as np

from calib.camera import camera_centre_table

__all__ = ["frame_status", "camera_azimuths_deg", "camera_spread", "camera_still", "fill_gaps", "EMPTY", "CAMERA_STILL"]

_MIN_AREA = 0.02  # a silhouette smaller than this fraction of the cylinder's image is "empty" ...
_TYPICAL_SHARE = 0.75  # ... when also under this share of the sequence's median area (a thin object is small in all)
_FLOOR_AREA = 0.002  # ... and under this fraction, whatever the other frames show
EMPTY = "empty silhouette"  # the reason such a frame is rejected (and kept, where it closes a gap)
_MIN_SUPPORT = 0.5  # outline fraction that must look like background
AREA_DROP = 0.67  # a frame whose mask's area is under this share of its neighbours' median ...
AREA_JUMP = 1.5  # ... or over this share is kept conservatively


def frame_status(area_px: np.ndarray, support: np.ndarray, border_px: np.ndarray, region_px: np.ndarray,
                 size: tuple[int, int]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Quality (V,) in [0, 1] and status per frame from areas, borders and outline support.

    Parameters
    ----------
    area_px, support, border_px, region_px : (V,) arrays
        Mask area, outline support (see ``recon.silhouettes``), mask pixels on
        the image border, area of the working volume's image, per frame.
    size : (W, H)
        Image size, pixels.
    """
    area = np.asarray(area_px, np.float64)
    V = len(area)
    W, H = size
    quality = np.zeros(V)
    status = []
    # a thin figure seen side on, or a small object in a wide working volume, covers under 2 % of the
    # cylinder's image in frames whose masks are whole: "empty" is small against the other frames too
    typical = float(np.median(area)) if V else 0.0
    refs = _neighbour_areas(area)
    for i in range(V):
        ref = refs[i]
        ratio = area[i] / ref if ref > 0 else (1.0 if area[i] == 0 else np.inf)
        quality[i] = float(support[i]) * (min(ratio, 1.0 / ratio) if 0 < ratio < np.inf else 0.0)
        small = area[i] < _MIN_AREA * region_px[i] and area[i] < _TYPICAL_SHARE * typical
        if region_px[i] == 0 or small or area[i] < _FLOOR_AREA * region_px[i]:
            quality[i] = 0.0
            if region_px[i] == 0:
                status.append("rejected: the working volume is not in view")
            elif area[i] == 0:
                status.append(f"rejected: {EMPTY} (0 px)")
            else:  # a mask of some thousand pixels is "empty" only against what it should cover: say so
                status.append(f"rejected: nearly {EMPTY} ({int(area[i])} px: {100 * area[i] / region_px[i]:.1f} % "
                              f"of the working volume's image, {100 * area[i] / max(typical, 1.0):.0f} % of the "
                              "median frame's)")
        elif border_px[i] > 0.25 * (W + H):
            status.append(f"conservative: silhouette touches the image border along {int(border_px[i])} px")
        elif not AREA_DROP <= ratio <= AREA_JUMP:
            status.append(f"conservative: silhouette area jumps to {100 * ratio:.0f}% of its neighbours'")
        elif support[i] < _MIN_SUPPORT:
            status.append(f"conservative: only {100 * support[i]:.0f}% of the outline looks like background")
        else:
            status.append("ok")
    return quality, tuple(status)


def _neighbour_areas(area: np.ndarray) -> np.ndarray:
    """(V,) the median area of each frame's neighbours, two each side in turn order (its own without any)."""
    V = len(area)
    out = np.array(area, np.float64)
    for i in range(V):
        nb = [area[(i + d) % V] for d in (-2, -1, 1, 2) if V > 2 and (i + d) % V != i]
        if nb:
            out[i] = float(np.median(nb))
    return out


def area_shortfall(area_px: np.ndarray) -> np.ndarray:
    """(V,) the pixels each frame's mask lacks against its neighbours' median area (as :func:`frame_status`
    weighs it) where it is under ``AREA_DROP`` of it; 0 elsewhere."""
    area = np.asarray(area_px, np.float64)
    ref = _neighbour_areas(area)
    return np.where(area < AREA_DROP * ref, ref - area, 0.0)


def camera_azimuths_deg(T_cam_table: np.ndarray) -> np.ndarray:
    """Angle (V,) degrees of each camera centre about the table +Y axis, ``atan2(Z, X)`` in the table frame."""
    C = camera_centre_table(np.asarray(T_cam_table, np.float64).reshape(-1, 4, 4))
    return np.degrees(np.arctan2(C[:, 2], C[:, 0]))


CAMERA_STILL = 0.02  # the camera stays put: its centres' spread in height and in distance from the axis,
# as a share of their mean distance from the table centre (real turntable sequences: <= 0.25 %)


def camera_spread(T_cam_table: np.ndarray) -> tuple[float, float, float]:
    """Seen from the table, the camera centres' spread (std, mm) in height and in distance from the axis, and
    their mean distance from the table centre: a camera that stays put while the table turns spreads neither."""
    C = camera_centre_table(np.asarray(T_cam_table, np.float64).reshape(-1, 4, 4))
    return (float(C[:, 1].std()), float(np.hypot(C[:, 0], C[:, 2]).std()),
            float(np.linalg.norm(C, axis=1).mean()))


def camera_still(T_cam_table: np.ndarray) -> bool:
    """Whether the camera stays put while the table turns (:func:`camera_spread` within ``CAMERA_STILL``)."""
    dy, dr, d = camera_spread(T_cam_table)
    return max(dy, dr) <= CAMERA_STILL * d


def _circular_gaps(angles_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted angles (n,) in [0, 360) and the gap (n,) from each to the next one (circularly)."""
    a = np.sort(np.mod(angles_deg, 360.0))
    if len(a) == 0:
        return a, a
    return a, np.diff(np.append(a, a[0] + 360.0))


def fill_gaps(status: tuple[str, ...], azimuths_deg: np.ndarray, max_gap_deg: float = 30.0) -> tuple[str, ...]:
    """Turn rejected frames into conservative ones until no gap between kept views exceeds ``max_gap_deg``.

    Within each too-wide gap between kept frames, walking from its start, the
    rejected frame farthest along but within ``max_gap_deg`` of the last kept
    one is kept (the fewest frames that close the gap); where a stretch of the
    turn has no frame at all (a half turn), the walk stops there and goes on
    from the gap's other end. The open half of a half turn stays open.
    """
    out = list(status)
    az = np.mod(np.asarray(azimuths_deg, np.float64), 360.0)
    dropped = [i for i, s in enumerate(out) if s.startswith("rejected")]
    kept = [i for i, s in enumerate(out) if not s.startswith("rejected")]
    if not dropped:
        return tuple(out)
    if not kept:  # nothing to measure gaps from: start at the first rejected frame
        kept = [dropped[0]]
        out[dropped[0]] = _keep(out[dropped[0]], 360.0)
    starts, gaps = _circular_gaps(az[kept])
    for start, gap in zip(starts, gaps, strict=True):
        if gap <= max_gap_deg:
            continue
        inside = sorted(((az[j] - start) % 360.0, j) for j in dropped if 0 < (az[j] - start) % 360.0 < gap)
        ahead = _walk(inside, gap, max_gap_deg)
        reached = max([d for d, j in inside if j in ahead], default=0.0)
        behind = _walk([(gap - d, j) for d, j in reversed(inside) if d > reached], gap - reached, max_gap_deg)
        for j in ahead | behind:
            out[j] = _keep(out[j], gap)
    return tuple(out)


def _walk(inside: list[tuple[float, int]], gap: float, max_gap_deg: float) -> set[int]:
    """Frames to keep, walking from 0 towards ``gap`` over ``inside`` (sorted (offset, frame)): each step
    the farthest frame within ``max_gap_deg``; stops at ``gap`` or where no frame is that close (a
    stretch of the turn no frame shows: nothing to keep there)."""
    keep, pos = set(), 0.0
    while gap - pos > max_gap_deg:
        near = [(d, j) for d, j in inside if pos < d <= pos + max_gap_deg]
        if not near:
            break
        pos, j = near[-1]
        keep.add(j)
    return keep


def _keep(status: str, gap_deg: float) -> str:
    reason = status[len("rejected: "):] if status.startswith("rejected: ") else status
    return f"conservative: kept although {reason} (dropping it leaves {gap_deg:.0f} deg of the turn without a view)"
