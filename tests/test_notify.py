"""sd_notify against a datagram socket the test owns."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from leveler.daemon.notify import Notifier


@pytest.fixture
def listener(tmp_path: Path):  # type: ignore[no-untyped-def]
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify.sock"
    sock.bind(str(path))
    sock.settimeout(2)
    yield sock, str(path)
    sock.close()


def test_outside_systemd_everything_is_a_quiet_no_op() -> None:
    n = Notifier({})
    assert not n.enabled and n.watchdog_interval_s is None
    assert n.ready("x") is False and n.watchdog() is False


def test_ready_status_watchdog_reach_the_socket(listener) -> None:  # type: ignore[no-untyped-def]
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000"})
    assert n.watchdog_interval_s == pytest.approx(2.0)
    assert n.ready("levelling")
    assert sock.recv(4096) == b"READY=1\nSTATUS=levelling"
    n.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"
    n.status("two\nlines")
    assert sock.recv(4096) == b"STATUS=two lines"
    n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"


def test_abstract_namespace_address() -> None:
    name = f"leveler-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).watchdog()
        assert sock.recv(100) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_watchdog_for_another_pid_is_ignored(listener) -> None:  # type: ignore[no-untyped-def]
    _, path = listener
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"})
    assert n.watchdog_interval_s is None


def test_a_vanished_manager_is_reported_not_raised(tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    assert n.watchdog() is False
    assert n.watchdog() is False
    assert len([r for r in caplog.records if "sd_notify" in r.message]) == 1
