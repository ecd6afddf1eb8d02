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
    from leveler.analysis.spectral import Spectrum

# The band edges and the decade in between where the stand's noise is specified.
_MARKERS_HZ = ((1e-4, "0.1 mHz"), (1e-3, "1 mHz"), (1e-2, "10 mHz"))


def plot_asd(
    curves: Sequence[tuple[str, Spectrum]], path: str | Path, *, ylabel: str, title: str = ""
) -> Path:
    """Log-log plot of amplitude spectral densities, one labelled line per curve; PNG at 120 dpi.

    Dotted vertical lines mark 0.1, 1 and 10 mHz where they fall inside the plotted band
    (outside it they would only stretch the axis).
    """
    if not curves:
        raise ValueError("plot_asd needs at least one (label, Spectrum) curve")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for label, spectrum in curves:
        ax.loglog(spectrum.freq_hz, spectrum.asd, label=label, linewidth=1.2)
    f_lo = min(float(s.freq_hz.min()) for _, s in curves)
    f_hi = max(float(s.freq_hz.max()) for _, s in curves)
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
    if title:
        ax.set_title(title)
    ax.grid(True, which="major", alpha=0.5)
    ax.grid(True, which="minor", alpha=0.2)
    ax.legend()
    out = Path(path)
    fig.savefig(out, dpi=120, format="png")
    return out


def block_means(t: np.ndarray, *series: np.ndarray,
                points: int = 2000) -> tuple[np.ndarray, list[np.ndarray]]:
    """Block averages (about `points` of them) of a time axis and series: a night of
    10 Hz samples drawn one by one is a band of noise, its minute averages show the drift."""
    block = max(len(t) // points, 1)
    n = len(t) // block * block
    def avg(x: np.ndarray) -> np.ndarray:
        return x[:n].reshape(-1, block).mean(axis=1)
    return avg(t), [avg(x) for x in series]
