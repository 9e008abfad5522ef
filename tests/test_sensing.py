"""Sensing: MJX quantities against MuJoCo C, wrist-wrench compensation, gradients.

Tolerances (float64): kinematics, Jacobians, mass matrix, bias 1e-8 relative;
J-dot q-dot 1e-7; sensor readings 1e-6 N (MJX's Newton solve vs C's).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import jaxsync
from jaxsync._physics import static_contact_geoms

N_CONFIGS = 20


def _c_reference(m, d, arm):
    """What MuJoCo C says about one arm, at the state in ``d`` (after mj_forward)."""
    dofs = list(arm.dof_adr)
    p = d.site_xpos[arm.pad_site].copy()
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jp, jr, arm.pad_site)
    djp, djr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacDot(m, d, djp, djr, p, arm.ee_body)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    return {
        "pad_pos": p,
        "pad_rot": d.site_xmat[arm.pad_site].reshape(3, 3).copy(),
        "jac": np.vstack([jp, jr])[:, dofs],
        "jac_dot_qd": np.concatenate([djp @ d.qvel, djr @ d.qvel]),
        "mass": full[np.ix_(dofs, dofs)],
        "bias": d.qfrc_bias[dofs].copy(),
        "wrist_raw": np.concatenate(
            [d.sensordata[arm.force_adr : arm.force_adr + 3], d.sensordata[arm.torque_adr : arm.torque_adr + 3]]
        ),
    }


def _random_states(model, n, seed=0):
    """Random arm poses, velocities and torques, pads at least 1 cm off the object."""
    m = model.mj_model
    rng = np.random.default_rng(seed)
    base = model.keyframe_qpos("approach")
    found = 0
    while found < n:
        d = mujoco.MjData(m)
        d.qpos[:] = base
        d.qpos[:14] += rng.uniform(-0.8, 0.8, 14)
        d.qvel[:14] = rng.uniform(-1.5, 1.5, 14)
        d.ctrl[:] = rng.uniform(-0.3, 0.3, m.nu) * m.actuator_ctrlrange[:, 1]
        mujoco.mj_forward(m, d)
        gaps = [
            mujoco.mj_geomDistance(m, d, arm.pad_geom, model.index.object_geom, 0.05, None) for arm in model.index.arms
        ]
        if min(gaps) > 0.01:
            found += 1
            yield d


@pytest.fixture(scope="module")
def random_pairs(model, forward_sense):
    """(C data, MJX sensed) at random configurations, velocities and torques."""
    out = []
    for d in _random_states(model, N_CONFIGS):
        dx, sensed = forward_sense(model.mjx_model, mjx.put_data(model.mj_model, d, impl="jax"))
        out.append((d, dx, sensed))
    return out


def test_static_contact_order_matches_mjx(model, random_pairs):
    _, dx, _ = random_pairs[0]
    np.testing.assert_array_equal(np.asarray(dx._impl.contact.geom), static_contact_geoms(model.mjx_model))


def test_leaf_sensors_equal_mjx_sensor_acc_in_contact(model, forward_sense):
    """The wrist sensors of a step (``_physics.leaf_sensor_acc``: each wrist
    body's inertial wrench less its contact wrench, no RNE over the whole
    tree) against MJX's ``sensor_acc`` (run by ``mjx.forward``), both pads
    pressed into the object, the arms moving: the same readings and the same
    end-effector accelerations to 1e-12."""
    from jaxsync import _physics

    m, index = model.mj_model, model.index
    rng = np.random.default_rng(4)
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos("grasp")
    d.qpos[index.right.qpos_adr[1]] += 0.05  # the right pad pushes the object into the left one
    d.qvel[:14] = rng.uniform(-0.3, 0.3, 14)
    d.ctrl[:] = rng.uniform(-0.3, 0.3, m.nu) * m.actuator_ctrlrange[:, 1]
    dx, _ = forward_sense(model.mjx_model, mjx.put_data(m, d, impl="jax"))
    for arm in index.arms:  # both pads in contact: the contact part of the wrench is exercised
        assert np.linalg.norm(np.asarray(_physics.contact_force_on(model.mjx_model, dx, arm.contact_id, True))) > 1.0
    plan = _physics.leaf_sensor_plan(model.mjx_model)
    assert [row[3] for row in plan] == [index.right.ee_body] * 2 + [index.left.ee_body] * 2
    blank = dx.replace(sensordata=jnp.zeros_like(dx.sensordata)).tree_replace(
        {"_impl.cacc": jnp.zeros_like(dx._impl.cacc)}
    )
    got = jax.jit(lambda x: _physics.leaf_sensor_acc(model.mjx_model, x, plan))(blank)
    want = np.asarray(dx.sensordata)
    assert np.abs(want).max() > 1.0
    np.testing.assert_allclose(np.asarray(got.sensordata), want, rtol=0, atol=1e-12 * np.abs(want).max())
    for arm in index.arms:
        np.testing.assert_allclose(
            np.asarray(got._impl.cacc[arm.ee_body]), np.asarray(dx._impl.cacc[arm.ee_body]), rtol=0, atol=1e-12
        )


def test_leaf_sensor_plan_leaves_other_sensors_to_mjx():
    """A force sensor on a body with children needs the children's wrenches:
    the plan is None and ``after_control`` runs MJX's own ``sensor_acc``."""
    from jaxsync import _physics

    xml = """<mujoco><worldbody><body name="a"><joint type="hinge"/><geom size=".1"/><site name="sa"/>
      <body name="b" pos="0 0 -.3"><joint type="hinge"/><geom size=".1"/><site name="sb"/></body>
      </body></worldbody><sensor><force site="%s"/><torque site="%s"/></sensor></mujoco>"""
    leaf = mjx.put_model(mujoco.MjModel.from_xml_string(xml % ("sb", "sb")), impl="jax")
    inner = mjx.put_model(mujoco.MjModel.from_xml_string(xml % ("sb", "sa")), impl="jax")
    assert [row[:5] for row in _physics.leaf_sensor_plan(leaf)] == [
        (int(mujoco.mjtSensor.mjSENS_FORCE), 0, 1, 2, 1),
        (int(mujoco.mjtSensor.mjSENS_TORQUE), 3, 1, 2, 1),
    ]
    assert _physics.leaf_sensor_plan(inner) is None


@pytest.mark.parametrize(
    "field,rtol,atol",
    [
        ("pad_pos", 1e-10, 1e-10),
        ("pad_rot", 1e-10, 1e-10),
        ("jac", 1e-8, 1e-10),
        ("jac_dot_qd", 1e-7, 1e-9),
        ("mass", 1e-8, 1e-10),
        ("bias", 1e-8, 1e-8),
        ("wrist_raw", 1e-6, 1e-6),
    ],
)
def test_mjx_matches_mujoco_c(model, random_pairs, field, rtol, atol):
    for d, _, sensed in random_pairs:
        for arm, got in zip(model.index.arms, (sensed.right, sensed.left), strict=True):
            want = _c_reference(model.mj_model, d, arm)[field]
            np.testing.assert_allclose(np.asarray(getattr(got, field)), want, rtol=rtol, atol=atol, err_msg=field)


def test_pad_twist_is_jacobian_times_qd(model, random_pairs):
    for d, _, sensed in random_pairs:
        for arm, got in zip(model.index.arms, (sensed.right, sensed.left), strict=True):
            vel = np.zeros(6)
            mujoco.mj_objectVelocity(model.mj_model, d, mujoco.mjtObj.mjOBJ_SITE, arm.pad_site, vel, 0)
            np.testing.assert_allclose(np.asarray(got.pad_vel), np.concatenate([vel[3:], vel[:3]]), atol=1e-9)


def test_compensation_removes_weight_and_inertia_without_contact(model, random_pairs):
    """Pads off the object, arms accelerating under random torques: the
    compensated wrench is zero although the raw sensor reads the end
    effector's weight and inertial force (several newtons)."""
    raw_norms = []
    for _, _, sensed in random_pairs:
        assert np.all(np.asarray(sensed.obj.pad_distance) > 0.005), "pads must be clear of the object here"
        for arm in (sensed.right, sensed.left):
            raw_norms.append(np.linalg.norm(np.asarray(arm.wrist_raw[:3])))
            np.testing.assert_allclose(np.asarray(arm.wrench), 0.0, atol=1e-8)
    assert min(raw_norms) > 0.5  # the test would catch a missing compensation


def _settle_clamp(model, squeeze=10.0, seconds=1.5):
    """MuJoCo C: both arms hold the grasp pose (computed-torque PD) and push
    their pads into the object with ``squeeze`` newtons."""
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos("grasp")
    q_ref = d.qpos.copy()
    mujoco.mj_forward(m, d)
    full = np.zeros((m.nv, m.nv))
    for _ in range(int(seconds / m.opt.timestep)):
        tau = d.qfrc_bias.copy()
        mujoco.mj_fullM(m, d, full)
        for arm in model.index.arms:
            dofs, qa = list(arm.dof_adr), list(arm.qpos_adr)
            jp = np.zeros((3, m.nv))
            mujoco.mj_jacSite(m, d, jp, None, arm.pad_site)
            normal = d.site_xmat[arm.pad_site].reshape(3, 3)[:, 2]
            pd = 400 * (q_ref[qa] - d.qpos[qa]) - 40 * d.qvel[dofs]
            tau[dofs] += full[np.ix_(dofs, dofs)] @ pd + jp[:, dofs].T @ (squeeze * normal)
        d.ctrl[:] = np.concatenate([tau[list(a.dof_adr)] for a in model.index.arms])
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    return d


def test_clamped_wrench_equals_true_contact_force(model, forward_sense):
    """Object clamped and at rest: the compensated wrist wrench equals MJX's
    contact force within 1e-6 N (the two come from the same solve), and
    MuJoCo C's within 1e-4 N (MJX's and C's Newton solves stop at different
    residuals)."""
    d = _settle_clamp(model)
    m = model.mj_model
    assert np.linalg.norm(d.qvel) < 1e-3, "the clamp should be at rest"
    dx, sensed = forward_sense(model.mjx_model, mjx.put_data(m, d, impl="jax"))
    pad_forces = np.asarray(sensed.obj.pad_forces)
    # the pads push the object towards each other, ~10 N each
    assert pad_forces[0][1] > 5 and pad_forces[1][1] < -5
    for arm, s, f_obj in zip(model.index.arms, (sensed.right, sensed.left), pad_forces, strict=True):
        # MuJoCo C's contact force, for the same contact, as a second opinion
        c = [
            i
            for i in range(d.ncon)
            if {d.contact[i].geom1, d.contact[i].geom2} == {arm.pad_geom, model.index.object_geom}
        ]
        assert len(c) == 1
        f6 = np.zeros(6)
        mujoco.mj_contactForce(m, d, c[0], f6)
        frame = d.contact[c[0]].frame.reshape(3, 3)
        on_geom2 = frame.T @ f6[:3]
        on_object = on_geom2 if d.contact[c[0]].geom2 == model.index.object_geom else -on_geom2
        np.testing.assert_allclose(f_obj, on_object, atol=1e-4)
        # object on arm = -(pad on object); the torque about the pad origin is
        # that of a point force at the contact point
        np.testing.assert_allclose(np.asarray(s.wrench[:3]), -f_obj, atol=1e-6)
        lever = np.asarray(dx._impl.contact.pos[arm.contact_id] - s.pad_pos)
        np.testing.assert_allclose(np.asarray(s.wrench[3:]), np.cross(lever, -f_obj), atol=1e-5)


def test_passive_trajectory_mjx_matches_c(model):
    """1 s with zero torques: the arms fall under gravity and joint damping,
    the object rests on its stand. MJX and MuJoCo C stay within 1e-6 rad/m."""
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos("approach")
    steps = int(1.0 / m.opt.timestep)
    c_traj = []
    for _ in range(steps):
        mujoco.mj_step(m, d)
        c_traj.append(d.qpos.copy())
    c_traj = np.array(c_traj)

    d0 = mujoco.MjData(m)
    d0.qpos[:] = model.keyframe_qpos("approach")

    @jax.jit
    def run(dx):
        def body(dx, _):
            dx = mjx.step(model.mjx_model, dx)
            return dx, dx.qpos

        return jax.lax.scan(body, dx, None, length=steps)[1]

    x_traj = np.asarray(run(jaxsync.put_data(m, d0)))
    moved = np.abs(c_traj[-1, :14] - c_traj[0, :14]).max()
    assert moved > 0.5, "the arms should have fallen"
    err = np.abs(x_traj - c_traj).max()
    assert err < 1e-6, f"max |qpos_mjx - qpos_c| over 1 s = {err:.2e}"


@pytest.mark.slow
def test_grad_of_sensed_quantities_matches_central_differences(model):
    """jax.grad through one physics step (the converged solve, implicit
    adjoint) and ``sense`` of the next state, the right pad pressed 2 mm into
    the object: against a central difference along a random direction."""
    from jaxsync import _physics

    mx, index = model.mjx_model, model.index
    d = mujoco.MjData(model.mj_model)
    d.qpos[:] = model.keyframe_qpos("grasp")
    d.qpos[index.right.qpos_adr[0]] += 0.002
    dx = _physics.put_data(model.mj_model, d)
    ctrl = jnp.zeros(model.mj_model.nu)

    def scalar(qvel):
        d1 = _physics.after_control(mx, _physics.before_control(mx, dx.replace(qvel=qvel)), ctrl)
        s = jaxsync.sense(mx, _physics.before_control(mx, d1), index)
        return (
            jnp.sum(s.right.wrench**2)
            + jnp.sum(s.left.jac**2)
            + jnp.sum(s.right.mass)
            + jnp.sum(s.obj.pad_forces**2)
            + jnp.sum(s.left.jac_dot_qd)
        )

    f = jax.jit(scalar)
    value, grad = jax.jit(jax.value_and_grad(scalar))(dx.qvel)
    assert np.isfinite(value) and np.all(np.isfinite(grad))
    u = jnp.asarray(np.random.default_rng(2).standard_normal(dx.qvel.size))
    h = 1e-6
    fd = (float(f(dx.qvel + h * u)) - float(f(dx.qvel - h * u))) / (2 * h)
    assert abs(float(grad @ u)) > 1.0
    assert abs(fd - float(grad @ u)) <= 1e-5 * abs(fd)
