"""Checks of the independent thrust-stand generator's own physics and file format (not leveler)."""

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
from scipy.optimize import curve_fit
from scipy.special import j0

from bench.independent import thrust_stand as ts

SEEDS = range(80)


def _seed_where(pred: Any, scenario: str = "stepped", limit: int = 300) -> int:
    """First seed whose drawn setup satisfies pred (draws only, no simulation)."""
    for s in range(limit):
        if pred(ts.draw_setup(s, scenario)[0]):
            return s
    raise AssertionError("no seed found")


def _shortest(pred: Any, scenario: str = "stepped", limit: int = 120) -> int:
    """The seed with the fewest samples among those satisfying pred."""
    best = min((ts.draw_setup(s, scenario)[0] for s in range(limit)),
               key=lambda su: su.n if pred(su) else math.inf)
    assert pred(best)
    return best.seed


# ------------------------------------------------------------------ draws

def test_parameter_ranges() -> None:
    for seed in SEEDS:
        for scen in ts.SCENARIOS:
            su, _ = ts.draw_setup(seed, scen)
            st = su.stand
            assert 0.01 <= st.K0 <= 0.5 and 0.01 <= st.J <= 0.2
            assert 0.05 <= st.f0 <= 1.0 and 3.0 <= st.Q <= 50.0
            Ls = su.stated["L_m"]
            assert 0.1 <= Ls["value"] <= 0.4
            assert abs(st.L - Ls["value"]) <= Ls["sigma"] * (1 + 1e-12)
            assert st.L_s == st.L
            assert abs(st.M - su.stated["M_kg"]["value"]) <= su.stated["M_kg"]["sigma"] * 1.001
            lc = su.extras["l_cm_drawn_m"]
            assert 0.05e-3 <= abs(lc) <= 1e-3
            assert (st.l_cm == 0.0) if scen == "null" else (st.l_cm == lc)
            assert su.fs in (2, 5, 10) and su.substeps * su.fs * su.h == pytest.approx(1.0)
            cal = su.calibration
            assert abs(cal["thrust_e_F"]) <= 0.02 and abs(cal["tilt_gain_error"]) <= 0.03
            assert 0.1e-6 <= abs(cal["tilt_offset_rad"]) <= 0.5e-6
            for k in ("disp_white_factor", "disp_walk_factor", "tilt_white_factor"):
                assert 0.75 <= su.noise[k] <= 0.9 or 1.1 <= su.noise[k] <= 1.25
            sch = su.schedule
            sq = next(s for s in sch["thrust"] if s["kind"] == "square")
            P = sq["period_s"]
            assert 0.3e-6 <= sq["F_N"] <= 5e-6 and 100.0 <= P <= 600.0
            if 40 * st.decay_time <= 600.0:
                assert P / 2 >= 20 * st.decay_time * (1 - 1e-3)
            else:
                assert P == 600.0
            # trapezoid corners on the sub-step grid: the piecewise-linear torque is exact
            for v in (P / 2, sq["t_first_rise_s"], sq["rise_s"]):
                assert abs(v / su.h - round(v / su.h)) < 1e-6
            if scen in ("stepped", "null"):
                pl = sch["pitch"]["plateaus"]
                assert 5 <= len(pl) <= 9 and 10e-6 <= sch["pitch"]["span_rad"] <= 25e-6
                assert max(abs(p["alpha_rad"]) for p in pl) <= 1.2 * sch["pitch"]["span_rad"]
                for a, b in itertools.pairwise(pl):
                    assert 20.0 - 1e-6 <= b["t_start_s"] - a["t_end_s"] <= 60.0 + 1e-6
                assert all(p["t_end_s"] - p["t_start_s"] >= 4 * P - 1e-6 for p in pl)
            elif scen == "drift":
                dur = (su.n - 1) / su.fs
                assert 12 * 3600 - 1 <= dur <= 24 * 3600
                pitch = sch["pitch"]
                assert 5e-6 <= pitch["peak_rad"] <= 25e-6 and 3 <= len(pitch["components"]) <= 4
                assert all(7200 <= c["period_s"] <= 86400 for c in pitch["components"])
                c = pitch["cooler"]
                assert 200 <= c["period_s"] <= 800 and 0.1e-6 <= c["peak_to_peak_rad"] <= 0.5e-6
            else:
                pt, sine = sch["pitch"], sch["thrust"][0]
                assert 0.05 <= pt["f_hz"] <= 0.15 and sine["f_hz"] < 0.7 * st.f0
                assert 1.04 <= sine["f_hz"] / pt["f_hz"] <= 1.2
                assert 3600.0 <= pt["t_to_s"] - pt["t_from_s"] <= 3 * 3600.0 + 30
                assert 3 <= sq["n_periods"] <= 6 and 10e-6 <= pt["amp_rad"] <= 30e-6


def test_style_varies() -> None:
    styles = [ts.draw_setup(s)[0].style for s in SEEDS]
    assert {s["delimiter_name"] for s in styles} == set(ts.DELIMITERS)
    assert {s["t"]["unit"] for s in styles} == {"s", "ms", "days"}
    assert {s["displacement"]["unit"] for s in styles} == {"um", "nm", "counts"}
    for s in styles:
        assert "t_s" not in s["columns"] and len(set(s["columns"])) == len(s["columns"])
        assert 1 <= len(s["extras"]) <= 2


# ------------------------------------------------------------------ discretisation

def _ode_reference(stand: ts.Stand, knots_t: np.ndarray, knots_u: np.ndarray,
                   x0: tuple[float, float]) -> np.ndarray:
    """theta at the knots, by DOP853 on each interval of the piecewise-linear torque."""
    out = [x0[0]]
    y = np.array(x0, dtype=float)
    for k in range(knots_t.size - 1):
        t0, t1, u0, u1 = knots_t[k], knots_t[k + 1], knots_u[k], knots_u[k + 1]
        slope = (u1 - u0) / (t1 - t0)

        def rhs(t: float, y: np.ndarray, t0: float = t0, u0: float = u0,
                slope: float = slope) -> list[float]:
            tq = u0 + slope * (t - t0)
            return [y[1], (tq - stand.lam * y[1] - stand.K0 * y[0]) / stand.J]

        sol = solve_ivp(rhs, (t0, t1), y, method="DOP853", rtol=1e-12, atol=1e-22)
        y = sol.y[:, -1]
        out.append(y[0])
    return np.array(out)


@pytest.mark.parametrize("scenario", ["stepped", "dual"])
@pytest.mark.parametrize("kind", ["low_q", "high_q"])
def test_discretisation_matches_solve_ivp(scenario: str, kind: str) -> None:
    pred = (lambda s: s.stand.Q < 6) if kind == "low_q" else (lambda s: s.stand.Q > 35)
    su = ts.draw_setup(_seed_where(pred, scenario), scenario)[0]
    st, h, S = su.stand, su.h, su.substeps
    rng = np.random.default_rng(11)
    dt_s = S * h
    n = round(150.0 / dt_s) + 1
    knots_t = np.arange(n) * dt_s
    # torque: a step train (thrust) plus a random piecewise-linear gravity torque
    tq = 2e-7 * (np.mod(knots_t, 40.0) < 20.0) + 5e-8 * np.cumsum(rng.normal(0, 0.3, n))
    tq[knots_t < 3.0] = 0.0
    t_sub = np.arange((n - 1) * S + 1) * h
    theta, _ = ts.simulate(st, np.interp(t_sub, knots_t, tq), h, S, 3e-6, -1e-6)
    ref = _ode_reference(st, knots_t, tq, (3e-6, -1e-6))
    assert np.max(np.abs(theta - ref)) < 1e-6 * np.max(np.abs(ref))


def test_recording_matches_ode_of_the_schedule() -> None:
    """The clean dual recording, continued by an ODE solve of the continuous schedule (thrust
    sine, sin(alpha) of the pitch sine), from the simulated state at a sample in the section."""
    seed = _shortest(lambda s: True, "dual")
    rec = ts.generate(seed, "dual", clean=True)
    st, sch, a = rec.setup.stand, rec.setup.schedule, rec.arrays
    k0 = int(np.searchsorted(a["t_s"], sch["pitch"]["t_from_s"] - 30.0))
    k1 = k0 + int(300 * rec.setup.fs)
    t = a["t_s"][k0:k1 + 1]

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        tq = float(ts.torque_true(tt, sch, st))
        return [y[1], (tq - st.lam * y[1] - st.K0 * y[0]) / st.J]

    y0 = [a["theta_rad"][k0], a["theta_dot_rad_per_s"][k0]]
    sol = solve_ivp(rhs, (t[0], t[-1]), y0, t_eval=t, method="DOP853", rtol=1e-11,
                    atol=1e-20, max_step=0.5)
    ref = sol.y[0]
    assert np.max(np.abs(a["theta_rad"][k0:k1 + 1] - ref)) < 2e-6 * np.max(np.abs(ref))


# ------------------------------------------------------------------ statics and ringdown

def test_static_deflection() -> None:
    su = ts.draw_setup(_seed_where(lambda s: s.stand.Q > 30))[0]
    st = su.stand
    tau = 1.3e-6 * 0.25
    dur = 40 * st.decay_time
    S, h = su.substeps, su.h
    n = int(dur * su.fs) + 1
    t_sub = np.arange((n - 1) * S + 1) * h
    theta, theta_dot = ts.simulate(st, np.where(t_sub >= 1.0, tau, 0.0), h, S)
    assert theta[-1] == pytest.approx(tau / st.K0, rel=1e-9)
    assert abs(theta_dot[-1]) < 1e-9 * st.w0 * tau / st.K0


def test_plateaus_settle_to_truth() -> None:
    """Clean stepped recording: at the end of every half period inside a plateau, x equals the
    truth's x_on / x_off, and x_on / (L_s F L) is the paper's compliance S = (1 + r) / K0."""
    seed = _shortest(lambda s: s.schedule["thrust"][0]["period_s"] / 2
                     >= 20 * s.stand.decay_time)
    rec = ts.generate(seed, "stepped", clean=True)
    tr, a, st = rec.truth, rec.arrays, rec.setup.stand
    sw = tr["square_wave"]
    P, t0, F = sw["period_s"], sw["t_first_rise_s"], sw["F_N"]
    t = a["t_s"]
    checked = 0
    for p in tr["plateaus"]:
        k = math.ceil((p["t_start_s"] - t0) / (P / 2)) + 1
        while t0 + k * P / 2 <= p["t_end_s"]:
            edge = t0 + k * P / 2
            i = int(np.searchsorted(t, edge - 1e-9)) - 1        # last sample before the edge
            want = p["x_off_m"] if k % 2 == 0 else p["x_on_m"]   # even k: a rise follows
            assert a["x_true_m"][i] == pytest.approx(want, rel=1e-6,
                                                     abs=1e-6 * sw["static_step_x_m"])
            if k % 2:
                S = a["x_true_m"][i] / st.L_s / (F * st.L)
                assert S == pytest.approx(p["S_rad_per_N_m"], rel=1e-6)
                assert F * st.L / (a["x_true_m"][i] / st.L_s) == pytest.approx(
                    p["K_N_m_per_rad"], rel=1e-6)
            checked += 1
            k += 1
    assert checked >= 6 * len(tr["plateaus"])
    for p in tr["plateaus"]:
        r = st.Mgl * math.sin(p["alpha_rad"]) / (F * st.L)
        assert p["r"] == pytest.approx(r, rel=1e-12)
        assert p["K_N_m_per_rad"] == pytest.approx(st.K0 / (1 + r), rel=1e-12)


def test_free_ringdown_frequency_and_decay() -> None:
    for pred in (lambda s: s.stand.Q < 5, lambda s: s.stand.Q > 30):
        su = ts.draw_setup(_seed_where(pred))[0]
        st = su.stand
        n = int(8 * st.decay_time * su.fs) + 1
        theta, _ = ts.simulate(st, np.zeros((n - 1) * su.substeps + 1), su.h, su.substeps,
                               2e-6, 0.0)
        t = np.arange(n) / su.fs

        def model(t: np.ndarray, amp: float, gam: float, wd: float, ph: float) -> np.ndarray:
            return amp * np.exp(-gam * t) * np.cos(wd * t + ph)

        p0 = [2e-6, st.gamma * 1.02, 2 * np.pi * st.f_damped * 0.99, 0.0]
        (_, gam, wd, _), _ = curve_fit(model, t, theta, p0=p0, xtol=1e-14, ftol=1e-14)
        w0 = math.hypot(wd, gam)
        assert w0 / (2 * np.pi) == pytest.approx(st.f0, rel=1e-7)
        assert w0 / (2 * gam) == pytest.approx(st.Q, rel=1e-6)
        assert 1 / gam == pytest.approx(st.decay_time, rel=1e-6)


# ------------------------------------------------------------------ scenarios

def _seed_short_stepped() -> int:
    return _shortest(lambda s: True)


def test_null_has_no_tilt_coupling() -> None:
    seed = _seed_short_stepped()
    null = ts.generate(seed, "null", clean=True)
    st, sch, su = null.setup.stand, null.setup.schedule, null.setup
    assert st.l_cm == 0.0 and null.truth["pendulum"]["Mgl_cm_N_m_per_rad"] == 0.0
    assert all(p["r"] == 0.0 and p["K_N_m_per_rad"] == st.K0 for p in null.truth["plateaus"])
    assert np.ptp(null.arrays["alpha_rad"]) > 15e-6                 # the pitch did move
    t_sub = np.arange((su.n - 1) * su.substeps + 1) * su.h
    thrust_only = ts.thrust_true(t_sub, sch) * st.L
    th, _ = ts.simulate(st, thrust_only, su.h, su.substeps,
                        null.truth["initial_state"]["theta0_rad"],
                        null.truth["initial_state"]["theta_dot0_rad_per_s"])
    assert np.array_equal(th, null.arrays["theta_rad"])
    # same seed, stepped: same stand, schedule and noise; the difference is the tilt response
    step = ts.generate(seed, "stepped", clean=True)
    assert step.setup.schedule == sch and step.setup.stand.l_cm != 0.0
    diff = step.arrays["x_true_m"] - null.arrays["x_true_m"]
    assert np.max(np.abs(diff)) > 1e-3 * null.truth["square_wave"]["static_step_x_m"]


def test_null_and_stepped_share_noise() -> None:
    seed = _seed_short_stepped()
    a, b = ts.generate(seed, "null"), ts.generate(seed, "stepped")
    for key in ("white_m", "zero_m", "tilt_read_rad", "thrust_logged_N"):
        assert np.array_equal(a.arrays[key], b.arrays[key])


def test_dual_lines_match_truth() -> None:
    seed = _shortest(lambda s: True, "dual")
    rec = ts.generate(seed, "dual", clean=True)
    tr, a, st = rec.truth, rec.arrays, rec.setup.stand
    pt = rec.setup.schedule["pitch"]
    t_from = pt["t_from_s"]
    sel = (a["t_s"] > t_from + 40 * st.decay_time + 30) & (a["t_s"] < pt["t_to_s"] - 5)
    tt = a["t_s"][sel] - t_from
    cols = [np.ones(tt.size)]
    for ln in tr["dual_lines"]:
        w = 2 * np.pi * ln["f_hz"]
        cols += [np.sin(w * tt + ln["drive_phase_rad"]), np.cos(w * tt + ln["drive_phase_rad"])]
    coef, *_ = np.linalg.lstsq(np.column_stack(cols), a["x_true_m"][sel], rcond=None)
    for j, ln in enumerate(tr["dual_lines"]):
        s, c = coef[1 + 2 * j], coef[2 + 2 * j]
        want = ln["x_amp_m"] * complex(math.cos(ln["x_phase_rad"]), math.sin(ln["x_phase_rad"]))
        assert abs(complex(s, c) - want) < 1e-4 * abs(want), ln["source"]
    sine = rec.setup.schedule["thrust"][0]
    mean_torque = sine["F_amp_N"] * st.L + st.Mgl * math.sin(pt["alpha0_rad"]) * j0(pt["amp_rad"])
    assert coef[0] == pytest.approx(st.L_s * mean_torque / st.K0, rel=1e-4)


def test_drift_follows_the_gravity_torque() -> None:
    seed = _shortest(lambda s: s.schedule["thrust"][0]["period_s"] / 2
                     >= 20 * s.stand.decay_time, "drift", limit=40)
    rec = ts.generate(seed, "drift", clean=True)
    st, a, tr = rec.setup.stand, rec.arrays, rec.truth
    pitch = rec.setup.schedule["pitch"]
    assert np.max(np.abs(a["alpha_rad"])) <= pitch["peak_rad"] + pitch["cooler"][
        "peak_to_peak_rad"] / 2 + 1e-12
    sw = tr["square_wave"]
    P, t0 = sw["period_s"], sw["t_first_rise_s"]
    edges = t0 + np.arange(1, int(a["t_s"][-1] / (P / 2)) - 2) * P / 2
    idx = np.searchsorted(a["t_s"], edges - 1e-9) - 1
    # quasi-static: the pitch moves slowly, so x at the end of a half period is the static value
    quasi = st.L_s * (a["thrust_true_N"][idx] * st.L + st.Mgl * np.sin(a["alpha_rad"][idx])) / st.K0
    err = np.abs(a["x_true_m"][idx] - quasi)
    # bound: the lag (x'/(Q w0)) and the ringing after a kink of the cooler's triangle
    # (~ slope / w0), with the fastest pitch rate of the record
    x_rate = np.max(np.abs(np.diff(a["alpha_rad"]))) * rec.setup.fs * abs(st.Mgl) * st.L_s / st.K0
    bound = 3.0 * x_rate / st.w0 + 1e-8 * sw["static_step_x_m"]
    assert np.all(err <= bound)
    grav = st.L_s * st.Mgl * np.sin(a["alpha_rad"]) / st.K0
    assert bound < 0.05 * np.ptp(grav)             # the check resolves the tilt coupling


# ------------------------------------------------------------------ files

def _read(out: Path, truth: dict[str, Any]) -> dict[str, np.ndarray]:
    imp = truth["import"]
    lines = (out / truth["file"]["csv_file"]).read_text().splitlines()
    body = [ln for ln in lines if not ln.startswith(imp["comment_prefix"])]
    rows = list(csv.reader(body, delimiter=imp["delimiter"]))
    header, data = rows[0], rows[1:]
    assert header == imp["columns"]
    si = {}
    for role, spec in imp["roles"].items():
        j = header.index(spec["column"])
        raw = np.array([float(r[j]) for r in data])
        si[role] = raw * spec["scale"] + spec["offset"]
    return si


def _style_seeds() -> list[int]:
    """Short stepped seeds covering every delimiter, time unit and displacement unit."""
    keys = {}
    for s in range(120):
        su = ts.draw_setup(s)[0]
        sty = su.style
        for key in (sty["delimiter_name"], sty["t"]["column"], sty["displacement"]["unit"]):
            if key not in keys or su.n < keys[key][0]:
                keys[key] = (su.n, s)
    return sorted({s for _, s in keys.values()})


@pytest.mark.parametrize("seed", _style_seeds())
def test_csv_round_trip(seed: int, tmp_path: Path) -> None:
    rec = ts.generate(seed, "stepped")
    truth = ts.write_files(rec, tmp_path)
    si = _read(tmp_path, truth)
    a = rec.arrays
    roles = truth["import"]["roles"]
    want = {"t": a["t_s"], "thrust": a["thrust_logged_N"], "displacement": a["x_meas_m"],
            "tilt": a["tilt_read_rad"]}
    for role, w in want.items():
        res = roles[role]["resolution_si"]
        tol = 0.5 * res * (1 + 1e-6) + 4e-16 * max(1.0, abs(roles[role]["offset"]))
        assert si[role].size == rec.setup.n
        assert np.max(np.abs(si[role] - w)) <= tol, role
    lines = (tmp_path / truth["file"]["csv_file"]).read_text().splitlines()
    pre = lines[: truth["file"]["preamble_lines"]]
    assert all(ln.startswith("#") for ln in pre)
    assert not lines[truth["file"]["header_line"] - 1].startswith("#")
    text = "\n".join(pre)
    assert f"L = {truth['arm']['L_stated_m']:.4f} m" in text
    assert truth["import"]["delimiter_name"] in text
    on_disk = json.loads((tmp_path / truth["file"]["truth_file"]).read_text())
    assert on_disk == ts._plain(truth)


def test_truth_keys(tmp_path: Path) -> None:
    seed = _seed_short_stepped()
    truth = ts.write_recording(seed, tmp_path, "null")
    for key in ("pendulum", "arm", "stated", "sampling", "schedule", "calibration", "noise",
                "displacement_zero", "initial_state", "import", "file", "plateaus",
                "square_wave", "settling"):
        assert key in truth
    p = truth["pendulum"]
    for key in ("K0_N_m_per_rad", "J_kg_m2", "lambda_N_m_s_per_rad", "f0_hz", "Q", "M_kg",
                "l_cm_m", "Mgl_cm_N_m_per_rad"):
        assert key in p
    for key in ("L_true_m", "L_stated_m", "L_sigma_m", "L_sensor_m"):
        assert key in truth["arm"]
    assert set(truth["import"]["roles"]) == {"t", "thrust", "displacement", "tilt"}
    assert truth["import"]["roles"]["t"]["unit"] in ("s", "ms", "days")
    assert truth["import"]["delimiter"] in ts.DELIMITERS.values()
    ring = truth["initial_state"]
    assert ring["theta0_rad"] != ring["theta_eq0_rad"] and ring["theta_dot0_rad_per_s"] != 0.0
    assert (tmp_path / f"thrust_stand_{seed}_null.csv").exists()
    assert (tmp_path / f"truth_{seed}_null.json").exists()


def test_reproducible(tmp_path: Path) -> None:
    seed = _seed_short_stepped()
    for d in ("a", "b"):
        assert ts.main([str(seed), str(tmp_path / d), "--scenario", "stepped"]) == 0
    name = f"thrust_stand_{seed}_stepped.csv"
    tname = f"truth_{seed}_stepped.json"
    assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert (tmp_path / "a" / tname).read_bytes() == (tmp_path / "b" / tname).read_bytes()
    other = ts.generate(seed + 1, "stepped")
    assert other.truth["pendulum"] != json.loads(
        (tmp_path / "a" / tname).read_text())["pendulum"]
