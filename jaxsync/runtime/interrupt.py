"""Ctrl-C that stops a long run at its next safe point, wherever it lands.

Python's own SIGINT handler raises KeyboardInterrupt in whatever code runs
when the signal arrives. Some code swallows it: a garbage-collection
callback (JAX frees device buffers from one), a ``__del__`` or a weakref
callback print "Exception ignored in ..." and the run goes on as if nothing
had been asked. Inside :func:`deferred` the first Ctrl-C only records the
request; the run's loop calls :func:`check` at its safe points (between
iterations, tuning runs, chunks: where its checkpoint is whole) and stops
there with KeyboardInterrupt. A second Ctrl-C raises at once, where it
lands; the request stays recorded, so even a swallowed second one stops the
run at its next check. A request that comes after the last check stops the
run when :func:`deferred` ends. The previous handler is restored on leaving.

The handler is installed only from the main thread and only over Python's
default handler (a caller's own SIGINT handler is left in place); nested
``deferred`` blocks share the outermost one's.

Example:
  >>> with deferred():
  ...     for i in range(n):
  ...         step(i)
  ...         save_checkpoint(i)
  ...         check()  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

FIRST_MESSAGE = b"\ninterrupt: stopping at the next safe point, with its checkpoint (Ctrl-C again to stop at once)\n"

_requests = 0  # Ctrl-Cs recorded since the outermost deferred() began
_depth = 0  # nesting of deferred() blocks; the handler belongs to the outermost


def _handler(signum, frame) -> None:
    global _requests
    _requests += 1
    if _requests > 1:
        raise KeyboardInterrupt
    # os.write, not print: the signal may land inside a print to the same stream
    with contextlib.suppress(OSError):
        os.write(2, FIRST_MESSAGE)


def requested() -> bool:
    """Whether a Ctrl-C was recorded inside the current :func:`deferred` block."""
    return _requests > 0


def check() -> None:
    """A safe point: KeyboardInterrupt when a Ctrl-C was recorded."""
    if _requests:
        raise KeyboardInterrupt


@contextlib.contextmanager
def deferred():
    """Within: Ctrl-C is recorded and raised at the next :func:`check` (see the module)."""
    global _depth, _requests
    if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
        yield
        return
    outermost = _depth == 0
    install = outermost and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    previous = signal.signal(signal.SIGINT, _handler) if install else None
    if outermost:
        _requests = 0
    _depth += 1
    try:
        yield
        if outermost:
            check()  # a request after the last safe point
    finally:
        _depth -= 1
        if outermost:
            if install:
                signal.signal(signal.SIGINT, previous)
            _requests = 0
