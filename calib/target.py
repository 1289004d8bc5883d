"""The printed target: two concentric rings (black strokes on white).

Geometry in the table frame (mm): rings of centre-line radii ``r_outer_mm`` and
``r_inner_mm`` about the origin, strokes ``stroke_mm`` wide, in the plane Y = 0.
Angle marks (issue 3) extend this spec; the detector reads what the generator
draws from the same :class:`TargetSpec`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TargetSpec"]


@dataclass(frozen=True)
class TargetSpec:
    """Nominal geometry of the printed target, millimetres."""

    r_outer_mm: float
    r_inner_mm: float
    stroke_mm: float = 3.0

    def __post_init__(self) -> None:
        if not (self.r_outer_mm > 0 and self.r_inner_mm > 0):
            raise ValueError(f"ring radii must be positive, got {self.r_outer_mm}, {self.r_inner_mm}")
        if self.r_inner_mm >= self.r_outer_mm:
            raise ValueError(f"--r-inner ({self.r_inner_mm}) must be smaller than --r-outer ({self.r_outer_mm})")
        if not (0 <= self.stroke_mm < 0.5 * (self.r_outer_mm - self.r_inner_mm)):
            raise ValueError(f"stroke width {self.stroke_mm} mm does not fit between the rings")

    @property
    def radius_ratio(self) -> float:
        return self.r_outer_mm / self.r_inner_mm
