"""The running loop as EPICS Channel Access PVs, served by caproto on a thread of its own.

The lab's control system then archives the tilt beside the thrust stand's channels, raises
its alarms and lets a scan pause while the loop is unlocked. What the PVs show is read from
the daemon's `status()` a few times a second (the loop itself is not touched); writes, when
[epics] writable allows them, go through the daemon's own request path, so a put is checked
exactly as `leveler tune`/`start`/`stop`/`reset` are, and its event names the client.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from leveler.live.config import EpicsConfig
from leveler.rt import background_thread
from leveler.typed_config import ConfigError

_log = logging.getLogger(__name__)
STATES = ("idle", "engaged", "fault", "modulating")
#: the client of the put being handled: caproto hands its putters the value alone
_CLIENT: contextvars.ContextVar[str] = contextvars.ContextVar("epics_client", default="?")


def _groups() -> tuple[type, type]:
    """The PV groups (read-only, and with the writable PVs), built on first use: caproto is
    an optional extra, imported only by a daemon that serves PVs."""
    from caproto import ChannelType
    from caproto.server import PVGroup, pvproperty

    # caproto shares one alarm among the PVs of an alarm group: each PV its own, or the
    # piezo's MINOR is overwritten by the next PV's NO_ALARM
    def ai(name: str, units: str, precision: int, doc: str) -> Any:
        return pvproperty(name=name, value=0.0, units=units, precision=precision, doc=doc,
                          read_only=True, alarm_group=name)

    class Readable(PVGroup):  # type: ignore[misc]
        reading = ai("READING", "m", 12, "sensor reading, pendulum end")
        tilt = ai("TILT", "rad", 12, "platform tilt the reading means")
        piezo = ai("PIEZO", "V", 3, "piezo voltage applied")
        p = ai("P", "V", 4, "PID proportional term")
        i = ai("I", "V", 4, "PID integral term")
        d = ai("D", "V", 4, "PID derivative term")
        period_p99 = ai("PERIOD_P99", "s", 6, "loop period, 99th percentile")
        period_max = ai("PERIOD_MAX", "s", 6, "loop period, longest")
        overruns = pvproperty(name="OVERRUNS", value=0, read_only=True, alarm_group="OVERRUNS",
                              doc="cycles that missed their deadline")
        state = pvproperty(name="STATE", value="idle", dtype=ChannelType.ENUM,
                           enum_strings=list(STATES), read_only=True, alarm_group="STATE",
                           doc="loop state")
        fault = pvproperty(name="FAULT", value="", dtype=ChannelType.CHAR, max_length=256,
                           report_as_string=True, read_only=True, alarm_group="FAULT",
                           doc="why in fault")

    class Writable(Readable):  # type: ignore[misc]
        setpoint = pvproperty(name="SETPOINT", value=0.0, units="m", precision=12,
                              doc="setpoint of the reading")
        kp = pvproperty(name="KP", value=0.0, units="V/m", precision=6, doc="P gain")
        ki = pvproperty(name="KI", value=0.0, units="V/(m s)", precision=6, doc="I gain")
        kd = pvproperty(name="KD", value=0.0, units="V s/m", precision=6, doc="D gain")
        engage = pvproperty(name="ENGAGE", value=0, doc="1: close the loop, 0: open it")
        reset = pvproperty(name="RESET", value=0, doc="1: leave the fault state")

    return Readable, Writable


#: caproto's messages that come with a traceback though nothing crashed: a put we refused
#: (our warning says why) and a beacon no caRepeater listens for (the message says it)
_EXPECTED = ("Invalid write request", "Failed to send beacon")


def _refusal_without_traceback(record: logging.LogRecord) -> bool:
    """Keep the line, drop the traceback, for the expected messages: a journal full of
    tracebacks reads as a crash at 3 a.m."""
    if str(record.msg).startswith(_EXPECTED):
        record.exc_info, record.exc_text = None, None
    return True


def _switch(name: str, value: Any) -> bool:
    """A 0/1 PV's put: anything else is refused, not read as true."""
    if value not in (0, 1):
        raise ValueError(f"{name} takes 0 or 1, got {value!r}")
    return bool(value)


class EpicsServer:
    """Serve `cfg.prefix`-named PVs from `status()`; `act(request, who)` applies a put (the
    daemon's `request`)."""

    def __init__(self, cfg: EpicsConfig, status: Callable[[], dict[str, Any]],
                 act: Callable[[dict[str, Any], str], dict[str, Any]],
                 piezo_range_v: tuple[float, float]) -> None:
        try:
            readable, writable = _groups()
        except ImportError:
            raise ConfigError("[epics] serve = true but the caproto package is not "
                              "installed: install leveler's `epics` extra (docs/install.md), "
                              "or set serve = false") from None
        self.cfg, self._status, self._act = cfg, status, act
        for name in ("caproto.ctx", "caproto.circ"):  # the server's and its clients' logs
            logging.getLogger(name).addFilter(_refusal_without_traceback)
        self._range = piezo_range_v
        self.group = (writable if cfg.writable else readable)(prefix=cfg.prefix)
        if cfg.writable:
            self._wire_puts()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="epics", daemon=True)
        self._thread.start()
        if not self._ready.wait(10) or self._error is not None:
            raise ConfigError(f"[epics] cannot serve on {', '.join(cfg.interfaces)}: "
                              f"{self._error or 'no answer in 10 s'}")

    # -- the server thread --------------------------------------------------------------

    def _serve(self) -> None:
        background_thread()  # under the service: below the loop, as the log writer's threads
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to __init__ if it never became ready
            if self._ready.is_set():
                _log.error("EPICS server stopped: %s: %s", type(exc).__name__, exc)
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        from caproto.asyncio.server import Context

        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        ctx = Context(self.group.pvdb, list(self.cfg.interfaces))
        server = asyncio.create_task(ctx.run())
        await asyncio.sleep(0.2)  # bound, or failed to bind
        if server.done():
            server.result()  # raises what went wrong
        lo, hi = self._range  # what Phoebus and the archiver show beside the severities
        near = self.cfg.piezo_near_rail_fraction * (hi - lo)
        await self.group.piezo.write_metadata(
            lower_ctrl_limit=lo, upper_ctrl_limit=hi, lower_alarm_limit=lo,
            upper_alarm_limit=hi, lower_warning_limit=lo + near, upper_warning_limit=hi - near)
        self._ready.set()
        try:
            while not self._stop.is_set():
                try:
                    await self._update()
                except Exception:  # one bad refresh must not freeze every PV for good
                    _log.exception("EPICS: refreshing the PVs failed; trying again")
                try:
                    await asyncio.wait_for(self._stop.wait(), 1.0 / self.cfg.update_hz)
                except TimeoutError:
                    pass
        finally:
            server.cancel()
            await asyncio.gather(server, return_exceptions=True)

    async def _update(self) -> None:
        from caproto import AlarmSeverity, AlarmStatus

        st = self._status()
        g, s = self.group, st["sample"]
        stale = s is None or st["loop"]["stalled"]
        invalid = {"severity": AlarmSeverity.INVALID_ALARM, "status": AlarmStatus.TIMEOUT}
        ok = {"severity": AlarmSeverity.NO_ALARM, "status": AlarmStatus.NO_ALARM}

        async def put(pv: Any, value: Any, alarm: dict[str, Any] | None = None) -> None:
            # not verified: caproto's limit check would put its own (empty) alarm over ours
            await pv.write(value, verify_value=False, **(alarm or {}))
            # hand the interpreter lock back between PVs: a loop thread waking now waits for
            # one write, not for the whole update (measured: p99 lateness 2.6x at 1 kHz)
            time.sleep(0)

        if s is not None:
            await put(g.reading, s.sensor_m, invalid if stale else ok)
            await put(g.tilt, st["tilt_rad"], invalid if stale else ok)
            await put(g.piezo, s.applied_v, invalid if stale else self._piezo_alarm(s))
            for pv, v in ((g.p, s.p_v), (g.i, s.i_v), (g.d, s.d_v)):
                await put(pv, v, invalid if stale else ok)
        loop = st["loop"]
        await put(g.period_p99, loop.get("period_p99_s", 0.0))
        await put(g.period_max, loop.get("period_max_s", 0.0))
        await put(g.overruns, int(loop["overruns"]))
        fault = st["state"] == "fault"
        await put(g.state, st["state"], {"severity": AlarmSeverity.MAJOR_ALARM,
                                         "status": AlarmStatus.STATE} if fault
                  else invalid if stale else ok)
        await put(g.fault, st["fault_reason"][:255])
        if self.cfg.writable:  # the readbacks: what the loop runs with now
            c = st["controller"]
            for pv, key in ((g.setpoint, "setpoint_m"), (g.kp, "kp_v_per_m"),
                            (g.ki, "ki_v_per_m_s"), (g.kd, "kd_v_s_per_m")):
                if pv.value != c[key]:
                    await put(pv, c[key])
            engaged = int(st["state"] in ("engaged", "modulating"))
            if g.engage.value != engaged:
                await put(g.engage, engaged)

    def _piezo_alarm(self, s: Any) -> dict[str, Any]:
        """MAJOR at a rail (the command saturated), MINOR within the near-rail fraction."""
        from caproto import AlarmSeverity, AlarmStatus

        lo, hi = self._range
        near = self.cfg.piezo_near_rail_fraction * (hi - lo)
        if s.saturated or not lo < s.applied_v < hi:
            return {"severity": AlarmSeverity.MAJOR_ALARM, "status": AlarmStatus.HIHI
                    if s.applied_v >= (lo + hi) / 2 else AlarmStatus.LOLO}
        if s.applied_v > hi - near or s.applied_v < lo + near:
            return {"severity": AlarmSeverity.MINOR_ALARM, "status": AlarmStatus.HIGH
                    if s.applied_v >= (lo + hi) / 2 else AlarmStatus.LOW}
        return {"severity": AlarmSeverity.NO_ALARM, "status": AlarmStatus.NO_ALARM}

    def _wire_puts(self) -> None:
        """Each writable PV's put becomes a daemon request on behalf of its client."""
        g = self.group
        requests: dict[Any, Callable[[Any], dict[str, Any]]] = {
            g.setpoint: lambda v: {"verb": "tune", "setpoint_m": float(v)},
            g.kp: lambda v: {"verb": "tune", "kp_v_per_m": float(v)},
            g.ki: lambda v: {"verb": "tune", "ki_v_per_m_s": float(v)},
            g.kd: lambda v: {"verb": "tune", "kd_v_s_per_m": float(v)},
            g.engage: lambda v: {"verb": "start" if _switch("ENGAGE", v) else "stop"},
            g.reset: lambda v: {"verb": "reset"} if _switch("RESET", v) else {},
        }
        for pv, make in requests.items():
            original = pv.auth_write

            async def auth_write(hostname: str, username: str, *args: Any,
                                 _original: Any = original, **kw: Any) -> Any:
                token = _CLIENT.set(f"{username}@{hostname}")
                try:
                    return await _original(hostname, username, *args, **kw)
                finally:
                    _CLIENT.reset(token)

            pv.auth_write = auth_write

            async def putter(_group: Any, instance: Any, value: Any,
                             _make: Callable[[Any], dict[str, Any]] = make) -> Any:
                who = f"EPICS {_CLIENT.get()}"
                try:
                    req = _make(value)
                    if req:
                        loop = asyncio.get_running_loop()
                        await loop.run_in_executor(None, self._act, req, who)
                except Exception as exc:  # the client gets ECA_PUTFAIL with this text
                    _log.warning("EPICS put %s = %r by %s refused: %s", instance.pvname, value,
                                 who, exc)
                    raise
                return value

            pv.putter = putter.__get__(g)  # type: ignore[attr-defined]

    def close(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=5)


