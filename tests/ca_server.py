"""The daemon serving its EPICS PVs on a Channel Access port of the test's own, on loopback
only, and the client environment that finds it there (tests of the PVs and of the Bluesky
device)."""

from __future__ import annotations

import socket
import time
from typing import Any


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ca_env(port: int) -> dict[str, str]:
    return {"EPICS_CA_SERVER_PORT": str(port), "EPICS_CA_REPEATER_PORT": str(port + 1),
            "EPICS_CA_AUTO_ADDR_LIST": "NO", "EPICS_CA_ADDR_LIST": "127.0.0.1",
            "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO", "EPICS_CAS_BEACON_ADDR_LIST": "127.0.0.1",
            "EPICS_CAS_BEACON_PORT": str(port + 1)}


def epics_daemon(start_daemon: Any, *, writable: bool = False, sim: str = "",
                 replace: dict[str, str] | None = None) -> tuple[Any, int]:
    port = free_port()
    table = (f"\n[epics]\nserve = true\nwritable = {'true' if writable else 'false'}\n"
             "update_hz = 10.0\n")
    d = start_daemon(rate_hz=20.0, sim=sim, replace=replace, env=ca_env(port),
                     edit=lambda text: text + table)
    d.wait_status_lines(1)
    time.sleep(1.5)  # the loop's period statistics are recomputed once a second
    return d, port
