"""The tuner's loss and evaluator: what ``jax.value_and_grad`` differentiates.

:func:`make_loss` is the mean cost (``optimize.cost``) of a batch of
closed-loop rollouts; differentiated, it runs jaxsync's body-tree passes
under ``jax.checkpoint``. :func:`traced_value_and_grad` keeps its gradient's
traced form on disk between runs. :func:`make_evaluator` and
:func:`eval_summary` score gains on validation and held-out scenarios.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.control import compliance as _compliance
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.cost import cost, cost_terms
from jaxsync.optimize.tuning.params import TuneSpec  # noqa: F401  (the docstring's example)
from jaxsync.optimize.tuning.scenarios import training_base
from jaxsync.physics import step as _physics
from jaxsync.runtime import programs
from jaxsync.runtime.cache import traced_on_disk
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.actuation import substeps_for_rate
from jaxsync.sim.crosscheck import metric_rows
from jaxsync.sim.rollout import make_rollout

BOUND_WEIGHT = 100.0  # the cost of exceeding a compliance bound by 10 %: 1 (a squared hinge)
IMPACT_TEMPERATURE = 0.1  # N, of the smooth first-impact peak


def make_loss(model, base: _gains.Gains, cfg: TuneConfig, *, differentiated: bool = True):
    """loss(theta, scenarios) -> (mean cost, mean cost terms), jit- and grad-ready.

    The parameters ``cfg.problem`` tunes, at ``base``'s values for the rest;
    it reads ``cfg.program()`` alone (the problem and the training rollouts).

    ``differentiated=True`` (a loss to take the gradient of) rematerialises the
    rollout's steps and runs jaxsync's tree passes (a smaller program to
    differentiate); ``False`` (a loss only evaluated, e.g. over a CMA-ES
    population) runs MJX's own passes, faster over large vmapped batches. The
    same values to rounding.

    Example:
      >>> loss = make_loss(jaxsync.load_model(), jaxsync.default_gains(), TuneConfig(task="short"))
      >>> value, terms = loss(TuneSpec().init(jaxsync.default_gains()), batch)  # doctest: +SKIP
    """
    problem, training = cfg.program()
    spec, weights = problem.tuned, problem.weights
    max_impact, max_stiffness = problem.max_impact_N, problem.max_stiffness_N_per_m
    fn = make_rollout(
        model,
        problem.controller,
        training_base(training)[1],
        remat=differentiated,
        passes="tree" if differentiated else "mjx",
        truncate_every=training.truncate_every,
        start=training.train_start,
        actuation=training.actuation,
        control_substeps=substeps_for_rate(model, training.control_rate),
        distro=training.distro,
    )

    stiffness = compliance_fn(model, problem.controller) if max_stiffness else None

    def one(gains, s):
        traj = fn(gains, s)
        terms = cost_terms(traj, s, weights)
        if max_impact:
            terms["impact"] = smooth_impact(traj)
        return cost(traj, s, weights), terms

    def loss(theta, scenarios):
        gains = spec.to_gains(theta, base)
        c, terms = jax.vmap(one, in_axes=(None, 0))(gains, scenarios)
        c, terms = c.mean(), jax.tree_util.tree_map(jnp.mean, terms)
        if max_impact:  # the batch's mean first impact, bounded
            terms["impact_bound"] = bound_penalty(terms.pop("impact"), max_impact)
            c = c + terms["impact_bound"]
        if stiffness is not None:
            terms["stiffness_bound"] = bound_penalty(stiffness(gains), max_stiffness)
            c = c + terms["stiffness_bound"]
        return c, terms

    return loss


def bound_penalty(value, bound):
    """BOUND_WEIGHT (value / bound - 1)^2 above the bound, 0 below."""
    return BOUND_WEIGHT * jax.nn.relu(value / bound - 1.0) ** 2


def smooth_impact(traj):
    """The first-impact peak (``jaxsync.sim.metrics.first_impact_peak``), log-sum-exp smooth."""
    fn = _metrics.normal_forces(traj.pad_forces, traj.pad_normal)
    mask = _metrics.impact_mask(traj.time, fn)
    return _metrics.smooth_max(fn.reshape(-1), mask.reshape(-1), IMPACT_TEMPERATURE)


def compliance_fn(model, controller: str, axis: str | None = "normal"):
    """gains -> the apparent stiffness at the pad, N/m (``jaxsync.control.compliance``):
    along ``axis`` ("normal" or "tangential"), or both as a dict (``axis=None``);
    a schedule's is the largest over its phases. ros2_admittance's is the
    classical law's: the same mass, damping and spring at the pad, whose
    static offset under a force is the same (an approximation: its offsets
    are integrated in joint space); ros2_synchronous's the synchronous law's,
    whose offset its command carries once the reference has caught up."""
    pos, rot = _compliance.probe_geometry(model)
    dt = float(model.mj_model.opt.timestep)

    def figures(g):
        k = _compliance.apparent_stiffness(controller, g, pos, rot, dt)
        return k if axis is None else k[axis]

    def fn(gains):
        if isinstance(gains, _schedule.Schedule):
            return jax.tree_util.tree_map(jnp.max, jax.vmap(figures)(gains.phases))
        return figures(gains)

    return fn


@programs.memoize(maxsize=8)
def make_evaluator(
    model,
    duration: float,
    controller: str = "synchronous",
    actuation: str = "torque",
    control_substeps: int = 1,
    distro: str = "jazzy",
):
    """evaluate(gains, scenarios) -> batched Metrics on the full task (accurate solver);
    one per configuration and process (a study's runs share it); ``actuation``,
    ``control_substeps`` and ``distro``: the arms' stack (``Stack.rollout_options``)."""
    fn = make_rollout(
        model, controller, duration, actuation=actuation, control_substeps=control_substeps, distro=distro
    )
    return jax.jit(jax.vmap(lambda g, s: _metrics.summarize(fn(g, s), s), in_axes=(None, 0)))


def eval_summary(m) -> dict:
    """A batch of metrics as the loop records it: means over the rollouts kept (not dropped, finite)."""
    rows = metric_rows(m)
    m = _metrics.to_arrays(m)
    kept = ~(m["dropped"] | m["nonfinite"])
    mean = lambda x: float(np.mean(x[kept])) if kept.any() else None  # noqa: E731
    return {
        "settled_peak_resultant_N": mean(m["settled_peak_resultant_N"]),
        "grip_force_error_rel": mean(m["grip_force_error_rel"]),
        "dropped": int(m["dropped"].sum()),
        "nonfinite": int(m["nonfinite"].sum()),
        "chattering": int(m["chattering"].sum()),
        "first_impact_peak_N": mean(m["first_impact_peak_N"]),
        "per_scenario_peak_N": m["settled_peak_resultant_N"].tolist(),
        "per_scenario": rows,  # what the MuJoCo C check compares with (jaxsync.sim.crosscheck.sim_to_sim)
        # every metric of every scenario (NaN, e.g. the drop time of a held object: None)
        "metrics": {k: [None if x != x else x for x in v.tolist()] for k, v in m.items()},
    }


def traced_value_and_grad(loss, model, base, cfg, args, log):
    """jit(value_and_grad(loss)), its traced form kept on disk between runs
    (``jaxsync.runtime.cache.traced_on_disk``), keyed by everything the loss
    closes over: the model, ``base`` and ``cfg.program()``."""
    problem, training = cfg.program()
    key = repr(
        (
            "tune.value_and_grad",
            problem.tuned.describe(),
            _schedule.to_file_dict(base),
            {**dataclasses.asdict(problem), "spec": None, "weights": tuple(problem.weights)},
            dataclasses.asdict(training),
            model.path,
            model.fingerprint,  # the MJCF file's bytes, or what a robot file composes
            model.solver,
        )
    )
    value_and_grad = traced_on_disk(jax.value_and_grad(loss, has_aux=True), args, key, log=log)
    _physics.forget_stage_traces()
    return value_and_grad
