"""What the search leaves: lines in the held-out residual that no effect family explained.

When the search stops, the held-out part's residual is compared with its smooth noise
spectrum bin by bin (`leveler.analysis.whittle`). A periodogram bin over a correct
spectrum is exponentially distributed, so with n bins looked at, z > ln(n / alpha) happens
by chance in a fraction alpha of logs: that is the threshold, the look-elsewhere cost
included. A line beyond it that the training part shows too is structure the model
misses and no family could name; saying so, with where it lives, is better than naming the
nearest wrong family or nothing.

Where it lives: the band, and the coherence of the residual with the piezo command and the
logged temperature at those frequencies. In a closed loop any tilt the model misses is
coherent with the command (the loop answers it), so a high command coherence alone does
not point at the actuator; a high temperature coherence points at a thermal path. Lines
that crowd into one band are fitted as a bump (`leveler.analysis.bump`): a mode rung by
its own noise, whose frequency, Q and rms say which part of the stand it may be.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.signal import coherence

from leveler.analysis.bump import Bump, Spectra
from leveler.analysis.nuisance import Projection
from leveler.analysis.predict import Measured
from leveler.analysis.whittle import Blocks, Whitener

#: the chance that a log whose model is right is said to hold unexplained structure
FALSE_ALARM = 0.01
_FIRST_BIN = 4  # the lowest bins hold the offset and trends; the noise fit leaves them out


@dataclass
class Leftover:
    """Significant lines left in the held-out residual."""

    f_hz: list[float]  # the strongest, at most five
    z: list[float]  # periodogram over the noise spectrum there
    threshold: float
    band: str
    coherence_command: float | None
    coherence_temperature: float | None
    bump: Bump | None = None  # the lines' power as a mode rung by noise, if it is one

    def describe(self) -> str:
        lines = ", ".join(f"{_hz(f)} (z {z:.0f})" for f, z in
                          zip(self.f_hz, self.z, strict=True))
        where = []
        if self.coherence_command is not None:
            where.append(f"coherence with the piezo command {self.coherence_command:.2f}")
        if self.coherence_temperature is not None:
            where.append(f"with the temperature {self.coherence_temperature:.2f}")
        if self.bump is not None:
            b = self.bump
            where.append(f"their power is a bump at {_hz(b.f0_hz)}, Q {b.q:.3g}, "
                         f"{b.rms_m * 1e9:.3g} nm rms: a mode rung by its own noise?")
        return (f"unexplained structure in {self.band}: {lines} stand above the noise "
                f"(threshold z {self.threshold:.1f}, {FALSE_ALARM * 100:g} % false alarms); "
                + "; ".join(where))

    def as_dict(self) -> dict[str, object]:
        return {"f_hz": self.f_hz, "z": self.z, "threshold": self.threshold,
                "band": self.band, "coherence_command": self.coherence_command,
                "coherence_temperature": self.coherence_temperature,
                "bump": None if self.bump is None else {
                    "f0_hz": self.bump.f0_hz, "q": self.bump.q, "rms_m": self.bump.rms_m,
                    "deviance": self.bump.deviance}}


def _hz(f: float) -> str:
    return f"{f:.4g} Hz" if f >= 1.0 else f"{f * 1e3:.4g} mHz"


def _zscores(residual: np.ndarray, w: Whitener, nuis: Projection
             ) -> tuple[np.ndarray, np.ndarray]:
    """(f, z) of the residual with the recalibrated knobs solved out, from bin _FIRST_BIN."""
    nb = len(w.f_hz)
    e = nuis.residual(w.whiten(residual))[1][:2 * nb]
    return w.f_hz[_FIRST_BIN:], (e[:nb] ** 2 + e[nb:] ** 2)[_FIRST_BIN:]


#: a mode rung by noise fitted near a frequency on some spectra: the bump, and why it is
#: no such mode ("" if it is one); diagnose's own rule (`leveler.analysis.diagnose`)
ModeFit = Callable[[Spectra, float], tuple[Bump, str]]


def leftover(meas: Measured, residual: np.ndarray, train: tuple[Whitener, Projection],
             test: tuple[Whitener, Projection],
             bands_hz: dict[str, tuple[float, float]], mode_near: ModeFit) -> Leftover | None:
    """Lines of `residual` (full length) beyond the look-elsewhere threshold in the
    held-out part (`test`: its whitener, fitted to this residual, and the knobs) that stand
    beyond it in the training part as well; None if there are none. Their power is fitted
    as a mode rung by noise with `mode_near`, the search's own fit and rule.

    The knobs are solved out first, as in every comparison diagnose makes (the cooler's
    level, above all: a cooler 8 % off in a log leaves its comb). A line must be seen in
    both parts: a chance excursion is not, and a disturbance that is really there is."""
    f, z = _zscores(residual, *test)
    threshold = math.log(len(z) / FALSE_ALARM)
    f_tr, z_tr = _zscores(residual, *train)
    seen = z_tr > math.log(len(z_tr) / FALSE_ALARM)
    df = f[1] - f[0]
    hits = [i for i in np.flatnonzero(z > threshold)
            if np.any(seen & (np.abs(f_tr - f[i]) <= df))]
    if not hits:
        return None
    top = np.array(hits)[np.argsort(z[hits])[::-1][:5]]
    f0 = float(f[top[0]])
    band = next((name for name, (lo, hi) in bands_hz.items() if lo <= f0 < hi), "")
    w = test[0]
    seg = residual[w.span]
    fs = 1.0 / meas.dt_s
    nper = max(len(seg) // 8, 16)

    def coh(other: np.ndarray | None) -> float | None:
        if other is None or np.ptp(other[w.span]) == 0:
            return None
        fc, c = coherence(seg, other[w.span], fs=fs, nperseg=nper)
        return float(np.max(np.interp(f[top], fc, c)))

    return Leftover([float(v) for v in f[top]], [float(v) for v in z[top]], threshold, band,
                    coh(meas.u_v), coh(meas.sig.temperature_k),
                    _bump(residual, train[0], w, f0, len(z), mode_near))


def _bump(residual: np.ndarray, train: Whitener, test: Whitener, f0_hz: float,
          bins: int, mode_near: ModeFit) -> Bump | None:
    """The lines' power as a band-pass bump, fitted on the held-out block and seen in the
    training one beyond a penalty for its three parameters; None if it is no mode (a
    line, a comb: `mode_near`'s rule) or the training block does not show it."""
    bump, why = mode_near(Spectra(Blocks([test]), residual), f0_hz)
    if why:
        return None
    seen = Spectra(Blocks([train]), residual).deviance(bump.f0_hz, bump.q, bump.rms_m)
    return bump if seen > 3 * math.log(2 * bins) else None
