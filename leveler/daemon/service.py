"""`leveler run`: the foreground daemon on a real-time clock (what systemd starts).

The loop thread owns the drivers, the PID and the log. Everything else reaches it through
`call` (control-socket verbs, run between cycles) or flags (signals), so no lock is ever
taken on the hot path. SIGINT/SIGTERM end the loop between cycles; whatever ends it, the
actuator is made safe and the log finished. SIGHUP (or the `reload` verb) reloads the
config: a file that fails validation, drops keys the running file set (cut short?) or sets
gains the plant model predicts unstable is rejected, logged, and the running config kept.
"""

from __future__ import annotations

import contextlib
import dataclasses
import faulthandler
import functools
import logging
import math
import os
import pwd
import queue
import re
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any

from leveler import __version__
from leveler.analysis.stability import predicted_instability
from leveler.daemon.control_server import (
    ControlServer,
    Peer,
    Wait,
    claim_socket_dir,
    refuse_if_served,
    resolve_group,
)
from leveler.daemon.notify import Notifier
from leveler.daemon.persist import set_keys, write_atomic
from leveler.daemon.protocol import (
    PERIODIC_KEYS,
    ProtocolError,
    bool_arg,
    default_socket_path,
    modulate_args,
    reload_args,
    tune_args,
)
from leveler.drivers.base import DriverError, Status
from leveler.errors import LogError
from leveler.log.rotate import RotatingLog
from leveler.loop.clock import RealtimeClock
from leveler.loop.cycle import ENGAGED, FAULT, IDLE, MODULATING, Loop
from leveler.loop.modulation import Wave
from leveler.loop.pid import PID, PIDGains
from leveler.rt import demote_thread, freeze_heap, lock_memory, scheduler
from leveler.settings import (
    Config,
    ControllerConfig,
    check_tune_values,
    config_diff,
    explicit_keys,
    load_config,
)
from leveler.sim.params import PlantParams
from leveler.stand import Stand, open_stand
from leveler.typed_config import ConfigError

_log = logging.getLogger("leveler")
WALL_STEP_REPORT_S = 1.0  # smaller corrections (NTP slewing, jitter) are not news
CALL_TIMEOUT_S = 2.0
STALL_AFTER_S = 1.0  # no cycle for this long (or 10 periods, if longer): `status` says stalled


class _Call:
    """A function to run on the loop thread, with its outcome for the waiting caller."""

    def __init__(self, fn: Callable[[float], Any]) -> None:
        self.fn = fn
        self.done = threading.Event()
        self.result: Any = None
        self.error: BaseException | None = None


class Daemon:
    """One running leveler: config, drivers, loop, log, control socket, systemd link."""

    def __init__(self, config_path: str | Path, duration_s: float | None = None) -> None:
        self.config_path = Path(config_path)
        self.cfg, text = load_config(self.config_path)
        self._keys = explicit_keys(text)  # what the running file sets itself
        self._config_lock = threading.Lock()  # one reload or persist at a time
        self.duration_s = duration_s
        self.stop_reason = ""
        self._reload_requested = False
        self._calls: queue.SimpleQueue[_Call] = queue.SimpleQueue()
        self._pending_events: deque[tuple[str, str, dict[str, Any]]] = deque()
        self.notifier = Notifier()
        self.started_mono = time.monotonic()
        self.last_cycle_mono = self.started_mono  # the loop thread's last completed cycle
        # The loop thread's, set as run() starts (status() runs on a client thread).
        self.memory = "not locked: loop not started"
        self.scheduler = "loop not started"
        try:
            self.gid = resolve_group(self.cfg.control.group)
        except KeyError as exc:
            raise ConfigError(f"{self.config_path}: {exc.args[0]}") from None
        self.socket_path = Path(self.cfg.control.socket_path or default_socket_path())
        claim_socket_dir(self.socket_path)  # before any device is opened or log created
        refuse_if_served(self.socket_path)
        self.stand: Stand = open_stand(self.cfg)
        self.stand.connect()
        metadata = {"config": text, "config_path": str(self.config_path.resolve()),
                    "version": __version__, "started_utc": datetime.now(UTC).isoformat()}
        lc = self.cfg.log
        self.log = RotatingLog(Path(lc.dir), metadata=metadata, truth=self.stand.truth is not None,
                               environment=self.stand.thermometer is not None,
                               chunk_interval_s=lc.chunk_interval_s, compression=lc.compression,
                               rotate_interval_s=lc.rotate_interval_s,
                               rotate_bytes=lc.rotate_bytes, retry_interval_s=lc.retry_interval_s,
                               on_fault=self._log_fault)
        self.dt = 1.0 / self.cfg.loop.rate_hz
        pid = PID(self.cfg.controller.pid_config(), initial_output_v=self.stand.actuator.safe_v)
        self.live = None
        self.epics: Any = None  # the EPICS server, started with the loop (run)
        if self.cfg.live.foxglove:  # after the log: a refused address leaves nothing open
            from leveler.live.foxglove import FoxgloveStream

            try:
                self.live = FoxgloveStream(self.cfg.live, self.cfg.loop.rate_hz)
            except ConfigError:
                self.log.close()
                self.stand.close()
                raise
        sinks = [self.log] if self.live is None else [self.log, self.live]
        self.loop = Loop(self.stand.sensor, self.stand.actuator, pid, self.dt, sinks,
                         self.stand.truth, policy=self.cfg.loop,
                         thermometer=self.stand.thermometer,
                         thermometer_interval_s=self.cfg.thermometer.interval_s,
                         feedforward=self.cfg.controller.feedforward())
        self._was_engaged = False  # the state a fault interrupted, for resuming after it
        self._reconnect_wait_s = 0.0  # 0: not in fault (or the fault has just come)
        self._next_reconnect = 0.0
        self._resume = False  # close the loop after resume_after_good_samples good readings
        self._good_run = 0
        self._reengage_after_wave = False  # a forced modulation opened the loop
        # A [[sim.faults]] clock_step offsets the wall time the clock sees (simulated backend).
        self._clock_steps = [f for f in self.cfg.sim.faults if f.kind == "clock_step"
                             ] if self.cfg.sensor.backend == "sim" else []
        self._injected_step_ns = 0
        self.clock = RealtimeClock(self.dt,
                                   wall_now_ns=lambda: time.time_ns() + self._injected_step_ns)
        self._reported_step_ns = 0
        self.server = ControlServer(self.socket_path, self, gid=self.gid,
                                    max_clients=self.cfg.control.max_clients,
                                    max_clients_per_uid=self.cfg.control.max_clients_per_uid,
                                    idle_timeout_s=self.cfg.control.idle_timeout_s)

    # ---- called from other threads -------------------------------------------------
    def call(self, fn: Callable[[float], Any], timeout_s: float = CALL_TIMEOUT_S) -> Any:
        """Run fn(t) on the loop thread between cycles and return its result."""
        c = _Call(fn)
        self._calls.put(c)
        if not c.done.wait(timeout_s):
            raise ProtocolError(f"the control loop did not answer within {timeout_s:g} s "
                                "(stalled or stopping)")
        if c.error is not None:
            raise c.error
        return c.result

    def note(self, kind: str, reason: str, **detail: Any) -> None:
        """Queue an event for the log from any thread; the loop thread writes it."""
        self._pending_events.append((kind, reason, detail))

    def refused(self, peer: Peer, why: str, repeats: int) -> None:
        """A refused connection (rate-limited by the server: `repeats` more were not reported
        since the last report for this uid)."""
        more = f" ({repeats} more refusals of this uid since the last report)" if repeats else ""
        _log.warning("control: refused pid %d uid %d: %s%s", peer.pid, peer.uid, why, more)
        self.note("access", "refused", uid=peer.uid, gid=peer.gid, pid=peer.pid,
                  unreported_before=repeats)

    def _log_fault(self, message: str) -> None:
        _log.error("log: %s", message)

    def handle(self, req: dict[str, Any], peer: Peer) -> dict[str, Any]:
        return self.request(req, _who(peer.uid))

    def request(self, req: dict[str, Any], who: str) -> dict[str, Any]:
        """One control request, checked as the socket checks it, on behalf of `who` (the
        socket's peer, an EPICS client): the events it makes name them."""
        verb = req["verb"]
        if verb == "status":
            return {"ok": True, "status": self.status()}
        if verb == "start":
            return {"ok": True, "state": self.call(lambda t: self._start(t, who))}
        if verb == "stop":
            return {"ok": True, "state": self.call(lambda t: self._stop(t, who))}
        if verb == "reset":
            return {"ok": True, "state": self.call(lambda t: self._reset(t, who))}
        if verb == "rotate":
            try:  # thread-safe; keeps I/O off the loop
                path = self.log.rotate(f"requested by {who}")
            except LogError as exc:  # a log fault (status shows it), not a daemon error
                where = f"still writing {self.log.path}" if self.log.path else "logging is down"
                raise ProtocolError(f"rotate failed: {exc}; {where} (a log fault in `leveler "
                                    f"status`; a new file is tried every "
                                    f"{self.cfg.log.retry_interval_s:g} s)") from None
            return {"ok": True, "path": str(path)}
        if verb == "modulate":
            amplitude_v, period_s, cycles, shape, force = modulate_args(req)
            return {"ok": True, **self.call(
                lambda t: self._modulate(t, who, amplitude_v, period_s, cycles, shape, force))}
        if verb == "tune":
            values, persist = tune_args(req)
            new = self._validated(values)
            forced = bool_arg(req, "tune", "force")
            if not forced:
                try:
                    self._refuse_unstable(self.cfg.plant, self.cfg.controller, new)
                except ProtocolError as exc:
                    raise ProtocolError(f"tune: {exc}") from None
            reason = f"tune by {who}" + (" (--force: no stability check)" if forced else "")
            self.call(lambda t: self._apply_controller(new, t, reason))
            if persist:
                self._persist(values)
            return {"ok": True, "controller": dataclasses.asdict(new), "persisted": persist}
        if verb == "reload":
            accept_dropped, force = reload_args(req)
            return {"ok": True, **self.reload(who, accept_dropped=accept_dropped, force=force)}
        raise ProtocolError(f"verb {verb!r} is not served here")

    def reload(self, who: str, *, accept_dropped: bool = False,
               force: bool = False) -> dict[str, Any]:
        """Re-read the config file and apply it only if it is whole: valid, setting every key
        the running file set (unless `accept_dropped`), and with gains the plant model
        predicts stable (unless `force`). Runs off the loop thread (parsing, python-control);
        the change is applied between two cycles. A refusal is logged and raised."""
        with self._config_lock:
            try:
                new, text = load_config(self.config_path)
                dropped = sorted(self._keys - explicit_keys(text))
                if dropped and not accept_dropped:
                    named = ", ".join(dropped[:12]) + (f" and {len(dropped) - 12} more"
                                                       if len(dropped) > 12 else "")
                    raise ProtocolError(
                        f"{self.config_path} no longer sets {len(dropped)} key(s) the running "
                        f"config set: {named} (a file cut short?); they would take their "
                        "defaults. To mean that: leveler reload --accept-dropped")
                if text and not text.endswith("\n") and not accept_dropped:
                    last = text.rsplit("\n", 1)[-1].strip()
                    raise ProtocolError(
                        f"{self.config_path} ends mid-line (no newline after {last!r}): a "
                        "file cut short? Its last value may be cut too. To mean it: leveler "
                        "reload --accept-dropped")
                self._refuse_without_thermometer(new.controller)
                if not force:
                    self._refuse_unstable(new.plant, self.cfg.controller, new.controller)
            except (ConfigError, ProtocolError) as exc:
                _log.error("reload rejected, keeping the running config: %s", exc)
                self.note("reload", f"rejected: {exc}", by=who)
                raise ProtocolError(f"reload rejected, the running config is kept: {exc}"
                                    ) from None
            try:
                return self.call(lambda t: self._apply_reload(new, text, t, who, dropped,
                                                              force))
            except ProtocolError as exc:  # the loop did not answer: say so in the journal
                _log.error("reload (%s): %s", who, exc)
                raise

    def _instability(self, plant: PlantParams, c: ControllerConfig) -> str | None:
        """Why the plant model predicts `c`'s gains unstable at the running rate, or None."""
        return predicted_instability(plant, self.cfg.loop.rate_hz, c.kp_v_per_m,
                                     c.ki_v_per_m_s, c.kd_v_s_per_m, c.d_filter_tau_s,
                                     c.periodic_terms(), c.notch(), c.ki2_v_per_m_s2)

    def _unstable_at_start(self) -> str | None:
        """Why the plant model says the configured gains make an unstable loop, or None.

        Checked before engage_on_start closes the loop: gains tuned at another rate, or for
        a pendulum of the other kind (a hanging one reads tilt with the opposite sign), would
        otherwise set the stand ringing at once. `leveler start` still engages by hand."""
        why = self._instability(self.cfg.plant, self.cfg.controller)
        if why is not None:
            _log.warning("not engaged on start: %s; the actuator holds its safe voltage "
                         "(check the gains with `leveler tune --suggest`; `leveler start` "
                         "engages anyway)", why)
        return why

    def _refuse_unstable(self, plant: PlantParams, old: ControllerConfig,
                         new: ControllerConfig) -> None:
        """ProtocolError if `new` changes the loop's gains to ones the plant model predicts
        unstable at the running rate (a setpoint or limit change is never refused here)."""
        gains = ("kp_v_per_m", "ki_v_per_m_s", "kd_v_s_per_m", "ki2_v_per_m_s2", "d_filter_tau_s",
                 *PERIODIC_KEYS, "notch_frequency_hz", "notch_q", "notch_depth")
        if all(getattr(old, k) == getattr(new, k) for k in gains):
            return
        why = self._instability(plant, new)
        if why is not None:
            raise ProtocolError(f"{why}; nothing applied (check the margins with `leveler "
                                "tune --suggest`, or --force to apply anyway)")

    def watch(self, req: dict[str, Any], wait: Wait) -> Iterator[dict[str, Any]]:
        """Samples at a decimated rate (default 10 Hz) until the client leaves; rate_hz was
        checked by protocol.parse_request. `wait` notices a client that hangs up, and the
        server caps it at idle_timeout_s, so even rate_hz 1e-6 cannot hold a slot."""
        period = max(1.0 / float(req.get("rate_hz", 10.0)), self.dt)
        last_seq = -1
        while not self.stop_reason:
            s = self.loop.last
            if s is not None and s.seq != last_seq:
                last_seq = s.seq
                yield {"sample": s}
            if not wait(period):
                return

    def status(self) -> dict[str, Any]:
        """Served from the control thread, so it answers while the loop hangs in a device
        call: the age of the last cycle tells a stalled loop from a healthy one."""
        s = self.loop.last
        pend = self.cfg.plant.pendulum
        stats = self.clock.stats()
        age_s = time.monotonic() - self.last_cycle_mono
        return {
            "version": __version__,
            "pid": os.getpid(),
            "config_path": str(self.config_path),
            "uptime_s": round(time.monotonic() - self.started_mono, 3),
            "state": self.loop.state,
            "fault_reason": self.loop.fault_reason,
            "faults": self.loop.faults,
            "last_fault": self.loop.last_fault,
            "driver_errors": dict(self.loop.errors),
            "modulation": (dataclasses.asdict(self.loop.wave) if self.loop.wave is not None
                           else None),
            "sample": s,
            "tilt_rad": (s.sensor_m / (pend.amplification * pend.sensor_arm_m)
                         if s is not None else None),
            "controller": dataclasses.asdict(self.cfg.controller),
            "thermometer": self._thermometer_status(),
            "loop": {"rate_hz": self.cfg.loop.rate_hz, "cycles": self.clock.cycles,
                     "overruns": self.clock.overruns, "scheduler": self.scheduler,
                     "memory": self.memory, "last_cycle_age_s": round(age_s, 3),
                     "stalled": age_s > max(STALL_AFTER_S, 10 * self.dt), **stats},
            "log": {"path": str(self.log.path) if self.log.path else None,
                    "samples_written": self.log.samples_written, "dropped": self.log.dropped,
                    "healthy": self.log.healthy, "error": self.log.last_error,
                    "faults": self.log.faults, "last_fault": self.log.last_fault},
            "live": {"foxglove": self.live.url if self.live is not None else None,
                     "epics": None if self.epics is None else {
                         "serving": self.epics.serving,
                         "prefix": self.cfg.epics.prefix, "writable": self.cfg.epics.writable,
                         "interfaces": list(self.cfg.epics.interfaces)}},
        }

    def _thermometer_status(self) -> dict[str, Any] | None:
        """The last reading and the feedforward, None without a thermometer."""
        loop = self.loop
        if loop.thermometer is None:
            return None
        r, now_t = loop.temperature, loop.last.t_s if loop.last is not None else math.nan
        return {"backend": self.cfg.thermometer.backend,
                "interval_s": self.cfg.thermometer.interval_s,
                "temperature_k": r.temperature_k if r is not None else None,
                "age_s": round(now_t - r.t_s, 3) if r is not None else None,
                "errors": loop.thermometer_errors, "trouble": loop.thermometer_trouble,
                "feedforward_v": loop.ff.v if loop.ff is not None else None}

    # ---- run on the loop thread ----------------------------------------------------
    def _start(self, t: float, who: str) -> str:
        if self.loop.state == FAULT:
            raise ProtocolError(f"in fault ({self.loop.fault_reason}); run `leveler reset` "
                                "first")
        if self.loop.state == MODULATING:
            raise ProtocolError("modulating: wait for the wave to end, or `leveler stop` to "
                                "abort it")
        self.loop.engage(t, f"start by {who}")
        return self.loop.state

    def _stop(self, t: float, who: str) -> str:
        self._resume = False  # a person said stop: no automatic resume after a reconnect
        self._reengage_after_wave = False
        self.loop.disengage(t, f"stop by {who}")
        return self.loop.state

    def _maybe_reconnect(self, t: float, now: float) -> None:
        """In fault, reconnect the devices at doubling intervals and probe the sensor; a
        good reading leaves the fault (and closes the loop again if it was closed): a
        pulled cable put back at 3 a.m. must not need a person to resume leveling."""
        lc = self.cfg.loop
        if self._reconnect_wait_s == 0.0:  # the fault just came: first try after the minimum
            self._reconnect_wait_s = lc.reconnect_min_s
            self._next_reconnect = now + self._reconnect_wait_s
            return
        if now < self._next_reconnect:
            return
        try:
            self.stand.close()
            self.stand.connect()
            reading = self.stand.sensor.read(t)
            if reading.status != Status.OK:
                raise DriverError(f"probe reading not OK ({reading.status.name})")
        except DriverError as exc:
            self._reconnect_wait_s = min(2 * self._reconnect_wait_s, lc.reconnect_max_s)
            self._next_reconnect = now + self._reconnect_wait_s
            self.loop.emit("reconnect", f"failed: {exc}", t,
                           next_try_s=round(self._reconnect_wait_s, 3))
            return
        self.loop.emit("reconnect", "devices answer again", t)
        self.loop.reset(t, "reconnected")
        # Close the loop again from the next good cycle's reading (bumpless).
        self._resume = self._was_engaged and lc.resume_after_reconnect
        self._good_run = 0

    def _modulate(self, t: float, who: str, amplitude_v: float, period_s: float, cycles: int,
                  shape: str, force: bool) -> dict[str, Any]:
        """Start a tilt modulation from idle; from engaged only if forced, and then close the
        loop again when the wave has ended."""
        loop = self.loop
        if loop.state == ENGAGED and not force:
            raise ProtocolError("engaged: the loop would fight the modulation; `leveler stop` "
                                "first, or force it (the loop closes again afterwards)")
        if loop.state not in (IDLE, ENGAGED):
            raise ProtocolError(f"cannot modulate while {loop.state}")
        try:  # checked before the loop opens: a refused wave leaves it as it was
            Wave(loop.held_v, amplitude_v, period_s, cycles, shape=shape).check_fits(
                self.cfg.controller.output_min_v, self.cfg.controller.output_max_v, self.dt)
        except ValueError as exc:
            raise ProtocolError(f"modulate: {exc}") from None
        was_engaged = loop.state == ENGAGED
        if was_engaged:
            loop.disengage(t, f"modulate --force by {who}")
        wave = loop.modulate(t, amplitude_v, period_s, cycles, f"modulate by {who}", shape)
        self._reengage_after_wave = was_engaged
        pend, pz = self.cfg.plant.pendulum, self.cfg.plant.piezo
        return {"wave": dataclasses.asdict(wave), "rate_hz": self.cfg.loop.rate_hz,
                "model": {"sensor_m_per_rad": pend.amplification * pend.sensor_arm_m,
                          "tilt_rad_per_v": pz.gain_m_per_v
                          / self.cfg.plant.platform.support_spacing_m,
                          "pendulum": dataclasses.asdict(pend),
                          "disturbances": self.cfg.plant.disturbances}}

    def _check_wall_clock(self, t: float) -> None:
        """Report a step of the system clock (more than WALL_STEP_REPORT_S since the last
        report); log times stay on the monotonic timeline either way."""
        self._injected_step_ns = round(sum(f.size for f in self._clock_steps if t >= f.at_s)
                                       * 1e9)
        step = self.clock.wall_step_ns()
        if abs(step - self._reported_step_ns) > WALL_STEP_REPORT_S * 1e9:
            self.loop.emit("clock", f"wall clock stepped by "
                           f"{(step - self._reported_step_ns) / 1e9:+.3f} s; log times keep the "
                           "monotonic timeline", t, offset_s=step / 1e9)
            self._reported_step_ns = step

    def _reset(self, t: float, who: str) -> str:
        if self.loop.state != FAULT:
            return self.loop.state
        try:
            self.stand.close()
            self.stand.connect()
        except Exception as exc:
            raise ProtocolError(f"reset failed, still in fault: reconnect: {exc}") from None
        self.loop.reset(t, f"reset by {who}")
        return self.loop.state

    def _validated(self, values: dict[str, Any]) -> ControllerConfig:
        """The controller config with `values` applied, checked as a whole first."""
        try:
            check_tune_values(self.cfg, values)  # within the sensor's and actuator's ranges
            new = dataclasses.replace(self.cfg.controller, **values)
            new.pid_config()
        except (ValueError, ConfigError) as exc:
            raise ProtocolError(f"tune: {exc}") from None
        self._refuse_without_thermometer(new)
        return new

    def _refuse_without_thermometer(self, new: ControllerConfig) -> None:
        """ProtocolError for a feedforward on a daemon that reads no thermometer (one added
        to the file is opened at the next restart, not by a tune or reload)."""
        if new.feedforward() is not None and self.loop.thermometer is None:
            raise ProtocolError(
                "a temperature feedforward needs a thermometer, and this daemon reads none: "
                f"add [thermometer] to {self.config_path} and restart it "
                "(docs/configuration.md)")

    def _apply_controller(self, new: ControllerConfig, t: float, reason: str) -> None:
        """Apply gains, setpoint, limits and slew bumplessly; log what changed."""
        old = self.cfg.controller
        pid = self.loop.pid
        changed = {k: [getattr(old, k), getattr(new, k)] for k in dataclasses.asdict(new)
                   if getattr(old, k) != getattr(new, k)}
        if (new.output_min_v, new.output_max_v) != (old.output_min_v, old.output_max_v):
            pid.set_limits(new.output_min_v, new.output_max_v)
        if new.slew_v_per_s != old.slew_v_per_s:
            pid.set_slew(new.slew_v_per_s)
        if new.setpoint_m != old.setpoint_m:
            pid.set_setpoint(new.setpoint_m)
        gains = PIDGains(new.kp_v_per_m, new.ki_v_per_m_s, new.kd_v_s_per_m, new.ki2_v_per_m_s2)
        if gains != PIDGains(old.kp_v_per_m, old.ki_v_per_m_s, old.kd_v_s_per_m,
                             old.ki2_v_per_m_s2):
            pid.set_gains(gains)
        if new.periodic_terms() != old.periodic_terms():
            pid.set_periodic(new.periodic_terms())
        if new.notch() != old.notch():
            pid.set_notch(new.notch())
        if new.feedforward() != old.feedforward():
            self.loop.set_feedforward(new.feedforward())
        self.cfg = dataclasses.replace(self.cfg, controller=new)
        if changed:
            self.loop.emit("tune", reason, t, **changed)

    def _persist(self, values: dict[str, Any]) -> None:
        with self._config_lock:
            try:
                text = set_keys(self.config_path.read_text(), "controller", values)
                write_atomic(self.config_path, text, load_config)
            except (OSError, ConfigError) as exc:
                raise ProtocolError(f"tune applied, but not persisted: {exc}") from None
            self._keys |= explicit_keys(text)
        self.note("persist", "controller written to config", path=str(self.config_path),
                  **values)

    def _apply_reload(self, new: Config, text: str, t: float, who: str,
                      dropped: list[str], forced: bool) -> dict[str, Any]:
        """Apply a checked config: [controller] at once (bumpless), the status interval too;
        the rest is reported as needing a restart. Logs the diff of effective values."""
        diff = {k: list(v) for k, v in config_diff(self.cfg, new).items()}
        live_loop = dataclasses.replace(new.loop, status_interval_s=self.cfg.loop.status_interval_s)
        restart = ["loop"] if live_loop != self.cfg.loop else []
        restart += [name for name in ("log", "control", "sensor", "actuator", "plant", "sim",
                                      "thermometer")
                    if getattr(new, name) != getattr(self.cfg, name)]
        self._apply_controller(new.controller, t, f"reload ({who})"
                               + (" (--force: no stability check)" if forced else ""))
        self.cfg = dataclasses.replace(self.cfg, loop=dataclasses.replace(
            self.cfg.loop, status_interval_s=new.loop.status_interval_s))
        self._keys = explicit_keys(text)
        self.loop.emit("reload", "applied", t, by=who, changed=diff, needs_restart=restart,
                       dropped=dropped, forced=forced)
        _log.info("reload (%s) applied: %s", who, "; ".join(
            f"{k} {old!r} -> {value!r}" for k, (old, value) in diff.items()) or "no change")
        if restart:
            _log.warning("reload: changes to [%s] take effect at the next restart",
                         "], [".join(restart))
        return {"changed": diff, "needs_restart": restart, "dropped": dropped}

    def _drain(self, t: float) -> None:
        while self._pending_events:
            kind, reason, detail = self._pending_events.popleft()
            self.loop.emit(kind, reason, t, **detail)
        while True:
            try:
                c = self._calls.get_nowait()
            except queue.Empty:
                break
            try:
                c.result = c.fn(t)
            except BaseException as exc:
                c.error = exc
            c.done.set()

    def status_line(self) -> str:
        s = self.loop.last
        if s is None:
            return "no sample yet"
        pend = self.cfg.plant.pendulum
        tilt_rad = s.sensor_m / (pend.amplification * pend.sensor_arm_m)
        st = self.clock.stats()
        log = "" if self.log.healthy else f"  LOG FAULT: {self.log.last_error}"
        errors = sum(self.loop.errors.values())
        return (
            f"t={s.t_s:9.1f} s  {s.state:<7}  sensor={s.sensor_m * 1e9:+9.2f} nm  "
            f"tilt={tilt_rad * 1e9:+8.2f} nrad  piezo={s.applied_v:7.3f} V"
            f"{' SAT' if s.saturated else ''}  period p50/p99/max="
            f"{st['period_p50_s'] * 1e3:.2f}/{st['period_p99_s'] * 1e3:.2f}/"
            f"{st['period_max_s'] * 1e3:.2f} ms  overruns={self.clock.overruns}  "
            f"{f'driver_errors={errors}  ' if errors else ''}"
            f"logged={self.log.samples_written}{log}"
        )

    def run(self) -> int:
        """Serve until signalled (or for duration_s); returns the process exit code."""
        handlers = {signal.SIGINT: self._on_stop, signal.SIGTERM: self._on_stop,
                    signal.SIGHUP: self._on_hup}
        previous = {sig: signal.signal(sig, h) for sig, h in handlers.items()}
        loop, clock, cfg = self.loop, self.clock, self.cfg
        # A thread holding the interpreter lock keeps the loop waiting up to one switch
        # interval (5 ms by default) after its deadline: keep that below a period.
        sys.setswitchinterval(min(sys.getswitchinterval(), self.dt / 4))
        self.memory, self.scheduler = lock_memory(), scheduler()
        unstable = self._unstable_at_start() if cfg.loop.engage_on_start else None
        frozen = freeze_heap()  # last before the loop: what exists now lives as long
        print(f"leveler {__version__}: {cfg.sensor.backend} backend at {cfg.loop.rate_hz:g} Hz, "
              f"logging to {self.log.path}, control socket {self.socket_path}"
              + (f", live view {self.live.url} (Foxglove: Open connection)"
                 if self.live is not None else ""), flush=True)
        wd = self.notifier.watchdog_interval_s
        next_wd = time.monotonic()
        next_status = time.monotonic() + cfg.loop.status_interval_s
        good, ready = 0, False
        t = 0.0
        try:
            self.server.start()
            if cfg.epics.serve:  # its puts come back through self.request, as the socket's
                from leveler.live.epics import EpicsServer

                lo, hi, _ = cfg.actuator_range_v()
                self.epics = EpicsServer(cfg.epics, self.status, self.request, (lo, hi))
            t = clock.tick()
            loop.emit("start", "daemon started", t, config=str(self.config_path),
                      socket=str(self.socket_path), scheduler=self.scheduler,
                      memory=self.memory, heap_frozen=frozen)
            loop.cycle(t, clock.wall_ns(t))
            if unstable is not None:  # the actuator stays at its safe voltage
                loop.emit("stability", f"not engaged on start: {unstable}", t)
            elif self.cfg.loop.engage_on_start:
                loop.engage(t, "engage_on_start")
            while not self.stop_reason and (self.duration_s is None or t < self.duration_s):
                t = clock.tick()
                self._drain(t)
                if self._reload_requested:  # parsing and checks off the loop thread
                    self._reload_requested = False
                    threading.Thread(target=self._reload_on_signal, name="reload",
                                     daemon=True).start()
                s = loop.cycle(t, clock.wall_ns(t))
                now = self.last_cycle_mono = time.monotonic()
                if loop.state == FAULT:
                    self._reengage_after_wave = False  # a procedure that faulted stays open
                    self._maybe_reconnect(t, now)
                else:
                    self._reconnect_wait_s = 0.0
                    if self._resume:  # after a reconnect: N good readings, then close
                        self._good_run = self._good_run + 1 if s.status == 0 else 0
                        if self._good_run >= cfg.loop.resume_after_good_samples:
                            self._resume = False
                            loop.engage(t, f"resume after reconnect ({self._good_run} good "
                                        "readings)")
                    if self._reengage_after_wave and loop.state != MODULATING:
                        self._reengage_after_wave = False
                        loop.engage(t, "resume after modulation")
                    self._was_engaged = loop.state == ENGAGED
                if wd is not None and now >= next_wd:
                    self.notifier.watchdog()  # from this thread: a stalled loop stops it
                    next_wd = now + wd
                if not ready:
                    good = good + 1 if s.status == 0 else 0
                    if good >= self.cfg.loop.ready_samples:
                        ready = True
                        self.notifier.ready(self.status_line())
                if now >= next_status:
                    next_status += self.cfg.loop.status_interval_s
                    self._check_wall_clock(t)
                    line = self.status_line()
                    print(line, flush=True)
                    self.notifier.status(line)
        except BaseException as exc:  # a bug, not a DriverError: the log says what it was
            self.stop_reason = self.stop_reason or f"unexpected {type(exc).__name__}: {exc}"
            raise
        finally:
            self.notifier.stopping()
            safe = self.stand.actuator.make_safe()  # first: nothing below can stop it
            try:
                reason = self.stop_reason or "finished"
                if not safe:
                    reason += ("; the safe voltage could NOT be set (actuator unreachable): "
                               "the piezo holds its last voltage")
                    _log.critical("stopping: %s", reason)
                if loop.state in (ENGAGED, MODULATING):  # the log says what was cut short
                    loop.disengage(t, reason)
                loop.emit("stop", reason, t, overruns=clock.overruns,
                          sensor_errors=loop.errors["sensor"],
                          actuator_errors=loop.errors["actuator"], safe=safe)
            finally:  # even if the log refused those events: finish it, remove the socket
                with contextlib.ExitStack() as closing:  # each runs even if one before fails
                    for sig, handler in previous.items():
                        closing.callback(signal.signal, sig, handler)
                    for close in (self.notifier.close, self.stand.close, self.log.close,
                                  self.server.close):
                        closing.callback(close)
                    for server in (self.live, self.epics):
                        if server is not None:
                            closing.callback(server.close)
        print(f"stopped ({self.stop_reason or 'finished'}): {self.log.samples_written} samples "
              f"in {', '.join(str(p) for p in self.log.files)}", file=sys.stderr, flush=True)
        return 0

    def _on_stop(self, signum: int, frame: FrameType | None) -> None:
        self.stop_reason = signal.Signals(signum).name

    def _on_hup(self, signum: int, frame: FrameType | None) -> None:
        self._reload_requested = True

    def _reload_on_signal(self) -> None:
        demote_thread()  # started by the loop thread: not at its real-time priority
        with contextlib.suppress(ProtocolError):  # reload() logged why
            self.reload("SIGHUP")


@functools.lru_cache(maxsize=64)
def _who(uid: int) -> str:
    """A socket peer as events name it: "uid 1000 (alice)", the name when the system knows
    it (an EPICS put names its client as user@host; the log should read alike). Looked up
    once per uid: the passwd file is read on every lookup, and a client may send thousands
    of requests a second on the thread that shares the loop's interpreter lock."""
    try:
        return f"uid {uid} ({pwd.getpwuid(uid).pw_name})"
    except KeyError:
        return f"uid {uid}"


def run_daemon(config_path: str | Path, duration_s: float | None = None) -> int:
    faulthandler.enable()  # a watchdog SIGABRT then leaves every thread's stack in the journal
    os.umask(0o027)  # logs readable by the daemon's group, by no one else: whoever starts it
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    # The Modbus driver reports every failure itself (driver_error events, `status`); the
    # library's own ERROR lines and frame dumps would repeat each one in the journal.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        daemon = Daemon(config_path, duration_s)
    except DriverError as exc:  # at start only: later, faults and reconnects handle it
        why = re.sub(r";? *retrying in [0-9.]+ s\.?$", "", str(exc))
        print(f"leveler run: cannot start, a device does not answer: {why}\n"
              "(exit 1: under systemd the service is started again after RestartSec; by "
              "hand, check the wiring, or start `leveler emulate` for an emulated stand)",
              file=sys.stderr, flush=True)
        return 1
    return daemon.run()
