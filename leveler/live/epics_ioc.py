"""The Channel Access server itself: a process of its own, started by the daemon
(leveler.live.epics), so caproto's Python never holds the loop's interpreter lock.

It speaks JSON lines with the daemon over its stdin and stdout: the daemon sends the loop's
state a few times a second ({"status": ...}) and the answers to puts ({"reply": id, "error":
text or null}); this process says {"ready": true} or {"failed": why} once, then hands each
put on a writable PV to the daemon ({"put": id, "req": ..., "who": "EPICS user@host"}), whose
request path checks it exactly as `leveler tune`/`start`/`stop`/`reset`. Its log lines go to
stderr, the daemon's journal. It ends when the daemon says stop or its stdin closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import itertools
import json
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

_log = logging.getLogger(__name__)
STATES = ("idle", "engaged", "fault", "modulating")
#: the client of the put being handled: caproto hands its putters the value alone
_CLIENT: contextvars.ContextVar[str] = contextvars.ContextVar("epics_client", default="?")


def _groups() -> tuple[type, type]:
    """The PV groups (read-only, and with the writable PVs)."""
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
        i = ai("I", "V", 4, "PID integral + resonant terms")
        d = ai("D", "V", 4, "PID derivative term")
        period_p99 = ai("PERIOD_P99", "s", 6, "loop period, 99th percentile")
        period_max = ai("PERIOD_MAX", "s", 6, "loop period, longest")
        overruns = pvproperty(name="OVERRUNS", value=0, read_only=True, alarm_group="OVERRUNS",
                              doc="cycles that missed their deadline")
        state = pvproperty(name="STATE", value="idle", dtype=ChannelType.ENUM,
                           enum_strings=list(STATES), read_only=True, alarm_group="STATE",
                           doc="loop state")
        # a char waveform, not a DBR_STRING (40 characters): the whole reason, read as text
        fault = pvproperty(name="FAULT", value="", dtype=ChannelType.CHAR, max_length=256,
                           report_as_string=False, read_only=True, alarm_group="FAULT",
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
_BEACON_QUIET_S = 3600.0
_beacon_said = -math.inf


def _refusal_without_traceback(record: logging.LogRecord) -> bool:
    """Keep the line, drop the traceback, for the expected messages: a journal full of
    tracebacks reads as a crash at 3 a.m. A beacon nobody hears is said once an hour, not
    every 15 s (without a caRepeater on the machine, every beacon fails)."""
    global _beacon_said
    if not str(record.msg).startswith(_EXPECTED):
        return True
    record.exc_info, record.exc_text = None, None
    if str(record.msg).startswith("Failed to send beacon"):
        now = time.monotonic()
        if now - _beacon_said < _BEACON_QUIET_S:
            return False
        _beacon_said = now
        record.msg = str(record.msg) + " (said once an hour; EPICS_CAS_BEACON_PORT sets it)"
    return True


def _switch(name: str, value: Any) -> bool:
    """A 0/1 PV's put: anything else is refused, not read as true."""
    if value not in (0, 1):
        raise ValueError(f"{name} takes 0 or 1, got {value!r}")
    return bool(value)


class Ioc:
    """The PVs of `prefix`, refreshed from the daemon's status lines, puts handed to it."""

    def __init__(self, prefix: str, interfaces: list[str], writable: bool,
                 piezo_range_v: tuple[float, float], near_rail_fraction: float,
                 stale_after_s: float) -> None:
        readable, writable_group = _groups()
        self.interfaces, self.writable = interfaces, writable
        self._stale_after_s, self._last_status, self._stale = stale_after_s, time.monotonic(), False
        self.group = (writable_group if writable else readable)(prefix=prefix)
        self._range, self._near = piezo_range_v, near_rail_fraction
        self._pending: dict[int, asyncio.Future[str | None]] = {}
        self._ids = itertools.count(1)
        if writable:
            self._wire_puts()

    async def main(self) -> None:
        from caproto.asyncio.server import Context

        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=1 << 20)
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        ctx = Context(self.group.pvdb, self.interfaces)
        server = asyncio.create_task(ctx.run())
        await asyncio.sleep(0.2)  # bound, or failed to bind
        if server.done():
            _say({"failed": f"{type(server.exception()).__name__}: {server.exception()}"})
            return
        lo, hi = self._range  # what Phoebus and the archiver show beside the severities
        near = self._near * (hi - lo)
        await self.group.piezo.write_metadata(  # display limits too: Phoebus' bar uses them
            lower_ctrl_limit=lo, upper_ctrl_limit=hi, lower_disp_limit=lo, upper_disp_limit=hi,
            lower_alarm_limit=lo, upper_alarm_limit=hi, lower_warning_limit=lo + near,
            upper_warning_limit=hi - near)
        _say({"ready": True})
        watchdog = asyncio.create_task(self._watch_daemon())
        try:
            while line := await reader.readline():
                msg = json.loads(line)
                if "status" in msg:
                    self._last_status, self._stale = time.monotonic(), False
                    try:
                        await self._update(msg["status"])
                    except Exception:  # one bad refresh must not freeze every PV for good
                        _log.exception("EPICS: refreshing the PVs failed; trying again")
                elif "reply" in msg:
                    fut = self._pending.pop(msg["reply"], None)
                    if fut is not None and not fut.done():
                        fut.set_result(msg["error"])
                elif msg.get("stop"):
                    break
        finally:
            watchdog.cancel()
            server.cancel()
            await asyncio.gather(server, watchdog, return_exceptions=True)

    async def _watch_daemon(self) -> None:
        """A daemon that stops sending (frozen, or its relay stuck) cannot say it stalled:
        its readings go INVALID here once no status came for stale_after_s."""
        from caproto import AlarmSeverity, AlarmStatus

        g = self.group
        while True:
            await asyncio.sleep(min(0.5, self._stale_after_s / 4))
            if self._stale or time.monotonic() - self._last_status < self._stale_after_s:
                continue
            self._stale = True
            _log.warning("EPICS: no status from the daemon for %.1f s; its PVs are INVALID "
                         "until it answers again", time.monotonic() - self._last_status)
            for pv in (g.reading, g.tilt, g.piezo, g.p, g.i, g.d, g.state):
                await pv.write(pv.value, verify_value=False,
                               severity=AlarmSeverity.INVALID_ALARM, status=AlarmStatus.TIMEOUT)

    async def _update(self, st: dict[str, Any]) -> None:
        from caproto import AlarmSeverity, AlarmStatus

        g, s = self.group, st["sample"]
        stale = s is None or st["stalled"]
        invalid = {"severity": AlarmSeverity.INVALID_ALARM, "status": AlarmStatus.TIMEOUT}
        ok = {"severity": AlarmSeverity.NO_ALARM, "status": AlarmStatus.NO_ALARM}

        async def put(pv: Any, value: Any, alarm: dict[str, Any] | None = None) -> None:
            # not verified: caproto's limit check would put its own (empty) alarm over ours
            await pv.write(value, verify_value=False, **(alarm or {}))

        if s is not None:
            await put(g.reading, s["sensor_m"], invalid if stale else ok)
            await put(g.tilt, s["tilt_rad"], invalid if stale else ok)
            await put(g.piezo, s["applied_v"], invalid if stale else self._piezo_alarm(s))
            for pv, key in ((g.p, "p_v"), (g.i, "i_v"), (g.d, "d_v")):
                await put(pv, s[key], invalid if stale else ok)
        await put(g.period_p99, st["period_p99_s"])
        await put(g.period_max, st["period_max_s"])
        await put(g.overruns, st["overruns"])
        fault = st["state"] == "fault"
        await put(g.state, st["state"], {"severity": AlarmSeverity.MAJOR_ALARM,
                                         "status": AlarmStatus.STATE} if fault
                  else invalid if stale else ok)
        await put(g.fault, st["fault_reason"][:255])
        if self.writable:  # the readbacks: what the loop runs with now
            c = st["controller"]
            for pv, key in ((g.setpoint, "setpoint_m"), (g.kp, "kp_v_per_m"),
                            (g.ki, "ki_v_per_m_s"), (g.kd, "kd_v_s_per_m")):
                if pv.value != c[key]:
                    await put(pv, c[key])
            engaged = int(st["state"] in ("engaged", "modulating"))
            if g.engage.value != engaged:
                await put(g.engage, engaged)

    def _piezo_alarm(self, s: dict[str, Any]) -> dict[str, Any]:
        """MAJOR at a rail (the command saturated), MINOR within the near-rail fraction."""
        from caproto import AlarmSeverity, AlarmStatus

        lo, hi = self._range
        near = self._near * (hi - lo)
        v = s["applied_v"]
        if s["saturated"]:  # at the controller's limit: HIHI at its top, LOLO at its bottom
            lo_v, hi_v = s["limits_v"]
            return {"severity": AlarmSeverity.MAJOR_ALARM, "status": AlarmStatus.HIHI
                    if abs(hi_v - v) < abs(v - lo_v) else AlarmStatus.LOLO}
        if not lo < v < hi:
            return {"severity": AlarmSeverity.MAJOR_ALARM, "status": AlarmStatus.HIHI
                    if v >= hi else AlarmStatus.LOLO}
        if v > hi - near or v < lo + near:
            return {"severity": AlarmSeverity.MINOR_ALARM, "status": AlarmStatus.HIGH
                    if v >= (lo + hi) / 2 else AlarmStatus.LOW}
        return {"severity": AlarmSeverity.NO_ALARM, "status": AlarmStatus.NO_ALARM}

    async def _ask(self, req: dict[str, Any], who: str) -> None:
        """The daemon's answer to a put; its refusal raised here, with its reason."""
        rid = next(self._ids)
        fut: asyncio.Future[str | None] = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        _say({"put": rid, "req": req, "who": who})
        try:
            error = await asyncio.wait_for(fut, 30.0)
        finally:
            self._pending.pop(rid, None)
        if error is not None:
            raise ValueError(error)

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
                        await self._ask(req, who)
                except Exception as exc:  # the client gets ECA_PUTFAIL with this text
                    shown = value.tolist() if hasattr(value, "tolist") else value
                    _log.warning("EPICS put %s = %r by %s refused: %s", instance.pvname, shown,
                                 who, exc)
                    raise
                return value

            pv.putter = putter.__get__(g)  # type: ignore[attr-defined]


def _say(msg: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


def main(argv: list[str]) -> int:
    """argv[0]: the server's settings as JSON (prefix, interfaces, writable, piezo_range_v,
    near_rail_fraction, stale_after_s), from leveler.live.epics."""
    with contextlib.suppress(OSError, AttributeError):  # the daemon's priority is inherited:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # network work, not RT
    for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C and `systemctl stop` reach the
        signal.signal(sig, signal.SIG_IGN)       # whole group: the daemon ends us, in order
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    for name in ("caproto.ctx", "caproto.circ"):  # the server's and its clients' logs
        logging.getLogger(name).addFilter(_refusal_without_traceback)
    a = json.loads(argv[0])
    ioc = Ioc(a["prefix"], a["interfaces"], a["writable"], tuple(a["piezo_range_v"]),
              a["near_rail_fraction"], a["stale_after_s"])
    asyncio.run(ioc.main())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
