"""Metrics of a rollout, defined once (docs/metrics.md). Pure JAX, differentiable.

Forces are those of the pads on the object (world frame). The settled window
is the hold phase after ``scenario.settle_time``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.sim.scenario import GRAVITY, Scenario, phase_times
from jaxsync.sim.trajectory import at_torque_limit

# A rollout counts as a drop when, during carry or hold, the object is this
# far from its planned position (it fell, or slipped out of the grasp).
DROP_DISTANCE = 0.03

# A rollout counts as chattering when a pad's normal force changes, from one
# control step to the next, by more than this (RMS over the settled window).
# A held ball's force follows the sensor noise (~0.1-0.3 N per step on the
# paper model's default task); a discrete force loop past its stability limit
# flips the force by 10 N and more every step (docs/metrics.md).
CHATTER_THRESHOLD_N = 1.0

# The first impact: the window after a pad first touches the object (its
# normal force above IMPACT_CONTACT_N) over which its peak counts.
IMPACT_CONTACT_N = 0.05
IMPACT_WINDOW_S = 0.1


def normal_forces(pad_forces: jax.Array, pad_normal: jax.Array) -> jax.Array:
    """(T, 2) each pad's force on the object along the pad normal (pushing: positive).

    Args: pad_forces (T, 2, 3); pad_normal (T, 2, 3) unit normals pointing into the object.
    """
    return jnp.einsum("tij,tij->ti", pad_forces, pad_normal)


def safe_norm(x: jax.Array, axis: int = -1, floor2: float = 0.0) -> jax.Array:
    """sqrt(|x|^2 + floor2) along ``axis``, with a zero (not NaN) gradient at
    x = 0 when ``floor2`` is 0 (MJX's ``math.norm`` pattern: the exact norm).
    Every norm of a force or an error goes through here: the metrics take the
    exact norm, the tuning cost a floor of 1e-12 N^2 (a smooth minimum of
    1e-6 N, far below its 0.01 N scale).

    Example:
      >>> float(safe_norm(jnp.array([3.0, 4.0])))
      5.0
    """
    n2 = jnp.sum(x * x, axis=axis) + floor2
    zero = n2 == 0.0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, n2)))


def _unit(v: jax.Array) -> jax.Array:
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    return v / jnp.sqrt(jnp.where(n2 > 1e-24, n2, 1.0))


def grip_force(pad_forces: jax.Array, pad_pos: jax.Array) -> jax.Array:
    """(T,) internal (squeeze) force: the part of the pad forces in the null
    space of the grasp matrix. For two opposing contacts it is the squeeze
    along the line between them, u = (p_l - p_r)/|p_l - p_r|:
    grip = (f_r . u - f_l . u) / 2.

    Args: pad_forces (T, 2, 3) rows right, left; pad_pos (T, 2, 3).
    """
    u = _unit(pad_pos[:, 1] - pad_pos[:, 0])
    return 0.5 * (jnp.sum(pad_forces[:, 0] * u, -1) - jnp.sum(pad_forces[:, 1] * u, -1))


def resultant_force(pad_forces: jax.Array, plan_obj_acc: jax.Array, object_mass: jax.Array) -> jax.Array:
    """(T, 3) f_z = J_o^T f (eq. 7), the vector sum of the pad forces, minus
    the force the planned motion of the object needs, m (z''_d - g)."""
    return pad_forces.sum(axis=1) - object_mass * (plan_obj_acc - jnp.asarray(GRAVITY))


def internal_force_error(pad_forces: jax.Array, pad_pos: jax.Array, grip_force_d) -> jax.Array:
    """(T,) |(f_r - f_l)/2 - f_d u|, N: the internal force (the part of the
    pad forces that cancels in their sum) against the desired squeeze f_d
    along u = (p_l - p_r)/|p_l - p_r|. Beside the grip error's squeeze it
    counts the tangential forces the pads fight each other with."""
    u = _unit(pad_pos[:, 1] - pad_pos[:, 0])
    internal = 0.5 * (pad_forces[:, 0] - pad_forces[:, 1])
    return safe_norm(internal - grip_force_d * u)


def sync_error(delta: jax.Array) -> jax.Array:
    """(T,) |delta_r - delta_l| of the position part (eq. 13), m. delta (T, 2, 6)."""
    return safe_norm(delta[:, 0, :3] - delta[:, 1, :3])


def settled_mask(time: jax.Array, s: Scenario) -> jax.Array:
    """(T,) 1.0 inside the settled hold window."""
    _, _, t_hold = phase_times(s)
    return (time >= t_hold + s.settle_time).astype(time.dtype)


def smooth_max(x: jax.Array, mask: jax.Array, temperature: jax.Array) -> jax.Array:
    """A log-sum-exp peak of x over the mask (for costs): -> max as temperature -> 0."""
    z = jnp.where(mask > 0, x / temperature, -jnp.inf)
    return temperature * (jax.nn.logsumexp(z) - jnp.log(jnp.maximum(mask.sum(), 1.0)))


class Metrics(NamedTuple):
    """Scalars of one rollout (vmap gives a batch)."""

    settled_peak_resultant_N: jax.Array
    rms_resultant_N: jax.Array
    mean_grip_force_N: jax.Array
    grip_force_error_rel: jax.Array  # |mean grip - f_d| / f_d, settled window
    grip_force_error_rel_max: jax.Array  # max |grip - f_d| / f_d, settled window
    sync_error_rms_m: jax.Array
    internal_force_error_rms_N: jax.Array  # RMS of internal_force_error, settled window
    object_error_rms_m: jax.Array
    torque_effort: jax.Array  # mean |tau|^2 over the rollout, N^2 m^2
    dropped: jax.Array  # bool
    drop_time_s: jax.Array  # first time the object was lost, nan if never
    nonfinite: jax.Array  # bool
    nonfinite_time_s: jax.Array
    force_chatter_N: jax.Array  # RMS step-to-step change of a pad's normal force, settled window (worse pad)
    chattering: jax.Array  # bool: force_chatter_N > CHATTER_THRESHOLD_N
    first_impact_peak_N: jax.Array  # largest normal pad force in the first IMPACT_WINDOW_S of contact
    torque_limit_share_right: jax.Array  # share of control steps with a joint of the arm at its torque limit
    torque_limit_share_left: jax.Array


def torque_limit_share(torque, limits) -> np.ndarray:
    """(2,) per arm (right, left): the share of control steps at which some
    joint's commanded torque is at its limit (``jaxsync.sim.trajectory.at_torque_limit``).
    ``torque`` (T, 2 n) as a Trajectory records it; ``limits`` (2, n), N m."""
    limits = np.asarray(limits, dtype=float).reshape(-1)
    return at_torque_limit(np.asarray(torque, dtype=float), limits).mean(0)


def force_chatter(pad_forces: jax.Array, pad_normal: jax.Array, mask: jax.Array) -> jax.Array:
    """() the RMS over the masked window of each pad's step-to-step change in
    normal force, the larger of the two pads' (N)."""
    fn = normal_forces(pad_forces, pad_normal)
    d = fn[1:] - fn[:-1]
    m = (mask[1:] * mask[:-1])[:, None]
    return jnp.sqrt(jnp.max(jnp.sum(m * d**2, 0) / jnp.maximum(jnp.sum(m), 1.0)))


def impact_mask(time: jax.Array, normal: jax.Array) -> jax.Array:
    """(T, 2) 1.0 inside each pad's first-impact window: from its first step
    with a normal force above ``IMPACT_CONTACT_N`` for ``IMPACT_WINDOW_S``
    (zero for a pad that never touches). ``normal`` (T, 2) from :func:`normal_forces`."""
    touch = normal > IMPACT_CONTACT_N
    t0 = jnp.where(touch.any(0), time[jnp.argmax(touch, axis=0)], jnp.inf)
    inside = (time[:, None] >= t0[None]) & (time[:, None] < t0[None] + IMPACT_WINDOW_S)
    return inside.astype(normal.dtype)


def first_impact_peak(pad_forces: jax.Array, pad_normal: jax.Array, time: jax.Array) -> jax.Array:
    """() the largest normal pad force inside either pad's first-impact window (N)."""
    fn = normal_forces(pad_forces, pad_normal)
    return jnp.max(jnp.where(impact_mask(time, fn) > 0, fn, 0.0))


def _masked_mean(x, mask):
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def _first_time(flag, time):
    return jnp.where(flag.any(), time[jnp.argmax(flag)], jnp.nan)


def _finite(traj) -> jax.Array:
    """(T,) the joint positions and pad forces finite."""
    return jnp.isfinite(traj.qpos).all(-1) & jnp.isfinite(traj.pad_forces).reshape(len(traj.time), -1).all(-1)


def lost_mask(traj) -> jax.Array:
    """(T,) the object lost: once carried (phase 2 on), more than DROP_DISTANCE
    from its planned position, or the state no longer finite. ``dropped`` is
    its ``any()``."""
    return _lost(traj.phase, safe_norm(traj.obj_pos - traj.plan_obj_pos), _finite(traj))


def _lost(phase, obj_err, finite) -> jax.Array:
    return (phase >= 2) & ((obj_err > DROP_DISTANCE) | ~finite)


def summarize(traj, s: Scenario) -> Metrics:
    """All metrics of one trajectory (a ``jaxsync.Trajectory``); ``jax.vmap`` it for a batch.

    Example:
      >>> traj = jaxsync.rollout(model, jaxsync.default_gains(), s, duration=1.7)  # doctest: +SKIP
      >>> m = summarize(traj, s)
      >>> float(m.settled_peak_resultant_N), bool(m.dropped)
    """
    mask = settled_mask(traj.time, s)
    res = safe_norm(resultant_force(traj.pad_forces, traj.plan_obj_acc, s.object_mass))
    grip = grip_force(traj.pad_forces, traj.pad_pos)
    grip_err = jnp.abs(grip - s.grip_force) / s.grip_force
    mean_grip = _masked_mean(grip, mask)
    obj_err = safe_norm(traj.obj_pos - traj.plan_obj_pos)
    finite = _finite(traj)
    lost = _lost(traj.phase, obj_err, finite)
    return Metrics(
        settled_peak_resultant_N=jnp.max(jnp.where(mask > 0, res, 0.0)),
        rms_resultant_N=jnp.sqrt(_masked_mean(res**2, mask)),
        mean_grip_force_N=mean_grip,
        grip_force_error_rel=jnp.abs(mean_grip - s.grip_force) / s.grip_force,
        grip_force_error_rel_max=jnp.max(jnp.where(mask > 0, grip_err, 0.0)),
        sync_error_rms_m=jnp.sqrt(_masked_mean(sync_error(traj.delta) ** 2, mask)),
        internal_force_error_rms_N=jnp.sqrt(
            _masked_mean(internal_force_error(traj.pad_forces, traj.pad_pos, s.grip_force) ** 2, mask)
        ),
        object_error_rms_m=jnp.sqrt(_masked_mean(obj_err**2, mask)),
        torque_effort=jnp.mean(jnp.sum(traj.torque**2, -1)),
        dropped=lost.any(),
        drop_time_s=_first_time(lost, traj.time),
        nonfinite=~finite.all(),
        nonfinite_time_s=_first_time(~finite, traj.time),
        force_chatter_N=(chatter := force_chatter(traj.pad_forces, traj.pad_normal, mask)),
        chattering=chatter > CHATTER_THRESHOLD_N,
        first_impact_peak_N=first_impact_peak(traj.pad_forces, traj.pad_normal, traj.time),
        torque_limit_share_right=jnp.mean(traj.at_torque_limit[:, 0].astype(traj.time.dtype)),
        torque_limit_share_left=jnp.mean(traj.at_torque_limit[:, 1].astype(traj.time.dtype)),
    )


def series(traj, s: Scenario) -> dict[str, jax.Array]:
    """The curves that plots and CSVs show, keyed by column name.

    Example:
      >>> curves = series(traj, s)  # doctest: +SKIP
      >>> curves["resultant_force_N"].shape  # doctest: +SKIP
      (T,)
    """
    fn = normal_forces(traj.pad_forces, traj.pad_normal)
    res = resultant_force(traj.pad_forces, traj.plan_obj_acc, s.object_mass)
    return {
        "time_s": traj.time,
        "right_normal_force_N": fn[:, 0],
        "left_normal_force_N": fn[:, 1],
        "grip_force_N": grip_force(traj.pad_forces, traj.pad_pos),
        "resultant_force_N": safe_norm(res),
        "resultant_x_N": res[:, 0],
        "resultant_y_N": res[:, 1],
        "resultant_z_N": res[:, 2],
        "sync_error_m": sync_error(traj.delta),
        "object_error_m": safe_norm(traj.obj_pos - traj.plan_obj_pos),
        "phase": traj.phase,
    }


BOOL_METRICS = ("dropped", "nonfinite", "chattering")


def to_arrays(m: Metrics) -> dict[str, np.ndarray]:
    """Metrics (one rollout or a batch) as host numpy arrays by name; the flags as bool."""
    return {k: np.asarray(v).astype(bool) if k in BOOL_METRICS else np.asarray(v) for k, v in m._asdict().items()}


def to_dict(m: Metrics) -> dict:
    """One rollout's metrics as plain Python for JSON: floats, bools for the
    flags, None for NaN (e.g. ``drop_time_s`` when nothing dropped)."""
    out = {}
    for k, v in to_arrays(m).items():
        v = v.item()
        out[k] = None if isinstance(v, float) and math.isnan(v) else v
    return out


def drop_time(m) -> float | None:
    """When the object was lost (s), None if it was held; ``m`` Metrics or their to_dict()."""
    get = m.get if isinstance(m, dict) else lambda k: getattr(m, k)
    if not bool(np.asarray(get("dropped"))):
        return None
    t = get("drop_time_s")
    return float(np.asarray(t)) if t is not None else float("nan")
