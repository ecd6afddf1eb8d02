"""Config fuzzing: every bad file is refused with an error naming the file and the key.

The shipped configs are mutated (wrong types, numbers as strings, NaN and inf, negative,
zero, huge and tiny values, keys missing or unknown at every level, units changed in key
names, min and max swapped, tables replaced by values) and written back as TOML. Each case
must either load or raise ConfigError whose one-line message starts with the file and then
the dotted key of what was changed (a check across several fields may name their table);
any other exception is a bug. `leveler run` on such a file must exit 2 with that line and
no traceback, before it creates a log or a socket: the daemon refuses rather than guesses.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
import tomllib
import typing
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from leveler.settings import Config, load_config
from leveler.typed_config import ConfigError

REPO = Path(__file__).resolve().parents[1]
BASES = ("sim.toml", "lab-modbus.toml")
FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


# ---- TOML out (the stdlib only reads it) ------------------------------------------------
def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else {math.inf: "inf", -math.inf: "-inf"}.get(v, repr(v))
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a TOML basic string for these characters
    if isinstance(v, datetime):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(data: dict[str, Any]) -> str:
    return "".join(f"{k} = {toml_value(v)}\n" for k, v in data.items())


# ---- the key space ----------------------------------------------------------------------
def schema_paths(cls: type, prefix: str = "") -> tuple[list[str], list[str]]:
    """(leaf keys, table keys) of a config dataclass, optional tables included."""
    leaves, tables = [], []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        key = prefix + f.name
        sub = [t for t in (hints[f.name], *typing.get_args(hints[f.name]))
               if dataclasses.is_dataclass(t)]
        if sub:
            tables.append(key)
            more_leaves, more_tables = schema_paths(sub[0], key + ".")
            leaves += more_leaves
            tables += more_tables
        else:
            leaves.append(key)
    return leaves, tables


def file_paths(data: dict[str, Any], prefix: str = "") -> tuple[list[str], list[str]]:
    leaves, tables = [], []
    for k, v in data.items():
        if isinstance(v, dict):
            tables.append(prefix + k)
            more_leaves, more_tables = file_paths(v, f"{prefix}{k}.")
            leaves += more_leaves
            tables += more_tables
        else:
            leaves.append(prefix + k)
    return leaves, tables


SCHEMA_LEAVES, SCHEMA_TABLES = schema_paths(Config)
BASE_DATA = {name: tomllib.loads((REPO / "config" / name).read_text()) for name in BASES}
UNITS = {"_hz": "_khz", "_s": "_ms", "_m": "_mm", "_v": "_mv", "_kg": "_g", "_rad": "_deg",
         "_k": "_c", "_bytes": "_mb"}


def get(data: dict[str, Any], path: str) -> Any:
    for part in path.split("."):
        data = data[part]
    return data


def set_path(data: dict[str, Any], path: str, value: Any) -> list[str]:
    """Set data[path] = value, making missing or non-table parents tables; returns the
    paths changed (a table made here counts: its required keys are now missing)."""
    parts = path.split(".")
    changed = [path]
    for i, part in enumerate(parts[:-1]):
        if not isinstance(data.get(part), dict):
            data[part] = {}
            changed.append(".".join(parts[: i + 1]))
        data = data[part]
    data[parts[-1]] = value
    return changed


def delete(data: dict[str, Any], path: str) -> list[str]:
    *parents, last = path.split(".")
    for part in parents:
        data = data[part]
    del data[last]
    return [path]


# ---- mutations --------------------------------------------------------------------------
KEY = st.from_regex(r"\A[a-z][a-z0-9_]{0,14}\Z")
TEXT = st.text(st.characters(blacklist_categories=("Cc", "Cs")), max_size=12)
BAD_NUMBERS = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, -1e-9, 1e308,
                               -1e308, 1e-300, 0, -1, 10**30, 10**400, -(10**400), 2**63])
BAD_VALUES = st.one_of(
    BAD_NUMBERS,
    st.floats(),
    st.integers(),
    st.booleans(),
    TEXT,
    st.sampled_from(["10.0", "1e-3", "10 Hz", "", "nan", "inf", "true", "-5"]),
    st.lists(st.integers(), max_size=3),
    st.dictionaries(KEY, st.integers(), max_size=2),
    st.just(datetime(1979, 5, 27, 7, 32)),
)


@st.composite
def mutation(draw: st.DrawFn, data: dict[str, Any]) -> list[str]:
    """Apply one mutation to `data` in place; returns the dotted paths it touched."""
    leaves, tables = file_paths(data)
    kind = draw(st.sampled_from(["value", "value", "number", "missing", "unknown", "units",
                                 "swap", "table", "fault"]))
    if kind == "missing" and leaves + tables:
        return delete(data, draw(st.sampled_from(leaves + tables)))
    if kind == "unknown":
        table = draw(st.sampled_from(["", *sorted(set(tables + SCHEMA_TABLES))]))
        name = draw(KEY)
        known = {p.rsplit(".", 1)[-1] for p in SCHEMA_LEAVES + SCHEMA_TABLES
                 if p.startswith(table + ".") or (not table and "." not in p)}
        if name in known:
            name += "_x"  # an unknown key in this table
            if name in known:
                return []
        return set_path(data, f"{table}.{name}" if table else name, 1.0)
    if kind == "units":
        with_units = [p for p in leaves if any(p.endswith(u) for u in UNITS)]
        if with_units:
            path = draw(st.sampled_from(with_units))
            unit = next(u for u in sorted(UNITS, key=len, reverse=True) if path.endswith(u))
            value = get(data, path)
            delete(data, path)
            return [path, *set_path(data, path[: -len(unit)] + UNITS[unit], value)]
    if kind == "swap":
        pairs = [(p, p.replace("min", "max")) for p in leaves
                 if "min" in p.rsplit(".", 1)[-1] and p.replace("min", "max") in leaves]
        if pairs:
            lo, hi = draw(st.sampled_from(pairs))
            a, b = get(data, lo), get(data, hi)
            set_path(data, lo, b)
            set_path(data, hi, a)
            return [lo, hi]
    numbers = [p for p in leaves if type(get(data, p)) in (int, float)]
    if kind == "number" and numbers:  # NaN, inf, zero, negative, huge or tiny in place
        return set_path(data, draw(st.sampled_from(numbers)), draw(BAD_NUMBERS))
    if kind == "fault":  # an array of tables: [[sim.faults]], one entry spoiled
        faults = [{"kind": "nan", "at_s": 5.0, "duration_s": 1.0},
                  {"kind": "spike", "at_s": 1.0, "size": 1e-6}]
        i = draw(st.integers(0, 1))
        key = draw(st.sampled_from(["kind", "at_s", "duration_s", "size", "at_ms"]))
        if draw(st.booleans()):
            faults[i][key] = draw(BAD_VALUES)
        else:
            faults[i].pop(key, None)  # kind is required
        return [*set_path(data, "sim.faults", faults)[1:], f"sim.faults[{i}].{key}"]
    if kind == "table" and tables:
        return set_path(data, draw(st.sampled_from(tables)), draw(BAD_VALUES))
    path = draw(st.sampled_from(sorted(set(leaves + SCHEMA_LEAVES))))
    return set_path(data, path, draw(BAD_VALUES))


def named_keys(message: str, path: Path) -> list[str]:
    """The dotted keys an error names: what comes between the file and the next ': '."""
    assert message.startswith(f"{path}: "), message
    head = message[len(f"{path}: "):].split(": ", 1)[0]
    return re.findall(r"[A-Za-z_]\w*(?:\.\w+|\[\d+\])*", head)


def related(named: str, changed: str) -> bool:
    """The key itself, a table holding it (checks across fields), or a key inside it
    (a table deleted, replaced or made incomplete)."""
    return named == changed or changed.startswith((named + ".", named + "[")) or (
        named.startswith((changed + ".", changed + "[")))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzzcfg")


@pytest.mark.parametrize("base", BASES)
def test_the_shipped_configs_load(base: str) -> None:
    load_config(REPO / "config" / base)


@FUZZ
@given(base=st.sampled_from(BASES), data=st.data())
def test_mutated_configs_load_or_name_file_and_key(workdir: Path, base: str,
                                                   data: st.DataObject) -> None:
    cfg = json.loads(json.dumps(BASE_DATA[base]))  # a deep copy (the shipped files are plain)
    changed: list[str] = []
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        changed += data.draw(mutation(cfg), label="mutation")
    path = workdir / f"mutated-{base}"
    path.write_text(to_toml(cfg))
    try:
        load_config(path)
    except ConfigError as exc:
        message = str(exc)
        assert "\n" not in message
        named = named_keys(message, path)
        assert any(related(n, c) for n in named for c in changed), (message, changed)
        what = message[len(f"{path}: "):].split(": ", 1)[-1]
        event(re.sub(r"\(known here.*|, got .*|-?\d[\d.e+-]*", "", what)[:50])
    else:
        event("loaded")


@FUZZ
@given(base=st.sampled_from(BASES), cut=st.integers(0, 10**6), junk=st.binary(max_size=8),
       at=st.integers(0, 10**6))
def test_damaged_toml_is_named_by_file_and_line(workdir: Path, base: str, cut: int,
                                                junk: bytes, at: int) -> None:
    """A file cut short and with a few stray bytes in it: TOML syntax (or UTF-8) errors
    name the file and where; what still parses must name a key when refused."""
    raw = (REPO / "config" / base).read_bytes()
    raw = raw[: cut % (len(raw) + 1)]
    at %= len(raw) + 1
    path = workdir / f"damaged-{base}"
    path.write_bytes(raw[:at] + junk + raw[at:])
    try:
        load_config(path)
    except ConfigError as exc:
        message = str(exc)
        assert message.startswith(f"{path}: ") and "\n" not in message, message
        if "invalid TOML" in message:
            assert re.search(r"at line \d+|at end of document|not UTF-8", message), message
        else:
            assert named_keys(message, path), message


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"", "is empty: no tables or keys"),
        (b"# only a comment\n\n   \n", "is empty: no tables or keys"),
        (b"[loop]\n", None),
        (b'[actuator]\nsafe_v = 200.0\n', "actuator.safe_v: 200.0 V is outside the simulated "
                                          "piezo's range"),
        (b"\x00\x01\x02", "invalid TOML"),
        (b"[loop]\nrate_hz = 10.0  # \xff\xfe\n", "invalid TOML: not UTF-8"),
        (b"[loop]\nrate_hz = 1" + b"0" * 400 + b"\n", "loop.rate_hz: must be finite"),
        (b"[loop]\nrate_hz = 10.0\n[loop]\nrate_hz = 20.0\n", "invalid TOML"),
        (b"[[loop]]\nrate_hz = 10.0\n", "loop: expected a table"),
        (b"[control]\nmax_clients = 0\n", "control.max_clients: must be >= 1"),
        (b"[control]\nidle_timeout_s = -1\n", "control.idle_timeout_s: must be > 0"),
        (b"[log]\nrotate_bytes = -1\n", "log.rotate_bytes: must be >= 65536"),
        (b"[controller]\noutput_min_v = 150.0\noutput_max_v = 0.0\n",
         "controller: output_min_v (150.0) must be below output_max_v"),
        (b'[sensor]\nbackend = "modbus"\n[actuator]\nbackend = "modbus"\n',
         'sensor: backend = "modbus" needs a [sensor.modbus] table'),
        (b'[sensor]\nbackend = "sim"\n[actuator]\nbackend = "modbus"\n[actuator.modbus]\n',
         "sensor.backend and actuator.backend: "),
    ],
)
def test_edge_files(tmp_path: Path, content: bytes, needle: str | None) -> None:
    path = tmp_path / "edge.toml"
    path.write_bytes(content)
    if needle is None:
        assert load_config(path)[0] == Config()
        return
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value).startswith(f"{path}: {needle}"), str(err.value)


def test_a_directory_or_unreadable_path_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=f"^{re.escape(str(tmp_path))}: cannot read"):
        load_config(tmp_path)


DAEMON_CASES = [  # (text in config/sim.toml, its replacement, start of the error after the file)
    ("rate_hz = 10.0", 'rate_hz = "fast"', "loop.rate_hz: expected a number"),
    ("setpoint_m = 0.0", "setpoint_m = nan", "controller.setpoint_m: must be finite"),
    ("slew_v_per_s = 10.0", "slew_v_per_s = -10.0", "controller.slew_v_per_s: must be > 0"),
    ("mass_kg = 0.185", "mass_g = 185.0", "plant.pendulum.mass_g: unknown key"),
    ("[sim]\n", "[sim]\nfrobnicate = 1\n", "sim.frobnicate: unknown key"),
    ("[loop]\n", "[loop\n", "invalid TOML"),
    ("seed = 1", "seed = 1  # \udcff", "invalid TOML: not UTF-8"),
    ("safe_v = 75.0", "safe_v = 200.0", "actuator.safe_v: 200.0 V is outside the simulated "
                                        "piezo's range"),
]


def test_the_daemon_refuses_to_start_on_a_bad_config(tmp_path: Path) -> None:
    """One line on stderr naming file and key, exit 2, no traceback, no log, no socket.
    The cases run as concurrent processes: each spends its time importing, not failing."""
    base = (REPO / "config" / "sim.toml").read_text()
    runs = []
    for n, (old, new, needle) in enumerate(DAEMON_CASES):
        work = tmp_path / f"case{n}"
        work.mkdir()
        assert old in base
        sock = work / "c.sock"
        text = base.replace(old, new).replace('dir = "logs"', f'dir = "{work / "logs"}"')
        bad = work / "bad.toml"
        bad.write_bytes((text + f'\n[control]\nsocket_path = "{sock}"\n').encode(
            "utf-8", "surrogateescape"))
        proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                                 str(bad)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, cwd=work)
        runs.append((proc, work, bad, sock, needle))
    for proc, work, bad, sock, needle in runs:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 2, err
        assert err.startswith(f"leveler run: error: {bad}: {needle}"), err
        assert err.count("\n") == 1 and "Traceback" not in err
        assert out == ""
        assert not (work / "logs").exists() and not sock.exists()
