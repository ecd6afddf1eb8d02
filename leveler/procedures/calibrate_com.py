"""Centre-of-mass calibration by dual-frequency modulation (paper sec. 3.3, Fig. 11).

The base pitch is modulated at f1 (0.1 Hz, 25 urad) and a calibration force at f2 (0.11 Hz,
1 uN) is applied at the same time. Both are torques on the same pendulum, so the displacement
lines at f1 and f2 have amplitudes L |H(f1)| M g sin(a1) l_cm and L |H(f2)| F2 L, with
H = 1 / (K0 - J w^2 + i lambda w). Their ratio gives

    l_cm = (A1 / A2) (F2 L / (M g sin a1)) |H(f2)| / |H(f1)|,

with the known force as the scale: the sensor gain and K0 cancel, only the small change of |H|
between f1 and f2 (2.3 % with the defaults) is taken from the pendulum model. The counterweight
position follows from the mass model: l_cm2 = l_cm (m1 + m2) / m2.

A1 and A2 are read from ASD peaks (leveler.analysis.spectral.lpsd) on a dense axis around the lines,
with few averages so that the bins are 0.4 mHz wide and the 10 mHz apart lines do not leak into each
other. The line amplitude is ASD sqrt(2 ENBW), ENBW = 1.5 fs / segment for the Hann window; on this
axis both lines get the longest segment, so the ASD ratio is the amplitude ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from leveler.analysis.spectral import Spectrum, lpsd
from leveler.procedures.stiffness import SENSOR_NOISE_M_PER_RTHZ
from leveler.sim.torsion import (
    DEFAULT_BALANCED_MASS_KG,
    DEFAULT_COUNTERWEIGHT_KG,
    TorsionParams,
    com_offset_m,
    sensor_noise,
    simulate,
)

TILT_AMPLITUDE_RAD = 25e-6
TILT_FREQUENCY_HZ = 0.1
FORCE_AMPLITUDE_N = 1e-6
FORCE_FREQUENCY_HZ = 0.11
COUNTERWEIGHT_OFFSETS_M = (1e-3, 2e-3, 3e-3, 4e-3, 5e-3)
DURATION_S = 4000.0
FS_HZ = 5.0
_K_DES = 10  # averages wanted: few, for 0.4 mHz bins that separate the two lines cleanly
_PEAK_BAND = (0.95, 1.05)  # readout axis: from 0.95 f_low to 1.05 f_high
_PEAK_POINTS = 600  # < 0.1 bin per axis step: the Hann scalloping loss stays below 0.1 %


@dataclass(frozen=True)
class ComResult:
    """One calibration: truth, the two ASD peaks, and what they give."""

    counterweight_offset_m: float  # l_cm2 set in the simulator
    com_offset_m: float  # true l_cm = m2 / (m1 + m2) l_cm2
    tilt_peak_asd_m_per_rthz: float  # ASD at f1
    force_peak_asd_m_per_rthz: float  # ASD at f2
    tilt_line_m: float  # displacement amplitude at f1
    force_line_m: float  # displacement amplitude at f2
    recovered_com_offset_m: float
    recovered_counterweight_offset_m: float
    displacement_m: np.ndarray  # the simulated record, for the figure

    @property
    def relative_error(self) -> float:
        return self.recovered_com_offset_m / self.com_offset_m - 1


def figure_spectrum(x: np.ndarray, fs_hz: float) -> Spectrum:
    """ASD from 10 mHz to 1 Hz for the Fig. 11 plot, with the readout's resolution."""
    return lpsd(x, fs_hz, fmin_hz=0.01, fmax_hz=min(1.0, 0.45 * fs_hz), n_freqs=800,
                k_des=_K_DES)


def _peak(spec: Spectrum, f_hz: float, fs_hz: float) -> tuple[float, float]:
    """Largest ASD within a bin of f_hz and the sine amplitude it means: ASD sqrt(3 fs / seg)."""
    near = np.abs(spec.freq_hz - f_hz) <= fs_hz / spec.segment_len
    i = int(np.flatnonzero(near)[np.argmax(spec.asd[near])])
    asd = float(spec.asd[i])
    return asd, asd * math.sqrt(3 * fs_hz / float(spec.segment_len[i]))


def response_magnitude(p: TorsionParams, f_hz: float) -> float:
    """|H(f)| = |1 / (K0 - J w^2 + i lambda w)| [rad/(N m)]."""
    w = 2 * math.pi * f_hz
    return 1 / abs(complex(p.stiffness_nm_per_rad - p.inertia_kgm2 * w * w,
                           p.damping_nms_per_rad * w))


def calibrate(p: TorsionParams, displacement_m: np.ndarray, fs_hz: float, *,
              tilt_amplitude_rad: float = TILT_AMPLITUDE_RAD,
              tilt_frequency_hz: float = TILT_FREQUENCY_HZ,
              force_amplitude_n: float = FORCE_AMPLITUDE_N,
              force_frequency_hz: float = FORCE_FREQUENCY_HZ,
              ) -> tuple[float, tuple[float, float], tuple[float, float]]:
    """l_cm from a displacement record; also (ASD, amplitude) of the tilt and the force line.

    Uses from `p` only what is known without the unknown offset: M, g, L and the dynamics
    (K0, J, lambda) for the |H(f2)| / |H(f1)| correction.
    """
    lo, hi = _PEAK_BAND
    f_lo, f_hi = lo * min(tilt_frequency_hz, force_frequency_hz), hi * max(
        tilt_frequency_hz, force_frequency_hz)
    spec = lpsd(displacement_m, fs_hz, fmin_hz=f_lo, fmax_hz=f_hi, n_freqs=_PEAK_POINTS,
                k_des=_K_DES)
    tilt = _peak(spec, tilt_frequency_hz, fs_hz)
    force = _peak(spec, force_frequency_hz, fs_hz)
    h_ratio = response_magnitude(p, force_frequency_hz) / response_magnitude(
        p, tilt_frequency_hz)
    l_cm = (tilt[1] / force[1]) * force_amplitude_n * p.arm_m / (
        p.mass_kg * p.gravity_m_per_s2 * math.sin(tilt_amplitude_rad)) * h_ratio
    return l_cm, tilt, force


def calibration_run(p: TorsionParams, rng: np.random.Generator, *,
                    duration_s: float = DURATION_S, fs_hz: float = FS_HZ,
                    tilt_amplitude_rad: float = TILT_AMPLITUDE_RAD,
                    tilt_frequency_hz: float = TILT_FREQUENCY_HZ,
                    force_amplitude_n: float = FORCE_AMPLITUDE_N,
                    force_frequency_hz: float = FORCE_FREQUENCY_HZ,
                    noise_m_per_rthz: float = SENSOR_NOISE_M_PER_RTHZ) -> np.ndarray:
    """End displacement L theta + sensor noise under the two modulations applied together."""
    n = round(duration_s * fs_hz)
    t = np.arange(n) / fs_hz
    pitch = tilt_amplitude_rad * np.sin(2 * math.pi * tilt_frequency_hz * t)
    force = force_amplitude_n * np.sin(2 * math.pi * force_frequency_hz * t)
    theta = simulate(p, 1 / fs_hz, force, pitch_rad=pitch)
    return p.arm_m * theta + sensor_noise(rng, n, noise_m_per_rthz, fs_hz)


def calibrate_offsets(base: TorsionParams | None = None,
                      offsets_m: tuple[float, ...] = COUNTERWEIGHT_OFFSETS_M, *,
                      balanced_mass_kg: float = DEFAULT_BALANCED_MASS_KG,
                      counterweight_kg: float = DEFAULT_COUNTERWEIGHT_KG,
                      duration_s: float = DURATION_S, fs_hz: float = FS_HZ,
                      tilt_amplitude_rad: float = TILT_AMPLITUDE_RAD,
                      tilt_frequency_hz: float = TILT_FREQUENCY_HZ,
                      force_amplitude_n: float = FORCE_AMPLITUDE_N,
                      force_frequency_hz: float = FORCE_FREQUENCY_HZ,
                      seed: int = 0) -> list[ComResult]:
    """Simulate the calibration with the counterweight at each offset (along y) and recover it."""
    base = TorsionParams() if base is None else base
    if abs(tilt_frequency_hz - force_frequency_hz) < 6 / duration_s:  # 4 bins of 1.5 / T
        raise ValueError("f1 and f2 are too close for this run length: the lines would merge")
    mods = {"tilt_amplitude_rad": tilt_amplitude_rad, "tilt_frequency_hz": tilt_frequency_hz,
            "force_amplitude_n": force_amplitude_n, "force_frequency_hz": force_frequency_hz}
    rng = np.random.default_rng(seed)
    results = []
    for offset in offsets_m:
        l_cm = com_offset_m(balanced_mass_kg, counterweight_kg, offset)
        p = replace(base, mass_kg=balanced_mass_kg + counterweight_kg, com_y_m=l_cm)
        x = calibration_run(p, rng, duration_s=duration_s, fs_hz=fs_hz, **mods)
        recovered, tilt, force = calibrate(p, x, fs_hz, **mods)
        results.append(ComResult(
            counterweight_offset_m=offset, com_offset_m=l_cm,
            tilt_peak_asd_m_per_rthz=tilt[0], force_peak_asd_m_per_rthz=force[0],
            tilt_line_m=tilt[1], force_line_m=force[1], recovered_com_offset_m=recovered,
            recovered_counterweight_offset_m=recovered * (balanced_mass_kg + counterweight_kg)
            / counterweight_kg,
            displacement_m=x))
    return results
