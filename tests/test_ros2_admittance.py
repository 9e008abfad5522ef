"""ros2_controllers' admittance rule (jaxsync.control.ros2_admittance) against
closed forms and against an independent NumPy transcription of the C++.

The transcription below follows admittance_rule_impl.hpp line by line
(jazzy ed360c97d6e9 lines 176-351, rolling 94e74de35f9d lines 144-334, humble
ad559d9c8054 lines 170-345) and the controller's wrench offset
(admittance_controller.cpp jazzy 508-514), with Eigen's own quaternion and
angle-axis conversions and an explicit inverse, as kinematics_interface_kdl
writes it; it calls nothing of the port. Float64: tests/conftest.py enables x64.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxsync._errors import ConfigError
from jaxsync.control import ros2_admittance as ra

DT = 0.002
_AT_ZERO = ra.JointPoint(*(np.zeros(6),) * 3)  # a reference of six joints at rest at zero

# ---------------------------------------------------------------------------
# The NumPy transcription of the C++


def _eigen_quaternion(mat):
    """Eigen's quaternionbase_assign_impl (rotation matrix -> w, x, y, z)."""
    q = [0.0, 0.0, 0.0]  # x, y, z
    t = mat[0, 0] + mat[1, 1] + mat[2, 2]
    if t > 0.0:
        t = math.sqrt(t + 1.0)
        w = 0.5 * t
        t = 0.5 / t
        q = [(mat[2, 1] - mat[1, 2]) * t, (mat[0, 2] - mat[2, 0]) * t, (mat[1, 0] - mat[0, 1]) * t]
    else:
        i = 0
        if mat[1, 1] > mat[0, 0]:
            i = 1
        if mat[2, 2] > mat[i, i]:
            i = 2
        j = (i + 1) % 3
        k = (j + 1) % 3
        t = math.sqrt(mat[i, i] - mat[j, j] - mat[k, k] + 1.0)
        q[i] = 0.5 * t
        t = 0.5 / t
        w = (mat[k, j] - mat[j, k]) * t
        q[j] = (mat[j, i] + mat[i, j]) * t
        q[k] = (mat[k, i] + mat[i, k]) * t
    return w, np.array(q)


def _eigen_angle_axis(mat):
    """angle_axis.angle() * angle_axis.axis() of Eigen::AngleAxisd(mat)."""
    w, v = _eigen_quaternion(mat)
    n = math.sqrt(float(v @ v))
    if n == 0.0:
        return 0.0 * v
    angle = 2.0 * math.atan2(n, abs(w))
    if w < 0.0:
        n = -n
    return angle * (v / n)


class CppAdmittanceRule:
    """Members of AdmittanceRule and its AdmittanceState, updated as the C++ does."""

    def __init__(self, num_joints, distro, parameters, selected_axes):
        self.distro = distro
        self.p = parameters  # YAML names
        # AdmittanceState(num_joints) and reset(): zeros
        self.joint_pos = np.zeros(num_joints)
        self.joint_vel = np.zeros(num_joints)
        self.joint_acc = np.zeros(num_joints)
        self.admittance_velocity = np.zeros(6)
        self.admittance_acceleration = np.zeros(6)
        self.wrench_world_ = np.zeros(6)
        self.wrench_base = np.zeros(6)
        # apply_parameters_update
        self.end_effector_weight_ = np.zeros(3)
        self.end_effector_weight_[2] = -parameters["gravity_compensation.CoG.force"]
        self.cog_pos_ = np.array(parameters["gravity_compensation.CoG.pos"], dtype=float)
        self.mass = np.array(parameters["admittance.mass"], dtype=float)
        self.stiffness = np.array(parameters["admittance.stiffness"], dtype=float)
        self.selected_axes = np.array([1.0 if a else 0.0 for a in selected_axes])
        self.mass_inv = np.zeros(6)
        self.damping = np.zeros(6)
        for i in range(6):
            self.mass_inv[i] = 1.0 / parameters["admittance.mass"][i]
            ratio = parameters["admittance.damping_ratio"][i]
            self.damping[i] = ratio * 2 * math.sqrt(self.mass[i] * self.stiffness[i])

    # kinematics_interface_kdl: the damped pseudo-inverse and the forward map
    def convert_cartesian_deltas_to_joint_deltas(self, jac, delta_x):
        n = jac.shape[1]
        jacobian_inverse = np.linalg.inv(jac.T @ jac + self.p["kinematics.alpha"] * np.eye(n)) @ jac.T
        return jacobian_inverse @ delta_x

    def process_wrench_measurements(self, measured_wrench, sensor_world_rot, cog_world_rot):
        sample = np.zeros((3, 2))
        sample[:, 0] = measured_wrench[:3]
        sample[:, 1] = measured_wrench[3:]
        sample_world = sensor_world_rot @ sample
        sample_world[2, 0] -= self.end_effector_weight_[2]
        sample_world[:, 1] -= np.cross(cog_world_rot @ self.cog_pos_, self.end_effector_weight_)
        flat = np.concatenate([sample_world[:, 0], sample_world[:, 1]])  # Eigen's column-major (i)
        a = self.p["ft_sensor.filter_coefficient"]
        for i in range(6):
            self.wrench_world_[i] = a * flat[i] + (1 - a) * self.wrench_world_[i]

    def calculate_admittance_rule(self, kin, dt):
        rot_base_control = kin["rot_base_control"]
        if self.distro == "rolling":
            rot6 = np.zeros((6, 6))
            rot6[:3, :3] = rot_base_control
            rot6[3:, 3:] = rot_base_control
            K = np.diag(self.stiffness)
            D = np.diag(self.damping)
            M_inv = np.diag(self.mass_inv)
        else:
            K = np.zeros((6, 6))
            K[:3, :3] = rot_base_control @ np.diag(self.stiffness[:3]) @ rot_base_control.T
            K[3:, 3:] = rot_base_control @ np.diag(self.stiffness[3:]) @ rot_base_control.T
            D = np.zeros((6, 6))
            D[:3, :3] = rot_base_control @ np.diag(self.damping[:3]) @ rot_base_control.T
            D[3:, 3:] = rot_base_control @ np.diag(self.damping[3:]) @ rot_base_control.T
        desired_trans_base_ft = kin["trans_base_ft"]
        ref_trans_base_ft = kin["ref_trans_base_ft"]
        X = np.zeros(6)
        X[:3] = desired_trans_base_ft[:3, 3] - ref_trans_base_ft[:3, 3]
        R = desired_trans_base_ft[:3, :3] @ ref_trans_base_ft[:3, :3].T
        X[3:] = _eigen_angle_axis(R)
        X_dot = self.admittance_velocity.copy()
        F_base = self.wrench_base.copy()
        if self.distro == "rolling":
            F_control = rot6.T @ F_base
            F_control = F_control * self.selected_axes
            X_ddot = rot6 @ M_inv @ (F_control - D @ rot6.T @ X_dot - K @ rot6.T @ X)
        else:
            F_control = np.zeros(6)
            F_control[:3] = rot_base_control.T @ F_base[:3]
            F_control[3:] = rot_base_control.T @ F_base[3:]
            F_control = F_control * self.selected_axes
            F_base[:3] = rot_base_control @ F_control[:3]
            F_base[3:] = rot_base_control @ F_control[3:]
            X_ddot = self.mass_inv * (F_base - D @ X_dot - K @ X)
        jac = kin["jacobian"]
        self.joint_acc = self.convert_cartesian_deltas_to_joint_deltas(jac, X_ddot)
        for i in range(len(self.joint_acc)):
            self.joint_acc[i] -= self.p["admittance.joint_damping"] * self.joint_vel[i]
        self.joint_vel = self.joint_vel + self.joint_acc * dt
        self.joint_pos = self.joint_pos + self.joint_vel * dt
        self.admittance_velocity = jac @ self.joint_vel
        self.admittance_acceleration = jac @ self.joint_acc

    def update(self, kin, measured_wrench, reference, dt, wrench_reference=None):
        if wrench_reference is not None:  # admittance_controller.cpp add_wrenches
            measured_wrench = np.array([measured_wrench[i] + wrench_reference[i] for i in range(6)])
        rot_world_sensor = kin["rot_world_base"] @ kin["trans_base_ft"][:3, :3]
        rot_world_cog = kin["rot_world_base"] @ kin["rot_base_cog"]
        self.process_wrench_measurements(measured_wrench, rot_world_sensor, rot_world_cog)
        self.wrench_base[:3] = kin["rot_world_base"].T @ self.wrench_world_[:3]
        self.wrench_base[3:] = kin["rot_world_base"].T @ self.wrench_world_[3:]
        self.calculate_admittance_rule(kin, dt)
        n = len(self.joint_pos)
        positions = [reference[0][i] + self.joint_pos[i] for i in range(n)]
        velocities = [reference[1][i] + self.joint_vel[i] for i in range(n)]
        accelerations = [reference[2][i] + self.joint_acc[i] for i in range(n)]
        return np.array(positions), np.array(velocities), np.array(accelerations)


# ---------------------------------------------------------------------------
# random inputs


def _rotation(rng, scale=math.pi):
    w = rng.normal(size=3)
    w *= rng.uniform(0, scale) / np.linalg.norm(w)
    t = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / t
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def _transform(rot, pos):
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, pos
    return out


def _random_kinematics(rng, n=7):
    ref_rot = _rotation(rng)
    return {
        "jacobian": rng.normal(size=(6, n)),
        # the measured F/T frame within 1 rad of the reference (angle-axis far from pi)
        "trans_base_ft": _transform(_rotation(rng, 1.0) @ ref_rot, rng.normal(size=3)),
        "ref_trans_base_ft": _transform(ref_rot, rng.normal(size=3)),
        "rot_world_base": _rotation(rng),
        "rot_base_control": _rotation(rng),
        "rot_base_cog": _rotation(rng),
    }


def _random_parameters(rng):
    return {
        "admittance.mass": rng.uniform(0.5, 5.0, 6),
        "admittance.damping_ratio": rng.uniform(0.3, 2.0, 6),
        "admittance.stiffness": rng.uniform(10.0, 500.0, 6),
        "admittance.joint_damping": rng.uniform(0.0, 10.0),
        "ft_sensor.filter_coefficient": rng.uniform(0.01, 1.0),
        "kinematics.alpha": rng.uniform(0.01, 0.1),
        "gravity_compensation.CoG.pos": rng.normal(size=3) * 0.1,
        "gravity_compensation.CoG.force": rng.uniform(0.0, 20.0),
    }


def _params(p, distro):
    return ra.make_params(
        p["admittance.mass"],
        p["admittance.damping_ratio"],
        p["admittance.stiffness"],
        joint_damping=p["admittance.joint_damping"],
        filter_coefficient=p["ft_sensor.filter_coefficient"],
        alpha=p["kinematics.alpha"],
        cog_pos=p["gravity_compensation.CoG.pos"],
        cog_force=p["gravity_compensation.CoG.force"],
        distro=distro,
    )


def _kin(k):
    return ra.Kinematics(**{name: jnp.asarray(v) for name, v in k.items()})


# ---------------------------------------------------------------------------
# 2. the port against the transcription


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling", "humble"])
def test_port_matches_numpy_transcription(distro):
    rng = np.random.default_rng(sum(map(ord, distro)))
    n, steps = 7, 6
    axes = tuple(bool(b) for b in rng.integers(0, 2, 6))
    p = _random_parameters(rng)
    cpp = CppAdmittanceRule(n, distro, p, axes)
    rule = ra.admittance_rule(distro, axes)
    step = jax.jit(rule.step)
    params, state = _params(p, distro), rule.init(n)
    for _ in range(steps):
        kin = _random_kinematics(rng, n)
        wrench = rng.normal(size=6) * 10.0
        wrench_ref = None if distro == "humble" else rng.normal(size=6)
        ref = tuple(rng.normal(size=n) for _ in range(3))
        dt = rng.uniform(0.001, 0.01)
        expected = cpp.update(kin, wrench, ref, dt, wrench_ref)
        command, state = step(
            params,
            state,
            _kin(kin),
            jnp.asarray(wrench),
            ra.JointPoint(*map(jnp.asarray, ref)),
            dt,
            None if wrench_ref is None else jnp.asarray(wrench_ref),
        )
        for got, want in zip(command, expected, strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(state.wrench_world, cpp.wrench_world_, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(state.admittance_velocity, cpp.admittance_velocity, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(state.admittance_acceleration, cpp.admittance_acceleration, rtol=1e-10, atol=1e-10)
    assert np.abs(cpp.joint_acc).max() > 1e-3  # the comparison saw motion, not zeros


def test_eigen_angle_axis_transcription_is_the_rotation_vector():
    """The transcription's own check: Eigen's angle-axis of exp(w) is w (angle < pi)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        w = rng.normal(size=3)
        w *= rng.uniform(0.0, 3.0) / np.linalg.norm(w)
        k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        t = np.linalg.norm(w)
        rot = np.eye(3) + math.sin(t) / t * k + (1 - math.cos(t)) / t**2 * k @ k
        np.testing.assert_allclose(_eigen_angle_axis(rot), w, atol=1e-12)


# ---------------------------------------------------------------------------
# the mass frame (PR #1139) and the wrench path, in closed form


def _identity_kinematics(n=6, jacobian=None, rot_base_control=None):
    return ra.Kinematics(
        jacobian=jnp.eye(6, n) if jacobian is None else jnp.asarray(jacobian),
        trans_base_ft=jnp.eye(4),
        ref_trans_base_ft=jnp.eye(4),
        rot_world_base=jnp.eye(3),
        rot_base_control=jnp.eye(3) if rot_base_control is None else jnp.asarray(rot_base_control),
        rot_base_cog=jnp.eye(3),
    )


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling", "humble"])
def test_first_acceleration_is_inverse_mass_in_the_distros_frame(distro):
    """J = I, alpha = 0, at rest: q_ddot = M^-1 F, with M diagonal in the base
    frame on jazzy, kilted and humble and in the control frame on rolling."""
    rng = np.random.default_rng(11)
    rot = _rotation(rng)
    mass = np.array([1.0, 2.0, 4.0, 0.5, 0.25, 3.0])
    params = ra.make_params(mass, np.ones(6), 100 * np.ones(6), alpha=0.0, filter_coefficient=1.0)
    force = rng.normal(size=6)
    rule = ra.admittance_rule(distro)
    _, state = rule.step(params, rule.init(6), _identity_kinematics(rot_base_control=rot), force, _AT_ZERO, DT)
    rot6 = np.block([[rot, np.zeros((3, 3))], [np.zeros((3, 3)), rot]])
    if distro == "rolling":
        expected = rot6 @ np.diag(1 / mass) @ rot6.T @ force
    else:
        expected = force / mass
    np.testing.assert_allclose(state.joint_acc, expected, rtol=1e-12)
    assert not np.allclose(rot6 @ np.diag(1 / mass) @ rot6.T @ force, force / mass, rtol=1e-3)


def test_unselected_axes_get_no_force_in_the_control_frame():
    rng = np.random.default_rng(5)
    rot = _rotation(rng)
    axes = (True, False, True, True, True, False)
    params = ra.make_params(np.ones(6), np.ones(6), 100 * np.ones(6), alpha=0.0, filter_coefficient=1.0)
    rule = ra.admittance_rule("jazzy", axes)
    kin = _identity_kinematics(rot_base_control=rot)
    _, state = rule.step(params, rule.init(6), kin, rng.normal(size=6), _AT_ZERO, DT)
    in_control = np.concatenate([rot.T @ state.joint_acc[:3], rot.T @ state.joint_acc[3:]])
    np.testing.assert_allclose(in_control[[1, 5]], 0.0, atol=1e-14)
    assert np.all(np.abs(in_control[[0, 2, 3, 4]]) > 1e-6)


def test_gravity_compensation_cancels_a_static_tool():
    """A tool of weight G whose CoG sits at c in the F/T frame, sensor tilted by
    R (world = base): the sensor reads f = R^T (0, 0, -G), tau = c x f; the
    compensated wrench is zero."""
    rng = np.random.default_rng(2)
    rot, cog, weight = _rotation(rng), np.array([0.01, -0.02, 0.08]), 12.0
    f = rot.T @ np.array([0.0, 0.0, -weight])
    measured = np.concatenate([f, np.cross(cog, f)])
    params = ra.make_params(np.ones(6), np.ones(6), np.ones(6), cog_pos=cog, cog_force=weight, filter_coefficient=1.0)
    out = ra.process_wrench_measurements(params, jnp.zeros(6), measured, rot, rot)
    np.testing.assert_allclose(out, 0.0, atol=1e-12)
    uncompensated = ra.process_wrench_measurements(params._replace(cog_force=0.0), jnp.zeros(6), measured, rot, rot)
    np.testing.assert_allclose(uncompensated[2], -weight, rtol=1e-12)


def test_wrench_reference_adds_to_the_measurement_and_humble_has_none():
    params = ra.make_params(np.ones(6), np.ones(6), 100 * np.ones(6), filter_coefficient=1.0)
    measured, offset = jnp.arange(1.0, 7.0), jnp.full(6, 0.5)
    rule = ra.admittance_rule("rolling")
    _, with_ref = rule.step(params, rule.init(6), _identity_kinematics(), measured, _AT_ZERO, DT, offset)
    _, summed = rule.step(params, rule.init(6), _identity_kinematics(), measured + offset, _AT_ZERO, DT)
    np.testing.assert_allclose(with_ref.wrench_world, measured + offset, rtol=1e-15)
    np.testing.assert_allclose(with_ref.joint_pos, summed.joint_pos, rtol=1e-15)
    humble = ra.admittance_rule("humble")
    with pytest.raises(ConfigError, match="wrench_reference.*humble"):
        humble.step(params, humble.init(6), _identity_kinematics(), measured, _AT_ZERO, DT, offset)


# ---------------------------------------------------------------------------
# 1. one axis: the recurrence, its stability, the filter


def _one_axis_params(mass, damping, stiffness, joint_damping=0.0):
    """Axis x carries the given M, D, K (D through its damping ratio)."""
    zeta = damping / (2.0 * jnp.sqrt(mass * stiffness))
    ones = jnp.ones(6)
    return ra.AdmittanceParams(
        mass=ones.at[0].set(mass),
        damping_ratio=ones.at[0].set(zeta),
        stiffness=ones.at[0].set(stiffness),
        joint_damping=jnp.asarray(joint_damping, float),
        filter_coefficient=jnp.asarray(1.0),
        alpha=jnp.asarray(0.0),
        cog_pos=jnp.zeros(3),
        cog_force=jnp.asarray(0.0),
    )


_AXIS_RULE = ra.admittance_rule("jazzy")
_X_JACOBIAN = jnp.eye(6, 1)  # one prismatic joint moving the F/T frame along base x


def _axis_step(params, pos, vel, force):
    """The port on one joint of an arm that reached the last position command:
    the F/T frame sits at the commanded offset pos (reference at 0)."""
    kin = _identity_kinematics(1, _X_JACOBIAN)._replace(trans_base_ft=jnp.eye(4).at[0, 3].set(pos))
    state = ra.AdmittanceState(
        joint_pos=jnp.array([pos]),
        joint_vel=jnp.array([vel]),
        joint_acc=jnp.zeros(1),
        admittance_velocity=_X_JACOBIAN @ jnp.array([vel]),
        admittance_acceleration=jnp.zeros(6),
        wrench_world=jnp.zeros(6),
    )
    zero = jnp.zeros(1)
    _, state = _AXIS_RULE.step(params, state, kin, jnp.zeros(6).at[0].set(force), ra.JointPoint(zero, zero, zero), DT)
    return state.joint_pos[0], state.joint_vel[0]


@jax.jit
def _one_step_map(params):
    return jnp.stack(jax.jacfwd(lambda x: jnp.stack(_axis_step(params, x[0], x[1], 0.0)))(jnp.zeros(2)))


@jax.jit
def _settle(params, pos0, steps_force):
    def body(x, force):
        x = _axis_step(params, x[0], x[1], force)
        return x, x[0]

    _, pos = jax.lax.scan(body, (pos0, jnp.asarray(0.0)), steps_force)
    return pos


@pytest.mark.parametrize(
    "mass, damping, stiffness, joint_damping",
    [(1.0, 40.0, 400.0, 0.0), (2.0, 900.0, 5000.0, 0.0), (0.5, 10.0, 20000.0, 5.0), (1.0, 990.0, 25.0, 0.0)],
)
def test_recurrence_roots_are_the_eigenvalues_of_the_ports_one_step_map(mass, damping, stiffness, joint_damping):
    jac = np.asarray(_one_step_map(_one_axis_params(mass, damping, stiffness, joint_damping)))
    eig = np.sort_complex(np.linalg.eigvals(jac))
    roots = np.sort_complex(ra.one_axis_roots(mass, damping, stiffness, DT, joint_damping))
    np.testing.assert_allclose(eig, roots, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "h_d, h2_k, stable",
    [
        (1.98, 0.02, True),  # just below dt D/M = 2, 2 dt D/M + dt^2 K/M = 3.98
        (2.02, 0.02, False),  # just above dt D/M = 2
        (1.995, 0.02, False),  # below dt D/M = 2, but 2 dt D/M + dt^2 K/M = 4.01
        (1.0, 1.98, True),  # 2 dt D/M + dt^2 K/M just below 4
        (1.0, 2.02, False),  # just above
    ],
)
def test_port_diverges_exactly_where_the_condition_says(h_d, h2_k, stable):
    mass = 1.0
    damping, stiffness = h_d * mass / DT, h2_k * mass / DT**2
    assert ra.one_axis_stable(mass, damping, stiffness, DT) is stable
    pos = np.asarray(_settle(_one_axis_params(mass, damping, stiffness), 0.01, jnp.zeros(4000)))
    if stable:
        assert np.all(np.isfinite(pos)) and abs(pos[-1]) < 1e-6
    else:
        assert not (np.all(np.isfinite(pos)) and abs(pos[-1]) < 1e3)


def test_stability_condition_is_the_roots_inside_the_unit_circle():
    """The derivation checked on a grid: Jury's conditions against the roots."""
    for h_d in np.linspace(0.01, 2.5, 60):
        for h2_k in np.linspace(0.001, 4.5, 60):
            roots = ra.one_axis_roots(1.0, h_d / DT, h2_k / DT**2, DT)
            inside = np.max(np.abs(roots)) < 1.0 - 1e-12
            edge = abs(np.max(np.abs(roots)) - 1.0) < 1e-9
            assert edge or inside == ra.one_axis_stable(1.0, h_d / DT, h2_k / DT**2, DT), (h_d, h2_k)


def test_one_axis_settles_at_force_over_stiffness():
    mass, damping, stiffness, force = 1.0, 2 * math.sqrt(400.0), 400.0, 3.0
    pos = _settle(_one_axis_params(mass, damping, stiffness), 0.0, jnp.full(3000, force))
    np.testing.assert_allclose(pos[-1], force / stiffness, rtol=1e-9)


def test_filter_step_response_is_its_closed_form():
    """exponentialSmoothing from zero under a constant sample u:
    y_k = u (1 - (1 - a)^k)."""
    a, steps = 0.05, 80
    params = ra.make_params(np.ones(6), np.ones(6), 100 * np.ones(6), filter_coefficient=a)
    u = jnp.array([1.0, -2.0, 3.0, 0.1, 0.2, -0.3])

    def body(y, _):
        y = ra.process_wrench_measurements(params, y, u, jnp.eye(3), jnp.eye(3))
        return y, y

    _, ys = jax.lax.scan(body, jnp.zeros(6), None, length=steps)
    k = np.arange(1, steps + 1)[:, None]
    np.testing.assert_allclose(ys, np.asarray(u) * (1 - (1 - a) ** k), rtol=1e-12)


# ---------------------------------------------------------------------------
# 3. parameters


def test_defaults_follow_the_yaml_and_each_distros_kinematics_plugin():
    p = ra.make_params(np.ones(6), np.ones(6), np.ones(6))
    assert float(p.joint_damping) == 5.0 and float(p.filter_coefficient) == 0.05 and float(p.alpha) == 0.01
    assert float(ra.make_params(np.ones(6), np.ones(6), np.ones(6), distro="humble").alpha) == 0.000005
    leaves = jax.tree_util.tree_leaves(p)
    assert len(leaves) == 8 and all(leaf.dtype == jnp.float64 for leaf in leaves)


def test_damping_gradient_is_finite_at_zero_stiffness():
    p = ra.make_params(np.ones(6), np.ones(6), np.zeros(6))
    grad = jax.grad(lambda s: ra.damping(p._replace(stiffness=s)).sum())(p.stiffness)
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(ra.damping(p), 0.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"mass": [1, 1, 0.0, 1, 1, 1]}, r"admittance\.mass\[2\] = 0\.0: allowed \[0\.0001, 1000000\.0\]"),
        ({"stiffness": [1, 1, 1, 1, 1, -1]}, r"admittance\.stiffness\[5\] = -1\.0: allowed \[0\.0, 100000000\.0\]"),
        ({"damping_ratio": [1, 1]}, r"admittance\.damping_ratio: 6 numbers"),
        ({"joint_damping": -1.0}, r"admittance\.joint_damping = -1\.0: allowed >= 0\.0"),
        ({"cog_pos": [0, 0]}, r"gravity_compensation\.CoG\.pos: 3 numbers"),
        ({"filter_coefficient": float("nan")}, r"ft_sensor\.filter_coefficient: finite"),
        ({"distro": "iron"}, r"distro 'iron': one of jazzy, kilted, rolling, humble"),
    ],
)
def test_parameter_errors_name_the_parameter_and_what_is_allowed(kwargs, match):
    args = {"mass": np.ones(6), "damping_ratio": np.ones(6), "stiffness": np.ones(6)} | kwargs
    with pytest.raises(ConfigError, match=match):
        ra.make_params(**args)


def test_rule_and_one_axis_errors_name_what_is_allowed():
    with pytest.raises(ConfigError, match=r"admittance\.selected_axes: 6 booleans"):
        ra.admittance_rule("jazzy", (True,) * 5)
    with pytest.raises(ConfigError, match=r"distro 'foxy': one of"):
        ra.admittance_rule("foxy")
    with pytest.raises(ConfigError, match=r"dt: a finite number > 0"):
        ra.one_axis_roots(1.0, 1.0, 1.0, 0.0)
    with pytest.raises(ConfigError, match=r"stiffness: a finite number >= 0"):
        ra.one_axis_stable(1.0, 1.0, -1.0, DT)


def test_gradient_through_steps_matches_finite_differences():
    """The gains' gradient through three updates (float64, central differences)."""
    rng = np.random.default_rng(8)
    rule = ra.admittance_rule("rolling", (True, True, False, True, True, True))
    params = _params(_random_parameters(rng), "rolling")
    inputs = [(_kin(_random_kinematics(rng)), jnp.asarray(rng.normal(size=6) * 10.0)) for _ in range(3)]
    ref = ra.JointPoint(*(jnp.zeros(7),) * 3)

    def final_command(params):
        state = rule.init(7)
        for kin, wrench in inputs:
            command, state = rule.step(params, state, kin, wrench, ref, DT)
        return command.positions

    check_grads(final_command, (params,), order=1, modes=("rev",), eps=1e-6)


def test_the_stability_index_is_the_one_axis_bound_and_deployable_mass_meets_the_margin():
    """stability_index < 1 exactly where the one-axis recurrence is stable (K > 0);
    deployable_mass raises a mass to index 1 / DEPLOY_MARGIN and leaves the rest."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        m, d, k = rng.uniform(0.05, 5.0), rng.uniform(0.0, 3000.0), rng.uniform(1.0, 5000.0)
        index = float(ra.stability_index(m, d, k, DT))
        if abs(index - 1.0) > 1e-9:
            assert (index < 1.0) == ra.one_axis_stable(m, d, k, DT), (m, d, k, index)
    mass = np.array([2.0, 2.0, 2.0, 0.05])
    damping, stiffness = np.array([109.5, 2000.0, 2000.0, 2.8]), np.array([1500.0, 50.0, 50.0, 40.0])
    raised = ra.deployable_mass(mass, damping, stiffness, DT)
    np.testing.assert_allclose(ra.stability_index(raised, damping, stiffness, DT)[1:3], 1 / ra.DEPLOY_MARGIN)
    assert raised[0] == 2.0 and raised[3] == 0.05 and raised[1] == pytest.approx(3.0, rel=1e-4)
