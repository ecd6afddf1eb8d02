"""Simulation: leveler's closed loop against python-control's on the same non-linear loop.

The loop is the default stand (config/sim.toml) with the full non-linear pendulum
(`model = "nonlinear"`: sin() and RK4, 4 substeps), its piezo (range and slew), its sensor
through the 16-bit ADC, and the config's PID controller with its slew limit and
back-calculation anti-windup. python-control gets it as two discrete-time `nlsys` (plant,
controller) joined by `interconnect` and run by `input_output_response`, with the same
disturbance sequence (thermal and cooler tilt, sensor noise and drift, drawn from the same
seed) as inputs. It is the same arithmetic: the bench checks that both produce the same
sensor and command sequences, and says how far apart they are (normally not at all).

python-control is run on a shorter horizon (it is slow); steps per second normalise it.
Figures (goal: >= 100x python-control):
- leveler's Plant + PID objects stepped directly: the same maths, nothing else;
- `run_virtual` on the objects alone (kernel off): the daemon's whole loop (drivers,
  reading screens, records, truth);
- `run_virtual` as `leveler sim` runs it: the uneventful cycles in the numba-compiled
  kernel (leveler.loop.kernel, bit for bit the objects' arithmetic; tests/test_kernel.py),
  compile-cache load included;
- the default (linear) config's whole loop, for scale;
- a 24 h day at the default rate with every sample (and the truth) logged, as
  `leveler sim --out` does it: goal <= 8 s (quick mode: a quarter day, times 4);
- the `leveler sim --duration 24h --out` command end to end, which also runs the open-loop
  day and the spectra (no goal; what the README quotes).
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import control as ct
import numpy as np
from common import REPO, at_least, at_most, bench_tmpdir, row  # beside this script

from leveler.log.writer import LogWriter
from leveler.loop.pid import PID
from leveler.settings import Config, load_config
from leveler.sim.disturbance import Disturbances
from leveler.sim.params import PlantParams
from leveler.sim.pendulum import ramp_terms
from leveler.sim.plant import Plant
from leveler.virtual import run_virtual

SECTION = "simulation"
DAY_S = 86400.0
CONFIG = REPO / "config" / "sim.toml"


def nonlinear(cfg: Config) -> Config:
    pend = dataclasses.replace(cfg.plant.pendulum, model="nonlinear")
    return dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, pendulum=pend))


def leveler_steps(cfg: Config, n: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Plant + PID stepped as Loop.cycle orders them: (seconds, sensor_m, command_v)."""
    dt = 1.0 / cfg.loop.rate_hz
    plant = Plant(cfg.plant, dt, seed=1)
    pid = PID(cfg.controller.pid_config(), initial_output_v=cfg.actuator.safe_v)
    ys = np.empty(n)
    cs = np.empty(n)
    measure, update, command, step = plant.measure, pid.update, plant.command, plant.step
    start = time.perf_counter()
    for k in range(n):
        _, y, _ = measure()
        cmd = update(y, dt).command_v
        command(cmd)
        step()
        ys[k] = y
        cs[k] = cmd
    return time.perf_counter() - start, ys, cs


def disturbance_inputs(params: PlantParams, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per step: platform tilt other than the piezo's [rad], and sensor drift + noise [m]."""
    dist = Disturbances(params, dt, 1)  # what Plant(params, dt, seed=1) draws
    tilt: list[float] = []
    add: list[float] = []
    offset = params.platform.initial_tilt_rad
    while len(tilt) < n:
        b = dist.next_block()
        tilt += [th + co + fx + offset for th, co, fx in
                 zip(b.thermal_tilt_rad, b.cooler_tilt_rad, b.effect_tilt_rad, strict=True)]
        add += [d + w for d, w in zip(b.drift_m, b.noise_m, strict=True)]
    return np.array(tilt[:n]), np.array(add[:n])


def python_control_loop(cfg: Config) -> ct.InterconnectedSystem:
    """The same closed loop as python-control systems: plant and PID, discrete time."""
    params = cfg.plant
    pend, pz, se = params.pendulum, params.piezo, params.sensor
    dt = 1.0 / cfg.loop.rate_hz
    mgl, kf = pend.gravity_stiffness_nm_per_rad, pend.flexure_stiffness_nm_per_rad
    c, j, arm = pend.damping_nms_per_rad, pend.inertia_kgm2, pend.sensor_arm_m
    tilt_per_v = pz.gain_m_per_v / params.platform.support_spacing_m
    max_dv = pz.slew_v_per_s * dt
    h = dt / 4  # PendulumModel's RK4 substeps
    ramp_k = [(float(a), float(b)) for a, b in ramp_terms(pend, dt)[::-1]]
    top = 2**se.adc_bits - 1

    def acc(th: float, om: float, phi: float) -> float:
        return (mgl * math.sin(th + phi) - kf * th - c * om) / j

    def plant_update(t: float, x: np.ndarray, u: np.ndarray, p: dict) -> list[float]:
        th, om, v, phi_before = x
        target = min(max(u[0], pz.min_v), pz.max_v)
        dv = min(max(target - v, -max_dv), max_dv)
        v, before = v + dv, v
        phi = tilt_per_v * (v - pz.ref_v) + u[1]
        th, om = th - (phi - phi_before), om + c / j * (phi - phi_before)  # J phi''
        for _ in range(4):
            k1t, k1o = om, acc(th, om, phi)
            k2t, k2o = om + 0.5 * h * k1o, acc(th + 0.5 * h * k1t, om + 0.5 * h * k1o, phi)
            k3t, k3o = om + 0.5 * h * k2o, acc(th + 0.5 * h * k2t, om + 0.5 * h * k2o, phi)
            k4t, k4o = om + h * k3o, acc(th + h * k3t, om + h * k3o, phi)
            th += h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
            om += h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
        ramp_s = abs(v - before) / pz.slew_v_per_s  # the piezo's ramp (ramp_terms)
        g_theta = g_omega = 0.0
        for k_theta, k_omega in ramp_k:
            g_theta = (g_theta + k_theta) * ramp_s
            g_omega = (g_omega + k_omega) * ramp_s
        dphi = tilt_per_v * (v - before)
        return [th + g_theta * dphi, om + g_omega * dphi, v, phi]

    def plant_output(t: float, x: np.ndarray, u: np.ndarray, p: dict) -> list[float]:
        sensed = arm * x[0] + u[2]
        counts = math.floor((se.gain_v_per_m * sensed + se.offset_v - se.adc_min_v) / se.lsb_v
                            + 0.5)
        counts = min(max(counts, 0), top)
        return [(counts * se.lsb_v + se.adc_min_v - se.offset_v) / se.gain_v_per_m]

    pc = cfg.controller.pid_config()
    kp, ki, kd = pc.gains.kp, pc.gains.ki, pc.gains.kd
    lo, hi, slew, tau = pc.output_min_v, pc.output_max_v, pc.slew_v_per_s * dt, pc.d_filter_tau_s
    target, ramp = pc.setpoint_m, pc.setpoint_ramp_m_per_s * dt
    # leveler.loop.pid's back-calculation gain dt / (Tt + dt), Tt by Astrom and Hagglund's rule;
    # no integral: no tracking; kp == 0 (no Ti): track over three samples.
    if pc.tracking_time_s > 0.0:
        k_track = dt / (pc.tracking_time_s + dt)
    elif ki == 0.0:
        k_track = 0.0
    elif kp == 0.0:
        k_track = 0.25
    else:
        tt = abs(kp / ki) if kd == 0.0 else math.sqrt(abs(kd / ki))
        k_track = dt / (tt + dt)

    def law(x: np.ndarray, y: float) -> tuple[float, ...]:
        """leveler.loop.pid.PID.update as a function of the state
        [integral V, last output V, last measurement m, filtered derivative m/s, setpoint m,
        started 0/1]: (integral, error, unclamped, command, derivative, setpoint)."""
        i, last, prev, df, sp, started = x
        if sp != target:
            sp = min(max(target, sp - ramp), sp + ramp)
        e = sp - y
        p = kp * e
        if started:
            df = (tau * df + (y - prev)) / (tau + dt)
        else:  # the first update outputs the voltage it took over
            df = 0.0
            i = last - p
        u = p + i - kd * df
        cmd = min(max(u, lo), hi)
        cmd = min(max(cmd, last - slew), last + slew)
        return i, e, u, cmd, df, sp

    def pid_update(t: float, x: np.ndarray, u: np.ndarray, p: dict) -> list[float]:
        i, e, unclamped, cmd, df, sp = law(x, u[0])
        delta = ki * e * dt + (cmd - unclamped) * k_track
        if (delta > 0.0 and cmd >= hi) or (delta < 0.0 and cmd <= lo):
            delta = 0.0  # never integrate further into the rail it sits on
        return [i + delta, cmd, u[0], df, sp, 1.0]

    def pid_output(t: float, x: np.ndarray, u: np.ndarray, p: dict) -> list[float]:
        return [law(x, u[0])[3]]

    plant = ct.nlsys(plant_update, plant_output, inputs=["cmd", "tilt", "noise"],
                     outputs=["y"], states=["theta", "omega", "v", "phi"], dt=dt, name="plant")
    pid = ct.nlsys(pid_update, pid_output, inputs=["y"], outputs=["cmd"],
                   states=["i", "last", "prev", "df", "sp", "started"], dt=dt, name="pid")
    return ct.interconnect([plant, pid], inputs=["tilt", "noise"], outputs=["y", "cmd"])


def python_control_steps(cfg: Config, n: int) -> tuple[float, np.ndarray, np.ndarray]:
    """(seconds, sensor_m, command_v) of n steps of the python-control closed loop."""
    dt = 1.0 / cfg.loop.rate_hz
    loop = python_control_loop(cfg)
    tilt, noise = disturbance_inputs(cfg.plant, dt, n)
    settled = Plant(cfg.plant, dt, seed=1)  # the same settled start
    theta0, phi0 = settled.pendulum.theta, settled.tilt_rad()
    v0 = cfg.actuator.safe_v  # the PID starts (bumplessly) from the held voltage
    x0 = [theta0, 0.0, cfg.plant.piezo.ref_v, phi0, 0.0, v0, 0.0, 0.0,
          cfg.controller.pid_config().setpoint_m, 0.0]
    t = np.arange(n) * dt
    start = time.perf_counter()
    r = ct.input_output_response(loop, t, [tilt, noise], X0=x0)
    secs = time.perf_counter() - start
    return secs, np.asarray(r.outputs[0]), np.asarray(r.outputs[1])


def whole_loop_s(cfg: Config, duration_s: float, kernel: str = "auto") -> float:
    start = time.perf_counter()
    run_virtual(cfg, duration_s, 1, engaged=True, kernel=kernel)
    return time.perf_counter() - start


def logged_day_s(cfg: Config, text: str, duration_s: float, out: Path) -> float:
    """run_virtual with every sample and truth record logged, as `leveler sim --out`."""
    start = time.perf_counter()
    with LogWriter(out, truth=True, chunk_interval_s=cfg.log.chunk_interval_s,
                   compression=cfg.log.compression, metadata={"config": text}) as writer:
        run_virtual(cfg, duration_s, 1, engaged=True, writer=writer)
    return time.perf_counter() - start


def sim_command_s(duration_s: float, out: Path) -> float:
    """`leveler sim --out` end to end, process start to exit."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "sim", "--config", str(CONFIG),
                           "--duration", f"{duration_s:g}s", "--seed", "1", "--out", str(out),
                           "--json"], capture_output=True, text=True, check=True)
    secs = time.perf_counter() - start
    json.loads(proc.stdout)  # it finished and said something sensible
    return secs


def run(quick: bool) -> list[dict[str, Any]]:
    cfg, text = load_config(CONFIG)
    nl = nonlinear(cfg)
    rate = cfg.loop.rate_hz
    n_pc = 2_000 if quick else 6_000
    n_lev = 30_000 if quick else 150_000
    loop_s = 3600.0 if quick else 6 * 3600.0
    day_s = DAY_S / 4 if quick else DAY_S
    scale = DAY_S / day_s

    pc_s, pc_y, pc_cmd = python_control_steps(nl, n_pc)
    lev_s, lev_y, lev_cmd = leveler_steps(nl, n_lev)
    dy = float(np.max(np.abs(pc_y - lev_y[:n_pc])))
    dcmd = float(np.max(np.abs(pc_cmd - lev_cmd[:n_pc])))
    same = ("identical outputs" if dy == 0.0 and dcmd == 0.0 else
            f"outputs differ by up to {dy:.2g} m, {dcmd:.2g} V")
    objects_nl = whole_loop_s(nl, loop_s / 6, kernel="off")
    cold_nl = whole_loop_s(nl, loop_s)  # the process's first: numba and its cached kernel load
    whole_nl = whole_loop_s(nl, loop_s)
    whole_lin = whole_loop_s(cfg, loop_s)
    pc_rate = n_pc / pc_s
    lev_rate = n_lev / lev_s
    obj_rate = loop_s / 6 * rate / objects_nl
    nl_rate = loop_s * rate / whole_nl
    with bench_tmpdir() as tmp:
        day = logged_day_s(cfg, text, day_s, Path(tmp) / "day.mcap") * scale
        command_s = 2 * 3600.0 if quick else DAY_S
        command = sim_command_s(command_s, Path(tmp) / "cmd.mcap")
    hours = f"{command_s / 3600:g}h"
    quick_note = f"; quick mode: {day_s / 3600:g} h timed, times {scale:g}" if scale != 1 else ""
    return [
        row(SECTION, "python-control, non-linear loop (baseline)", pc_rate, "steps/s",
            note=f"discrete nlsys plant + PID via interconnect, input_output_response, "
                 f"{n_pc} steps; {same} to leveler's over those steps"),
        row(SECTION, "leveler Plant + PID objects, same loop", lev_rate, "steps/s",
            baseline="python-control", ratio=lev_rate / pc_rate,
            note=f"{n_lev} steps: the objects the kernel is held to, stepped directly"),
        row(SECTION, "leveler run_virtual, objects only, same loop", obj_rate, "steps/s",
            baseline="python-control", ratio=obj_rate / pc_rate,
            note=f"kernel off: the daemon's whole loop (drivers, screens, records, truth), "
                 f"{loop_s / 6 / 3600:g} h at {rate:g} Hz"),
        row(SECTION, "leveler run_virtual, same loop", nl_rate, "steps/s",
            baseline="python-control", ratio=nl_rate / pc_rate, goal=">= 100x",
            met=at_least(nl_rate / pc_rate, 100.0),
            note=f"as `leveler sim`: uneventful cycles in the compiled kernel, the rest on "
                 f"the objects, {loop_s / 3600:g} h at {rate:g} Hz"),
        row(SECTION, "  the same, first run in a process", loop_s * rate / cold_nl, "steps/s",
            baseline="python-control", ratio=loop_s * rate / cold_nl / pc_rate,
            note=f"includes loading numba and the cached kernel: "
                 f"{cold_nl - whole_nl:.2f} s once per process"),
        row(SECTION, "run_virtual, default (linear) config", loop_s * rate / whole_lin,
            "steps/s", note="for scale: what `leveler sim` steps; not python-control's model"),
        row(SECTION, "24 h at 10 Hz, every sample logged", day, "s", goal="<= 8 s",
            met=at_most(day, 8.0),
            note=f"run_virtual + LogWriter (samples and truth), closed loop{quick_note}"),
        row(SECTION, f"`leveler sim --duration {hours} --out`", command, "s",
            note="the command end to end: start-up, the logged closed-loop run, the open-loop "
                 "run, spectra"),
    ]
