"""The loop in virtual time against the simulated stand: the one harness that `leveler sim`,
`leveler modulate --sim`, the synthetic logs of the analysis tests and the benchmarks run.

It is the daemon's own loop, drivers and PID, with a `VirtualClock` instead of the real-time
one, so every simulated figure is a figure of the code that runs the stand. Long runs hand
the uneventful cycles to `leveler.loop.kernel` (compiled by numba when installed), which
does the same arithmetic on the same state bit for bit; every other cycle (a new
disturbance block, a reading the screen flags, a fault, a procedure) is the objects' own.
Virtual time outruns any log writer: a run given a writer waits for it every few thousand
cycles rather than letting its backlog grow (or drop records).
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from leveler.drivers.base import Actuator
from leveler.drivers.simulated import SimulatedStand
from leveler.log.writer import Columns, LogWriter
from leveler.loop import kernel as kn
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import ENGAGED, IDLE, Loop, Sink
from leveler.loop.pid import PID
from leveler.records import Environment, Event, Sample, Truth
from leveler.settings import Config
from leveler.sim.plant import Plant
from leveler.stand import open_stand

_PACE_EVERY = 20_000  # cycles between waits for a log writer, and its allowed backlog
# Runs shorter than this stay on the objects: loading numba and the cached kernel (~0.5 s)
# is not worth it for less than about a minute of 1 kHz loop.
KERNEL_MIN_CYCLES = 50_000
KERNELS = ("auto", "numba", "python", "off")
_NONE = np.zeros(0)  # the kernel's per-cycle drives, unused: the loop decides every command


class Recorder:
    """In-memory sink: sample times, reading, applied voltage, true tilt, events."""

    def __init__(self) -> None:
        self.t_s = array("d")
        self.sensor_m = array("d")
        self.applied_v = array("d")
        self.tilt_rad = array("d")
        self.events: list[Event] = []
        self.environments: list[Environment] = []  # the thermometer's readings, if any

    def extend(self, out: np.ndarray, n: int) -> None:
        """Append the first n cycles of a kernel's output."""
        for dst, row in ((self.t_s, kn.T_S), (self.sensor_m, kn.SENSOR_M),
                         (self.applied_v, kn.APPLIED_V), (self.tilt_rad, kn.TILT_RAD)):
            dst.frombytes(out[row, :n].tobytes())

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self.t_s.append(s.t_s)
        self.sensor_m.append(s.sensor_m)
        self.applied_v.append(s.applied_v)

    def truth(self, t: Truth, log_time_ns: int) -> None:
        self.tilt_rad.append(t.tilt_rad)

    def event(self, e: Event, log_time_ns: int) -> None:
        self.events.append(e)

    def environment(self, e: Environment, log_time_ns: int) -> None:
        self.environments.append(e)


@dataclass
class Run:
    """What a run recorded, as numpy views of the recorder's arrays."""

    t_s: np.ndarray
    sensor_m: np.ndarray
    applied_v: np.ndarray
    tilt_rad: np.ndarray
    events: list[Event] = field(default_factory=list)


class VirtualStand:
    """The stand a config describes (backend "sim"), its loop and a virtual clock.

    `wrap_actuator` lets a caller put something between the loop and the piezo (the
    synthetic logs' dither); `sinks` receive every record besides the recorder. `kernel`
    chooses who runs `run`'s uneventful cycles: "auto" the compiled kernel for long runs
    when numba is installed, "numba" or "python" (its interpreted form, for tests) always,
    "off" never. Use as a context manager: leaving it puts the actuator in its safe state
    and closes the stand.
    """

    def __init__(self, cfg: Config, seed: int, *, sinks: Sequence[Sink] = (),
                 wrap_actuator: Callable[[Actuator], Actuator] | None = None,
                 start_wall_ns: int | None = None, kernel: str = "auto") -> None:
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, not {kernel!r}")
        self.dt_s = 1.0 / cfg.loop.rate_hz
        self.stand = open_stand(cfg, seed)
        self.stand.connect()
        actuator = self.stand.actuator if wrap_actuator is None else wrap_actuator(
            self.stand.actuator)
        self.recorder = Recorder()
        self.loop = Loop(self.stand.sensor, actuator, PID(cfg.controller.pid_config()),
                         self.dt_s, [self.recorder, *sinks], self.stand.truth, policy=cfg.loop,
                         thermometer=self.stand.thermometer,
                         thermometer_interval_s=cfg.thermometer.interval_s,
                         feedforward=cfg.controller.feedforward())
        self.clock = VirtualClock(self.dt_s, start_wall_ns)
        self.t_s = self.clock.tick()
        self._kernel_mode = kernel
        self._kernel: _Kernel | None = None

    def __enter__(self) -> VirtualStand:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stand.actuator.make_safe()
        self.stand.close()

    def cycle(self) -> Sample:
        """One cycle at the present time; `step` advances the clock first."""
        return self.loop.cycle(self.t_s, self.clock.wall_ns(self.t_s))

    def tick(self) -> float:
        """Advance the clock one period (a procedure may act between tick and cycle)."""
        self.t_s = self.clock.tick()
        return self.t_s

    def step(self) -> Sample:
        self.tick()
        return self.cycle()

    def run(self, cycles: int, *, writer: LogWriter | None = None,
            progress: Callable[[float], None] | None = None) -> None:
        """`cycles` steps, pacing to `writer` and reporting the fraction done to `progress`."""
        every = max(min(cycles // 200, _PACE_EVERY), 1)
        fast = self._fast(cycles, every)
        k, mark = 0, every
        while k < cycles:
            n = min(cycles, mark) - k
            if fast is None:
                for _ in range(n):
                    self.step()
            else:
                fast.advance(n)
            k += n
            if k == mark:
                mark += every
                if writer is not None:
                    writer.wait_drained(max_backlog=_PACE_EVERY)
                if progress is not None:
                    progress(k / cycles)
        if progress is not None:
            progress(1.0)

    def _fast(self, cycles: int, chunk: int) -> _Kernel | None:
        """The kernel for a run of `cycles`, or None where only the objects can run it."""
        mode = self._kernel_mode
        if mode == "off" or (mode == "auto" and cycles < KERNEL_MIN_CYCLES):
            return None
        fn = kn.cycles if mode == "python" else kn.compiled()
        if fn is None:
            if mode == "numba":
                raise RuntimeError("kernel='numba' needs numba: pip install lab-leveler[fast]")
            return None
        why = _Kernel.unsupported(self)
        if why:
            return None
        if self._kernel is None or self._kernel.fn is not fn or len(self._kernel.out[0]) < chunk:
            self._kernel = _Kernel(self, fn, chunk)
        return self._kernel

    def recorded(self, first: int = 0) -> Run:
        """The recorded series from sample `first` on."""
        r = self.recorder
        return Run(*(np.frombuffer(a)[first:] for a in (r.t_s, r.sensor_m, r.applied_v,
                                                         r.tilt_rad)), r.events)


# The plant's private state, mapped to `leveler.loop.kernel`'s arrays here and only here
# (the PID's by the kernel module, its own wing's), for the loop's `_Kernel` and a null
# log's schedule (`leveler.analysis.nullcal`): tests hold the kernel's runs to the objects'.

def kernel_unsupported(plant: Plant, pid: PID | None) -> str:
    """Why `kernel.cycles` cannot step this plant and PID ('' when it can): it knows one
    conversion a cycle, no effect stepped sample by sample (an actuator's, a delay, a
    sensor's, a resonance) and a PID without a notch or a double integral."""
    if plant.samples_per_cycle != 1:
        return "oversampling ADC"
    if plant._actuator_fx or plant._delay_s > 0 or plant._sensor_fx or plant._resonances:
        return "an actuator, sensor or resonance effect"
    return kn.pid_unsupported(pid) if pid is not None else ""


def kernel_constants(plant: Plant, pid: PID | None, dt_s: float, period_s: float,
                     stuck_after: int = 0, max_step_m: float = 0.0, spike_max: int = 0
                     ) -> np.ndarray:
    """The constants of `plant` and `pid` stepped every `dt_s` on a clock of `period_s`,
    with the loop's screen (0: a screen that passes every reading). Without a PID (an
    open loop alone) its terms are 0."""
    pend = plant.pendulum
    k = np.zeros(kn.N_CONST + 2 * len(plant._ramp_k))
    if pid is not None:
        kn.pid_constants(pid, dt_s, k)
    for i, v in ((kn.K_TILT_PER_V, plant._tilt_per_v), (kn.K_V_REF, plant._v_ref),
                 (kn.K_V_MIN, plant._v_min), (kn.K_V_MAX, plant._v_max),
                 (kn.K_MAX_DV, plant._max_dv), (kn.K_ARM, plant._arm),
                 (kn.K_GAIN, plant._gain), (kn.K_OFFSET, plant._offset),
                 (kn.K_ADC_MIN, plant._adc_min), (kn.K_LSB, plant._lsb),
                 (kn.K_TOP, plant._top), (kn.K_LINEAR, pend._linear),
                 (kn.K_A11, pend._a11), (kn.K_A12, pend._a12), (kn.K_A21, pend._a21),
                 (kn.K_A22, pend._a22), (kn.K_B1, pend._b1), (kn.K_B2, pend._b2),
                 (kn.K_C_PER_J, pend._c_per_j), (kn.K_J, pend._j), (kn.K_C, pend._c),
                 (kn.K_K, pend._k), (kn.K_MGL, pend._mgl), (kn.K_SUBSTEPS, pend._substeps),
                 (kn.K_PLANT_DT, plant.dt_s), (kn.K_OFFSET_TILT, plant._offset_tilt),
                 (kn.K_DT, dt_s), (kn.K_PERIOD, period_s),
                 (kn.K_STUCK_AFTER, stuck_after), (kn.K_MAX_STEP_M, max_step_m),
                 (kn.K_SPIKE_MAX, spike_max)):
        k[i] = v
    k[kn.K_SLEW_V_PER_S] = plant._slew_v_per_s
    k[kn.K_RAMP_TERMS:] = np.ravel(plant._ramp_k)
    return k


def kernel_block_arrays(plant: Plant) -> tuple[np.ndarray, ...]:
    """The plant's current disturbance block, as `kernel.cycles` takes it."""
    b = plant._block
    return (b.arrays["thermal_tilt_rad"], b.arrays["cooler_tilt_rad"],
            b.arrays["effect_tilt_rad"], b.arrays["noise_m"], b.arrays["drift_m"],
            b.arrays["temperature_k"])


def export_state(plant: Plant, pid: PID | None, dt_s: float, s: np.ndarray, c: np.ndarray
                 ) -> np.ndarray:
    """The plant's and PID's state into `s` (up to HELD_V) and `c` (N, BLOCK_I); returns
    the resonant terms' array (`kernel.cycles`' `res`)."""
    pend = plant.pendulum
    s[:kn.SP] = (plant.v_applied, plant.v_target, plant.v_effective, plant._lag_v,
                 pend.theta, pend.omega, pend._phi)
    c[kn.N], c[kn.BLOCK_I] = plant.n, plant._i
    return kn.export_pid(pid, dt_s, s) if pid is not None else np.zeros((kn.N_RES, 0))


def import_state(plant: Plant, pid: PID | None, s: np.ndarray, c: np.ndarray, res: np.ndarray,
                 engaged: bool) -> None:
    """`export_state` undone: the state the kernel left, back to the objects (the PID's
    only if it was `engaged`: an idle kernel leaves it as it was)."""
    pend = plant.pendulum
    st = s.tolist()
    (plant.v_applied, plant.v_target, plant.v_effective, plant._lag_v, pend.theta,
     pend.omega, pend._phi) = st[kn.V_APPLIED:kn.SP]
    if engaged and pid is not None:
        kn.import_pid(pid, s, res)
    plant.n, plant._i = int(c[kn.N]), int(c[kn.BLOCK_I])


class _Kernel:
    """`leveler.loop.kernel.cycles` run on a VirtualStand's objects: their state out to
    arrays, the uneventful cycles in the kernel, the state back, the records to the sinks;
    the cycle that stopped it run by the objects themselves."""

    def __init__(self, vs: VirtualStand, fn: Callable[..., tuple[int, int]],
                 chunk: int) -> None:
        self.vs = vs
        self.fn = fn
        self.sim = vs.stand.sensor
        assert isinstance(self.sim, SimulatedStand)
        self.s = np.zeros(kn.N_STATE)
        self.c = np.zeros(kn.N_COUNT, dtype=np.int64)
        self.out = np.zeros((kn.N_OUT, chunk))
        self.out_i = np.zeros((2, chunk), dtype=np.int64)
        self._block: object = None
        self._arrays: tuple[np.ndarray, ...] = ()
        self.res = np.zeros((kn.N_RES, 0))
        self.cycles = 0  # run by the kernel (the rest of a run was the objects')

    @staticmethod
    def unsupported(vs: VirtualStand) -> str:
        """Why the kernel cannot run this stand's cycles ('' when it can): it knows the plain
        simulated stand, one conversion a cycle, no effect stepped sample by sample and a PID
        without a notch or a double integral, no thermometer."""
        sim = vs.stand.sensor
        if not isinstance(sim, SimulatedStand) or vs.loop.actuator is not sim:
            return "not the plain simulated stand (another driver, or a wrapped actuator)"
        if sim._faults or math.isfinite(sim._hang_at_s) or math.isfinite(sim._fail_at_s):
            return "fault injection"
        if why := kernel_unsupported(sim.plant, vs.loop.pid):
            return why
        if sim.plant.dt_s != vs.dt_s:
            return "plant and loop steps differ"
        if vs.loop.thermometer is not None:
            return "a thermometer (read for the temperature feedforward)"
        return ""

    # The loop's state's names here are its own, private ones: this class is the one place
    # that maps them to the kernel's arrays (the plant's and PID's: `export_state` above),
    # and tests hold the two runs to each other.

    def _ready(self) -> bool:
        """Whether the loop is in a state the kernel knows (else the objects run a cycle)."""
        loop = self.vs.loop
        return (loop.state in (IDLE, ENGAGED) and loop.wave is None
                and not (loop._in_a_row or loop._unreported or loop._bad_in_a_row)
                and (loop.state == IDLE or loop.pid._prev is not None)
                and loop.pid.config.notch is None and not loop.pid.config.gains.ki2
                and not self.sim._unplugged)

    def advance(self, n: int) -> None:
        """Run n cycles, the kernel's where it can and the objects' where it cannot."""
        vs = self.vs
        done = 0
        while done < n:
            if not self._ready():
                vs.step()
                done += 1
                continue
            self._export()
            m, why = self.fn(self.s, self.c, self._constants(), *self._block_arrays(),
                             self.res, _NONE, _NONE, self.out, self.out_i, n - done)
            self._import(m)
            done += m
            self.cycles += m
            if why == kn.BEFORE:
                vs.step()
                done += 1
            elif why == kn.AFTER_STEP:
                vs.cycle()  # the plant has stepped: the read measures without stepping again
                done += 1

    def _block_arrays(self) -> tuple[np.ndarray, ...]:
        b = self.sim.plant._block
        if b is not self._block:
            self._block = b
            self._arrays = kernel_block_arrays(self.sim.plant)
        return self._arrays

    def _constants(self) -> np.ndarray:
        vs, loop = self.vs, self.vs.loop
        pol = loop.policy
        return kernel_constants(self.sim.plant, loop.pid, loop.dt_s, vs.clock.period_s,
                            pol.stuck_after_samples, pol.max_step_m, pol.spike_reject_max)

    def _export(self) -> None:
        vs, loop = self.vs, self.vs.loop
        self.res = export_state(self.sim.plant, loop.pid, loop.dt_s, self.s, self.c)
        self.s[kn.HELD_V:] = (loop.held_v, loop._last_value_m, loop._last_good_m)
        self.c[kn.SEQ:] = (loop.seq, vs.clock._n, loop._same_in_a_row,
                           loop._spikes_in_a_row, loop.state == ENGAGED)

    def _import(self, m: int) -> None:
        vs, loop = self.vs, self.vs.loop
        import_state(self.sim.plant, loop.pid, self.s, self.c, self.res,
                        loop.state == ENGAGED)
        loop.held_v, loop._last_value_m, loop._last_good_m = self.s[kn.HELD_V:].tolist()
        loop.seq, vs.clock._n = int(self.c[kn.SEQ]), int(self.c[kn.TICK])
        loop._same_in_a_row, loop._spikes_in_a_row = int(self.c[kn.SAME]), int(self.c[kn.SPIKES])
        vs.t_s = vs.clock._n * vs.clock.period_s
        if m:
            self._emit(m)

    def _emit(self, m: int) -> None:
        """The records of m kernel cycles: to the recorder and log writers in bulk, to any
        other sink one by one, and the last sample to the loop."""
        vs, loop = self.vs, self.vs.loop
        vs.recorder.extend(self.out, m)
        seq0, state = loop.seq - m, loop.state
        out, out_i = self.out[:, :m].copy(), self.out_i[:, :m].copy()
        wall = (vs.clock.start_wall_ns + np.rint(out[kn.T_S] * 1e9).astype(np.int64)).tolist()
        sample = {"seq": np.arange(seq0, seq0 + m), "t_s": out[kn.T_S],
                  "raw_counts": out_i[kn.RAW_COUNTS], "sensor_m": out[kn.SENSOR_M],
                  "status": 0, "setpoint_m": out[kn.SETPOINT_M],
                  "error_m": out[kn.SETPOINT_M] - out[kn.SENSOR_M], "p_v": out[kn.P_V],
                  "i_v": out[kn.I_V], "d_v": out[kn.D_V], "command_v": out[kn.COMMAND_V],
                  "applied_v": out[kn.APPLIED_V], "saturated": out_i[kn.SATURATED] != 0,
                  "state": state}
        truth = {"seq": sample["seq"], "t_s": out[kn.T_S], "tilt_rad": out[kn.TILT_RAD],
                 "thermal_tilt_rad": out[kn.THERMAL_RAD], "cooler_tilt_rad": out[kn.COOLER_RAD],
                 "piezo_tilt_rad": out[kn.PIEZO_RAD], "pendulum_rad": out[kn.PENDULUM_RAD],
                 "temperature_k": out[kn.TEMPERATURE_K], "sensor_drift_m": out[kn.DRIFT_M]}
        others = []
        for sink in loop.sinks:
            if isinstance(sink, LogWriter):
                sink.columns(Columns(sample, truth, wall))
            elif sink is not vs.recorder:
                others.append(sink)
        first = 0 if others else m - 1  # without such sinks only the last is needed
        rows = (v[first:].tolist() if isinstance(v, np.ndarray) else [v] * (m - first)
                for v in sample.values())
        samples = [Sample(*r) for r in zip(*rows, strict=True)]
        if others:
            truths = [Truth(*r) for r in zip(*(v.tolist() for v in truth.values()),
                                              strict=True)]
            for s, t, w in zip(samples, truths, wall, strict=True):
                for sink in others:
                    sink.sample(s, w)
                    sink.truth(t, w)
        loop.last = samples[-1]
        loop._wall_ns = wall[-1]


def run_virtual(cfg: Config, duration_s: float, seed: int, *, engaged: bool,
                writer: LogWriter | None = None,
                progress: Callable[[float], None] | None = None,
                start_wall_ns: int | None = None, kernel: str = "auto") -> Run:
    """`leveler sim`'s run: duration_s of virtual time, closed loop or open (the piezo at
    its safe voltage), with every record to `writer` if given (`kernel`: VirtualStand's)."""
    sinks = [] if writer is None else [writer]
    with VirtualStand(cfg, seed, sinks=sinks, start_wall_ns=start_wall_ns,
                      kernel=kernel) as vs:
        vs.loop.emit("start", "sim", vs.t_s, engaged=engaged, seed=seed)
        vs.cycle()
        if engaged:
            vs.loop.engage(vs.t_s, "sim start")
        vs.run(round(duration_s / vs.dt_s) - 1, writer=writer, progress=progress)
        vs.loop.emit("stop", "sim end", vs.t_s)
        return vs.recorded()

