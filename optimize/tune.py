"""Gradient-based gain tuning through MJX rollouts: the loss and the loop.

Each iteration: sample a batch of randomised scenarios (``tasks``, seeded by
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
import math
import os
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jaxsync.optimize import checkpoint
from jaxsync.optimize.cost import CostWeights, cost, cost_terms
from jaxsync.optimize.loop import apply_update, make_optimizer
from jaxsync.optimize.params import TuneSpec
from jaxsync.optimize.tasks import training_base, training_batch

from jaxsync._errors import ConfigError, JaxsyncError
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.io import results as _results
from jaxsync.physics import step as _physics
from jaxsync.runtime.cache import traced_on_disk
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.rollout import make_rollout

# TuneConfig fields the training loss's program depends on (the rest steer the loop)
_PROGRAM_FIELDS = ("train_duration", "eval_duration", "truncate_every", "train_start", "train_task", "task", "batch")


class TuneError(JaxsyncError):
    """Tuning cannot go on (e.g. gradients kept being non-finite)."""


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """How to tune (defaults: ``jaxsync tune``'s).

    Example:
      >>> cfg = TuneConfig(iterations=10, batch=2, task="short").validate()
    """

    iterations: int = 60
    batch: int = 4
    learning_rate: float = 0.05
    optimizer: str = "adam"
    schedule: str = "cosine"  # or "constant"
    clip_norm: float = 1.0
    seed: int = 0
    heldout_seed: int = 1000
    heldout_batch: int = 16
    train_duration: float = 2.0  # of the "short" task; the "full" task runs eval_duration
    eval_duration: float = 4.0
    truncate_every: int | None = None  # exact full-horizon gradient; a window length truncates it
    checkpoint_every: int = 5
    max_bad_steps: int = 3
    train_start: str = "approach"  # keyframe the training rollouts start from
    train_task: tuple = ()  # (field, value) overrides of the training task
    task: str = "full"  # "full": the default task, as held out; "short": jaxsync.short_task() (2 s)
    validate_every: int = 5  # iterations between validation evaluations (0: none, keep the last iterate)
    validation_seed: int = 500
    validation_batch: int = 16
    method: str = "lbfgs"  # optimize.methods.METHODS (docs/tuning.md: measured best); "adam" is the optax loop
    popsize: int = 16  # CMA-ES population (methods "cmaes" and "cmaes-lbfgs")

    def validate(self) -> TuneConfig:
        if self.learning_rate <= 0 or not math.isfinite(self.learning_rate):
            raise ConfigError(f"learning rate must be positive, got {self.learning_rate}")
        if not self.clip_norm > 0 or not math.isfinite(self.clip_norm):
            raise ConfigError(
                f"clip (the gradient's global-norm bound) must be a positive number, got {self.clip_norm}: "
                "0 would zero every update and a negative bound reverse the gradient"
            )
        for name in ("iterations", "batch", "heldout_batch", "checkpoint_every", "max_bad_steps", "validation_batch"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name.replace('_', ' ')} must be a positive integer, got {getattr(self, name)}")
        if self.validate_every < 0:
            raise ConfigError(f"validate every must be 0 (off) or a positive integer, got {self.validate_every}")
        if len({self.seed, self.heldout_seed, self.validation_seed}) < 3:
            raise ConfigError(
                f"the training, validation and held-out seeds must differ (got {self.seed}, "
                f"{self.validation_seed}, {self.heldout_seed}): held-out scenarios are never trained on or selected on"
            )
        if not hasattr(optax, self.optimizer) or self.optimizer.startswith("_"):
            raise ConfigError(
                f"optimizer must name an optax optimiser (adam, adamw, sgd, lion, ...), got {self.optimizer!r}"
            )
        if self.task not in ("short", "full"):
            raise ConfigError(f"training task must be 'short' or 'full', got {self.task!r}")
        from jaxsync.optimize.methods import METHODS

        if self.method not in METHODS:
            raise ConfigError(f"method must be one of {list(METHODS)}, got {self.method!r}")
        if self.popsize < 2:
            raise ConfigError(f"popsize must be at least 2, got {self.popsize}")
        if self.schedule not in ("cosine", "constant"):
            raise ConfigError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        return self

    def optimizer_transform(self) -> optax.GradientTransformation:
        """This configuration's optax optimiser (cosine or constant rate, clipped)."""
        return make_optimizer(
            self.learning_rate,
            optimizer=self.optimizer,
            schedule=self.schedule,
            iterations=self.iterations,
            clip_norm=self.clip_norm,
        )


# ------------------------------------------------------------------- the loss


def make_loss(
    model, spec: TuneSpec, base: _gains.Gains, cfg: TuneConfig, weights: CostWeights, *, differentiated: bool = True
):
    """loss(theta, scenarios) -> (mean cost, mean cost terms), jit- and grad-ready.

    ``differentiated=True`` (a loss to take the gradient of) rematerialises the
    rollout's steps and runs jaxsync's tree passes (a smaller program to
    differentiate); ``False`` (a loss only evaluated, e.g. over a CMA-ES
    population) runs MJX's own passes, faster over large vmapped batches. The
    same values to rounding.

    Example:
      >>> loss = make_loss(jaxsync.load_model(), TuneSpec(),
      ...                  jaxsync.default_gains(), TuneConfig(task="short"), CostWeights())
      >>> value, terms = loss(TuneSpec().init(jaxsync.default_gains()), batch)  # doctest: +SKIP
    """
    fn = make_rollout(
        model,
        "synchronous",
        training_base(cfg)[1],
        remat=differentiated,
        truncate_every=cfg.truncate_every,
        start=cfg.train_start,
    )

    def one(gains, s):
        traj = fn(gains, s)
        return cost(traj, s, weights), cost_terms(traj, s, weights)

    def loss(theta, scenarios):
        gains = spec.to_gains(theta, base)
        c, terms = jax.vmap(one, in_axes=(None, 0))(gains, scenarios)
        return c.mean(), jax.tree_util.tree_map(jnp.mean, terms)

    return loss


def make_evaluator(model, duration: float):
    """evaluate(gains, scenarios) -> batched Metrics on the full task (accurate solver)."""
    fn = make_rollout(model, "synchronous", duration)
    return jax.jit(jax.vmap(lambda g, s: _metrics.summarize(fn(g, s), s), in_axes=(None, 0)))


def eval_summary(m) -> dict:
    """A batch of metrics as the loop records it: means over the rollouts kept (not dropped, finite)."""
    import numpy as np
    from jaxsync.optimize.compare import metric_rows

    rows = metric_rows(m)
    m = _metrics.to_arrays(m)
    kept = ~(m["dropped"] | m["nonfinite"])
    mean = lambda x: float(np.mean(x[kept])) if kept.any() else None  # noqa: E731
    return {
        "settled_peak_resultant_N": mean(m["settled_peak_resultant_N"]),
        "grip_force_error_rel": mean(m["grip_force_error_rel"]),
        "dropped": int(m["dropped"].sum()),
        "nonfinite": int(m["nonfinite"].sum()),
        "per_scenario_peak_N": m["settled_peak_resultant_N"].tolist(),
        "per_scenario": rows,  # what the MuJoCo C check compares with (jaxsync.optimize.compare.sim_to_sim)
    }


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


# ------------------------------------------------------------------- the loop


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


def _fresh(spec: TuneSpec, base, opt, method=None, seed: int = 0) -> TuneState:
    theta = spec.init(base)
    if opt is None:  # an optimize.methods method on the flat parameters
        x0 = np.asarray(ravel_pytree(theta)[0])
        return TuneState(theta, method.init(x0, seed), 0, 0, (), (), {})
    return TuneState(theta, opt.init(theta), 0, 0, (), (), {})


def _resumed(path: str, fingerprint, spec: TuneSpec, base, opt) -> TuneState:
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


def _save(path: str | None, state: TuneState, fingerprint) -> None:
    if path:
        d = state._asdict()
        d.update(history=list(state.history), validation=list(state.validation), fingerprint=fingerprint)
        checkpoint.save(path, d)


def _validated(state: TuneState, validate: Callable, spec: TuneSpec, base, log) -> TuneState:
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
    neither, a checkpoint or a former run's results are a ConfigError naming
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


def _traced_value_and_grad(loss, model, spec, base, cfg, weights, args, log):
    """jit(value_and_grad(loss)), its traced form kept on disk between runs
    (``jaxsync.runtime.cache.traced_on_disk``), keyed by everything the loss closes over."""
    import hashlib

    with open(model.path, "rb") as f:
        model_hash = hashlib.sha256(f.read()).hexdigest()
    program = {k: v for k, v in dataclasses.asdict(cfg).items() if k in _PROGRAM_FIELDS}
    key = repr(
        (
            "tune.value_and_grad",
            spec.describe(),
            _schedule.to_file_dict(base),
            program,
            tuple(weights),
            model.path,
            model_hash,
            model.solver,
        )
    )
    value_and_grad = traced_on_disk(jax.value_and_grad(loss, has_aux=True), args, key, log=log)
    _physics.forget_stage_traces()
    return value_and_grad


def _method_options(cfg: TuneConfig) -> dict:
    if cfg.method == "cmaes":
        return {"popsize": cfg.popsize}
    if cfg.method == "cmaes-lbfgs":
        from jaxsync.optimize.methods import CMAES

        return {"cmaes": CMAES(popsize=cfg.popsize)}
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

    def __init__(self, loss, get_value_and_grad, theta, scen, cfg: TuneConfig, n_total: int | None = None):
        from jaxsync.optimize.methods import Oracle

        _, self.unravel = ravel_pytree(theta)
        self.scen = scen

        def vg(x):  # traced (or read from disk) at its first use: CMA-ES alone never needs it
            (value, _), grad = get_value_and_grad()(self.unravel(jnp.asarray(x)), scen)
            return float(value), np.asarray(ravel_pytree(grad)[0])

        if n_total is not None:
            from jaxsync.optimize import parallel

            pop_dp = parallel.population_values(loss, self.unravel, n_total)
            values = lambda X: pop_dp(X, scen)  # noqa: E731
        else:
            pop = jax.jit(jax.vmap(lambda x, s: loss(self.unravel(x), s)[0], in_axes=(0, None)))
            values = lambda X: pop(jnp.asarray(X), scen)  # noqa: E731
        self.oracle = Oracle(value_and_grad=vg, values=values)


def _method_step(state: TuneState, method, oracle: _MethodOracle, cfg: TuneConfig, spec, base, log):
    """One iteration of an ``optimize.methods`` method; the history row as Adam's (no cost terms)."""
    t0 = time.perf_counter()
    i = state.iteration
    calls0, pop0 = oracle.oracle.gradient_calls, oracle.oracle.forward_rollouts
    mstate, r = method.step(state.opt_state, oracle.oracle)
    x = method.incumbent(mstate)
    accepted = bool(r.get("accepted", 1))
    finite = bool(np.isfinite(r["train_cost"])) and bool(np.all(np.isfinite(x)))
    bad = 0 if finite else state.bad + 1
    if not finite:
        log(f"iteration {i}: non-finite cost ({cfg.method}: cost {r.get('train_cost')}); no step taken")
        if bad >= cfg.max_bad_steps:
            raise TuneError(f"{cfg.method}: {bad} non-finite iterations in a row, the last at iteration {i}")
    # a line search that found no lower cost, twice in a row (the second time a
    # short steepest-descent step after the curvature memory was reset): the
    # fixed batch's cost is at a local minimum to the line search's resolution
    stalled = finite and not accepted
    prev = state.history[-1] if state.history else None
    converged = stalled and prev is not None and bool(prev["skipped"]) and math.isfinite(prev["cost"])
    if stalled:
        log(
            f"iteration {i}: no step lowered the training cost"
            + ("; converged, stopping" if converged else "; curvature memory reset")
        )
    row = {
        "iteration": i,
        "cost": float(r["train_cost"]),
        "grad_norm": float(r.get("grad_norm", float("nan"))),
        "skipped": int(not (accepted and finite)),
        "seconds": time.perf_counter() - t0,
        "gradient_calls": oracle.oracle.gradient_calls - calls0,
        "population_rollouts": (oracle.oracle.forward_rollouts - pop0) * cfg.batch,
    }
    theta = oracle.unravel(jnp.asarray(x)) if np.all(np.isfinite(x)) else state.theta
    state = state._replace(theta=theta, opt_state=mstate, iteration=i + 1, bad=bad, history=(*state.history, row))
    return state, row, converged


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
    the last iterate's. Checkpoints (``out/checkpoint.pkl``) every
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
    from tqdm import tqdm

    cfg.validate()
    from jaxsync.optimize import parallel

    weights = weights if weights is not None else CostWeights()
    loss = make_loss(model, spec, base, cfg, weights)
    n_total = parallel.batch_size(cfg.batch) if parallel.active() else None
    batch_cfg = dataclasses.replace(cfg, batch=n_total) if n_total else cfg  # every process draws the whole batch
    main = jax.process_index() == 0
    say = tqdm.write if main else (lambda m: None)
    from jaxsync.optimize import methods as _methods

    method = None if cfg.method == "adam" else _methods.get(cfg.method, **_method_options(cfg))
    opt = cfg.optimizer_transform() if method is None else None
    train_base = training_base(cfg)[0]
    ckpt = os.path.join(out, "checkpoint.pkl") if out else None
    if ckpt and not resume and not restart and os.path.exists(ckpt) and main:
        prepare_out(out)  # the error naming --resume and --restart
    if out and main:
        _results.ensure_writable_dir(out)
    write_ckpt = ckpt if main else None  # every process reads a checkpoint to resume; process 0 writes them
    state = _resumed(ckpt, fingerprint, spec, base, opt) if resume else _fresh(spec, base, opt, method, cfg.seed)
    every = cfg.validate_every if validate is not None else 0

    def progress_bar(first: bool):
        # the run's first iteration traces and compiles the gradient (minutes
        # cold, seconds warm): it gets a bar of its own, replaced after it by
        # one whose clock starts then, so that the rate and the ETA come from
        # the iterations after it (issue 11: an ETA of 08:45 for seconds per step)
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
            state = _validated(state._replace(iteration=0), validate, spec, base, say)._replace(iteration=start)
        elif every and (start % every == 0 or start == cfg.iterations) and state.validation[-1]["iteration"] != start:
            state = _validated(state, validate, spec, base, say)  # interrupted between a step and its validation
        oracle = None
        for i in range(start, cfg.iterations):
            # Adam: a fresh batch every iteration; the other methods: one fixed batch (a deterministic objective)
            scen = training_batch(batch_cfg, i if method is None else 0, train_base)

            def get_value_and_grad(scen=scen, theta=state.theta):
                nonlocal value_and_grad
                if value_and_grad is None and n_total:
                    value_and_grad = parallel.value_and_grad(loss, n_total)
                elif value_and_grad is None:
                    value_and_grad = _traced_value_and_grad(loss, model, spec, base, cfg, weights, (theta, scen), say)
                return value_and_grad

            converged = False
            if method is None:
                state, row = _step(state, get_value_and_grad(), opt, scen, cfg, spec, base, say)
            else:
                if oracle is None:  # CMA-ES's populations only evaluate the loss
                    forward = make_loss(model, spec, base, cfg, weights, differentiated=False)
                    oracle = _MethodOracle(forward, get_value_and_grad, state.theta, scen, cfg, n_total)
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
                state = _validated(state, validate, spec, base, say)
            if (i + 1) % cfg.checkpoint_every == 0 or last:
                _save(write_ckpt, state, fingerprint)
            if converged:
                say(f"{cfg.method} converged on its batch after {i + 1} iterations: stopped early")
                break
    except KeyboardInterrupt:
        if write_ckpt:
            _save(write_ckpt, state, fingerprint)
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
