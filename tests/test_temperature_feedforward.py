"""The temperature feedforward in the loop (issue 21, part 1): the thermometer as a driver,
the filter through the model's lags, bumpless switching, a failing thermometer, the log,
and what it does to the simulated stand's true tilt."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.signal import lfilter

from leveler.analysis import feedforward as ffa
from leveler.analysis.spectral import asd_at
from leveler.drivers.simulated_config import FaultSpec
from leveler.loop.feedforward import Feedforward, FeedforwardFilter, FeedforwardPath
from leveler.loop.pid import PID, ControllerConfig, PIDConfig, PIDGains
from leveler.settings import Config, ThermometerConfig, load_config
from leveler.sim.effects import TemperatureCoupling
from leveler.typed_config import ConfigError
from leveler.virtual import VirtualStand, run_virtual

from conftest import REPO  # isort: skip

LAB = load_config(REPO / "config" / "lab.toml")[0]


def _with_thermometer(cfg: Config, ff: Feedforward | None, interval_s: float = 1.0,
                      **sim: object) -> Config:
    cfg = dataclasses.replace(cfg, thermometer=ThermometerConfig("sim", interval_s),
                              sim=dataclasses.replace(cfg.sim, **sim))
    return cfg if ff is None else ffa.with_feedforward(cfg, ff, interval_s)


def test_filter_is_the_models_lag_through_each_path() -> None:
    """Fed every dt, each path is the first-order lags the simulated stand and the fitted
    coupling use (a held signal), times its gain, from zero at the first reading."""
    rng = np.random.default_rng(3)
    temp = 295 + np.cumsum(rng.standard_normal(5000)) * 1e-3
    dt = 0.5
    ff = Feedforward((FeedforwardPath(-50.0, 1800.0), FeedforwardPath(-25.0, 600.0, 60.0),
                      FeedforwardPath(3.0)))
    f = FeedforwardFilter(ff, resume_after_s=10.0)
    got = np.array([f.feed(i * dt, t) for i, t in enumerate(temp)])
    want = np.zeros_like(temp)
    for p in ff.paths:
        y = temp.copy()
        for lag in p.lags_s:
            a = math.exp(-dt / lag)
            y = lfilter([1 - a], [1, -a], y, zi=[a * temp[0]])[0]
        want += p.gain_v_per_k * (y - temp[0])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert got[0] == 0.0


def test_filter_holds_through_an_outage_and_goes_on_from_there() -> None:
    f = FeedforwardFilter(Feedforward((FeedforwardPath(-50.0, 100.0),)), resume_after_s=10.0)
    for i in range(200):
        f.feed(float(i), 295.0 + 0.01 * i)  # a ramp: the output moves
    held = f.v
    assert held < -1.0
    # 10 min without a reading, the temperature 0.5 K higher: no 25 V step, the lags
    # restart at the new reading from the held output
    assert f.feed(800.0, 297.5) == pytest.approx(held, abs=1e-12)
    f.feed(801.0, 297.5)
    assert f.v == pytest.approx(held, abs=1e-12)
    f.rezero()
    assert f.v == 0.0 and f.feed(802.0, 297.6) == pytest.approx(-50 * 0.1 * (1 - math.exp(
        -1 / 100)), rel=1e-9)


def _pid() -> PID:
    pid = PID(PIDConfig(PIDGains(1e5, 7e5, 0.0), 0.0, 150.0), initial_output_v=75.0)
    pid.engage(1e-9, 75.0)
    return pid


def test_pid_adds_the_feedforward_and_absorbs_it_bumplessly() -> None:
    pid, ref = _pid(), _pid()
    for k in range(5):
        a = pid.update(2e-9, 0.1, ff_v=0.3 * k)
        b = ref.update(2e-9, 0.1)
        assert a.command_v == pytest.approx(b.command_v + 0.3 * k, abs=1e-12)
    # switched off: what it added stays in the command, through the integral
    pid.absorb_feedforward()
    assert pid.update(2e-9, 0.1).command_v == pytest.approx(
        ref.update(2e-9, 0.1).command_v + 0.3 * 4, abs=1e-12)
    # a retune while a feedforward runs: the re-solved integral must not take it in too
    pid.update(2e-9, 0.1, ff_v=1.0)
    before = pid.output_v
    pid.set_gains(PIDGains(2e5, 7e5, 0.0))
    assert pid.update(2e-9, 0.1, ff_v=1.0).command_v == pytest.approx(before, abs=1e-3)


def _after_a_reading(vs: VirtualStand) -> None:
    """Step until the last cycle read the thermometer (the next nine will not, at 1 s)."""
    while True:
        vs.step()
        if vs.recorder.environments and vs.recorder.environments[-1].seq == vs.loop.seq - 1:
            return


def test_switching_the_feedforward_on_and_off_in_the_loop_is_bumpless() -> None:
    """Three stands on one seed: never a feedforward, one switched on, one switched on and
    later off. Switched on, it adds nothing at once (the same command as without); switched
    off between readings, the next command is the one it would have been with it on."""
    cfg = _with_thermometer(LAB, None)
    ff = Feedforward((FeedforwardPath(-5000.0, 30.0),))  # large and fast: a bump would show
    stands = [VirtualStand(cfg, seed=2, kernel="off") for _ in range(3)]
    for vs in stands:
        for _ in range(300):
            vs.step()
        vs.loop.engage(vs.t_s)
        _after_a_reading(vs)
    for vs in stands[1:]:
        vs.loop.set_feedforward(ff)
    first = [vs.step().command_v for vs in stands]
    assert first[1] == first[0] == first[2]
    for vs in stands:
        for _ in range(1200):
            vs.step()
        _after_a_reading(vs)
    assert abs(stands[1].loop.ff.v) > 0.1, stands[1].loop.ff.v  # it is doing something
    assert abs(stands[1].loop.last.command_v - stands[0].loop.last.command_v) > 0.1
    stands[2].loop.set_feedforward(None)
    on, off = stands[1].step().command_v, stands[2].step().command_v
    assert off == pytest.approx(on, abs=1e-9)
    for vs in stands:
        vs.__exit__()


def test_engaging_with_a_feedforward_configured_is_bumpless() -> None:
    """The filter runs while idle; an engage zeroes it, so the first command is the one
    without a feedforward, and it adds only what the temperature does from then on."""
    ff = Feedforward((FeedforwardPath(-5000.0, 30.0),))
    plain, fed = (VirtualStand(c, seed=3, kernel="off") for c in (
        _with_thermometer(LAB, None), _with_thermometer(LAB, ff)))
    for vs in (plain, fed):
        for _ in range(1200):
            vs.step()
        _after_a_reading(vs)  # the first engaged cycle reads no temperature
    assert abs(fed.loop.ff.v) > 0.1  # idle, it followed the temperature
    for vs in (plain, fed):
        vs.loop.engage(vs.t_s)
    assert fed.step().command_v == plain.step().command_v
    for vs in (plain, fed):
        vs.__exit__()


def test_a_failing_thermometer_holds_the_feedforward_and_never_faults_the_loop() -> None:
    ff = Feedforward((FeedforwardPath(-50.0, 60.0),))
    cfg = _with_thermometer(LAB, ff, faults=(FaultSpec("thermometer", at_s=200.0,
                                                       duration_s=120.0),))
    with VirtualStand(cfg, seed=4, kernel="off") as vs:
        vs.loop.engage(vs.t_s)
        for _ in range(int(600 * cfg.loop.rate_hz)):
            vs.step()
        env, events = vs.recorder.environments, vs.recorder.events
        assert vs.loop.state == "engaged" and vs.loop.thermometer_errors == 120
    t = np.array([e.t_s for e in env])
    temp = np.array([e.temperature_k for e in env])
    v = np.array([e.feedforward_v for e in env])
    out = (t >= 200.0) & (t < 320.0)
    assert np.isnan(temp[out]).all() and np.isfinite(temp[~out]).all()
    assert np.ptp(v[out]) == 0.0  # held
    i = np.flatnonzero(t >= 320.0)[0]
    assert abs(v[i] - v[i - 1]) < 1e-9  # resumed from where it was held
    said = [e.reason for e in events if e.kind == "thermometer"]
    assert len(said) == 3, said  # the first failure, one a minute later, the return
    assert said[0].startswith("thermometer read failed: injected thermometer fault")
    assert "readings again after 120.0 s" in said[-1]


def test_the_feedforward_brings_a_coupled_stand_to_the_sensor_floor() -> None:
    """The integral-only lab stand, its table tilting 10 urad/K through 1800 s and 5 urad/K
    through 600 s more: the designed feedforward through the simulated thermometer (1 mK
    noise) takes the true tilt at 0.5-2 mHz down to the perfect feedforward's."""
    coupled = dataclasses.replace(LAB, plant=dataclasses.replace(
        LAB.plant, effects=LAB.plant.effects.with_effect(TemperatureCoupling(
            tilt_per_kelvin_rad_per_k=5e-6, lag_s=600.0))))
    ff = ffa.design(coupled.plant)
    assert ff is not None and [p.gain_v_per_k for p in ff.paths] == pytest.approx([-50, -25])
    dur, f = 6 * 3600.0, [5e-4, 1e-3, 2e-3]
    b = ffa.bound(coupled, dur, seed=6, ff=ff)
    assert b.worth_it and b.suggested is not None
    i = [int(np.argmin(abs(b.freqs_hz - x))) for x in f]
    assert (b.current[i] / b.suggested[i] > 3).all(), b.current[i] / b.suggested[i]
    assert (b.suggested[i] < 1.15 * b.best[i]).all(), b.suggested[i] / b.best[i]


def test_reading_the_thermometer_changes_no_other_random_draw() -> None:
    a = run_virtual(LAB, 300.0, 7, engaged=True, kernel="off")
    b = run_virtual(_with_thermometer(LAB, None), 300.0, 7, engaged=True, kernel="off")
    np.testing.assert_array_equal(a.tilt_rad, b.tilt_rad)
    np.testing.assert_array_equal(a.applied_v, b.applied_v)


@pytest.mark.parametrize(("toml", "says"), [
    ("[controller]\nfeedforward_gains_v_per_k = [-50.0]\nfeedforward_lags_s = [1800.0]\n",
     "controller.feedforward_gains_v_per_k: a temperature feedforward needs a thermometer"),
    ("[controller]\nfeedforward_gains_v_per_k = [-50.0, 2.0]\nfeedforward_lags_s = [1800.0]\n"
     "[thermometer]\nbackend = \"sim\"\n", "feedforward_lags_s needs one lag [s] per gain"),
    ("[controller]\nfeedforward_gains_v_per_k = [-50.0]\nfeedforward_lags_s = [-1.0]\n"
     "[thermometer]\nbackend = \"sim\"\n", "feedforward_lags_s[0] must be finite and >= 0"),
    ("[thermometer]\nbackend = \"modbus\"\n", "needs a [thermometer.modbus] table"),
    ("[thermometer]\ninterval_s = 0\n", "thermometer.interval_s"),
])
def test_config_errors_name_the_key_and_the_file(tmp_path, toml: str, says: str) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value) and says in str(err.value), err.value


def test_a_simulated_thermometer_needs_the_simulated_stand() -> None:
    modbus = load_config(REPO / "config" / "lab-modbus.toml")[0]
    with pytest.raises(ValueError, match='"sim" reads the simulated plate'):
        dataclasses.replace(modbus, thermometer=ThermometerConfig("sim"))


def test_controller_config_round_trips_the_paths() -> None:
    c = ControllerConfig(feedforward_gains_v_per_k=(-50.0, 0.0, 2.0),
                         feedforward_lags_s=(1800.0, 5.0, 0.0))
    ff = c.feedforward()
    assert ff is not None and [p.gain_v_per_k for p in ff.paths] == [-50.0, 2.0]  # 0: no path
    assert ControllerConfig().feedforward() is None


def test_the_replay_what_if_feeds_the_logs_temperature_forward(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Replay's what-if of a logged run with the feedforward added (tune --suggest --model
    --log): fed the log's own thermometer, it takes the temperature's tilt out of the
    reading at the mHz; a log without a temperature is refused, naming it."""
    from leveler.analysis.predict import Predictor, load_measured
    from leveler.analysis.replay import what_if
    from leveler.log.writer import LogWriter

    coupled = dataclasses.replace(_with_thermometer(LAB, None), plant=dataclasses.replace(
        LAB.plant, effects=LAB.plant.effects.with_effect(TemperatureCoupling(
            tilt_per_kelvin_rad_per_k=5e-6, lag_s=600.0))))
    log = tmp_path / "coupled.mcap"
    text = (REPO / "config" / "lab.toml").read_text() + '\n[thermometer]\nbackend = "sim"\n'
    with LogWriter(log, truth=True, environment=True, metadata={"config": text}) as w:
        run_virtual(coupled, 4 * 3600.0, 5, engaged=True, writer=w)
    meas = load_measured(str(log), model=None)
    assert meas.sig.temperature_k is not None
    pred = Predictor(meas.config.plant, meas)
    ff = ffa.design(coupled.plant)
    assert ff is not None and meas.controller is not None
    with_ff = dataclasses.replace(meas.controller, **{k: tuple(v) for k, v in
                                                      ffa.values(ff).items()})
    f = [7e-4, 1e-3, 2e-3]
    span = slice(3000, None)
    logged = asd_at(meas.y_m[span], 10.0, f)
    replayed = asd_at(what_if(meas, pred, with_ff)[span], 10.0, f)
    assert (logged / replayed > 2).all(), logged / replayed
    as_is = asd_at(what_if(meas, pred, meas.controller)[span], 10.0, f)
    assert (abs(as_is / logged - 1) < 0.2).all(), as_is / logged  # the logged loop, replayed
    meas.sig = dataclasses.replace(meas.sig, temperature_k=None)
    with pytest.raises(ValueError, match="needs the log's temperature"):
        what_if(meas, pred, with_ff)
