"""Gradient-based gain tuning through MJX rollouts: the loss and the loop.

Each iteration: sample a batch of randomised scenarios (``scenarios``, seeded by
the iteration, so a resumed run sees the same batches), take
``jax.value_and_grad`` of the mean cost (``cost``) through the batched
closed-loop rollouts (jaxsync's one physics: MJX's converged solve,
differentiated implicitly; the exact full-horizon gradient unless
``truncate_every`` is set), and take one step of the configured method
(``methods``: L-BFGS by default, or a first-order optax optimiser) on the
unconstrained parameters (``params``; a non-finite gradient skips the step).
Validation scenarios pick the iterate; the loop's state is a
:class:`TuneState`, checkpointed (``checkpoint``) every few iterations and
on Ctrl-C.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from tqdm import tqdm

from jaxsync._errors import JaxsyncError
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.io import results as _results
from jaxsync.optimize.tuning import methods as _methods
from jaxsync.optimize.tuning import parallel
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.loss import make_loss, traced_value_and_grad
from jaxsync.optimize.tuning.scenarios import training_base, training_batch
from jaxsync.optimize.tuning.tune_state import (
    CHECKPOINT,
    TuneResult,
    TuneState,
    convergence_record,
    criterion_text,
    fresh_state,
    plateaued,
    prepare_out,
    resumed_state,
    save_state,
    select_iterate,
    validated,
)
from jaxsync.runtime import interrupt as _interrupt


class TuneError(JaxsyncError):
    """Tuning cannot go on (e.g. gradients kept being non-finite)."""


# ------------------------------------------------------------------- the loop


LOST_VALIDATIONS = 2
"""Validations in a row that drop the object in every scenario, after which a run stops."""


def lost_everywhere(validation) -> bool:
    """Whether the last :data:`LOST_VALIDATIONS` validations (not the start's)
    dropped the object in every scenario: the iterates have walked where the
    scenarios are lost, whose training cost is a constant with no gradient
    (``optimize.cost``), so that a first-order method moves on its momentum
    alone (measured: Adam at 0.2 on the UR5e-like pair never came back,
    docs/calibrate.md)."""
    last = list(validation)[1:][-LOST_VALIDATIONS:]
    return len(last) == LOST_VALIDATIONS and all(
        v["settled_peak_resultant_N"] is None and v.get("dropped") for v in last
    )


def method_of(cfg: TuneConfig):
    """The configuration's method (``optimize.methods``), with its options."""
    m = cfg.method
    if m.name == "cmaes":
        return _methods.get("cmaes", popsize=m.popsize)
    if m.name == "cmaes-lbfgs":
        return _methods.get("cmaes-lbfgs", cmaes=_methods.CMAES(popsize=m.popsize))
    if m.first_order:
        return _methods.get(m.name, optimizer=cfg.optimizer_transform())
    return _methods.get(m.name)


class _MethodOracle:
    """The training objective of a method (``optimize.methods``) over the flat
    parameters, on one training batch at a time: the tuner's traced gradient
    (its cost terms kept for the history) and, for CMA-ES, one batched
    forward pass of the population (data-parallel over the run's devices when
    it has several: ``optimize.parallel``)."""

    def __init__(self, loss, get_value_and_grad, theta, scen, cfg: TuneConfig, n_total: int | None = None, batch=None):
        _, self.unravel = ravel_pytree(theta)
        self.scen = scen

        self.terms = {}

        def vg(x):  # traced (or read from disk) at its first use: CMA-ES alone never needs it
            (value, terms), grad = get_value_and_grad(self.scen)(self.unravel(jnp.asarray(x)), self.scen)
            self.terms = {k: float(v) for k, v in terms.items()}
            return float(value), np.asarray(ravel_pytree(grad)[0])

        value = None
        if n_total is not None:
            pop_dp = parallel.population_values(loss, self.unravel, n_total)
            values = lambda X: pop_dp(X, self.scen)  # noqa: E731
        else:
            pop = jax.jit(jax.vmap(lambda x, s: loss(self.unravel(x), s)[0], in_axes=(0, None)))
            values = lambda X: pop(jnp.asarray(X), self.scen)  # noqa: E731
            one = jax.jit(lambda x, s: loss(self.unravel(x), s)[0])  # L-BFGS's backtracking trials
            value = lambda x: one(jnp.asarray(x), self.scen)  # noqa: E731

        def renew(k):  # training batch k (same shapes: no new compile)
            self.scen = batch(k)

        self.oracle = _methods.Oracle(
            value_and_grad=vg, values=values, value=value, renew=renew if batch is not None else None
        )


def _method_step(state: TuneState, method, oracle: _MethodOracle, cfg: TuneConfig, spec, base, log):
    """One iteration of an ``optimize.methods`` method and its history row (a
    first-order method's with its cost terms, taken at the iterate it stepped from)."""
    t0 = time.perf_counter()
    i = state.iteration
    calls0, pop0, v0 = oracle.oracle.gradient_calls, oracle.oracle.forward_rollouts, oracle.oracle.value_calls
    mstate, r = method.step(state.opt_state, oracle.oracle)
    x = method.incumbent(mstate)
    accepted = bool(r.get("accepted", 1))
    finite = bool(np.isfinite(r["train_cost"])) and bool(np.all(np.isfinite(x)))
    bad = 0 if finite else state.bad + 1
    if not finite:
        log(f"iteration {i}: non-finite cost or gradient ({cfg.method.name}: cost {r.get('train_cost')}); step skipped")
        if bad >= cfg.loop.max_bad_steps:
            g = _schedule.to_file_dict(spec.to_gains(state.theta, base))
            raise TuneError(
                f"{cfg.method.name}: {bad} non-finite iterations in a row, the last at iteration {i}; stopping. "
                f"Gains at that point: {g}"
            )
    # the method says when it has converged (L-BFGS: twice in a row no step lowers
    # the cost by more than ftol of it on its last batch; before that it goes on
    # with a fresh one, "renewed")
    stalled = finite and not accepted
    small = finite and accepted and bool(r.get("small"))  # taken, counted as no lower cost
    converged = bool(r.get("converged"))
    if stalled or small:
        if r.get("renewed"):
            then = f"; converged on its training batch, going on with a fresh one ({r['renewed']})"
        elif converged:
            then = "; converged, stopping"
        else:
            then = "; counted as none" if small else "; curvature memory reset"
        what = "no step lowered the training cost"
        what = f"the step lowered the training cost by at most {r['small']:.2g} of it" if small else what
        log(f"iteration {i}: {what}" + then)
    row = {
        "iteration": i,
        "cost": float(r["train_cost"]),
        "grad_norm": float(r.get("grad_norm", float("nan"))),
        "skipped": int(not (accepted and finite)),
        "seconds": time.perf_counter() - t0,
        "gradient_calls": oracle.oracle.gradient_calls - calls0,
        "value_calls": oracle.oracle.value_calls - v0,  # forward-only values (L-BFGS's backtracking)
        "population_rollouts": (oracle.oracle.forward_rollouts - pop0) * cfg.training.batch,
    }
    if getattr(method, "fresh_batches", False):
        row.update({f"term_{k}": v for k, v in oracle.terms.items()})
    theta = oracle.unravel(jnp.asarray(x)) if np.all(np.isfinite(x)) else state.theta
    state = state._replace(theta=theta, opt_state=mstate, iteration=i + 1, bad=bad, history=(*state.history, row))
    return state, row, converged


@_interrupt.deferred()  # Ctrl-C stops the loop after an iteration, never lost in a callback
def tune(
    model,
    base: _gains.Gains,
    cfg: TuneConfig,
    *,
    out: str | None = None,
    resume: bool = False,
    restart: bool = False,
    fingerprint: dict | None = None,
    progress: bool = True,
    on_iteration: Callable | None = None,
    validate: Callable | None = None,
) -> TuneResult:
    """Tune ``base``'s parameters named by ``cfg.problem`` on ``model``; returns a :class:`TuneResult`.

    With ``validate`` (gains -> an evaluation dict, see :func:`select_iterate`)
    the start and every ``cfg.loop.validate_every`` iterations (and the last)
    are evaluated, and the returned gains are the selected iterate's; without
    it, the last iterate's. Checkpoints (``out/checkpoint.npz``, data only)
    every ``cfg.loop.checkpoint_every`` iterations and on Ctrl-C; ``resume``
    continues from the last one and ends where an uninterrupted run with the
    same seed ends; a checkpoint already in ``out`` is an error unless
    ``resume`` or ``restart`` (start over, overwriting it) is given
    (``jaxsync tune`` checks the whole folder first: :func:`prepare_out`).
    ``on_iteration(i, theta, row)`` is called after each step.

    Every method steps through ``optimize.methods``: a first-order one on a
    fresh training batch every iteration, the others on one batch at a time
    (L-BFGS moves on to a fresh one when it has converged on its own).

    With more than one JAX device (several GPUs, or a multi-process run:
    ``jaxsync.runtime.distributed``) the loss is data-parallel (``optimize.parallel``):
    ``cfg.training.batch`` scenarios per process, sharded over every device, the cost and
    gradient averaged over all of them; every process runs the same optimiser
    steps and process 0 alone writes the checkpoint.

    Example:
      >>> cfg = TuneConfig(iterations=2, task="short")
      >>> result = tune(jaxsync.load_model(), jaxsync.default_gains(), cfg)
      >>> result.gains.k_rk, result.history[-1]["cost"]  # doctest: +SKIP
    """
    cfg.validate()
    spec = cfg.problem.tuned
    loss = make_loss(model, base, cfg)
    n_total = parallel.batch_size(cfg.training.batch) if parallel.active() else None
    batch_cfg = cfg.replace(batch=n_total) if n_total else cfg  # every process draws the whole batch
    main = jax.process_index() == 0
    say = tqdm.write if main else (lambda m: None)
    method = method_of(cfg)
    fresh_batches = getattr(method, "fresh_batches", False)
    iterations = cfg.loop.iterations
    train_base = training_base(cfg.training)[0]
    ckpt = os.path.join(out, CHECKPOINT) if out else None
    # a cosine learning-rate decay spans the run: its length is part of the state
    decay = iterations if cfg.method.first_order and cfg.method.schedule == "cosine" else None
    if ckpt and not resume and not restart and os.path.exists(ckpt) and main:
        prepare_out(out)  # the error naming resume and restart
    if out and main:
        _results.ensure_writable_dir(out)
    write_ckpt = ckpt if main else None  # every process reads a checkpoint to resume; process 0 writes them
    state = (
        resumed_state(ckpt, fingerprint, spec, base, method, decay)
        if resume
        else fresh_state(spec, base, method, cfg.data.seed)
    )
    every = cfg.loop.validate_every if validate is not None else 0

    def progress_bar(first: bool):
        # the run's first iteration traces and compiles the gradient (minutes
        # cold, seconds warm): it gets a bar of its own, replaced after it by
        # one whose clock starts then, so that the rate and the ETA come from
        # the iterations after it (not an ETA of minutes for seconds per step)
        return tqdm(
            total=iterations,
            initial=state.iteration,
            disable=not (progress and main),
            unit="it",
            dynamic_ncols=True,
            leave=not first,
            desc="first iteration (compiles unless cached)" if first else None,
        )

    bar = progress_bar(first=True)
    value_and_grad = None  # traced at its first use, from its arguments

    def get_value_and_grad(scen):
        nonlocal value_and_grad
        if value_and_grad is None and n_total:
            value_and_grad = parallel.value_and_grad(loss, n_total)
        elif value_and_grad is None:
            value_and_grad = traced_value_and_grad(loss, model, base, cfg, (state.theta, scen), say)
        return value_and_grad

    t_start = time.perf_counter()
    loop = cfg.loop

    def plateau() -> bool:
        return bool(every) and plateaued(list(state.validation), loop.plateau_tol, loop.plateau_validations)

    reason = "cap"
    try:
        start = state.iteration
        if every and not state.validation:
            state = validated(state._replace(iteration=0), validate, spec, base, say, loop.grip_floor)
            state = state._replace(iteration=start)
        elif every and (start % every == 0 or start == iterations) and state.validation[-1]["iteration"] != start:
            # interrupted between a step and its validation
            state = validated(state, validate, spec, base, say, loop.grip_floor)
        forward = make_loss(model, base, cfg, differentiated=False)  # CMA-ES's populations only evaluate the loss
        fresh = lambda k: training_batch(batch_cfg, k, train_base)  # noqa: E731
        oracle = _MethodOracle(forward, get_value_and_grad, state.theta, fresh(0), cfg, n_total, fresh)
        converged = getattr(method, "converged", lambda s: False)(state.opt_state)
        if converged:
            reason = "method"
            say(f"{cfg.method.name} had converged on its batch after {start} iterations: nothing to continue")
        elif plateau():
            converged, reason = True, "plateau"
            say(f"the run had converged after {start} iterations (its validation figure): nothing to continue")
        elif lost_everywhere(state.validation):
            converged, reason = True, "lost"
            say(f"the run had stopped after {start} iterations, its iterates dropping everything: nothing to continue")
        for i in range(start, start if converged else iterations):
            if fresh_batches:  # a first-order method: a fresh batch every iteration
                oracle.oracle.use(i)
            state, row, converged = _method_step(state, method, oracle, cfg, spec, base, say)
            bar.update(1)
            if i == start:
                bar.close()
                bar = progress_bar(first=False)
            bar.set_postfix(cost=f"{row['cost']:.4g}", grad=f"{row['grad_norm']:.3g}")
            if on_iteration is not None:
                on_iteration(i, state.theta, row)
            if converged:
                reason = "method"
            last = converged or i + 1 == iterations
            lost = flat = False
            if every and ((i + 1) % every == 0 or last):
                state = validated(state, validate, spec, base, say, loop.grip_floor)
                lost = not last and lost_everywhere(state.validation)
                held = not lost and not converged and plateau()
                flat = held and not last
                if lost:
                    reason = "lost"
                elif held:
                    reason = "plateau"
            if (i + 1) % cfg.loop.checkpoint_every == 0 or last or lost or flat:
                save_state(write_ckpt, state, fingerprint, method, decay)
            _interrupt.check()  # a safe point: a Ctrl-C recorded during the iteration stops here
            if converged:
                say(f"{cfg.method.name} converged on its batch after {i + 1} iterations: stopped early")
                break
            if flat:
                say(
                    f"converged after {i + 1} iterations: the validation figure moved by less than "
                    f"{100 * loop.plateau_tol:g} % over the last {loop.plateau_validations} validations"
                )
                break
            if lost:
                say(
                    f"the last {LOST_VALIDATIONS} validations dropped the object in every scenario: stopped after "
                    f"{i + 1} iterations (the selected iterate stands; a lower learning rate may go further)"
                )
                break
    except KeyboardInterrupt:
        if write_ckpt:
            save_state(write_ckpt, state, fingerprint, method, decay)
            say(
                f"interrupted: checkpoint saved to {ckpt} after {state.iteration} iterations; "
                "run again with resume to continue"
            )
        raise
    finally:
        bar.close()
    last = spec.to_gains(state.theta, base)
    selected = select_iterate(list(state.validation), loop.grip_floor)
    gains = spec.to_gains(state.kept[selected["iteration"]], base) if selected is not None else last
    record = convergence_record(reason, state, cfg, time.perf_counter() - t_start)
    if reason == "cap":
        say(f"not converged: the cap of {iterations} iterations came before {criterion_text(cfg)} (more "
            "--iterations continue it with --resume)")  # fmt: skip
    return TuneResult(gains, list(state.history), list(state.validation), selected, last, state, record)
