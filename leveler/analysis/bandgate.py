"""The sanity gate on held-out blocks: an accepted effect must not make a band of the
residual's spectrum worse, measured against the noise spectrum (issue 17, part 7).

Held-out evidence is a sum over every bin: a candidate can win it by explaining a strong
band while it adds power that is not in the data in another, and that trade is a wrong
form or a wrong name, not a finding. Per band, each bin's residual power over the noise
spectrum (1 where the model explains all but the noise) is compared with and without the
candidate, on the held-out blocks, with the knobs solved as the candidate is scored.

The forms are approximations of a real stand's effects, so a band counts as worse only
when the rise is beyond the noise (WORSE_SIGMA), beyond the noise level itself or what was
there (WORSE_REL: a band the noise spectrum over-fitted, at 0.5, that comes back to 1 is
not worse), and a real share of what the candidate explains elsewhere (WORSE_SHARE).
On the independent generator's tuning logs (seeds 9003-9005), the rule without that share
stopped a strong Bouc-Wen loop's single play, which gives back 65 % of its held-out gain in
10-100 mHz, and also a medium one's that gave back about 2 % there and a strong
temperature coupling about 5 % in 1-10 mHz: right names, in forms a little off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from leveler.analysis.whittle import ENBW_BINS, Blocks

#: a band is worse when its normalised power rises by this many standard errors ...
WORSE_SIGMA = 4.0
#: ... by this share above what it was, or above the noise if it was below ...
WORSE_REL = 0.1
#: ... and by this share of what the candidate takes off the bands it improves
WORSE_SHARE = 0.2
#: fewer bins than this in a band say nothing about it
MIN_BINS = 8


@dataclass(frozen=True)
class BandChange:
    """One band of the held-out blocks, without and with a candidate."""

    before: float  # mean normalised power (1: the noise alone)
    after: float
    rise_sigma: float  # the rise in standard errors of the candidate's change
    gain: float  # summed power the candidate takes off the band (< 0: adds)
    judged: bool = True  # False: under MIN_BINS bins, its gain only counted


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
                 ) -> dict[str, BandChange]:
    """Each band (the mean itself left out), judged where it has MIN_BINS bins; a
    slow effect's gain in the few lowest bins still counts. `change`: the power of
    the difference of the two whitened residuals. Where the candidate adds c to a residual
    of noise n, a bin's power rises by |c|^2 - 2 Re(n c*), whose spread is sqrt(2) |c| in
    noise units: the rise is weighed against that, not against the bins' scatter, which a
    single strong line would make look like noise."""
    out = {}
    for name, (lo, hi) in bands_hz.items():
        sel = (f_hz >= lo) & (f_hz < hi) & (f_hz > 0)
        if not np.any(sel):
            continue
        rise = float(np.sum(after[sel] - before[sel]))
        spread = math.sqrt(2.0 * ENBW_BINS * float(np.sum(change[sel])))
        out[name] = BandChange(float(np.mean(before[sel])), float(np.mean(after[sel])),
                               rise / spread if spread > 0 else 0.0, -rise,
                               bool(np.count_nonzero(sel) >= MIN_BINS))
    return out


def worse_band(changes: dict[str, BandChange]) -> str:
    """Why the candidate fails the gate ("" if it passes): the band it makes worse."""
    explained = sum(max(c.gain, 0.0) for c in changes.values())
    for name, c in changes.items():
        if (c.judged and c.rise_sigma > WORSE_SIGMA
                and c.after > (1 + WORSE_REL) * max(c.before, 1.0)
                and -c.gain > WORSE_SHARE * explained):
            share = (f"{-c.gain / explained:.0%} of what it explains elsewhere"
                     if explained > 0 else "and it explains nothing elsewhere")
            return (f"makes the {name} band worse on the held-out part: residual power "
                    f"{c.before:.3g} -> {c.after:.3g} of the noise ({c.rise_sigma:.1f} "
                    f"standard errors), {share}")
    return ""
