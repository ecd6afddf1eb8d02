"""[live]: the optional live stream, off unless an address is given."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field

from leveler.typed_config import positive


def parse_address(text: str) -> tuple[str, int]:
    """'HOST:PORT' or ':PORT' (loopback) -> (host, port); port 0 takes any free one."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r} is not HOST:PORT (e.g. \"127.0.0.1:8765\")")
    host = host.strip("[]") or "127.0.0.1"
    if host != "localhost":
        try:
            ipaddress.ip_address(host)
        except ValueError:  # a host name would hide which interface it binds
            raise ValueError(f"{host!r} is not an IP address: give one (127.0.0.1, the "
                             "default; 0.0.0.0 exposes it on every interface) or localhost"
                             ) from None
    return host, int(port)


@dataclass(frozen=True, slots=True)
class LiveConfig:
    """The Foxglove WebSocket stream: what `foxglove` binds ("" = off; loopback unless a
    lab deliberately names another address: anyone who can reach it sees the loop, though
    nothing it sends can change the loop), the rate the topics are decimated to, and the
    running ASD of the reading (recomputed every `asd_interval_s` over the last
    `asd_span_s`)."""

    foxglove: str = ""
    rate_hz: float = positive(50.0)
    asd_interval_s: float = positive(5.0)
    asd_span_s: float = positive(600.0)

    def __post_init__(self) -> None:
        if self.foxglove:
            try:
                parse_address(self.foxglove)
            except ValueError as exc:
                raise ValueError(f"foxglove: {exc}") from None
        if self.asd_span_s < 10 * self.asd_interval_s:
            raise ValueError(f"asd_span_s: {self.asd_span_s:g} s should be at least ten "
                             f"asd_interval_s ({10 * self.asd_interval_s:g} s)")


@dataclass(frozen=True, slots=True)
class EpicsConfig:
    """[epics]: Channel Access PVs of the running loop (the `epics` extra, caproto). Off
    unless `serve`; on the loopback interface unless `interfaces` names others; read-only
    unless `writable`, and then only setpoint, gains, engage and reset, each checked as
    `leveler tune`/`start`/`stop`/`reset` check them and logged with the client's user@host."""

    serve: bool = False
    prefix: str = "LEV:"
    interfaces: tuple[str, ...] = ("127.0.0.1",)
    writable: bool = False
    update_hz: float = positive(2.0)
    piezo_near_rail_fraction: float = field(default=0.05, metadata={"gt": 0.0, "le": 0.5})

    def __post_init__(self) -> None:
        if not self.prefix or any(c.isspace() for c in self.prefix):
            raise ValueError(f"prefix: {self.prefix!r} must be non-empty, without spaces")
        for a in self.interfaces:
            try:
                ipaddress.ip_address(a)
            except ValueError:
                raise ValueError(f"interfaces: {a!r} is not an IP address (127.0.0.1, the "
                                 "default; 0.0.0.0 for every interface)") from None
