"""ros2_controllers' admittance rule, term by term: what a position-controlled
arm running ``admittance_controller`` computes each control period.

A port of ``AdmittanceRule::update``, ``calculate_admittance_rule`` and
``process_wrench_measurements`` (file
``admittance_controller/include/admittance_controller/admittance_rule_impl.hpp``
of ros-controls/ros2_controllers) for three releases. Citations below name a
line of that file at these commits:

    J  jazzy   ed360c97d6e9e74cb884e3e39a949d987cd15c11  (kilted 0f8eb14e1a73
       computes the same: only its ``update`` is laid out as R's, no #1139)
    R  rolling 94e74de35f9d04f313aca8f29df66c3a76004aa7  (holds PR #1139,
       8bb3727790d3, mass in the control frame)
    H  humble  ad559d9c8054f128296ac094d7130e162e61b37a  (H line = J line - 6)

``C`` names ``admittance_controller/src/admittance_controller.cpp`` at the same
commit, ``KDL`` ``kinematics_interface_kdl/src/kinematics_interface_kdl.cpp``
of ros-controls/kinematics_interface (jazzy 0f3df4e218e5, master 38f56c733ac8,
humble 5c20d171d2b2), ``TB`` ``control_toolbox/filters.hpp`` of
ros-controls/control_toolbox (jazzy 05de3c67f1ac). ``docs/ros2-rule.md`` gives
the equations in the order they run.

Pure functions in optax's manner: ``rule = admittance_rule(distro,
selected_axes)``; ``state = rule.init(num_joints)``; ``command, state =
rule.step(params, state, kinematics, measured_wrench, reference, dt)``. The
kinematics come in as inputs, exactly what the C++ asks its kinematics plugin.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import so3 as _so3
from jaxsync.control.names import DISTROS

# where PR #1139 holds: M^-1 applied in the control frame (R 243-246, 279-281)
MASS_IN_CONTROL_FRAME = {"jazzy": False, "kilted": False, "rolling": True, "humble": False}
# kinematics.alpha (YAML default 0.01) is read by the KDL plugin on jazzy and
# later (KDL jazzy 52-58, ``ns + "alpha"``); humble's plugin reads the node's
# top-level ``alpha`` instead, default 0.000005 (KDL humble 38-44).
DEFAULT_ALPHA = {"jazzy": 0.01, "kilted": 0.01, "rolling": 0.01, "humble": 0.000005}


class AdmittanceParams(NamedTuple):
    """The numbers of ``admittance_controller_parameters.yaml`` that the rule
    reads, under their YAML names; every leaf a float64 array.

    mass (6,)               admittance.mass: kg (x, y, z), kg m^2 (rx, ry, rz)
    damping_ratio (6,)      admittance.damping_ratio: zeta, D = 2 zeta sqrt(M K)
    stiffness (6,)          admittance.stiffness: N/m, N m/rad
    joint_damping ()        admittance.joint_damping: 1/s, on joint velocities
    filter_coefficient ()   ft_sensor.filter_coefficient: weight of the raw sample
    alpha ()                kinematics.alpha (humble: the node's ``alpha``),
                            damping of the pseudo-inverse (J^T J + alpha I)^-1 J^T
    cog_pos (3,)            gravity_compensation.CoG.pos: m, in the CoG frame
    cog_force ()            gravity_compensation.CoG.force: N, weight m g
    """

    mass: jax.Array
    damping_ratio: jax.Array
    stiffness: jax.Array
    joint_damping: jax.Array
    filter_coefficient: jax.Array
    alpha: jax.Array
    cog_pos: jax.Array
    cog_force: jax.Array


class Kinematics(NamedTuple):
    """What the C++ asks kinematics_interface for in one update (n joints).

    ``calculate_link_transform(q, link)`` is the pose of ``link`` in the chain's
    base frame (``kinematics.base``), q the current joint positions unless said.

    jacobian (6, n)          Jacobian of ``ft_sensor.frame.id`` at q (KDL
                             ``JntToJac`` of that segment: base frame, reference
                             point the F/T frame's origin, rows [v; omega])
    trans_base_ft (4, 4)     ``calculate_link_transform(q, ft_sensor.frame.id)``
    ref_trans_base_ft (4, 4) the same at the reference joint positions
    rot_world_base (3, 3)    rotation of ``calculate_link_transform(q,
                             fixed_world_frame.frame.id)`` (the C++'s name)
    rot_base_control (3, 3)  rotation of ``... control.frame.id``
    rot_base_cog (3, 3)      rotation of ``... gravity_compensation.frame.id``

    ``kinematics.tip``'s transform, which J 160-161 also computes, is never read.
    """

    jacobian: jax.Array
    trans_base_ft: jax.Array
    ref_trans_base_ft: jax.Array
    rot_world_base: jax.Array
    rot_base_control: jax.Array
    rot_base_cog: jax.Array


class JointPoint(NamedTuple):
    """trajectory_msgs/JointTrajectoryPoint: (n,) each, rad, rad/s, rad/s^2."""

    positions: jax.Array
    velocities: jax.Array
    accelerations: jax.Array


class AdmittanceState(NamedTuple):
    """``AdmittanceState`` and ``wrench_world_`` of the C++, zero at reset.

    joint_pos, joint_vel, joint_acc (n,)   the admittance offset in joint space
    admittance_velocity (6,)               J joint_vel, base frame: next X_dot
    admittance_acceleration (6,)           J joint_acc (state message only)
    wrench_world (6,)                      the exponential filter's output
    """

    joint_pos: jax.Array
    joint_vel: jax.Array
    joint_acc: jax.Array
    admittance_velocity: jax.Array
    admittance_acceleration: jax.Array
    wrench_world: jax.Array


class AdmittanceRule(NamedTuple):
    """``init(num_joints) -> state``; ``step(params, state, kinematics,
    measured_wrench, reference, dt, wrench_reference=None) -> (command, state)``."""

    init: Callable[[int], AdmittanceState]
    step: Callable[..., tuple[JointPoint, AdmittanceState]]


def _vector(name: str, value, size: int | None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if size is None:
        if arr.ndim != 0:
            raise ConfigError(f"{name}: a single number, got shape {arr.shape}")
    elif arr.shape != (size,):
        raise ConfigError(f"{name}: {size} numbers (fixed_size<> {size}), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name}: finite numbers, got {arr.tolist()}")
    return arr


def _bounded(name: str, arr: np.ndarray, low: float, high: float) -> None:
    for i, v in enumerate(np.atleast_1d(arr)):
        if not low <= v <= high:
            raise ConfigError(f"{name}[{i}] = {float(v)!r}: allowed [{low!r}, {high!r}] (element_bounds<>)")


def make_params(
    mass,
    damping_ratio,
    stiffness,
    *,
    joint_damping=5.0,
    filter_coefficient=0.05,
    alpha=None,
    cog_pos=(0.0, 0.0, 0.0),
    cog_force=0.0,
    distro: str = "jazzy",
) -> AdmittanceParams:
    """Checked parameters, with the YAML's defaults and validation (J yaml
    52-56, 68-72, 94-148). ``alpha=None`` takes the distro's effective default
    (``DEFAULT_ALPHA``). CoG.pos has no YAML default: zero here is inert while
    CoG.force is 0, the torque term being CoG.pos x weight. Eager, not for jit.
    """
    _check_distro(distro)
    mass = _vector("admittance.mass", mass, 6)
    _bounded("admittance.mass", mass, 0.0001, 1000000.0)
    stiffness = _vector("admittance.stiffness", stiffness, 6)
    _bounded("admittance.stiffness", stiffness, 0.0, 100000000.0)
    damping_ratio = _vector("admittance.damping_ratio", damping_ratio, 6)
    joint_damping = _vector("admittance.joint_damping", joint_damping, None)
    if joint_damping < 0.0:
        raise ConfigError(f"admittance.joint_damping = {float(joint_damping)!r}: allowed >= 0.0 (gt_eq)")
    alpha = DEFAULT_ALPHA[distro] if alpha is None else alpha
    return AdmittanceParams(
        mass=jnp.asarray(mass),
        damping_ratio=jnp.asarray(damping_ratio),
        stiffness=jnp.asarray(stiffness),
        joint_damping=jnp.asarray(joint_damping),
        filter_coefficient=jnp.asarray(_vector("ft_sensor.filter_coefficient", filter_coefficient, None)),
        alpha=jnp.asarray(_vector("kinematics.alpha", alpha, None)),
        cog_pos=jnp.asarray(_vector("gravity_compensation.CoG.pos", cog_pos, 3)),
        cog_force=jnp.asarray(_vector("gravity_compensation.CoG.force", cog_force, None)),
    )


def _check_distro(distro) -> None:
    if distro not in DISTROS:
        raise ConfigError(f"distro {distro!r}: one of {', '.join(DISTROS)}")


def _check_axes(selected_axes) -> tuple[bool, ...]:
    axes = tuple(selected_axes)
    if len(axes) != 6 or not all(isinstance(a, (bool, np.bool_)) for a in axes):
        raise ConfigError(
            f"admittance.selected_axes: 6 booleans (x, y, z, rx, ry, rz; fixed_size<> 6), got {selected_axes!r}"
        )
    return tuple(bool(a) for a in axes)


def damping(params: AdmittanceParams) -> jax.Array:
    """D = damping_ratio 2 sqrt(mass stiffness), (6,) (J 142-144, R 137-139).

    With stiffness 0 an axis gets no damping whatever its ratio. The square
    root is guarded so that its gradient stays finite there.
    """
    mk = params.mass * params.stiffness
    positive = mk > 0.0
    return params.damping_ratio * 2.0 * jnp.where(positive, jnp.sqrt(jnp.where(positive, mk, 1.0)), 0.0)


def process_wrench_measurements(
    params: AdmittanceParams,
    wrench_world: jax.Array,
    measured_wrench: jax.Array,
    sensor_world_rot: jax.Array,
    cog_world_rot: jax.Array,
) -> jax.Array:
    """The filtered, gravity-compensated wrench, (6,) (J 325-351, R 308-334).

        w   = [R_s f; R_s tau]                  R_s = sensor_world_rot (3, 3)
        g   = (0, 0, -CoG.force)                end_effector_weight_ (J 132)
        w_f += CoG.force  (z only: w_f,z -= g_z), w_tau -= (R_c CoG.pos) x g
        wrench_world' = a w + (1 - a) wrench_world,  a = filter_coefficient

    Args: wrench_world (6,) the filter's last output; measured_wrench (6,)
    [force; torque] in the F/T frame; cog_world_rot (3, 3).
    """
    measured_wrench = jnp.asarray(measured_wrench)
    force = sensor_world_rot @ measured_wrench[:3]  # J 339: rotate only, the
    torque = sensor_world_rot @ measured_wrench[3:]  # torque stays about the sensor's origin
    weight = jnp.zeros(3).at[2].set(-params.cog_force)  # end_effector_weight_, J 132
    force = force.at[2].add(-weight[2])  # J 342
    torque = torque - jnp.cross(cog_world_rot @ params.cog_pos, weight)  # J 343
    raw = jnp.concatenate([force, torque])
    a = params.filter_coefficient  # TB jazzy 43-47: a raw + (1 - a) last
    return a * raw + (1.0 - a) * wrench_world  # J 346-350


def _block(rot: jax.Array) -> jax.Array:
    """(6, 6) diag(rot, rot): rot_base_control_6d (R 231-233)."""
    zero = jnp.zeros((3, 3))
    return jnp.block([[rot, zero], [zero, rot]])


def calculate_admittance_rule(
    params: AdmittanceParams,
    state: AdmittanceState,
    kinematics: Kinematics,
    wrench_base: jax.Array,
    dt,
    *,
    distro: str = "jazzy",
    selected_axes: tuple[bool, ...] = (True,) * 6,
) -> AdmittanceState:
    """One step of the admittance dynamics in joint space (J 234-323,
    R 226-306, H 228-317). With R = rot_base_control, R6 = diag(R, R),
    k, d, m the (6,) stiffness, damping and mass:

        X      = [p_ft(q) - p_ft(q_ref); log(R_ft(q) R_ft(q_ref)^T)]  base frame
        X_dot  = state.admittance_velocity       (J joint_vel of the last step)
        F      = R6 S R6^T wrench_base           S = diag(selected_axes)
        jazzy, kilted, humble:  K = R6 diag(k) R6^T, D = R6 diag(d) R6^T,
                                X_ddot = diag(m)^-1 (F - D X_dot - K X)
        rolling:                X_ddot = R6 diag(m)^-1 (S R6^T wrench_base
                                         - diag(d) R6^T X_dot - diag(k) R6^T X)
        q_ddot = (J^T J + alpha I)^-1 J^T X_ddot - joint_damping q_dot
        q_dot += q_ddot dt;  q += q_dot dt       (semi-implicit Euler)
        admittance_velocity = J q_dot;  admittance_acceleration = J q_ddot

    X is measured (the pose of the F/T frame at the current joints against the
    one at the reference joints), not integrated: the integrated quantities are
    the joint offsets. Shapes as in ``Kinematics``; wrench_base (6,); dt in s.
    """
    _check_distro(distro)
    selected_axes = _check_axes(selected_axes)
    rot_base_control = kinematics.rot_base_control
    rot6 = _block(rot_base_control)
    stiffness, damp = params.stiffness, damping(params)
    # X (J 265-280): the F/T frame at the current joints against the reference;
    # Eigen's AngleAxisd(R) gives angle in [0, pi] times axis, the SO(3) log
    trans_ft, ref_ft = kinematics.trans_base_ft, kinematics.ref_trans_base_ft
    x_pos = trans_ft[:3, 3] - ref_ft[:3, 3]  # J 269-270
    x_rot = _so3.log(trans_ft[:3, :3] @ ref_ft[:3, :3].T)  # J 271-280
    x = jnp.concatenate([x_pos, x_rot])
    x_dot = state.admittance_velocity  # J 283
    select = jnp.asarray(selected_axes, dtype=x.dtype)
    f_control = select * (rot6.T @ wrench_base)  # J 289-292, R 273-274
    if MASS_IN_CONTROL_FRAME[distro]:
        # R 279-281: the law written in the control frame, M^-1 there too
        x_ddot = rot6 @ ((f_control - damp * (rot6.T @ x_dot) - stiffness * (rot6.T @ x)) / params.mass)
    else:
        f_base = rot6 @ f_control  # J 293-294
        k_base = rot6 @ jnp.diag(stiffness) @ rot6.T  # J 239-251 (R K R^T per block)
        d_base = rot6 @ jnp.diag(damp) @ rot6.T  # J 254-262
        # J 297-298: mass_inv.cwiseProduct, per axis of the chain's base frame
        x_ddot = (f_base - d_base @ x_dot - k_base @ x) / params.mass
    jac = kinematics.jacobian
    n = jac.shape[1]
    # J 299-301 -> KDL 186-213: (J^T J + alpha I)^-1 J^T X_ddot
    joint_acc = jnp.linalg.solve(jac.T @ jac + params.alpha * jnp.eye(n), jac.T @ x_ddot)
    joint_acc = joint_acc - params.joint_damping * state.joint_vel  # J 304-308, the last step's q_dot
    joint_vel = state.joint_vel + joint_acc * dt  # J 311
    joint_pos = state.joint_pos + joint_vel * dt  # J 312, with the updated q_dot
    return AdmittanceState(
        joint_pos=joint_pos,
        joint_vel=joint_vel,
        joint_acc=joint_acc,
        admittance_velocity=jac @ joint_vel,  # J 315-317 -> KDL 114-136
        admittance_acceleration=jac @ joint_acc,  # J 318-320
        wrench_world=state.wrench_world,
    )


def admittance_rule(distro: str = "jazzy", selected_axes=(True,) * 6) -> AdmittanceRule:
    """The rule of one release; ``distro`` and ``admittance.selected_axes`` are
    static (Python values, checked here).

    ``step(params, state, kinematics, measured_wrench, reference, dt,
    wrench_reference=None)`` runs ``AdmittanceRule::update`` (J 176-232,
    R 144-224, H 170-226), after the controller's own input step:

        w      = measured_wrench + wrench_reference    C 508-514 (jazzy on; none on humble)
        wrench_world = process_wrench_measurements(w, R_wb R_ft, R_wb R_cog)   J 192-196
        wrench_base  = R_wb^T wrench_world                                    J 199-202
        state  = calculate_admittance_rule(...)                               J 209
        command = reference + (q, q_dot, q_ddot) of the state                 J 219-229

    R_wb is ``rot_world_base`` as the C++ composes it (J 192-195): a rotation
    from the F/T frame to the fixed world frame only when that frame is the
    chain's base (R_wb = I), the usual setting and the one this port is for.

    Args: measured_wrench, wrench_reference (6,) [force; torque] in the F/T
    frame (C 348-358 refuses a reference in another frame); reference a
    ``JointPoint`` of (n,); dt the period in s. Returns the ``JointPoint``
    written to the joints' command interfaces and the next state.
    """
    _check_distro(distro)
    axes = _check_axes(selected_axes)

    def init(num_joints: int) -> AdmittanceState:
        # AdmittanceState(num_joints) and wrench_world_.setZero() (J 110, 116)
        zeros = jnp.zeros(num_joints)
        six = jnp.zeros(6)
        return AdmittanceState(zeros, zeros, zeros, six, six, six)

    def step(params, state, kinematics, measured_wrench, reference, dt, wrench_reference=None):
        if wrench_reference is not None:
            if distro == "humble":
                raise ConfigError("wrench_reference: none on humble (its controller has no ~/wrench_reference)")
            measured_wrench = measured_wrench + wrench_reference  # C 54-69, 514
        rot_world_base = kinematics.rot_world_base
        wrench_world = process_wrench_measurements(
            params,
            state.wrench_world,
            measured_wrench,
            rot_world_base @ kinematics.trans_base_ft[:3, :3],  # J 192-193, R 187-190
            rot_world_base @ kinematics.rot_base_cog,  # J 194-195
        )
        wrench_base = jnp.concatenate([rot_world_base.T @ wrench_world[:3], rot_world_base.T @ wrench_world[3:]])
        state = calculate_admittance_rule(
            params,
            state._replace(wrench_world=wrench_world),
            kinematics,
            wrench_base,
            dt,
            distro=distro,
            selected_axes=axes,
        )
        command = JointPoint(
            positions=reference.positions + state.joint_pos,  # J 223-224
            velocities=reference.velocities + state.joint_vel,  # J 225-226
            accelerations=reference.accelerations + state.joint_acc,  # J 227-228
        )
        return command, state

    return AdmittanceRule(init=init, step=step)


def _one_axis_checked(mass, damping, stiffness, dt, joint_damping) -> tuple[float, float]:
    for name, v in (("mass", mass), ("dt", dt)):
        if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
            raise ConfigError(f"{name}: a finite number > 0, got {v!r}")
    for name, v in (("damping", damping), ("stiffness", stiffness), ("joint_damping", joint_damping)):
        if not (isinstance(v, (int, float)) and v >= 0 and math.isfinite(v)):
            raise ConfigError(f"{name}: a finite number >= 0, got {v!r}")
    return dt * (damping / mass + joint_damping), dt * dt * stiffness / mass


# admittance_controller_parameters.yaml's element_bounds on admittance.mass and admittance.stiffness
MASS_BOUNDS = (1e-4, 1e6)
STIFFNESS_BOUNDS = (0.0, 1e8)

DEPLOY_MARGIN = 1.5
"""The margin an export asks of the deployed rule on every axis: stable with
D/M and K/M raised this much (:func:`stability_index` <= 1 / DEPLOY_MARGIN).
jaxsync's own stability ratio asks the same 1.5 of its own stack
(``jaxsync.control.gains.STABILITY_MARGIN``)."""


def stability_index(mass, damping, stiffness, dt: float, joint_damping=0.0):
    """(2 dt d + dt^2 K/M) / 4, d = D/M + joint_damping, elementwise: the
    rule's one-axis recurrence is stable below 1 (:func:`one_axis_stable`,
    with K > 0) and rings at half the control rate at 1. Scaling D/M and K/M
    by c scales it by c: 1 / index is the axis's margin.

    Example:
      >>> float(stability_index(2.0, 2000.0, 50.0, 0.002))  # the paper's normal axis
      1.000025
    """
    m = np.asarray(mass, dtype=float)
    d = np.asarray(damping, dtype=float) / m + joint_damping
    return (2.0 * dt * d + dt * dt * np.asarray(stiffness, dtype=float) / m) / 4.0


def deployable_mass(mass, damping, stiffness, dt: float, margin: float = DEPLOY_MARGIN):
    """The mass, elementwise, raised where needed so that
    ``stability_index`` <= 1 / ``margin``: M >= margin (2 dt D + dt^2 K) / 4."""
    need = mass_needed(np.asarray(damping, dtype=float), np.asarray(stiffness, dtype=float), dt, margin)
    return np.maximum(np.asarray(mass, dtype=float), need)


def mass_needed(damping, stiffness, dt: float, margin: float = DEPLOY_MARGIN):
    """margin (2 dt D + dt^2 K) / 4, elementwise (NumPy or JAX arrays): the
    least mass at which ``stability_index`` is 1 / ``margin``."""
    return margin * (2.0 * dt * damping + dt * dt * stiffness) / 4.0


def one_axis_roots(mass: float, damping: float, stiffness: float, dt: float, joint_damping: float = 0.0) -> np.ndarray:
    """Characteristic roots (2,) complex of the rule on one axis.

    One joint moving the F/T frame along one axis (Jacobian 1), alpha = 0, an arm
    that reaches each position command before the next update (so the measured
    X of step k is the offset p_{k-1} commanded at step k - 1), with
    h = dt, d = D/M + joint_damping, k = K/M and v the joint velocity:

        v_k = v_{k-1} + h (F/M - d v_{k-1} - k p_{k-1}),   p_k = p_{k-1} + h v_k
        [p; v]_k = A [p; v]_{k-1} + b,  A = [[1 - h^2 k, h (1 - h d)], [-h k, 1 - h d]]
        lambda^2 - (2 - h d - h^2 k) lambda + (1 - h d) = 0

    (trace A = 2 - hd - h^2 k, det A = 1 - hd).
    """
    hd, hk = _one_axis_checked(mass, damping, stiffness, dt, joint_damping)
    return np.roots([1.0, -(2.0 - hd - hk), 1.0 - hd]).astype(complex)


def one_axis_stable(mass: float, damping: float, stiffness: float, dt: float, joint_damping: float = 0.0) -> bool:
    """Whether both roots of ``one_axis_roots`` lie inside the unit circle.

    Jury's test for lambda^2 + a1 lambda + a0 (a1 = -(2 - hd - h^2 k),
    a0 = 1 - hd) asks |a0| < 1, 1 + a1 + a0 > 0 and 1 - a1 + a0 > 0:

        0 < dt d < 2,   dt^2 K/M > 0,   2 dt d + dt^2 K/M < 4      (d = D/M + joint_damping)

    i.e. dt D/M < 2 and 2 dt D/M + dt^2 K/M < 4 without joint damping; with
    K > 0 the second implies the first. With D = 2 zeta sqrt(M K) and
    omega = sqrt(K/M): 4 zeta omega dt + (omega dt)^2 < 4. K = 0 leaves a root
    at 1 (no spring: the offset stays where the force left it), not stable.
    """
    hd, hk = _one_axis_checked(mass, damping, stiffness, dt, joint_damping)
    return bool(0.0 < hd < 2.0 and hk > 0.0 and 2.0 * hd + hk < 4.0)
