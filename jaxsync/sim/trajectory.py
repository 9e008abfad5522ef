"""What a rollout records: the ``Trajectory`` pytree and its row, built once for both engines."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Trajectory(NamedTuple):
    """What a rollout records, one row per control step (leading axis T).

    Times are the start of each control period. Forces on the object are
    those the contacts exerted during that period (from its constraint solve).
    """

    time: jax.Array  # (T,)
    qpos: jax.Array  # (T, nq) state at the start of the period
    qvel: jax.Array  # (T, nv)
    obj_pos: jax.Array  # (T, 3)
    obj_vel: jax.Array  # (T, 3)
    plan_obj_pos: jax.Array  # (T, 3) z_d
    plan_obj_acc: jax.Array  # (T, 3)
    plan_grip_force: jax.Array  # (T,) ramped f_d
    phase: jax.Array  # (T,) 0 close, 1 squeeze, 2 carry, 3 hold
    pad_pos: jax.Array  # (T, 2, 3) actual pad positions
    plan_pad_pos: jax.Array  # (T, 2, 3) x_id
    pad_normal: jax.Array  # (T, 2, 3) actual pad normals
    pad_forces: jax.Array  # (T, 2, 3) true force of each pad on the object
    wrist_wrench: jax.Array  # (T, 2, 6) compensated (noisy) wrist wrench the controller used
    torque: jax.Array  # (T, 14)
    offset: jax.Array  # (T, 2, 6) x_ik - x_id
    delta: jax.Array  # (T, 2, 6) absolute errors (eq. 12)
    impedance_offset: jax.Array  # (T, 2, 6) e_i
    at_torque_limit: jax.Array  # (T, 2) bool per arm: some joint's torque at its limit (at_torque_limit)


TORQUE_LIMIT_FRACTION = 0.999  # a joint whose commanded torque reaches this share of its limit is at it


def at_torque_limit(torque, limit):
    """(..., 2) per arm: whether some joint's commanded torque is at its limit
    (``TORQUE_LIMIT_FRACTION`` of it or beyond: the motor saturates).
    ``torque`` (..., 2 n) right arm's n then left's; ``limit`` (2 n,), N m.
    NumPy or JAX arrays alike."""
    sat = abs(torque) >= TORQUE_LIMIT_FRACTION * limit
    return sat.reshape(sat.shape[:-1] + (2, -1)).any(-1)


def row(
    t, qpos, qvel, obj_pos, obj_vel, plan, arms, pad_forces, torque, info, cstate, stack=jnp.stack, *, limit
) -> Trajectory:
    """One control step's row, from the plan, the sensed (right, left) arms, the
    controller's torque, info and new state (``stack``: ``np.stack`` on host
    data); ``limit`` the joints' torque limits (2 n,)."""
    return Trajectory(
        time=t,
        qpos=qpos,
        qvel=qvel,
        obj_pos=obj_pos,
        obj_vel=obj_vel,
        plan_obj_pos=plan.obj_pos,
        plan_obj_acc=plan.obj_acc,
        plan_grip_force=plan.grip_force,
        phase=plan.phase,
        pad_pos=stack([a.pad_pos for a in arms]),
        plan_pad_pos=plan.pad_pos,
        pad_normal=stack([a.pad_rot[:, 2] for a in arms]),
        pad_forces=pad_forces,
        wrist_wrench=stack([a.wrench for a in arms]),
        torque=torque,
        offset=info.offset,
        delta=info.delta,
        impedance_offset=cstate.impedance.offset,
        at_torque_limit=at_torque_limit(torque, limit),
    )
