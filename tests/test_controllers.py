"""The literature baselines and the compliance measures, against closed forms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.control import baselines, compliance
from jaxsync.control import controller as ctrl
from jaxsync.control.gains import USED, default_gains
from jaxsync.control.impedance import step_response
from jaxsync.optimize.studies import sweep_spec
from jaxsync.sim import metrics as _metrics

DT = 0.002
PADS = np.array([[0.65, -0.06, 0.85], [0.65, 0.06, 0.85]])  # the clamp axis along world y
# pad frames: z (the normal) into the object, x along world x
ROTS = np.stack([np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])])


def test_pad_frames_of_the_probe_geometry_point_into_the_object():
    for i in range(2):
        np.testing.assert_allclose(ROTS[i] @ ROTS[i].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(ROTS[i]), 1.0)
    inward = PADS.mean(0) - PADS
    for i in range(2):
        assert ROTS[i][:, 2] @ inward[i] > 0


def _ref(wrench=None):
    return ctrl.Reference(
        pad_pos=jnp.asarray(PADS),
        pad_rot=jnp.asarray(ROTS),
        pad_vel=jnp.zeros((2, 6)),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.zeros((2, 6)) if wrench is None else wrench,
        q_rest=jnp.zeros((2, 7)),
    )


def _offsets(kind, gains, wrench, steps, shift=0.0):
    """Offsets after ``steps`` periods with the pads held at their plan (moved
    by ``shift`` (2, 3), m) and a constant wrench error."""
    pads = ctrl.Pads(pos=jnp.asarray(PADS + shift), rot=jnp.asarray(ROTS), wrench=jnp.asarray(wrench))
    state = ctrl.init()
    for _ in range(steps):
        out, state, _, _ = ctrl.offsets(ctrl.ControllerOptions(kind=kind), gains, state, pads, _ref(), DT)
    return [np.asarray(x) for x in out], state


def test_grasp_split_is_the_null_space_decomposition_of_eq_7():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(2, 6))
    h_e, h_i = baselines.split_wrenches(jnp.asarray(h), jnp.asarray(PADS))
    w = np.asarray(baselines.grasp_matrix(jnp.asarray(PADS), jnp.asarray(PADS.mean(0))))
    # the external wrench: the sum of forces, the moments and lever arms about the midpoint
    r = PADS - PADS.mean(0)
    np.testing.assert_allclose(h_e[:3], h[:, :3].sum(0), atol=1e-12)
    np.testing.assert_allclose(h_e[3:], h[:, 3:].sum(0) + np.cross(r, h[:, :3]).sum(0), atol=1e-12)
    np.testing.assert_allclose(w @ np.asarray(h_i).reshape(12), 0.0, atol=1e-12)  # internal: no net wrench
    # a pure squeeze is all internal; the same force on both pads all external
    squeeze = np.zeros((2, 6))
    squeeze[0, 1], squeeze[1, 1] = -3.0, 3.0
    e, i = baselines.split_wrenches(jnp.asarray(squeeze), jnp.asarray(PADS))
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    np.testing.assert_allclose(i, squeeze, atol=1e-12)
    common = np.zeros((2, 6))
    common[:, 2] = 1.5
    e, i = baselines.split_wrenches(jnp.asarray(common), jnp.asarray(PADS))
    np.testing.assert_allclose(i, 0.0, atol=1e-12)
    np.testing.assert_allclose(e[:3], [0.0, 0.0, 3.0], atol=1e-12)


def test_rigid_transport_moves_the_pads_with_the_object():
    pads = jnp.asarray(PADS)
    moved = np.asarray(baselines.transport_to_pads(jnp.array([0.01, 0, 0, 0, 0, 0.0]), pads))
    np.testing.assert_allclose(moved[:, :3], [[0.01, 0, 0]] * 2, atol=1e-12)
    spin = np.asarray(baselines.transport_to_pads(jnp.array([0, 0, 0, 0, 0, 0.1]), pads))
    r = PADS - PADS.mean(0)
    np.testing.assert_allclose(spin[:, :3], np.cross([0, 0, 0.1], r), atol=1e-12)
    np.testing.assert_allclose(spin[:, 3:], [[0, 0, 0.1]] * 2, atol=1e-12)


@pytest.mark.parametrize("wrench_kind", ["squeeze", "common"])
def test_object_impedance_at_twice_one_arm_is_the_classical_controller_for_forces(wrench_kind):
    """With M_E, D_E, K_E twice one arm's (the defaults), the external filter
    moves both pads as the two classical filters would for a common force,
    and a squeeze goes to the internal filters, which are the classical ones."""
    g = default_gains()
    w = np.zeros((2, 6))
    if wrench_kind == "squeeze":
        w[0, 1], w[1, 1] = -0.8, 0.8
    else:
        w[:, 0] = 0.4
    (off_c, rate_c, acc_c), _ = _offsets("classical", g, w, 30)
    (off_o, rate_o, acc_o), _ = _offsets("object_impedance", g, w, 30)
    assert np.abs(off_c).max() > 1e-5
    np.testing.assert_allclose(off_o, off_c, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(rate_o, rate_c, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(acc_o, acc_c, rtol=1e-5, atol=1e-8)


def test_task_space_is_a_pi_loop_on_the_internal_force():
    """x_ic - x_id = K_P h_I + K_I (n dt) h_I for a constant internal wrench
    error h_I; an external force moves nothing (the absolute variable tracks its plan)."""
    g = default_gains()
    f = 0.8
    w = np.zeros((2, 6))
    w[0, 1], w[1, 1] = -f, f  # squeeze in world y = the pads' normals
    n = 40
    (off, rate, acc), state = _offsets("task_space", g, w, n)
    kp, ki = np.asarray(g.force_p)[2], np.asarray(g.force_i)[2]
    normal_r = ROTS[0][:, 2]  # +y
    # the error on the right pad is -f along world y = -f along its normal
    np.testing.assert_allclose(off[0, :3] @ normal_r, -f * (kp + ki * n * DT), rtol=1e-9)
    np.testing.assert_allclose(rate[0, :3] @ normal_r, -f * ki, rtol=1e-9)
    np.testing.assert_allclose(off[0, :3], -off[1, :3], atol=1e-15)  # the relative variable, shared equally
    np.testing.assert_allclose(acc, 0.0)
    common = np.zeros((2, 6))
    common[:, 2] = 1.0
    (off, _, _), _ = _offsets("task_space", g, common, 10)
    np.testing.assert_allclose(off, 0.0, atol=1e-15)


def test_every_controller_reads_its_own_gains_only():
    """A change to the gains a controller does not read (``USED``) leaves its offsets as they are."""
    g = default_gains()
    rng = np.random.default_rng(1)
    w, shift = rng.normal(size=(2, 6)) * 0.5, rng.normal(size=(2, 3)) * 1e-3
    for kind in jaxsync.CONTROLLERS:
        (off, _, _), _ = _offsets(kind, g, w, 5, shift)
        others = [f for f in g._fields if f not in USED[kind] and not f.startswith(("kp_", "kd_"))]
        changed = g._replace(**{f: getattr(g, f) * 1.7 for f in others})
        (off2, _, _), _ = _offsets(kind, changed, w, 5, shift)
        np.testing.assert_array_equal(off, off2, err_msg=kind)
        for f in USED[kind]:  # and each gain it reads does change them
            (off3, _, _), _ = _offsets(kind, g._replace(**{f: getattr(g, f) * 1.7}), w, 5, shift)
            assert np.abs(off3 - off).max() > 1e-9, (kind, f)


def test_traced_switch_computes_what_each_static_controller_computes():
    g = default_gains()
    w = np.random.default_rng(2).normal(size=(2, 6))
    pads = ctrl.Pads(pos=jnp.asarray(PADS) + 1e-3, rot=jnp.asarray(ROTS), wrench=jnp.asarray(w))
    for kind in jaxsync.CONTROLLERS:
        static = ctrl.ControllerOptions(kind=kind)
        a = ctrl.offsets(static, g, ctrl.init(), pads, _ref(), DT)
        b = jax.jit(lambda s: ctrl.offsets(s, g, ctrl.init(), pads, _ref(), DT))(ctrl.ControllerSwitch.of(static))
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15, err_msg=kind)


# ------------------------------------------------------------------ compliance


def _stiffness(kind, g, **kw):
    return {k: float(v) for k, v in compliance.apparent_stiffness(kind, g, PADS, ROTS, DT, **kw).items()}


def test_classical_apparent_stiffness_follows_its_admittance_filter():
    """Tangentially (M 2 kg, K 1500 N/m, critically damped) the pad yields as
    the mass-spring-damper's step response: K_app = 1 N / e(0.1 s)."""
    g = default_gains()
    m, b, k = (float(np.asarray(x)[0, 0]) for x in (g.imp_mass, g.imp_damping, g.imp_stiffness))
    expected = 1.0 / float(step_response(m, b, k, 1.0, compliance.PROBE_TIME))
    got = _stiffness("classical", g)["tangential"]
    np.testing.assert_allclose(got, expected, rtol=0.05)  # implicit Euler at 2 ms against the continuous filter
    # the soft normal axis: yielding, an integrating force loop, ~ B / t
    b_n = float(g.imp_damping[0, 2])
    np.testing.assert_allclose(_stiffness("classical", g)["normal"], b_n / compliance.PROBE_TIME, rtol=0.05)


@pytest.mark.parametrize("k", [(0.5, -0.5, 0.5, 0.5), (0.2, -0.3, 0.7, 0.4), (0.0, 0.0, 1.0, 1.0)])
def test_synchronous_apparent_stiffness_closed_form(k):
    """With the pads at their references (delta_i = -offset_i) and only the
    right pad pushed, the squeeze cross term gives d = off_r - off_l =
    (k_rl + k_ll) e / (1 + k_rk - k_lk) and off_r = k_rl e - k_rk d: the
    classical stiffness divided by k_rl - k_rk (k_rl + k_ll) / (1 + k_rk - k_lk)."""
    k_rk, k_lk, k_rl, k_ll = k
    g = default_gains()._replace(k_rk=k_rk, k_lk=k_lk, k_rl=k_rl, k_ll=k_ll)
    factor = k_rl - k_rk * (k_rl + k_ll) / (1 + k_rk - k_lk)
    classical = _stiffness("classical", g)
    sync = _stiffness("synchronous", g)
    for axis in ("normal", "tangential"):
        np.testing.assert_allclose(sync[axis], classical[axis] / factor, rtol=1e-6, err_msg=axis)


def test_task_space_apparent_stiffness_closed_form():
    """Along the normal half a one-pad force is internal: dx = (K_P + K_I T) / 2."""
    g = default_gains()
    n = round(compliance.PROBE_TIME / DT)
    kp, ki = np.asarray(g.force_p), np.asarray(g.force_i)
    got = _stiffness("task_space", g)
    np.testing.assert_allclose(got["normal"], 2 / (kp[2] + ki[2] * n * DT), rtol=1e-9)
    # tangentially the force also turns the object: h_I = (I - W^+ W) h, W of eq. 7 (numpy here)
    r = PADS - PADS.mean(0)
    hat = lambda v: np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])  # noqa: E731
    w = np.hstack([np.block([[np.eye(3), np.zeros((3, 3))], [hat(ri), np.eye(3)]]) for ri in r])
    tangential = 0.0
    for a in (0, 1):
        h = np.zeros(12)
        h[:3] = ROTS[0][:, a]
        h_i = h - w.T @ np.linalg.solve(w @ w.T, w @ h)
        local = ROTS[0].T @ h_i[:3]
        dx = ROTS[0] @ ((kp[:3] + ki[:3] * n * DT) * local) @ ROTS[0][:, a]
        tangential = max(tangential, 1 / dx)
    np.testing.assert_allclose(got["tangential"], tangential, rtol=1e-9)


def test_apparent_stiffness_is_differentiable_and_softens_with_damping():
    g = default_gains()
    grad = jax.grad(lambda g: compliance.apparent_stiffness("classical", g, PADS, ROTS, DT)["normal"])(g)
    assert float(grad.imp_damping[0, 2]) > 0  # more normal damping: stiffer over 0.1 s
    assert float(jnp.abs(grad.k_rk)) == 0.0  # not read by the classical controller


def test_first_impact_peak_and_internal_force_error_on_hand_made_forces():
    t = np.arange(0, 0.5, DT)
    normal = np.zeros((len(t), 2))
    normal[50:, 0] = 2.0
    normal[60, 0] = 7.0  # inside the right pad's first 0.1 s of contact
    normal[150, 0] = 9.0  # later: not its first impact
    normal[80:, 1] = 3.0
    normal[90, 1] = 5.0
    dirs = np.broadcast_to(np.array([[0, 1.0, 0], [0, -1.0, 0]]), (len(t), 2, 3))
    forces = normal[..., None] * dirs
    peak = _metrics.first_impact_peak(jnp.asarray(forces), jnp.asarray(dirs), jnp.asarray(t))
    np.testing.assert_allclose(float(peak), 7.0)
    pos = np.broadcast_to(PADS, (len(t), 2, 3))
    err = np.asarray(_metrics.internal_force_error(jnp.asarray(forces), jnp.asarray(pos), 2.5))
    # (f_r - f_l) / 2 along +y is (2 + 3) / 2 = 2.5 late on: no error; a shear pair counts
    np.testing.assert_allclose(err[-1], 0.0, atol=1e-12)
    sheared = forces.copy()
    sheared[:, 0, 0] += 0.4
    sheared[:, 1, 0] -= 0.4
    err = np.asarray(_metrics.internal_force_error(jnp.asarray(sheared), jnp.asarray(pos), 2.5))
    np.testing.assert_allclose(err[-1], 0.4, atol=1e-12)


def test_baselines_hold_the_ball_on_the_short_task(rollouts):
    """Each baseline, at its default gains, grasps, lifts and holds."""
    s = rollouts["scenario"]
    for name in ("object_impedance", "task_space"):
        m = _metrics.summarize(rollouts[name], s)
        assert not bool(m.dropped) and not bool(m.nonfinite), name
        assert not bool(m.chattering), name
        assert float(m.grip_force_error_rel) < 0.10, name
        assert float(m.object_error_rms_m) < 0.005, name


def test_sweeps_address_the_baselines_per_axis_gains():
    t = sweep_spec.resolve_name("force_i.z")
    assert (t.kind, t.field, t.index) == ("gain", "force_i", (2,))
    assert sweep_spec.resolve_name("obj_stiffness").index == (slice(None),)
    with pytest.raises(jaxsync.ConfigError, match="per-axis gains"):
        sweep_spec.resolve_name("force_i.r.z")
    p = sweep_spec.parse_param("force_i.z=0.0002,0.0008")
    g, _ = sweep_spec.build_batch([p], np.array([[0.0002], [0.0008]]), default_gains(), jaxsync.default_scenario())
    np.testing.assert_allclose(g.force_i[:, 2], [0.0002, 0.0008])
    np.testing.assert_allclose(g.force_i[:, :2], np.broadcast_to(np.asarray(default_gains().force_i)[:2], (2, 2)))
