"""Plant parameters in SI units, defaults from the paper (see PHYSICS.md).

One `PlantParams` describes the whole simulated stand; it is the `[plant]` table of a
config file, so a fitted model is just another config file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from leveler.sim.effects import EffectsParams
from leveler.typed_config import non_negative, positive

G_STANDARD = 9.80665


@dataclass(frozen=True, slots=True)
class PendulumParams:
    """Pendulum tiltmeter: a mass on a flexure, sensed at its end, of either kind.

    `com_length_m` is signed: the centre of mass above the pivot (> 0) makes today's
    inverted amplifier, N = 1 / (k / (m g L) - 1); below it (< 0, a hanging pendulum or
    beam balance with offset d = -L) the restoring torque is k + m g d and the static
    response -m g d / (k + m g d). Defaults give the paper's example k = 0.1 N m/rad,
    m g L = 0.09 N m/rad (N = 9).
    """

    model: Literal["linear", "nonlinear"] = "linear"
    mass_kg: float = positive(0.185)
    com_length_m: float = 0.0496
    flexure_stiffness_nm_per_rad: float = positive(0.1)
    inertia_kgm2: float = positive(5.0e-4)
    damping_nms_per_rad: float = non_negative(1.2e-4)
    sensor_arm_m: float = positive(0.05)
    gravity_m_per_s2: float = positive(G_STANDARD)

    def __post_init__(self) -> None:
        mgl = self.gravity_stiffness_nm_per_rad
        k = self.flexure_stiffness_nm_per_rad
        if self.com_length_m == 0:
            raise ValueError(
                "com_length_m = 0: with its centre of mass on the pivot the pendulum feels no "
                "gravity torque and reads no static tilt (> 0: inverted, above the pivot; "
                "< 0: hanging, below it)")
        if mgl >= k:
            raise ValueError(
                f"inverted pendulum has no stable equilibrium: gravity stiffness m g L_cm = "
                f"{mgl:.4g} N m/rad >= flexure stiffness k = {k:.4g} N m/rad "
                "(reduce mass_kg or com_length_m, or stiffen the flexure)"
            )

    @property
    def gravity_stiffness_nm_per_rad(self) -> float:
        return self.mass_kg * self.gravity_m_per_s2 * self.com_length_m

    @property
    def amplification(self) -> float:
        """Small-angle static theta/phi = m g L / (k - m g L): N > 0 inverted, -1..0 hanging."""
        return 1.0 / (self.flexure_stiffness_nm_per_rad / self.gravity_stiffness_nm_per_rad - 1.0)

    @property
    def natural_frequency_hz(self) -> float:
        """sqrt((k - m g L) / J) / 2 pi: the resonance of theta's response."""
        k_eff = self.flexure_stiffness_nm_per_rad - self.gravity_stiffness_nm_per_rad
        return math.sqrt(k_eff / self.inertia_kgm2) / (2 * math.pi)

    @property
    def zero_frequency_hz(self) -> float:
        """sqrt(|m g L| / J) / 2 pi: where the J phi'' term equals the gravity term (a
        right-half-plane zero when inverted, the response's notch when hanging)."""
        return math.sqrt(abs(self.gravity_stiffness_nm_per_rad) / self.inertia_kgm2) / math.tau


@dataclass(frozen=True, slots=True)
class PlatformParams:
    """The table: tilt = piezo stroke / support spacing + disturbances + offset."""

    support_spacing_m: float = positive(0.5)
    initial_tilt_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class ThermalParams:
    """Plate temperature (random walk + daily cycle) -> first-order lag -> tilt.

    The default random walk is what puts the open-loop sensor ASD at 0.1 mHz near the
    paper's 5.7 um/sqrt(Hz); 10 urad/K is the paper's iron-table example (+-2 K, +-20 urad).
    """

    mean_k: float = positive(295.15)
    random_walk_k_per_sqrt_s: float = non_negative(6.7e-4)
    daily_amplitude_k: float = non_negative(0.3)
    daily_phase_rad: float = 0.0
    lag_s: float = non_negative(1800.0)
    tilt_per_kelvin_rad_per_k: float = 1.0e-5
    # the plate thermometer a [thermometer] backend = "sim" reads: white noise per reading
    # and its resolution (the step it reports in; 0: none)
    thermometer_noise_k: float = non_negative(1.0e-3)
    thermometer_resolution_k: float = non_negative(0.0)


@dataclass(frozen=True, slots=True)
class CoolerParams:
    """A water cooler's sawtooth tilt, as the paper's inverted pendulum saw it.

    The table cannot jump: the tilt ramps up for (1 - fall_fraction) of the period and
    back down in the rest (fall_fraction = 0.5 is a triangle).
    """

    period_s: float = positive(300.0)
    peak_to_peak_rad: float = non_negative(2.8e-8)
    fall_fraction: float = field(default=0.1, metadata={"gt": 0.0, "le": 0.5})
    phase_s: float = non_negative(0.0)


@dataclass(frozen=True, slots=True)
class PiezoParams:
    """Piezo actuator under one support: voltage range, stroke per volt, slew limit."""

    min_v: float = 0.0
    max_v: float = 150.0
    gain_m_per_v: float = positive(1.0e-7)
    slew_v_per_s: float = positive(100.0)
    ref_v: float = 75.0

    def __post_init__(self) -> None:
        if not self.min_v < self.max_v:
            raise ValueError(f"piezo.min_v ({self.min_v}) must be below max_v ({self.max_v})")
        if not self.min_v <= self.ref_v <= self.max_v:
            raise ValueError(f"piezo.ref_v ({self.ref_v}) must lie in [min_v, max_v]")


@dataclass(frozen=True, slots=True)
class SensorParams:
    """Capacitive displacement sensor and the ADC that digitizes its voltage."""

    gain_v_per_m: float = positive(2.0e5)
    offset_v: float = 0.0
    noise_m_per_rthz: float = non_negative(5.0e-10)
    drift_m_per_sqrt_s: float = non_negative(9.0e-12)
    adc_bits: int = field(default=16, metadata={"ge": 2, "le": 32})
    adc_min_v: float = -10.0
    adc_max_v: float = 10.0
    samples_per_cycle: int = field(default=1, metadata={"ge": 1, "le": 4096})

    def __post_init__(self) -> None:
        if not self.adc_min_v < self.adc_max_v:
            raise ValueError(f"sensor.adc_min_v ({self.adc_min_v}) must be below adc_max_v")

    @property
    def lsb_v(self) -> float:
        return (self.adc_max_v - self.adc_min_v) / (2**self.adc_bits - 1)

    @property
    def lsb_m(self) -> float:
        return self.lsb_v / self.gain_v_per_m


@dataclass(frozen=True, slots=True)
class UncertaintyParams:
    """1-sigma calibration tolerances of the numbers above, as fractions of their values
    (0.03 = 3 %; 0 = known exactly). `leveler diagnose` fits the log to the model within
    them before it looks for a missing effect, so an in-tolerance offset is a calibration,
    not a finding."""

    piezo_gain_rel: float = non_negative(0.0)
    support_spacing_rel: float = non_negative(0.0)
    sensor_arm_rel: float = non_negative(0.0)
    sensor_gain_rel: float = non_negative(0.0)
    amplification_rel: float = non_negative(0.0)
    natural_frequency_rel: float = non_negative(0.0)
    q_rel: float = non_negative(0.0)
    thermal_tilt_rel: float = non_negative(0.0)
    cooler_amplitude_rel: float = non_negative(0.0)
    # the pendulum's mass and moment of inertia: they turn a response's zero into a
    # centre-of-mass distance (`leveler calibrate-com LOG`)
    mass_rel: float = non_negative(0.0)
    inertia_rel: float = non_negative(0.0)
    # of the stated noise levels' amplitudes; 0: not vouched for, so diagnose fits the
    # residual's noise freely even where it can only extrapolate (`leveler.analysis.told`)
    noise_rel: float = non_negative(0.0)

    @property
    def sensor_path_rel(self) -> float:
        """The reading per unit tilt: sensor arm x amplification x sensor gain."""
        return math.sqrt(self.sensor_arm_rel**2 + self.amplification_rel**2
                         + self.sensor_gain_rel**2)

    @property
    def actuator_path_rel(self) -> float:
        """The tilt per piezo volt: piezo gain / support spacing."""
        return math.hypot(self.piezo_gain_rel, self.support_spacing_rel)


@dataclass(frozen=True, slots=True)
class PlantParams:
    """The whole simulated stand."""

    pendulum: PendulumParams = field(default_factory=PendulumParams)
    platform: PlatformParams = field(default_factory=PlatformParams)
    thermal: ThermalParams = field(default_factory=ThermalParams)
    cooler: CoolerParams = field(default_factory=CoolerParams)
    piezo: PiezoParams = field(default_factory=PiezoParams)
    sensor: SensorParams = field(default_factory=SensorParams)
    effects: EffectsParams = field(default_factory=EffectsParams)
    uncertainty: UncertaintyParams = field(default_factory=UncertaintyParams)

    @property
    def disturbances(self) -> list[tuple[float, float]]:
        """(period [s], peak to peak tilt [rad]) of each periodic tilt disturbance the model
        knows: its cooler, and a periodic disturbance among its effects (a tilt modulation
        at one of their periods cannot tell them from its response)."""
        out = [(self.cooler.period_s, self.cooler.peak_to_peak_rad)]
        pd = self.effects.periodic_disturbance
        if pd is not None:
            out.append((pd.period_s, abs(pd.peak_to_peak_rad)))
        return [(period, pp) for period, pp in out if pp > 0]
