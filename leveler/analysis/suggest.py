"""PID gains suggested from the plant model (python-control), with the margins to judge them.

The model is the linear stand at the loop rate: piezo volts -> stroke (`gain_m_per_v`) ->
platform tilt (/ `support_spacing_m`) -> pendulum (`discrete_matrices`: theta from phi,
the platform's own rotation included) -> sensor (`sensor_arm_m` * theta), with the tilt
held over each step (zero-order hold). That is exactly `leveler.sim.plant.Plant`: the
loop reads y[n] at t_n, writes u[n] after, and u[n] is held over the step to t_{n+1}, so
y[n+1] is the first reading to see it. The model is strictly proper, so it already
carries that one sample of computational delay; another z^-1 would count it twice (the
tests pin this against the simulator's step response).
ADC quantization, the piezo and output slew limits, the output rails and anti-windup are
not modelled: the margins hold for small signals, which is how the loop spends its life.

The controller is `leveler.loop.pid.PID` in discrete form: P on the error, the integral
accumulated by forward Euler (the output uses the integral *before* this sample's
``ki e dt``: ki dt / (z - 1)), D a backward-Euler first-order filtered difference,
kd (z - 1) / ((tau + dt) z - tau). PID puts D on the measurement; with a fixed setpoint
that is D on the error up to sign, so the loop transfer function is the same.

Design rule (`suggest`). The disturbance is thermal tilt, largest at the lowest
frequencies, so the figure of merit is the loop gain, |1 + L|, at 0.1 and 1 mHz, which an
integral term sets: |L| ~ ki * DC gain / (2 pi f). The pendulum's lightly damped resonance
(0.71 Hz, Q ~ 19 with the defaults: the plant gain there is ~20x its DC gain) caps it. The
loop is *gain* stabilised there: |L| <= 1/2 over the whole resonance band (f_r/2 to 2 f_r),
i.e. >= 6 dB of gain margin whatever the phase there: extra delay cannot destabilise it, and
nothing relies on cancelling a resonance that moves (f_r rests on the small difference
k - m g L_cm). The 2x of gain it tolerates is about +5 % of m g L_cm on the default stand.
In continuous time |C| at the resonance is sqrt(kp^2 + (ki / w_r)^2), so for a given
resonance gain kp only costs ki: the integrator alone maximises low-frequency suppression
and reaches a crossover near f_r / (2 Q) (17 mHz by default) with ~89 deg of phase margin.
(Sampled, kp = ki dt / 2 would cancel the integrator's half-sample lag for ~2.5 % more ki at
10 Hz; not worth a term.) The requested phase margin is therefore a floor: going below
the integrator's would need kp < 0, a right-half-plane controller zero that also raises the
resonance gain; a floor above it is met exactly with a PI zero below the crossover (on the
default stand only up to ~90.7 deg: kp itself lifts the resonance gain). The crossover
(unless given) is the highest that keeps both, found by bisection (the resonance gain grows
with it), and never above f_r / 5, which keeps it where the plant is flat and its phase is
not the resonance's (this binds only for Q below ~2.5). No D in this rule. A D placed *on*
the resonance (kd ~ ki / w_r^2: complex zeros cancelling a Q ~ 19 pole pair) is undone by a
few percent of error in m g L_cm. A larger, unfiltered D (zeros well below f_r) instead
*damps* it, and that lifts the integral ~46x on the default stand: config/sim.toml's hand
design, proven stable for m g L_cm -5..+3 %, inertia -20..+25 %, damping x0.5..2
(tests/test_tuning.py).
This rule does not design that yet: the damping rests on the loop's phase lag at f_r and
needs that robustness sweep, which is not automated here. The result is checked with
`control.stability_margins` and the closed-loop poles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import control
import numpy as np

from leveler.sim.effects import ExtraResonance
from leveler.sim.params import PlantParams
from leveler.sim.pendulum import discrete_matrices

SUPPRESSION_HZ = (1e-4, 1e-3, 1e-2)
RESONANCE_LOOP_GAIN_MAX = 0.5  # over the resonance band: 6 dB of gain margin at any phase
MIN_GAIN_MARGIN_DB = 6.0
CROSSOVER_CAP = 0.2  # of the resonance frequency
_BAND_POINTS = 4000  # resolves a resonance of Q up to ~1000 to well under 1 %


@dataclass(frozen=True)
class Suggestion:
    """Gains and what the linear model says about the loop they make.

    ``suppression_at`` maps frequency (Hz) to |1 + L|: how many times smaller the closed
    loop leaves a disturbance there than the open loop. ``resonance_loop_gain`` is the peak
    |L| over the resonance band (f_r/2 to 2 f_r).
    """

    kp_v_per_m: float
    ki_v_per_m_s: float
    kd_v_s_per_m: float
    d_filter_tau_s: float
    crossover_hz: float  # nan if |L| never crosses 1
    phase_margin_deg: float
    gain_margin_db: float  # inf if the phase never crosses -180 deg
    gain_margin_at_hz: float | None
    stable: bool
    suppression_at: dict[float, float]
    resonance_loop_gain: float


def plant_tf(params: PlantParams, rate_hz: float) -> control.TransferFunction:
    """Piezo volts -> sensor metres, discretized at dt = 1 / rate_hz as the simulator steps it:
    the pendulum, and an extra resonance the model names that the piezo rings."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    pe = params.pendulum
    a, b = discrete_matrices(pe, 1.0 / rate_hz)
    volts = params.piezo.gain_m_per_v / params.platform.support_spacing_m * pe.sensor_arm_m
    sys = control.ss(a, b[:, None] * volts, [[1.0, 0.0, 0.0]], [[0.0]], 1.0 / rate_hz)
    tf = control.minreal(control.tf(sys), verbose=False)
    for fx in params.effects.of("response"):
        if isinstance(fx, ExtraResonance) and fx.gain:
            # in parallel, on the piezo's tilt, with the pendulum's timing (sim's Plant.step)
            num, den = fx.discrete(1.0 / rate_hz)
            num[0] = 0.0  # strictly proper (ZOH): rounding leaves ~1e-17
            k = (params.piezo.gain_m_per_v / params.platform.support_spacing_m * fx.gain
                 * pe.sensor_arm_m * pe.amplification)
            tf = tf + control.tf(list(k * num), list(den), 1.0 / rate_hz)
    return tf


def controller_tf(kp: float, ki: float, kd: float, d_filter_tau_s: float,
                  rate_hz: float, ki2: float = 0.0) -> control.TransferFunction:
    """`leveler.loop.pid.PID` from error to volts (D taken on the error; see module doc).

    Terms with a zero gain are left out rather than added as 0 / (z - 1): that would
    leave an uncontrollable pole on the unit circle in the closed loop.
    """
    dt = 1.0 / rate_hz
    c = control.tf([kp], [1.0], dt)
    if ki2:  # i' = i + ki dt e + ki2 dt s1', s1' = s1 + dt e: one fraction over (z - 1)^2
        # (ki dt / (z - 1) + ki2 dt^2 z / (z - 1)^2 added as two would leave a third,
        # uncancelled pole at z = 1 in the closed loop's state space)
        c = c + control.tf([ki * dt + ki2 * dt * dt, -ki * dt], [1.0, -2.0, 1.0], dt)
    elif ki:
        c = c + control.tf([ki * dt], [1.0, -1.0], dt)
    if kd:
        c = c + control.tf([kd, -kd], [d_filter_tau_s + dt, -d_filter_tau_s], dt)
    return c


def _resonance_band_hz(params: PlantParams, rate_hz: float) -> np.ndarray:
    f_r, nyquist = params.pendulum.natural_frequency_hz, rate_hz / 2
    if not f_r / 2 < nyquist:
        raise ValueError(
            f"loop rate {rate_hz:g} Hz is too low for the pendulum resonance at {f_r:.3g} Hz: "
            "the sensor would alias it; run the loop at more than 4x the resonance")
    return np.linspace(f_r / 2, min(2 * f_r, nyquist * (1 - 1e-9)), _BAND_POINTS)


def _grid_hz(params: PlantParams, rate_hz: float, f_min_hz: float) -> np.ndarray:
    """Log-spaced up to just below Nyquist, dense over the resonance band."""
    log = np.geomspace(f_min_hz, rate_hz / 2 * (1 - 1e-9), 3000)
    return np.unique(np.concatenate([log, _resonance_band_hz(params, rate_hz)]))


def _response(sys: control.TransferFunction, f_hz: np.ndarray | float) -> np.ndarray:
    return np.asarray(sys(np.exp(2j * np.pi * np.asarray(f_hz) * sys.dt)))


def loop_margins(params: PlantParams, rate_hz: float, kp: float, ki: float, kd: float,
                 d_filter_tau_s: float, ki2: float = 0.0) -> Suggestion:
    """Margins, crossover and suppression of the loop these gains make (e.g. the config's)."""
    loop = controller_tf(kp, ki, kd, d_filter_tau_s, rate_hz, ki2) * plant_tf(params, rate_hz)
    band = _resonance_band_hz(params, rate_hz)
    # A dense grid of our own: python-control's default one for a discrete loop is too coarse
    # for a Q ~ 19 peak, and its polynomial method reports the integrator at z = 1 as a
    # phase crossover.
    f_hz = _grid_hz(params, rate_hz, 1e-7)
    frd = control.FrequencyResponseData(_response(loop, f_hz), 2 * np.pi * f_hz, smooth=True)
    gm, pm, _, w_pc, w_gc, _ = control.stability_margins(frd)
    poles = control.feedback(loop, 1).poles()
    return Suggestion(
        kp_v_per_m=kp,
        ki_v_per_m_s=ki,
        kd_v_s_per_m=kd,
        d_filter_tau_s=d_filter_tau_s,
        crossover_hz=float(w_gc) / (2 * np.pi),
        phase_margin_deg=float(pm),
        gain_margin_db=20 * math.log10(gm) if math.isfinite(gm) else math.inf,
        gain_margin_at_hz=float(w_pc) / (2 * np.pi) if math.isfinite(gm) else None,
        stable=bool(np.all(np.abs(poles) < 1.0)),
        suppression_at={f: float(abs(1 + _response(loop, f))) for f in SUPPRESSION_HZ},
        resonance_loop_gain=float(np.abs(_response(loop, band)).max()),
    )


def _round_toward_zero(x: float) -> float:
    """Three significant digits, rounded toward zero (a gain never rounds up past a limit)."""
    if x == 0:
        return 0.0
    e = math.floor(math.log10(abs(x))) - 2
    return float(f"{math.trunc(x / 10.0**e)}e{e}")


def suggest(params: PlantParams, rate_hz: float, *, bandwidth_hz: float | None = None,
            phase_margin_deg: float = 60.0) -> Suggestion:
    """PI gains with the most low-frequency suppression the resonance allows (module doc).

    ``bandwidth_hz`` fixes the crossover instead of the highest allowed; ValueError, saying
    why, if that crossover or the phase margin cannot be had with the resonance gain-stabilised.
    """
    if not 0 < phase_margin_deg < 180:
        raise ValueError(f"phase_margin_deg must be in (0, 180), got {phase_margin_deg}")
    if bandwidth_hz is not None and not bandwidth_hz > 0:
        raise ValueError(f"bandwidth_hz must be > 0, got {bandwidth_hz}")
    dt = 1.0 / rate_hz
    plant = plant_tf(params, rate_hz)
    band = _resonance_band_hz(params, rate_hz)
    z_band = np.exp(2j * np.pi * band * dt)
    p_band = _response(plant, band)
    integ_band = dt / (z_band - 1)

    def gains(fc: float) -> tuple[float, float]:
        z = np.exp(2j * np.pi * fc * dt)
        p, integ = complex(_response(plant, fc)), dt / (z - 1)
        ki = 1 / abs(p * integ)
        if 180 + math.degrees(np.angle(p * integ)) >= phase_margin_deg:
            return 0.0, ki
        # kp + ki integ = c, with c the controller that puts L(fc) at the wanted margin.
        c = np.exp(1j * math.radians(phase_margin_deg - 180)) / p
        ki = c.imag / integ.imag
        return c.real - ki * integ.real, ki

    def feasible(fc: float) -> bool:
        kp, ki = gains(fc)
        return ki > 0 and np.abs((kp + ki * integ_band) * p_band).max() <= RESONANCE_LOOP_GAIN_MAX

    f_r = params.pendulum.natural_frequency_hz
    lo, hi = CROSSOVER_CAP * f_r * 1e-6, CROSSOVER_CAP * f_r
    resonance = (
        f"the pendulum resonance at {f_r:.3g} Hz raises the plant gain "
        f"{np.abs(p_band).max() / abs(plant.dcgain()):.3g}x above DC, and the loop gain there "
        f"must stay <= {RESONANCE_LOOP_GAIN_MAX} ({MIN_GAIN_MARGIN_DB:g} dB gain margin)")
    if not feasible(lo):
        raise ValueError(f"no PI reaches {phase_margin_deg:g} deg of phase margin: {resonance}; "
                         "ask for less phase margin")
    if not feasible(hi):
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if feasible(mid) else (lo, mid)
    if bandwidth_hz is None:
        fc = lo
    elif bandwidth_hz > lo:
        raise ValueError(
            f"a crossover of {bandwidth_hz:g} Hz is not achievable: {resonance}, and the "
            f"crossover stays below {CROSSOVER_CAP:g} x the resonance; the highest with "
            f">= {phase_margin_deg:g} deg of phase margin is {lo:.3g} Hz")
    else:
        fc = bandwidth_hz
    kp, ki = (_round_toward_zero(g) for g in gains(fc))
    s = loop_margins(params, rate_hz, kp, ki, 0.0, 0.0)
    if not (s.stable and s.gain_margin_db >= MIN_GAIN_MARGIN_DB
            and s.phase_margin_deg >= phase_margin_deg - 1.0):
        raise ValueError(
            f"the design check failed for kp = {kp:g}, ki = {ki:g}: stable = {s.stable}, "
            f"gain margin {s.gain_margin_db:.3g} dB, phase margin {s.phase_margin_deg:.3g} deg; "
            "the plant is outside what this PI rule handles")
    return s


def _toml_float(x: float) -> str:
    text = f"{x:.6g}"
    return text if any(ch in text for ch in ".e") else text + ".0"


def _freq(f_hz: float | None) -> str:
    if f_hz is None or not math.isfinite(f_hz):
        return "none"
    return f"{f_hz * 1e3:.3g} mHz" if f_hz < 1 else f"{f_hz:.3g} Hz"


def _rows(s: Suggestion) -> list[tuple[str, str]]:
    gm = ("none (phase never -180 deg)" if not math.isfinite(s.gain_margin_db)
          else f"{s.gain_margin_db:.1f} dB at {_freq(s.gain_margin_at_hz)}")
    rows = [
        ("crossover (|L| = 1)", _freq(s.crossover_hz)),
        ("phase margin", f"{s.phase_margin_deg:.1f} deg" if math.isfinite(s.phase_margin_deg)
         else "none (|L| never 1)"),
        ("gain margin", gm),
        ("peak |L| at the resonance", f"{20 * math.log10(s.resonance_loop_gain):.1f} dB"
         if s.resonance_loop_gain > 0 else "0"),
        ("closed loop", "stable" if s.stable else "UNSTABLE"),
    ]
    rows += [(f"suppression at {_freq(f)}", f"{v:.3g}x") for f, v in s.suppression_at.items()]
    return rows


def report(s: Suggestion, current: Suggestion | None = None) -> str:
    """The proposal as config lines, then its margins (next to the current gains' if given)."""
    lines = [
        "Suggested gains (PI; the pendulum resonance limits the crossover):",
        "[controller]",
        f"kp_v_per_m = {_toml_float(s.kp_v_per_m)}",
        f"ki_v_per_m_s = {_toml_float(s.ki_v_per_m_s)}",
        f"kd_v_s_per_m = {_toml_float(s.kd_v_s_per_m)}",
        "",
    ]
    ours = _rows(s)
    if current is None:
        lines += [f"{name:<28}{value}" for name, value in ours]
    else:
        lines.append(f"{'':<28}{'suggested':<26}current")
        lines += [f"{name:<28}{value:<26}{other}"
                  for (name, value), (_, other) in zip(ours, _rows(current), strict=True)]
    lines += [
        "",
        "suppression = |1 + L|: open-loop over closed-loop disturbance amplitude.",
        "Linear model (zero-order hold at the loop rate, one sample from reading to effect);",
        "ADC quantization, piezo and output slew, output limits and anti-windup are ignored.",
    ]
    return "\n".join(lines)


def plot(params: PlantParams, rate_hz: float, s: Suggestion, path: str | Path) -> Path:
    """Bode (|L| and phase) and Nyquist of the loop with these gains; PNG at 120 dpi.

    The Nyquist panel is zoomed on -1 with the |L| = 1/2 circle the resonance must stay
    inside; the integrator's branch toward -j infinity runs off it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from leveler.analysis.plots import sci

    loop = (controller_tf(s.kp_v_per_m, s.ki_v_per_m_s, s.kd_v_s_per_m, s.d_filter_tau_s,
                          rate_hz) * plant_tf(params, rate_hz))
    f_hz = _grid_hz(params, rate_hz, 1e-5)
    resp = _response(loop, f_hz)

    fig = Figure(figsize=(12, 6), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2, width_ratios=(3, 2))
    mag = fig.add_subplot(grid[0, 0])
    phase = fig.add_subplot(grid[1, 0], sharex=mag)
    nyq = fig.add_subplot(grid[:, 1])
    mag.loglog(f_hz, np.abs(resp), linewidth=1.2)
    mag.axhline(1.0, color="0.3", linewidth=0.8)
    mag.axhline(RESONANCE_LOOP_GAIN_MAX, color="C3", linestyle=":", linewidth=1,
                label=f"|L| = {RESONANCE_LOOP_GAIN_MAX} (6 dB)")
    for f in SUPPRESSION_HZ:
        mag.axvline(f, color="0.3", linestyle=":", linewidth=0.8)
        mag.annotate(_freq(f), (f, 1), xycoords=("data", "axes fraction"), xytext=(2, -2),
                     textcoords="offset points", va="top", fontsize=8, color="0.3")
    if math.isfinite(s.crossover_hz):
        # a point on |L| = 1, not a vertical line: that would cross the frequency names
        mag.plot([s.crossover_hz], [1.0], "o", color="C2", markersize=6,
                 label=f"crossover {_freq(s.crossover_hz)}")
    mag.set_ylabel("|L| [V/V]")
    mag.legend(fontsize=8, loc="upper right")
    mag.set_title(f"kp {sci(s.kp_v_per_m)} V/m, ki {sci(s.ki_v_per_m_s)} V/(m s), "
                  f"kd {sci(s.kd_v_s_per_m)} V s/m: phase margin {s.phase_margin_deg:.1f} deg, "
                  f"gain margin {s.gain_margin_db:.1f} dB", fontsize=10)
    fig.suptitle("Loop gain L = controller [V/m] × plant [m/V]: Bode and Nyquist", fontsize=11)
    phase.semilogx(f_hz, np.degrees(np.unwrap(np.angle(resp))), linewidth=1.2)
    phase.axhline(-180.0, color="0.3", linewidth=0.8)
    phase.set_xlabel("Frequency [Hz]")
    phase.set_ylabel("phase of L [deg]")
    for ax in (mag, phase):
        ax.grid(True, which="major", alpha=0.5)
        ax.grid(True, which="minor", alpha=0.2)

    angle = np.linspace(0, 2 * np.pi, 361)
    nyq.plot(resp.real, resp.imag, linewidth=1.2, label="L, f > 0")
    nyq.plot(resp.real, -resp.imag, linewidth=0.8, linestyle="--", color="C0", label="f < 0")
    nyq.plot(np.cos(angle), np.sin(angle), color="0.6", linewidth=0.8)
    nyq.plot(RESONANCE_LOOP_GAIN_MAX * np.cos(angle), RESONANCE_LOOP_GAIN_MAX * np.sin(angle),
             color="C3", linestyle=":", linewidth=1)
    nyq.plot([-1.0], [0.0], "x", color="C3", markersize=9, label="-1")
    nyq.set_xlim(-2.0, 1.5)
    nyq.set_ylim(-2.0, 2.0)
    nyq.set_aspect("equal")
    nyq.set_xlabel("Re L [V/V]")
    nyq.set_ylabel("Im L [V/V]")
    nyq.set_title("Nyquist, zoomed on -1", fontsize=10)
    nyq.grid(True, alpha=0.4)
    nyq.legend(fontsize=8, loc="lower right")

    out = Path(path)
    fig.savefig(out, dpi=120, format="png")
    return out
