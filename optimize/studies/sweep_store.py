"""The chunk store of a sweep: finished chunks on disk, so that a run can be resumed.

Each finished chunk is written atomically to ``chunks/chunk_NNNNN.npz`` next
to ``plan.json`` (the sweep's fingerprint); a re-run of the same plan with
``--resume`` reads finished chunks back instead of recomputing them.
"""

from __future__ import annotations

import io
import json
import os
import shutil

import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results
from jaxsync.optimize.studies.sweep_plan import Plan


def _chunk_path(out: str, i: int) -> str:
    return os.path.join(out, "chunks", f"chunk_{i:05d}.npz")


def save_chunk(out: str, i: int, start: int, stop: int, metrics: dict) -> None:
    buf = io.BytesIO()
    np.savez(buf, start=start, stop=stop, **metrics)
    _results.atomic_write_bytes(_chunk_path(out, i), buf.getvalue())


def load_chunk(out: str, i: int, start: int, stop: int, fields) -> dict | None:
    path = _chunk_path(out, i)
    if not os.path.exists(path):
        return None
    try:
        with np.load(path) as z:
            if int(z["start"]) != start or int(z["stop"]) != stop:
                return None
            got = {k: z[k].copy() for k in fields}
    except Exception:  # noqa: BLE001 - an unreadable chunk is recomputed
        return None
    if any(v.shape != (stop - start,) for v in got.values()):
        return None
    return got


def prepare_out(out: str, plan: Plan, restart: bool, resume: bool = False) -> dict | None:
    """Check what ``out`` holds, then create it; return the stored plan.json when resuming.

    A folder holding a sweep (plan.json) is continued (``resume``: the same
    sweep's finished chunks are read back) or discarded (``restart``), never
    silently taken over: with neither, it is a ConfigError naming both flags,
    as ``jaxsync tune`` does with a checkpoint. Nothing is created or removed
    before these checks pass.
    """
    if resume and restart:
        raise ConfigError("--resume continues the sweep in --out and --restart discards it: give one of them")
    path = os.path.join(out, "plan.json")
    stored = None
    if os.path.exists(path):
        try:
            with open(path) as f:
                stored = json.load(f)
        except (OSError, json.JSONDecodeError):
            stored = None
    if stored is not None and not restart:
        if stored.get("fingerprint") != plan.fingerprint:
            raise ConfigError(
                f"output folder {out!r} holds a different sweep (plan.json fingerprint "
                f"{stored.get('fingerprint')}, this one {plan.fingerprint}); pass --restart to discard it "
                "or choose another --out"
            )
        if not resume:
            raise ConfigError(
                f"output folder {out!r} holds this sweep ({_progress(out, stored)}): pass --resume to continue "
                "it (finished chunks are read back), --restart to discard it and start over, or choose another --out"
            )
    if resume and stored is None:
        raise ConfigError(f"--resume: no sweep to continue in {out!r} (no readable plan.json)")
    _results.ensure_writable_dir(out)
    if restart or stored is None:  # --restart, or a fresh sweep: any stored state goes
        stored = None
        shutil.rmtree(os.path.join(out, "chunks"), ignore_errors=True)
        for f in ("results.csv", "summary.json", "heatmap.png", "line.png", "scatter.png", "plan.json"):
            if os.path.exists(os.path.join(out, f)):
                os.unlink(os.path.join(out, f))
    os.makedirs(os.path.join(out, "chunks"), exist_ok=True)
    return stored


def _progress(out: str, stored: dict) -> str:
    """'3 of 8 chunks done' or 'finished', from the chunk files on disk."""
    try:
        done = sum(1 for f in os.listdir(os.path.join(out, "chunks")) if f.endswith(".npz"))
    except OSError:
        done = 0
    n = stored.get("n_chunks")
    if n and done >= n:
        return "finished"
    return f"{done} of {n} chunks done" if n else f"{done} chunks done"


def read_plan(out: str, plan: Plan) -> dict | None:
    try:
        with open(os.path.join(out, "plan.json")) as f:
            stored = json.load(f)
    except (OSError, json.JSONDecodeError):
        return None
    return stored if stored.get("fingerprint") == plan.fingerprint else None
