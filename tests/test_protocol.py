"""Request checks: every malformed request is named, nothing reaches the loop."""

from __future__ import annotations

import math
import os
import socket
from pathlib import Path

import pytest

from leveler.daemon.protocol import (
    MAX_LINE_BYTES,
    ProtocolError,
    client_socket_candidates,
    default_socket_path,
    parse_request,
    reload_args,
    socket_problem,
    tune_args,
    untrusted_socket_dir,
)


@pytest.mark.parametrize(
    ("line", "needle"),
    [
        (b"{not json", "not valid JSON"),
        (b"[1, 2]", "must be a JSON object"),
        (b'{"verb": "explode"}', "unknown verb 'explode'"),
        (b'{"v": 2, "verb": "status"}', "protocol version 2 not supported"),
        (b'{"verb": "tune", "kp_v_per_m": NaN}', "not valid JSON"),
        (b"x" * (MAX_LINE_BYTES + 1), "longer than"),
    ],
)
def test_bad_requests_are_named(line: bytes, needle: str) -> None:
    with pytest.raises(ProtocolError, match=needle):
        parse_request(line)


@pytest.mark.parametrize(
    ("req", "needle"),
    [
        ({"kp_v_per_m": "abc"}, "kp_v_per_m must be a number"),
        ({"kp_v_per_m": True}, "kp_v_per_m must be a number"),
        ({"ki_v_per_m_s": -1.0}, "ki_v_per_m_s must be >= 0.0"),
        ({"slew_v_per_s": 0.0}, "slew_v_per_s must be > 0"),
        ({"notch_q": 0.0}, r"notch_q must be > 0"),  # persisted, it would not load again
        ({"notch_depth": 1.0}, r"notch_depth must be in \[0, 1\)"),
        ({"periodic_radius": 0.0}, r"periodic_radius must be in \(0, 1\]"),
        ({"kq": 1.0}, "unknown key 'kq'"),
        ({}, "nothing to change"),
        ({"kp_v_per_m": 1.0, "persist": "yes"}, "persist must be true or false"),
        ({"setpoint_m": 1e400}, "must be finite"),
        ({"kp_v_per_m": None}, "kp_v_per_m must be a finite number, got null"),
        ({"slew_v_per_s": "inf", "kp_v_per_m": "inf"}, "kp_v_per_m must be a number"),
        ({"slew_v_per_s": "Infinity"}, "slew_v_per_s must be a number"),
        ({"slew_v_per_s": -1e400}, "slew_v_per_s must be finite"),
        ({"setpoint_m": 1.0}, "setpoint_m 1 m is not a plausible sensor reading"),
        ({"setpoint_m": -2e-3}, r"within \+-0.001 m"),
    ],
)
def test_bad_tune_arguments_are_named(req: dict[str, object], needle: str) -> None:
    with pytest.raises(ProtocolError, match=needle):
        tune_args({"v": 1, "verb": "tune", **req})


def test_good_tune() -> None:
    values, persist = tune_args({"verb": "tune", "kp_v_per_m": 2, "setpoint_m": -1e-8,
                                 "persist": True})
    assert values == {"kp_v_per_m": 2.0, "setpoint_m": -1e-8} and persist


def test_an_infinite_slew_is_no_limit_as_in_the_config() -> None:
    """docs/configuration.md allows slew_v_per_s = inf; JSON cannot carry it, so the
    request says "inf"."""
    assert tune_args({"verb": "tune", "slew_v_per_s": "inf"})[0] == {"slew_v_per_s": math.inf}
    assert tune_args({"verb": "tune", "slew_v_per_s": math.inf})[0] == {
        "slew_v_per_s": math.inf}


@pytest.mark.parametrize("line", [b"", b"\n", b"\r\n", b"  \t\r\n"])
def test_an_empty_line_is_a_request_that_gets_an_error(line: bytes) -> None:
    with pytest.raises(ProtocolError, match="empty request"):
        parse_request(line)


@pytest.mark.parametrize(
    "line",
    [b'{"v":1,"verb":"stop","verb":"start"}', b'{"v":1,"verb":"start","verb":"stop"}',
     b'{"v":1,"v":1,"verb":"status"}',
     b'{"v":1,"verb":"tune","kp_v_per_m":1.0,"kp_v_per_m":2.0}',
     b'{"v":1,"verb":"status","x":{"a":1,"a":2}}'],
)
def test_a_repeated_key_is_refused_not_the_last_one_taken(line: bytes) -> None:
    with pytest.raises(ProtocolError, match="given twice"):
        parse_request(line)


def test_socket_places() -> None:
    assert default_socket_path({"RUNTIME_DIRECTORY": "/run/leveler"}, 998) == Path(
        "/run/leveler/control.sock")
    assert default_socket_path({}, 0) == Path("/run/leveler/control.sock")
    assert default_socket_path({"XDG_RUNTIME_DIR": "/run/user/1000"}, 1000) == Path(
        "/run/user/1000/leveler/control.sock")
    assert default_socket_path({}, 1000) == Path("/tmp/leveler-1000/control.sock")
    assert client_socket_candidates({"LEVELER_SOCKET": "/x.sock"})[0] == Path("/x.sock")


def test_reload_takes_two_flags_and_nothing_else() -> None:
    assert reload_args({"v": 1, "verb": "reload"}) == (False, False)
    assert reload_args({"verb": "reload", "accept_dropped": True, "force": True}) == (True, True)
    for bad, needle in (({"accept_dropped": 1}, "accept_dropped must be true or false"),
                        ({"force": "yes"}, "force must be true or false"),
                        ({"forced": True}, "unknown key 'forced'")):
        with pytest.raises(ProtocolError, match=needle):
            reload_args({"verb": "reload", **bad})
    assert tune_args({"verb": "tune", "kd_v_s_per_m": 0.0, "force": True})[0] == {
        "kd_v_s_per_m": 0.0}
    with pytest.raises(ProtocolError, match="force must be true or false"):
        tune_args({"verb": "tune", "kd_v_s_per_m": 0.0, "force": None})


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a directory to nobody")
def test_a_socket_directory_is_trusted_only_if_no_one_else_can_write_it(tmp_path: Path) -> None:
    d = tmp_path / "d"
    d.mkdir(mode=0o750)
    assert untrusted_socket_dir(d, {0}) is None
    d.chmod(0o1777)
    assert "writable by anyone (mode 1777)" in str(untrusted_socket_dir(d, {0}))
    d.chmod(0o770)
    assert "writable by its group (mode 0770)" in str(untrusted_socket_dir(d, {0}))
    d.chmod(0o755)
    os.chown(d, 65534, 65534)
    assert "belongs to uid 65534, not to uid 0" in str(untrusted_socket_dir(d, {0}))
    assert untrusted_socket_dir(d, {0, 65534}) is None
    (tmp_path / "f").write_text("")
    assert "is not a directory" in str(untrusted_socket_dir(tmp_path / "f", {0}))


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a directory to nobody")
def test_the_client_trusts_a_system_users_directory_only_where_root_alone_could_make_it(
        tmp_path: Path) -> None:
    """/run/leveler belongs to the service's user but sits in root-only /run: trusted. The same
    directory in a world-writable place (/tmp) could be anyone's: not trusted."""
    parent = tmp_path / "run"
    parent.mkdir(mode=0o755)
    service = parent / "leveler"
    service.mkdir(mode=0o755)
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(service / "c.sock"))
        os.chown(service, 65534, 65534)
        os.chown(service / "c.sock", 65534, 65534)
        assert socket_problem(service / "c.sock") is None
        parent.chmod(0o1777)
        assert "belongs to uid 65534" in str(socket_problem(service / "c.sock"))
        parent.chmod(0o755)
        os.chown(service / "c.sock", 1234, 1234)  # not the directory owner's
        assert "c.sock belongs to uid 1234" in str(socket_problem(service / "c.sock"))
    (service / "plain").write_text("")
    os.chown(service / "plain", 65534, 65534)
    assert "is not a socket" in str(socket_problem(service / "plain"))
    assert socket_problem(service / "missing.sock") is None  # connect() will say so
