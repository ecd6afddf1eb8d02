"""leveler replay: a simulated log replays against its own model down to the noise; the
what-if predicts what other gains really do; imported CSV data replays like the log it
came from; unusable logs get clear errors."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
from figure_capture import legend_texts, saved_figures

from leveler.analysis.predict import Predictor, load_measured
from leveler.analysis.replay import replay, what_if
from leveler.analysis.spectral import asd_at
from leveler.analysis.synthetic import make_measured
from leveler.cli.main import main
from leveler.log.reader import read_log
from leveler.settings import load_config

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def night(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four hours of quiet closed-loop leveling of the nominal plant."""
    cfg, text = load_config(REPO / "config" / "sim.toml")
    log = tmp_path_factory.mktemp("replay") / "night.mcap"
    make_measured(log, cfg, text, None, duration_s=4 * 3600, seed=8)
    return log


def test_own_model_leaves_only_sensor_noise(night: Path) -> None:
    meas = load_measured(night)
    result, _, _ = replay(meas)
    se = meas.config.plant.sensor
    floor = np.hypot(se.noise_m_per_rthz * np.sqrt(0.5 * 10.0), se.lsb_m / np.sqrt(12))
    assert result["rms_m"] < 1.2 * floor
    assert result["temperature_logged"]
    assert set(result["band_rms_m"]) == {"0.1-1 mHz", "1-10 mHz", "10-100 mHz", "0.1-1 Hz",
                                          "1 Hz-Nyquist"}
    # In closed loop the model explains what the sensor saw: most of it is noise, but
    # a model without the thermometer would leave the thermal tilt (checked next).
    assert result["variance_explained"] > 0.25  # 0.295 measured with the default gains


def test_without_the_temperature_the_thermal_tilt_is_unexplained(night: Path) -> None:
    meas = load_measured(night)
    full = replay(meas)[0]
    meas.sig = type(meas.sig)(meas.sig.t_s, meas.sig.dt_s, None)
    blind = replay(meas)[0]
    assert not blind["temperature_logged"]
    assert blind["band_rms_m"]["0.1-1 mHz"] > 10 * full["band_rms_m"]["0.1-1 mHz"]


def test_what_if_reruns_the_logged_controller_under_another_models_file(
        night: Path, tmp_path: Path) -> None:
    """Replayed against a --model file whose [controller] differs (a 1 mV/s slew, a 0.5 s
    derivative filter), the what-if with the logged gains still reproduces the log: the
    rest of the controller is the logged one."""
    text = (REPO / "config" / "sim.toml").read_text()
    other, n = re.subn(r"(?m)^slew_v_per_s = 10.0$", "slew_v_per_s = 0.001", text)
    other, m = re.subn(r"(?m)^d_filter_tau_s = .*$", "d_filter_tau_s = 0.5", other)
    assert n == m == 1
    (tmp_path / "other.toml").write_text(other)
    meas = load_measured(night, model=tmp_path / "other.toml")
    assert meas.config.controller.slew_v_per_s == 0.001
    same = what_if(meas, Predictor(meas.config.plant, meas), meas.gains)
    assert np.max(np.abs(same[3000:] - meas.y_m[3000:])) < 1e-12


def test_what_if_gains_predict_a_real_rerun(night: Path, tmp_path: Path) -> None:
    """A quarter of the integral and derivative gains: the what-if prediction from the logged
    run against an actual run of the same plant and disturbance realization with them."""
    meas = load_measured(night)
    pred = Predictor(meas.config.plant, meas)
    same = what_if(meas, pred, meas.gains)
    # The logged gains reproduce the log (once past the engage at the start).
    assert np.max(np.abs(same[3000:] - meas.y_m[3000:])) < 1e-12
    kp, ki, kd = meas.gains
    predicted = what_if(meas, pred, (kp, ki / 4, kd / 4))
    text = (REPO / "config" / "sim.toml").read_text()
    tuned, n = re.subn(r"(?m)^ki_v_per_m_s = .*$", f"ki_v_per_m_s = {ki / 4!r}", text)
    tuned, m = re.subn(r"(?m)^kd_v_s_per_m = .*$", f"kd_v_s_per_m = {kd / 4!r}", tuned)
    assert n == m == 1
    (tmp_path / "tuned.toml").write_text(tuned)
    cfg4, _ = load_config(tmp_path / "tuned.toml")
    make_measured(tmp_path / "rerun.mcap", cfg4, tuned, None, duration_s=4 * 3600, seed=8)
    actual = read_log(tmp_path / "rerun.mcap").samples["sensor_m"]
    skip = 3000
    for f in (1e-3, 1e-2):
        got = asd_at(predicted[skip:], 10.0, [f])[0]
        want = asd_at(actual[skip:], 10.0, [f])[0]
        before = asd_at(meas.y_m[skip:], 10.0, [f])[0]
        assert abs(got / want - 1) < 0.25, (f, got, want, before)
    # A quarter of the gain leaves about four times the in-loop residual at 1 mHz.
    assert asd_at(predicted[skip:], 10.0, [1e-3])[0] > 2 * asd_at(meas.y_m[skip:], 10.0,
                                                                  [1e-3])[0]


def test_cli_json_out_and_plot(night: Path, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str],
                               monkeypatch: pytest.MonkeyPatch) -> None:
    figures = saved_figures(monkeypatch)
    out, png = tmp_path / "replay.mcap", tmp_path / "replay.png"
    assert main(["replay", str(night), "--json", "--out", str(out), "--plot", str(png),
                 "--gains", "0,1.4e6,0"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["what_if"]["gains"]["ki_v_per_m_s"] == 1.4e6
    assert len(r["what_if"]["predicted_asd_m_rthz"]) == 3
    assert png.stat().st_size > 10_000
    # The figure names the log and the model, every axis its unit, the residual what it
    # is, and the dotted lines the report's band edges they are.
    [fig] = figures
    assert fig.get_suptitle() == "replay of night.mcap against the log's config"
    top, bottom = fig.axes
    assert [(ax.get_xlabel(), ax.get_ylabel()) for ax in (top, bottom)] == [
        ("time from the first sample [h]", "sensor reading [nm]"),
        ("frequency [Hz]", "ASD [m/√Hz]")]
    assert "residual = measured − model" in legend_texts(fig)
    # 4 h reach down to 0.1 mHz only with a few averages: its edge is named where it is
    # inside the spectra, and no edge beyond them stretches the axis
    f = bottom.get_lines()[0].get_xdata()
    edges = [(1e-4, "0.1 mHz"), (1e-3, "1 mHz"), (1e-2, "10 mHz"), (0.1, "0.1 Hz"),
             (1.0, "1 Hz")]
    assert [t.get_text() for t in bottom.texts] == [
        name for edge, name in edges if f[0] <= edge <= f[-1]]
    assert len(bottom.texts) >= 4

    from mcap.reader import make_reader

    with out.open("rb") as fh:
        msgs = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages()]
    assert len(msgs) == r["samples"]
    m = msgs[5000]
    assert m["residual_m"] == pytest.approx(m["measured_m"] - m["predicted_m"], abs=1e-18)
    assert main(["replay", str(night)]) == 0
    text = capsys.readouterr().out
    assert "residual RMS" in text and "1-10 mHz" in text


def test_plot_counts_hours_from_the_first_sample(night: Path, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """An imported log's clock is absolute (a logger's Unix time): the time axis counts from
    the first sample, as the report does, not from 1970."""
    from dataclasses import replace as with_

    from leveler.analysis.replay import plot_replay

    meas = load_measured(night)
    meas = with_(meas, sig=with_(meas.sig, t_s=meas.t_s + 1.7e9))
    _, pred, span = replay(meas)
    figures = saved_figures(monkeypatch)
    plot_replay(tmp_path / "r.png", meas, pred, span, "replay")
    hours = figures[0].axes[0].get_lines()[0].get_xdata()
    assert 0 <= hours[0] < 1 and hours[-1] == pytest.approx(4.0, abs=0.05)


def test_imported_csv_replays_like_the_log_it_came_from(night: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    data = read_log(night)
    s, t = data.samples, data.truth
    csv = tmp_path / "other.csv"
    rows = np.column_stack([s["t_s"], s["applied_v"], s["sensor_m"], t["temperature_k"]])
    np.savetxt(csv, rows, delimiter=",", fmt="%.17g",
               header="t_s,actuator_V,sensor_m,temperature_K", comments="")
    assert main(["import-csv", str(csv), "--out", str(tmp_path / "other.mcap")]) == 0
    capsys.readouterr()
    cfg = tmp_path / "model.toml"
    cfg.write_text((REPO / "config" / "sim.toml").read_text())
    direct = replay(load_measured(night))[0]
    imported = replay(load_measured(tmp_path / "other.mcap", cfg))[0]
    assert imported["temperature_logged"]
    assert imported["rms_m"] == pytest.approx(direct["rms_m"], rel=1e-6)


def test_unusable_logs_get_clear_errors(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    cfg, text = load_config(REPO / "config" / "sim.toml")
    short = tmp_path / "short.mcap"
    make_measured(short, cfg, text, None, duration_s=30.0, seed=1)
    assert main(["replay", str(short)]) == 2
    assert "replay needs at least 1000" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all" * 100)
    for cmd in ("replay", "diagnose"):
        assert main([cmd, str(junk)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"leveler {cmd}: error:") and "Traceback" not in err


def test_a_log_with_ticks_a_late_loop_skipped_replays(tmp_path: Path) -> None:
    """A real-time loop that wakes more than a period late skips the deadlines it missed
    (loop time jumps, seq does not): such a log replays, the skipped ticks put back with
    the reading interpolated and the voltage held, as the piezo held it (a running
    daemon's log at 100 Hz on a loaded machine was refused as "not uniformly spaced")."""
    from leveler.log.writer import LogWriter
    from leveler.virtual import VirtualStand

    cfg, text = load_config(REPO / "config" / "sim.toml")
    log = tmp_path / "late.mcap"
    with LogWriter(log, truth=True, metadata={"config": text}) as w, VirtualStand(
            cfg, 3, sinks=[w], kernel="off") as vs:
        vs.cycle()
        vs.loop.engage(vs.t_s)
        for n in range(3000):
            if n in (700, 1500, 1501):
                vs.tick()  # a deadline missed: its cycle never runs
            vs.step()
    samples = read_log(log).samples
    assert len(samples["seq"]) == 3001 and np.ptp(np.diff(samples["t_s"])) > 0.05
    meas = load_measured(log)
    assert len(meas.y_m) == 3004 and meas.bad_samples == 3
    np.testing.assert_allclose(np.diff(meas.t_s), 0.1, rtol=1e-9)
    i = 701  # the skipped tick's slot: the voltage of the cycle before it, held
    assert meas.u_v[i] == meas.u_v[i - 1] and np.isfinite(meas.y_m).all()
    assert main(["replay", str(log), "--json"]) == 0


def test_the_start_states_fit_as_a_direct_solve_does_and_keep_nanometre_shapes_on_a_day() -> None:
    """The start states' least squares by scaled normal equations equals a direct solve
    where that is well posed (3 h), and on a day keeps shapes of nanometres beside the
    offset: numpy's lstsq cuts singular values under eps x rows of the largest, and a
    column of ones over 864,000 samples sits 1e12 above them."""
    from leveler.analysis.predict import _StartStates

    rng = np.random.default_rng(3)
    for n in (108_000, 864_000):
        t = np.arange(n) * 0.1
        ring = np.exp(-t / 40.0)
        shapes = [1e-9 * np.exp(-t / 1800.0), 1e-9 * ring * np.cos(4.4 * t),
                  1e-9 * ring * np.sin(4.4 * t)]
        truth = 0.7 * shapes[0] - 2.0 * shapes[1] + 1.5 * shapes[2]
        r = 3e-9 + truth + 1e-10 * rng.standard_normal(n)
        fit = _StartStates(shapes).fit(r)
        np.testing.assert_allclose(fit - fit.mean(), truth - truth.mean(),
                                   atol=1e-2 * np.ptp(truth))
        if n == 108_000:
            a = np.column_stack([np.ones(n), *shapes])
            coef = np.linalg.lstsq(a, r, rcond=None)[0]
            np.testing.assert_allclose(fit, a[:, 1:] @ coef[1:], atol=1e-6 * np.ptp(truth))


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="numba not installed")
def test_the_compiled_slewed_pass_is_numpys_to_the_bit(night: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """`pend_slewed`'s one compiled pass (injections, lfilter's recursion, offset and arm)
    must give numpy's passes exactly: a replay is compared with others to 1e-12 of the
    noise, and which one ran must not decide a verdict. Steps of every size, so the
    slewing's injections are not zero."""
    from leveler import jit
    from leveler.analysis import predict

    meas = load_measured(night)
    pred = predict.Predictor(meas.config.plant, meas)
    rng = np.random.default_rng(7)
    n = len(meas.y_m)
    phi_end = pred.actuator_tilt(np.cumsum(rng.normal(0.0, 0.5, n)) * rng.integers(0, 2, n))
    phi = phi_end + 1e-7 * np.cumsum(rng.normal(size=n))
    assert pred._a[0] == 1.0 and len(pred._a) >= 2  # a filter it compiles
    compiled = pred.pend_slewed(phi, phi_end)
    assert jit.compiled(predict._slewed_pass) is not None  # it ran compiled
    monkeypatch.setattr(jit, "compiled", lambda fn: None)  # as without numba
    assert np.array_equal(compiled, pred.pend_slewed(phi, phi_end))
    assert np.ptp(compiled) > 0


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="numba not installed")
def test_the_compiled_ramp_gain_is_numpys_to_the_bit(night: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """`ramp_gain`'s Horner sums compiled must be numpy's passes exactly, for ramps of
    every length up to the step (zero ones included: a held voltage)."""
    from leveler import jit
    from leveler.sim import pendulum

    meas = load_measured(night)
    dt = meas.dt_s
    terms = pendulum.ramp_terms(meas.config.plant.pendulum, dt)
    tau = np.random.default_rng(3).uniform(0.0, dt, 20_000)
    tau[::3] = 0.0
    compiled = pendulum.ramp_gain(terms, tau)
    assert jit.compiled(pendulum._horner) is not None  # it ran compiled
    monkeypatch.setattr(jit, "compiled", lambda fn: None)  # as without numba
    assert np.array_equal(compiled, pendulum.ramp_gain(terms, tau))
    assert compiled.shape == (20_000, 2) and np.all(compiled[tau == 0] == 0)
    assert np.ptp(compiled[:, 0]) > 0 and np.ptp(compiled[:, 1]) > 0


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="numba not installed")
@pytest.mark.parametrize("delay_s", [0.037, 0.0999, 0.237])
def test_the_compiled_delayed_slew_is_numpys_to_the_bit(
        night: Path, monkeypatch: pytest.MonkeyPatch, delay_s: float) -> None:
    """`delayed_slew` compiled must be numpy's passes exactly: a night's commands with a
    square's edges laid over them, so that ramps pass the steps' ends (a fraction of a
    step late, and whole steps too)."""
    from leveler import jit
    from leveler.analysis.predict import slewed
    from leveler.sim import pendulum

    meas = load_measured(night)
    dt, p = meas.dt_s, meas.config.plant
    u = meas.u_v + 6.0 * np.sign(np.sin(2 * np.pi * meas.t_s / 64.0))
    v = slewed(u, p.piezo.slew_v_per_s * dt)[0]
    tau = np.minimum(np.abs(np.diff(v, prepend=v[:1])) / p.piezo.slew_v_per_s, dt)
    compiled = pendulum.delayed_slew(p.pendulum, dt, v, tau, delay_s)
    assert jit.compiled(pendulum._delayed_pass) is not None  # it ran compiled
    monkeypatch.setattr(jit, "compiled", lambda fn: None)  # as without numba
    plain = pendulum.delayed_slew(p.pendulum, dt, v, tau, delay_s)
    for a, b in ((compiled[0], plain[0]), (compiled[1], plain[1]),
                 (compiled[2][0], plain[2][0]), (compiled[2][1], plain[2][1])):
        assert np.array_equal(a, b)
        assert np.ptp(a) > 0
    assert np.count_nonzero(tau > dt - delay_s % dt) > 100  # ramps passed steps' ends


def test_a_predictor_set_up_from_memory_is_the_one_built_afresh(night: Path) -> None:
    """`Predictor` keeps the set-up its knobs do not touch (`predict._memo`); what it
    hands out for one set of numbers must be what a fresh build gives, whatever was
    built in between, and must change with the numbers it depends on."""
    import dataclasses

    from leveler.analysis import predict

    meas = load_measured(night)
    plant = meas.config.plant

    def built(lag_s: float, slew_v_per_s: float) -> Predictor:
        return Predictor(dataclasses.replace(
            plant, thermal=dataclasses.replace(plant.thermal, lag_s=lag_s),
            piezo=dataclasses.replace(plant.piezo, slew_v_per_s=slew_v_per_s)), meas)

    lag, slew = plant.thermal.lag_s, plant.piezo.slew_v_per_s
    first = built(lag, slew).base.y_m
    lagged = built(3 * lag, slew).base.y_m
    slow = built(lag, slew / 1e4).base.y_m  # a slew that holds back the PID's steps
    again = built(lag, slew).base.y_m
    predict._MEMO.clear()
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(built(lag, slew).base.y_m, first)
    for other in (lagged, slow):
        assert np.max(np.abs(other - first)) > 1e-10


def test_the_set_up_kept_longest_unused_is_dropped_first() -> None:
    """`predict._memo` keeps the last `_MEMO_SIZE` set-ups used, not the last made: a
    recalibration asks for the cooler's waveform every step, and for the pendulum's
    slewing terms anew at each resonance it tries."""
    from leveler.analysis import predict

    predict._MEMO.clear()
    log, made = np.zeros(3), []

    def get(i: int) -> np.ndarray:
        return predict._memo((log,), (i,), lambda: made.append(i) or np.full(3, float(i)))

    for i in range(predict._MEMO_SIZE):
        get(i)
    assert get(0)[0] == 0.0  # kept: now the most recently used
    get(99)  # drops 1, the least recently used
    get(0)
    get(1)
    assert made == [*range(predict._MEMO_SIZE), 99, 1]
    assert not get(99).flags.writeable  # handed out read-only
    predict._MEMO.clear()
