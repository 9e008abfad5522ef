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
from conftest import make_forward_sense, paper_model
from mujoco import mjx

import jaxsync
from jaxsync.physics import body_tree as _body_tree
from jaxsync.physics import step as _physics
from jaxsync.physics.step import static_contact_geoms

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


def _random_pairs(model, forward_sense):
    out = []
    for d in _random_states(model, N_CONFIGS):
        dx, sensed = forward_sense(model.mjx_model, mjx.put_data(model.mj_model, d, impl="jax"))
        out.append((d, dx, sensed))
    return out


def compile_ahead():
    """The programs of this module's tests that compile most (tests/conftest.py: compiled ahead in a second
    process): the stages against MJX's (eager operations and the Jacobians) and the passive trajectory."""
    model = paper_model()
    forward_sense = make_forward_sense(model)
    test_position_and_velocity_stages_equal_mjx(model, forward_sense, _random_pairs(model, forward_sense))
    test_passive_trajectory_mjx_matches_c(model)


@pytest.fixture(scope="module")
def random_pairs(model, forward_sense):
    """(C data, MJX sensed) at random configurations, velocities and torques."""
    return _random_pairs(model, forward_sense)


def test_static_contact_order_matches_mjx(model, random_pairs):
    _, dx, _ = random_pairs[0]
    np.testing.assert_array_equal(np.asarray(dx._impl.contact.geom), static_contact_geoms(model.mjx_model))


def test_leaf_sensors_equal_mjx_sensor_acc_in_contact(model, forward_sense):
    """The wrist sensors of a step (``_physics.leaf_sensor_acc``: each wrist
    body's inertial wrench less its contact wrench, no RNE over the whole
    tree) against MJX's ``sensor_acc`` (run by ``mjx.forward``), both pads
    pressed into the object, the arms moving: the same readings and the same
    end-effector accelerations to 1e-12."""
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


_POSITION_FIELDS = (
    "qpos", "xanchor", "xaxis", "xpos", "xquat", "xmat", "xipos", "ximat", "geom_xpos", "geom_xmat",
    "site_xpos", "site_xmat", "subtree_com", "cdof", "actuator_length", "_impl.M", "_impl.qLD",
    "_impl.actuator_moment", "_impl.cinert", "_impl.crb", "_impl.contact.dist", "_impl.contact.pos",
    "_impl.contact.frame", "cvel", "cdof_dot", "qfrc_bias", "_impl.actuator_velocity",
    "_impl.efc_J", "_impl.efc_pos", "_impl.efc_aref",
)  # fmt: skip


def _field(d, name):
    for part in name.split("."):
        d = getattr(d, part)
    return np.asarray(d)


def test_position_and_velocity_stages_equal_mjx(model, forward_sense, random_pairs):
    """``_physics.before_control(..., passes="tree")`` (what gradient programs
    run: jaxsync's tree passes, kinematics level by level, com_pos, crb, com_vel
    and the bias forces as products with static tree matrices; MJX's other
    stages) against ``mjx.forward``'s, and the Jacobians that sensing reads
    against MJX's, at random states
    and at a clamp with both pads in contact, the object's quaternion not of
    unit length (kinematics normalises it, in ``qpos`` too): every position
    and velocity field the step reads, to 1e-12 (rounding: the two sum in
    other orders)."""
    m, mx, index = model.mj_model, model.mjx_model, model.index
    assert _body_tree.kinematics_plan(mx) is not None  # the dual-arm tree is covered: the tree passes run
    clamp = mujoco.MjData(m)
    clamp.qpos[:] = model.keyframe_qpos("grasp")
    clamp.qpos[index.right.qpos_adr[1]] += 0.05
    quat = slice(index.object_qpos_adr + 3, index.object_qpos_adr + 7)
    clamp.qpos[quat] = 1.3 * (clamp.qpos[quat] + 0.1)
    mujoco.mj_forward(m, clamp)
    jacobians = jax.jit(lambda f, mx, d, p, b, passes="mjx": f(mx, d, p, b, passes), static_argnums=(0, 4, 5))
    largest = {}  # the clamp is at rest (no Jacobian derivative), the random states move
    for d in [clamp] + [d for d, _, _ in random_pairs[:3]]:
        state = mjx.put_data(m, d, impl="jax")
        want, _ = forward_sense(mx, state)  # mjx.forward, MJX's kinematics
        got = _physics.before_control(mx, state, "tree")
        for name in _POSITION_FIELDS:
            w = _field(want, name)
            np.testing.assert_allclose(
                _field(got, name), w, rtol=0, atol=1e-12 * max(1.0, np.abs(w).max()), err_msg=name
            )
        for arm in index.arms:  # the pads' Jacobians and their time derivatives, as sense() reads them
            point = want.site_xpos[arm.pad_site]
            for f in (_physics.jac, _physics.jac_dot):
                tree, mine = (
                    jacobians(f, mx, got, point, arm.ee_body, "tree"),
                    jacobians(f, mx, want, point, arm.ee_body),
                )
                for a, b in zip(tree, mine, strict=True):
                    b = np.asarray(b)
                    largest[f] = max(largest.get(f, 0.0), np.abs(b).max())
                    np.testing.assert_allclose(np.asarray(a), b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))
    assert len(largest) == 2 and min(largest.values()) > 0.0


def test_tree_passes_cover_each_joint_type():
    """Free, ball, slide and hinge joints (off-centre), bodies without joints,
    two subtrees whose parents lie at different places, everything moving:
    jaxsync's tree passes and Jacobians give MuJoCo C's fields;
    a body with two joints or a mocap body is left to MJX."""
    xml = """<mujoco><option><flag contact="disable"/></option><worldbody>
      <body name="f" pos=".1 .2 .3"><freejoint/><geom size=".1"/>
        <body pos="0 .2 0" quat=".9 .1 .3 .2"><joint type="ball" pos=".05 0 0"/><geom size=".1"/><site/>
          <body pos=".3 0 0"><joint type="slide" axis="1 1 0"/><geom size=".1"/></body></body>
        <body pos="0 0 .4"><geom size=".1"/>
          <body pos=".1 0 0" euler="10 20 30"><joint type="hinge" pos="0 .1 0" axis="0 1 1"/><geom size=".1"/></body>
        </body></body>
      <body pos="1 0 0"><joint type="hinge" axis="1 0 0" ref=".3"/><geom size=".1" pos=".1 0 0"/><site pos="0 .1 0"/>
        <body pos="0 0 .2"><joint type="hinge" axis="0 0 1"/><geom size=".1"/></body></body>
    </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    mx = mjx.put_model(m, impl="jax")
    assert _body_tree.kinematics_plan(mx) is not None
    d = mujoco.MjData(m)
    d.qpos[:] = np.random.default_rng(0).normal(size=m.nq)  # quaternions of any length: both normalise them
    d.qvel[:] = np.random.default_rng(1).normal(size=m.nv)
    dx = mjx.put_data(m, d, impl="jax")
    mujoco.mj_forward(m, d)  # the reference: MuJoCo C

    @jax.jit
    def jaxsync_stages(mx, dx):
        dx = _body_tree.com_vel(mx, _body_tree.com_pos(mx, _body_tree.kinematics(mx, dx)))
        gravity = jnp.concatenate([jnp.zeros(3), -mx.opt.gravity])
        dx = dx.replace(qfrc_bias=_body_tree.bias_force(mx, dx, gravity)).tree_replace(
            {"_impl.crb": _body_tree.crb_body(mx, dx)}
        )
        return dx, [f(mx, dx, dx.xpos[b] + 0.1, b) for f in (_body_tree.jac, _body_tree.jac_dot) for b in (3, 5)]

    got, got_jac = jaxsync_stages(mx, dx)
    names = _POSITION_FIELDS[1:14] + ("_impl.cinert", "_impl.crb", "cvel", "cdof_dot", "qfrc_bias")
    for name in names:
        w = getattr(d, name.removeprefix("_impl."))
        w = w.reshape(_field(got, name).shape)
        assert np.abs(w).max() > 0.0, name
        np.testing.assert_allclose(_field(got, name), w, rtol=0, atol=1e-10 * max(1.0, np.abs(w).max()), err_msg=name)
    for adr in (3, 7):  # the free and the ball joint's quaternions, normalised in qpos (as MJX does)
        q = d.qpos[adr : adr + 4]
        np.testing.assert_allclose(np.asarray(got.qpos[adr : adr + 4]), q / np.linalg.norm(q), rtol=0, atol=1e-14)
    for k, (f, b) in enumerate((f, b) for f in (mujoco.mj_jac, mujoco.mj_jacDot) for b in (3, 5)):
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        f(m, d, jp, jr, d.xpos[b] + 0.1, b)
        for want, g in zip((jp, jr), got_jac[k], strict=True):
            assert np.abs(want).max() > 0.0
            np.testing.assert_allclose(np.asarray(g), want.T, rtol=0, atol=1e-10)
    two = mujoco.MjModel.from_xml_string(
        xml.replace('<joint type="ball" pos=".05 0 0"/>', '<joint axis="1 0 0"/><joint axis="0 1 0"/>')
    )
    assert _body_tree.kinematics_plan(mjx.put_model(two, impl="jax")) is None
    mocap = mujoco.MjModel.from_xml_string(
        xml.replace('<body pos="1 0 0">', '<body mocap="true" pos="2 0 0"/><body pos="1 0 0">')
    )
    assert _body_tree.kinematics_plan(mjx.put_model(mocap, impl="jax")) is None


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
