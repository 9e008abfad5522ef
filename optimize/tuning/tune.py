"""Gradient-based gain tuning through MJX rollouts: the loss and the loop.

Each iteration: sample a batch of randomised scenarios (``scenarios``, seeded by
the iteration, so a resumed run sees the same batches), take
``jax.value_and_grad`` of the mean cost (``cost``) through the batched
closed-loop rollouts (jaxsync's one physics: MJX's converged solve,
differentiated implicitly; the exact full-horizon gradient unless
``truncate_every`` is set), and take one optax
step on the unconstrained parameters (``params``, ``loop``; a non-finite
gradient skips the step). Validation scenarios pick the iterate; the loop's
state is a :class:`TuneState`, checkpointed (``checkpoint``) every few
iterations and on Ctrl-C.
"""

from __future__ import annotations

import dataclasses
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
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.loop import apply_update
from jaxsync.optimize.tuning.loss import make_loss, traced_value_and_grad
from jaxsync.optimize.tuning.params import TuneSpec
from jaxsync.optimize.tuning.scenarios import training_base, training_batch
from jaxsync.optimize.tuning.tune_state import (
    CHECKPOINT,
    TuneResult,
    TuneState,
    fresh_state,
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


def _method_options(cfg: TuneConfig) -> dict:
    if cfg.method == "cmaes":
        return {"popsize": cfg.popsize}
    if cfg.method == "cmaes-lbfgs":
        return {"cmaes": _methods.CMAES(popsize=cfg.popsize)}
    return {}


def _step(state: TuneState, value_and_grad, opt, scen, cfg: TuneConfig, spec: TuneSpec, base, log):
    """One iteration: gradient, optax step (skipped if not finite), the history row."""
    t0 = time.perf_counter()
    i = state.iteration
    (value, terms), grad = value_and_grad(state.theta, scen)
    u = apply_update(opt, state.theta, state.opt_state, value, grad)
    gnorm, finite = float(u.grad_norm), bool(u.finite)
    bad = 0 if finite else state.bad + 1
    if not finite:
        log(f"iteration {i}: non-finite cost or gradient (cost {float(value)}, |grad| {gnorm}); step skipped")
        if bad >= cfg.max_bad_steps:
            g = _schedule.to_file_dict(spec.to_gains(state.theta, base))
            raise TuneError(
                f"{bad} non-finite gradients in a row, the last at iteration {i}; stopping. Gains at that point: {g}"
            )
    row = {
        "iteration": i,
        "cost": float(value),
        "grad_norm": gnorm,
        "skipped": int(not finite),
        "seconds": time.perf_counter() - t0,
        **{f"term_{k}": float(v) for k, v in terms.items()},
    }
    state = state._replace(
        theta=u.params, opt_state=u.opt_state, iteration=i + 1, bad=bad, history=(*state.history, row)
    )
    return state, row


class _MethodOracle:
    """The fixed-batch objective of a non-Adam method (``optimize.methods``) over
    the flat parameters, built on the tuner's traced gradient and, for CMA-ES,
    one batched forward pass of the population (data-parallel over the run's
    devices when it has several: ``optimize.parallel``)."""

    def __init__(self, loss, get_value_and_grad, theta, scen, cfg: TuneConfig, n_total: int | None = None, batch=None):
        _, self.unravel = ravel_pytree(theta)
        self.scen = scen

        def vg(x):  # traced (or read from disk) at its first use: CMA-ES alone never needs it
            (value, _), grad = get_value_and_grad()(self.unravel(jnp.asarray(x)), self.scen)
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
    """One iteration of an ``optimize.methods`` method; the history row as Adam's (no cost terms)."""
    t0 = time.perf_counter()
    i = state.iteration
    calls0, pop0, v0 = oracle.oracle.gradient_calls, oracle.oracle.forward_rollouts, oracle.oracle.value_calls
    mstate, r = method.step(state.opt_state, oracle.oracle)
    x = method.incumbent(mstate)
    accepted = bool(r.get("accepted", 1))
    finite = bool(np.isfinite(r["train_cost"])) and bool(np.all(np.isfinite(x)))
    bad = 0 if finite else state.bad + 1
    if not finite:
        log(f"iteration {i}: non-finite cost ({cfg.method}: cost {r.get('train_cost')}); no step taken")
        if bad >= cfg.max_bad_steps:
            raise TuneError(f"{cfg.method}: {bad} non-finite iterations in a row, the last at iteration {i}")
    # the method says when it has converged (L-BFGS: no lower cost twice in a
    # row on its last batch; before that it goes on with a fresh one, "renewed")
    stalled = finite and not accepted
    converged = bool(r.get("converged"))
    if stalled:
        if r.get("renewed"):
            then = f"; converged on its training batch, going on with a fresh one ({r['renewed']})"
        else:
            then = "; converged, stopping" if converged else "; curvature memory reset"
        log(f"iteration {i}: no step lowered the training cost" + then)
    row = {
        "iteration": i,
        "cost": float(r["train_cost"]),
        "grad_norm": float(r.get("grad_norm", float("nan"))),
        "skipped": int(not (accepted and finite)),
        "seconds": time.perf_counter() - t0,
        "gradient_calls": oracle.oracle.gradient_calls - calls0,
        "value_calls": oracle.oracle.value_calls - v0,  # forward-only values (L-BFGS's backtracking)
        "population_rollouts": (oracle.oracle.forward_rollouts - pop0) * cfg.batch,
    }
    theta = oracle.unravel(jnp.asarray(x)) if np.all(np.isfinite(x)) else state.theta
    state = state._replace(theta=theta, opt_state=mstate, iteration=i + 1, bad=bad, history=(*state.history, row))
    return state, row, converged


@_interrupt.deferred()  # Ctrl-C stops the loop after an iteration, never lost in a callback
def tune(
    model,
    spec: TuneSpec,
    base: _gains.Gains,
    cfg: TuneConfig,
    weights: CostWeights | None = None,
    *,
    out: str | None = None,
    resume: bool = False,
    restart: bool = False,
    fingerprint: dict | None = None,
    progress: bool = True,
    on_iteration: Callable | None = None,
    validate: Callable | None = None,
) -> TuneResult:
    """Run the optimisation loop; returns a :class:`TuneResult`.

    With ``validate`` (gains -> an evaluation dict, see :func:`select_iterate`)
    the start and every ``cfg.validate_every`` iterations (and the last) are
    evaluated, and the returned gains are the selected iterate's; without it,
    the last iterate's. Checkpoints (``out/checkpoint.npz``, data only) every
    ``cfg.checkpoint_every`` iterations and on Ctrl-C; ``resume`` continues
    from the last one and ends where an uninterrupted run with the same seed
    ends; a checkpoint already in ``out`` is an error unless ``resume`` or
    ``restart`` (start over, overwriting it) is given (``jaxsync tune``
    checks the whole folder first: :func:`prepare_out`).
    ``on_iteration(i, theta, row)`` is called after each step.

    With more than one JAX device (several GPUs, or a multi-process run:
    ``jaxsync.runtime.distributed``) the loss is data-parallel (``optimize.parallel``):
    ``cfg.batch`` scenarios per process, sharded over every device, the cost and
    gradient averaged over all of them; every process runs the same optimiser
    steps and process 0 alone writes the checkpoint.

    Example:
      >>> cfg = TuneConfig(iterations=2, task="short")
      >>> result = tune(jaxsync.load_model(), TuneSpec(), jaxsync.default_gains(), cfg)
      >>> result.gains.k_rk, result.history[-1]["cost"]  # doctest: +SKIP
    """
    cfg.validate()

    weights = weights if weights is not None else CostWeights()
    loss = make_loss(model, spec, base, cfg, weights)
    n_total = parallel.batch_size(cfg.batch) if parallel.active() else None
    batch_cfg = dataclasses.replace(cfg, batch=n_total) if n_total else cfg  # every process draws the whole batch
    main = jax.process_index() == 0
    say = tqdm.write if main else (lambda m: None)
    method = None if cfg.method == "adam" else _methods.get(cfg.method, **_method_options(cfg))
    opt = cfg.optimizer_transform() if method is None else None
    train_base = training_base(cfg)[0]
    ckpt = os.path.join(out, CHECKPOINT) if out else None
    # a cosine learning-rate decay spans the run: its length is part of the state
    decay = cfg.iterations if method is None and cfg.schedule == "cosine" else None
    if ckpt and not resume and not restart and os.path.exists(ckpt) and main:
        prepare_out(out)  # the error naming --resume and --restart
    if out and main:
        _results.ensure_writable_dir(out)
    write_ckpt = ckpt if main else None  # every process reads a checkpoint to resume; process 0 writes them
    state = (
        resumed_state(ckpt, fingerprint, spec, base, opt, method, decay)
        if resume
        else fresh_state(spec, base, opt, method, cfg.seed)
    )
    every = cfg.validate_every if validate is not None else 0

    def progress_bar(first: bool):
        # the run's first iteration traces and compiles the gradient (minutes
        # cold, seconds warm): it gets a bar of its own, replaced after it by
        # one whose clock starts then, so that the rate and the ETA come from
        # the iterations after it (not an ETA of minutes for seconds per step)
        return tqdm(
            total=cfg.iterations,
            initial=state.iteration,
            disable=not (progress and main),
            unit="it",
            dynamic_ncols=True,
            leave=not first,
            desc="first iteration (compiles unless cached)" if first else None,
        )

    bar = progress_bar(first=True)
    value_and_grad = None  # traced at the first step, from its arguments
    try:
        start = state.iteration
        if every and not state.validation:
            state = validated(state._replace(iteration=0), validate, spec, base, say)._replace(iteration=start)
        elif every and (start % every == 0 or start == cfg.iterations) and state.validation[-1]["iteration"] != start:
            state = validated(state, validate, spec, base, say)  # interrupted between a step and its validation
        oracle = None
        for i in range(start, cfg.iterations):
            # Adam: a fresh batch every iteration; the other methods: one fixed batch (a deterministic objective)
            scen = training_batch(batch_cfg, i if method is None else 0, train_base)

            def get_value_and_grad(scen=scen, theta=state.theta):
                nonlocal value_and_grad
                if value_and_grad is None and n_total:
                    value_and_grad = parallel.value_and_grad(loss, n_total)
                elif value_and_grad is None:
                    value_and_grad = traced_value_and_grad(loss, model, spec, base, cfg, weights, (theta, scen), say)
                return value_and_grad

            converged = False
            if method is None:
                state, row = _step(state, get_value_and_grad(), opt, scen, cfg, spec, base, say)
            else:
                if oracle is None:  # CMA-ES's populations only evaluate the loss
                    forward = make_loss(model, spec, base, cfg, weights, differentiated=False)
                    fresh = lambda k: training_batch(batch_cfg, k, train_base)  # noqa: E731
                    oracle = _MethodOracle(forward, get_value_and_grad, state.theta, scen, cfg, n_total, fresh)
                state, row, converged = _method_step(state, method, oracle, cfg, spec, base, say)
            bar.update(1)
            if i == start:
                bar.close()
                bar = progress_bar(first=False)
            bar.set_postfix(cost=f"{row['cost']:.4g}", grad=f"{row['grad_norm']:.3g}")
            if on_iteration is not None:
                on_iteration(i, state.theta, row)
            last = converged or i + 1 == cfg.iterations
            if every and ((i + 1) % every == 0 or last):
                state = validated(state, validate, spec, base, say)
            if (i + 1) % cfg.checkpoint_every == 0 or last:
                save_state(write_ckpt, state, fingerprint, method, decay)
            _interrupt.check()  # a safe point: a Ctrl-C recorded during the iteration stops here
            if converged:
                say(f"{cfg.method} converged on its batch after {i + 1} iterations: stopped early")
                break
    except KeyboardInterrupt:
        if write_ckpt:
            save_state(write_ckpt, state, fingerprint, method, decay)
            say(
                f"interrupted: checkpoint saved to {ckpt} after {state.iteration} iterations; "
                "run again with --resume to continue"
            )
        raise
    finally:
        bar.close()
    last = spec.to_gains(state.theta, base)
    selected = select_iterate(list(state.validation))
    gains = spec.to_gains(state.kept[selected["iteration"]], base) if selected is not None else last
    return TuneResult(gains, list(state.history), list(state.validation), selected, last, state)
