"""ros2_controllers' admittance rule in jaxsync's closed loop: the controller
``"ros2_admittance"``, position-controlled arms only.

Each arm runs ``jaxsync.control.ros2_admittance`` (the port of
``AdmittanceRule::update``) as a deployment would, one instance per arm, with
these choices (docs/ros2-rule.md, "ros2_controllers' rule in the loop"):

- The joint reference the rule offsets is the plan without compliance: q_ref,
  integrated with the position stack's CLIK (``jaxsync.control.joint_space.
  command_rate``: same gain lambda = 2 kp_pos / kd_pos, damped least squares
  alone, the plan's twist not refined, null space toward q_rest) toward the
  planned pad pose (ref.pad_pos, ref.pad_rot, ref.pad_vel; no offsets). It
  lives in the controller state; its velocity is the CLIK rate and its
  acceleration 0.
- The pad is the F/T, control and gravity-compensation frame; the chain's base
  is the world (rot_world_base = I). ``Kinematics``: jacobian = the sensed
  pad Jacobian (world frame, at the pad), trans_base_ft = the sensed pad pose,
  rot_base_control = rot_base_cog = the sensed pad rotation.
- ref_trans_base_ft, the pad pose at q_ref: the controller sees the sensed arm,
  not the model, so it is the sensed pose carried back to q_ref to first
  order, p - J_v (q - q_ref) and exp(-J_w (q - q_ref)) R (exact up to
  O(|q - q_ref|^2): the offsets are milliradians). The same estimate is the
  pad pose the CLIK closes on for q_ref, so q_ref follows the plan, not the
  compliant pad (a CLIK on the sensed pad would integrate the compliance away).
- measured_wrench: the pad's compensated wrench f_i (object on arm, about the
  pad) in the pad frame. jaxsync removed the end effector's weight already, so
  CoG.force = 0. wrench_reference = -f_id in the pad frame (the C++ adds it to
  the measurement: at rest f_i = f_id + K X). Humble has no wrench reference:
  there the grip force is not held (the rule sees f_i alone).
- AdmittanceParams as the ros2-admittance export writes them (``jaxsync.io.
  export``): stiffness = imp_stiffness (the pad frame is the control frame),
  the mass per axis of the base where the release applies it there (Jazzy,
  Kilted, Humble: each pad axis's mass on the world axis it lies along in
  the plan, ``jaxsync.io.ros2_target.mass_in_base``), damping_ratio =
  imp_damping / (2 sqrt(M K)) with the mass as written, so that the rule's
  D is the tuned one (0 on an axis with K = 0: the rule has no damping
  there, as deployed), joint_damping 0, filter_coefficient 1.0, alpha =
  ``COMMAND_ALPHA``.
- The joint command is the rule's command.positions (q_ref + its joint offset).

``"ros2_synchronous"`` is the same rule with the reference's target carrying
the paper's coupling less the rule's own offset (:func:`coupled_reference`);
``"ros2_coupled"`` the rule with the coupling family of
``jaxsync.control.coupling`` (:func:`family_target`), entering through the
reference's target or onto the rule's reference joints.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxsync.control import coupling as _coupling
from jaxsync.control import joint_space as _joint_space
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import so3 as _so3
from jaxsync.control import sync as _sync
from jaxsync.control.names import (
    DEFAULT_DISTRO,
    check_actuation,  # noqa: F401 (re-exported)
)
from jaxsync.physics.sensing import ArmState


class Ros2State(NamedTuple):
    """q_ref (2, n): each arm's reference joint positions; rule: the two arms'
    ``AdmittanceState``, every leaf stacked (2, ...) right then left."""

    q_ref: jax.Array
    rule: _ra.AdmittanceState


def init(q0: jax.Array) -> Ros2State:
    """The state at the start: q_ref at the arms' joint positions ``q0`` (2 n,)
    (right arm's n, then left's), the rules at zero offset."""
    q0 = jnp.asarray(q0)
    n = q0.shape[0] // 2
    one = _ra.admittance_rule(DEFAULT_DISTRO).init(n)
    return Ros2State(q_ref=q0.reshape(2, n), rule=jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), one))


def params(gains, arm: int, pad_rot=None, distro: str = DEFAULT_DISTRO, ft_filter=1.0) -> _ra.AdmittanceParams:
    """The rule's parameters of arm ``arm`` (0 right, 1 left) from jaxsync's
    gains, traced (``make_params`` checks eagerly; these are the export's).
    ``pad_rot`` (3, 3): the planned pad rotation in the base (the world),
    which places each pad axis's mass on a base axis where ``distro``
    applies the mass there; None: the mass in the pad frame's order.
    ``ft_filter``: ft_sensor.filter_coefficient (the scenario's)."""
    m, d, k = gains.imp_mass[arm], gains.imp_damping[arm], gains.imp_stiffness[arm]
    if pad_rot is not None and not _ra.MASS_IN_CONTROL_FRAME[distro]:
        along = jnp.argmax(jnp.abs(pad_rot), axis=1)  # base axis i lies along pad axis along[i]
        m = m[jnp.concatenate([along, along + 3])]
    mk = m * k
    positive = mk > 0.0
    zeta = jnp.where(positive, d / (2.0 * jnp.sqrt(jnp.where(positive, mk, 1.0))), 0.0)
    zero = jnp.zeros_like(m[0])
    return _ra.AdmittanceParams(
        mass=m,
        damping_ratio=zeta,
        stiffness=k,
        joint_damping=zero,
        filter_coefficient=zero + ft_filter,
        alpha=zero + _joint_space.COMMAND_ALPHA,
        cog_pos=jnp.zeros(3, m.dtype),
        cog_force=zero,
    )


def pose_at(arm: ArmState, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The pad pose at joints ``q``, from the sensed pose and Jacobian to first
    order: (p - J_v (q_s - q), exp(-J_w (q_s - q)) R), world frame."""
    dx = arm.jac @ (arm.q - q)
    return arm.pad_pos - dx[:3], _so3.exp(-dx[3:]) @ arm.pad_rot


def kinematics(arm: ArmState, q_ref: jax.Array) -> _ra.Kinematics:
    """What the rule asks its kinematics plugin, the pad as F/T, control and
    gravity frame and the world as the chain's base."""
    ref_pos, ref_rot = pose_at(arm, q_ref)
    return _ra.Kinematics(
        jacobian=arm.jac,
        trans_base_ft=_transform(arm.pad_pos, arm.pad_rot),
        ref_trans_base_ft=_transform(ref_pos, ref_rot),
        rot_world_base=jnp.eye(3, dtype=arm.pad_rot.dtype),
        rot_base_control=arm.pad_rot,
        rot_base_cog=arm.pad_rot,
    )


def _transform(pos: jax.Array, rot: jax.Array) -> jax.Array:
    return jnp.eye(4, dtype=rot.dtype).at[:3, :3].set(rot).at[:3, 3].set(pos)


def _in_pad(rot: jax.Array, wrench: jax.Array) -> jax.Array:
    return jnp.concatenate([rot.T @ wrench[:3], rot.T @ wrench[3:]])


def reference_step(gains, arm: ArmState, q_ref: jax.Array, ref, i: int, dt: float) -> tuple[jax.Array, jax.Array]:
    """q_ref one period on: the CLIK of the position stack toward arm ``i``'s
    planned pad pose, closed on the pad pose at q_ref (:func:`pose_at`).
    Returns (q_ref', its rate)."""
    pos, rot = pose_at(arm, q_ref)
    rate = _joint_space.command_rate(
        arm._replace(pad_pos=pos, pad_rot=rot),
        q_ref,
        ref.pad_pos[i],
        ref.pad_rot[i],
        ref.pad_vel[i],
        ref.q_rest[i],
        gains.kp_pos,
        gains.kd_pos,
        gains.kp_null,
        gains.kd_null,
    )
    return q_ref + dt * rate, rate


def _errors(state: Ros2State, arms, ref):
    """(2, 6) each: the sensed pads' absolute errors delta_i = x_id - x_i
    (eq. 12), the rules' Cartesian offsets e_i = J_i dq_i and their rates
    J_i dqdot_i from the last period, world frame."""
    delta = jnp.stack(
        [_sync.absolute_error(ref.pad_pos[i], ref.pad_rot[i], arms[i].pad_pos, arms[i].pad_rot) for i in range(2)]
    )
    e = jnp.stack([arms[i].jac @ state.rule.joint_pos[i] for i in range(2)])
    e_dot = jnp.stack([arms[i].jac @ state.rule.joint_vel[i] for i in range(2)])
    return delta, e, e_dot


def coupled_reference(gains, state: Ros2State, arms, ref, cross_term: str = "squeeze"):
    """The target each arm's reference joints follow under ``"ros2_synchronous"``:
    the plan plus the paper's synchronous offset o_i less the rule's own offset
    e_i, x_id + o_i - e_i, its rate xdot_id + odot_i - edot_i, so that the
    command the rule adds e_i to carries the paper's law x_id + o_i
    (eqs. 12-17) once the reference has caught up (a time 1 / lambda,
    lambda = 2 kp_pos / kd_pos). o_i = delta_ik + k_il x_ild, delta_ik =
    k_ik (delta_r - delta_l) from the sensed pads (eqs. 12, 13) and x_ild the
    cross term (eq. 16) of the rules' Cartesian offsets e_i = J_i dq_i (their
    rates J_i dqdot_i) from the last period. In the squeeze (e_r = -e_l)
    k_rl = k_ll = 1/2 and k_ik = 0 command the rule's own offset; all k zero
    hold the pads on the plan (position control, no compliance at rest)."""
    delta, e, e_dot = _errors(state, arms, ref)
    k_il = jnp.stack([gains.k_rl, gains.k_ll])
    off = (
        _sync.synchronous_offset(
            _sync.relative_compensation(delta, gains.k_rk, gains.k_lk),
            k_il,
            _sync.cross_mapped(e, ref.pad_pos, cross_term),
        )
        - e
    )
    off_vel = k_il[:, None] * _sync.cross_mapped(e_dot, ref.pad_pos, cross_term) - e_dot
    return _offset_reference(ref, off, off_vel)


def family_target(gains, cstate, state: Ros2State, arms, ref):
    """The coupling family's offset o_i (``jaxsync.control.coupling``) from the
    sensed pads' absolute errors, the rules' Cartesian offsets e_i = J_i dq_i
    and rates from the last period, and the pads' wrench errors. Returns
    (o (2, 6), its rate (2, 6), world frame, the family's new state)."""
    delta, e, e_dot = _errors(state, arms, ref)
    eps = jnp.stack([arms[i].wrench for i in range(2)]) - ref.wrench
    u, u_dot = _coupling.inputs(gains, delta, e, e_dot, eps, ref.pad_rot)
    return _coupling.step(gains, cstate, u, u_dot, ref.pad_rot)


def _offset_reference(ref, off, off_vel):
    return ref._replace(
        pad_pos=ref.pad_pos + off[:, :3],
        pad_rot=jnp.stack([_so3.exp(off[i, 3:]) @ ref.pad_rot[i] for i in range(2)]),
        pad_vel=ref.pad_vel + off_vel,
    )


def step(
    gains,
    state: Ros2State,
    arms,
    ref,
    dt: float,
    distro: str = DEFAULT_DISTRO,
    coupled: bool = False,
    cross_term: str = "squeeze",
    ft_filter=1.0,
    family=None,
    placement: str = "reference",
):
    """One control period of both arms' rules.

    Args: gains; state; arms (right, left) sensed ``ArmState``; ref a
    ``jaxsync.control.controller.Reference``; dt the period, s; distro the
    release (static); coupled (static): the reference each rule offsets
    carries the paper's coupling (:func:`coupled_reference`), cross_term its
    reading of eq. 16; ft_filter the rule's F/T filter coefficient;
    family: the coupling family's state (``jaxsync.control.coupling``,
    "ros2_coupled"; None: none), entering as ``placement`` says (static).
    Returns (2 n,) the joint position commands, the new state and (2, 6) the
    rules' Cartesian offsets J dq (world frame, at the pad); with ``family``
    also the family's new state.
    """
    rule = _ra.admittance_rule(distro)
    target, shift = ref, None
    if coupled:
        target = coupled_reference(gains, state, arms, ref, cross_term)
    if family is not None:
        o, o_vel, family = family_target(gains, family, state, arms, ref)
        if placement == "reference":
            target = _offset_reference(ref, o, o_vel)
        elif placement == "direct":
            shift = (o, o_vel)
        else:
            raise ValueError(f"placement must be one of {_coupling.PLACEMENTS}, got {placement!r}")
    out, q_refs, rules, offsets = [], [], [], []
    for i in range(2):
        arm = arms[i]
        q_ref, rate = reference_step(gains, arm, state.q_ref[i], target, i, dt)
        q_rule, rate_rule = q_ref, rate
        if shift is not None:  # the offset on the rule's reference joints, through J#, this period
            dls = jnp.linalg.solve(
                arm.jac.T @ arm.jac + _joint_space.COMMAND_ALPHA * jnp.eye(arm.jac.shape[1]), arm.jac.T
            )
            q_rule, rate_rule = q_ref + dls @ shift[0][i], rate + dls @ shift[1][i]
        w_ref = None if distro == "humble" else -_in_pad(arm.pad_rot, ref.wrench[i])
        command, rs = rule.step(
            params(gains, i, ref.pad_rot[i], distro, ft_filter),
            jax.tree_util.tree_map(lambda x, i=i: x[i], state.rule),
            kinematics(arm, q_rule),
            _in_pad(arm.pad_rot, arm.wrench),
            _ra.JointPoint(q_rule, rate_rule, jnp.zeros_like(rate)),
            dt,
            wrench_reference=w_ref,
        )
        out.append(command.positions)
        q_refs.append(q_ref)
        rules.append(rs)
        offsets.append(arm.jac @ rs.joint_pos)
    new = Ros2State(q_ref=jnp.stack(q_refs), rule=jax.tree_util.tree_map(lambda *x: jnp.stack(x), *rules))
    if family is not None:
        return jnp.concatenate(out), new, jnp.stack(offsets), family
    return jnp.concatenate(out), new, jnp.stack(offsets)
