"""Request checks: every malformed request is named, nothing reaches the loop."""

from __future__ import annotations

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
    ],
)
def test_bad_tune_arguments_are_named(req: dict[str, object], needle: str) -> None:
    with pytest.raises(ProtocolError, match=needle):
        tune_args({"v": 1, "verb": "tune", **req})


def test_good_tune() -> None:
    values, persist = tune_args({"verb": "tune", "kp_v_per_m": 2, "setpoint_m": -1e-8,
                                 "persist": True})
    assert values == {"kp_v_per_m": 2.0, "setpoint_m": -1e-8} and persist


def test_socket_places() -> None:
    assert default_socket_path({"RUNTIME_DIRECTORY": "/run/leveler"}, 998) == Path(
        "/run/leveler/control.sock")
    assert default_socket_path({}, 0) == Path("/run/leveler/control.sock")
    assert default_socket_path({"XDG_RUNTIME_DIR": "/run/user/1000"}, 1000) == Path(
        "/run/user/1000/leveler/control.sock")
    assert default_socket_path({}, 1000) == Path("/tmp/leveler-1000/control.sock")
    assert client_socket_candidates({"LEVELER_SOCKET": "/x.sock"})[0] == Path("/x.sock")
