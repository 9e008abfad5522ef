"""ros2_controllers' admittance rule as a controller in the closed loop
(``jaxsync.control.ros2_loop``): it holds the ball on position-controlled
arms, each period is the port's ``step``, it fails where the explicit rule's
bound says, the torque stack refuses it, and MuJoCo C agrees with MJX.

One MJX program (the jazzy rule, gains as arguments) serves every MJX run
here; the MuJoCo C run compiles the control step alone."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TEST_DURATION, fast_scenario

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.control import controller as _controller
from jaxsync.control import joint_space as _joint_space
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import ros2_loop as _ros2_loop
from jaxsync.control import so3 as _so3
from jaxsync.control.gains import USED
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.physics.sensing import ArmState
from jaxsync.sim import metrics as _metrics

DELAY = 1


def _translational_mass(g, mass):
    """x, y and z masses of both arms at ``mass``: the same on every axis of
    any frame, so that jazzy's M^-1 per base axis is the pad normal's too."""
    return g._replace(imp_mass=g.imp_mass.at[:, :3].set(mass))


def compile_ahead():
    """The rule's and the coupled rule's MJX programs (tests/conftest.py: compiled ahead in a second process)."""
    from conftest import paper_model

    m = paper_model()
    s = fast_scenario(delay=float(DELAY))
    for controller in ("ros2_admittance", "ros2_synchronous"):
        g = jaxsync.default_gains(m, "position", controller)
        traj = jaxsync.rollout(m, g, s, controller=controller, duration=TEST_DURATION, actuation="position")
        traj.time.block_until_ready()


@pytest.fixture(scope="module")
def loop_runs(model):
    s = fast_scenario(delay=float(DELAY))
    g = jaxsync.default_gains(model, "position")

    def run(gains, **kw):
        traj = jax.block_until_ready(
            jaxsync.rollout(
                model, gains, s, controller="ros2_admittance", duration=TEST_DURATION, actuation="position", **kw
            )
        )
        return traj, _metrics.summarize(traj, s)

    return {
        "scenario": s,
        "gains": g,
        "default": run(g),
        **{mass: run(_translational_mass(g, mass)) for mass in (3.0, 2.0, 1.8)},
        "mujoco": run(g, backend="mujoco"),
    }


def _holds(m):
    return not bool(m.dropped) and not bool(m.chattering) and not bool(m.nonfinite)


def test_the_rule_holds_the_ball_on_position_controlled_arms(loop_runs):
    """The position stack's defaults (normal mass 3 kg on the world axis
    along the pad normal, dt D/M = 1.33), delay 1: held, no chatter, a small
    grip error, the pads near the plan while the object is held."""
    traj, m = loop_runs["default"]
    assert _holds(m)
    assert float(m.grip_force_error_rel) < 0.01
    assert float(m.grip_force_error_rel_max) < 0.06
    assert float(m.settled_peak_resultant_N) < 0.15
    assert not np.asarray(traj.at_torque_limit).any()
    # the pads stay near the plan: the compliance moves them by a fraction of a millimetre
    hold = np.asarray(traj.phase) == 3
    assert np.abs(np.asarray(traj.pad_pos - traj.plan_pad_pos))[hold].max() < 2e-3


def test_the_rule_fails_past_its_explicit_bound(loop_runs):
    """dt D/M on the pad normal (D = 2000 N s/m, 2 ms): 1.33 at 3 kg holds
    the ball quietly; 2.00 at 2 kg (the bound) still holds it in this loop
    but rings (measured: settled peak resultant 0.083 N against 0.038 N,
    force chatter 0.22 N against 0.11 N); 2.22 at 1.8 kg, past it, loses the
    grip (forces up to 455 N, then the ball falls)."""
    m3, m2, m18 = (loop_runs[k][1] for k in (3.0, 2.0, 1.8))
    assert _holds(m3) and _holds(m2)
    assert float(m2.settled_peak_resultant_N) > 1.5 * float(m3.settled_peak_resultant_N)
    assert float(m2.force_chatter_N) > 1.5 * float(m3.force_chatter_N)
    assert bool(m18.chattering) or bool(m18.nonfinite) or bool(m18.dropped)


def test_mujoco_c_agrees_with_mjx_on_the_held_run(loop_runs):
    (x, mx), (c, mc) = loop_runs["default"], loop_runs["mujoco"]
    assert _holds(mc)
    np.testing.assert_allclose(float(mc.settled_peak_resultant_N), float(mx.settled_peak_resultant_N), rtol=0.05)
    np.testing.assert_allclose(float(mc.grip_force_error_rel), float(mx.grip_force_error_rel), rtol=0.2, atol=1e-4)
    assert float(jnp.abs(x.obj_pos - c.obj_pos).max()) < 5e-4


def test_an_export_re_simulates_bit_for_bit(model, loop_runs, tmp_path):
    """Gains as a tuner leaves them (every digit used), exported to ros2-admittance
    (the mass per base axis, damping as a ratio), read back and rolled out
    again: the same gains to the last bit, and the identical trajectory."""
    rng = np.random.default_rng(7)
    g = loop_runs["gains"]
    g = g._replace(
        **{
            f: jnp.asarray(getattr(g, f)) * (1.0 + 0.1 * rng.uniform(-1, 1, np.shape(getattr(g, f))))
            for f in ("imp_mass", "imp_damping", "imp_stiffness", "kp_pos", "kd_pos")
        }
    )
    _export.export(g, "ros2-admittance", str(tmp_path), _export.ros2_target(model.mj_model))
    back = gains_file.load(str(tmp_path))
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(g), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    s = loop_runs["scenario"]
    runs = [
        jaxsync.rollout(model, x, s, controller="ros2_admittance", duration=TEST_DURATION, actuation="position")
        for x in (g, back)
    ]
    assert not _metrics.summarize(runs[0], s).dropped
    for a, b in zip(*(jax.tree_util.tree_leaves(r) for r in runs), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_rule_plus_the_coupling_commands_the_papers_law_and_holds_the_ball(model, loop_runs):
    """ros2_synchronous at its own defaults (k_rk = -k_lk = 0.25) holds the ball,
    and so do k_rl = k_ll = 1/2 without the relative-error term (in the squeeze
    the law's 2 k_il e_i is the rule's own offset). Its command carries the
    paper's law, not the rule's offset plus it: with every factor zero the
    rule's yield is taken back out of the reference, the pads are held on the
    plan and the grip force is no longer regulated (measured: 144 % grip
    error against the rule's 0.05 %; the rule's offset plus the coupling
    would be the rule itself)."""
    s = loop_runs["scenario"]
    g = jaxsync.default_gains(model, "position", "ros2_synchronous")
    assert float(g.k_rk) == -float(g.k_lk) == 0.25 and float(g.k_rl) == float(g.k_ll) == 0.5
    run = lambda x: _metrics.summarize(  # noqa: E731
        jaxsync.rollout(model, x, s, controller="ros2_synchronous", duration=TEST_DURATION, actuation="position"), s
    )
    zeros = lambda *names: g._replace(**{k: jnp.zeros(()) for k in names})  # noqa: E731
    coupled, squeeze, stiff = run(g), run(zeros("k_rk", "k_lk")), run(zeros("k_rk", "k_lk", "k_rl", "k_ll"))
    assert _holds(coupled) and _holds(squeeze)
    assert float(coupled.grip_force_error_rel) < 0.01 and float(squeeze.grip_force_error_rel) < 0.01
    rule = loop_runs["default"][1]
    assert float(rule.grip_force_error_rel) < 0.01
    assert float(stiff.grip_force_error_rel) > 0.5, float(stiff.grip_force_error_rel)


def test_the_coupled_reference_is_the_papers_offset_on_the_plan(model):
    """coupled_reference: x_id + k_ik (delta_r - delta_l) + k_il (e_i - e_j) - e_i
    (the squeeze reading) with e_i = J_i dq_i, and the rates
    k_il (edot_i - edot_j) - edot_i: the rule adds e_i back."""
    rng = np.random.default_rng(5)
    n = 7
    g = jaxsync.default_gains(model, "position")._replace(
        k_rk=jnp.asarray(0.3), k_lk=jnp.asarray(-0.2), k_rl=jnp.asarray(0.4), k_ll=jnp.asarray(0.6)
    )
    rot = [_so3.exp(jnp.asarray(rng.normal(0, 0.3, 3))) for _ in range(4)]
    arms = tuple(
        ArmState(
            q=jnp.asarray(rng.normal(size=n)),
            qd=jnp.zeros(n),
            pad_pos=jnp.asarray(rng.normal(0, 0.1, 3)),
            pad_rot=rot[i],
            pad_vel=jnp.zeros(6),
            jac=jnp.asarray(rng.normal(size=(6, n))),
            jac_dot_qd=jnp.zeros(6),
            mass=jnp.eye(n),
            bias=jnp.zeros(n),
            wrist_raw=jnp.zeros(6),
            wrench=jnp.zeros(6),
        )
        for i in range(2)
    )
    ref = _controller.Reference(
        pad_pos=jnp.asarray(rng.normal(0, 0.1, (2, 3))),
        pad_rot=jnp.stack(rot[2:]),
        pad_vel=jnp.asarray(rng.normal(0, 0.1, (2, 6))),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.zeros((2, 6)),
        q_rest=jnp.zeros((2, n)),
    )
    state = _ros2_loop.init(jnp.zeros(2 * n))
    dq = jnp.asarray(rng.normal(0, 1e-3, (2, n)))
    dq_dot = jnp.asarray(rng.normal(0, 1e-2, (2, n)))
    state = state._replace(rule=state.rule._replace(joint_pos=dq, joint_vel=dq_dot))
    out = _ros2_loop.coupled_reference(g, state, arms, ref)
    delta = [
        np.concatenate([ref.pad_pos[i] - arms[i].pad_pos, _so3.rotation_error(ref.pad_rot[i], arms[i].pad_rot)])
        for i in range(2)
    ]
    e = [np.asarray(arms[i].jac @ dq[i]) for i in range(2)]
    e_dot = [np.asarray(arms[i].jac @ dq_dot[i]) for i in range(2)]
    k_ik, k_il = (0.3, -0.2), (0.4, 0.6)
    for i, j in ((0, 1), (1, 0)):
        off = k_ik[i] * (delta[0] - delta[1]) + k_il[i] * (e[i] - e[j]) - e[i]
        np.testing.assert_allclose(out.pad_pos[i], ref.pad_pos[i] + off[:3], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(out.pad_rot[i], _so3.exp(off[3:]) @ ref.pad_rot[i], rtol=1e-12, atol=1e-15)
        rate = k_il[i] * (e_dot[i] - e_dot[j]) - e_dot[i]
        np.testing.assert_allclose(out.pad_vel[i], ref.pad_vel[i] + rate, atol=1e-15)
    assert USED["ros2_synchronous"] == USED["ros2_admittance"] + ("k_rk", "k_lk", "k_rl", "k_ll")


def test_the_torque_stack_refuses_the_rule(model):
    s = fast_scenario()
    g = jaxsync.default_gains(model)
    for call in (
        lambda: jaxsync.rollout(model, g, s, controller="ros2_admittance", duration=TEST_DURATION),
        lambda: jaxsync.rollout(model, g, s, controller="ros2_admittance", duration=TEST_DURATION, backend="mujoco"),
        lambda: jaxsync.make_rollout(model, "ros2_admittance", duration=TEST_DURATION),
    ):
        with pytest.raises(ConfigError, match=r"ros2_admittance.*actuation='torque'"):
            call()
    with pytest.raises(ConfigError, match="static ControllerOptions"):
        _controller.ControllerSwitch.of(_controller.ControllerOptions(kind="ros2_admittance"))
    with pytest.raises(ConfigError, match="distro"):
        _controller.ControllerOptions(kind="ros2_admittance", distro="iron")


def _arm(rng, n=7):
    jac = rng.normal(size=(6, n))
    return ArmState(
        q=rng.normal(size=n) * 0.3,
        qd=rng.normal(size=n) * 0.1,
        pad_pos=rng.normal(size=3) * 0.3,
        pad_rot=np.asarray(_so3.exp(jnp.asarray(rng.normal(size=3)))),
        pad_vel=rng.normal(size=6) * 0.01,
        jac=jac,
        jac_dot_qd=np.zeros(6),
        mass=np.eye(n),
        bias=np.zeros(n),
        wrist_raw=np.zeros(6),
        wrench=rng.normal(size=6) * np.array([10, 10, 10, 0.5, 0.5, 0.5]),
    )


def _by_hand(g, arm, i, q_ref, rule_state, ref, dt, distro):
    """One period of arm ``i`` from the port's own pieces: make_params (as the
    export writes the gains), the CLIK for q_ref, Kinematics, rule.step."""
    m, d, k = (np.asarray(x, dtype=float)[i] for x in (g.imp_mass, g.imp_damping, g.imp_stiffness))
    if distro != "rolling":  # the mass per axis of the base (the world), where the release applies it
        along = np.argmax(np.abs(np.asarray(ref.pad_rot[i])), axis=1)
        m = m[np.concatenate([along, along + 3])]
    params = _ra.make_params(
        m, d / (2.0 * np.sqrt(m * k)), k, joint_damping=0.0, filter_coefficient=1.0, alpha=0.01, distro=distro
    )

    def pose(q):  # the pad pose at q, to first order from the sensed one
        dx = arm.jac @ (arm.q - q)
        return arm.pad_pos - dx[:3], _so3.exp(-dx[3:]) @ arm.pad_rot

    pos, rot = pose(q_ref)
    rate = _joint_space.command_rate(
        arm._replace(pad_pos=pos, pad_rot=rot),
        q_ref,
        ref.pad_pos[i],
        ref.pad_rot[i],
        ref.pad_vel[i],
        ref.q_rest[i],
        g.kp_pos,
        g.kd_pos,
        g.kp_null,
        g.kd_null,
    )
    q_ref = q_ref + dt * rate
    ref_pos, ref_rot = pose(q_ref)

    def transform(p, r):
        return jnp.eye(4).at[:3, :3].set(r).at[:3, 3].set(p)

    kin = _ra.Kinematics(
        jacobian=arm.jac,
        trans_base_ft=transform(arm.pad_pos, arm.pad_rot),
        ref_trans_base_ft=transform(ref_pos, ref_rot),
        rot_world_base=jnp.eye(3),
        rot_base_control=arm.pad_rot,
        rot_base_cog=arm.pad_rot,
    )
    r = arm.pad_rot
    measured = jnp.concatenate([r.T @ arm.wrench[:3], r.T @ arm.wrench[3:]])
    w_ref = -jnp.concatenate([r.T @ ref.wrench[i, :3], r.T @ ref.wrench[i, 3:]])
    command, rule_state = _ra.admittance_rule(distro).step(
        params,
        rule_state,
        kin,
        measured,
        _ra.JointPoint(q_ref, rate, jnp.zeros(7)),
        dt,
        wrench_reference=None if distro == "humble" else w_ref,
    )
    return command.positions, q_ref, rule_state


@pytest.mark.parametrize("distro", ["jazzy", "rolling", "humble"])
def test_each_period_is_the_ports_step(model, distro):
    """Two control periods of the controller against the port's rule.step
    called by hand on the same inputs, per arm."""
    rng = np.random.default_rng(4)
    g = jaxsync.default_gains(model, "position")
    dt = 0.002
    ref = _controller.Reference(
        pad_pos=jnp.asarray(rng.normal(size=(2, 3)) * 0.3),
        pad_rot=jnp.stack([_so3.exp(jnp.asarray(rng.normal(size=3))) for _ in range(2)]),
        pad_vel=jnp.asarray(rng.normal(size=(2, 6)) * 0.01),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.asarray(rng.normal(size=(2, 6))),
        q_rest=jnp.asarray(rng.normal(size=(2, 7)) * 0.3),
    )
    options = _controller.ControllerOptions(kind="ros2_admittance", distro=distro)
    q0 = jnp.asarray(rng.normal(size=14) * 0.3)
    state = _controller.init(q0)
    hand = [(q0[:7], _ra.admittance_rule(distro).init(7)), (q0[7:], _ra.admittance_rule(distro).init(7))]
    step = jax.jit(lambda st, arms, cmd: _controller.step_position(options, g, st, arms, ref, dt, cmd))
    command = q0
    for _ in range(2):
        arms = (_arm(rng), _arm(rng))
        command, state, info = step(state, arms, command)
        for i in range(2):
            positions, q_ref, rs = _by_hand(g, arms[i], i, *hand[i], ref, dt, distro)
            hand[i] = (q_ref, rs)
            np.testing.assert_allclose(command[7 * i : 7 * (i + 1)], positions, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(state.ros2.q_ref[i], q_ref, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(state.ros2.rule.joint_pos[i], rs.joint_pos, rtol=1e-10, atol=1e-14)
            np.testing.assert_allclose(info.offset[i], arms[i].jac @ rs.joint_pos, rtol=1e-10, atol=1e-14)
    assert float(jnp.abs(state.ros2.rule.joint_pos).max()) > 0.0  # the rule moved: the check is not of zeros


def test_the_gains_map_to_the_exports_parameters(model):
    """damping_ratio = D / (2 sqrt(M K)), as the ros2-admittance export writes it; the rule's D is then D."""
    g = jaxsync.default_gains(model, "position")
    for i in range(2):
        p = _ros2_loop.params(g, i)
        np.testing.assert_allclose(_ra.damping(p), g.imp_damping[i], rtol=1e-12)
        assert float(p.cog_force) == 0.0 and float(p.joint_damping) == 0.0
        assert float(p.filter_coefficient) == 1.0 and float(p.alpha) == _joint_space.COMMAND_ALPHA
    assert set(USED["ros2_admittance"]) == {"imp_mass", "imp_damping", "imp_stiffness"}
    # jazzy applies the mass per world axis: the paper plan's pad normal (z) lies along the world's y, so
    # the normal's 3 kg goes to index 1, and damping_ratio is formed with it (the rule's D stays the tuned D)
    pad_rot = jnp.asarray([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])  # the right pad's at the grasp
    p = _ros2_loop.params(g, 0, pad_rot, "jazzy")
    m = np.asarray(g.imp_mass)[0]
    np.testing.assert_allclose(p.mass, m[[1, 2, 0, 4, 5, 3]])
    np.testing.assert_allclose(_ra.damping(p), g.imp_damping[0], rtol=1e-12)
    np.testing.assert_allclose(_ros2_loop.params(g, 0, pad_rot, "rolling").mass, m)  # rolling: the control frame


def test_a_period_is_differentiable_in_the_gains(model):
    """Two periods from the start (q_ref at the sensed joints): finite
    gradients of the commands in every gain the loop reads."""
    rng = np.random.default_rng(0)
    arms = (_arm(rng), _arm(rng))
    ref = _controller.Reference(
        pad_pos=jnp.stack([a.pad_pos for a in arms]),
        pad_rot=jnp.stack([a.pad_rot for a in arms]),
        pad_vel=jnp.zeros((2, 6)),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.ones((2, 6)),
        q_rest=jnp.zeros((2, 7)),
    )
    q0 = jnp.concatenate([a.q for a in arms])
    options = _controller.ControllerOptions(kind="ros2_admittance")

    def loss(g):
        state, command = _controller.init(q0), q0
        for _ in range(2):
            command, state, _ = _controller.step_position(options, g, state, arms, ref, 0.002, command)
        return jnp.sum(command**2)

    grad = jax.jit(jax.grad(loss))(jaxsync.default_gains(model, "position"))
    for name in ("imp_mass", "imp_damping", "imp_stiffness", "kp_pos", "kd_pos", "kp_null", "kd_null"):
        assert np.all(np.isfinite(np.asarray(getattr(grad, name)))), name
    assert float(jnp.abs(grad.imp_mass).max()) > 0.0


def test_the_ft_filter_comes_from_the_scenario(model, loop_runs):
    """Scenario.ft_filter is the rule's ft_sensor.filter_coefficient and the
    filter jaxsync's own laws read the wrench through: a filtered sensor
    changes both runs (the same programs), and both still hold the ball."""
    s, g = loop_runs["scenario"], loop_runs["gains"]
    assert float(_ros2_loop.params(g, 0, ft_filter=0.2).filter_coefficient) == 0.2
    filtered = s._replace(ft_filter=jnp.asarray(0.2))
    run = lambda c, x: jaxsync.rollout(  # noqa: E731
        model, g, x, controller=c, duration=TEST_DURATION, actuation="position"
    )
    a = run("ros2_admittance", filtered)
    assert float(jnp.abs(a.pad_forces - loop_runs["default"][0].pad_forces).max()) > 1e-3
    assert _holds(_metrics.summarize(a, filtered))
    b, c = run("synchronous", filtered), run("synchronous", s)
    assert float(jnp.abs(b.pad_forces - c.pad_forces).max()) > 1e-3
    assert _holds(_metrics.summarize(b, filtered))


def test_every_law_reads_the_rules_filtered_force_error(model):
    """On position-controlled arms jaxsync's laws read f_i - f_id through the
    rule's F/T filter: after each period their filter state is the rule's
    wrench_world (measurement plus set-point, filtered, world frame) on the
    same inputs; with a = 1 the raw error, bit for bit, whatever the filter held."""
    rng = np.random.default_rng(11)
    g = jaxsync.default_gains(model, "position")
    ref = _controller.Reference(
        pad_pos=jnp.asarray(rng.normal(size=(2, 3)) * 0.3),
        pad_rot=jnp.stack([_so3.exp(jnp.asarray(rng.normal(size=3))) for _ in range(2)]),
        pad_vel=jnp.zeros((2, 6)),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.asarray(rng.normal(size=(2, 6))),
        q_rest=jnp.zeros((2, 7)),
    )
    q0 = jnp.asarray(rng.normal(size=14) * 0.3)
    kinds = ("synchronous", "task_space", "ros2_admittance")
    steps = {
        k: jax.jit(
            lambda st, arms, a, k=k: _controller.step_position(
                _controller.ControllerOptions(kind=k), g, st, arms, ref, 0.002, q0, a
            )
        )
        for k in kinds
    }
    states = dict.fromkeys(kinds, _controller.init(q0))
    for _ in range(3):
        arms = (_arm(rng), _arm(rng))
        for k in kinds:
            _, states[k], _ = steps[k](states[k], arms, 0.3)
        for k in kinds[:2]:
            np.testing.assert_allclose(
                states[k].wrench_filter, states["ros2_admittance"].ros2.rule.wrench_world, rtol=1e-10, atol=1e-12
            )
    raw = jnp.stack([a.wrench for a in arms]) - ref.wrench
    assert float(jnp.abs(states["synchronous"].wrench_filter - raw).max()) > 1e-2  # filtered: not the raw error
    one = [steps["synchronous"](states["synchronous"]._replace(wrench_filter=w), arms, 1.0) for w in (raw * 1e3, raw)]
    for x, y in zip(jax.tree_util.tree_leaves(one[0]), jax.tree_util.tree_leaves(one[1]), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(np.asarray(one[0][1].wrench_filter), np.asarray(raw))


def test_the_compliance_probe_reads_the_rules_stand_in(model):
    """The probe (jaxsync.control.compliance) reads ros2_admittance as the
    classical law at the pad and ros2_synchronous as the synchronous law,
    whose offset its command carries at rest: their figures, to the bit, and
    a softer squeeze with the cross term than without it."""
    from jaxsync.control import compliance as _compliance  # noqa: PLC0415 -- this test alone probes

    g = jaxsync.default_gains(model, "position", "ros2_synchronous")
    probe = lambda c, x=g: _compliance.stiffness_at_pad(model, c, x)  # noqa: E731
    assert probe("ros2_admittance") == probe("classical")
    assert probe("ros2_synchronous") == probe("synchronous")
    weak = g._replace(k_rl=jnp.asarray(0.75), k_ll=jnp.asarray(0.75))
    assert probe("ros2_synchronous", weak)["normal"] < 0.9 * probe("ros2_synchronous")["normal"]
