"""Figures of the stand's noise spectra (e.g. open loop vs closed loop).

matplotlib is imported inside the functions so that `import leveler` stays fast on the
controller; the figure is drawn on an Agg canvas directly, without pyplot, so no GUI backend
or global figure state is involved (safe from scripts, tests and threads).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    from leveler.analysis.spectral import Spectrum
    from leveler.loop.pid import ControllerConfig
    from leveler.virtual import Run

# The band edges and the decade in between where the stand's noise is specified.
_MARKERS_HZ = ((1e-4, "0.1 mHz"), (1e-3, "1 mHz"), (1e-2, "10 mHz"))

# Figure 15 of the paper: the in-loop sensor's ASD at 0.1 mHz [m/√Hz], loop open and closed.
PAPER_FIG15_HZ = 1e-4
PAPER_FIG15_M_RTHZ = {"open": 5.7e-6, "closed": 2.8e-7}


def plot_asd(
    curves: Sequence[tuple[str, Spectrum]], path: str | Path, *, ylabel: str, title: str = "",
    zoom_hz: tuple[float, float] | None = None,
) -> Path:
    """Log-log plot of amplitude spectral densities, one labelled line per curve; PNG at 120 dpi.

    Dotted vertical lines mark 0.1, 1 and 10 mHz where they fall inside the plotted band
    (outside it they would only stretch the axis). `zoom_hz` adds an inset magnifying that
    band, for lines too close together to tell apart on the log axis.
    """
    if not curves:
        raise ValueError("plot_asd needs at least one (label, Spectrum) curve")
    fig = _figure((8, 5))
    ax = fig.add_subplot()
    lines = _draw_asd(ax, curves, ylabel)
    if zoom_hz is not None:
        _zoom(ax, lines, zoom_hz, ylabel)
    if title:
        ax.set_title(title)
    ax.legend()
    return _save(fig, path)


def plot_sim(opened: Run, closed: Run, fs_hz: float, path: str | Path, *,
             controller: ControllerConfig, duration_s: float, seed: int) -> Path:
    """`leveler sim --plot`: open vs closed loop, (a) the in-loop sensor against the paper's
    Fig. 15 point and (b) the true platform tilt, which only a simulation knows: a loop can
    quiet its own sensor without levelling the platform. The gains are in the title because
    the curves mean nothing without them."""
    from leveler.analysis.spectral import lpsd

    runs = {"open": opened, "closed": closed}
    fig = _figure((8, 8))
    sensor_ax, tilt_ax = fig.subplots(2, 1, sharex=True)
    lines = _draw_asd(sensor_ax,
                      [(f"{k} loop", lpsd(r.sensor_m, fs_hz)) for k, r in runs.items()],
                      "displacement ASD [m/√Hz]", extra_hz=[PAPER_FIG15_HZ])
    for (state, value), line, marker in zip(PAPER_FIG15_M_RTHZ.items(), lines, "os",
                                            strict=True):
        sensor_ax.plot([PAPER_FIG15_HZ], [value], marker, color=line.get_color(),
                       markerfacecolor="none", markersize=9, markeredgewidth=1.8,
                       label=f"paper, {state} {value * 1e6:.2g} µm/√Hz")
    sensor_ax.set_title("(a) in-loop sensor: pendulum-end displacement", fontsize=10)
    _draw_asd(tilt_ax, [(f"{k} loop", lpsd(r.tilt_rad, fs_hz)) for k, r in runs.items()],
              "tilt ASD [rad/√Hz]", extra_hz=[PAPER_FIG15_HZ])
    tilt_ax.set_title("(b) true platform tilt, out of loop (known only in simulation)",
                      fontsize=10)
    for ax in (sensor_ax, tilt_ax):
        ax.legend(fontsize=9)
    sensor_ax.label_outer()
    c = controller
    fig.suptitle(f"leveler sim: {duration_s / 3600:g} h at {fs_hz:g} Hz, seed {seed}\n"
                 f"PID kp {sci(c.kp_v_per_m)} V/m, ki {sci(c.ki_v_per_m_s)} V/(m s), "
                 f"kd {sci(c.kd_v_s_per_m)} V s/m, D filter {sci(c.d_filter_tau_s)} s",
                 fontsize=11)
    return _save(fig, path)


def sci(x: float) -> str:
    """2.2e+07 as 2.2×10⁷ (mathtext): a title is read, not parsed."""
    mantissa, exponent = f"{x:.2e}".split("e")
    if x == 0 or -2 <= int(exponent) <= 2:
        return f"{x:.3g}"
    return f"{float(mantissa):.3g}×10$^{{{int(exponent)}}}$"


def _figure(size_in: tuple[float, float]) -> Figure:
    """A figure on its own Agg canvas (no pyplot: see the module docstring)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size_in, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | Path) -> Path:
    out = Path(path)
    fig.savefig(out, dpi=120, format="png")
    return out


def _draw_asd(ax: Axes, curves: Sequence[tuple[str, Spectrum]], ylabel: str,
              extra_hz: Sequence[float] = ()) -> list[Line2D]:
    """The curves on log-log axes with the band markers, labels and grid; no legend, so the
    caller can add its own lines first. `extra_hz`: frequencies the caller will mark
    beyond the curves, where the band markers should reach too."""
    lines = [ax.loglog(spectrum.freq_hz, spectrum.asd, label=label, linewidth=1.2)[0]
             for label, spectrum in curves]
    f_lo = min([float(s.freq_hz.min()) for _, s in curves] + list(extra_hz))
    f_hi = max([float(s.freq_hz.max()) for _, s in curves] + list(extra_hz))
    for f_hz, text in _MARKERS_HZ:
        if f_lo <= f_hz <= f_hi:
            ax.axvline(f_hz, color="0.3", linestyle=":", linewidth=1)
            ax.annotate(
                text,
                (f_hz, 1),
                xycoords=("data", "axes fraction"),
                xytext=(2, -2),
                textcoords="offset points",
                va="top",
                fontsize=8,
                color="0.3",
            )
    ax.set_xlabel("Frequency [Hz]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", alpha=0.5)
    ax.grid(True, which="minor", alpha=0.2)
    return lines


def _zoom(ax: Axes, lines: Sequence[Line2D], band_hz: tuple[float, float], ylabel: str) -> None:
    """An inset, upper left, with `lines` between band_hz on a linear frequency axis (the
    band is narrow), and the zoomed box outlined on `ax`."""
    from matplotlib.ticker import MaxNLocator, StrMethodFormatter

    f_lo, f_hi = band_hz
    inset = ax.inset_axes((0.12, 0.42, 0.33, 0.5))
    peak, floor = 0.0, np.inf
    for line in lines:
        f, asd = (np.asarray(v, dtype=float) for v in line.get_data())
        inside = (f >= f_lo) & (f <= f_hi)
        inset.plot(f[inside], asd[inside], color=line.get_color(), linewidth=1.0)
        peak, floor = max(peak, float(asd[inside].max())), min(floor, float(asd[inside].min()))
    inset.set_yscale("log")
    inset.set_xlim(f_lo, f_hi)
    inset.set_ylim(floor / 1.5, peak * 1.5)
    inset.xaxis.set_major_locator(MaxNLocator(4))
    inset.xaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    inset.set_xlabel("Frequency [Hz]", fontsize=7)
    inset.set_ylabel(ylabel, fontsize=7)
    inset.tick_params(labelsize=7)
    inset.grid(True, which="major", alpha=0.4)
    ax.indicate_inset_zoom(inset, edgecolor="0.3")


def block_means(t: np.ndarray, *series: np.ndarray,
                points: int = 2000) -> tuple[np.ndarray, list[np.ndarray]]:
    """Block averages (about `points` of them) of a time axis and series: a night of
    10 Hz samples drawn one by one is a band of noise, its minute averages show the drift."""
    block = max(len(t) // points, 1)
    n = len(t) // block * block
    def avg(x: np.ndarray) -> np.ndarray:
        return x[:n].reshape(-1, block).mean(axis=1)
    return avg(t), [avg(x) for x in series]
