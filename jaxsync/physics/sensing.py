"""From an MJX state to everything the controllers need (pure JAX).

Conventions (``docs/equations.md``): world frame; 6-vectors are
``[linear; angular]`` (force then torque, velocity then angular velocity),
matching the stacked Jacobian ``J = [J_p; J_r]`` of the pad frame. The wrist
wrench ``f_i`` is the wrench the *object exerts on arm i*, about the pad-frame
origin (controller.md's notation).

``sense`` expects ``d`` after :func:`jaxsync.physics.step.before_control` (or
``mjx.forward``): kinematics and dynamics are those of the current state; the
force/torque sensors and body accelerations come from the last constraint
solve (one physics step earlier inside a rollout).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from mujoco import mjx

from jaxsync.physics import step as _physics
from jaxsync.physics.model import ArmIndex, ModelIndex


class ArmState(NamedTuple):
    """What one arm's controller reads. Shapes for one environment."""

    q: jax.Array  # (7,) joint angles
    qd: jax.Array  # (7,) joint velocities
    pad_pos: jax.Array  # (3,) pad-frame origin (pad face centre), world
    pad_rot: jax.Array  # (3, 3) pad-frame rotation; column 2 is the outward pad normal
    pad_vel: jax.Array  # (6,) pad twist J qd, [linear; angular]
    jac: jax.Array  # (6, 7) geometric Jacobian of the pad frame, [J_p; J_r]
    jac_dot_qd: jax.Array  # (6,) dJ/dt qd
    mass: jax.Array  # (7, 7) arm block of the joint-space mass matrix
    bias: jax.Array  # (7,) c + g: Coriolis, centrifugal and gravity (qfrc_bias), no passive forces
    wrist_raw: jax.Array  # (6,) force/torque sensor reading, sensor frame
    wrench: jax.Array  # (6,) compensated wrist wrench f_i: object on arm, about pad origin, world


class ObjectState(NamedTuple):
    """The object, and the true pad contact forces (metrics only)."""

    pos: jax.Array  # (3,) centre of mass
    quat: jax.Array  # (4,) orientation, w x y z
    linvel: jax.Array  # (3,) world
    angvel: jax.Array  # (3,) world
    pad_forces: jax.Array  # (2, 3) force of the right and left pad on the object, world
    pad_distance: jax.Array  # (2,) signed pad-object distance (negative: penetration)


class Sensed(NamedTuple):
    right: ArmState
    left: ArmState
    obj: ObjectState


def compensate_wrist_wrench(
    raw: jax.Array,
    ft_rot: jax.Array,
    ft_pos: jax.Array,
    origin: jax.Array,
    cinert: jax.Array,
    cvel: jax.Array,
    cacc: jax.Array,
    pad_pos: jax.Array,
) -> jax.Array:
    """Wrist sensor reading (6,) -> wrench of the object on the arm about the pad (6,).

    MuJoCo's force/torque sensor reads the wrench that the parent exerts on the
    end-effector body (``cfrc_int``), in the sensor frame. For the end
    effector, a leaf body: parent wrench + contact wrench = inertial wrench
    (I a + v x* I v, gravity included via ``cacc``). So the contact wrench is
    the inertial wrench minus the sensed one; this removes the end effector's
    weight and its inertia at the current acceleration.

    Args:
      raw: (6,) sensor force and torque, sensor frame.
      ft_rot, ft_pos: (3, 3), (3,) sensor site pose.
      origin: (3,) where MuJoCo's com-based spatial vectors act
        (``subtree_com`` of the end effector's root body).
      cinert, cvel, cacc: (10,), (6,), (6,) the end effector's com-based
        inertia, velocity and acceleration.
      pad_pos: (3,) the pad-frame origin, where the result's torque is taken.
    """
    f_int = ft_rot @ raw[:3]
    t_int = ft_rot @ raw[3:] + jnp.cross(ft_pos - origin, f_int)
    ext = _physics.inertial_wrench(cinert, cvel, cacc) - jnp.concatenate([t_int, f_int])
    force = ext[3:]
    torque = ext[:3] + jnp.cross(origin - pad_pos, force)
    return jnp.concatenate([force, torque])


def sense_arm(m: mjx.Model, d: mjx.Data, arm: ArmIndex, mass_full: jax.Array, passes: str = "mjx") -> ArmState:
    dofs = jnp.array(arm.dof_adr)
    pad_pos = d.site_xpos[arm.pad_site]
    jacp, jacr = _physics.jac(m, d, pad_pos, arm.ee_body, passes)
    jac = jnp.concatenate([jacp.T, jacr.T])  # (6, nv)
    djp, djr = _physics.jac_dot(m, d, pad_pos, arm.ee_body, passes)
    jac_dot_qd = jnp.concatenate([djp.T @ d.qvel, djr.T @ d.qvel])
    qd = d.qvel[dofs]
    raw = jnp.concatenate(
        [d.sensordata[arm.force_adr : arm.force_adr + 3], d.sensordata[arm.torque_adr : arm.torque_adr + 3]]
    )
    return ArmState(
        q=d.qpos[jnp.array(arm.qpos_adr)],
        qd=qd,
        pad_pos=pad_pos,
        pad_rot=d.site_xmat[arm.pad_site],
        pad_vel=jac @ d.qvel,
        jac=jac[:, dofs],
        jac_dot_qd=jac_dot_qd,
        mass=mass_full[dofs][:, dofs],
        bias=d.qfrc_bias[dofs],
        wrist_raw=raw,
        wrench=compensate_wrist_wrench(
            raw,
            d.site_xmat[arm.ft_site],
            d.site_xpos[arm.ft_site],
            d.subtree_com[arm.root_body],
            d._impl.cinert[arm.ee_body],
            d.cvel[arm.ee_body],
            d._impl.cacc[arm.ee_body],
            pad_pos,
        ),
    )


def sense_object(m: mjx.Model, d: mjx.Data, index: ModelIndex) -> ObjectState:
    qa, va = index.object_qpos_adr, index.object_dof_adr
    quat = d.qpos[qa + 3 : qa + 7]
    rot = d.xmat[index.object_body]
    pad_forces = jnp.stack([_physics.contact_force_on(m, d, arm.contact_id, arm.object_is_geom1) for arm in index.arms])
    return ObjectState(
        pos=d.qpos[qa : qa + 3],
        quat=quat,
        linvel=d.qvel[va : va + 3],
        angvel=rot @ d.qvel[va + 3 : va + 6],  # free-joint angular velocity is in the body frame
        pad_forces=pad_forces,
        pad_distance=jnp.stack([_physics.contact_distance(d, arm.contact_id) for arm in index.arms]),
    )


def sense(m: mjx.Model, d: mjx.Data, index: ModelIndex, passes: str = "mjx") -> Sensed:
    """Every controller input and the object's true state, as one pytree.

    Args:
      m: MJX model (may carry batched or traced parameters).
      d: MJX data after the position and velocity stages (see module doc).
      index: static ids from :func:`jaxsync.load_model` (``model.index``).
      passes: the Jacobians' tree passes (``jaxsync.physics.step.PASSES``; the
        same values): ``"tree"`` in gradient programs.
    """
    mass_full = _physics.full_mass_matrix(m, d)
    return Sensed(
        right=sense_arm(m, d, index.right, mass_full, passes),
        left=sense_arm(m, d, index.left, mass_full, passes),
        obj=sense_object(m, d, index),
    )
