"""One registry of the memos that hold jaxsync's traced and compiled programs.

A rollout, a sweep's chunk function or a sensitivity program is built once per
configuration and kept (``functools.lru_cache`` under :func:`memoize`), so a
second call neither traces nor compiles again. :func:`clear` drops them all,
for a long-lived process that has moved on (the test suite calls it between
modules to bound its memory); programs needed again come back from the
persistent compilation cache.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

from jaxsync.runtime import patches

_MEMOS: list = []
_CLEARERS: list[Callable[[], None]] = []


def memoize(maxsize: int):
    """``functools.lru_cache(maxsize)``, registered so that :func:`clear` empties it."""

    def wrap(fn):
        cached = functools.lru_cache(maxsize=maxsize)(fn)
        _MEMOS.append(cached)
        return cached

    return wrap


def on_clear(fn: Callable[[], None]) -> Callable[[], None]:
    """Register ``fn`` (a memo that is not an lru_cache) to run on :func:`clear`."""
    _CLEARERS.append(fn)
    return fn


def clear(executables: bool = True) -> None:
    """Drop every memoised program; with ``executables`` also JAX's compiled
    executables (its traces stay: the physics is not traced again)."""
    for memo in _MEMOS:
        memo.cache_clear()
    for fn in _CLEARERS:
        fn()
    if executables:
        patches.clear_compiled_executables()
