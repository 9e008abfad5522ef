"""A calibration problem over part of its windows: halves, held-out windows, one joint's.

The parts share the problem's delay and replay mode
(``jaxsync.calibrate.fit.Problem``): setting either on one sets it on all.
"""

from __future__ import annotations


def split(prob, every: int, keep: bool):
    """The problem over the windows but every ``every``-th in time (``keep``), or over those (not
    ``keep``); every other where there are fewer than ``2 every`` windows; None under 2 windows."""
    n = len(prob.dominant)
    every = every if n >= 2 * every else 2
    held = set(range(every - 1, n, every))
    rows = [i for i in range(n) if (i not in held) == keep]
    if len(rows) < 2:
        return None
    part = subset(prob, rows)
    part.dominant = [prob.dominant[i] for i in rows]
    if hasattr(part, "blocks"):
        del part.blocks
    return part


def halved(prob, k: int):
    """The problem over every other window of each joint (k = 0: the first, third, ...; 1: the others)."""
    rows = []
    for j in sorted(set(prob.dominant)):
        own = [i for i, d in enumerate(prob.dominant) if d == j]
        rows += own[k::2] if len(own) > 1 else own
    half = subset(prob, sorted(rows))
    half.dominant = [prob.dominant[i] for i in sorted(rows)]
    if hasattr(half, "blocks"):
        del half.blocks  # built again over this half's windows
    return half


def subset(prob, rows):
    """The same problem over the windows ``rows`` only."""
    ms = prob.sequences
    sub = object.__new__(type(prob))
    sub.__dict__.update(prob.__dict__)
    # the same model sequences, fewer of them (ModelSequences' own constructor compiles the spec again)
    part = object.__new__(type(ms))
    part.__dict__.update(ms.__dict__)
    for key in ("sequence_name", "initial_state", "control", "sensordata", "measured_rollout"):
        setattr(part, key, [getattr(ms, key)[i] for i in rows])
    sub.sequences = part
    sub.residual_fn = prob.residual_over(part)  # the delay and the replay mode: shared (Problem._shared)
    return sub
