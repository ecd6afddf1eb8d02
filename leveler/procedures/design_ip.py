"""Inverted-pendulum tilt amplifier design: amplification N against counterweight mass.

The paper (Cong et al. 2024, section 3.2, Figure 8) picks the counterweight of its tilt
amplifier by solving the static balance m g L_cm sin(theta + phi) = k theta at a 1 mrad
reference tilt phi for a range of counterweight masses. This is that procedure with our
geometry, not the paper's Simscape model: a flexure pivot of stiffness k carries a rigid
frame (mass m_f, centre of mass L_f above the pivot) and a point counterweight m_cw at
height h_cw, so

    m g L_cm = g (m_f L_f + m_cw h_cw),    small-angle N = 1 / (k / (m g L_cm) - 1).

The default stand (config/sim.toml) is a 185 g mass 49.6 mm above a 0.1 N m/rad flexure on
a massless rod, i.e. the paper's example m g L_cm = 0.09 N m/rad, N = 9: the configured
pendulum mass is read as the counterweight, and the frame is zero unless given.

Past the stability limit m g L_cm = k the upright pendulum has no stable equilibrium (the
flexure would have to hold it leaning over by tenths of a radian); those masses are
reported as unstable, not solved.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

from leveler.sim.params import PendulumParams
from leveler.sim.pendulum import equilibrium_angle


class DesignError(ValueError):
    """A request no counterweight meets, or a geometry that cannot work; the message says why."""


@dataclass(frozen=True, slots=True)
class IpModel:
    """The pendulum as a function of its counterweight; `base` supplies k, g and the rest."""

    base: PendulumParams
    cw_height_m: float
    frame_mass_kg: float = 0.0
    frame_com_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.cw_height_m > 0:
            raise DesignError(f"counterweight height must be > 0 m (above the pivot), got "
                              f"{self.cw_height_m:g}: below it, more mass amplifies less")
        if not self.frame_mass_kg >= 0:
            raise DesignError(f"frame mass must be >= 0 kg, got {self.frame_mass_kg:g}")
        if not self.stability_limit_kg > 0:
            raise DesignError(
                f"the frame alone is unstable: its m g L_cm = "
                f"{self.gravity_stiffness_nm_per_rad(0.0):.4g} N m/rad >= k = "
                f"{self.base.flexure_stiffness_nm_per_rad:.4g} N m/rad")

    def gravity_stiffness_nm_per_rad(self, cw_mass_kg: float) -> float:
        """m g L_cm of frame plus counterweight."""
        moment = self.frame_mass_kg * self.frame_com_m + cw_mass_kg * self.cw_height_m
        return self.base.gravity_m_per_s2 * moment

    def cw_mass_for(self, gravity_stiffness_nm_per_rad: float) -> float:
        """The counterweight mass that makes m g L_cm equal the given value."""
        g = self.base.gravity_m_per_s2
        frame_moment = self.frame_mass_kg * self.frame_com_m
        return (gravity_stiffness_nm_per_rad / g - frame_moment) / self.cw_height_m

    @property
    def stability_limit_kg(self) -> float:
        """Counterweight mass at which m g L_cm = k: small-angle N -> infinity."""
        return self.cw_mass_for(self.base.flexure_stiffness_nm_per_rad)

    def pendulum(self, cw_mass_kg: float) -> PendulumParams:
        """The whole pendulum; raises ValueError (PendulumParams') at or past the limit."""
        mass = self.frame_mass_kg + cw_mass_kg
        moment = self.frame_mass_kg * self.frame_com_m + cw_mass_kg * self.cw_height_m
        return dataclasses.replace(self.base, mass_kg=mass, com_length_m=moment / mass)


@dataclass(frozen=True, slots=True)
class Point:
    """One counterweight mass; the amplifications and angle are None past the limit."""

    cw_mass_kg: float
    gravity_stiffness_nm_per_rad: float
    n_small_angle: float | None
    n_at_tilt: float | None
    theta_rad: float | None

    @property
    def stable(self) -> bool:
        return self.n_small_angle is not None


def evaluate(model: IpModel, cw_mass_kg: float, tilt_rad: float) -> Point:
    """Small-angle N and the full non-linear N = theta / phi at the reference tilt."""
    try:
        p = model.pendulum(cw_mass_kg)
    except ValueError:
        return Point(cw_mass_kg, model.gravity_stiffness_nm_per_rad(cw_mass_kg), None, None,
                     None)
    theta = equilibrium_angle(p, tilt_rad)
    return Point(cw_mass_kg, p.gravity_stiffness_nm_per_rad, p.amplification,
                 theta / tilt_rad, theta)


def check_tilt(tilt_rad: float) -> None:
    if not 0 < tilt_rad < math.pi / 2:
        raise DesignError(f"reference tilt must lie in (0, pi/2) rad, got {tilt_rad:g}")


def max_amplification_at(tilt_rad: float) -> float:
    """The largest N = theta / phi a stable pendulum reaches at tilt phi: its value at the limit.

    At m g L_cm = k the balance reads u - sin(u) = phi with u = theta + phi (about
    (6 phi)^(1/3) for small phi), so unlike the small-angle N it stays finite: 180.8 at 1 mrad.
    """
    check_tilt(tilt_rad)
    u = brentq(lambda u: u - math.sin(u) - tilt_rad, 0.0, math.pi, xtol=1e-15)
    return float(u) / tilt_rad - 1.0


@dataclass(frozen=True, slots=True)
class Pick:
    """The counterweight for a requested N at the reference tilt."""

    target_n: float
    cw_mass_kg: float
    cw_mass_small_angle_kg: float
    point: Point
    dn_dm_per_kg: float


def pick(model: IpModel, target_n: float, tilt_rad: float) -> Pick:
    """The counterweight giving N = target_n at the reference tilt, from the exact inverse.

    theta = N phi fixes m g L_cm = k N phi / sin((N + 1) phi) in closed form, so no search
    is needed; the small-angle mass (m g L_cm = k N / (N + 1)) is given beside it, and
    dN/dm (small-angle) says how finely the counterweight must be trimmed.
    """
    if not target_n > 0:
        raise DesignError(f"the requested amplification N must be > 0, got {target_n:g}")
    n_max = max_amplification_at(tilt_rad)
    k = model.base.flexure_stiffness_nm_per_rad
    if target_n >= n_max:
        raise DesignError(
            f"no counterweight gives N = {target_n:g} at a {tilt_rad:g} rad tilt: a stable "
            f"pendulum stays below N = {n_max:.4g} there (reached at the stability limit, "
            f"m_cw = {model.stability_limit_kg:.4g} kg, where m g L_cm = k = {k:g} N m/rad); "
            "ask for a smaller N or design at a smaller --tilt-rad")
    gravity = k * target_n * tilt_rad / math.sin((target_n + 1) * tilt_rad)
    mass = model.cw_mass_for(gravity)
    if not mass > 0:
        frame = evaluate(model, 0.0, tilt_rad)
        raise DesignError(
            f"the frame alone already amplifies N = {frame.n_at_tilt:.4g} > {target_n:g} at "
            f"{tilt_rad:g} rad: no counterweight lowers it (lighten or lower the frame)")
    small = model.cw_mass_for(k * target_n / (target_n + 1))
    # dN/d(m g L_cm) = k / (k - m g L_cm)^2 = (N + 1)^2 / k, and d(m g L_cm)/dm_cw = g h_cw
    dn_dm = model.base.gravity_m_per_s2 * model.cw_height_m * (target_n + 1) ** 2 / k
    return Pick(target_n, mass, small, evaluate(model, mass, tilt_rad), dn_dm)


def _nice_step(span: float) -> float:
    """The smallest 1, 2 or 5 x 10^n that cuts span into at most 15 table rows."""
    base = 10.0 ** math.floor(math.log10(span / 15))
    return next(f * base for f in (1, 2, 5, 10) if f * base >= span / 15)


def default_range(model: IpModel, include_kg: float | None = None) -> tuple[float, float]:
    """0.5 to 1.05 times the stability limit, widened down to show `include_kg` (a pick),
    rounded out to the table step."""
    limit = model.stability_limit_kg
    lo = 0.5 * limit if include_kg is None else min(0.5 * limit, 0.8 * include_kg)
    step = _nice_step(1.05 * limit - lo)
    return max(math.floor(lo / step), 1) * step, math.ceil(1.05 * limit / step) * step


def table_masses(lo_kg: float, hi_kg: float, step_kg: float | None) -> list[float]:
    """lo, lo + step, ... <= hi; the step defaults to a round one giving 6 to 15 rows."""
    if not 0 < lo_kg < hi_kg:
        raise DesignError(f"the mass range needs 0 < MIN < MAX, got {lo_kg:g} {hi_kg:g} kg")
    step = _nice_step(hi_kg - lo_kg) if step_kg is None else step_kg
    if not step > 0:
        raise DesignError(f"--step-kg must be > 0, got {step:g}")
    n = math.floor((hi_kg - lo_kg) / step + 1e-9) + 1
    if n > 1000:
        raise DesignError(f"{n} table rows: choose a larger --step-kg (at most 1000 rows)")
    return [round(lo_kg + i * step, 12) for i in range(n)]


def plot_design(path: str | Path, model: IpModel, tilt_rad: float, lo_kg: float, hi_kg: float,
                chosen: Pick | None = None, *, title: str = "") -> Path:
    """N against counterweight mass, small-angle and non-linear, limit marked; PNG at 120 dpi.

    Log N axis: it shows N of order 1 and the divergence at the limit on one figure; the
    right axis is the equilibrium angle at the reference tilt (theta = N phi).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FormatStrFormatter, LogLocator

    limit = model.stability_limit_kg
    near = limit * (1.0 - np.geomspace(1e-6, 0.3, 150))  # resolve the steep approach
    masses = np.unique(np.concatenate([np.linspace(lo_kg, hi_kg, 400),
                                       near[(near >= lo_kg) & (near <= hi_kg)]]))
    points = [evaluate(model, float(m), tilt_rad) for m in masses]
    small = np.array([np.nan if p.n_small_angle is None else p.n_small_angle for p in points])
    full = np.array([np.nan if p.n_at_tilt is None else p.n_at_tilt for p in points])
    grams = masses * 1e3

    fig = Figure(figsize=(8, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.semilogy(grams, full, color="C0", linewidth=1.6,
                label=f"non-linear, at φ = {tilt_rad * 1e3:g} mrad")
    ax.semilogy(grams, small, color="C1", linestyle="--", linewidth=1.2,
                label="small angle: N = 1 / (k / (m g L_cm) − 1)")
    finite = full[np.isfinite(full) & (full > 0)]  # a frame below the pivot can give N < 0
    top = 2.0 * max_amplification_at(tilt_rad)
    bottom = 0.5 * float(finite.min()) if finite.size else 0.1
    ax.set_ylim(bottom, top)
    if lo_kg <= limit <= hi_kg:
        ax.axvline(limit * 1e3, color="C3", linewidth=1.2,
                   label=f"stability limit m g L_cm = k ({limit * 1e3:.1f} g)")
        ax.axvspan(limit * 1e3, hi_kg * 1e3, color="C3", alpha=0.12, linewidth=0,
                   label="unstable (no upright equilibrium)")
    if chosen is not None and lo_kg <= chosen.cw_mass_kg <= hi_kg:
        mg = chosen.cw_mass_kg * 1e3
        ax.plot([mg], [chosen.target_n], "o", color="k", zorder=5,
                label=f"N = {chosen.target_n:g}: {mg:.1f} g")
        ax.axhline(chosen.target_n, color="0.4", linestyle=":", linewidth=1)
    right = ax.secondary_yaxis("right", functions=(lambda n: n * tilt_rad * 1e3,
                                                   lambda t: t / (tilt_rad * 1e3)))
    right.set_ylabel(f"equilibrium angle θ at φ = {tilt_rad * 1e3:g} mrad [mrad]")
    for axis in (ax.yaxis, right.yaxis):  # 1, 2, 5, 10 rather than 10^0, 10^1
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FormatStrFormatter("%g"))
    ax.set_xlim(lo_kg * 1e3, hi_kg * 1e3)
    ax.set_xlabel("Counterweight mass [g]")
    ax.set_ylabel("Tilt amplification N = θ / φ")
    if title:
        ax.set_title(title)
    ax.grid(True, which="major", alpha=0.5)
    ax.grid(True, which="minor", alpha=0.2)
    ax.legend(loc="upper left", fontsize=9)
    out = Path(path)
    fig.savefig(out, dpi=120, format="png")
    return out
