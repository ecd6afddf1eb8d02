"""numba's compiled form of a plain function, when numba is installed (the `fast` extra).

One place decides how: once a process per function (kept here, so callers ask at every
call), cached on disk after the first compile (a second process loads it in ~0.3 s),
compiled afresh in each process where no cache directory is writable. A caller keeps a
numpy or interpreted path for when this gives None: numba is optional, and the real-time
daemon never imports it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any


@functools.cache
def compiled(fn: Callable[..., Any], *helpers: Callable[..., Any]
             ) -> Callable[..., Any] | None:
    """`fn` compiled by numba's njit, or None when numba is not installed. `helpers`: the
    plain functions of its module that `fn` calls, made callable from compiled code (each
    once a process; they stay plain for interpreted callers)."""
    try:
        import numba
    except ImportError:
        return None
    for helper in helpers:
        _jitable(helper)
    try:
        return numba.njit(cache=True, nogil=True)(fn)  # type: ignore[no-any-return]
    except RuntimeError:  # no writable cache directory
        return numba.njit(nogil=True)(fn)  # type: ignore[no-any-return]


@functools.cache
def _jitable(fn: Callable[..., Any]) -> None:
    from numba.extending import register_jitable

    register_jitable(fn)
