"""The sanity gate on held-out blocks: an accepted effect must not make any band of the
residual's spectrum worse, measured against the noise spectrum (issue 17, part 7).

Held-out evidence is a sum over every bin: a candidate can win it by explaining a strong
band while it adds power that is not in the data in another, and that trade is a wrong
form or a wrong name, not a finding. Per band, each bin's residual power over the noise
spectrum (1 where the model explains all but the noise) is compared with and without the
candidate, on the held-out blocks, with the knobs solved as the candidate is scored.
"""

from __future__ import annotations

import math

import numpy as np

from leveler.analysis.whittle import ENBW_BINS, Blocks

#: a band is worse when its normalised power rises by this many standard errors ...
WORSE_SIGMA = 4.0
#: ... and by this share of what it was (the forms and the noise spectrum are approximations)
WORSE_REL = 0.1
#: fewer bins than this in a band say nothing about it
MIN_BINS = 8


def bin_power(w: Blocks, white: np.ndarray) -> np.ndarray:
    """Per bin of `w` (in `w.f_hz`'s order), the power of a whitened residual (`w.whiten`'s
    layout: each block's real parts, then its imaginary parts): about 1 where the noise
    spectrum holds."""
    out, i = [], 0
    for p in w.parts:
        nb = len(p.f_hz)
        out.append(white[i:i + nb] ** 2 + white[i + nb:i + 2 * nb] ** 2)
        i += 2 * nb
    return np.concatenate(out)


def band_changes(f_hz: np.ndarray, before: np.ndarray, after: np.ndarray,
                 change: np.ndarray, bands_hz: dict[str, tuple[float, float]]
                 ) -> dict[str, tuple[float, float, float]]:
    """Per band with MIN_BINS bins (the mean itself left out): (mean normalised power
    before, after, the rise in standard errors). `change`: the power of the difference of
    the two whitened residuals. Where the candidate adds c to a residual of noise n, a
    bin's power rises by |c|^2 - 2 Re(n c*), whose spread is sqrt(2) |c| in noise units:
    the rise of a band is weighed against that, not against the bins' scatter, which a
    single strong line would make look like noise."""
    out = {}
    for name, (lo, hi) in bands_hz.items():
        sel = (f_hz >= lo) & (f_hz < hi) & (f_hz > 0)
        if np.count_nonzero(sel) < MIN_BINS:
            continue
        rise = float(np.sum(after[sel] - before[sel]))
        spread = math.sqrt(2.0 * ENBW_BINS * float(np.sum(change[sel])))
        out[name] = (float(np.mean(before[sel])), float(np.mean(after[sel])),
                     rise / spread if spread > 0 else 0.0)
    return out


def worse_band(changes: dict[str, tuple[float, float, float]]) -> str:
    """Why the candidate fails the gate ("" if it passes): the band it makes worse."""
    for name, (before, after, z) in changes.items():
        if z > WORSE_SIGMA and after - before > WORSE_REL * before:
            return (f"makes the {name} band worse on the held-out part: residual power "
                    f"{before:.3g} -> {after:.3g} of the noise ({z:.1f} standard errors)")
    return ""
