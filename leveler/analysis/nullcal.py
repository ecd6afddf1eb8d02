"""Acceptance thresholds calibrated on null data: how much held-out evidence a family
finds in logs that have nothing missing.

A complexity penalty (k ln n) knows nothing of a family's search: a grid of periods or
delays, a lattice scan and a free noise spectrum all find some evidence in pure noise,
and a generous penalty hides weak effects that held-out data do show. So the whole
detector is run on logs of the model itself (a parametric bootstrap): the model file's
stand with its calibrated numbers drawn from their stated tolerances and its noise terms
scaled within NOISE_SPREAD, run through the log's own schedule (the loop closed by the
logged controller where it was closed, the logged voltage where it was open, so the same
modulation), and the best held-out evidence of each family that no other gate (found
in training, a degenerate fit, the size gate) stops is recorded per run. Each family's
threshold is that statistic's upper tail at ALPHA / (number of families), so a whole null
log raises a false alarm with probability about ALPHA, grids and all. The tail beyond
the runs' reach is an exponential fitted to their top fifth (held-out evidence is a
likelihood ratio, whose tail is exponential).

The calibration raises a family's bar above its BIC penalty where the model's own nulls
show the penalty too low; it never lowers it. Nulls of the model cannot show what an
error of the model's *form* does, and a real stand's forms are never the model's: in the
independent generator's null logs a plain piezo fitted a 64 mV play with held-out
evidence 54 (penalty 21, stopped by the size gate), and a weak actuator delay was
named "hysteresis" on evidence 7.9, while the model's own nulls never found either.
A calibration is cached per model file and log shape (`cache_key`) with the code's hash,
so a change to the detector recalibrates.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from leveler.analysis.predict import Measured, actuator_excited, excitation_v
from leveler.analysis.recalibrate import PULL_LIMIT, knobs
from leveler.analysis.workers import one_blas_thread
from leveler.loop import kernel as kn
from leveler.loop.pid import PID
from leveler.sim.effects import Signals
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant
from leveler.virtual import (
    export_state,
    import_state,
    kernel_block_arrays,
    kernel_constants,
    kernel_unsupported,
)

#: the false-alarm rate per null log the thresholds are set for
ALPHA = 0.01
#: each noise term of the model is known to within this factor either way
NOISE_SPREAD = 1.25
#: the share of the runs, at the top, that the exponential tail is fitted to
TAIL_SHARE = 0.2
#: logs whose duration differs by less than this factor share a calibration
DURATION_BIN = 1.1


def draw_plant(plant: PlantParams, rng: np.random.Generator) -> PlantParams:
    """A healthy stand as the model file states it: each calibrated number offset by a
    normal draw of its tolerance (cut at PULL_LIMIT sigma), each noise term scaled by a
    log-uniform factor within NOISE_SPREAD."""
    p = plant
    for k in knobs(plant, temperature_logged=True, excited=True):
        p = k.apply(p, float(np.clip(rng.normal(0.0, k.sigma), -PULL_LIMIT * k.sigma,
                                     PULL_LIMIT * k.sigma)))

    def spread() -> float:
        return float(np.exp(rng.uniform(-math.log(NOISE_SPREAD), math.log(NOISE_SPREAD))))

    se, th = p.sensor, p.thermal
    return dataclasses.replace(
        p,
        sensor=dataclasses.replace(se, noise_m_per_rthz=se.noise_m_per_rthz * spread(),
                                   drift_m_per_sqrt_s=se.drift_m_per_sqrt_s * spread()),
        thermal=dataclasses.replace(
            th, random_walk_k_per_sqrt_s=th.random_walk_k_per_sqrt_s * spread()))


def simulate_null(meas: Measured, seed: int, kernel: str = "auto") -> Measured:
    """A log of the model with nothing missing, on `meas`'s schedule: where the loop was
    closed the logged controller closes it on the simulated readings (plus whatever else
    moved the voltage then, `excitation_v`); where it was open the logged voltage drives
    the piezo. A log that does not say what its controller was is replayed open loop. The
    temperature is what the plate thermometer reads (its noise and resolution), as in a
    log the daemon writes, not the plate's own.

    `kernel`: who runs the samples where nothing changes (`_NullLoop`): "auto" the
    compiled kernel where numba is installed, else the objects; "python" the kernel
    interpreted; "off" the objects alone. The same log to the bit whichever runs it."""
    rng = np.random.default_rng([seed, 0x4E55])
    params = draw_plant(meas.config.plant, rng)
    plant = Plant(params, meas.dt_s, int(rng.integers(2**31)))
    exc = excitation_v(meas) if meas.controller is not None else None
    on = (np.zeros(len(meas.y_m), dtype=bool) if meas.engaged is None or exc is None
          else np.asarray(meas.engaged, dtype=bool))
    pid = PID(meas.controller.pid_config()) if meas.controller is not None else None
    run = _NullLoop(plant, pid, meas.u_v, on, exc, meas.dt_s)
    run.run(_kernel(kernel))
    temp_k = (plant.thermometer_series_k(run.plate_k) if meas.sig.temperature_k is not None
              else None)
    sig = Signals(meas.t_s, meas.dt_s, temp_k)
    return dataclasses.replace(meas, path=f"null run {seed}", sig=sig, u_v=run.u, y_m=run.y,
                               bad_samples=0, incomplete="")


def _kernel(mode: str) -> Callable[..., tuple[int, int]] | None:
    if mode == "off":
        return None
    if mode == "python":
        return kn.cycles
    if mode == "auto":
        return kn.compiled()
    raise ValueError(f"kernel must be auto, python or off, not {mode!r}")


class _NullLoop:
    """A null log's schedule, sample by sample: each sample steps the plant from the last,
    reads it, and commands the piezo (the controller's answer plus the excitation where
    the loop was closed, the logged voltage where it was open). The objects run the
    samples where something changes (the first, the loop opening or closing, a new block
    of disturbances, a railed reading); `leveler.loop.kernel` the runs between them: a
    day's 864,000 samples took 2.7 s as objects."""

    CHUNK = 1 << 16  # the kernel's records, this many samples at a time

    def __init__(self, plant: Plant, pid: PID | None, logged_u: np.ndarray,
                 closed: np.ndarray, extra: np.ndarray | None, dt_s: float) -> None:
        n = len(logged_u)
        self.plant, self.pid, self.dt_s = plant, pid, dt_s
        self._logged = np.ascontiguousarray(logged_u, dtype=float)
        self._extra = None if extra is None else np.ascontiguousarray(extra, dtype=float)
        self._closed = closed
        # Python lists for the objects: numpy's scalar indexing costs more than a sample
        self._logged_l = self._logged.tolist()
        self._extra_l = None if extra is None else self._extra.tolist()
        self._closed_l = closed.tolist()
        self.y, self.u, self.plate_k = np.empty(n), np.empty(n), np.empty(n)
        self._was_on, self._held = False, self._logged_l[0]

    def sample(self, i: int, stepped: bool = False) -> None:
        """Sample i by the objects (`stepped`: the kernel has already stepped to it)."""
        plant = self.plant
        if i and not stepped:
            plant.step()
        if plant.samples_per_cycle > 1:
            yi = float(np.mean(plant.measure_block()[1]))
        else:
            yi = plant.measure()[1]
        self.y[i] = yi
        self.plate_k[i] = plant.plate_temperature_k()
        closed = self._closed_l[i]
        if closed and self.pid is not None and self._extra_l is not None:
            if not self._was_on:
                self.pid.engage(yi, self._held)
            self._held = self.pid.update(yi, self.dt_s).command_v
            v = self._held + self._extra_l[i]
        else:
            v = self._held = self._logged_l[i]
        self._was_on = closed
        self.u[i] = plant.command(v)

    def run(self, fn: Callable[..., tuple[int, int]] | None) -> None:
        """Every sample: by `fn` (`leveler.loop.kernel.cycles`, compiled or not) where it can,
        else (or with None) by the objects."""
        n, plant, pid = len(self.y), self.plant, self.pid
        if fn is None or kernel_unsupported(plant, pid):
            for i in range(n):
                self.sample(i)
            return
        s, c = np.zeros(kn.N_STATE), np.zeros(kn.N_COUNT, dtype=np.int64)
        out = np.zeros((kn.N_OUT, self.CHUNK))
        out_i = np.zeros((2, self.CHUNK), dtype=np.int64)
        k = kernel_constants(plant, pid, self.dt_s, plant.dt_s)
        # where each sample's run of the same open or closed loop ends
        change = np.flatnonzero(np.diff(self._closed.astype(np.int8))) + 1
        ends = np.append(change, n)
        none = np.zeros(0)
        i = 0
        while i < n:
            closed = self._closed_l[i] and self._extra is not None and pid is not None
            if i == 0 or self._closed_l[i] != self._closed_l[i - 1]:
                self.sample(i)
                i += 1
                continue
            limit = min(int(ends[np.searchsorted(ends, i, side="right")]) - i, self.CHUNK)
            res = export_state(plant, pid, self.dt_s, s, c)
            s[kn.HELD_V] = self._held
            c[kn.TICK], c[kn.ENGAGED] = plant.n, closed
            drive = ((none, self._extra[i:i + limit]) if closed
                     else (self._logged[i:i + limit], none))
            m, why = fn(s, c, k, *kernel_block_arrays(plant), res, *drive, out, out_i, limit)
            import_state(plant, pid, s, c, res, closed)
            self._held = float(s[kn.HELD_V])
            self.y[i:i + m] = out[kn.SENSOR_M, :m]
            self.u[i:i + m] = out[kn.APPLIED_V, :m]
            self.plate_k[i:i + m] = out[kn.TEMPERATURE_K, :m]
            i += m
            if why != kn.DONE:
                self.sample(i, stepped=why == kn.AFTER_STEP)
                i += 1


def null_statistic(meas: Measured) -> dict[str, float]:
    """Per family, the best held-out evidence of a fit that no other gate stops, in the
    first round of a diagnosis that accepts nothing (0: none found any)."""
    from leveler.analysis.diagnose import diagnose
    from leveler.sim.effects import EFFECTS

    d = diagnose(meas, max_effects=1, thresholds={name: math.inf for name in EFFECTS})
    best = {name: 0.0 for name in EFFECTS}
    for c in d.candidates:
        if c.round == 0 and c.size_ok:
            best[c.name] = max(best[c.name], c.deviance_test)
    return best


def _null_run(meas: Measured, seed: int) -> dict[str, float]:
    return null_statistic(simulate_null(meas, seed))


def tail_threshold(values: list[float], alpha: float) -> float:
    """The value a new draw exceeds with probability `alpha`: the empirical quantile where
    the runs reach it, else an exponential tail fitted to their top TAIL_SHARE."""
    v = np.sort(np.asarray(values, dtype=float))[::-1]
    n = len(v)
    if n == 0:
        return math.inf
    k = max(3, math.ceil(TAIL_SHARE * n)) if n >= 3 else n
    k = min(k, n)
    u = float(v[k - 1])  # the tail starts here: k of n runs at or above it
    p_u = k / n
    if alpha >= p_u:
        return float(np.quantile(v, 1.0 - alpha))
    scale = float(np.mean(v[: k - 1] - u)) if k > 1 else 0.0
    return u + scale * math.log(p_u / alpha)


@dataclass(frozen=True)
class NullCalibration:
    """Per family the held-out evidence a candidate must beat, and what it rests on."""

    thresholds: dict[str, float]
    runs: int
    alpha: float
    statistics: dict[str, list[float]]
    key: str
    wall_s: float

    def describe(self) -> str:
        return (f"acceptance thresholds calibrated on {self.runs} null runs of the model "
                f"(false alarms {self.alpha:.0%} per log; held-out evidence, where above "
                "the BIC penalty): " + ", ".join(f"{k} {v:.3g}"
                                                 for k, v in self.thresholds.items()))

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def from_statistics(stats: dict[str, list[float]], alpha: float, key: str,
                    wall_s: float) -> NullCalibration:
    per_family = alpha / max(len(stats), 1)
    thresholds = {name: tail_threshold(vals, per_family) for name, vals in stats.items()}
    runs = min((len(v) for v in stats.values()), default=0)
    return NullCalibration(thresholds, runs, alpha, stats, key, wall_s)


def _code_hash() -> str:
    """The detector's own source: a change to it makes a new calibration."""
    import leveler.analysis as analysis
    import leveler.sim as sim

    h = hashlib.sha256()
    for pkg in (analysis, sim):
        for path in sorted(Path(next(iter(pkg.__path__))).glob("*.py")):
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def cache_key(meas: Measured, alpha: float = ALPHA) -> str:
    """What a calibration depends on: the model file, the sample interval, the duration
    (within DURATION_BIN), whether anything but feedback moved the actuator, whether the
    temperature was logged, the false-alarm rate and the detector's code."""
    from leveler.analysis.diagnose import warmup_samples
    from leveler.analysis.predict import Predictor

    pred = Predictor(meas.config.plant, meas)
    duration = float(meas.t_s[-1] - meas.t_s[0])
    shape = {
        "model": meas.model_text,
        "dt_s": round(meas.dt_s, 9),
        "duration_bin": round(math.log(max(duration, 1.0)) / math.log(DURATION_BIN)),
        "excited": actuator_excited(meas, pred, slice(warmup_samples(meas, pred), None)),
        "controller": meas.controller is not None,
        "temperature": meas.sig.temperature_k is not None,
        "alpha": alpha,
        "code": _code_hash(),
    }
    return hashlib.sha256(json.dumps(shape, sort_keys=True).encode()).hexdigest()[:20]


def cache_dir() -> Path:
    """$LEVELER_CACHE_DIR, else $XDG_CACHE_HOME/leveler, else ~/.cache/leveler."""
    if d := os.environ.get("LEVELER_CACHE_DIR"):
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "leveler"


def cache_path(key: str) -> Path:
    return cache_dir() / f"nullcal-{key}.json"


def load_cached(key: str) -> NullCalibration | None:
    """The cached calibration for `key`, or None (none, or unreadable: recalibrate)."""
    path = cache_path(key)
    try:
        data = json.loads(path.read_text())
        return NullCalibration(**data)
    except (OSError, ValueError, TypeError):
        return None


def save(cal: NullCalibration) -> Path:
    """Write atomically: a calibration cut off halfway is no calibration."""
    path = cache_path(cal.key)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(cal.as_dict(), indent=1))
    os.replace(tmp, path)
    return path


def calibrate(meas: Measured, runs: int, *, jobs: int = 1, alpha: float = ALPHA,
              key: str | None = None, first_seed: int = 0,
              progress: Callable[[int, int], None] | None = None) -> NullCalibration:
    """`runs` null runs (parallel over `jobs` processes), each a simulated log on `meas`'s
    schedule diagnosed in full; the thresholds at `alpha` false alarms per log."""
    global _MEAS
    start = time.perf_counter()
    key = key or cache_key(meas, alpha)
    stats: dict[str, list[float]] = {}
    seeds = range(first_seed, first_seed + runs)

    def add(result: dict[str, float]) -> None:
        for name, v in result.items():
            stats.setdefault(name, []).append(v)
        if progress is not None:
            progress(len(next(iter(stats.values()))), runs)

    if jobs <= 1:
        for s in seeds:
            add(_null_run(meas, s))
    else:
        excitation_v(meas)  # read once here, and kept by every forked worker
        _MEAS = meas
        try:
            with ProcessPoolExecutor(jobs, mp_context=get_context("fork"),
                                     initializer=one_blas_thread) as pool:
                for fut in as_completed([pool.submit(_null_run_forked, s) for s in seeds]):
                    add(fut.result())
        finally:
            _MEAS = None
    return from_statistics(stats, alpha, key, time.perf_counter() - start)


#: the log the forked workers of `calibrate` simulate: shared by the fork, not pickled to
#: each run (a day is tens of MB), and the very object whose excitation they keep
_MEAS: Measured | None = None


def _null_run_forked(seed: int) -> dict[str, float]:
    assert _MEAS is not None
    return _null_run(_MEAS, seed)

