"""Tilt modulation analysis (paper sec. 3.2): what the inverted pendulum made of the wave.

A square wave's response is its settled steps. A triangle's is fitted (`sweep`): the reading
against the model pendulum's response to the applied voltage, which carries the pendulum's
lag and ringing, plus a term for the direction of travel, whose size is the opening between
the up and the down sweeps at the same voltage: a piezo's hysteresis, or a lag the model
does not have (a hysteresis keeps its opening at another sweep rate; a lag's grows with it).

The response against what the piezo geometry of the model predicts checks the lever arm
(piezo stroke / support spacing) and the pendulum's amplification on the stand. With the
torsion pendulum's own step it gives the paper's ratio (3 um on the inverted pendulum went
with about 0.4 um on the torsion pendulum) and the roll/pitch split it implies: the inverted
pendulum senses pitch (its axis is taken as the torsion pendulum's pitch axis); the torsion
pendulum answers M g (pitch l_cm,y + roll l_cm,x) / K0 at its arm, so with its
centre-of-mass offsets known (`leveler calibrate-com`) the roll that went with the measured
pitch follows.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from leveler.loop.modulation import Wave, unit
from leveler.sim.params import PendulumParams, PlantParams
from leveler.sim.pendulum import PendulumModel
from leveler.sim.torsion import TorsionParams

SETTLED_FRACTION = 0.5  # of each half period: the pendulum rings down in the first half
#: of each sweep of a triangle, left out after its turn: the model pendulum rings there too,
#: but a model a little off leaves ringing of opposite sign after the two turns, which the
#: direction term would take up
SWEEP_SETTLE_FRACTION = 0.25
COHERENT_ORDER = 20  # `coherent`: harmonic pairs m n up to this
#: `unit` over an array of phases (0..1): the loop's own definition of the waves' forms
forms = np.vectorize(unit, otypes=[float])


@dataclass(frozen=True, slots=True)
class Response:
    """Peak-to-peak step of a signal under the wave: mean and scatter over the half periods."""

    peak_to_peak: float
    scatter: float  # standard deviation of the single steps
    steps: int


def response(wave: Wave, t_s: np.ndarray, y: np.ndarray) -> Response:
    """The signal's step between the high and the low half periods.

    Each half period contributes the mean of its settled part (the last SETTLED_FRACTION);
    a step is a high mean minus the mean of the two lows around it (and the other way round),
    which cancels a linear drift. NaN samples (failed reads) are left out.
    """
    half = wave.period_s / 2
    means = []
    for k in range(2 * wave.cycles):
        a = wave.start_t_s + (k + 1 - SETTLED_FRACTION) * half
        b = wave.start_t_s + (k + 1) * half
        sel = (t_s >= a) & (t_s < b) & np.isfinite(y)
        if not sel.any():
            raise ValueError(f"no samples in half period {k} ({a:.3f}..{b:.3f} s): the run "
                             "is shorter than the wave, or every read failed")
        means.append(float(np.mean(y[sel])))
    m = np.asarray(means)
    if len(m) < 3:  # one cycle: one high, one low
        steps = np.array([m[0] - m[1]])
    else:
        sign = np.where(np.arange(1, len(m) - 1) % 2 == 0, 1.0, -1.0)  # k even: a high
        steps = sign * (m[1:-1] - 0.5 * (m[:-2] + m[2:]))
    return Response(float(np.mean(steps)), float(np.std(steps)), len(steps))


def peak_to_peak(wave: Wave, t_s: np.ndarray, x: np.ndarray) -> float:
    """A signal's peak to peak under the wave: a square's settled steps (`response`), a
    triangle's form fitted by least squares with a constant (NaN samples left out)."""
    if wave.shape == "square":
        return response(wave, t_s, x).peak_to_peak
    phase = (t_s - wave.start_t_s) / wave.period_s
    on = (phase >= 0) & (phase < wave.cycles) & np.isfinite(x)
    if not on.any():
        raise ValueError("no samples in the wave")
    form = forms(wave.shape, phase[on] % 1.0)
    a = np.column_stack([np.ones(len(form)), form])
    return 2.0 * float(np.linalg.lstsq(a, x[on], rcond=None)[0][1])


def model_of(plant: PlantParams) -> dict[str, Any]:
    """What the wave is read against: the reading per platform tilt (amplification x arm),
    the tilt per piezo volt (stroke / support spacing) and, for a triangle's fit, the
    pendulum whose dynamics the reading goes through."""
    pend = plant.pendulum
    return {"sensor_m_per_rad": pend.amplification * pend.sensor_arm_m,
            "tilt_rad_per_v": plant.piezo.gain_m_per_v / plant.platform.support_spacing_m,
            "pendulum": dataclasses.asdict(pend),
            "disturbances": plant.disturbances}


def coherent(wave: Wave, disturbances: list[tuple[float, float]],
             sensor_m_per_rad: float) -> list[str]:
    """Known disturbances ((period [s], peak to peak tilt [rad]) each) that repeat with the
    wave: a harmonic n of one within half the record's resolution (its phase turns less than
    half a cycle over the record) of an odd harmonic m of the wave (a square's steps and a
    triangle's direction term have only odd ones), where m n <= COHERENT_ORDER. A sawtooth's
    n-th harmonic is 1/(pi n) of its peak to peak, and the wave's m-th weighs 1/m, so such a
    pair can move the response by about 2 pp / (pi n m) at the sensor, the same in every
    cycle, which the cycles' scatter cannot show: at the cooler's own period a null
    triangle on the simulated stand opened by 5.9 nm at "127 sigma"."""
    resolution_hz = 0.5 / (wave.cycles * wave.period_s)
    out = []
    for period, pp_rad in disturbances:
        hits = [(m, n) for m in range(1, COHERENT_ORDER + 1, 2)
                for n in range(1, COHERENT_ORDER // m + 1)
                if abs(m / wave.period_s - n / period) < resolution_hz]
        if hits:
            m, n = min(hits, key=lambda mn: mn[0] * mn[1])
            size_m = 2 * pp_rad * sensor_m_per_rad / (math.pi * n * m)
            out.append(f"the model's {period:g} s disturbance repeats with this wave (its "
                       f"harmonic {n} on the wave's {m}): about {size_m * 1e9:.2g} nm of the "
                       "response may be it, which the scatter cannot show; a period that is "
                       "no multiple or fraction of it avoids this")
    return out


@dataclass(frozen=True, slots=True)
class Sweep:
    """A triangle's response, fitted cycle by cycle: means, and standard deviations over
    the cycles (NaN from one cycle)."""

    measured_over_model: float  # the reading's gain on the model pendulum's response
    measured_over_model_scatter: float
    opening_m: float  # the down sweep's reading minus the up sweep's at the same voltage
    opening_scatter_m: float
    cycles: int
    piezo_peak_to_peak_v: float


def model_reading(wave: Wave, t_s: np.ndarray, v: np.ndarray,
                  model: dict[str, Any]) -> np.ndarray:
    """The reading [m] the model predicts for the applied voltage `v` about the wave's centre:
    its linear pendulum, settled at the first sample, stepped at the log's rate; sample n
    reads what the voltages before it did, as the loop reads before it writes. A missing
    voltage is the wave's command."""
    pend = PendulumParams(**(model["pendulum"] | {"model": "linear"}))
    dt_s = float(np.median(np.diff(t_s)))
    command = np.array([wave.center_v if (c := wave.command_v(t)) is None else c
                        for t in t_s])
    phi = model["tilt_rad_per_v"] * (np.where(np.isfinite(v), v, command) - wave.center_v)
    pm = PendulumModel(pend, dt_s)
    pm.settle(pend, float(phi[0]))
    out = np.empty(len(t_s))
    for i, p in enumerate(phi.tolist()):
        out[i] = pm.theta
        pm.step(p)
    return out * pend.sensor_arm_m


def sweep(wave: Wave, t_s: np.ndarray, y: np.ndarray, v: np.ndarray,
          model: dict[str, Any]) -> Sweep:
    """Per cycle, least squares of the reading on: a constant, a linear drift, the model's
    reading (`model_reading`) and the direction of travel (+1 rising, -1 falling), on the
    samples past each sweep's first SWEEP_SETTLE_FRACTION. The sweeps kept cover the
    middle half of the swing both ways, so the direction term is the opening there."""
    phase = (t_s - wave.start_t_s) / wave.period_s
    k = np.floor(phase + 1e-9)
    frac = phase - k
    g = model_reading(wave, t_s, v, model)
    rising = (frac < 0.25) | (frac >= 0.75)
    since_turn = np.where(rising, (frac + 0.25) % 1.0, frac - 0.25) / 0.5
    keep = (since_turn >= SWEEP_SETTLE_FRACTION) & np.isfinite(y)
    piezo_pp = peak_to_peak(wave, t_s, v)
    gains, openings = [], []
    for c in range(wave.cycles):
        sel = keep & (k == c)
        if sel.sum() < 8:
            raise ValueError(f"cycle {c} has {int(sel.sum())} usable samples: the run is "
                             "shorter than the wave, or its reads failed")
        x = np.column_stack([np.ones(sel.sum()), frac[sel] - 0.5, g[sel],
                             np.where(rising[sel], 1.0, -1.0)])
        coef = np.linalg.lstsq(x, y[sel], rcond=None)[0]
        gains.append(float(coef[2]))
        openings.append(-2.0 * float(coef[3]))
    return Sweep(float(np.mean(gains)), _scatter(gains), float(np.mean(openings)),
                 _scatter(openings), wave.cycles, piezo_pp)


def _scatter(z: list[float]) -> float:
    return float(np.std(z, ddof=1)) if len(z) > 1 else math.nan


def analyze(wave: Wave, t: np.ndarray, y: np.ndarray, v: np.ndarray,
            model: dict[str, Any], where: str) -> dict[str, Any]:
    """The inverted pendulum's and the piezo's response to the wave, the tilt they mean,
    and that tilt against the model's piezo geometry (`model`: `model_of`); a triangle's
    also the opening between its sweeps."""
    wave_d = {"center_v": wave.center_v, "amplitude_v": wave.amplitude_v,
              "period_s": wave.period_s, "cycles": wave.cycles, "shape": wave.shape}
    out: dict[str, Any] = {"where": where, "wave": wave_d, "samples": len(t),
                           "coherent": coherent(wave, model.get("disturbances", []),
                                                 model["sensor_m_per_rad"])}
    if wave.shape == "square":
        ip: Response = response(wave, t, y)
        piezo_pp = response(wave, t, v).peak_to_peak
        ip_pp = ip.peak_to_peak
        out |= {"ip_scatter_m": ip.scatter, "ip_steps": ip.steps}
    else:
        sw = sweep(wave, t, y, v, model)
        piezo_pp = sw.piezo_peak_to_peak_v
        ip_pp = sw.measured_over_model * model["sensor_m_per_rad"] * model["tilt_rad_per_v"] \
            * piezo_pp
        m_per_v = ip_pp / piezo_pp
        se = sw.opening_scatter_m / math.sqrt(sw.cycles)
        slope = 2.0 * piezo_pp / wave.period_s
        out |= {"ip_scatter_m": sw.measured_over_model_scatter * ip_pp, "ip_steps": sw.cycles,
                "opening_m": sw.opening_m, "opening_sigma_m": se,
                "opening_v": sw.opening_m / m_per_v,
                "opening_of_swing": sw.opening_m / m_per_v / piezo_pp,
                "opening_as_lag_s": sw.opening_m / m_per_v / (2.0 * slope),
                "opening_z": sw.opening_m / se if se > 0 else math.nan}
        out = {k: None if isinstance(x, float) and math.isnan(x) else x for k, x in out.items()}
    expected_tilt = piezo_pp * model["tilt_rad_per_v"]
    tilt = ip_pp / model["sensor_m_per_rad"]
    return out | {
        "piezo_peak_to_peak_v": piezo_pp,
        "ip_peak_to_peak_m": ip_pp,
        "ip_m_per_v": ip_pp / piezo_pp,
        "tilt_peak_to_peak_rad": tilt,
        "model": {k: model[k] for k in ("sensor_m_per_rad", "tilt_rad_per_v")},
        "model_tilt_peak_to_peak_rad": expected_tilt,
        "measured_over_model": tilt / expected_tilt,
    }


def waves(t_s: np.ndarray, u_v: np.ndarray, usable: np.ndarray | None = None) -> list[Wave]:
    """The square and triangle waves of a recorded command (`drive_lines`: a line with
    harmonics on its span), each as the `Wave` that ran: its whole cycles on the span, the
    start where its fundamental rises through zero (both shapes' fundamentals are
    sin(w (t - start)), 4 A / pi for a square, 8 A / pi^2 for a triangle), and the shape
    whose form leaves the command the smaller residual."""
    from leveler.procedures.drive_lines import drive_spans, measure

    spans = drive_spans(t_s, u_v, usable)
    harmonic = {(s.a, s.b) for s in spans if s.harmonic > 1}
    found = []
    for line in measure(t_s, u_v, u_v, [s for s in spans if s.harmonic == 1
                                        and (s.a, s.b) in harmonic], settle_fraction=0.0):
        w, period = 2 * math.pi * line.frequency_hz, 1 / line.frequency_hz
        start = float(t_s[0]) - (math.atan2(line.command_v.imag, line.command_v.real)
                                 + math.pi / 2) / w
        start += math.ceil((line.start_s - start) / period) * period  # first whole cycle
        cycles = int((line.end_s - start) // period)
        if cycles < 1:
            continue
        sel = (t_s >= start) & (t_s < start + cycles * period)
        center, fundamental = float(np.mean(u_v[sel])), abs(line.command_v)
        phase = ((t_s[sel] - start) / period) % 1.0
        fits = []
        for shape, amplitude in (("square", fundamental * math.pi / 4),
                                 ("triangle", fundamental * math.pi**2 / 8)):
            form = center + amplitude * forms(shape, phase)
            fits.append((float(np.mean((u_v[sel] - form) ** 2)), shape, amplitude))
        _, shape, amplitude = min(fits)
        wave = Wave(center, amplitude, period, cycles, start, shape)
        found.append(_refined(wave, t_s[sel], u_v[sel]) if shape == "triangle" else wave)
    return found


def _refined(wave: Wave, t_s: np.ndarray, u_v: np.ndarray) -> Wave:
    """A triangle's start and period fitted to the command it ran (its centre and amplitude
    solved at each): the drive-line search's frequency, from 5 cycles, was 0.6 % off, and
    the direction term then slips a few per cent of a cycle by the last one. A triangle's
    form is smooth in both, unlike a square's edges."""
    from scipy.optimize import minimize

    def fit(x: np.ndarray) -> tuple[float, np.ndarray]:
        a = np.column_stack([np.ones(len(t_s)), forms("triangle", ((t_s - x[0]) / x[1]) % 1.0)])
        coef, *_ = np.linalg.lstsq(a, u_v, rcond=None)
        return float(np.mean((u_v - a @ coef) ** 2)), coef

    x0 = np.array([wave.start_t_s, wave.period_s])
    res = minimize(lambda x: fit(x)[0], x0, method="Nelder-Mead",
                   options={"xatol": 1e-4 * wave.period_s, "fatol": 0.0,
                            "initial_simplex": x0 + np.vstack([np.zeros(2), np.eye(2)])
                            * 0.01 * wave.period_s})
    start, period = (float(v) for v in res.x)
    _, (center, amplitude) = fit(res.x)
    return dataclasses.replace(wave, center_v=float(center), amplitude_v=float(amplitude),
                               start_t_s=start, period_s=period)


def torsion_split(r: dict[str, Any], tp_pp_m: float, tp: TorsionParams) -> dict[str, Any]:
    """The IP/TP ratio, and the roll that the TP's step implies next to the IP's pitch."""
    pitch = r["tilt_peak_to_peak_rad"]
    per_rad = tp.arm_m * tp.mass_kg * tp.gravity_m_per_s2 / tp.stiffness_nm_per_rad
    out: dict[str, Any] = {"peak_to_peak_m": tp_pp_m, "ip_over_tp": r["ip_peak_to_peak_m"]
                           / tp_pp_m, "pitch_only_peak_to_peak_m": per_rad * pitch * tp.com_y_m,
                           "com_x_m": tp.com_x_m, "com_y_m": tp.com_y_m}
    if tp.com_x_m:
        roll = (tp_pp_m / per_rad - pitch * tp.com_y_m) / tp.com_x_m
        out |= {"roll_peak_to_peak_rad": roll, "roll_over_pitch": roll / pitch,
                "tilt_axis_deg": math.degrees(math.atan2(roll, pitch))}
    return out
