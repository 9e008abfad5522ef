"""Atomic result files: write a temporary file beside the target, then rename.

An interrupted run never leaves a half-written result.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import socket
import tempfile
import time

import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.runtime.files import atomic_path, atomic_write_bytes  # noqa: F401  (part of this module's API)

# The outermost folder each ensure_writable_dir call created, so that a run
# that then fails can remove what it created and left empty
# (remove_created_dirs; jaxsync.cli.main does): a rejected run leaves no empty
# output folder behind.
_created: list[str] = []


def ensure_writable_dir(path: str) -> str:
    """Create ``path`` if needed and check that files can be written there."""
    try:
        top = None
        probe = os.path.abspath(path)
        while not os.path.lexists(probe):
            top, probe = probe, os.path.dirname(probe)
        try:
            os.makedirs(path, exist_ok=True)
        finally:
            if top is not None and os.path.isdir(top):
                _created.append(top)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".jaxsync-probe-"):
            pass
    except OSError as err:
        raise ConfigError(f"output folder {path!r} cannot be written: {err.strerror or err}") from None
    return path


LOCK = ".jaxsync.lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


@contextlib.contextmanager
def run_lock(out: str, what: str = "run", log=None):
    """Hold ``out`` for one run: a lock file (``.jaxsync.lock``: the process,
    its host and when it started) made with ``O_EXCL``, so a second run started
    into the same folder at the same time is refused instead of overwriting
    the first. Removed when the run ends, however it ends; a lock left by a
    killed run on this host (its process is gone) is named and taken over."""
    path = os.path.join(out, LOCK)
    me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S"), "what": what}
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                with open(path) as f:
                    held = json.load(f)
            except (OSError, ValueError):
                held = {}
            pid, host = held.get("pid"), held.get("host")
            if isinstance(pid, int) and host == me["host"] and not _alive(pid):
                if log is not None:
                    log(
                        f"{path}: a lock left by a run that was killed ({held.get('what', 'run')}, "
                        f"process {pid}, started {held.get('started')}); taking the folder over"
                    )
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(path)
                continue
            raise ConfigError(
                f"output folder {out!r} is in use by another jaxsync {held.get('what', 'run')} (process {pid} on "
                f"{host}, started {held.get('started')}): wait for it to end, or choose another --out "
                f"(if that process is gone, remove {path})"
            ) from None
        with os.fdopen(fd, "w") as f:
            json.dump(me, f)
        break
    else:
        raise ConfigError(f"output folder {out!r}: cannot take its lock {path}")
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            with open(path) as f:
                ours = json.load(f).get("pid") == me["pid"]
            if ours:
                os.unlink(path)


def forget_created_dirs() -> None:
    """Start a new run's record of created folders."""
    _created.clear()


def remove_created_dirs() -> list[str]:
    """Remove the empty folders ensure_writable_dir created since
    forget_created_dirs (and empty folders inside them); a folder holding a
    file is kept. Returns the folders removed."""
    removed = []
    while _created:
        top = _created.pop()
        for root, _, _ in os.walk(top, topdown=False):
            with contextlib.suppress(OSError):
                os.rmdir(root)
                removed.append(root)
    return removed


def atomic_write_text(path: str, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: str, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(x):

    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def write_csv(path: str, columns: dict[str, list]) -> None:
    """Columns of equal length -> CSV with a header row."""
    names = list(columns)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(names)
    for row in zip(*(columns[n] for n in names), strict=True):
        w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
    atomic_write_text(path, buf.getvalue())


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed)."""
    # imported on first use: the backend must be chosen before pyplot loads,
    # and only the commands that plot pay for matplotlib's import
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after the backend is chosen

    return plt


def save_figure(fig, path: str, dpi: int = 120) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
