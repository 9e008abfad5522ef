"""The coupling family on top of ros2_controllers' rule (``jaxsync.control.
coupling``, controllers ros2_coupled and ros2_coupled_direct): its special
cases are the rule alone and ros2_synchronous in the closed loop, each
period computes the documented per-axis pad-frame law (checked against a
NumPy transcription), its gradient is the finite difference's, the
compliance probe sees it, and it exports with its placement.

The closed-loop runs use MuJoCo C (the control step compiles alone)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import TEST_DURATION, fast_scenario

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.control import coupling as _coupling
from jaxsync.control import ros2_loop as _ros2_loop
from jaxsync.control.compliance import stiffness_at_pad
from jaxsync.control.names import FAMILY
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.optimize.tuning.params import TuneSpec
from jaxsync.physics.sensing import ArmState

DELAY = 1


def _leaves(traj):
    return [np.asarray(x, dtype=float) for x in jax.tree_util.tree_leaves(traj)]


@pytest.fixture(scope="module")
def runs(model):
    s = fast_scenario(delay=float(DELAY))

    def run(controller, g):
        return jax.block_until_ready(
            jaxsync.rollout(
                model, g, s, controller=controller, duration=TEST_DURATION, actuation="position", backend="mujoco"
            )
        )

    rule = jaxsync.default_gains(model, "position", "ros2_admittance")
    sync = jaxsync.default_gains(model, "position", "ros2_synchronous")
    rng = np.random.default_rng(3)
    filtered = rule._replace(**{f: jnp.asarray(rng.uniform(0.2, 0.9, (2, 6))) for f in _coupling.FILTER_FIELDS})
    direct = _coupling.of_synchronous(sync)
    return {
        "rule": run("ros2_admittance", rule),
        "family_zero": run("ros2_coupled", rule),
        "family_zero_filtered": run("ros2_coupled", filtered),
        "direct_zero": run("ros2_coupled_direct", rule),
        "sync": run("ros2_synchronous", sync),
        "family_sync": run("ros2_coupled", _coupling.of_synchronous(sync)),
        "direct_sync": run("ros2_coupled_direct", direct),
    }


@pytest.mark.parametrize("case", ["family_zero", "family_zero_filtered", "direct_zero"])
def test_no_coupling_is_the_rule_alone_bit_for_bit(runs, case):
    """Every channel's gain 0, whatever the filters and the placement: the
    same closed loop as ros2_admittance, every recorded value equal."""
    for a, b in zip(_leaves(runs["rule"]), _leaves(runs[case]), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_papers_coupling_is_ros2_synchronous(runs):
    """rel = (k_rk, -k_lk), own = k_il - 1, other = -k_il: ros2_synchronous's
    closed loop to rounding (the pad-frame rotations round differently),
    while the coupling moves the loop by far more than that."""
    sync, fam, rule = runs["sync"], runs["family_sync"], runs["rule"]
    assert float(np.abs(np.asarray(sync.pad_forces)).max()) > 1.0  # in contact
    worst = max(float(np.max(np.abs(a - b))) for a, b in zip(_leaves(sync), _leaves(fam), strict=True))
    coupled = max(float(np.max(np.abs(a - b))) for a, b in zip(_leaves(sync), _leaves(rule), strict=True))
    assert worst < 1e-8, worst
    assert coupled > 1e-2, coupled


def test_the_direct_placement_is_not_the_reference_one(runs):
    """The same gains entering onto the rule's reference joints in the same
    period run another loop than through the reference's target."""
    a, b = np.asarray(runs["family_sync"].pad_forces), np.asarray(runs["direct_sync"].pad_forces)
    assert np.all(np.isfinite(b))
    assert float(np.max(np.abs(a - b))) > 1e-3


def _arm(rng, n=7):
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot = rot * np.sign(np.linalg.det(rot))
    return ArmState(
        q=jnp.asarray(rng.normal(size=n) * 0.3),
        qd=jnp.asarray(rng.normal(size=n) * 0.1),
        pad_pos=jnp.asarray(rng.normal(size=3) * 0.1),
        pad_rot=jnp.asarray(rot),
        pad_vel=jnp.asarray(rng.normal(size=6) * 0.1),
        jac=jnp.asarray(rng.normal(size=(6, n))),
        jac_dot_qd=jnp.zeros(6),
        mass=jnp.eye(n),
        bias=jnp.zeros(n),
        wrist_raw=jnp.zeros(6),
        wrench=jnp.asarray(rng.normal(size=6) * 5.0),
    )


def _numpy_family(g, value, rate, delta, e, e_dot, eps, rots):
    """The module docstring's law, transcribed: per arm i (j = 1 - i), the
    four inputs in arm i's planned pad frame, filtered, weighted per axis."""
    out, out_vel = [], []
    for i in range(2):
        j, rot = 1 - i, np.asarray(rots[i])
        pad = lambda v, rot=rot: np.concatenate([rot.T @ v[:3], rot.T @ v[3:]])  # noqa: E731
        k = np.asarray(g.imp_stiffness)[i] + np.asarray(g.imp_damping)[i] / 0.1
        u = [pad(delta[i] - delta[j]), pad(e[i]), pad(e[j]), pad(eps[j]) / k]
        du = [np.zeros(6), pad(e_dot[i]), pad(e_dot[j]), np.zeros(6)]
        o, ov = np.zeros(6), np.zeros(6)
        for c, (gain, filt) in enumerate(zip(_coupling.GAIN_FIELDS, _coupling.FILTER_FIELDS, strict=True)):
            a, cg = np.asarray(getattr(g, filt))[i], np.asarray(getattr(g, gain))[i]
            full = np.diag(cg) + np.asarray(g.cpl_block)[c, i]  # the channel's 6x6 block, its gain the diagonal
            o += full @ (a * u[c] + (1 - a) * value[c, i])
            ov += full @ (a * du[c] + (1 - a) * rate[c, i])
        out.append(np.concatenate([rot @ o[:3], rot @ o[3:]]))
        out_vel.append(np.concatenate([rot @ ov[:3], rot @ ov[3:]]))
    return np.stack(out), np.stack(out_vel)


def _family_case(seed=0):
    rng = np.random.default_rng(seed)
    g = jaxsync.default_gains()
    g = g._replace(
        **{f: jnp.asarray(rng.uniform(-1.5, 1.5, (2, 6))) for f in _coupling.GAIN_FIELDS},
        **{f: jnp.asarray(rng.uniform(0.1, 1.0, (2, 6))) for f in _coupling.FILTER_FIELDS},
        cpl_block=jnp.asarray(rng.uniform(-1.0, 1.0, (4, 2, 6, 6)) * (1.0 - np.eye(6))),
    )
    arms = (_arm(rng), _arm(rng))
    ref = jaxsync.Reference(
        pad_pos=jnp.asarray(rng.normal(size=(2, 3)) * 0.1),
        pad_rot=jnp.stack([_arm(rng).pad_rot, _arm(rng).pad_rot]),
        pad_vel=jnp.zeros((2, 6)),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.asarray(rng.normal(size=(2, 6))),
        q_rest=jnp.zeros((2, 7)),
    )
    state = _ros2_loop.init(jnp.zeros(14))
    state = state._replace(
        rule=state.rule._replace(
            joint_pos=jnp.asarray(rng.normal(size=(2, 7)) * 1e-3),
            joint_vel=jnp.asarray(rng.normal(size=(2, 7)) * 1e-2),
        )
    )
    cstate = _coupling.CouplingState(
        value=jnp.asarray(rng.normal(size=(4, 2, 6)) * 1e-3), rate=jnp.asarray(rng.normal(size=(4, 2, 6)) * 1e-2)
    )
    return g, cstate, state, arms, ref


def test_each_period_is_the_documented_per_axis_law():
    g, cstate, state, arms, ref = _family_case()
    off, off_vel, new = _ros2_loop.family_target(g, cstate, state, arms, ref)
    delta = np.stack(
        [
            np.asarray(jaxsync.control.sync.absolute_error(ref.pad_pos[i], ref.pad_rot[i], a.pad_pos, a.pad_rot))
            for i, a in enumerate(arms)
        ]
    )
    e = np.stack([np.asarray(a.jac) @ np.asarray(state.rule.joint_pos[i]) for i, a in enumerate(arms)])
    e_dot = np.stack([np.asarray(a.jac) @ np.asarray(state.rule.joint_vel[i]) for i, a in enumerate(arms)])
    eps = np.stack([np.asarray(a.wrench) for a in arms]) - np.asarray(ref.wrench)
    want, want_vel = _numpy_family(
        g, np.asarray(cstate.value), np.asarray(cstate.rate), delta, e, e_dot, eps, np.asarray(ref.pad_rot)
    )
    np.testing.assert_allclose(np.asarray(off), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(off_vel), want_vel, rtol=1e-12, atol=1e-15)
    # a second period from the new state filters the same inputs once more: a filter, not a pass-through
    off2, _, _ = _ros2_loop.family_target(g, new, state, arms, ref)
    assert float(np.max(np.abs(np.asarray(off2) - want))) > 1e-6


def test_the_familys_gradient_is_the_finite_differences():
    """d(command)/d(every family gain and filter) through one rule period,
    against central differences: the tuner's gradient reaches each channel."""
    g, cstate, state, arms, ref = _family_case(1)

    @jax.jit
    def command(theta):
        gains = g._replace(**theta)
        out, _, _, _ = _ros2_loop.step(gains, state, arms, ref, 0.002, family=cstate)
        return out

    theta = {f: getattr(g, f) for f in _coupling.FIELDS}
    w = jnp.asarray(np.random.default_rng(2).normal(size=14))
    grad = jax.grad(lambda t: command(t) @ w)(theta)
    for f in _coupling.FIELDS:
        for idx in [(1, 0, 2, 4), (3, 1, 4, 0)] if f == _coupling.BLOCK_FIELD else [(0, 2), (1, 4)]:
            h = 1e-6
            up = dict(theta, **{f: theta[f].at[idx].add(h)})
            down = dict(theta, **{f: theta[f].at[idx].add(-h)})
            fd = float((command(up) - command(down)) @ w) / (2 * h)
            assert abs(float(grad[f][idx]) - fd) <= 1e-6 * max(1.0, abs(fd)), (f, idx, float(grad[f][idx]), fd)
            assert abs(fd) > 1e-9, (f, idx)  # every channel moves the command


def test_the_compliance_probe_reads_the_family(model):
    """The study's equal-compliance bound sees the coupling: no coupling is
    the rule's stiffness, the paper's is ros2_synchronous's, and the own
    channel at +1 on the normal axis halves the normal stiffness."""
    rule = jaxsync.default_gains(model, "position", "ros2_admittance")
    sync = jaxsync.default_gains(model, "position", "ros2_synchronous")
    k_rule = stiffness_at_pad(model, "ros2_admittance", rule)
    assert stiffness_at_pad(model, "ros2_coupled", rule) == k_rule
    k_sync = stiffness_at_pad(model, "ros2_synchronous", sync)
    k_fam = stiffness_at_pad(model, "ros2_coupled", _coupling.of_synchronous(sync))
    for axis in k_sync:
        assert k_fam[axis] == pytest.approx(k_sync[axis], rel=1e-12)
    soft = stiffness_at_pad(model, "ros2_coupled", rule._replace(cpl_own=rule.cpl_own.at[:, 2].set(1.0)))
    assert soft["normal"] == pytest.approx(k_rule["normal"] / 2, rel=1e-3)
    assert soft["tangential"] == k_rule["tangential"]


def test_the_tuner_maps_the_family_into_its_bounds():
    spec = TuneSpec(tuned=_coupling.FIELDS, per_arm=True)
    g = jaxsync.default_gains()._replace(cpl_rel=jnp.full((2, 6), 0.3), cpl_force=jnp.full((2, 6), -1.2))
    theta = spec.init(g)
    back = spec.to_gains(theta, g)
    np.testing.assert_allclose(np.asarray(back.cpl_rel), 0.3, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.cpl_force), -1.2, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.cpl_own_a), 0.95, rtol=1e-12)  # filters start below 1
    far = spec.to_gains({k: v + 50.0 for k, v in theta.items()}, g)
    assert float(np.max(np.asarray(far.cpl_rel))) <= _coupling.GAIN_MAX
    assert float(np.max(np.asarray(far.cpl_rel_a))) <= 1.0
    assert float(np.max(np.asarray(far.cpl_block))) == pytest.approx(_coupling.GAIN_MAX)
    np.testing.assert_array_equal(np.diagonal(np.asarray(far.cpl_block), axis1=-2, axis2=-1), 0.0)  # off it only
    jaxsync.control.gains.validate(far)
    assert spec.size() == 8 * 12 + 4 * 2 * 30
    shared = TuneSpec(tuned=(_coupling.BLOCK_FIELD,))
    moved = shared.to_gains({_coupling.BLOCK_FIELD: shared.init(g)[_coupling.BLOCK_FIELD] + 0.1}, g)
    np.testing.assert_array_equal(np.asarray(moved.cpl_block)[:, 0], np.asarray(moved.cpl_block)[:, 1])
    assert shared.size() == 4 * 30
    with pytest.raises(ConfigError, match="no isotropic form"):
        TuneSpec(tuned=(_coupling.BLOCK_FIELD,), isotropic=True)
    with pytest.raises(ConfigError, match="its diagonal must be 0"):
        jaxsync.control.gains.validate(g._replace(cpl_block=jnp.ones((4, 2, 6, 6))))


def _every_digit_family(g, seed=3):
    """``g`` with every family entry set to values that use every digit (blocks off their diagonal)."""
    rng = np.random.default_rng(seed)
    out = {f: rng.uniform(-0.5, 0.5, (2, 6)) for f in _coupling.GAIN_FIELDS}
    out.update({f: rng.uniform(0.2, 1.0, (2, 6)) for f in _coupling.FILTER_FIELDS})
    out[_coupling.BLOCK_FIELD] = rng.uniform(-0.2, 0.2, (4, 2, 6, 6)) * _coupling.OFF_DIAGONAL
    return g._replace(**{k: jnp.asarray(v) for k, v in out.items()})


def test_the_family_exports_with_its_placement_and_reads_back_bit_for_bit(model, tmp_path):
    """Without a family controller named, the family is refused (the two admittance files alone would run the
    rule uncoupled); named, synchronisation.yaml carries the controller, its placement and every entry, and
    the folder reads back to the same gains, bit for bit, naming the controller (the files alone: the loop's
    stability check, which these gains fail, is tests/test_loop_stability.py's)."""
    g = _every_digit_family(jaxsync.default_gains(model, "position", "ros2_coupled"))
    for controller in (None, "ros2_admittance"):
        with pytest.raises(ConfigError, match="coupling family"):
            jaxsync.export_gains(g, "ros2-admittance", str(tmp_path / "x"), controller=controller)
    assert not (tmp_path / "x").exists()
    for controller, placement in FAMILY.items():
        out = tmp_path / controller
        _export.export(g, "ros2-admittance", str(out), _export.ros2_target(model.mj_model), controller=controller)
        sync = yaml.safe_load((out / "synchronisation.yaml").read_text())["dual_arm_synchronisation"]["ros__parameters"]
        assert (sync["schema_version"], sync["controller"], sync["coupling_placement"]) == (3, controller, placement)
        np.testing.assert_array_equal(sync["cpl_other_left"], np.asarray(g.cpl_other)[1])
        np.testing.assert_array_equal(np.reshape(sync["cpl_block_force_right"], (6, 6)), np.asarray(g.cpl_block)[3, 0])
        back = gains_file.load(str(out))
        for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(g), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert gains_file.controller_of(str(out)) == controller
    # what was read back re-simulates the identical trajectory (MuJoCo C, the family's own step)
    s = fast_scenario(delay=float(DELAY))
    back = gains_file.load(str(tmp_path / "ros2_coupled"))
    roll = lambda x: jaxsync.rollout(  # noqa: E731
        model, x, s, controller="ros2_coupled", duration=TEST_DURATION, actuation="position", backend="mujoco"
    )
    a, b = _leaves(roll(g)), _leaves(roll(back))
    assert np.isfinite(a[0]).all()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    # a hand-edited placement that is not the controller's, or an entry cut short, is named
    text = (tmp_path / "ros2_coupled" / "synchronisation.yaml").read_text()
    for old, new in (
        ("coupling_placement: reference", "coupling_placement: direct"),
        ("cpl_rel_right: [", "cpl_rel_right: [1.0, "),
    ):
        (tmp_path / "ros2_coupled" / "synchronisation.yaml").write_text(text.replace(old, new))
        with pytest.raises(ConfigError, match="coupling_placement|cpl_rel_right must be a list of 6"):
            gains_file.load(str(tmp_path / "ros2_coupled"))
    assert jaxsync.export_gains(g, "yaml", str(tmp_path / "y")).same
