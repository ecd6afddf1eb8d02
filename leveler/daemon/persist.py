"""Write tuned values back into the config file: atomically, keeping the lab's comments.

A lab config is a document people annotate, so values are replaced in place in the text
of their section rather than re-serialized; the result is validated as a whole before it
replaces the old file (write to a temporary file, fsync, rename, fsync the directory).
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path

_HEADER = re.compile(r"^\s*\[([^\[\]]+)\]\s*(#.*)?$")


def _fmt(value: float) -> str:
    return repr(float(value)) if value == value and abs(value) != float("inf") else "inf"


def set_keys(text: str, section: str, values: dict[str, float]) -> str:
    """`text` with `section`'s keys set to `values` (added at the section's end if absent)."""
    lines = text.splitlines(keepends=True)
    start = end = None
    for i, line in enumerate(lines):
        m = _HEADER.match(line)
        if m and start is None and m.group(1).strip() == section:
            start = i
        elif m and start is not None:
            end = i
            break
    if start is None:
        body = "".join(f"{k} = {_fmt(v)}\n" for k, v in values.items())
        sep = "" if not text or text.endswith("\n") else "\n"
        return f"{text}{sep}\n[{section}]\n{body}"
    end = len(lines) if end is None else end
    pending = dict(values)
    last_key = start
    for i in range(start + 1, end):
        m = re.match(r"^(\s*)([A-Za-z0-9_]+)(\s*=\s*)([^#\n]*?)(\s*#.*)?(\r?\n)?$", lines[i])
        if not m:
            continue
        last_key = i
        key = m.group(2)
        if key in pending:
            lines[i] = (f"{m.group(1)}{key}{m.group(3)}{_fmt(pending.pop(key))}"
                        f"{m.group(5) or ''}{m.group(6) or ''}")
    if pending:
        if not lines[last_key].endswith("\n"):
            lines[last_key] += "\n"
        lines[last_key + 1:last_key + 1] = [f"{k} = {_fmt(v)}\n" for k, v in pending.items()]
    return "".join(lines)


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
