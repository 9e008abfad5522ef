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
from jaxsync.optimize.tuning import checkpoint
from jaxsync.optimize.tuning.methods import LBFGS
from jaxsync.optimize.tuning.params import TuneSpec


def select_iterate(validation: list[dict], grip_floor: float = 0.0) -> dict | None:
    """The validated iterate with the lowest settled peak resultant whose grip
    error is not worse than the start's (the first entry, which therefore always
    qualifies) or at most ``grip_floor`` (relative: a run continued from tuned
    gains, whose grip error is already far below what matters, may trade a
    little of it), that dropped nothing and chattered in no scenario more than the
    start did (``jaxsync.sim.metrics.CHATTER_THRESHOLD_N``). Where the tuning
    bounds compliance, only iterates within the bounds (``within_bounds``)
    are chosen from; when none is (the start outside them too), the one that
    exceeds them least (``bound_excess``), then the lowest peak. Entries:
    {"iteration", "settled_peak_resultant_N", "grip_force_error_rel",
    "dropped", "nonfinite", "chattering", ...}."""
    if not validation:
        return None
    grip0 = max(validation[0]["grip_force_error_rel"], grip_floor)
    chatter0 = validation[0].get("chattering", 0)
    ok = [
        v
        for v in validation
        if v["settled_peak_resultant_N"] is not None
        and not v["dropped"]
        and not v["nonfinite"]
        and (v is validation[0] or (v["grip_force_error_rel"] <= grip0 and v.get("chattering", 0) <= chatter0))
    ]
    if not ok:
        return validation[0]
    within = [v for v in ok if v.get("within_bounds", True)]
    if within:
        return min(within, key=lambda v: v["settled_peak_resultant_N"])
    return min(ok, key=lambda v: (v.get("bound_excess", 0.0), v["settled_peak_resultant_N"]))


STOP_REASONS = {
    "method": "the method converged on its training batches (no step lowered the cost by more than "
    f"{LBFGS.ftol:.2g} of it)",
    "plateau": "the validation figure moved by less than the tolerance over the last validations",
    "lost": "the iterates dropped the object in every validation scenario",
}
"""Why a run stopped before its cap; the first two are convergence (at the cap: :func:`criterion_text`)."""


def convergence_record(reason: str, state, cfg, seconds: float) -> dict:
    """What ``summary.json`` says of a run's convergence: whether and why it
    stopped (:data:`STOP_REASONS`), the criterion, and the cost: iterations,
    gradients, forward-only costs, training and validation rollouts, seconds
    (this call's, a resumed run's not counting the earlier part's)."""
    h = list(state.history)
    b = cfg.training.batch
    gradients = int(sum(r.get("gradient_calls", 0) for r in h))
    values = int(sum(r.get("value_calls", 0) for r in h))
    population = int(sum(r.get("population_rollouts", 0) for r in h))
    return {
        "converged": reason in ("method", "plateau"),
        "reason": reason,
        "why": f"the cap came before {criterion_text(cfg)}" if reason == "cap" else STOP_REASONS[reason],
        "criterion": {
            "plateau_tol": cfg.loop.plateau_tol,
            "plateau_validations": cfg.loop.plateau_validations,
            "validate_every": cfg.loop.validate_every,
            "iterations_cap": cfg.loop.iterations,
        },
        "iterations": state.iteration,
        "gradient_calls": gradients,
        "value_calls": values,
        "training_rollouts": b * (gradients + values) + population,
        "validation_rollouts": len(state.validation) * cfg.data.validation_batch,
        "seconds": float(seconds),
    }


def criterion_text(cfg) -> str:
    """What converging takes, in words: the method's own criterion, and the plateau where on."""
    loop = cfg.loop
    own = "L-BFGS converging on its batches" if cfg.method.name in ("lbfgs", "cmaes-lbfgs") else ""
    plateau = (
        f"the validation figure moving by at most {100 * loop.plateau_tol:g} % over "
        f"{loop.plateau_validations} validations"
        if loop.plateau_tol > 0 and loop.validate_every
        else ""
    )
    said = " or ".join(x for x in (own, plateau) if x)
    return said or f"a criterion ({cfg.method.name} has none of its own: --plateau-tol sets one)"


def plateaued(validation: list[dict], tol: float, over: int) -> bool:
    """Whether the validation figure (each validation's mean settled peak)
    moved by at most ``tol``, relative, over the last ``over`` validations:
    the last ``over`` + 1 figures lie within ``tol`` of their lowest. The
    run's converged criterion (``Loop.plateau_tol`` and
    ``plateau_validations``; ``tol`` 0 never holds). A stretch in which a
    validation dropped or diverged anywhere, or crossed the compliance
    bounds, has moved.

    Example:
      >>> v = [{"iteration": i, "settled_peak_resultant_N": p, "grip_force_error_rel": 0.0,
      ...       "dropped": 0, "nonfinite": 0} for i, p in enumerate([1.0, 0.5, 0.499, 0.498])]
      >>> plateaued(v, 0.02, 2), plateaued(v, 0.02, 3)
      (True, False)
    """
    if tol <= 0 or len(validation) <= over:
        return False
    last = list(validation)[-(over + 1) :]
    peaks = [v["settled_peak_resultant_N"] for v in last]
    if any(p is None for p in peaks) or any(v.get("dropped") or v.get("nonfinite") for v in last):
        return False
    if len({bool(v.get("within_bounds", True)) for v in last}) > 1:
        return False
    return max(peaks) - min(peaks) <= tol * min(peaks)


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
    convergence: dict | None = None  # convergence_record: converged or not, why, and what it cost


def fresh_state(spec: TuneSpec, base, method, seed: int = 0) -> TuneState:
    """The state a run starts from: ``base``'s parameters, ``method``'s (``optimize.methods``) first state."""
    theta = spec.init(base)
    x0 = np.asarray(ravel_pytree(theta)[0])
    return TuneState(theta, method.init(x0, seed), 0, 0, (), (), {})


def _differences(saved: dict | None, given: dict) -> list[str]:
    saved = saved or {}
    return [
        f"{k}: {saved.get(k)!r} then, {given.get(k)!r} now"
        for k in sorted(set(saved) | set(given))
        if saved.get(k) != given.get(k)
    ]


def _gains_added_since(saved: dict | None, given: dict | None) -> dict | None:
    """``saved`` (a checkpoint's fingerprint) with each gain its starting gains lack, a gain jaxsync
    added since, at the value ``given`` holds when that is the gain's default: the run behaved so."""
    if not saved or not given or not isinstance(saved.get("gains_start"), dict):
        return saved
    start, now = saved["gains_start"], given.get("gains_start") or {}
    if "schedule" in start or "schedule" in now:
        return saved
    default = _gains.to_dict(_gains.default_gains())
    added = {k: v for k, v in now.items() if k not in start and v == default.get(k)}
    return {**saved, "gains_start": {**start, **added}} if added else saved


def resumed_state(
    path: str, fingerprint, spec: TuneSpec, base, method, schedule_iterations: int | None = None
) -> TuneState:
    """The state a checkpoint holds, ``method``'s (``optimize.methods``)
    rebuilt from its data. ``schedule_iterations``: the run's length where
    the learning-rate schedule depends on it (a cosine decay): a resumed run
    of another length would not end where an uninterrupted one ends, and is
    refused."""
    saved = checkpoint.load(path)
    was_run = _gains_added_since(saved.get("fingerprint"), fingerprint)
    if fingerprint is not None and was_run != fingerprint:
        diff = "; ".join(_differences(was_run, fingerprint))
        raise ConfigError(
            f"{path} was written by a run with other settings ({diff}): resume it with those, or restart",
            inputs=("resume", "restart"),
        )
    was = saved.get("schedule_iterations")
    if schedule_iterations is not None and was is not None and was != schedule_iterations:
        raise ConfigError(
            f"iterations {schedule_iterations}, but the run in {path} decays its learning rate over {was} "
            f"iterations (a cosine schedule): resume it with iterations {was}, or restart (runs with a constant "
            "schedule can be extended)",
            inputs=("iterations", "schedule", "restart"),
        )
    theta = jax.tree_util.tree_map(jnp.asarray, saved["theta"])
    opt_state = method.from_data(saved["opt_state"])
    return TuneState(
        theta=theta,
        opt_state=opt_state,
        iteration=int(saved["iteration"]),
        bad=int(saved["bad"]),
        history=tuple(saved["history"]),
        validation=tuple(saved.get("validation", [])),
        kept={int(k): jax.tree_util.tree_map(jnp.asarray, v) for k, v in saved.get("kept", {}).items()},
    )


def save_state(path: str | None, state: TuneState, fingerprint, method, schedule_iterations: int | None = None) -> None:
    """Write ``state`` to the checkpoint ``path`` (data only: ``optimize.checkpoint``)."""
    if path:
        d = state._asdict()
        d["opt_state"] = method.to_data(state.opt_state)
        d.update(
            history=list(state.history),
            validation=list(state.validation),
            fingerprint=fingerprint,
            schedule_iterations=schedule_iterations,
        )
        checkpoint.save(path, d)


def validated(state: TuneState, validate: Callable, spec: TuneSpec, base, log, grip_floor: float = 0.0) -> TuneState:
    """Evaluate the current iterate; keep its parameters while it may be selected."""
    i = state.iteration
    r = {"iteration": i, **validate(spec.to_gains(state.theta, base))}
    validation = (*state.validation, r)
    best = select_iterate(list(validation), grip_floor)["iteration"]
    kept = {k: v for k, v in {**state.kept, i: state.theta}.items() if k == best}
    peak, grip = r["settled_peak_resultant_N"], r["grip_force_error_rel"]
    log(
        f"validation after {i} iterations: settled peak "
        + (f"{peak:.5f} N, grip error {100 * grip:.2f} %" if peak is not None else "n/a (all dropped)")
        + (f", {r['dropped']} dropped" if r.get("dropped") else "")
        + f"; selected so far: iteration {best}"
    )
    return state._replace(validation=validation, kept=kept)


CHECKPOINT = "checkpoint.npz"
# What a tuning run writes to its folder (the checkpoint by tune(), the rest by
# jaxsync tune): removed together when a run starts over (--restart).
RUN_FILES = (
    CHECKPOINT,
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
    both.
    """
    if resume and restart:
        raise ConfigError(
            "resume continues the run in out and restart discards it: give one of them", inputs=("resume", "restart")
        )
    ckpt = os.path.join(out, CHECKPOINT)
    if resume:
        if not os.path.exists(ckpt):
            raise ConfigError(
                f"no checkpoint at {ckpt} to resume from: restart instead to start a run there (discarding any "
                "results it holds), or choose another output folder",
                inputs=("resume", "restart", "out"),
            )
        return
    found = [f for f in RUN_FILES if os.path.exists(os.path.join(out, f))]
    if restart:
        for f in found:
            os.unlink(os.path.join(out, f))
        return
    if CHECKPOINT in found:
        raise ConfigError(
            f"output folder {out!r} holds a tuning run ({', '.join(found)}): resume to continue it, restart to "
            "discard it and start over, or choose another output folder",
            inputs=("resume", "restart", "out"),
        )
    if found:
        raise ConfigError(
            f"output folder {out!r} holds a tuning run's results ({', '.join(found)}) and no checkpoint to "
            "resume from: restart to discard them and start over, or choose another output folder",
            inputs=("restart", "out"),
        )
