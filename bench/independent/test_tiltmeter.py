"""Checks of the independent tiltmeter generator's own physics and file format (not of leveler)."""

from __future__ import annotations

import csv
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bench.independent import tiltmeter as tm


def _seed_where(pred: Any, limit: int = 200) -> int:
    """First seed whose drawn setup satisfies pred (draws only, no simulation)."""
    for s in range(limit):
        if pred(tm.draw_setup(s)[0]):
            return s
    raise AssertionError("no seed found")


def _steady_state(p: tm.Pendulum, f: float, h: float = 0.25) -> complex:
    """theta/phi from a long noise-free run started at rest, fitted over its last 10 cycles.

    The run lasts >= 12 ring-down times, so the start transient is below 1e-5 of itself.
    """
    gamma = p.c / (2 * p.J)
    dur = max(30.0 / f, 12.0 / gamma)
    t = np.arange(int(dur / h) + 1) * h
    theta = tm.simulate_deflection(p, np.sin(2 * np.pi * f * t), h)
    keep = t >= t[-1] - 10.0 / f
    w = 2 * np.pi * f * t[keep]
    basis = np.column_stack([np.sin(w), np.cos(w), np.ones(w.size)])
    coef, *_ = np.linalg.lstsq(basis, theta[keep], rcond=None)
    # A piecewise-linear sine keeps its phase; its fundamental is scaled by sinc^2(w h / 2).
    return complex(coef[0], coef[1]) / np.sinc(f * h) ** 2


def test_parameter_ranges() -> None:
    for seed in range(60):
        s, _ = tm.draw_setup(seed)
        p, tr, sch = s.pendulum, s.true, s.schedule
        assert 0.01 <= p.J <= 0.2 and 0.2 <= p.m <= 5.0 and p.d > 0
        assert 2e-3 <= p.f_z <= 15e-3
        assert 0.3 <= p.k / p.mgd <= 3.0 and 5.0 <= p.Q <= 300.0
        assert p.f_0 > p.f_z
        for name, st in s.stated.items():
            u = (tr[name] - st["value"]) / st["sigma"]
            assert math.isclose(u, st["true_offset_in_sigma"], rel_tol=1e-9)
            if name in tm.OFFSET_1_TO_2_SIGMA:
                assert 1.0 <= abs(u) <= 2.0
            else:
                assert abs(u) <= 1.0
        for key in ("white_factor", "drift_walk_factor", "platform_walk_factor"):
            assert 0.75 <= s.noise[key] <= 0.9 or 1.1 <= s.noise[key] <= 1.25
        f = np.array([st["f_hz"] for st in sch["steps"]])
        assert 8 <= f.size <= 12
        assert np.all(np.diff(np.sort(f)) > 0)
        assert 0.2 <= f.min() / p.f_z <= 0.3 and 3.4 <= f.max() / p.f_z <= 4.6
        assert np.all(np.abs(f / 1e-5 - np.round(f / 1e-5)) > 1e-6)   # not on a 10 uHz grid
        for st in sch["steps"]:
            dur = st["t_end_s"] - st["t_start_s"]
            assert math.isclose(dur, max(15.0 / st["f_hz"], 2400.0), abs_tol=2e-3)
        gaps = [b["t_start_s"] - a["t_end_s"] for a, b in itertools.pairwise(sch["steps"])]
        assert all(120.0 <= g <= 360.0 for g in gaps)
        assert 0.0 < sch["bias_V"] - sch["amplitude_V"] and sch["bias_V"] + sch["amplitude_V"] < 150
        assert 20.0 <= sch["snr_dc_target"] <= 200.0
        assert 0.8 <= s.n_samples / tm.FS_HZ / 86400 <= 2.1


def test_zero_and_inertial_limit() -> None:
    s, _ = tm.draw_setup(_seed_where(lambda s: s.pendulum.Q > 100))
    p = s.pendulum
    at_zero = _steady_state(p, p.f_z)
    assert abs(at_zero) < 1e-3                       # no response at the zero
    high = _steady_state(p, 4 * p.f_z)
    assert -1.35 < high.real < -0.9 and abs(high.imag) < 0.1   # about -1: inertia holds psi
    assert abs(high - complex(p.tilt_response(4 * p.f_z))) < 0.01 * abs(high)
    # far above the resonance the inertial limit is reached
    assert abs(_steady_state(p, 40 * p.f_0, h=0.02) + 1.0) < 0.01


@pytest.mark.parametrize("kind", ["high_q", "low_q"])
def test_steady_state_matches_truth(kind: str) -> None:
    pred = (lambda s: s.pendulum.Q > 200) if kind == "high_q" else (lambda s: s.pendulum.Q < 15)
    rec = tm.generate(_seed_where(pred), clean=True)
    tr = rec.setup.true
    per_volt = tr["sensor_arm_m"] * tr["piezo_gain_m_per_V"] / tr["support_spacing_m"]
    for row in rec.truth["transfer_function"]:
        want = complex(row["re_m_per_V"], row["im_m_per_V"])
        got = per_volt * _steady_state(rec.setup.pendulum, row["f_hz"])
        assert abs(got - want) <= 0.01 * abs(want) + 1e-4 * per_volt, row["f_hz"]


def _fit_phasor(t: np.ndarray, y: np.ndarray, f: float, harmonics: int,
                ring: tuple[float, float] | None) -> complex:
    """Fundamental phasor of y (Re H e^{iwt} form) with odd harmonics, a constant, and optionally
    the pendulum's free ring-down (gamma, omega_d) so a step needs no settling time."""
    cols = [np.ones(t.size)]
    for n in range(1, harmonics + 1, 2):
        cols += [np.cos(2 * np.pi * n * f * t), np.sin(2 * np.pi * n * f * t)]
    if ring is not None:
        env = np.exp(-ring[0] * t)
        cols += [env * np.cos(ring[1] * t), env * np.sin(ring[1] * t)]
    coef, *_ = np.linalg.lstsq(np.column_stack(cols), y, rcond=None)
    return complex(coef[1], -coef[2])


@pytest.mark.parametrize("drive", ["sine", "square"])
def test_pipeline_steps_match_truth(drive: str) -> None:
    """Clean end-to-end run: in every sweep step sensor/V at the fundamental equals the truth."""
    rec = tm.generate(_seed_where(lambda s: s.pendulum.Q < 15), drive=drive, clean=True)
    p, a = rec.setup.pendulum, rec.arrays
    gamma = p.c / (2 * p.J)
    ring = (gamma, math.sqrt((2 * math.pi * p.f_0) ** 2 - gamma**2))
    harm = 1 if drive == "sine" else 15
    for st, row in zip(rec.truth["drive"]["steps"], rec.truth["transfer_function"], strict=True):
        sel = (a["t_s"] > st["t_start_s"] + 10.0) & (a["t_s"] < st["t_end_s"])
        t = a["t_s"][sel] - st["t_start_s"]
        v = _fit_phasor(t, a["v_true_V"][sel], st["f_hz"], harm, None)
        y = _fit_phasor(t, a["sensor_m"][sel], st["f_hz"], harm, ring)
        want = complex(row["re_m_per_V"], row["im_m_per_V"])
        assert abs(y / v - want) <= 0.01 * abs(want), st["f_hz"]
        amp = abs(v) * (math.pi / 4 if drive == "square" else 1.0)
        assert math.isclose(amp, rec.truth["drive"]["amplitude_V"], rel_tol=0.01)


def test_matches_full_sine_equation() -> None:
    """The linear exact discretisation agrees with an ODE solve of the full sin() equation."""
    p = tm.draw_setup(3)[0].pendulum
    g = tm.G_M_PER_S2
    f, a, off = 2.5 * p.f_z, 3e-6, 40e-6
    h = 0.5 / tm.SUBSTEPS
    t = np.arange(int(4000 / h) + 1) * h
    phi = off + a * np.sin(2 * np.pi * f * t)
    th0, thd0 = -20e-6, 3e-8
    theta = tm.simulate_deflection(p, phi, h, th0, thd0)[:: tm.SUBSTEPS]

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        ph = off + a * math.sin(2 * math.pi * f * tt)
        phd = a * 2 * math.pi * f * math.cos(2 * math.pi * f * tt)
        acc = (-p.c * (y[1] - phd) - p.k * (y[0] - ph) - p.m * g * p.d * math.sin(y[0])) / p.J
        return [y[1], acc]

    ts = t[:: tm.SUBSTEPS]
    sol = solve_ivp(rhs, (0.0, ts[-1]), [th0 + off, thd0 + a * 2 * math.pi * f], t_eval=ts,
                    method="DOP853", rtol=1e-11, atol=1e-16)
    ref = sol.y[0] - (off + a * np.sin(2 * np.pi * f * ts))
    assert np.max(np.abs(theta - ref)) < 1e-4 * np.ptp(ref)


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[tm.Recording, dict[str, Any], Path]:
    rec = tm.generate(2)
    out = tmp_path_factory.mktemp("tiltmeter")
    return rec, tm.write_files(rec, out), out


def _mjd(line: str) -> float:
    return float(line.split(tm.DELIMITER)[0])


def test_stray_rows_where_truth_says(written: tuple[tm.Recording, dict[str, Any], Path]) -> None:
    _, truth, out = written
    lines = (out / truth["csv_file"]).read_text().splitlines()
    header = tm.DELIMITER.join(truth["columns"])
    kinds = sorted(s["kind"] for s in truth["stray_rows"])
    assert kinds.count("repeated_header") == kinds.count("duplicate") == 1
    assert kinds.count("out_of_order") == kinds.count("gap") == 1
    assert 3 <= kinds.count("nan_field") + kinds.count("empty_field") <= 5
    day = 86400.0
    for s in truth["stray_rows"]:
        ln = lines[s["line"] - 1]
        if s["kind"] == "repeated_header":
            assert ln == header
        elif s["kind"] == "duplicate":
            assert ln == lines[s["line"] - 2] and s["duplicate_of_line"] == s["line"] - 1
        elif s["kind"] == "out_of_order":
            assert s["swapped_with_line"] == s["line"] + 1
            t0, t1, t2 = (_mjd(lines[s["line"] - 2 + i]) for i in range(3))
            assert t0 < t2 < t1 and math.isclose((t1 - t2) * day, 0.5, abs_tol=0.011)
        elif s["kind"] == "gap":
            dt_gap = (_mjd(ln) - _mjd(lines[s["after_line"] - 1])) * day
            assert 3 <= s["n_missing"] <= 20
            assert math.isclose(dt_gap, 0.5 * (s["n_missing"] + 1), abs_tol=0.011)
        else:
            col = truth["columns"].index(s["column"])
            assert ln.split(tm.DELIMITER)[col] == ("NaN" if s["kind"] == "nan_field" else "")
    # nothing else is odd: every other step is 0.5 s +- jitter, every other field parses
    flagged = {s["line"] for s in truth["stray_rows"]}
    flagged |= {s["line"] + 1 for s in truth["stray_rows"] if s["kind"] == "out_of_order"}
    prev = None
    for i, ln in enumerate(lines[truth["first_data_line"] - 1:], start=truth["first_data_line"]):
        if ln == header:
            continue
        fields = ln.split(tm.DELIMITER)
        assert len(fields) == 4
        if i in flagged or (prev is not None and prev in flagged):
            prev = i
            continue
        assert all(x not in ("", "NaN") for x in fields)
        if prev is not None and lines[i - 2] != header:
            assert math.isclose((_mjd(ln) - _mjd(lines[prev - 1])) * day, 0.5, abs_tol=0.011)
        prev = i


def test_file_round_trips(written: tuple[tm.Recording, dict[str, Any], Path]) -> None:
    rec, truth, out = written
    text = (out / truth["csv_file"]).read_text().splitlines()
    pre = text[: truth["preamble_lines"]]
    assert all(ln.startswith("#") for ln in pre)
    assert text[truth["header_line"] - 1] == tm.DELIMITER.join(truth["columns"])
    with open(out / truth["csv_file"], newline="") as fh:
        rows = [r for r in csv.reader(fh, delimiter=truth["delimiter"])
                if r and not r[0].startswith("#") and r[0] != truth["time_column"]]
    assert len(rows) == truth["n_data_rows"]
    uniq = sorted({tuple(r) for r in rows}, key=lambda r: float(r[0]))
    t_s = (np.array([float(r[0]) for r in uniq]) - truth["mjd_start"]) * 86400.0
    idx = np.rint(t_s / 0.5).astype(int)
    assert np.max(np.abs(t_s - 0.5 * idx)) < 0.0055          # +-5 ms jitter, 9-decimal days
    gap = next(s for s in truth["stray_rows"] if s["kind"] == "gap")
    assert len(uniq) == truth["n_samples_simulated"] - gap["n_missing"]
    assert len(set(idx.tolist())) == len(idx) and idx[0] == 0
    a = rec.arrays
    ok = np.array([all(x not in ("", "NaN") for x in r) for r in uniq])
    counts = np.array([int(r[1]) for r, g in zip(uniq, ok, strict=True) if g])
    volts = np.array([float(r[2]) for r, g in zip(uniq, ok, strict=True) if g])
    assert np.array_equal(counts, a["counts"][idx[ok]])
    assert np.allclose(volts, a["pzt_V"][idx[ok]], atol=5e-4)
    on_disk = json.loads((out / "truth.json").read_text())
    assert on_disk == tm._plain(truth)
    for key in ("true", "stated", "d_true_m", "f_z_hz", "f_0_hz", "Q", "drive_frequencies_hz",
                "drive_spans_s", "scale_m_per_count", "columns", "delimiter", "time_unit",
                "stray_rows", "seed", "transfer_function"):
        assert key in on_disk
    assert on_disk["time_unit"] == "days" and "d_m" not in on_disk["stated"]


def test_drift_dominates_and_start_is_out_of_equilibrium(
        written: tuple[tm.Recording, dict[str, Any], Path]) -> None:
    rec, truth, _ = written
    a, tr = rec.arrays, rec.setup.true
    assert np.var(a["drift_m"]) > 0.75 * np.var(a["sensor_m"])
    assert truth["drift_variance_fraction"] > 0.75
    theta_eq = rec.setup.pendulum.tilt_response(0.0).real * a["phi_rad"][0]
    assert abs(a["theta_rad"][0] - theta_eq) * tr["sensor_arm_m"] >= 0.3e-6
    # the drive response sits well above the white noise but far below the drift
    assert 20.0 <= truth["snr"]["dc_response_over_noise_per_bin"] <= 200.0


def test_cli_square(tmp_path: Path) -> None:
    assert tm.main(["4", str(tmp_path), "--drive", "square"]) == 0
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["drive"]["kind"] == "square"
    with open(tmp_path / truth["csv_file"], newline="") as fh:
        rows = [r for r in csv.reader(fh, delimiter=";") if r and r[0][0].isdigit()]
    t = (np.array([float(r[0]) for r in rows]) - truth["mjd_start"]) * 86400.0
    v = np.array([float(r[2]) if r[2] not in ("", "NaN") else np.nan for r in rows])
    t0, t1 = truth["drive_spans_s"][0]
    inside = v[(t > t0 + 5) & (t < t1)]
    levels = truth["drive"]["bias_V"] + np.array([-1, 1]) * truth["drive"]["amplitude_V"]
    near = np.min(np.abs(inside[:, None] - levels[None, :]), axis=1) < 0.01
    assert np.nanmean(near) > 0.9
