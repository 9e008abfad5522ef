"""The laws against closed forms: the joint-space law (eqs. 18, 19), the
absolute error on SO(3) (eq. 12), the synchronous offset (eqs. 13, 14, 16,
17), and the production gradient path's forward values."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import TEST_DURATION, make_forward_sense, paper_model
from mujoco import mjx

from jaxsync.control import joint_space as _joint_space
from jaxsync.control import so3 as _so3
from jaxsync.control import sync as _sync
from jaxsync.control.gains import default_gains
from jaxsync.sim import closed_loop as _closed_loop
from jaxsync.sim import rollout as _rollout
from jaxsync.sim.scenario import short_task


def _production_rollout(model):
    """What the tuner differentiates: rematerialised steps, tree passes, truncated windows."""
    return jax.jit(
        _rollout.make_rollout(model, "synchronous", TEST_DURATION, remat=True, passes="tree", truncate_every=100)
    )


def compile_ahead():
    """``forward_sense`` (tests/conftest.py) on a state like ``free_arms``, and the
    production rollout (compiled ahead in a second process: tests/conftest.py)."""
    model = paper_model()
    d = mujoco.MjData(model.mj_model)
    d.qpos[:] = model.keyframe_qpos("grasp")
    jax.block_until_ready(make_forward_sense(model)(model.mjx_model, mjx.put_data(model.mj_model, d, impl="jax")))
    jax.block_until_ready(_production_rollout(model)(default_gains(), short_task()))


# ------------------------------------------------------- joint-space law


@pytest.fixture(scope="module")
def free_arms(model, forward_sense):
    """Both arms near the grasp pose, moving, with the object 3 m below the
    stand: no contact, so the arm dynamics are M ddq + c + g + D dq = tau."""
    m = model.mj_model
    rng = np.random.default_rng(3)
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos("grasp")
    d.qpos[:14] += rng.uniform(-0.2, 0.2, 14)
    qa = model.index.object_qpos_adr
    d.qpos[qa : qa + 3] = [0.65, 0.0, -2.2]
    d.qvel[:14] = rng.uniform(-0.5, 0.5, 14)
    dx, sensed = forward_sense(model.mjx_model, mjx.put_data(m, d, impl="jax"))
    assert np.abs(np.asarray(sensed.obj.pad_forces)).max() == 0.0
    return dx, (sensed.right, sensed.left)


def test_null_space_projector_leaves_the_task_acceleration_unchanged(free_arms):
    """tau's posture term acts through N = I - J^+ J: changing the rest posture
    (lambda) changes the torques but not the pad acceleration J M^-1 tau. The
    damped pseudo-inverse leaks |J N| <= damping^2 / sigma_min of it (~1e-5)."""
    _, arms = free_arms
    rng = np.random.default_rng(0)
    for arm in arms:
        jac = np.asarray(arm.jac)
        null = np.eye(7) - np.asarray(_joint_space.damped_pinv(arm.jac)) @ jac
        assert np.abs(jac @ null).max() < 1e-5
        ddx = jnp.asarray(rng.normal(size=6))
        q_a, q_b = (jnp.asarray(np.asarray(arm.q) + rng.uniform(-0.5, 0.5, 7)) for _ in range(2))
        tau_a = np.asarray(_joint_space.torques(arm, ddx, q_a, 100.0, 20.0, jnp.zeros(6)))
        tau_b = np.asarray(_joint_space.torques(arm, ddx, q_b, 100.0, 20.0, jnp.zeros(6)))
        dq_acc = np.linalg.solve(np.asarray(arm.mass), tau_a - tau_b)  # the joint accelerations differ...
        assert np.linalg.norm(dq_acc) > 1.0
        # ...the pad's does not (up to the damped pseudo-inverse's leak, ~1e-5)
        assert np.linalg.norm(jac @ dq_acc) < 1e-4 * np.linalg.norm(dq_acc)


@pytest.mark.parametrize("n", [6, 7])
def test_the_position_command_refines_the_planned_twist_alone(n):
    """On position-controlled arms the plan's twist moves the pad at 1 -
    (alpha / (s^2 + alpha))^2 along each singular direction of J (value s),
    J# alone at s^2 / (s^2 + alpha); the feedback and the compliance's rates
    keep J#. A random J with one weak direction (s = 0.2, where J# moves
    the pad at 0.8 of the twist asked)."""
    rng = np.random.default_rng(n)
    u, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    w, _ = np.linalg.qr(rng.normal(size=(n, n)))
    s = np.array([2.0, 1.5, 1.0, 0.8, 0.5, 0.2])
    jac = u @ np.diag(s) @ w[:, :6].T
    alpha = _joint_space.COMMAND_ALPHA
    arm = _laws_arm(jnp.asarray(jac), rng)
    q = jnp.asarray(rng.normal(size=n))
    err = rng.normal(size=6) * 1e-3
    pos_ref, rot_ref = arm.pad_pos + err[:3], _so3.exp(jnp.asarray(err[3:])) @ arm.pad_rot
    plan, compliance = rng.normal(size=6), rng.normal(size=6)
    gains = (jnp.asarray(100.0), jnp.asarray(5.0), jnp.asarray(10.0), jnp.asarray(2.0))

    def rate(vel, plan_vel):
        return np.asarray(_joint_space.command_rate(arm, q, pos_ref, rot_ref, vel, q, *gains, plan_vel=plan_vel))

    refined, plain = rate(jnp.asarray(plan + compliance), jnp.asarray(plan)), rate(jnp.asarray(plan + compliance), None)
    dls = np.linalg.solve(jac.T @ jac + alpha * np.eye(n), jac.T)
    np.testing.assert_allclose(refined - plain, dls @ (plan - jac @ dls @ plan), atol=1e-12)
    # the plan's task-space gain per singular direction, with nothing else in the command
    only_plan = rate(jnp.asarray(plan), jnp.asarray(plan)) - rate(jnp.zeros(6), None)
    got = u.T @ (jac @ only_plan) / (u.T @ plan)
    np.testing.assert_allclose(got, 1.0 - (alpha / (s**2 + alpha)) ** 2, rtol=1e-9)
    assert got[-1] > 0.95 and (u.T @ (jac @ dls @ plan) / (u.T @ plan))[-1] < 0.81
    # at rest (no plan) the command is that of J# alone
    np.testing.assert_array_equal(rate(jnp.asarray(compliance), jnp.zeros(6)), rate(jnp.asarray(compliance), None))


def test_the_command_feed_forward_is_the_damped_least_squares_of_the_plan():
    """dq_ff = J# (ff_vel dx_plan + ff_acc ddx_plan) per arm for jaxsync's
    laws, nothing for ros2_controllers' rule (it has no such term) and
    nothing with both gains 0 (the defaults)."""
    from jaxsync.control import controller as _controller  # noqa: PLC0415

    rng = np.random.default_rng(3)
    jacs = [rng.normal(size=(6, 7)) for _ in range(2)]
    arms = tuple(_laws_arm(jnp.asarray(j), rng) for j in jacs)
    vel, acc = rng.normal(size=(2, 6)), rng.normal(size=(2, 6))
    ref = SimpleNamespace(pad_vel=jnp.asarray(vel), pad_acc=jnp.asarray(acc))
    g = default_gains()._replace(ff_vel=jnp.asarray(0.004), ff_acc=jnp.asarray(0.0013))
    alpha = _joint_space.COMMAND_ALPHA
    dls = [np.linalg.solve(j.T @ j + alpha * np.eye(7), j.T) for j in jacs]
    want = np.concatenate([d @ (0.004 * v + 0.0013 * a) for d, v, a in zip(dls, vel, acc, strict=True)])
    opts = _controller.ControllerOptions
    for kind in ("classical", "synchronous", "object_impedance", "task_space"):
        got = _controller.command_feedforward(opts(kind=kind), g, arms, ref)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-15)
    rule = _controller.command_feedforward(opts(kind="ros2_admittance"), g, arms, ref)
    np.testing.assert_array_equal(np.asarray(rule), 0.0)
    none = _controller.command_feedforward(opts(kind="synchronous"), default_gains(), arms, ref)
    np.testing.assert_array_equal(np.asarray(none), 0.0)


def _laws_arm(jac, rng):
    """The parts of an arm's sensed state the position command reads."""
    return SimpleNamespace(
        jac=jac, pad_pos=jnp.asarray(rng.normal(size=3)), pad_rot=_so3.exp(jnp.asarray(rng.normal(size=3)))
    )


def test_torques_produce_the_commanded_pad_acceleration(model, forward_sense, free_arms):
    """eqs. 18, 19 on a contact-free arm: apply the law's torques in MJX and the
    pads accelerate as commanded, J ddq + dJ dq = ddx, up to the joint damping
    the law does not compensate (-J M^-1 D dq, computed here) and the damped
    pseudo-inverse (relative 1e-5)."""
    dx, arms = free_arms
    m = model.mj_model
    rng = np.random.default_rng(1)
    ddx = [jnp.asarray(rng.normal(size=6)) for _ in arms]
    taus = [
        _joint_space.torques(arm, a, arm.q + 0.1, 100.0, 20.0, jnp.zeros(6)) for arm, a in zip(arms, ddx, strict=True)
    ]
    tau = np.asarray(jnp.concatenate(taus))
    assert np.all(np.abs(tau) < m.actuator_ctrlrange[:, 1])  # within the actuators' range: no clipping
    ctrl = tau[_closed_loop.consts(model).act_order]
    # committed to dx's device like the rest of dx (an uncommitted argument compiles another program)
    stepped, _ = forward_sense(model.mjx_model, dx.replace(ctrl=jax.device_put(ctrl, dx.ctrl.device)))
    qacc = np.asarray(stepped.qacc)
    for index, arm, want in zip(model.index.arms, arms, ddx, strict=True):
        dofs = list(index.dof_adr)
        got = np.asarray(arm.jac) @ qacc[dofs] + np.asarray(arm.jac_dot_qd)
        damping = m.dof_damping[dofs] * np.asarray(arm.qd)
        want = np.asarray(want) - np.asarray(arm.jac) @ np.linalg.solve(np.asarray(arm.mass), damping)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * (1 + np.abs(want).max()))


# ------------------------------------------------------------ SO(3), eq. 12


def _rodrigues(axis, angle):
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.mark.parametrize("angle", [1e-9, 1e-4, 0.3, 2.0, 3.0])
def test_absolute_error_is_the_rotation_vector_closed_form(angle):
    """delta = x_d - x (eq. 12): the position difference, and for R_d = Rot(a,
    angle) R the world-frame rotation vector angle * a (Rodrigues in numpy)."""
    rng = np.random.default_rng(int(angle * 1000))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    other = rng.normal(size=3)
    rot = _rodrigues(other / np.linalg.norm(other), 1.0)
    rot_d = _rodrigues(axis, angle) @ rot
    pos, pos_d = rng.normal(size=3), rng.normal(size=3)
    delta = np.asarray(_sync.absolute_error(jnp.asarray(pos_d), jnp.asarray(rot_d), jnp.asarray(pos), jnp.asarray(rot)))
    np.testing.assert_allclose(delta[:3], pos_d - pos, atol=1e-15)
    np.testing.assert_allclose(delta[3:], angle * axis, rtol=1e-9, atol=1e-15)
    # and it is what rotates rot onto rot_d
    np.testing.assert_allclose(np.asarray(_so3.exp(jnp.asarray(delta[3:]))) @ rot, rot_d, atol=1e-12)


def test_synchronous_offset_closed_form():
    """x_ik - x_id = k_ik (delta_r - delta_l) + k_il (e_i - e_j) (eqs. 13, 14,
    16, 17 with the squeeze cross term), by hand for known numbers."""
    delta = jnp.array([[0.002, -0.001, 0.0, 0.01, 0.0, 0.0], [0.0, 0.001, 0.003, 0.0, -0.02, 0.0]])
    e = jnp.array([[0.0, 0.004, 0.0, 0.0, 0.0, 0.05], [0.0, -0.002, 0.001, 0.0, 0.0, 0.0]])
    k_rk, k_lk, k_rl, k_ll = 0.5, -0.25, 0.6, 0.8
    delta_k = _sync.relative_compensation(delta, jnp.asarray(k_rk), jnp.asarray(k_lk))
    mapped = _sync.cross_mapped(e, jnp.zeros((2, 3)), "squeeze")
    out = np.asarray(_sync.synchronous_offset(delta_k, jnp.array([k_rl, k_ll]), mapped))
    rel = np.array([0.002, -0.002, -0.003, 0.01, 0.02, 0.0])  # delta_r - delta_l
    e_rl = np.array([0.0, 0.006, -0.001, 0.0, 0.0, 0.05])  # e_r - e_l
    want = np.stack([k_rk * rel + k_rl * e_rl, k_lk * rel - k_ll * e_rl])
    np.testing.assert_allclose(out, want, atol=1e-15)
    # neutral gains (k_rk = k_lk = 0, k_il = 1, no cross term): the classical offset e_i
    neutral = _sync.synchronous_offset(
        _sync.relative_compensation(delta, jnp.asarray(0.0), jnp.asarray(0.0)),
        jnp.ones(2),
        _sync.cross_mapped(e, jnp.zeros((2, 3)), "none"),
    )
    np.testing.assert_array_equal(np.asarray(neutral), np.asarray(e))


# --------------------------------------------- the production gradient path


def test_truncated_rematerialised_rollout_has_the_plain_forward_values(model, rollouts):
    """What the tuner differentiates (remat=True, truncate_every windows) rolls
    out the plain rollout: both only change the backward pass, and its tree
    passes (``passes="tree"``: the same formulas summed in another order) only
    the rounding: every field within 1e-11 of its largest value (measured:
    7e-13 at most, the contact forces). Checked against the shared plain
    rollout of the test task (grasp, lift, hold)."""
    plain = rollouts["synchronous"]
    prod = _production_rollout(model)(rollouts["gains"], rollouts["scenario"])
    assert np.abs(np.asarray(plain.pad_forces)).max() > 1.0  # in contact: the solve matters
    for name, a, b in zip(plain._fields, plain, prod, strict=True):
        a = np.asarray(a)
        np.testing.assert_allclose(np.asarray(b), a, rtol=0, atol=1e-11 * max(1.0, np.abs(a).max()), err_msg=name)
