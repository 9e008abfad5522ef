"""The tuning cost over one rollout (docs/tuning.md). Built from the metric
definitions of ``jaxsync.sim.metrics``: nothing is defined twice."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxsync._errors import ConfigError
from jaxsync.sim import metrics as _metrics


class CostWeights(NamedTuple):
    """The weight of each term of the tuning cost (docs/tuning.md).

    Example:
      >>> w = CostWeights(grip=3.0)
      >>> total = cost(traj, s, w)  # doctest: +SKIP
    """

    resultant_ms: float = 1.0  # mean square resultant force over the settled window, per (0.01 N)^2
    # smooth (log-sum-exp) peak of the resultant, per 0.01 N, at peak_temperature: a temperature well below
    # the peaks tuning reaches (0.4-0.6 mN on the paper model), so that the term is their peak and not their
    # mean, and a weight that keeps it the cost's largest term there (docs/convergence.md: 2 mN and 1 left
    # the tuned peak free to move 1.4x between starts a millionth apart)
    resultant_peak: float = 5.0
    grip: float = 10.0  # |relative error| of the mean grip force (the metric, smoothed at 0.01 %), per 1 %
    sync: float = 0.1  # mean square synchronisation error, per (1 mm)^2
    effort: float = 1e-4  # mean |tau|^2, per (10 N m)^2
    peak_temperature: float = 1e-4  # N, of the smooth peak
    # relative: the grip term is sqrt(e^2 + s^2), |e| above s, quadratic (flat) below it
    grip_smooth: float = 1e-4
    # opt-in: the pads' friction margin at its worst in carry and hold, short of
    # FRICTION_MARGIN of the nominal grip's cone, per that share (0: not computed)
    friction_margin: float = 0.0


RESULTANT_SCALE = 0.01  # N
RESULTANT_FLOOR2 = 1e-12  # N^2, under the root of the resultant's norm (smooth at zero)
GRIP_SCALE = 0.01  # relative
GRIP_SMOOTH = CostWeights().grip_smooth  # relative: the smooth metric's |x| ~ sqrt(x^2 + s^2)
SYNC_SCALE = 1e-3  # m
EFFORT_SCALE = 10.0  # N m


SYNC_FLOOR2 = 1e-18  # m^2, under the root of the smooth rms synchronisation error
FRICTION_MARGIN = 0.5  # share of mu f_d the friction margin is kept above
FRICTION_SOFTNESS = 0.05  # of that share: softplus width, and the smooth worst's temperature


def _settled(traj, s):
    """What the cost and the smooth metrics read off one rollout: the settled
    window's mask and size, the resultant's norm, the relative error of the
    window's mean grip force and the synchronisation error."""
    mask = _metrics.settled_mask(traj.time, s)
    n = jnp.maximum(mask.sum(), 1.0)
    res = _metrics.resultant_force(traj.pad_forces, traj.plan_obj_acc, s.object_mass)
    res_norm = _metrics.safe_norm(res, floor2=RESULTANT_FLOOR2)
    # the metric's grip error: of the window's mean grip force (noise averages out)
    mean_grip = jnp.sum(mask * _metrics.grip_force(traj.pad_forces, traj.pad_pos)) / n
    grip_err = (mean_grip - s.grip_force) / s.grip_force
    return mask, n, res_norm, grip_err, _metrics.sync_error(traj.delta)


def smooth_metrics(traj, s, temperature: float = CostWeights().peak_temperature) -> dict[str, jax.Array]:
    """The headline metrics of one rollout in the smooth forms the cost uses
    (differentiable everywhere): the settled peak resultant (log-sum-exp peak
    at ``temperature``, N), the grip-force error (sqrt(e^2 + s^2), relative)
    and the rms synchronisation error over the settled window (m)."""
    mask, n, res_norm, grip_err, sync = _settled(traj, s)
    return {
        "settled_peak_resultant_N": _metrics.smooth_max(res_norm, mask, temperature),
        "grip_force_error_rel": jnp.sqrt(grip_err**2 + GRIP_SMOOTH**2),
        "sync_error_rms_m": jnp.sqrt(jnp.sum(mask * sync**2) / n + SYNC_FLOOR2),
    }


def cost_terms(traj, s, w: CostWeights) -> dict[str, jax.Array]:
    """Each weighted term (scalars). ``traj`` a Trajectory, ``s`` its Scenario.

    A rollout that loses the object (``jaxsync.sim.metrics.lost_mask``) costs
    what holding nothing costs (:func:`held_nothing_terms`), a constant of the
    scenario and the plan with no gradient: a dropped object's own cost is
    as large (its weight unsupported: 2.4e5 for 0.5 kg) and moves erratically
    with the gains, and its gradient, which says nothing about holding the
    object, would swamp the batch's. A step that drops a held scenario still
    raises the cost by that much, and one that saves a dropped one lowers it.
    """
    terms = _terms(traj, s, w)
    lost = _metrics.lost_mask(traj).any()
    nothing = held_nothing_terms(traj, s, w)
    out = {k: jnp.where(lost, nothing[k], v) for k, v in terms.items()}
    if w.friction_margin:  # read before any loss: a lost rollout's gradient toward holding on
        out["friction_margin"] = w.friction_margin * friction_shortfall(traj, s)
    return out


def friction_shortfall(traj, s) -> jax.Array:
    """How far the pads' friction margin falls short of ``FRICTION_MARGIN``,
    at its worst over carry and hold before the object is lost (smooth; 0
    while the margin stays above it, 1 on the cone's edge, more in slip).

    A pad's margin is mu f_n - |f_t|, what the friction cone has left, as a
    share of mu f_d, the nominal grip's cone (1: no tangential load; about
    0.75 holding a 0.5 kg ball at 10 N and mu = 1). It falls as the pads part
    or the load grows, before the object slips out: a gradient toward
    holding on where a drop costs a constant with none (:func:`cost_terms`).
    """
    f_n = _metrics.normal_forces(traj.pad_forces, traj.pad_normal)  # (T, 2)
    f_t = traj.pad_forces - f_n[..., None] * traj.pad_normal
    margin = (s.friction * f_n - _metrics.safe_norm(f_t, floor2=RESULTANT_FLOOR2)) / (s.friction * s.grip_force)
    t = FRICTION_SOFTNESS * FRICTION_MARGIN
    short = t * jax.nn.softplus((FRICTION_MARGIN - jnp.min(margin, -1)) / t)  # the worse pad
    held = jnp.cumsum(_metrics.lost_mask(traj)) == 0
    mask = (traj.phase >= 2) & held
    some = mask.any()  # none where lost at the carry's first sample: read one sample, weigh it 0
    mask = mask | (~some & (jnp.arange(mask.shape[0]) == 0))
    return some * _metrics.smooth_max(short, mask, t) / FRICTION_MARGIN


def held_nothing_terms(traj, s, w: CostWeights) -> dict[str, jax.Array]:
    """The terms of ``traj``'s plan with no force at the pads (the object's
    planned weight and motion borne by nothing, the grip 100 % short),
    synchronised and effortless: gain-independent (no gradient)."""
    empty = traj._replace(
        pad_forces=jnp.zeros_like(traj.pad_forces), delta=jnp.zeros_like(traj.delta), torque=jnp.zeros_like(traj.torque)
    )
    return jax.lax.stop_gradient(_terms(empty, s, w))


def _terms(traj, s, w: CostWeights) -> dict[str, jax.Array]:
    mask, n, res_norm, grip_err, sync = _settled(traj, s)
    return {
        "resultant_ms": w.resultant_ms * jnp.sum(mask * res_norm**2) / n / RESULTANT_SCALE**2,
        "resultant_peak": w.resultant_peak * _metrics.smooth_max(res_norm, mask, w.peak_temperature) / RESULTANT_SCALE,
        # the metric's statistic (mean |error| over scenarios), not its square:
        # a squared term is flat near the small errors the task starts from
        "grip": w.grip * jnp.sqrt(grip_err**2 + w.grip_smooth**2) / GRIP_SCALE,
        "sync": w.sync * jnp.sum(mask * sync**2) / n / SYNC_SCALE**2,
        "effort": w.effort * jnp.mean(jnp.sum(traj.torque**2, -1)) / EFFORT_SCALE**2,
    }


def cost(traj, s, w: CostWeights) -> jax.Array:
    return sum(cost_terms(traj, s, w).values())


def parse_weights(items) -> CostWeights:
    """CostWeights from "NAME=VALUE" strings over the defaults (the value checks: ``TuneConfig.validate``).

    Example:
      >>> parse_weights(["grip=3"]).grip
      3.0
    """
    w = CostWeights()
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in CostWeights._fields:
            raise ConfigError(
                f"a cost weight must be NAME=VALUE with NAME one of {list(CostWeights._fields)}, got {item!r}",
                inputs=("weights",),
            )
        try:
            w = w._replace(**{name: float(value)})
        except ValueError:
            raise ConfigError(f"cost weight {name}: not a number: {value!r}", inputs=("weights",)) from None
    return w
