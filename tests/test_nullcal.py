"""Thresholds calibrated on null data: the tail estimate, the null logs it simulates on a
log's own schedule, and the CLI's calibration and cache."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from leveler.analysis import nullcal, predict
from leveler.analysis.predict import excitation_v, load_measured
from leveler.analysis.synthetic import make_measured
from leveler.cli.main import main
from leveler.loop import kernel as kn
from leveler.settings import load_config

REPO = Path(__file__).resolve().parents[1]


def test_the_tail_beyond_the_runs_is_extrapolated_to_the_right_quantile() -> None:
    """Exponential null statistics (as a likelihood ratio's tail is): from 50 runs the
    1-in-800 level, ln 800 = 6.7, comes out right on average and within 40 % nearly
    always; a naive maximum of 50 would be ln 50 = 3.9."""
    rng = np.random.default_rng(5)
    alpha = 0.01 / 8
    got = np.array([nullcal.tail_threshold(list(rng.exponential(1.0, 50)), alpha)
                    for _ in range(400)])
    truth = math.log(1 / alpha)
    assert abs(np.mean(got) / truth - 1) < 0.1
    assert np.mean(np.abs(got / truth - 1) < 0.4) > 0.85


def test_within_the_runs_the_threshold_is_the_empirical_quantile() -> None:
    values = list(np.arange(100.0))
    assert nullcal.tail_threshold(values, 0.5) == pytest.approx(np.quantile(values, 0.5))
    assert nullcal.tail_threshold([], 0.01) == math.inf


def test_thresholds_rise_with_what_the_nulls_find() -> None:
    rng = np.random.default_rng(6)
    stats = {"quiet": [0.0] * 30, "busy": list(20.0 + 5.0 * rng.exponential(1.0, 30))}
    cal = nullcal.from_statistics(stats, 0.01, "k", 1.0)
    assert cal.thresholds["quiet"] == 0.0  # the penalty then stands: see diagnose
    assert cal.thresholds["busy"] > max(stats["busy"])  # 1 in 200 per family, 30 runs
    assert cal.runs == 30
    assert "30 null runs" in cal.describe()


@pytest.fixture(scope="module")
def modulated_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg, text = load_config(REPO / "config" / "sim.toml")
    log = tmp_path_factory.mktemp("nullcal") / "mod.mcap"
    make_measured(log, cfg, text, None, duration_s=2400.0, seed=3, dither_v=4.0,
                  dither_period_s=90.0)
    return log


def test_a_null_run_follows_the_logs_schedule_and_modulation(modulated_log: Path) -> None:
    meas = load_measured(modulated_log)
    a, b, again = (nullcal.simulate_null(meas, s) for s in (1, 2, 1))
    assert len(a.y_m) == len(meas.y_m)
    # the same modulation drives the piezo; the readings are a new draw of the model
    assert np.std(excitation_v(a) - excitation_v(meas)) < 1e-6 * np.std(excitation_v(meas))
    assert np.array_equal(a.y_m, again.y_m) and not np.array_equal(a.y_m, b.y_m)
    assert 0.3 < np.std(a.y_m) / np.std(meas.y_m) < 3.0
    assert (a.sig.temperature_k is None) == (meas.sig.temperature_k is None)
    # what the plate thermometer reads, its noise included, as the daemon logs it: the
    # plate's own temperature moves by ~0.2 mK a sample, the noise by 1 mK
    noise_k = meas.config.plant.thermal.thermometer_noise_k
    assert a.sig.temperature_k is not None and noise_k > 0
    scatter_k = float(np.std(np.diff(a.sig.temperature_k))) / math.sqrt(2)
    assert scatter_k == pytest.approx(noise_k, rel=0.2)


KERNELS = ["python", pytest.param("auto", marks=pytest.mark.skipif(
    kn.compiled() is None, reason="numba not installed"))]


def _count_kernel_samples(monkeypatch: pytest.MonkeyPatch, kernel: str, compiled: str,
                          interpreted: str) -> list[int]:
    """Wrap the kernel function `kernel` selects ("auto": the compiled one that the factory
    `compiled` returns; "python": `interpreted`): the list gets each call's sample count."""
    ran: list[int] = []
    fn = getattr(kn, compiled)() if kernel == "auto" else getattr(kn, interpreted)

    def counted(*args: object) -> tuple[int, int]:
        out = fn(*args)
        ran.append(out[0])
        return out

    if kernel == "auto":
        monkeypatch.setattr(kn, compiled, lambda: counted)
    else:
        monkeypatch.setattr(kn, interpreted, counted)
    return ran


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("schedule", ["closed, dithered", "open third, then closed",
                                      "open, no controller", "oversampled"])
def test_the_kernel_simulates_a_null_log_as_the_objects_do(
        modulated_log: Path, schedule: str, kernel: str, monkeypatch: pytest.MonkeyPatch
        ) -> None:
    """The uneventful samples in `leveler.loop.kernel` (compiled or interpreted), the rest
    by the objects: the same null log to the bit as the objects' alone, on each schedule
    a log has (an open modulated third, then the loop closed with its excitation; no
    controller at all), across the disturbances' blocks; the kernel ran most of it
    where it can, none of it where it cannot (an oversampling ADC)."""
    meas = load_measured(modulated_log)
    n = len(meas.y_m)
    if schedule == "open third, then closed":
        assert meas.engaged is not None
        meas = dataclasses.replace(meas, engaged=np.arange(n) >= n // 3)
    elif schedule == "open, no controller":
        meas = dataclasses.replace(meas, controller=None)
    elif schedule == "oversampled":
        plant = meas.config.plant
        meas = dataclasses.replace(meas, config=dataclasses.replace(
            meas.config, plant=dataclasses.replace(plant, sensor=dataclasses.replace(
                plant.sensor, samples_per_cycle=4))))
    ran = _count_kernel_samples(monkeypatch, kernel, "compiled", "cycles")
    ref = nullcal.simulate_null(meas, 4, kernel="off")
    assert not ran
    got = nullcal.simulate_null(meas, 4, kernel=kernel)
    assert np.array_equal(got.y_m, ref.y_m)
    assert np.array_equal(got.u_v, ref.u_v)
    assert got.sig.temperature_k is not None
    assert np.array_equal(got.sig.temperature_k, ref.sig.temperature_k)
    if schedule == "oversampled":
        assert not ran
    else:
        assert sum(ran) > 0.9 * n
    if schedule == "open, no controller":  # the logged voltage, slewed, is what drove it
        assert np.max(np.abs(got.u_v - meas.u_v)) < 1e-9
    with pytest.raises(ValueError, match="kernel must be"):
        nullcal.simulate_null(meas, 4, kernel="fast")


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # interpreted
@pytest.mark.parametrize("schedule", ["closed, dithered", "closed twice", "resonant terms",
                                      "a notch", "an overflow"])
def test_the_kernel_replays_the_controller_as_the_objects_do(
        modulated_log: Path, schedule: str, kernel: str, monkeypatch: pytest.MonkeyPatch
        ) -> None:
    """`excitation_v`'s replay of the logged controller by `kernel.replay` after each
    engage: the same excitation to the bit as the `PID` object's alone, the loop closed
    once or twice, with resonant terms; the objects alone where the kernel cannot run the
    PID (a notch), and where the PID raises (an overflow), raising as they do."""
    meas = load_measured(modulated_log)
    n = len(meas.y_m)
    c = meas.controller
    assert c is not None and meas.engaged is not None
    if schedule == "closed twice":
        meas = dataclasses.replace(meas, engaged=(np.arange(n) % (n // 2)) >= n // 6)
    elif schedule in ("resonant terms", "a notch"):
        c = dataclasses.replace(c, periodic_period_s=300.0, periodic_gains_v_per_m_s=(2e3, 1e3),
                                periodic_phases_rad=(0.3, -0.2)) if schedule != "a notch" \
            else dataclasses.replace(c, notch_frequency_hz=0.7)
        meas = dataclasses.replace(meas, controller=c)
    elif schedule == "an overflow":
        y = meas.y_m.copy()
        y[n - 5] = 1e308
        meas = dataclasses.replace(meas, y_m=y)
    ran = _count_kernel_samples(monkeypatch, kernel, "compiled_replay", "replay")
    if schedule == "an overflow":
        for k in ("off", kernel):
            with pytest.raises(OverflowError):
                predict._excitation_v(meas, kernel=k)
        assert ran and sum(ran) > 0.5 * n  # the kernel ran up to it, then the objects
        return
    ref = predict._excitation_v(meas, kernel="off")
    assert ref is not None and not ran
    got = predict._excitation_v(meas, kernel=kernel)
    assert got is not None and np.array_equal(got, ref)
    closed = int(np.count_nonzero(meas.engaged))
    if schedule == "a notch":
        assert not ran
    else:
        engages = int(np.count_nonzero(np.diff(np.asarray(meas.engaged, np.int8)) == 1)
                      + bool(meas.engaged[0]))
        assert sum(ran) == closed - engages  # all but each engage's first sample
    assert np.std(ref[np.asarray(meas.engaged)]) > 0  # a dither to be found
    with pytest.raises(ValueError, match="kernel must be"):
        predict._excitation_v(meas, kernel="fast")


def test_forked_workers_calibrate_as_one_process_does(modulated_log: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The workers read the log from the fork (not pickled to each run) and keep its
    excitation, read once before it; the statistics are the same runs' either way."""
    meas = load_measured(modulated_log)
    replays = []
    real = predict._excitation_v
    monkeypatch.setattr(predict, "_excitation_v", lambda m: replays.append(m) or real(m))
    forked = nullcal.calibrate(meas, 2, jobs=2, key="k")
    assert replays == [meas]  # once, here; each worker kept it
    alone = nullcal.calibrate(meas, 2, jobs=1, key="k")
    assert forked.runs == alone.runs == 2
    assert ({k: sorted(v) for k, v in forked.statistics.items()}
            == {k: sorted(v) for k, v in alone.statistics.items()})
    assert forked.thresholds == alone.thresholds


def test_the_excitation_of_the_last_two_logs_is_kept(modulated_log: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A null calibration's worker asks about the log and its own null run in turn."""
    a, b, c = (load_measured(modulated_log) for _ in range(3))
    replays = []
    real = predict._excitation_v
    monkeypatch.setattr(predict, "_excitation_v", lambda m: replays.append(m) or real(m))
    for m in (a, b, a, b, c, b, a):
        assert excitation_v(m) is excitation_v(m)
    assert [next(i for i, x in enumerate((a, b, c)) if x is m) for m in replays] == [0, 1, 2, 0]


def test_a_drawn_stand_stays_within_its_stated_tolerances() -> None:
    cfg, _ = load_config(REPO / "config" / "sim.toml")
    p, u = cfg.plant, cfg.plant.uncertainty
    rng = np.random.default_rng(0)
    arms = [nullcal.draw_plant(p, rng).pendulum.sensor_arm_m / p.pendulum.sensor_arm_m - 1
            for _ in range(300)]
    assert np.std(arms) == pytest.approx(u.sensor_path_rel, rel=0.2)
    assert max(np.abs(arms)) <= 3 * u.sensor_path_rel + 1e-12


def test_cli_calibrates_caches_and_reuses(modulated_log: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = ["--model-out", str(tmp_path / "fitted.toml"), "--json"]
    assert main(["diagnose", str(modulated_log), "--null-runs", "2", "--jobs", "1", *out]) == 0
    got = capsys.readouterr()
    first = json.loads(got.out)["thresholds"]
    assert first["source"] == "null calibration" and first["runs"] == 2
    # how long it took and where it went; no bar on a pipe (tests/test_progress.py)
    assert "null calibration of 2 runs in" in got.err and "2/2" not in got.err
    assert nullcal.cache_path(first["key"]).exists()
    assert set(first["by_family"]) >= {"periodic_disturbance", "actuator_delay"}
    assert all(v >= 0 for v in first["by_family"].values())

    assert main(["diagnose", str(modulated_log), *out]) == 0  # the cache, no new runs
    got = capsys.readouterr()
    assert json.loads(got.out)["thresholds"] == first
    assert "null calibration" not in got.err
    # its dither is a square: a hysteresis would hardly show, and it says so
    assert "square modulation" in json.loads(got.out)["unseen"]["actuator_hysteresis"]
    cands = json.loads(got.out)["candidates"]
    scored = [c for c in cands if c["penalty"] > 0]
    assert scored and all(c["threshold"] == max(c["penalty"], first["by_family"][c["name"]])
                          for c in scored)


def test_cli_says_when_thresholds_are_not_calibrated(modulated_log: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("LEVELER_CACHE_DIR", str(tmp_path / "empty-cache"))
    assert main(["diagnose", str(modulated_log), "--model-out",
                 str(tmp_path / "f.toml")]) == 0
    assert "not calibrated on null data (--null-runs 50" in capsys.readouterr().out
    assert main(["diagnose", str(modulated_log), "--null-runs", "-1"]) == 2
    assert "--null-runs -1" in capsys.readouterr().err
