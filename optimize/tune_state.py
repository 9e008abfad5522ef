"""The tuning loop's state: fresh, resumed from a checkpoint, validated, and
the output folder it is written to."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.optimize import checkpoint
from jaxsync.optimize.params import TuneSpec


def select_iterate(validation: list[dict]) -> dict | None:
    """The validated iterate with the lowest settled peak resultant whose grip
    error is not worse than the start's (the first entry, which therefore always
    qualifies). Entries: {"iteration", "settled_peak_resultant_N",
    "grip_force_error_rel", "dropped", "nonfinite", ...}."""
    if not validation:
        return None
    grip0 = validation[0]["grip_force_error_rel"]
    ok = [
        v
        for v in validation
        if v["settled_peak_resultant_N"] is not None
        and not v["dropped"]
        and not v["nonfinite"]
        and (v is validation[0] or v["grip_force_error_rel"] <= grip0)
    ]
    return min(ok, key=lambda v: v["settled_peak_resultant_N"]) if ok else validation[0]


# ------------------------------------------------------------------- the state


class TuneState(NamedTuple):
    """Everything the loop carries from one iteration to the next (and checkpoints)."""

    theta: dict  # the unconstrained parameters (TuneSpec)
    opt_state: Any
    iteration: int  # steps taken
    bad: int  # non-finite steps in a row
    history: tuple  # one row (dict) per step
    validation: tuple  # one evaluation (dict) per validated iterate
    kept: dict  # iteration -> theta, of the iterate that may still be selected


class TuneResult(NamedTuple):
    gains: _gains.Gains  # the selected iterate's (the last iterate's without validation)
    history: list  # one row per step: iteration, cost, grad_norm, skipped, seconds, term_*
    validation: list  # the evaluations of the validated iterates
    selected: dict | None  # the selected evaluation (None without validation)
    last_gains: _gains.Gains
    state: TuneState


def fresh_state(spec: TuneSpec, base, opt, method=None, seed: int = 0) -> TuneState:
    theta = spec.init(base)
    if opt is None:  # an optimize.methods method on the flat parameters
        x0 = np.asarray(ravel_pytree(theta)[0])
        return TuneState(theta, method.init(x0, seed), 0, 0, (), (), {})
    return TuneState(theta, opt.init(theta), 0, 0, (), (), {})


def resumed_state(path: str, fingerprint, spec: TuneSpec, base, opt) -> TuneState:
    saved = checkpoint.load(path)
    if fingerprint is not None and saved.get("fingerprint") != fingerprint:
        raise ConfigError(
            f"--resume: {path} was written by a run with other options; its options: {saved.get('fingerprint')}"
        )
    theta = jax.tree_util.tree_map(jnp.asarray, saved["theta"])
    if opt is None:  # an optimize.methods state: plain Python and numpy, kept as saved
        opt_state = saved["opt_state"]
    else:
        template = jax.tree_util.tree_structure(opt.init(theta))
        opt_state = jax.tree_util.tree_unflatten(template, jax.tree_util.tree_leaves(saved["opt_state"]))
        opt_state = jax.tree_util.tree_map(jnp.asarray, opt_state)
    return TuneState(
        theta=theta,
        opt_state=opt_state,
        iteration=int(saved["iteration"]),
        bad=int(saved["bad"]),
        history=tuple(saved["history"]),
        validation=tuple(saved.get("validation", [])),
        kept={int(k): jax.tree_util.tree_map(jnp.asarray, v) for k, v in saved.get("kept", {}).items()},
    )


def save_state(path: str | None, state: TuneState, fingerprint) -> None:
    if path:
        d = state._asdict()
        d.update(history=list(state.history), validation=list(state.validation), fingerprint=fingerprint)
        checkpoint.save(path, d)


def validated(state: TuneState, validate: Callable, spec: TuneSpec, base, log) -> TuneState:
    """Evaluate the current iterate; keep its parameters while it may be selected."""
    i = state.iteration
    r = {"iteration": i, **validate(spec.to_gains(state.theta, base))}
    validation = (*state.validation, r)
    best = select_iterate(list(validation))["iteration"]
    kept = {k: v for k, v in {**state.kept, i: state.theta}.items() if k == best}
    peak, grip = r["settled_peak_resultant_N"], r["grip_force_error_rel"]
    log(
        f"validation after {i} iterations: settled peak "
        + (f"{peak:.5f} N, grip error {100 * grip:.2f} %" if peak is not None else "n/a (all dropped)")
        + (f", {r['dropped']} dropped" if r.get("dropped") else "")
        + f"; selected so far: iteration {best}"
    )
    return state._replace(validation=validation, kept=kept)


# What a tuning run writes to its folder (checkpoint.pkl by tune(), the rest by
# jaxsync tune): removed together when a run starts over (--restart).
RUN_FILES = (
    "checkpoint.pkl",
    "heldout_before.json",
    "gains.json",
    "gains_last.json",
    "history.csv",
    "loss.png",
    "summary.json",
)


def prepare_out(out: str, *, resume: bool = False, restart: bool = False) -> None:
    """Check what ``out`` holds before a run writes there; reads, never creates.

    A folder holding a tuning run is continued (``resume``) or discarded
    (``restart``: its RUN_FILES are removed), never silently overwritten: with
    neither, a checkpoint or an earlier run's results are a ConfigError naming
    both flags.
    """
    if resume and restart:
        raise ConfigError("--resume continues the run in --out and --restart discards it: give one of them")
    ckpt = os.path.join(out, "checkpoint.pkl")
    if resume:
        if not os.path.exists(ckpt):
            raise ConfigError(f"--resume: no checkpoint at {ckpt}")
        return
    found = [f for f in RUN_FILES if os.path.exists(os.path.join(out, f))]
    if restart:
        for f in found:
            os.unlink(os.path.join(out, f))
        return
    if "checkpoint.pkl" in found:
        raise ConfigError(
            f"output folder {out!r} holds a tuning run ({', '.join(found)}): pass --resume to continue it, "
            "--restart to discard it and start over, or choose another --out"
        )
    if found:
        raise ConfigError(
            f"output folder {out!r} holds a tuning run's results ({', '.join(found)}) and no checkpoint to "
            "--resume from: pass --restart to discard them and start over, or choose another --out"
        )
