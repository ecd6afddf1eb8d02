"""Write tuned values back into the config file: atomically, keeping the lab's own form.

A lab config is a document people annotate and write in whatever TOML form they like
(tables, dotted keys, inline tables), so values are set through tomlkit, which keeps
comments, key order and each table's form; the result is validated as a whole before it
replaces the old file (write to a temporary file, fsync, rename, fsync the directory).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import tomlkit
from tomlkit.exceptions import TOMLKitError

from leveler.typed_config import ConfigError


def _parse(text: str) -> tomlkit.TOMLDocument:
    try:
        return tomlkit.parse(text)
    except TOMLKitError as exc:
        raise ConfigError(f"the config is not valid TOML: {exc}") from None


def set_keys(text: str, section: str, values: dict[str, float | tuple[float, ...]]) -> str:
    """`text` with the keys of `section` (dotted for nested tables, e.g. "plant.pendulum")
    set to `values`: replaced where they are, added to the section if absent, the section
    added at the end if the file has none."""
    doc = _parse(text)
    table: tomlkit.TOMLDocument | tomlkit.items.Table = doc
    parts = section.split(".")
    for depth, part in enumerate(parts):
        if part not in table:
            # a parent only named on its way to the child gets no header of its own
            table[part] = tomlkit.table(is_super_table=depth < len(parts) - 1)
        table = table[part]
    for key, value in values.items():
        table[key] = [float(v) for v in value] if isinstance(value, tuple | list) else float(value)
    return tomlkit.dumps(doc)


def without_table(text: str, section: str) -> str:
    """`text` without the (dotted) table `section` and everything under it, in any form."""
    doc = _parse(text)
    *parents, last = section.split(".")
    table: tomlkit.TOMLDocument | tomlkit.items.Table = doc
    for part in parents:
        if part not in table:
            return text
        table = table[part]
    if last in table:
        del table[last]
    return tomlkit.dumps(doc)


def write_atomic(path: Path, text: str, validate: Callable[[Path], object],
                 mode: int | None = None) -> None:
    """Replace `path` by `text` only if `validate(tmpfile)` accepts it; never half-written.

    The new file gets `mode` if given, else the mode of the file it replaces (else 0600)."""
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        validate(tmp)
        if mode is not None:
            os.chmod(tmp, mode)
        elif path.exists():
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    finally:
        tmp.unlink(missing_ok=True)
