"""Request checks: every malformed request is named, nothing reaches the loop."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from leveler.protocol import (
    MAX_LINE_BYTES,
    ProtocolError,
    client_socket_candidates,
    default_socket_path,
    parse_request,
    tune_args,
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
