"""The simulated plant against the paper's equations and python-control."""

from __future__ import annotations

import dataclasses
import itertools
import math

import control
import numpy as np
import pytest

from leveler.analysis.predict import slewed
from leveler.sim.params import PendulumParams, PlantParams, SensorParams
from leveler.sim.pendulum import PendulumModel, equilibrium_angle
from leveler.sim.plant import Plant, slew_lag_v
from leveler.typed_config import ConfigError, build


def paper_pendulum(**kw: object) -> PendulumParams:
    """k = 0.1 N m/rad and m g L_cm = 0.09 N m/rad exactly (the paper's example)."""
    base = {"mass_kg": 0.1, "com_length_m": 0.09 / (0.1 * 9.80665)}
    base.update(kw)
    return PendulumParams(**base)  # type: ignore[arg-type]


def test_amplification_is_the_papers_nine() -> None:
    p = paper_pendulum()
    assert p.amplification == pytest.approx(9.0, rel=1e-9)


@pytest.mark.parametrize("phi", [1e-9, 1e-7, 1e-6, 2e-5])
def test_small_angle_equilibrium_matches_n_within_1_percent(phi: float) -> None:
    p = paper_pendulum()
    theta = equilibrium_angle(p, phi)
    assert theta / phi == pytest.approx(p.amplification, rel=0.01)


def test_nonlinear_equilibrium_solves_the_transcendental_equation() -> None:
    p = paper_pendulum()
    phi = 1e-3  # the paper's reference tilt for the counterweight sweep
    theta = equilibrium_angle(p, phi)
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad
    assert mgl * math.sin(theta + phi) == pytest.approx(k * theta, rel=1e-12)
    # At 1 mrad the sin() curvature already shows: a little below the small-angle N.
    assert 0.99 * p.amplification < theta / phi < p.amplification


def test_nonlinear_dynamics_settle_at_the_root_solve() -> None:
    p = paper_pendulum(model="nonlinear", damping_nms_per_rad=2e-3)
    model = PendulumModel(p, dt_s=0.01)
    phi = 5e-3
    for _ in range(20000):
        model.step(phi)
    assert model.theta == pytest.approx(equilibrium_angle(p, phi), rel=1e-6)


def test_linear_and_nonlinear_agree_at_micro_radians() -> None:
    lin = PendulumModel(paper_pendulum(), 0.1)
    nl = PendulumModel(paper_pendulum(model="nonlinear"), 0.1)
    phis = 1e-6 * np.sin(np.arange(2000) * 0.05)
    a, b = [], []
    for phi in phis:
        a.append(lin.step(float(phi)))
        b.append(nl.step(float(phi)))
    assert np.max(np.abs(np.subtract(a, b))) < 2e-3 * np.max(np.abs(a))


def test_refuses_a_pendulum_with_no_stable_equilibrium() -> None:
    with pytest.raises(ConfigError, match="no stable equilibrium") as err:
        build(PlantParams, {"pendulum": {"mass_kg": 0.3}}, "plant")
    assert "plant.pendulum" in str(err.value)
    assert "m g L_cm" in str(err.value)


def full_tf(p: PendulumParams) -> control.TransferFunction:
    """theta/phi = (m g L - J s^2) / (J s^2 + c s + k - m g L), written out from PHYSICS.md."""
    j, c = p.inertia_kgm2, p.damping_nms_per_rad
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad
    return control.tf([-j, 0.0, mgl], [j, c, k - mgl])


@pytest.mark.parametrize("com_length_m", [0.0496, -0.02])
def test_linear_step_response_matches_the_full_equation(com_length_m: float) -> None:
    """A tilt step: the reading first jumps by -phi (the pendulum's inertia holds its absolute
    angle while the platform turns under it), then rings to the static response."""
    p = PendulumParams(com_length_m=com_length_m)
    dt, n, phi = 0.1, 600, 1e-6
    t = np.arange(n) * dt
    expected = phi * np.squeeze(control.step_response(full_tf(p), T=t).outputs)
    model = PendulumModel(p, dt)
    got = [0.0] + [model.step(phi) for _ in range(n - 1)]  # read before each step's tilt
    assert expected[0] == pytest.approx(-phi)
    np.testing.assert_allclose(got[1:], expected[1:], rtol=1e-6,
                               atol=1e-6 * phi * abs(p.amplification))
    assert control.dcgain(full_tf(p)) == pytest.approx(p.amplification, rel=1e-9)


def test_forced_response_with_random_tilt_matches_python_control() -> None:
    """Against python-control's ZOH of the full equation: its output at step n includes the
    direct term of that step's tilt, which the reading taken before the tilt moved does not."""
    p = PendulumParams()
    dt = 0.1
    sys_d = control.c2d(control.ss(full_tf(p)), dt, method="zoh")
    rng = np.random.default_rng(3)
    u = 1e-7 * rng.standard_normal(500)
    post = np.squeeze(control.forced_response(sys_d, U=u).outputs)
    model = PendulumModel(p, dt)
    got = [0.0] + [model.step(float(val)) for val in u[:-1]]
    np.testing.assert_allclose(got, post + u - np.concatenate([[0.0], u[:-1]]),
                               rtol=1e-9, atol=1e-18)


def _sine_gain(p: PendulumParams, f_hz: float, dt_s: float = 1e-3) -> complex:
    """theta/phi at f from the stepped model driven by a sine, one lock-in over whole cycles.
    The tilt held over each step lags it by dt / 2: 1 ms keeps that below 1 % at 1.4 Hz."""
    model = PendulumModel(p, dt_s)
    cycles = 20
    n = round(cycles / (f_hz * dt_s))
    t = np.arange(2 * n) * dt_s
    phi = 1e-6 * np.sin(2 * np.pi * f_hz * t)
    th = np.array([model.step(float(v)) for v in phi])[n:]  # second half: transients gone
    ref = np.exp(-2j * np.pi * f_hz * (t[n:] + dt_s))  # theta after step m is at t_(m+1)
    return complex(2 * np.mean(th * ref) / 1e-6 / -1j)


def test_a_hanging_pendulum_has_its_zero_at_m_g_d_over_j() -> None:
    """A beam balance 20 mm below its pivot: static response -m g d / (k + m g d), a notch at
    omega_z^2 = m g d / J, and the inertial limit -1 well above the resonance."""
    p = PendulumParams(com_length_m=-0.02, damping_nms_per_rad=5e-3)
    mgd = -p.gravity_stiffness_nm_per_rad
    k = p.flexure_stiffness_nm_per_rad
    assert p.amplification == pytest.approx(-mgd / (k + mgd))
    f_z = p.zero_frequency_hz
    assert f_z == pytest.approx(math.sqrt(mgd / p.inertia_kgm2) / (2 * math.pi))
    g_dc, g_z = _sine_gain(p, f_z / 20), _sine_gain(p, f_z)
    g_hi = _sine_gain(p, 12 * p.natural_frequency_hz)
    assert abs(g_dc) == pytest.approx(abs(p.amplification), rel=0.02)
    assert abs(g_z) < 0.05 * abs(g_dc)
    assert g_hi.real == pytest.approx(-1.0, abs=0.03)
    for f in (f_z / 3, f_z, 3 * f_z):  # the hold's lag, omega dt / 2, is 1.3 % at 3 f_z
        want = complex(full_tf(p)(2j * np.pi * f))
        assert abs(_sine_gain(p, f) - want) < 0.02 * abs(p.amplification) + 0.03 * abs(want)


def test_hanging_nonlinear_equilibrium_and_dynamics() -> None:
    p = PendulumParams(com_length_m=-0.02, model="nonlinear", damping_nms_per_rad=5e-3)
    phi = 2e-3
    theta = equilibrium_angle(p, phi)
    assert p.gravity_stiffness_nm_per_rad * math.sin(theta + phi) == pytest.approx(
        p.flexure_stiffness_nm_per_rad * theta, rel=1e-12)
    model = PendulumModel(p, 0.01)
    for _ in range(30000):
        model.step(phi)
    assert model.theta == pytest.approx(theta, rel=1e-6)


def test_a_centre_of_mass_on_the_pivot_is_refused_saying_why() -> None:
    with pytest.raises(ConfigError, match="com_length_m = 0") as err:
        build(PlantParams, {"pendulum": {"com_length_m": 0.0}}, "plant")
    assert "hanging" in str(err.value) and "inverted" in str(err.value)


def test_the_default_stand_keeps_its_figures() -> None:
    """The platform-rotation term changes no figure of the default stand: N, f_r, Q."""
    p = PendulumParams()
    assert p.amplification == pytest.approx(8.9858, rel=1e-4)
    assert p.natural_frequency_hz == pytest.approx(0.7120, rel=1e-3)
    assert p.zero_frequency_hz == pytest.approx(2.1345, rel=1e-3)
    w0 = 2 * math.pi * p.natural_frequency_hz
    assert p.inertia_kgm2 * w0 / p.damping_nms_per_rad == pytest.approx(18.64, rel=1e-3)


def test_piezo_is_clamped_and_slew_limited() -> None:
    plant = Plant(PlantParams(), dt_s=0.1)
    pz = plant.params.piezo
    assert plant.command(1000.0) == pytest.approx(pz.ref_v + pz.slew_v_per_s * 0.1)
    for _ in range(100):
        plant.command(1000.0)
        plant.step()
    assert plant.v_applied == pz.max_v
    plant.command(-5.0)
    plant.step()
    assert plant.v_applied == pytest.approx(pz.max_v - pz.slew_v_per_s * 0.1)


QUIET = {
    "thermal": {"random_walk_k_per_sqrt_s": 0.0, "daily_amplitude_k": 0.0},
    "cooler": {"peak_to_peak_rad": 0.0},
    "sensor": {"noise_m_per_rthz": 0.0, "drift_m_per_sqrt_s": 0.0},
}


def test_piezo_tilt_is_stroke_over_spacing() -> None:
    plant = Plant(build(PlantParams, QUIET), dt_s=0.1)
    t0 = plant.tilt_rad()
    plant.command(plant.v_applied + 5.0)
    plant.step()
    pz = plant.params.piezo
    assert plant.tilt_rad() - t0 == pytest.approx(
        5.0 * pz.gain_m_per_v / plant.params.platform.support_spacing_m, rel=1e-6)


def test_adc_quantizes_and_rails() -> None:
    se = SensorParams()
    params = PlantParams(sensor=se)
    plant = Plant(params, 0.1)
    counts, value, railed = plant.measure()
    assert not railed
    assert value == pytest.approx((counts * se.lsb_v + se.adc_min_v) / se.gain_v_per_m)
    assert se.lsb_m == pytest.approx(20.0 / 65535 / 2e5)  # 1.53 nm per count
    tilted = Plant(build(PlantParams, {"platform": {"initial_tilt_rad": 1e-3}}), 0.1)
    counts, _, railed = tilted.measure()
    assert railed and counts == 2**16 - 1


def test_cooler_shows_10_to_15_nm_at_the_pendulum_end() -> None:
    quiet = build(PlantParams, {
        "thermal": {"random_walk_k_per_sqrt_s": 0.0, "daily_amplitude_k": 0.0},
        "sensor": {"noise_m_per_rthz": 0.0, "drift_m_per_sqrt_s": 0.0, "adc_bits": 32},
    })
    plant = Plant(quiet, 0.1)
    xs = []
    for _ in range(round(3 * quiet.cooler.period_s / 0.1)):
        xs.append(plant.measure()[1])
        plant.step()
    settled = np.array(xs[len(xs) // 3:])
    assert 10e-9 <= settled.max() - settled.min() <= 15e-9


def test_same_seed_same_realization_other_seed_differs() -> None:
    def trace(seed: int) -> list[float]:
        plant = Plant(PlantParams(), 0.1, seed)
        out = []
        for _ in range(20000):
            out.append(plant.measure()[1])
            plant.step()
        return out

    assert trace(5) == trace(5)
    assert trace(5) != trace(6)


@pytest.mark.parametrize("resolution_k", [0.0, 1e-3])
def test_a_thermometer_series_reads_as_its_readings_one_by_one(resolution_k: float) -> None:
    """A null log's thermometer read at once: the same draws, the same rounding, across
    the blocks its noise is drawn in, after readings one at a time have begun a block."""
    params = PlantParams()
    params = dataclasses.replace(params, thermal=dataclasses.replace(
        params.thermal, thermometer_resolution_k=resolution_k))
    one, many = Plant(params, 0.1, 8), Plant(params, 0.1, 8)
    plate, by_one = [], []
    for i in range(10_000):
        if i < 100:  # both read the first 100 one at a time
            assert one.thermometer_k() == many.thermometer_k()
            many.step()
        else:
            plate.append(one.plate_temperature_k())
            by_one.append(one.thermometer_k())
        one.step()
    got = many.thermometer_series_k(np.array(plate))
    assert np.array_equal(got, by_one)
    assert np.std(np.diff(by_one)) > 0  # noise, not a constant


def test_a_slewing_piezo_lags_by_its_ramps_mean_and_the_pendulum_follows_the_ramp() -> None:
    """The amplifier slews continuously: 5 V at 100 V/s takes half of a 0.1 s step, and its
    mean over the step is 1.25 V short of the new voltage (what a resonance is driven
    by); a full step's worth of slew is felt at half. Replay does the same with a log's
    commands, and a command beyond one step's slew (a log of other origin) leaves the
    piezo on its way. The pendulum follows the ramp itself: after one step, and after the
    two steps a 15 V change takes, its state is the continuous equation's, integrated
    with the ramp (held at its mean instead, theta was 0.9 of a radian per radian off)."""
    from scipy.integrate import solve_ivp

    from leveler.sim.pendulum import linear_matrices

    assert slew_lag_v(5.0, 10.0) == pytest.approx(1.25)
    assert slew_lag_v(-10.0, 10.0) == pytest.approx(-5.0)
    v, lag = slewed(np.array([0.0, 0.0, 25.0, 25.0, 25.0]), 10.0)
    assert v.tolist() == [0.0, 0.0, 10.0, 20.0, 25.0]
    assert lag.tolist() == pytest.approx([0.0, 0.0, 5.0, 5.0, 1.25])
    # Steps beyond the slew among small ones, in both directions and back to back: the
    # same as the amplifier stepped sample by sample.
    rng = np.random.default_rng(11)
    u = np.cumsum(rng.normal(0.0, 1.0, 5000) * (1 + 30 * (rng.random(5000) < 0.02)))
    walked, prev = [], u[0]
    for target in u:
        prev += min(max(target - prev, -10.0), 10.0)
        walked.append(prev)
    assert slewed(u, 10.0)[0] == pytest.approx(np.array(walked), abs=1e-9)
    for dv, steps in ((5.0, 1), (15.0, 2)):
        plant = Plant(build(PlantParams, QUIET), dt_s=0.1)
        p = plant.params.pendulum
        a, b = linear_matrices(p)
        kv, slew = plant._tilt_per_v, plant.params.piezo.slew_v_per_s
        phi0, theta0 = plant.tilt_rad(), plant.pendulum.theta
        plant.command(plant.v_applied + dv)
        for _ in range(steps):
            plant.step()
        ramp_s = dv / slew

        def tilt(t: float, kv=kv, ramp_s=ramp_s, dv=dv, phi0=phi0, slew=slew
                 ) -> tuple[float, float]:
            return (phi0 + kv * dv * min(t / ramp_s, 1.0), kv * slew if t < ramp_s else 0.0)

        def rhs(t: float, y: np.ndarray, tilt=tilt, a=a, b=b) -> list[float]:  # absolute
            phi, rate = tilt(t)
            return [y[1], a[1, 0] * (y[0] - phi) + a[1, 1] * (y[1] - rate) + b[1, 0] * phi]

        y = np.array([theta0 + phi0, 0.0])
        for span in ((0.0, ramp_s), (ramp_s, 0.1 * steps)):
            y = solve_ivp(rhs, span, y, rtol=1e-12, atol=1e-18).y[:, -1]
        exact = (y[0] - tilt(0.1 * steps)[0], y[1])
        assert plant.pendulum.theta == pytest.approx(exact[0], rel=1e-8, abs=1e-15)
        assert plant.pendulum.omega == pytest.approx(exact[1], rel=1e-8, abs=1e-14)


@pytest.mark.parametrize("delay_s", [0.037, 0.08, 0.137])
def test_a_delayed_piezo_switches_within_its_step_and_slews_from_there(delay_s: float) -> None:
    """A transport delay moves each ramp, whole: a 5 V change (a 50 ms ramp) and then a
    15 V one (a full step's ramp and half of one) start `delay_s` after their steps', a
    ramp that passes a step's end finishes in the next. After each step the plant's
    pendulum is the continuous equation's, integrated with that delayed ramp, and replay
    steps the same. Held at the mean of the two samples a delay straddles, as it was, the
    piezo moved a fraction of a step early: an independent simulator's delays were fitted
    1.3-1.5 times too long under a square modulation."""
    from scipy.integrate import solve_ivp

    from leveler.sim.pendulum import delayed_slew, linear_matrices

    params = build(PlantParams, QUIET | {"effects": {"actuator_delay": {"delay_s": delay_s}}})
    plant = Plant(params, dt_s=0.1)
    p = params.pendulum
    a, b = linear_matrices(p)
    kv, slew = plant._tilt_per_v, params.piezo.slew_v_per_s
    phi0, theta0, v0 = plant.tilt_rad(), plant.pendulum.theta, plant.v_applied
    changes = [(0.0, 5.0), (0.3, 15.0)]  # (when the command changes [s], by how much [V])
    ramps = []  # (start [s], end [s], start voltage): the piezo as it moves
    level = v0
    for t_s, dv in changes:
        start = t_s + delay_s
        ramps.append((start, start + dv / slew, level, dv))
        level += dv

    def tilt(t: float) -> tuple[float, float]:
        v, rate = v0, 0.0
        for t0, t1, _, dv in ramps:
            if t >= t1:
                v += dv
            elif t > t0:
                v += dv * (t - t0) / (t1 - t0)
                rate = dv / (t1 - t0)
        return phi0 + kv * (v - v0), kv * rate

    def rhs(t: float, y: np.ndarray) -> list[float]:  # absolute angle
        phi, rate = tilt(t)
        return [y[1], a[1, 0] * (y[0] - phi) + a[1, 1] * (y[1] - rate) + b[1, 0] * phi]

    y, t_prev = np.array([theta0 + phi0, 0.0]), 0.0
    commands = {round(t_s / 0.1): dv for t_s, dv in changes}
    target = v0
    for k in range(12):
        target += commands.get(k, 0.0)
        plant.command(target)
        plant.step()
        t_end = 0.1 * (k + 1)
        edges = sorted({t_prev, t_end, *(x for r in ramps for x in r[:2] if t_prev < x < t_end)})
        for lo, hi in itertools.pairwise(edges):
            y = solve_ivp(rhs, (lo, hi), y, rtol=1e-12, atol=1e-18).y[:, -1]
        t_prev = t_end
        exact = (y[0] - tilt(t_end)[0], y[1])
        assert plant.pendulum.theta == pytest.approx(exact[0], rel=1e-7, abs=1e-15), k
        assert plant.pendulum.omega == pytest.approx(exact[1], rel=1e-7, abs=1e-14), k
        assert plant.v_effective == pytest.approx(v0 + (tilt(t_end)[0] - phi0) / kv, abs=1e-9)
    # replay's vectorized form is the plant's, sample by sample
    v = np.array([v0] + [v0 + sum(dv for t_s, dv in changes if round(t_s / 0.1) <= k)
                         for k in range(12)])
    tau = np.minimum(np.abs(np.diff(slewed(v, slew * 0.1)[0], prepend=v0)) / slew, 0.1)
    ends = delayed_slew(p, 0.1, slewed(v, slew * 0.1)[0], tau, delay_s)[0]
    assert ends[-1] == pytest.approx(plant.v_effective, abs=1e-12)


def test_a_mode_rung_by_its_own_noise_adds_band_noise_of_its_rms() -> None:
    """The same seed with and without the mode's noise: everything else is drawn alike, so
    the difference of the analog readings is the mode's noise alone: its rms as stated,
    its power at its frequency."""
    quiet = {"sensor": {"adc_bits": 32}}
    mode = {"frequency_hz": 2.0, "q": 20.0, "gain": 0.0, "noise_rms_m": 3e-9}
    plain = Plant(build(PlantParams, quiet), 0.1, seed=3)
    rung = Plant(build(PlantParams, quiet | {"effects": {"extra_resonance": mode}}), 0.1, seed=3)
    diff = []
    for _ in range(60_000):
        diff.append(rung.measure()[1] - plain.measure()[1])
        plain.step()
        rung.step()
    x = np.array(diff[1000:])
    assert np.std(x) == pytest.approx(3e-9, rel=0.1)
    p = np.abs(np.fft.rfft(x * np.hanning(len(x)))) ** 2
    f = np.fft.rfftfreq(len(x), 0.1)
    assert f[np.argmax(p)] == pytest.approx(2.0, rel=0.05)
    band = np.abs(f - 2.0) < 2.0 / 20.0
    assert np.sum(p[band]) > 0.5 * np.sum(p)  # most of its power within its half-power band


@pytest.mark.parametrize(("lag_s", "dt_s", "n"), [
    (600.0, 0.1, 20_000),  # the plate's thermal lag over several chunks of four lags
    (1e5, 0.001, 5_000),  # a lag far beyond the block: one chunk
    (0.02, 0.1, 300),  # a lag under a sample: a sample a chunk
    (2.0, 0.1, 1),
])
def test_the_thermal_lag_is_scipys_lfilter_with_its_state_carried(lag_s: float, dt_s: float,
                                                                   n: int) -> None:
    """The simulated plant's first-order lag (numpy alone, so a simulated stand does not
    import scipy.signal) is lfilter([1 - a], [1, -a]) to 1e-12 of the signal, split into
    two blocks with the state carried between them."""
    from scipy.signal import lfilter

    from leveler.sim.disturbance import first_order_lag

    a = math.exp(-dt_s / lag_s)
    x = 293.0 + 0.01 * np.cumsum(np.random.default_rng(1).standard_normal(n))
    want, z_want = lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    half = n // 2
    y1, z = first_order_lag(x[:half], a, a * x[0], lag_s / dt_s)
    y2, z = first_order_lag(x[half:], a, z, lag_s / dt_s)
    assert np.max(np.abs(np.r_[y1, y2] - want)) < 1e-12 * 293.0
    assert z == pytest.approx(z_want[0], rel=1e-13)


@pytest.mark.parametrize(("f_hz", "q"), [(1.5, 12.0), (3.3, 30.0), (0.8, 5.0)])
def test_a_modes_noise_energy_is_its_impulse_responses(f_hz: float, q: float) -> None:
    """Its output variance per unit white input, by Parseval, is the sum of its squared
    impulse response (lfilter's, long past its ringing)."""
    from scipy.signal import lfilter

    from leveler.sim.effects import ExtraResonance
    from leveler.sim.plant import impulse_energy

    b, a = ExtraResonance(frequency_hz=f_hz, q=q, gain=0.1, noise_rms_m=1e-9).discrete(0.1)
    h = lfilter(b, a, np.r_[1.0, np.zeros(200_000)])
    assert impulse_energy(b, a) == pytest.approx(float(np.sum(h**2)), rel=1e-12)
