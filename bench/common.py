"""What every bench section shares: the row format of `make bench`'s table and results.json.

A section is a module beside this one with `run(quick: bool) -> list[dict]`; each dict is
one `row(...)`. `ratio` is leveler's figure relative to the row's baseline, measured in the
same run, expressed the way its goal is (">= 0.5x" or "<= 1.0x"); `met` is None when the
row has no goal or the run cannot judge it (quick mode).
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def row(section: str, what: str, value: float, unit: str, *, baseline: str = "",
        ratio: float | None = None, goal: str = "", met: bool | None = None,
        note: str = "") -> dict[str, Any]:
    return {"section": section, "what": what, "value": float(value), "unit": unit,
            "baseline": baseline, "ratio": None if ratio is None else float(ratio),
            "goal": goal, "met": met, "note": note}


def at_least(ratio: float, goal: float) -> bool:
    return bool(ratio >= goal)


def at_most(ratio: float, goal: float) -> bool:
    return bool(ratio <= goal)


def best_of(repeats: int, fn: Callable[[], float]) -> float:
    """The shortest of `repeats` timings: on a shared machine the others measure the load."""
    return min(fn() for _ in range(repeats))


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def bench_tmpdir() -> tempfile.TemporaryDirectory[str]:
    """Scratch space for the logs a section writes; $LEVELER_BENCH_TMP chooses the disk
    (the logging figures include the writes and the fsync, so a tmpfs /tmp flatters them)."""
    base = os.environ.get("LEVELER_BENCH_TMP") or None
    return tempfile.TemporaryDirectory(prefix="leveler-bench-", dir=base)


def seeds(text: str) -> list[int]:
    """A --seeds list: "301-310", "1,4,9" or both, "1-3,7"."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out
