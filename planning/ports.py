"""The ports of a standard 3-port pars plana vitrectomy: two working ports and the infusion.

Clinical layout (reference/facts.md: eophtha.com beginner's guide to vitrectomy; PubMed
11642375): the infusion cannula usually inferotemporal, the two working ports
superotemporal and superonasal, about the 10 and 2 o'clock positions; sclerotomies
3.0 / 3.5 / 4.0 mm behind the limbus in aphakic / pseudophakic / phakic eyes; the ora
serrata about 6 mm (nasal) to 7 mm (temporal) behind the limbus.

Clock face in the eye frame E, as the surgeon sees the eye (z_E towards the surgeon):
12 o'clock is +y_E (superior), 3 o'clock +x_E; hour h lies at azimuth 90 - 30 h deg
from +x_E towards +y_E. For a right eye the nose is on the 3 o'clock side, for a left
eye on the 9 o'clock side, so superotemporal is 10 o'clock on a right eye and 2 o'clock
on a left one.

Distance behind the limbus: measured along the eye wall on the port's meridian. The
scenario's reference trocar (planning.scenario.TROCAR_P_EC_MM, z_E = 7.2 mm) is a phakic
sclerotomy, REFERENCE_LIMBUS_MM behind the limbus; a port d mm behind the limbus lies
d - REFERENCE_LIMBUS_MM further back along the retina's meridian arc (forward when
negative), at the reference trocar's depth in the wall. With this anchor the emmetropic
eye's ora serrata (z_E = 5 mm) lies 6.9 mm behind the limbus, inside the 6-7 mm above.
Units: mm, deg where named; frame E.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.eyes import make_eye

REFERENCE_LIMBUS_MM = 4.0  # the reference trocar's distance behind the limbus (phakic eye)
# the pars plana: behind the pars plicata (about 3 mm behind the limbus, where aphakic
# sclerotomies go) and at least 1 mm in front of the nasal ora serrata (6 mm)
PARS_PLANA_MM = (3.0, 5.0)
PORT_ROLES = ("working", "infusion")
# the layout's clock hours: (name, role, right eye, left eye)
STANDARD_LAYOUT = (("superonasal", "working", 2.0, 10.0), ("superotemporal", "working", 10.0, 2.0),
                   ("infusion", "infusion", 8.0, 4.0))
SIDES = ("right", "left")
# Two sclerotomies at least this far apart (clock hours, 30 deg each: about 5 mm of pars plana
# 4 mm behind the limbus); the standard layout's lie 4-6 hours apart.
MIN_PORT_SEPARATION_H = 1.0


@dataclass(frozen=True)
class Port:
    """A sclerotomy: its name, role ("working" or "infusion"), clock hour in [1, 12] (the
    surgeon's view, 12 superior) and distance behind the limbus (mm, on the pars plana)."""

    name: str
    role: str
    clock_hour: float
    limbus_mm: float

    def __post_init__(self):
        if not (isinstance(self.name, str) and self.name):
            raise ValueError(f"port name must be a non-empty string, got {self.name!r}")
        if self.role not in PORT_ROLES:
            raise ValueError(f"port {self.name}: role must be one of {', '.join(PORT_ROLES)}, got {self.role!r}")
        if not (np.isfinite(self.clock_hour) and 1.0 <= self.clock_hour <= 12.0):
            raise ValueError(f"port {self.name}: clock hour must be in [1, 12], got {self.clock_hour}")
        lo, hi = PARS_PLANA_MM
        if not (np.isfinite(self.limbus_mm) and lo <= self.limbus_mm <= hi):
            raise ValueError(f"port {self.name}: {self.limbus_mm} mm behind the limbus is off the pars plana "
                             f"(allowed [{lo:g}, {hi:g}] mm)")

    @property
    def azimuth_rad(self) -> float:
        """The port's meridian: azimuth from +x_E towards +y_E, rad."""
        return float(np.radians(90.0 - 30.0 * self.clock_hour))


def standard_ports(side: str = "right", limbus_mm: float = REFERENCE_LIMBUS_MM,
                   clock_hours: dict | None = None) -> tuple[Port, ...]:
    """The 3-port layout of a `side` ("right"/"left") eye, every port `limbus_mm` behind the
    limbus; `clock_hours` overrides some ports' hours by name. ValueError on an unknown
    side or port name, or an hour outside [1, 12]."""
    if side not in SIDES:
        raise ValueError(f"eye side must be one of {', '.join(SIDES)}, got {side!r}")
    hours = dict(clock_hours or {})
    names = [name for name, *_ in STANDARD_LAYOUT]
    unknown = sorted(set(hours) - set(names))
    if unknown:
        raise ValueError(f"unknown port {unknown[0]!r}: the ports are {', '.join(names)}")
    ports = tuple(Port(name, role, float(hours.get(name, right if side == "right" else left)), float(limbus_mm))
                  for name, role, right, left in STANDARD_LAYOUT)
    for i, a in enumerate(ports):
        for b in ports[i + 1:]:
            apart = abs(a.clock_hour - b.clock_hour)
            if min(apart, 12.0 - apart) < MIN_PORT_SEPARATION_H:
                raise ValueError(f"ports {a.name} ({a.clock_hour:g} o'clock) and {b.name} ({b.clock_hour:g} o'clock) "
                                 f"lie less than {MIN_PORT_SEPARATION_H:g} clock hour apart")
    return ports


def _meridian(eye, azimuth: float, elevation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(directions (K, 3), retina points (K, 3)) in E on the meridian at `azimuth`, rad."""
    U = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1)
    return U, eye.pose.to_E(eye.surface_points(U))


def port_p_EC(eye_name: str, port: Port, reference_p_EC, eye_params: dict | None = None) -> np.ndarray:
    """The port's trocar (mm, E) on the eye `eye_name` (with `eye_params`; its shape about its own centre):
    on the port's meridian, `port.limbus_mm - REFERENCE_LIMBUS_MM` mm of retina arc behind
    the elevation of `reference_p_EC` (a trocar REFERENCE_LIMBUS_MM behind the limbus on
    this eye), as deep in the wall as it is."""
    eye = make_eye(eye_name, **(eye_params or {}))
    ref = np.asarray(reference_p_EC, dtype=float)
    e_ref = float(np.arctan2(ref[2], np.hypot(ref[0], ref[1])))
    u_ref = ref / np.linalg.norm(ref)
    wall = np.linalg.norm(ref) - np.linalg.norm(eye.pose.to_E(eye.surface_points(u_ref[None]))[0])
    elev = e_ref + np.linspace(-0.6, 0.6, 1201)  # +-34 deg about the reference: +-6 mm of arc
    U, P = _meridian(eye, port.azimuth_rad, elev)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    arc -= np.interp(e_ref, elev, arc)  # arc length from the reference elevation, + anterior
    e = float(np.interp(-(port.limbus_mm - REFERENCE_LIMBUS_MM), arc, elev))
    (u,), (p,) = _meridian(eye, port.azimuth_rad, np.array([e]))
    return p + wall * u
