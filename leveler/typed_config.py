"""Typed configuration from TOML: every value checked, every error names file and key.

Sections are frozen dataclasses; `build` walks their fields, so a new setting is a new
field with a default and (optionally) a bound in its metadata, nothing more. Unknown keys
are errors, not ignored: a typo in a lab config must not silently fall back to a default.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


def positive(default: float, **extra: Any) -> Any:
    """A float field that must be > 0."""
    return dataclasses.field(default=default, metadata={"gt": 0.0, **extra})


def non_negative(default: float, **extra: Any) -> Any:
    """A float field that must be >= 0."""
    return dataclasses.field(default=default, metadata={"ge": 0.0, **extra})


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is Literal:
        return " or ".join(repr(a) for a in typing.get_args(tp))
    return {float: "a number", int: "an integer", bool: "true or false", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp))
    )


def _bounded(value: float, key: str, meta: typing.Mapping[str, Any]) -> Any:
    """`value` if it satisfies the field's gt/ge/le bounds, else a ConfigError naming key."""
    if "gt" in meta and not value > meta["gt"]:
        raise ConfigError(f"{key}: must be > {meta['gt']}, got {value!r}")
    if "ge" in meta and not value >= meta["ge"]:
        raise ConfigError(f"{key}: must be >= {meta['ge']}, got {value!r}")
    if "le" in meta and not value <= meta["le"]:
        raise ConfigError(f"{key}: must be <= {meta['le']}, got {value!r}")
    return value


def _convert(tp: Any, value: Any, key: str, meta: typing.Mapping[str, Any]) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(args[0], value, key, meta)
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r}")
        return value
    if origin is tuple:  # tuple[X, ...]: a TOML array, e.g. of tables ([[sim.faults]])
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected an array, got {value!r}")
        (item,) = typing.get_args(tp)[:1]
        return tuple(_convert(item, v, f"{key}[{i}]", meta) for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table [{key}], got {value!r}")
        return build(tp, value, key)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            value = float(value)
        except OverflowError:  # TOML integers are unbounded in tomllib
            raise ConfigError(f"{key}: must be finite, got an integer beyond 1.8e308") from None
        if not math.isfinite(value) and not meta.get("allow_inf", False):
            raise ConfigError(f"{key}: must be finite, got {value!r}")
        return _bounded(value, key, meta)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return _bounded(value, key, meta)
    if tp in (bool, str):
        if not isinstance(value, tp):
            raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r}")
        return value
    raise TypeError(f"{key}: unsupported config field type {tp!r}")


def build(cls: type[T], table: dict[str, Any], where: str = "") -> T:
    """Make a `cls` from a TOML table; `where` is the dotted key path used in errors."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    prefix = f"{where}." if where else ""
    unknown = sorted(set(table) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields))
        raise ConfigError(f"{prefix}{unknown[0]}: unknown key (known here: {known})")
    values: dict[str, Any] = {}
    for name, f in fields.items():
        key = prefix + name
        if name in table:
            values[name] = _convert(hints[name], table[name], key, f.metadata)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{key}: missing (required)")
    try:
        return cls(**values)
    except ConfigError as exc:
        raise ConfigError(f"{prefix}{exc}") from None
    except ValueError as exc:  # a check across fields; at the top its message names the keys
        raise ConfigError(f"{where}: {exc}" if where else str(exc)) from None


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; syntax errors name the file and line."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        # a relative default (`leveler sim`'s config/sim.toml) read outside a checkout: say
        # where it was looked for and how to name another
        where = "" if path.is_absolute() else f" in {Path.cwd()}; name one with --config FILE"
        raise ConfigError(f"{path}: no such config file{where}") from None
    except OSError as exc:  # a directory, no permission: refuse to start, do not guess
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:  # tomllib decodes before parsing: not a TOMLDecodeError
        raise ConfigError(f"{path}: invalid TOML: not UTF-8 text (byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def load(cls: type[T], path: str | Path, section: str | None = None) -> T:
    """Load and validate `cls` from a TOML file (optionally one section of it)."""
    data = load_toml(path)
    if section is not None:
        data = data.get(section, {})
    try:
        return build(cls, data, section or "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
