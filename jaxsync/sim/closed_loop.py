"""The task meets a model and the controller, for either engine.

Per-model constants (the planned pad orientation, the rest posture, actuator
order, torque limits, which sensor entries are noisy), the initial posture,
the wrist-sensor noise, and one control period: plan -> reference ->
controller -> clipped torque. The MJX rollout (``jaxsync.sim.rollout``) and the
MuJoCo C rollout (``jaxsync.sim.rollout_mujoco``) both call these, so the task is
defined once.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxsync.control import controller as _controller
from jaxsync.control import schedule as _schedule
from jaxsync.control.controller import Reference
from jaxsync.physics.model import DualArmModel
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.scenario import Scenario

START_KEY = "approach"
REST_KEY = "grasp"


class Consts(NamedTuple):
    """Per-model constants, computed once in Python (never traced)."""

    pad_rot: np.ndarray  # (2, 3, 3) planned pad orientation (grasp keyframe)
    q_rest: np.ndarray  # (2, 7)
    qpos0: np.ndarray  # (nq,) start (approach keyframe)
    act_order: np.ndarray  # (14,) actuator index of each torque
    noise_scale_mask: np.ndarray  # (nsensordata, 2) 1 where the entry is a force / torque
    torque_limit: np.ndarray  # (14,)


def consts(model: DualArmModel, start: str = START_KEY) -> Consts:
    m, idx = model.mj_model, model.index
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos(REST_KEY)
    mujoco.mj_kinematics(m, d)
    pad_rot = np.stack([d.site_xmat[a.pad_site].reshape(3, 3) for a in idx.arms])
    q_rest = np.stack([d.qpos[list(a.qpos_adr)] for a in idx.arms])
    mask = np.zeros((m.nsensordata, 2))
    for a in idx.arms:
        mask[a.force_adr : a.force_adr + 3, 0] = 1
        mask[a.torque_adr : a.torque_adr + 3, 1] = 1
    act = np.array([i for a in idx.arms for i in a.actuator_ids])
    order = np.argsort(act)  # torque vector (arm-major) -> ctrl vector
    return Consts(
        pad_rot=pad_rot,
        q_rest=q_rest,
        qpos0=model.keyframe_qpos(start),
        act_order=order,
        noise_scale_mask=mask,
        torque_limit=m.actuator_ctrlrange[act, 1].copy(),
    )


def initial_qpos(model: DualArmModel, c: Consts, s: Scenario) -> jax.Array:
    """Arms at the start keyframe; the object on the stand, off the nominal centre by ``object_offset``."""
    qa = model.index.object_qpos_adr
    centre = _scenario.nominal_centre(s) + s.object_offset
    return jnp.asarray(c.qpos0).at[qa : qa + 3].set(centre)


def reference(s: Scenario, c: Consts, pl: _scenario.Plan) -> Reference:
    """The controller's reference from the plan: pad poses, velocities, accelerations, f_id, posture."""
    normals = jnp.asarray(c.pad_rot[:, :, 2])
    zeros = jnp.zeros((2, 3))
    return Reference(
        pad_pos=pl.pad_pos,
        pad_rot=jnp.asarray(c.pad_rot),
        pad_vel=jnp.concatenate([pl.pad_vel, zeros], axis=1),
        pad_acc=jnp.concatenate([pl.pad_acc, zeros], axis=1),
        wrench=_scenario.desired_wrench(s, pl, normals),
        q_rest=jnp.asarray(c.q_rest),
    )


def noise(s: Scenario, c: Consts, step: jax.Array) -> jax.Array:
    """(nsensordata,) white wrist-sensor noise of control step ``step`` (zero on other sensors)."""
    key = jax.random.wrap_key_data(jnp.asarray(s.noise_key, dtype=jnp.uint32))
    n = jax.random.normal(jax.random.fold_in(key, step), (c.noise_scale_mask.shape[0],))
    mask = jnp.asarray(c.noise_scale_mask)
    return n * (mask[:, 0] * s.force_noise + mask[:, 1] * s.torque_noise)


def _planned(gains, s, c: Consts, pad_start, t):
    normals = jnp.asarray(c.pad_rot[:, :, 2])
    pl = _scenario.plan(s, t, pad_start, normals)
    gains = _schedule.at(
        gains, jnp.stack(_scenario.phase_times(s)), t
    )  # constant gains pass through; a schedule blends its phases
    return gains, reference(s, c, pl), pl


def control(options, gains, s, c: Consts, cstate, arms, pad_start, t, dt):
    """Plan, desired wrench and one controller step, the torque clipped to the actuators' range."""
    gains, ref, pl = _planned(gains, s, c, pad_start, t)
    tau, cstate, info = _controller.step(options, gains, cstate, arms, ref, dt)
    tau = jnp.clip(tau, -c.torque_limit, c.torque_limit)
    return tau, cstate, info, pl


def control_position(options, gains, s, c: Consts, cstate, arms, pad_start, t, dt, command):
    """Plan, desired wrench and one controller step on position-controlled
    arms: the next integrated joint commands (2 n,), what the servo is sent
    (the same plus the plan's feed-forward,
    ``jaxsync.control.controller.command_feedforward``), the state, info,
    the plan and the reference the controller read."""
    gains, ref, pl = _planned(gains, s, c, pad_start, t)
    command, cstate, info = _controller.step_position(options, gains, cstate, arms, ref, dt, command, s.ft_filter)
    sent = _controller.sent_command(options, gains, arms, ref, command)
    return command, sent, cstate, info, pl, ref


def initial_command(model: DualArmModel, c: Consts) -> np.ndarray:
    """(2 n,) the arms' joint positions at the start: the first position command."""
    return np.asarray(c.qpos0)[[i for a in model.index.arms for i in a.qpos_adr]]
