"""`leveler status`: how the running daemon is (state, reading, piezo, gains, timing, log)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from leveler.cli.common import add_socket
from leveler.daemon.client import Client


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("status", help="state, reading, piezo, gains, loop timing and log of "
                       "the running daemon", description="Ask the running daemon how it is: "
                       "state (idle, engaged, fault and why), the last reading and the tilt it "
                       "means, piezo voltage, controller settings, loop period statistics and "
                       "overruns, and the log file.")
    p.add_argument("--json", action="store_true", help="print the status as one JSON object")
    add_socket(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with Client(args.socket) as client, client.reading():
        st = client.request("status")["status"]
        print(json.dumps(st) if args.json else format_status(st))
    return 0


def _limit(value: float | None) -> str:
    """A rate limit from JSON, where infinity (no limit) arrives as null."""
    return "none" if value is None else f"{value:g}"


def _driver_errors(counts: dict[str, int] | None) -> str:
    if counts is None:  # a daemon older than the count
        return "errors      (driver errors not reported by this daemon)"
    total = sum(counts.values())
    parts = ", ".join(f"{device} {n}" for device, n in counts.items())
    return f"errors      {total} driver errors since start ({parts})"


def _log_line(log: dict[str, Any]) -> str:
    where = log["path"] if log["path"] else "no file open (logging is down; retrying)"
    health = "healthy" if log["healthy"] else f"FAULT: {log['error']}"
    faults = log.get("faults", 0)  # a daemon older than the count has none
    return (f"log         {where}, {log['samples_written']} samples, {health}"
            + (f", {log['dropped']} dropped" if log["dropped"] else "")
            + (f"\n            {faults} log fault(s) since start; last: {log['last_fault']}"
               if faults else ""))


def format_status(st: dict[str, Any]) -> str:
    s = st.get("sample") or {}
    c, lp, log = st["controller"], st["loop"], st["log"]
    lines = [
        f"leveler {st['version']} (pid {st['pid']}), up {st['uptime_s'] / 60:.1f} min, "
        f"config {st['config_path']}",
        f"state       {st['state']}" + (f"  ({st['fault_reason']})" if st["fault_reason"] else ""),
        *([f"            {st['faults']} fault(s) since start; last: {st['last_fault']}"]
          if st.get("faults") and not st["fault_reason"] else []),
        *([f"            LOOP STALLED: no cycle for {lp['last_cycle_age_s']:.1f} s (a device "
           "call that does not return?); values below are from the last cycle"]
          if lp.get("stalled") else []),
        _driver_errors(st.get("driver_errors")),
    ]
    if s:
        lines += [
            f"sensor      {s['sensor_m'] * 1e9:+.2f} nm   (tilt {st['tilt_rad'] * 1e9:+.2f} nrad)"
            if s.get("sensor_m") is not None else "sensor      no valid reading",
            ("piezo       last write failed (voltage held)"
             if s.get("applied_v") is None else f"piezo       {s['applied_v']:.3f} V applied")
            + f", {s['command_v']:.3f} V commanded"
            + ("  SATURATED" if s["saturated"] else ""),
        ]
    lines += [
        f"controller  kp {c['kp_v_per_m']:.4g} V/m  ki {c['ki_v_per_m_s']:.4g} V/(m s)  "
        f"kd {c['kd_v_s_per_m']:.4g} V s/m  "
        + (f"ki2 {c['ki2_v_per_m_s2']:.4g} V/(m s^2)  " if c.get("ki2_v_per_m_s2") else "")
        + f"setpoint {c['setpoint_m']:.4g} m  "
        f"limits {c['output_min_v']:g}..{c['output_max_v']:g} V  "
        f"slew {_limit(c['slew_v_per_s'])} V/s",
        *([f"            resonant terms at harmonics 1-{len(c['periodic_gains_v_per_m_s'])} "
           f"of {c['periodic_period_s']:g} s (docs/replay.md)"]
          if c.get("periodic_gains_v_per_m_s") and c.get("periodic_period_s") else []),
        *([f"            notch on the reading at {c['notch_frequency_hz']:.4g} Hz, "
           f"Q {c['notch_q']:g}, depth {c['notch_depth']:g}"]
          if c.get("notch_frequency_hz") else []),
        *_thermometer_lines(st.get("thermometer"), st["state"]),
        f"loop        {lp['rate_hz']:g} Hz, {lp['cycles']} cycles, period p50/p99/max "
        f"{lp['period_p50_s'] * 1e3:.2f}/{lp['period_p99_s'] * 1e3:.2f}/"
        f"{lp['period_max_s'] * 1e3:.2f} ms, overruns {lp['overruns']}",
        _log_line(log),
        *_live_lines(st.get("live") or {}),
    ]
    return "\n".join(lines)


def _thermometer_lines(th: dict[str, Any] | None, state: str) -> list[str]:
    """The thermometer's last reading and what the feedforward adds (none configured: [])."""
    if th is None:
        return []
    if th["temperature_k"] is None:
        reading = "no reading yet"
    else:
        reading = f"{th['temperature_k']:.4f} K, {th['age_s']:.1f} s ago"
    line = f"thermometer {th['backend']}, every {th['interval_s']:g} s: {reading}"
    if th["errors"]:
        line += f", {th['errors']} failed reading(s) since start"
    out = [line]
    if th["trouble"]:
        out.append(f"            FAILING: {th['trouble']}; the feedforward holds")
    if th["feedforward_v"] is not None:
        out.append(f"            temperature feedforward {th['feedforward_v']:+.4f} V"
                   + (" (added while engaged)" if state != "engaged" else ""))
    return out


def _live_lines(live: dict[str, Any]) -> list[str]:
    """The live view and the EPICS server, when the config turned them on."""
    out = [f"live view   {live['foxglove']} (Foxglove)"] if live.get("foxglove") else []
    ep = live.get("epics")
    if ep:
        out.append(f"epics       {ep['prefix']}* on {', '.join(ep['interfaces'])}, "
                   + ("writable" if ep["writable"] else "read-only")
                   + ("" if ep.get("serving", True) else
                      "  STOPPED: the PVs are gone until leveler restarts (journal says why)"))
    return out
