"""The control protocol: line-delimited JSON over a Unix socket, versioned.

Request:  {"v": 1, "verb": "status"} (plus the verb's arguments), one per line.
Response: {"v": 1, "ok": true, ...} or {"v": 1, "ok": false, "error": "what was wrong"}.
Every line gets exactly one response (an empty one and an object that repeats a key are
errors, not skipped or half read); `watch` answers with one response and then a line per
streamed sample. JSON has no infinity: `tune` takes the string "inf" for slew_v_per_s (no
limit, as in the config), and responses carry non-finite numbers as null.
This module holds what client and server share: the version, the limits, the socket's
default place and the checks on a request's shape.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import orjson

from leveler.loop.modulation import SHAPES

VERSION = 1
MAX_LINE_BYTES = 64 * 1024
VERBS = ("status", "start", "stop", "tune", "watch", "rotate", "reset", "modulate", "reload")
#: verbs that take no arguments: any other key is a mistake, refused rather than ignored
NO_ARGS = ("status", "start", "stop", "rotate", "reset")
MAX_WATCH_HZ = 1000.0

#: tune arguments: config key -> lower bound (inclusive) or None
TUNE_KEYS: dict[str, float | None] = {
    "kp_v_per_m": 0.0,
    "ki_v_per_m_s": 0.0,
    "kd_v_s_per_m": 0.0,
    "ki2_v_per_m_s2": 0.0,
    "setpoint_m": None,
    "output_min_v": None,
    "output_max_v": None,
    "slew_v_per_s": None,
    "notch_frequency_hz": 0.0,  # 0: no notch (leveler.loop.notch)
    "notch_q": 0.0,
    "notch_depth": 0.0,
}
#: tune arguments that may be infinite (the string "inf" on the wire), as in the config
TUNE_INF_OK = ("slew_v_per_s",)
#: tune arguments of the resonant terms (leveler.loop.resonant): the period and radius are
#: numbers, the gains and phases lists of them (at most MAX_HARMONICS each)
PERIODIC_KEYS = ("periodic_period_s", "periodic_gains_v_per_m_s", "periodic_phases_rad",
                 "periodic_radius")
MAX_HARMONICS = 64
#: tune arguments of the temperature feedforward (leveler.loop.feedforward): lists of
#: numbers, a path per gain (at most MAX_HARMONICS)
FEEDFORWARD_KEYS = ("feedforward_gains_v_per_k", "feedforward_lags_s", "feedforward_lags2_s")
_LIST_KEYS = ("periodic_gains_v_per_m_s", "periodic_phases_rad", *FEEDFORWARD_KEYS)
#: the bound on a tune setpoint the request alone can check: a leveling sensor reads
#: micrometres, so a setpoint of millimetres is a unit slip (1 for 1e-6), not a setting
SETPOINT_BOUND_M = 1e-3


class ProtocolError(ValueError):
    """A request the daemon will not act on; the message goes back to the client."""


def default_socket_path(env: dict[str, str] | None = None, uid: int | None = None) -> Path:
    """Where the daemon listens when the config does not say.

    Under systemd RuntimeDirectory=leveler gives $RUNTIME_DIRECTORY; root without systemd
    uses /run/leveler; anyone else their own runtime directory.
    """
    env = dict(os.environ) if env is None else env
    uid = os.getuid() if uid is None else uid
    if env.get("RUNTIME_DIRECTORY"):
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0]) / "control.sock"
    if uid == 0:
        return Path("/run/leveler/control.sock")
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "leveler" / "control.sock"
    return Path(f"/tmp/leveler-{uid}/control.sock")


def untrusted_socket_dir(directory: Path, trusted_uids: set[int]) -> str | None:
    """Why a socket in `directory` may not be the one it claims to be, or None.

    Whoever can write a socket's directory can swap the socket for their own and read what
    clients send it; so, as ssh-agent and tmux insist, the directory must be owned by a
    trusted uid and writable by no one else (an attacker can make `/tmp/leveler-<uid>`
    before the daemon does)."""
    link = os.lstat(directory)
    if stat.S_ISLNK(link.st_mode) and link.st_uid not in trusted_uids:
        return (f"{directory} is a symlink of uid {link.st_uid}, who could point it elsewhere "
                "at any time")
    st = os.stat(directory)
    if not stat.S_ISDIR(st.st_mode):
        return f"{directory} is not a directory"
    if st.st_uid not in trusted_uids:
        return (f"{directory} belongs to uid {st.st_uid}, not to "
                + " or ".join(f"uid {u}" for u in sorted(trusted_uids))
                + ": someone else may have made it to plant their own socket")
    if st.st_mode & 0o022:
        who = "anyone" if st.st_mode & 0o002 else "its group"
        return (f"{directory} is writable by {who} (mode {stat.S_IMODE(st.st_mode):04o}), who "
                "could replace the socket")
    return None


def socket_problem(path: Path) -> str | None:
    """Why a client should not talk to the socket at `path`, or None: the directory and
    socket must belong to root, to us, or to a system user whose directory only root could
    have made (the service's /run/leveler, made by systemd under root-owned /run)."""
    me = os.geteuid()
    trusted = {0, me}
    directory = path.parent
    try:
        st = os.stat(path)
        owner = os.stat(directory).st_uid
        if owner not in trusted and untrusted_socket_dir(directory.parent, {0}) is None:
            trusted.add(owner)  # a directory only root could have created: the service's
        why = untrusted_socket_dir(directory, trusted)
    except PermissionError:
        return None  # we cannot reach it at all: connect() will say so
    except FileNotFoundError:
        return None
    if why is not None:
        return why
    if not stat.S_ISSOCK(st.st_mode):
        return f"{path} is not a socket"
    if st.st_uid not in trusted:
        return f"{path} belongs to uid {st.st_uid}, not to the owner of {directory}"
    return None


def client_socket_candidates(env: dict[str, str] | None = None) -> list[Path]:
    """Where a client looks, in order: $LEVELER_SOCKET, the service's, then a user daemon's."""
    env = dict(os.environ) if env is None else env
    out = [Path(env["LEVELER_SOCKET"])] if env.get("LEVELER_SOCKET") else []
    out.append(Path("/run/leveler/control.sock"))
    own = default_socket_path(env)
    if own not in out:
        out.append(own)
    return out


def parse_request(line: bytes) -> dict[str, Any]:
    """Decode and check one request line; raises ProtocolError naming the problem."""
    if len(line) > MAX_LINE_BYTES:
        raise ProtocolError(f"request longer than {MAX_LINE_BYTES} bytes")
    if not line.strip():
        raise ProtocolError('empty request: send one JSON object per line, e.g. '
                            '{"v": 1, "verb": "status"}')
    try:
        req = orjson.loads(line)  # strict JSON: NaN and Infinity are syntax errors here
    except orjson.JSONDecodeError as exc:
        raise ProtocolError(f"not valid JSON: {exc}") from None
    if not isinstance(req, dict):
        raise ProtocolError("request must be a JSON object")
    _refuse_duplicate_keys(line)
    version = req.get("v", VERSION)
    if type(version) is not int or version != VERSION:  # not 1.0, not true
        raise ProtocolError(f"protocol version {version!r} not supported (this daemon speaks "
                            f"{VERSION})")
    verb = req.get("verb")
    if verb not in VERBS:
        raise ProtocolError(f"unknown verb {verb!r}; verbs: {', '.join(VERBS)}")
    if verb in NO_ARGS:  # `{"verb": "stop", "force": 1}` must not stop the loop
        extra = sorted(set(req) - {"v", "verb"})
        if extra:
            raise ProtocolError(f"{verb}: unknown key {extra[0]!r}; {verb} takes no arguments")
    elif verb == "watch":
        _check_watch(req)
    return req


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            raise ProtocolError(f"key {key!r} given twice; which one was meant is not guessed")
        seen.add(key)
    return dict(pairs)


def _refuse_duplicate_keys(line: bytes) -> None:
    """orjson (like most parsers) keeps the last of repeated keys, so `{"verb": "stop",
    "verb": "start"}` would start the loop: a line orjson accepted is read once more, with
    a hook that sees every key."""
    try:
        json.loads(line, object_pairs_hook=_no_duplicates)
    except ProtocolError:
        raise
    except RecursionError:  # within orjson's depth limit but past Python's
        raise ProtocolError("not valid JSON: nested too deeply") from None
    except ValueError as exc:  # orjson accepted it, so this should not happen; refuse
        raise ProtocolError(f"not valid JSON: {exc}") from None


def _check_watch(req: dict[str, Any]) -> None:
    """A watch request's rate_hz (default 10), checked before the stream is promised."""
    extra = sorted(set(req) - {"v", "verb", "rate_hz"})
    if extra:
        raise ProtocolError(f"watch: unknown key {extra[0]!r}; keys: rate_hz")
    rate = req.get("rate_hz", 10.0)
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not (
            0 < rate <= MAX_WATCH_HZ):
        raise ProtocolError(f"watch: rate_hz must be a number in (0, {MAX_WATCH_HZ:g}], "
                            f"got {rate!r}")


def _list_args(req: dict[str, Any]) -> dict[str, Any]:
    """The resonant terms' and the feedforward's settings of a tune request, type-checked
    (their consistency is the controller config's to check)."""
    out: dict[str, Any] = {}
    for key in (*PERIODIC_KEYS, *FEEDFORWARD_KEYS):
        if key not in req:
            continue
        value = req[key]
        if key in _LIST_KEYS:
            if not isinstance(value, list) or len(value) > MAX_HARMONICS or not all(
                    not isinstance(v, bool) and isinstance(v, int | float)
                    and math.isfinite(v) for v in value):
                raise ProtocolError(f"tune: {key} must be a list of at most {MAX_HARMONICS} "
                                    f"finite numbers, got {value!r}")
            out[key] = tuple(float(v) for v in value)
        else:
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and value >= 0):
                raise ProtocolError(f"tune: {key} must be a finite number >= 0, got {value!r}")
            out[key] = float(value)
    return out


def tune_args(req: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """The settings of a tune request, type- and sign-checked, and its persist flag."""
    keys = (*TUNE_KEYS, *PERIODIC_KEYS, *FEEDFORWARD_KEYS)
    extra = sorted(set(req) - set(keys) - {"v", "verb", "persist", "force"})
    if extra:
        raise ProtocolError(f"tune: unknown key {extra[0]!r}; keys: {', '.join(keys)}")
    values: dict[str, Any] = _list_args(req)
    for key, lower in TUNE_KEYS.items():
        if key not in req:
            continue
        value = req[key]
        if key in TUNE_INF_OK and value == "inf":
            value = math.inf
        if value is None:  # what a client's NaN or infinity becomes in JSON
            raise ProtocolError(f"tune: {key} must be a finite number, got null (NaN or "
                                "infinity in the client; JSON has neither)")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ProtocolError(f"tune: {key} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value) and not (key in TUNE_INF_OK and value == math.inf):
            raise ProtocolError(f"tune: {key} must be finite, got {value!r}"
                                + (' (or "inf" for no limit)' if key in TUNE_INF_OK else ""))
        if lower is not None and value < lower:
            raise ProtocolError(f"tune: {key} must be >= {lower}, got {value!r}")
        values[key] = value
    if "slew_v_per_s" in values and values["slew_v_per_s"] <= 0:
        raise ProtocolError(f"tune: slew_v_per_s must be > 0, got {values['slew_v_per_s']!r}")
    # the config file's own bounds, so a persisted value is one the daemon can load again
    for key, ok, bound in (("notch_q", lambda v: v > 0, "> 0"),
                           ("notch_depth", lambda v: v < 1, "in [0, 1)"),
                           ("periodic_radius", lambda v: 0 < v <= 1, "in (0, 1]")):
        if key in values and not ok(values[key]):
            raise ProtocolError(f"tune: {key} must be {bound}, got {values[key]!r}")
    if abs(values.get("setpoint_m", 0.0)) > SETPOINT_BOUND_M:
        raise ProtocolError(
            f"tune: setpoint_m {values['setpoint_m']:g} m is not a plausible sensor reading: "
            f"it must lie within +-{SETPOINT_BOUND_M:g} m (the sensor reads micrometres; "
            "units are SI, so 1 um is 1e-6)")
    persist = bool_arg(req, "tune", "persist")
    bool_arg(req, "tune", "force")
    if not values:
        raise ProtocolError(f"tune: nothing to change; keys: {', '.join(keys)}")
    return values, persist


def bool_arg(req: dict[str, Any], verb: str, key: str) -> bool:
    """An optional true/false argument (false if absent); 1, "yes" or null are refused."""
    value = req.get(key, False)
    if not isinstance(value, bool):
        raise ProtocolError(f"{verb}: {key} must be true or false, got {value!r}")
    return value


def reload_args(req: dict[str, Any]) -> tuple[bool, bool]:
    """accept_dropped (keys the running file set may go back to their defaults) and force
    (apply gains the plant model predicts unstable) of a reload request."""
    extra = sorted(set(req) - {"v", "verb", "accept_dropped", "force"})
    if extra:
        raise ProtocolError(f"reload: unknown key {extra[0]!r}; keys: accept_dropped, force")
    return bool_arg(req, "reload", "accept_dropped"), bool_arg(req, "reload", "force")


def modulate_args(req: dict[str, Any]) -> tuple[float, float, int, str, bool]:
    """amplitude_v, period_s, cycles, shape and force of a modulate request, type-checked."""
    extra = sorted(set(req) - {"v", "verb", "amplitude_v", "period_s", "cycles", "shape",
                               "force"})
    if extra:
        raise ProtocolError(f"modulate: unknown key {extra[0]!r}; keys: amplitude_v, "
                            "period_s, cycles, shape, force")
    out: list[float] = []
    for key in ("amplitude_v", "period_s"):
        value = req.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float) or not (
                math.isfinite(value) and value > 0):
            raise ProtocolError(f"modulate: {key} must be a number > 0, got {value!r}")
        out.append(float(value))
    cycles = req.get("cycles", 1)
    if isinstance(cycles, bool) or not isinstance(cycles, int) or not 1 <= cycles <= 10_000:
        raise ProtocolError(f"modulate: cycles must be an integer in 1..10000, got {cycles!r}")
    shape = req.get("shape", "square")
    if shape not in SHAPES:
        raise ProtocolError(f"modulate: shape must be one of {', '.join(SHAPES)}, "
                            f"got {shape!r}")
    return out[0], out[1], cycles, shape, bool_arg(req, "modulate", "force")


def encode(obj: dict[str, Any]) -> bytes:
    """One response line; non-finite floats become null rather than invalid JSON."""
    return orjson.dumps({"v": VERSION, **obj}, option=orjson.OPT_SERIALIZE_NUMPY) + b"\n"
