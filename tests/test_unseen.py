"""What a log cannot show: diagnose says which families it never looked for, and that a
square modulation hardly tests for hysteresis, rather than letting "no missing effect"
stand for them."""

from __future__ import annotations

import dataclasses

import numpy as np

from leveler.analysis.diagnose import unseen
from leveler.analysis.evidence import modulation_steps
from leveler.analysis.predict import Measured
from leveler.sim.effects import Signals

HYST = "actuator_hysteresis"


def _modulated(meas: Measured, shape: str) -> Measured:
    """`meas` with a 1 V, 287 s modulation on its command."""
    phase = 2 * np.pi * (meas.t_s - meas.t_s[0]) / 287.0
    wave = (np.sign(np.sin(phase)) if shape == "square"
            else 2 / np.pi * np.arcsin(np.sin(phase)))
    return dataclasses.replace(meas, u_v=meas.u_v + 1.0 * wave)


def test_a_square_steps_a_triangle_sweeps(quiet: Measured) -> None:
    assert modulation_steps(_modulated(quiet, "square"))
    assert not modulation_steps(_modulated(quiet, "triangle"))
    assert not modulation_steps(quiet)  # the loop alone: no modulation


def test_under_a_square_hysteresis_is_hardly_looked_for(quiet: Measured) -> None:
    square = unseen(_modulated(quiet, "square"), True, [])
    assert "square modulation" in square[HYST] and "triangle" in square[HYST]
    assert HYST not in unseen(_modulated(quiet, "triangle"), True, [])
    assert HYST not in unseen(_modulated(quiet, "square"), True, [HYST])  # found anyway


def test_what_is_never_looked_for_says_why(quiet: Measured) -> None:
    assert unseen(quiet, True, []) == {}  # temperature logged, actuator seen
    cold = dataclasses.replace(quiet, sig=Signals(quiet.t_s, quiet.dt_s, None))
    why = unseen(cold, True, [])
    # a drift is as likely the table's unpredicted thermal tilt then
    assert set(why) == {"temperature_coupling", "sensor_drift"}
    assert all("no temperature was logged" in w for w in why.values())
    why = unseen(cold, False, [])
    assert set(why) == {"temperature_coupling", "actuator_delay", HYST, "extra_resonance",
                        "sensor_gain_error", "sensor_drift"}
    assert all(w.startswith("not looked for") for w in why.values())
