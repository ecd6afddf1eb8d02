"""leveler as an ophyd-async device over its EPICS PVs ([epics] serve), for Bluesky.

A thrust-measurement scan that reads `Leveler` beside its detectors records the reading, the
tilt, the piezo and the loop state in the same run (units from the PVs' EGU), and a plan can
move the setpoint. Imported in the lab's Bluesky session, not by the daemon: it needs the
`bluesky` extra (ophyd-async with its Channel Access backend) and nothing else of leveler.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from bluesky.protocols import Movable
from bluesky.suspenders import SuspendWhenChanged
from ophyd_async.core import AsyncStatus, StandardReadable, StrictEnum, wait_for_value
from ophyd_async.core import StandardReadableFormat as Format
from ophyd_async.epics.core import epics_signal_r, epics_signal_rw


class LoopState(StrictEnum):
    """LEV:STATE's choices, in the server's order (leveler.live.epics_ioc.STATES)."""

    IDLE = "idle"
    ENGAGED = "engaged"
    FAULT = "fault"
    MODULATING = "modulating"


class LevelerReadout(StandardReadable):
    """What a scan records at each point: reading (m) and tilt (rad), hinted so the live
    table and plots show them, the piezo voltage (V) and the loop state. Works against a
    read-only server ([epics] writable = false)."""

    def __init__(self, prefix: str = "LEV:", name: str = "") -> None:
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.reading = epics_signal_r(float, prefix + "READING")
            self.tilt = epics_signal_r(float, prefix + "TILT")
        with self.add_children_as_readables():
            self.piezo = epics_signal_r(float, prefix + "PIEZO")
            self.state = epics_signal_r(LoopState, prefix + "STATE")
        super().__init__(name=name)


class Leveler(LevelerReadout, Movable[float]):
    """The readout, and the setpoint (m) as a movable: needs [epics] writable = true.

    `set(x)` is done when the daemon has accepted the setpoint (a put it refuses, e.g. a
    setpoint in mm, fails the status; the daemon's journal says why). With `settle_m`, it is done
    only once the reading is within `settle_m` of x, so a scan's next reading sees the
    levelled stand; `settle_timeout_s` bounds that wait.
    """

    def __init__(self, prefix: str = "LEV:", name: str = "", settle_m: float | None = None,
                 settle_timeout_s: float = 60.0) -> None:
        with self.add_children_as_readables():  # read at each point, beside the reading
            self.setpoint = epics_signal_rw(float, prefix + "SETPOINT")
        self._settle_m, self._settle_timeout_s = settle_m, settle_timeout_s
        super().__init__(prefix, name)

    @AsyncStatus.wrap
    async def set(self, value: float) -> None:
        await self.setpoint.set(value)
        # a refused put leaves SETPOINT as it was; ophyd-async 0.21 passes the refusal as a
        # success (aioca's error is a falsy exception, which its retry wrapper drops), so
        # the readback is the check, and a refusal fails the move at once
        if (now := await self.setpoint.get_value(cached=False)) != value:
            raise ValueError(f"leveler refused setpoint {value!r} m (it stays {now!r} m); "
                             "the daemon's journal says why")
        if self._settle_m is not None:
            tol = self._settle_m
            await wait_for_value(self.reading, lambda r: abs(r - value) <= tol,
                                 timeout=self._settle_timeout_s)


def suspend_unless_engaged(lev: LevelerReadout, *, sleep: float = 1.0) -> SuspendWhenChanged:
    """A suspender for `RE.install_suspender`: the scan pauses while the loop is not engaged
    (opened by hand, in fault, modulating) and resumes, `sleep` seconds after it is engaged
    again, redoing the point it was at, so no point is recorded on an unlevelled stand."""
    return SuspendWhenChanged(_V1View(lev.state), expected_value="engaged", allow_resume=True,
                              sleep=sleep, tripped_message="the leveling loop is not engaged")


class _V1View:
    """An ophyd-async signal as bluesky's suspenders watch one (ophyd's subscribe(cb,
    event_type, run) calling cb(value=...), and get()); ophyd-async offers
    subscribe_reading only."""

    def __init__(self, signal: Any) -> None:
        self._signal = signal
        self._subs: dict[Callable[..., None], Callable[[dict[str, Any]], None]] = {}
        self.name = signal.name
        self._last = ""

    def get(self) -> str:
        """The last value seen (the suspender's message quotes it)."""
        return self._last

    def subscribe(self, cb: Callable[..., None], event_type: Any = None,
                  run: bool = True) -> None:
        def on_reading(reading: dict[str, Any]) -> None:
            self._last = str(next(iter(reading.values()))["value"])
            cb(value=self._last)

        self._subs[cb] = on_reading
        _on_bluesky_loop(lambda: self._signal.subscribe_reading(on_reading))

    def clear_sub(self, cb: Callable[..., None]) -> None:
        fn = self._subs.pop(cb)
        _on_bluesky_loop(lambda: self._signal.clear_sub(fn))


def _on_bluesky_loop(fn: Callable[[], None]) -> None:
    """fn() on the RunEngine's event loop, where ophyd-async subscribes (a suspender is
    installed from the caller's thread, which in Jupyter runs a loop of its own, and may be
    removed from the RunEngine's loop itself)."""
    from bluesky.run_engine import call_in_bluesky_event_loop, get_bluesky_event_loop

    try:
        here = asyncio.get_running_loop()
    except RuntimeError:
        here = None
    if here is not None and here is get_bluesky_event_loop():
        fn()
        return

    async def run() -> None:
        fn()

    call_in_bluesky_event_loop(run(), timeout=10)
