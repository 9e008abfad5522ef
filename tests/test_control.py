"""Control laws, rollouts and metrics: the paper's two controllers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TEST_DURATION, fast_scenario, paper_model

from jaxsync import ConfigError, Trajectory
from jaxsync.control import gains as _gains
from jaxsync.control import impedance as _impedance
from jaxsync.control import so3 as _so3
from jaxsync.control import sync as _sync
from jaxsync.control.gains import default_gains
from jaxsync.io import gains_file
from jaxsync.optimize.tuning.config import Problem
from jaxsync.optimize.tuning.cost import CostWeights, cost, cost_terms
from jaxsync.physics import step as _physics
from jaxsync.sim import metrics as _metrics
from jaxsync.sim import rollout as _rollout
from jaxsync.sim.rollout import make_rollout, rollout, steps_for

# ------------------------------------------------------------ pure laws


@pytest.mark.parametrize("mass,damping,stiffness", [(2.0, 8.0, 50.0), (2.0, 20.0, 50.0), (2.0, 60.0, 50.0)])
def test_admittance_filter_step_response(mass, damping, stiffness):
    """A 1-DoF admittance filter (eq. 15) against M e'' + B e' + K e = F's closed
    form (under-, critically and over-damped). The discretisation is first
    order: at dt = 0.5 ms the error stays below 1 % of the final value."""
    dt, force, n = 5e-4, 3.0, 4000
    frames = jnp.stack([jnp.eye(3), jnp.eye(3)])
    p = lambda v: jnp.full((2, 6), v)  # noqa: E731
    err = jnp.zeros((2, 6)).at[:, 2].set(force)  # a step along the pad normal

    def body(state, _):
        state, _ = _impedance.step(state, p(mass), p(damping), p(stiffness), frames, err, dt)
        return state, state.offset[0, 2]

    _, e = jax.lax.scan(body, _impedance.init(), None, length=n)
    t = dt * np.arange(1, n + 1)
    exact = _impedance.step_response(mass, damping, stiffness, force, t)
    assert np.abs(np.asarray(e) - exact).max() < 0.01 * force / stiffness


def test_so3_log_exp_roundtrip_and_gradient_at_identity():
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        w = axis / np.linalg.norm(axis) * rng.uniform(0, 3.0)  # angles below pi
        np.testing.assert_allclose(np.asarray(_so3.log(_so3.exp(jnp.asarray(w)))), w, atol=1e-9)
    g = jax.grad(lambda w: jnp.sum(_so3.log(_so3.exp(w)) ** 2))(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))
    g = jax.grad(lambda w: jnp.sum(_so3.log(_so3.exp(w))))(jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(g), 1.0, atol=1e-9)


def test_relative_errors_eq13():
    delta = jnp.array([[1.0, 2, 3, 0, 0, 0.1], [0.5, 2, 1, 0, 0, 0.3]])
    out = np.asarray(_sync.relative_compensation(delta, jnp.asarray(0.5), jnp.asarray(-0.25)))
    rel = np.array([0.5, 0, 2, 0, 0, -0.2])
    np.testing.assert_allclose(out, [0.5 * rel, -0.25 * rel])


def test_squeeze_cross_term_cancels_common_motion():
    """Equal world offsets (a rigid translation) cancel; opposite ones (a squeeze) double."""
    pads = jnp.array([[0.65, -0.1, 0.9], [0.65, 0.1, 0.9]])
    common = jnp.array([[0.0, 1, 2, 0.1, 0, 0], [0.0, 1, 2, 0.1, 0, 0]])
    np.testing.assert_allclose(np.asarray(_sync.cross_mapped(common, pads, "squeeze")), 0.0)
    squeeze = jnp.array([[0.0, 1, 0, 0, 0, 0], [0.0, -1, 0, 0, 0, 0]])
    np.testing.assert_allclose(np.asarray(_sync.cross_mapped(squeeze, pads, "squeeze")), 2 * np.asarray(squeeze))
    # the rigid reading keeps the common motion and cancels the squeeze
    np.testing.assert_allclose(np.asarray(_sync.cross_mapped(squeeze, pads, "rigid")), 0.0)
    rot = jnp.array([[0.0, 0, 0, 0, 0, 0], [0.0, 0, 0, 0.1, 0, 0]])  # the left pad turns about x
    # carried through the object, it moves the right pad by dtheta x (p_r - p_l)
    np.testing.assert_allclose(
        np.asarray(_sync.cross_mapped(rot, pads, "rigid"))[0, :3], np.cross([0.1, 0, 0], [0, -0.2, 0]), atol=1e-12
    )


# ------------------------------------------------------------- rollouts


def test_synchronous_with_neutral_gains_is_exactly_classical(rollouts):
    """k_rk = k_lk = 0, no cross term, k_rl = k_ll = 1: the same torques, bit for bit, over a whole rollout."""
    a, b = rollouts["classical"], rollouts["neutral"]
    np.testing.assert_array_equal(np.asarray(a.torque), np.asarray(b.torque))
    np.testing.assert_array_equal(np.asarray(a.qpos), np.asarray(b.qpos))
    # and the default synchronous gains do act differently
    assert np.abs(np.asarray(rollouts["synchronous"].torque) - np.asarray(a.torque)).max() > 1e-3


def test_rollout_shapes_and_finite(model, rollouts):
    n = steps_for(TEST_DURATION, model)
    for name in ("classical", "synchronous"):
        tr = rollouts[name]
        assert tr.time.shape == (n,) and tr.qpos.shape == (n, model.mj_model.nq)
        assert tr.pad_forces.shape == (n, 2, 3) and tr.torque.shape == (n, 14)
        assert tr.wrist_wrench.shape == (n, 2, 6) and tr.delta.shape == (n, 2, 6)
        for leaf in jax.tree_util.tree_leaves(tr):
            assert np.all(np.isfinite(np.asarray(leaf)))


def test_fast_scenario_grasps_lifts_and_holds(rollouts):
    """Sanity of the task: both pads press with ~f_d in the hold and the object follows the plan."""
    s = rollouts["scenario"]
    for name in ("classical", "synchronous"):
        m = _metrics.summarize(rollouts[name], s)
        assert not bool(m.dropped) and not bool(m.nonfinite)
        assert float(m.grip_force_error_rel) < 0.10, name  # the short task does not fully settle
        assert float(m.object_error_rms_m) < 0.005, name
        # carried by the planned lift (the y part re-centres the 3 mm start offset)
        moved = np.asarray(rollouts[name].obj_pos)[-1] - np.asarray(rollouts[name].obj_pos)[0]
        np.testing.assert_allclose(moved, np.asarray(s.lift), atol=0.005, err_msg=name)


def _batch(model):
    fn = jax.jit(jax.vmap(make_rollout(model, "synchronous", TEST_DURATION)))
    g = default_gains()
    gains = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), g)._replace(k_rk=jnp.array([0.5, 0.0]))
    scen = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), fast_scenario(), fast_scenario(object_mass=0.7))
    return fn, gains, scen


def compile_ahead():
    """The vmapped rollout (tests/conftest.py: compiled ahead in a second process)."""
    fn, gains, scen = _batch(paper_model())
    jax.block_until_ready(fn(gains, scen))


@pytest.fixture(scope="module")
def batched(model):
    """vmap over gains and scenarios at once: one compile for the batch."""
    fn, gains, scen = _batch(model)
    return fn, gains, scen, fn(gains, scen)


def test_vmap_over_gains_and_scenarios(model, batched, rollouts):
    fn, gains, scen, out = batched
    n = steps_for(TEST_DURATION, model)
    assert out.qpos.shape == (2, n, model.mj_model.nq) and out.pad_forces.shape == (2, n, 2, 3)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(out))
    # element 0 is the unbatched default rollout
    np.testing.assert_allclose(np.asarray(out.torque[0]), np.asarray(rollouts["synchronous"].torque), atol=1e-6)
    m = jax.vmap(_metrics.summarize)(out, scen)
    assert m.settled_peak_resultant_N.shape == (2,)


def test_no_recompilation_on_new_values(model, batched):
    fn, gains, scen, _ = batched
    before = fn._cache_size()
    fn(gains._replace(k_lk=jnp.array([-0.3, 0.2])), scen._replace(grip_force=jnp.array([8.0, 12.0])))
    assert fn._cache_size() == before


def test_gains_given_as_python_numbers_share_the_compiled_rollout(model, rollouts):
    """rollout() makes weak-typed gains and scenario fields (a Python number,
    jnp.asarray(0.2)) strong and every argument committed to the device
    first: one program for all of them (a weak float, or an array committed
    to a device, as a computation on the model's arrays returns it, was
    another argument type, another 29 s compile), with the same values as
    the strong array."""
    s, g = rollouts["scenario"], rollouts["gains"]
    program = _rollout._jitted(model, TEST_DURATION, 1)
    strong = rollout(model, g._replace(k_rl=jnp.asarray(np.float64(0.2))), s, duration=TEST_DURATION)
    n = program._cache_size()
    committed = jax.device_put(np.float64(0.2), _physics.local_device())
    assert committed.committed and not jnp.asarray(0.2).committed
    cases = (
        (0.2, s),
        (jnp.asarray(0.2), s),
        (committed, jax.device_put(s, _physics.local_device())),
        # scenario fields too: a Python number, a weak array, the same values
        (0.2, s._replace(grip_force=float(s.grip_force), friction=jnp.asarray(float(s.friction)))),
    )
    for weak, scenario in cases:
        tr = rollout(model, g._replace(k_rl=weak), scenario, duration=TEST_DURATION)
        np.testing.assert_array_equal(np.asarray(tr.pad_forces), np.asarray(strong.pad_forces))
    assert program._cache_size() == n == 1


def test_dropped_object_is_flagged(model):
    """A heavy object in a weak grip slips out: flagged with a time, not averaged in."""
    s = fast_scenario(object_mass=3.0, mass_estimate=3.0, grip_force=2.0)
    tr = rollout(model, default_gains(), s, controller="synchronous", duration=TEST_DURATION)
    m = _metrics.summarize(tr, s)
    assert bool(m.dropped)
    assert 0.5 <= float(m.drop_time_s) <= TEST_DURATION


def test_mjx_and_mujoco_c_backends_agree(model, rollouts, shared_rollout):
    """The same jitted control law stepping MuJoCo C. Measured on this task:
    once the pads are closed (t >= t_close) the normal forces agree within
    0.03 N; during the first impact a spike shifted by one step differs by up
    to ~6 N, so the force check starts at t_close. The object agrees within
    0.05 mm throughout."""
    s = rollouts["scenario"]
    c = shared_rollout(model, rollouts["gains"], s, controller="synchronous", duration=TEST_DURATION, backend="mujoco")
    x = rollouts["synchronous"]
    fx = np.asarray(_metrics.normal_forces(x.pad_forces, x.pad_normal))
    fc = np.asarray(_metrics.normal_forces(c.pad_forces, c.pad_normal))
    closed = np.asarray(x.time) >= float(s.t_close)
    assert np.abs(fx - fc)[closed].max() < 0.1
    assert np.abs(np.asarray(x.obj_pos) - np.asarray(c.obj_pos)).max() < 2e-4


# -------------------------------------------------------------- metrics


def _hand_made(T=10):
    """Two pads on the y axis squeezing with 10 N, plus a known net force."""
    z = lambda *shape: jnp.zeros((T, *shape))  # noqa: E731
    pad_pos = jnp.tile(jnp.array([[0.0, -0.1, 1.0], [0.0, 0.1, 1.0]]), (T, 1, 1))
    normal = jnp.tile(jnp.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), (T, 1, 1))
    # right pad pushes +y with 10 N, left -y with 10 N; both carry half of m g = 0.5*9.81
    f = jnp.tile(jnp.array([[0.0, 10.0, 0.5 * 0.5 * 9.81], [0.0, -10.0, 0.5 * 0.5 * 9.81]]), (T, 1, 1))
    f = f.at[7, 0, 0].add(0.3)  # one sample with a 0.3 N net force along x
    time = jnp.arange(T) * 0.1
    delta = z(2, 6).at[:, 0, 1].set(0.002)
    return Trajectory(
        time=time,
        qpos=z(21),
        qvel=z(20),
        obj_pos=z(3),
        obj_vel=z(3),
        plan_obj_pos=z(3),
        plan_obj_acc=z(3),
        plan_grip_force=jnp.full(T, 10.0),
        phase=jnp.full(T, 3),
        pad_pos=pad_pos,
        plan_pad_pos=pad_pos,
        pad_normal=normal,
        pad_forces=f,
        wrist_wrench=z(2, 6),
        torque=jnp.ones((T, 14)),
        offset=z(2, 6),
        delta=delta,
        impedance_offset=z(2, 6),
        at_torque_limit=jnp.zeros((T, 2), bool).at[:3, 1].set(True),
    )


def test_metrics_on_hand_made_contacts():
    tr = _hand_made()
    s = fast_scenario(object_mass=0.5, grip_force=10.0, t_close=0.1, t_squeeze=0.1, t_carry=0.1, settle_time=0.2)
    # settled window: t >= 0.3 + 0.2 = 0.5 -> samples 5..9
    np.testing.assert_allclose(np.asarray(_metrics.normal_forces(tr.pad_forces, tr.pad_normal)), 10.0)
    np.testing.assert_allclose(np.asarray(_metrics.grip_force(tr.pad_forces, tr.pad_pos))[:7], 10.0)
    m = _metrics.summarize(tr, s)
    np.testing.assert_allclose(float(m.settled_peak_resultant_N), 0.3, atol=1e-9)
    np.testing.assert_allclose(float(m.mean_grip_force_N), 10.0 + 0.0, atol=1e-9)
    np.testing.assert_allclose(float(m.grip_force_error_rel), 0.0, atol=1e-9)
    np.testing.assert_allclose(float(m.sync_error_rms_m), 0.002, atol=1e-9)
    np.testing.assert_allclose(float(m.torque_effort), 14.0)
    # the left arm at a torque limit in 3 of the T steps, the right never
    np.testing.assert_allclose(
        [float(m.torque_limit_share_right), float(m.torque_limit_share_left)], [0, 3 / len(tr.time)]
    )
    assert not bool(m.dropped) and np.isnan(float(m.drop_time_s))
    # a known grip error: both pads press 11 N
    m2 = _metrics.summarize(tr._replace(pad_forces=tr.pad_forces * jnp.array([1.0, 1.1, 1.0])), s)
    np.testing.assert_allclose(float(m2.grip_force_error_rel), 0.1, atol=1e-9)


def test_metrics_flag_nonfinite_and_drop():
    tr = _hand_made()
    s = fast_scenario(t_close=0.1, t_squeeze=0.1, t_carry=0.1, settle_time=0.2)
    bad = tr._replace(qpos=tr.qpos.at[6:, 0].set(jnp.nan))
    m = _metrics.summarize(bad, s)
    assert bool(m.nonfinite) and float(m.nonfinite_time_s) == pytest.approx(0.6)
    assert bool(m.dropped)
    far = tr._replace(obj_pos=tr.obj_pos.at[4:, 2].set(-0.05))
    m = _metrics.summarize(far, s)
    assert bool(m.dropped) and float(m.drop_time_s) == pytest.approx(0.4)


def test_a_lost_object_costs_holding_nothing_and_no_gradient():
    tr = _hand_made()
    s = fast_scenario(object_mass=0.5, grip_force=10.0, t_close=0.1, t_squeeze=0.1, t_carry=0.1, settle_time=0.2)
    w = CostWeights()
    far = tr._replace(obj_pos=tr.obj_pos.at[4:, 2].set(-0.05))  # lost from t = 0.4 s (as above)

    def scaled(traj, a):  # the pads' forces scaled by a: a stand-in for a gain
        return cost(traj._replace(pad_forces=a * traj.pad_forces), s, w)

    # held: the cost is the terms' (a 0.3 N peak over a 10 N grip) and moves with the forces
    held_grad = float(jax.grad(lambda a: scaled(tr, a))(1.0))
    assert 0 < float(cost_terms(tr, s, w)["resultant_peak"]) / w.resultant_peak < 40 and abs(held_grad) > 1.0
    # lost: the object's weight borne by nothing and the grip 100 % short, in closed form
    terms = cost_terms(far, s, w)
    weight = 0.5 * 9.81  # N
    assert float(terms["resultant_ms"]) == pytest.approx((weight / 0.01) ** 2, rel=1e-6)
    assert float(terms["grip"]) == pytest.approx(10.0 / 0.01, rel=1e-6)
    assert float(terms["sync"]) == 0.0 and float(terms["effort"]) == 0.0
    # ... whatever the pads did, and without a gradient
    assert float(scaled(far, 1.0)) == pytest.approx(float(scaled(far, 1.7)), rel=1e-12)
    assert float(jax.grad(lambda a: scaled(far, a))(1.0)) == 0.0


def test_the_grip_term_is_flat_below_its_smoothing():
    tr = _hand_made()
    s = fast_scenario(t_close=0.1, t_squeeze=0.1, t_carry=0.1, settle_time=0.2)

    def grip(a, smooth):  # the pads 10 N x (1 + a): a relative grip error a
        traj = tr._replace(pad_forces=tr.pad_forces * (1.0 + a))
        return cost_terms(traj, s, CostWeights(grip_smooth=smooth))["grip"]

    for e in (3e-4, 5e-3):
        for smooth in (1e-4, 1e-3):  # 10 per 1 %, of sqrt(e^2 + s^2)
            assert float(grip(e, smooth)) == pytest.approx(10.0 * np.hypot(e, smooth) / 0.01, rel=1e-6)
    # at 0.03 %, above the default smoothing the slope is nearly the |e|'s (1000 per unit);
    # below a smoothing of 0.1 % it is e / s of that: the term stops chasing errors that small
    assert float(jax.grad(grip)(3e-4, 1e-4)) == pytest.approx(1000 * 3 / np.hypot(3, 1), rel=1e-5)
    assert float(jax.grad(grip)(3e-4, 1e-3)) == pytest.approx(1000 * 0.3 / np.hypot(0.3, 1), rel=1e-5)
    with pytest.raises(ConfigError, match="grip_smooth"):
        Problem(weights=CostWeights(grip_smooth=0.0)).validate()


def test_the_friction_margin_term_reads_the_cone_before_the_loss():
    """Opt-in: 0 while the pads keep half the nominal grip's cone, 1 on its
    edge; a lost rollout's term reads the samples before the loss only and
    keeps a gradient toward squeezing harder, where the other terms have none."""
    tr = _hand_made()  # 10 N squeeze, each pad carrying 2.45 N of the weight: margin 0.755
    s = fast_scenario(object_mass=0.5, grip_force=10.0, t_close=0.1, t_squeeze=0.1, t_carry=0.1, settle_time=0.2)
    w = CostWeights(friction_margin=1.0)
    assert "friction_margin" not in cost_terms(tr, s, CostWeights())  # not computed by default

    def squeezed(traj, a):  # each pad's normal force scaled by a, its tangential load kept
        f_n = _metrics.normal_forces(traj.pad_forces, traj.pad_normal)
        return traj._replace(pad_forces=traj.pad_forces + (a - 1.0) * f_n[..., None] * traj.pad_normal)

    assert 0.0 <= float(cost_terms(tr, s, w)["friction_margin"]) < 1e-4
    # the normal force down to the tangential load (2.45 N at mu = 1): on the cone's edge
    edge = 0.5 * 0.5 * 9.81 / 10.0
    assert float(cost_terms(squeezed(tr, edge), s, w)["friction_margin"]) == pytest.approx(1.0, abs=0.01)
    # lost from t = 0.4 s: whatever the pads do after the loss, the term is the same ...
    far = squeezed(tr._replace(obj_pos=tr.obj_pos.at[4:, 2].set(-0.05)), edge)
    after = far._replace(pad_forces=far.pad_forces.at[4:].multiply(3.0))
    term = lambda traj: float(cost_terms(traj, s, w)["friction_margin"])  # noqa: E731
    assert term(after) == term(far) and term(far) > 0.5
    # ... and squeezing harder before it lowers the cost, the other terms being constant
    # (d margin / d a = 2.45 N / (mu f_d), over the kept share 0.5)
    grad = float(jax.grad(lambda a: cost(squeezed(far, a), s, w))(1.0))
    assert grad == pytest.approx(-edge / 0.5, rel=0.02)
    assert float(jax.grad(lambda a: cost(squeezed(far, a), s, CostWeights()))(1.0)) == 0.0


def test_gains_validation_and_json(tmp_path):
    g = default_gains()
    for k, v in _gains.to_dict(_gains.from_dict(_gains.to_dict(g))).items():
        np.testing.assert_allclose(v, np.asarray(getattr(g, k)))
    with pytest.raises(ConfigError, match="unknown gain"):
        _gains.from_dict({"k_xx": 1.0})
    with pytest.raises(ConfigError, match="k_rk"):
        _gains.from_dict({"k_rk": 1.5})
    with pytest.raises(ConfigError, match="imp_mass"):
        _gains.from_dict({"imp_mass": 0.0})
    p = tmp_path / "g.json"
    p.write_text('{"k_rk": 0.2, "imp_stiffness": [1, 2, 3, 4, 5, 6]}')
    g2 = gains_file.load(p)
    assert float(g2.k_rk) == 0.2 and np.asarray(g2.imp_stiffness).shape == (2, 6)
    p.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read JSON"):
        gains_file.load(p)


def test_the_costs_peak_term_is_the_peak_at_the_resultants_tuning_reaches():
    """At the 0.2-0.6 mN resultants tuned gains leave, the cost's smooth peak follows the peak, not the
    mean: a window whose top 5 % rises from 0.4 to 0.8 mN moves it by most of that rise, while a 2 mN
    temperature moved it by under a tenth (it measured the mean there; docs/convergence.md)."""
    n = 1000
    base = 2e-4 + 5e-5 * jnp.sin(jnp.linspace(0.0, 40.0, n))  # 0.15-0.25 mN
    mask = jnp.ones(n)
    top = jnp.arange(n) % 20 == 0  # 5 % of the window

    def rise(temperature):
        low, high = (_metrics.smooth_max(jnp.where(top, p, base), mask, temperature) for p in (4e-4, 8e-4))
        return float(high - low) / 4e-4

    assert rise(CostWeights().peak_temperature) > 0.5
    assert rise(0.002) < 0.1
