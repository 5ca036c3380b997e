"""The 3-port layout: clock hours, distances behind the limbus, bad input."""
from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning import SurgeryScenario
from planning.ports import PARS_PLANA_MM, REFERENCE_LIMBUS_MM, Port, port_p_EC, standard_ports
from planning.scenario import PORTS_EYE_POSE, SURGERY_EYE_POSE, TROCAR_P_EC_MM, default_trocar_E


def test_the_standard_layout_mirrors_between_the_eyes():
    right = {p.name: p.clock_hour for p in standard_ports("right")}
    left = {p.name: p.clock_hour for p in standard_ports("left")}
    assert right == {"superonasal": 2.0, "superotemporal": 10.0, "infusion": 8.0}
    assert left == {"superonasal": 10.0, "superotemporal": 2.0, "infusion": 4.0}


def test_a_port_at_the_reference_distance_and_3_oclock_is_the_reference_trocar():
    p = port_p_EC("emmetropic", Port("x", "working", 3.0, REFERENCE_LIMBUS_MM), TROCAR_P_EC_MM)
    assert np.allclose(p, TROCAR_P_EC_MM, atol=1e-3)


@settings(max_examples=20)
@given(hour=st.floats(1.0, 12.0), limbus=st.floats(*PARS_PLANA_MM))
def test_ports_lie_in_the_wall_on_their_meridian_further_back_the_further_from_the_limbus(hour, limbus):
    ref = default_trocar_E("emmetropic")
    p = port_p_EC("emmetropic", Port("x", "working", hour, limbus), ref)
    a = np.radians(90.0 - 30.0 * hour)
    assert np.isclose(np.arctan2(p[1], p[0]), np.arctan2(np.sin(a), np.cos(a)), atol=1e-9)
    # the wall arc from the reference: 1 mm of arc moves the port by about 1 mm (chord ~ arc)
    at_ref = port_p_EC("emmetropic", Port("x", "working", hour, REFERENCE_LIMBUS_MM), ref)
    assert np.linalg.norm(p - at_ref) == pytest.approx(abs(limbus - REFERENCE_LIMBUS_MM), abs=0.1)
    assert (p[2] - at_ref[2]) * (limbus - REFERENCE_LIMBUS_MM) <= 1e-9  # further from the limbus: further back
    SurgeryScenario(eye_name="emmetropic", ports=(Port("x", "working", hour, limbus),))  # in the wall, clear of the lens


def test_the_ports_placement_keeps_the_2_oclock_port_where_the_reference_trocar_is():
    """PORTS_EYE_POSE turns the eye about its visual axis so the 2 o'clock working port
    lies where the reference trocar lies in W: the model-building scan is the reference one."""
    sc = SurgeryScenario(eye_pose=PORTS_EYE_POSE, ports=standard_ports("right"))
    ref = SurgeryScenario(eye_pose=SURGERY_EYE_POSE)
    assert np.linalg.norm(sc.p_WC_of("superonasal") - ref.p_WC) < 0.02
    assert np.allclose(PORTS_EYE_POSE.R_WE[:, 2], SURGERY_EYE_POSE.R_WE[:, 2])  # the same visual axis


@pytest.mark.parametrize("kwargs, message", [
    (dict(clock_hours={"nasal": 3}), "unknown port 'nasal'"), (dict(clock_hours={"infusion": 13}), "[1, 12]"),
    (dict(clock_hours={"infusion": 0}), "[1, 12]"), (dict(limbus_mm=2.0), "off the pars plana"),
    (dict(limbus_mm=7.0), "off the pars plana"), (dict(side="up"), "eye side"),
    (dict(clock_hours={"superonasal": 10}), "superonasal (10 o'clock) and superotemporal (10 o'clock) lie less than 1"),
    (dict(clock_hours={"superonasal": 10.5}), "less than 1 clock hour apart")])
def test_bad_ports_are_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        standard_ports(**kwargs)


def test_ports_an_hour_apart_across_12_oclock_are_taken():
    """12 and 1 o'clock lie one clock hour apart (the hours wrap): allowed."""
    ports = standard_ports("right", clock_hours={"superotemporal": 12.0, "superonasal": 1.0})
    assert [p.clock_hour for p in ports] == [1.0, 12.0, 8.0]


def test_an_unknown_port_name_is_refused_by_the_scenario():
    sc = SurgeryScenario(ports=standard_ports("right"))
    with pytest.raises(ValueError, match="unknown port 'x': the ports are superonasal, superotemporal, infusion"):
        sc.p_WC_of("x")
