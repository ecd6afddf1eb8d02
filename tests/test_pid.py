"""Tests for leveler.loop.pid: invariants by Hypothesis, loop behaviour by small simulations.

Units follow the instrument: sensor readings of order a millimetre, piezo up to ~150 V,
so gains are large (V/m) and the tolerances below are meaningful at those scales.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from itertools import pairwise
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leveler.loop.pid import PID, PIDConfig, PIDGains, PIDOutput

FAST = settings(deadline=None)

measurements = st.floats(-1e-3, 1e-3)
dts = st.floats(1e-4, 10.0)
setpoints = st.floats(-1e-3, 1e-3)
gains_st = st.builds(
    PIDGains, kp=st.floats(-1e5, 1e5), ki=st.floats(-1e7, 1e7), kd=st.floats(-100.0, 100.0)
)
limits_st = st.tuples(st.floats(-200.0, 200.0), st.floats(1e-3, 400.0)).map(
    lambda t: (t[0], t[0] + t[1])
)
slews = st.floats(1e-2, 1e4)
any_slews = slews | st.just(math.inf)
taus = st.floats(0.0, 1.0)
ramps = st.floats(1e-4, 1.0) | st.just(math.inf)


def configs(
    slew: st.SearchStrategy[float] = any_slews,
    tau: st.SearchStrategy[float] = taus,
    ramp: st.SearchStrategy[float] = ramps,
) -> st.SearchStrategy[PIDConfig]:
    return st.builds(
        lambda gains, limits, sp, slew, tau, ramp, tt: PIDConfig(
            gains, limits[0], limits[1], sp, slew, tau, ramp, tt
        ),
        gains_st,
        limits_st,
        setpoints,
        slew,
        tau,
        ramp,
        st.just(0.0) | st.floats(1e-4, 10.0),
    )


Op = tuple[Any, ...]
update_ops = st.tuples(st.just("update"), measurements, dts)
gain_ops = st.tuples(st.just("gains"), gains_st)
setpoint_ops = st.tuples(st.just("setpoint"), setpoints)
slew_ops = st.tuples(st.just("slew"), slews)
limit_ops = st.tuples(st.just("limits"), limits_st)
engage_ops = st.tuples(st.just("engage"), measurements, st.floats(-300.0, 300.0))


def apply(pid: PID, op: Op) -> PIDOutput | None:
    """Run one generated operation; return the output if it was an update."""
    match op:
        case ("update", m, dt):
            return pid.update(m, dt)
        case ("gains", gains):
            pid.set_gains(gains)
        case ("setpoint", sp):
            pid.set_setpoint(sp)
        case ("slew", slew):
            pid.set_slew(slew)
        case ("limits", (lo, hi)):
            pid.set_limits(lo, hi)
        case ("engage", m, out):
            pid.engage(m, out)
        case _:
            raise AssertionError(op)
    return None


def clamp(x: float, lo: float, hi: float) -> float:
    return min(max(x, lo), hi)


# --- invariants over arbitrary operation sequences -----------------------------------------


@FAST
@given(
    configs(),
    st.floats(-300.0, 300.0),
    st.lists(update_ops | gain_ops | setpoint_ops | slew_ops | limit_ops | engage_ops, max_size=60),
)
def test_output_within_limits_and_saturated_flag_honest(
    config: PIDConfig, initial_v: float, ops: list[Op]
) -> None:
    pid = PID(config, initial_v)
    for op in ops:
        out = apply(pid, op)
        assert pid.config.output_min_v <= pid.output_v <= pid.config.output_max_v
        if out is not None:
            assert out.command_v == pid.output_v
            assert out.saturated == (out.command_v != out.p_v + out.i_v + out.d_v)


@FAST
@given(configs(slew=slews), st.lists(update_ops | gain_ops | setpoint_ops | slew_ops, max_size=60))
def test_output_rate_never_exceeds_slew(config: PIDConfig, ops: list[Op]) -> None:
    pid = PID(config)
    for op in ops:
        before = pid.output_v
        out = apply(pid, op)
        if out is not None:
            assert abs(out.command_v - before) <= pid.config.slew_v_per_s * op[2] + 1e-12


def test_narrowed_limits_clamp_at_once_despite_slew() -> None:
    pid = PID(PIDConfig(PIDGains(0.0, 0.0, 0.0), 0.0, 150.0, slew_v_per_s=1.0), 100.0)
    pid.set_limits(0.0, 50.0)
    assert pid.output_v == 50.0
    assert pid.update(0.0, 1e-3).command_v == 50.0


# --- anti-windup ---------------------------------------------------------------------------

DT = 1e-3
RAIL_LO, RAIL_HI = 0.0, 150.0
BIG_ERROR_M = 1e-2  # kp * error = 200 V: far past either rail


class NaivePI:
    """Textbook PI that keeps integrating while clamped: the windup the PID must avoid."""

    def __init__(self, gains: PIDGains) -> None:
        self.gains = gains
        self.i = 75.0

    def update(self, measurement_m: float, dt_s: float) -> float:
        error = -measurement_m
        self.i += self.gains.ki * error * dt_s
        return clamp(self.gains.kp * error + self.i, RAIL_LO, RAIL_HI)


def samples_to_leave_rail(update: Callable[[float, float], float], error_m: float) -> int:
    """Saturate for 10^5 samples at `error_m`, reverse it, count samples until off the rail."""
    rail = RAIL_HI if error_m > 0 else RAIL_LO
    for _ in range(100_000):
        command = update(-error_m, DT)  # setpoint is 0, so error = -measurement
    assert command == rail
    for n in range(1, 1001):
        if update(error_m, DT) != rail:
            return n
    return 1001


WINDUP_CASES = {
    "pid": PIDConfig(PIDGains(2e4, 2e6, 2.0), RAIL_LO, RAIL_HI, d_filter_tau_s=1e-3),
    "pi": PIDConfig(PIDGains(2e4, 2e6, 0.0), RAIL_LO, RAIL_HI),
    "i-only": PIDConfig(PIDGains(0.0, 2e6, 0.0), RAIL_LO, RAIL_HI),
    "slow-tracking": PIDConfig(PIDGains(2e4, 2e6, 0.0), RAIL_LO, RAIL_HI, tracking_time_s=100.0),
}


@pytest.mark.parametrize("error_m", [BIG_ERROR_M, -BIG_ERROR_M], ids=["upper", "lower"])
@pytest.mark.parametrize("config", WINDUP_CASES.values(), ids=WINDUP_CASES.keys())
def test_no_windup_after_long_saturation(config: PIDConfig, error_m: float) -> None:
    pid = PID(config, 75.0)
    assert samples_to_leave_rail(lambda m, dt: pid.update(m, dt).command_v, error_m) <= 3


def test_windup_criterion_catches_a_naive_integrator() -> None:
    naive = NaivePI(PIDGains(2e4, 2e6, 0.0))
    assert samples_to_leave_rail(naive.update, BIG_ERROR_M) > 100


def test_no_windup_under_slew_limit() -> None:
    # Far from the rails the slew limit is what saturates; the freeze does not apply, so
    # only back-calculation stops the integral running away while the output crawls.
    config = PIDConfig(PIDGains(2e4, 2e6, 0.0), -1e3, 1e3, slew_v_per_s=10.0)
    pid = PID(config, 0.0)
    for _ in range(5000):
        pid.update(-BIG_ERROR_M, DT)
    assert 0.0 < pid.output_v < config.output_max_v
    peak = pid.output_v
    commands = [pid.update(BIG_ERROR_M, DT).command_v for _ in range(3)]
    assert commands[-1] < peak


@FAST
@given(
    st.builds(PIDGains, st.floats(0.0, 1e5), st.floats(0.0, 1e7), st.floats(0.0, 100.0)),
    st.floats(0.0, 1.0),
    st.sampled_from([BIG_ERROR_M, -BIG_ERROR_M]),
    st.lists(dts, min_size=1, max_size=50),
)
def test_saturated_output_stays_on_rail_while_error_persists(
    gains: PIDGains, tau: float, error_m: float, steps: list[float]
) -> None:
    # Tracking must not overshoot when dt exceeds the tracking time: that would chatter
    # the output off the rail although the error still drives it there.
    pid = PID(PIDConfig(gains, RAIL_LO, RAIL_HI, d_filter_tau_s=tau))
    pid.engage(-error_m, 75.0)
    rail = RAIL_HI if error_m > 0 else RAIL_LO
    on_rail = False
    for dt in steps:
        command = pid.update(-error_m, dt).command_v
        assert command == rail or not on_rail
        on_rail = command == rail


# --- bumpless transfers --------------------------------------------------------------------

histories = st.lists(st.tuples(measurements, dts), min_size=1, max_size=20)


@FAST
@given(
    configs(slew=st.just(math.inf), tau=st.floats(1e-2, 1.0), ramp=st.just(math.inf)),
    histories,
    gains_st,
)
def test_gain_change_is_bumpless(
    config: PIDConfig, history: list[tuple[float, float]], gains: PIDGains
) -> None:
    # tau >= 10 ms and a 1 ps step keep the filtered derivative still; anything that moves
    # the output is then the gain change itself.
    pid = PID(config)
    for m, dt in history:
        pid.update(m, dt)
    before = pid.output_v
    pid.set_gains(gains)
    assert pid.config.gains == gains
    after = pid.update(history[-1][0], 1e-12).command_v
    assert after == pytest.approx(before, abs=1e-6)


@FAST
@given(configs(ramp=st.just(math.inf)), histories, measurements, st.floats(-300.0, 300.0), dts)
def test_engage_is_bumpless(
    config: PIDConfig,
    history: list[tuple[float, float]],
    measurement_m: float,
    output_v: float,
    dt_s: float,
) -> None:
    pid = PID(config)
    for m, dt in history:
        pid.update(m, dt)
    pid.engage(measurement_m, output_v)
    out = pid.update(measurement_m, dt_s)
    assert out.d_v == 0.0  # derivative seeded from the engage measurement: no kick
    expected = clamp(output_v, config.output_min_v, config.output_max_v)
    assert out.command_v == pytest.approx(expected, abs=1e-9)


@FAST
@given(configs(ramp=st.just(math.inf)), measurements, st.floats(-300.0, 300.0), dts)
def test_first_update_starts_from_initial_output(
    config: PIDConfig, measurement_m: float, initial_v: float, dt_s: float
) -> None:
    out = PID(config, initial_v).update(measurement_m, dt_s)
    expected = clamp(initial_v, config.output_min_v, config.output_max_v)
    assert out.command_v == pytest.approx(expected, abs=1e-9)


def test_default_initial_output_is_zero_clamped_into_range() -> None:
    gains = PIDGains(1.0, 1.0, 1.0)
    assert PID(PIDConfig(gains, -10.0, 10.0)).output_v == 0.0
    assert PID(PIDConfig(gains, 20.0, 150.0)).output_v == 20.0
    assert PID(PIDConfig(gains, -150.0, -20.0)).output_v == -20.0


# --- setpoint and derivative ---------------------------------------------------------------


@FAST
@given(
    st.floats(1e-4, 1e-1),
    st.lists(st.tuples(st.just("setpoint"), setpoints) | update_ops, max_size=60),
)
def test_setpoint_ramp_rate_respected_and_target_reached(ramp: float, ops: list[Op]) -> None:
    pid = PID(PIDConfig(PIDGains(1e3, 1e4, 0.1), -100.0, 100.0, setpoint_ramp_m_per_s=ramp))
    effective = 0.0
    for op in ops:
        out = apply(pid, op)
        target = pid.config.setpoint_m
        if out is None:
            assert target == op[1]
            continue
        allowed = ramp * op[2]
        if abs(target - effective) <= allowed:
            assert out.setpoint_m == target
        else:
            moved = out.setpoint_m - effective
            assert abs(moved) == pytest.approx(allowed, rel=1e-9)
            assert moved * (target - effective) > 0
        effective = out.setpoint_m


@pytest.mark.parametrize("tau", [0.0, 5e-3])
def test_setpoint_step_gives_no_derivative_kick(tau: float) -> None:
    pid = PID(PIDConfig(PIDGains(0.0, 0.0, 10.0), -100.0, 100.0, d_filter_tau_s=tau))
    for _ in range(10):
        pid.update(1e-4, DT)
    before = pid.output_v
    pid.set_setpoint(1e-3)
    out = pid.update(1e-4, DT)
    assert out.error_m == pytest.approx(1e-3 - 1e-4)
    assert out.d_v == 0.0
    assert out.command_v == before
    # The derivative path is live: the same step in the measurement does kick.
    assert pid.update(1e-4 + 1e-3, DT).d_v < -1.0


def derivative_step_response(tau: float, dt: float, n: int) -> list[float]:
    """d_v after a measurement step of 1e-3 m with kd = 1 V s/m, one entry per sample."""
    pid = PID(PIDConfig(PIDGains(0.0, 0.0, 1.0), -1e3, 1e3, d_filter_tau_s=tau))
    pid.update(0.0, dt)
    return [pid.update(1e-3, dt).d_v for _ in range(n)]


def test_derivative_filter_low_passes_with_time_constant_tau() -> None:
    tau, dt, step = 10e-3, 1e-4, 1e-3
    unfiltered = derivative_step_response(0.0, dt, 3)
    assert unfiltered == pytest.approx([-step / dt, 0.0, 0.0])

    response = derivative_step_response(tau, dt, 1000)
    peak = response[0]
    assert abs(peak) <= step / tau  # bounded by tau, not by the 100x larger step/dt
    assert all(abs(b) < abs(a) for a, b in pairwise(response))
    samples_per_tau = round(tau / dt)
    assert response[samples_per_tau] / peak == pytest.approx(math.exp(-1.0), rel=0.02)
    # A low-pass keeps the area: the net kick is still kd * step.
    assert sum(response) * dt == pytest.approx(-step, rel=1e-3)


# --- closed loop ---------------------------------------------------------------------------


def simulate_first_order_loop(gains: PIDGains, setpoint_m: float, seconds: float) -> float:
    """Piezo on a first-order plant with a constant disturbance; return the final error.

    x' = (G u + w - x) / T, discretised exactly for a zero-order-hold command.
    """
    plant_gain_m_per_v, plant_tau_s, disturbance_m, dt = 1e-6, 0.05, 3e-6, 1e-3
    pid = PID(PIDConfig(gains, -100.0, 100.0, setpoint_m=setpoint_m), 0.0)
    decay = math.exp(-dt / plant_tau_s)
    x = 0.0
    for _ in range(round(seconds / dt)):
        u = pid.update(x, dt).command_v
        x = decay * x + (1.0 - decay) * (plant_gain_m_per_v * u + disturbance_m)
    return setpoint_m - x


def test_pi_drives_steady_state_error_to_zero() -> None:
    setpoint = 5e-6
    # Loop gain kp G = 0.5, integral time = plant time constant.
    error = simulate_first_order_loop(PIDGains(5e5, 1e7, 0.0), setpoint, 2.0)
    assert abs(error) < 1e-4 * setpoint
    # The criterion is sharp enough to fail: P alone leaves a large offset.
    p_only_error = simulate_first_order_loop(PIDGains(5e5, 0.0, 0.0), setpoint, 2.0)
    assert abs(p_only_error) > 0.1 * setpoint


# --- validation ----------------------------------------------------------------------------

GOOD_GAINS = PIDGains(1.0, 1.0, 1.0)


@pytest.mark.parametrize("field", ["kp", "ki", "kd"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_gains_must_be_finite(field: str, bad: float) -> None:
    values = {"kp": 1.0, "ki": 1.0, "kd": 1.0, field: bad}
    with pytest.raises(ValueError, match=field):
        PIDGains(**values)


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("output_min_v", math.nan),
        ("output_min_v", -math.inf),
        ("output_max_v", math.inf),
        ("output_min_v", 10.0),  # equal to output_max_v
        ("output_min_v", 11.0),
        ("setpoint_m", math.nan),
        ("slew_v_per_s", 0.0),
        ("slew_v_per_s", -1.0),
        ("slew_v_per_s", math.nan),
        ("d_filter_tau_s", -1e-3),
        ("d_filter_tau_s", math.inf),
        ("d_filter_tau_s", math.nan),
        ("setpoint_ramp_m_per_s", 0.0),
        ("setpoint_ramp_m_per_s", math.nan),
        ("tracking_time_s", -1.0),
        ("tracking_time_s", math.nan),
    ],
)
def test_config_validation_names_the_field(field: str, bad: float) -> None:
    kwargs: dict[str, Any] = {"gains": GOOD_GAINS, "output_min_v": -10.0, "output_max_v": 10.0}
    kwargs[field] = bad
    with pytest.raises(ValueError, match=field):
        PIDConfig(**kwargs)


def test_unlimited_rates_are_valid() -> None:
    config = PIDConfig(GOOD_GAINS, -1.0, 1.0, slew_v_per_s=math.inf)
    assert config.setpoint_ramp_m_per_s == math.inf


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda pid: pid.set_limits(5.0, -5.0), "output_min_v"),
        (lambda pid: pid.set_limits(-5.0, math.nan), "output_max_v"),
        (lambda pid: pid.set_slew(0.0), "slew_v_per_s"),
        (lambda pid: pid.set_setpoint(math.nan), "setpoint_m"),
        (lambda pid: pid.update(0.0, 0.0), "dt_s"),
        (lambda pid: pid.update(0.0, -1e-3), "dt_s"),
        (lambda pid: pid.update(0.0, math.nan), "dt_s"),
        (lambda pid: pid.update(0.0, math.inf), "dt_s"),
        (lambda pid: pid.update(math.nan, 1e-3), "measurement_m"),
        (lambda pid: pid.update(-math.inf, 1e-3), "measurement_m"),
        (lambda pid: pid.engage(math.nan, 0.0), "measurement_m"),
        (lambda pid: pid.engage(0.0, math.inf), "output_v"),
    ],
)
def test_bad_input_is_rejected_without_changing_state(
    call: Callable[[PID], None], field: str
) -> None:
    def run(pid: PID) -> list[float]:
        return [pid.update(m, 1e-3).command_v for m in (1e-4, 2e-4, 1.5e-4)]

    pid, reference = (PID(PIDConfig(GOOD_GAINS, -10.0, 10.0, slew_v_per_s=1e3)) for _ in "ab")
    run(pid)
    run(reference)
    config = pid.config
    with pytest.raises(ValueError, match=field):
        call(pid)
    assert pid.config == config
    assert run(pid) == run(reference)


def test_overflowing_arithmetic_raises_without_changing_state() -> None:
    """Hypothesis found this via the loop: a 1e300 reading, kp 1.8e8 and kd 1e6 made
    inf - inf = NaN in the integral, and the next command was NaN."""
    gains = PIDGains(1.78e8, 0.0, 1e6)
    pid = PID(PIDConfig(gains, 0.0, 150.0, slew_v_per_s=100.0), initial_output_v=75.0)
    pid.engage(1e300, 75.0)
    with pytest.raises(OverflowError, match="overflowed"):
        pid.update(1e-6, 0.1)
    assert pid.output_v == 75.0
    pid.engage(1e-6, 75.0)  # a sane measurement re-seeds it: finite commands again
    assert math.isfinite(pid.update(1.1e-6, 0.1).command_v)
