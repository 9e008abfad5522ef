"""The joint-space law: Cartesian reference acceleration to joint torques (eqs. 18, 19)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxsync.control import so3 as _so3
from jaxsync.physics.sensing import ArmState

# Damping of the pseudo-inverse J^T (J J^T + lambda^2 I)^-1: negligible where
# the arm is well conditioned (sigma_min ~ 0.3 at the grasp), bounded joint
# accelerations near a singularity.
PINV_DAMPING = 1e-3


def damped_pinv(jac: jax.Array, damping: float = PINV_DAMPING) -> jax.Array:
    """(6, 7) -> (7, 6) damped least-squares pseudo-inverse."""
    return jac.T @ jnp.linalg.solve(jac @ jac.T + damping**2 * jnp.eye(jac.shape[0]), jnp.eye(jac.shape[0]))


def reference_acceleration(
    arm: ArmState,
    pos_ref: jax.Array,
    rot_ref: jax.Array,
    vel_ref: jax.Array,
    acc_ref: jax.Array,
    kp: jax.Array,
    kd: jax.Array,
) -> jax.Array:
    """ddx_k = ddx_ref + K_p (x_k - x) + K_d (dx_ref - dx), (6,), the inner
    position loop that makes the scheme position based. The pose error's
    rotation part is the SO(3) log of R_ref R^T."""
    err = jnp.concatenate([pos_ref - arm.pad_pos, _so3.rotation_error(rot_ref, arm.pad_rot)])
    return acc_ref + kp * err + kd * (vel_ref - arm.pad_vel)


def torques(
    arm: ArmState,
    ddx: jax.Array,
    q_rest: jax.Array,
    kp_null: jax.Array,
    kd_null: jax.Array,
    wrench: jax.Array,
) -> jax.Array:
    """tau = M ddq_d + c + g - J^T f with ddq_d = J^+ (ddx - dJ dq) + N lambda   (eqs. 18, 19).

    N = I - J^+ J projects the posture term lambda = K (q_rest - q) - D dq into
    the null space of the pad task (the redundant 7th degree of freedom).
    ``wrench`` is the object's wrench on the arm that -J^T f cancels (arm
    dynamics M ddq + c + g = tau + J^T f). The controllers pass the desired
    wrench f_id here, not the measured one (docs/controller.md: the measured
    wrench, one sample late and noisy, fed back at full gain made the stiff
    pad contact unstable).

    Args: ddx (6,); q_rest (7,); wrench (6,). Returns (7,).
    """
    pinv = damped_pinv(arm.jac)
    null = jnp.eye(arm.jac.shape[1]) - pinv @ arm.jac
    posture = kp_null * (q_rest - arm.q) - kd_null * arm.qd
    ddq = pinv @ (ddx - arm.jac_dot_qd) + null @ posture
    return arm.mass @ ddq + arm.bias - arm.jac.T @ wrench


# Damping of the joint-command least squares (J^T J + alpha I)^-1 J^T: the
# default ``kinematics.alpha`` of ros2_controllers' admittance controller
# (kinematics_interface_kdl, jazzy), so that jaxsync's position commands are
# made as the deployed controller makes them.
COMMAND_ALPHA = 0.01


def command_rate(
    arm: ArmState,
    command: jax.Array,
    pos_ref: jax.Array,
    rot_ref: jax.Array,
    vel_ref: jax.Array,
    q_rest: jax.Array,
    kp: jax.Array,
    kd: jax.Array,
    kp_null: jax.Array,
    kd_null: jax.Array,
    alpha: float = COMMAND_ALPHA,
    plan_vel: jax.Array | None = None,
) -> jax.Array:
    """dq_cmd/dt (n,): the joint position command's rate on a position-controlled arm.

        v      = dx_ref + lambda (x_ref - x),         lambda = kp / kd * 2 = 40 1/s at the defaults
        dq_cmd = J# v + J# (I - J J#) dx_plan + (I - J# J) mu (q_rest - q_cmd),
        J# = (J^T J + alpha I)^-1 J^T,  mu = kp_null / kd_null

    The inner position loop of the torque stack (eq. 18: (s + 40)^2 with the
    default kp, kd) becomes a first-order loop of the same bandwidth
    lambda on the measured pad pose x: integrated (``q_cmd += dt dq_cmd``)
    it has integral action, so the pad reaches x_ref though the servo sags
    under load. The damped least squares is the admittance rule's (alpha =
    ``kinematics.alpha``). A 7-joint arm's seventh joint: the null space of J
    (J# J is not quite a projector with alpha > 0; it is where J has no
    component) turns the command toward the rest posture at rate mu
    (kp_null / kd_null = 5 1/s at the defaults), as the torque stack's
    null-space term does; a 6-joint arm has none.

    The planned twist dx_plan (``plan_vel``; None: no such term) gets one
    step of iterative refinement: along a singular direction of J with value
    s, J# moves the pad at s^2 / (s^2 + alpha) of the twist asked, and the
    carry lost along a weak direction that has a share of the pad normal
    moves the pads apart, off the object (docs/deploy-tuning.md). Refined, the plan
    moves it at 1 - (alpha / (s^2 + alpha))^2 (still bounded as s -> 0); the
    compliance's rates and the feedback keep J#, so the command at rest is
    unchanged.

    Args: command (n,) the last joint command; pos_ref (3,), rot_ref (3, 3),
    vel_ref (6,) the compliant target (plan included); q_rest (n,);
    plan_vel (6,) the planned twist or None. Returns (n,) rad/s.
    """
    err = jnp.concatenate([pos_ref - arm.pad_pos, _so3.rotation_error(rot_ref, arm.pad_rot)])
    v = vel_ref + (2.0 * kp / kd) * err
    jac = arm.jac
    n = jac.shape[1]
    dls = jnp.linalg.solve(jac.T @ jac + alpha * jnp.eye(n), jac.T)
    null = jnp.eye(n) - dls @ jac
    rate = dls @ v + null @ ((kp_null / kd_null) * (q_rest - command))
    if plan_vel is not None:
        rate = rate + dls @ (plan_vel - jac @ (dls @ plan_vel))
    return rate


def plan_feedforward(
    arm: ArmState,
    plan_vel: jax.Array,
    plan_acc: jax.Array,
    ff_vel: jax.Array,
    ff_acc: jax.Array,
    alpha: float = COMMAND_ALPHA,
) -> jax.Array:
    """(n,) the joint command's feed-forward of the plan, rad:

        dq_ff = J# (ff_vel dx_plan + ff_acc ddx_plan),   J# = (J^T J + alpha I)^-1 J^T

    added to the integrated command on its way to the servo (the integrator
    does not see it, so at rest, with the plan still, the command is
    unchanged). A joint servo with stiffness k_j, damping b_j on the
    velocity error and inertia I_j follows a command with an error that
    obeys I_j e'' + b_j e' + k_j e = I_j q''_cmd: it lags I_j / k_j q'' behind
    an accelerating command, and releases that lag into its own lightly
    damped mode when the acceleration ends. ff_acc = I_j / k_j = 1 / w_j^2
    cancels it to first order; ff_vel leads the plan over a command delay
    (a delay of N periods: N dt).

    Args: plan_vel, plan_acc (6,) the planned pad twist and its rate;
    ff_vel (s), ff_acc (s^2). Returns (n,) rad.
    """
    jac = arm.jac
    dls = jnp.linalg.solve(jac.T @ jac + alpha * jnp.eye(jac.shape[1]), jac.T)
    return dls @ (ff_vel * plan_vel + ff_acc * plan_acc)
