"""The printed target: two concentric rings and a ring of angle marks.

Everything here is pure geometry in the table frame (mm), the one source of
truth for both the generator (``turntable.pattern``) and the angle reader
(``calib.marks``).

Rings
    Black strokes ``stroke_mm`` wide whose centre lines are circles of radii
    ``r_outer_mm`` and ``r_inner_mm`` about the origin, in the plane Y = 0:
    ink where ``|r - R| <= stroke_mm / 2``.

Turntable angle
    The angle of a table point ``(X, 0, Z)`` is ``theta = atan2(Z, X)`` in
    ``[0, 2 pi)``, measured from +X towards +Z. Seen from above (from +Y),
    with X to the right, +Z points down the page, so theta grows *clockwise*:
    turning a point by +theta is the rotation by ``-theta`` about +Y under the
    right-hand rule. Printed angle 0 is table +X.

Angle marks (``marks=True``)
    One track, the annulus ``mark_r0_mm <= r <= mark_r1_mm`` outside the outer
    ring (default ``r_outer + stroke/2 + 4.5`` to ``+ 12`` more, i.e. 86-98 mm
    for the 80/50/3 target: a white gap of 4.5 mm keeps the ring detector
    undisturbed). It is cut into ``N = len(mark_code)`` equal sectors
    (default 72 x 5 deg); sector ``k`` covers ``[k, k + 1) * 360/N`` deg and
    carries bit ``b_k`` of ``mark_code`` in Manchester code: each sector is
    split into two half-sectors, ink-then-paper for ``b_k = 1`` and
    paper-then-ink for ``b_k = 0`` (in increasing theta).

    Why this layout: every sector has a sharp radial edge at its middle whatever
    its bit (plus one at its start when the bit repeats), so edges are dense and
    evenly spread for the fine angle (about 110 of them); the track is half ink
    in every 5 deg, which makes local black/white levels easy; a shift by half a
    sector disagrees in at least half of the half-sectors, so the coarse
    position cannot slip by a half-sector; and the default 72-bit code was
    searched so that every window of 7 consecutive sectors is unique (any 7
    visible sectors give the absolute angle) and windows of 12 / 18 / 36 sectors
    differ from every other position in at least 2 / 4 / 11 sectors (reading
    through a few wrong cells).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np

__all__ = [
    "TargetSpec",
    "DEFAULT_MARK_CODE",
    "MARK_GAP_MM",
    "turntable_angle",
    "mark_halfcells",
    "mark_edges",
    "mark_cells",
    "ink_at",
]

#: 72-bit code of the default target (sector 0 first); see the module docstring.
DEFAULT_MARK_CODE = "101011000011111110111110011000100011011001000001100111010001011101101001"

#: Default white gap (mm) between the outer ring stroke's outer edge and the marks.
MARK_GAP_MM = 4.5
#: Default radial height (mm) of the mark track.
MARK_HEIGHT_MM = 12.0
#: Smallest white gap (mm) the spec accepts between the outer ring and the marks.
MIN_MARK_GAP_MM = 4.0


@dataclass(frozen=True)
class TargetSpec:
    """Nominal geometry of the printed target, millimetres.

    Attributes
    ----------
    r_outer_mm, r_inner_mm : float
        Centre-line radii of the two ring strokes.
    stroke_mm : float
        Width of both ring strokes.
    marks : bool
        Whether the target carries the angle-mark track.
    mark_r0_mm, mark_r1_mm : float or None
        Inner and outer radius of the mark track; ``None`` derives them from
        the outer ring (``r_outer + stroke/2 + 4.5`` and 12 mm more).
    mark_code : str
        The sector bits, ``'0'``/``'1'``, sector 0 first; its length is the
        number of sectors.
    """

    r_outer_mm: float
    r_inner_mm: float
    stroke_mm: float = 3.0
    marks: bool = True
    mark_r0_mm: float | None = None
    mark_r1_mm: float | None = None
    mark_code: str = DEFAULT_MARK_CODE

    def __post_init__(self) -> None:
        if not (0 < self.r_outer_mm < np.inf and 0 < self.r_inner_mm < np.inf):
            raise ValueError(f"ring radii must be positive finite numbers, got {self.r_outer_mm}, {self.r_inner_mm}")
        if self.r_inner_mm >= self.r_outer_mm:
            raise ValueError(f"--r-inner ({self.r_inner_mm}) must be smaller than --r-outer ({self.r_outer_mm})")
        if not (0 <= self.stroke_mm < 0.5 * (self.r_outer_mm - self.r_inner_mm)):
            raise ValueError(f"stroke width {self.stroke_mm} mm does not fit between the rings")
        ring_edge = self.r_outer_mm + self.stroke_mm / 2.0
        r0 = ring_edge + MARK_GAP_MM if self.mark_r0_mm is None else float(self.mark_r0_mm)
        r1 = r0 + MARK_HEIGHT_MM if self.mark_r1_mm is None else float(self.mark_r1_mm)
        object.__setattr__(self, "mark_r0_mm", r0)
        object.__setattr__(self, "mark_r1_mm", r1)
        if r0 - ring_edge < MIN_MARK_GAP_MM:
            raise ValueError(f"angle marks start at {r0} mm: they need a white gap of at least "
                             f"{MIN_MARK_GAP_MM} mm outside the outer ring's edge at {ring_edge} mm")
        if r1 - r0 < 4.0:
            raise ValueError(f"angle-mark track {r0}-{r1} mm is narrower than 4 mm")
        _check_code(self.mark_code)

    @property
    def radius_ratio(self) -> float:
        return self.r_outer_mm / self.r_inner_mm

    @property
    def n_sectors(self) -> int:
        """Number of code sectors of the mark track."""
        return len(self.mark_code)

    @property
    def extent_mm(self) -> float:
        """Radius (mm) of the outermost ink: the mark track, or the outer ring's edge."""
        ring = self.r_outer_mm + self.stroke_mm / 2.0
        # __post_init__ has replaced a None mark radius by its value
        return max(ring, cast(float, self.mark_r1_mm)) if self.marks else ring


def _check_code(code: str) -> None:
    if not isinstance(code, str) or set(code) - {"0", "1"}:
        raise ValueError("mark_code must be a string of '0' and '1'")
    n = len(code)
    if not 16 <= n <= 360:
        raise ValueError(f"mark_code must have 16 to 360 sectors, got {n}")
    # a code equal to one of its own cyclic shifts cannot give an absolute angle
    if (code + code).find(code, 1) < n:
        raise ValueError("mark_code is periodic: it cannot give an absolute angle")


def turntable_angle(X: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Turntable angle ``atan2(Z, X)`` in ``[0, 2 pi)`` radians of table points ``(X, 0, Z)``."""
    return np.mod(np.arctan2(Z, X), 2.0 * np.pi)


def mark_halfcells(spec: TargetSpec) -> np.ndarray:
    """Ink of the ``2N`` half-sectors of the mark track, (2N,) bool.

    Half-sector ``i`` covers angles ``[i, i + 1) * pi / N`` (radians); bit
    ``b_k`` gives half-sectors ``2k, 2k + 1`` = ``(b_k, not b_k)``.
    """
    bits = np.frombuffer(spec.mark_code.encode("ascii"), dtype=np.uint8) == ord("1")
    return np.column_stack([bits, ~bits]).ravel()


def mark_edges(spec: TargetSpec) -> tuple[np.ndarray, np.ndarray]:
    """Radial edges of the mark track: where the ink changes along theta.

    Returns
    -------
    theta : (E,) float64
        Edge angles, radians in ``[0, 2 pi)``, increasing.
    to_ink : (E,) bool
        True where paper turns to ink with increasing theta.
    """
    ink = mark_halfcells(spec)
    prev = np.roll(ink, 1)
    i = np.flatnonzero(ink != prev)
    return i * (np.pi / spec.n_sectors), ink[i].copy()


def mark_cells(spec: TargetSpec) -> np.ndarray:
    """Ink sectors of the mark track, merged runs of half-sectors.

    Returns
    -------
    (M, 4) float64
        Rows ``(theta0, theta1, r0_mm, r1_mm)``: ink where
        ``theta0 <= theta < theta1`` (radians, ``theta1`` may exceed 2 pi for a
        run across angle 0) and ``r0 <= r <= r1``. Empty without marks.
    """
    if not spec.marks:
        return np.zeros((0, 4))
    ink = mark_halfcells(spec)
    n2 = ink.size
    start = int(np.flatnonzero(ink != np.roll(ink, 1))[0])  # an edge, so runs never wrap inside
    rows = []
    i = start
    while i < start + n2:
        j = i
        while j < start + n2 and ink[j % n2] == ink[i % n2]:
            j += 1
        if ink[i % n2]:
            t0 = (i % n2) * np.pi / spec.n_sectors
            rows.append((t0, t0 + (j - i) * np.pi / spec.n_sectors, spec.mark_r0_mm, spec.mark_r1_mm))
        i = j
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def ink_at(spec: TargetSpec, X: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Whether the printed target has ink at table points ``(X, 0, Z)`` (mm).

    Vectorised over broadcastable ``X``, ``Z``; returns a bool array of their
    broadcast shape. This is the definition every drawing of the target follows.
    """
    X = np.asarray(X, dtype=np.float64)
    Z = np.asarray(Z, dtype=np.float64)
    r = np.hypot(X, Z)
    half = spec.stroke_mm / 2.0
    ink = (np.abs(r - spec.r_outer_mm) <= half) | (np.abs(r - spec.r_inner_mm) <= half)
    if spec.marks:
        track = (r >= spec.mark_r0_mm) & (r <= spec.mark_r1_mm)
        if np.any(track):
            Xb, Zb = np.broadcast_arrays(X, Z)
            n2 = 2 * spec.n_sectors
            i = np.floor(turntable_angle(Xb[track], Zb[track]) * (n2 / (2.0 * np.pi))).astype(np.int64) % n2
            ink[track] |= mark_halfcells(spec)[i]
    return ink
