"""Keep-out: monitored points stay outside a distance field (the crystalline lens).

The point barrier's rule (safety.constraints.point_barrier) on the other side of the
field: the clearance is -h (the field is > 0 inside the keep-out), kept above
`margin_mm`. The lens keep-out ellipsoid is exact, so its uncertainty is zero.
"""
from __future__ import annotations

from dataclasses import dataclass

from safety.constraints.point_barrier import PointBarrier


@dataclass(frozen=True)
class KeepOut(PointBarrier):
    """The points of `group` stay `d_safe_mm` (the margin, mm) outside the field in slot
    `field` (> 0 inside the keep-out region)."""

    d_safe_mm: float = 0.3
    name: str = "lens"

    side = -1.0
    reports_clearance = False


__all__ = ["KeepOut"]
