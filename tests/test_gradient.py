"""Gradient truth: the implicit adjoint of MJX's constraint solve (jaxsync.physics.step.solve_implicit).

Float64. One physics step in a clamp (both pads and the stand in contact, the
object sliding so that the elliptic cone's middle zone is active): the
implicit derivative against reverse mode through 40 unrolled Newton
iterations (where both have converged) and against central differences. The
whole 4 s task (approach, first contact, squeeze, lift, carry, hold) at a gain
point no other test uses, on randomised scenarios: the tuner's loss gradient
against central differences.
"""

from __future__ import annotations

import jax
import jax.extend.core
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import build_tuning_program, paper_model
from jax.flatten_util import ravel_pytree
from mujoco import mjx

import jaxsync
from jaxsync.optimize.tuning import loss as loss_mod
from jaxsync.optimize.tuning import tune as tune_mod
from jaxsync.optimize.tuning.scenarios import sample_scenarios, training_base
from jaxsync.physics import step as _physics
from jaxsync.sim import closed_loop as _closed_loop
from jaxsync.sim import scenario as _scenario

UNROLLED_ITERATIONS = 40


def _clamp_state(model):
    """A state with both pads pressed 0.5 mm into the object, the object
    sliding (tangential contact forces), random joint velocities."""
    s = _scenario.default_scenario(object_offset=[0.0, 0.0, 0.0], object_radius=0.1005)
    mx = _scenario.apply_to_model(model.mjx_model, s, model.index)
    c = _closed_loop.consts(model, _closed_loop.REST_KEY)
    qpos = np.asarray(_closed_loop.initial_qpos(model, c, s))
    rng = np.random.default_rng(3)
    qvel = 0.05 * rng.standard_normal(model.mj_model.nv)
    va = model.index.object_dof_adr
    qvel[va : va + 3] = [0.01, -0.004, 0.02]
    d = _physics.put_data(model.mj_model, mujoco.MjData(model.mj_model))
    d = d.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
    ctrl = jnp.asarray(2.0 * rng.standard_normal(model.mj_model.nu))
    return mx, d, ctrl


def _unrolled_model(mx):
    """The same model with one Newton iteration per ``mjx.solve`` call (the
    solve is then a plain function, differentiable through its iterations)."""
    opt = mx.opt.replace(iterations=1)
    return mx.replace(opt=opt)


def _one_step(model):
    """f(p) = a scalar of one physics step's qacc, constraint forces and wrist
    sensors, with p entering the velocity, the torques and the friction; and
    its gradient by the implicit adjoint and through unrolled iterations."""
    mx, d, ctrl = _clamp_state(model)
    weights = jnp.asarray(np.random.default_rng(5).standard_normal(20))
    nv = model.mj_model.nv

    def step(p, unrolled):
        m = _unrolled_model(mx) if unrolled else mx
        fr = m.pair_friction.at[:, :2].multiply(1.0 + p[-1])
        m = m.replace(pair_friction=fr)
        dd = _physics.before_control(m, d.replace(qvel=d.qvel + p[:nv]), "tree")  # as gradient programs run it
        u = ctrl + p[nv : nv + model.mj_model.nu]
        out = _physics.after_control(m, dd, u, UNROLLED_ITERATIONS)
        value = (
            jnp.dot(weights, out.qacc)
            + jnp.sum(out._impl.efc_force**2) * 1e-2
            + jnp.sum(out.sensordata[:12] * weights[:12])
        )
        # the step's solve, plain (MJX's) and implicit (jaxsync's), values only:
        # the sliding-clamp test reads them from this same program
        m = m.replace(pair_friction=jax.lax.stop_gradient(fr))
        accel = jax.lax.stop_gradient(mjx.fwd_acceleration(m, mjx.fwd_actuation(m, dd.replace(ctrl=u))))
        return value, (mjx.solve(m, accel), _physics.solve_implicit(m, accel))

    p0 = jnp.zeros(nv + model.mj_model.nu + 1)
    # one program gives the values (central differences), the gradient and the solves
    value_and_grad = jax.jit(jax.value_and_grad(step, has_aux=True), static_argnums=1)
    fn = lambda p, unrolled: step(p, unrolled)[0]  # noqa: E731
    return {
        "fn": fn,
        "f": lambda p, unrolled: value_and_grad(p, unrolled)[0][0],
        "grad": lambda p, unrolled: value_and_grad(p, unrolled)[1],
        "solves": lambda: value_and_grad(p0, False)[0][1],
        # forward mode through the implicit solve
        "jvp": jax.jit(lambda p, v: jax.jvp(lambda q: fn(q, False), (p,), (v,))),
        "p0": p0,
        "mx": mx,
    }


def compile_ahead():
    """This module's programs, in the order its tests come (tests/conftest.py:
    compiled ahead in a second process): the step's gradient, the tuner's
    (the session's ``tuning_program``), the step's forward mode."""
    model = paper_model()
    step = _one_step(model)
    jax.block_until_ready(step["solves"]())
    tuning = build_tuning_program(model)
    jax.block_until_ready(tuning["value_and_grad"](tuning["theta0"], tuning["scenarios"]))
    p0 = step["p0"]
    jax.block_until_ready(step["jvp"](p0, jnp.ones_like(p0)))


@pytest.fixture(scope="module")
def one_step(model):
    """``_one_step``: its programs compiled once for the module."""
    return _one_step(model)


def test_forward_values_are_mjx_solve_in_a_sliding_clamp(one_step, model):
    """The implicit path changes no value: qacc and forces equal plain
    mjx.solve's, bit for bit. And the step under test is the hard case: both
    pads pressed in with a normal force, friction acting (the elliptic cone's
    middle zone)."""
    mx = one_step["mx"]
    plain, implicit = one_step["solves"]()  # at p = 0: the clamp state as it is
    np.testing.assert_array_equal(np.asarray(plain.qacc), np.asarray(implicit.qacc))
    np.testing.assert_array_equal(np.asarray(plain._impl.efc_force), np.asarray(implicit._impl.efc_force))
    r = _physics.constraint_residual(mx, plain, plain.qacc)[0]
    assert float(jnp.linalg.norm(r)) < 1e-8 * float(jnp.linalg.norm(plain.qfrc_smooth))
    for arm in model.index.arms:
        assert float(plain._impl.contact.dist[arm.contact_id]) < -4e-4
        f = np.asarray(_physics.contact_force_on(mx, plain, arm.contact_id, arm.object_is_geom1))
        normal = abs(f[1])  # the clamping axis is y
        assert normal > 1.0
        assert np.hypot(f[0], f[2]) > 1e-3 * normal  # friction acts


def _count(jaxpr, name: str) -> int:
    """Equations of primitive ``name`` in a jaxpr and all its sub-jaxprs."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == name
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            n += _count(sub, name)
    return n


def test_rematerialised_backward_pass_does_not_solve_again(one_step):
    """Under ``jax.checkpoint`` with ``_physics.REMAT_POLICY`` (what
    ``make_rollout(remat=True)`` uses) the converged solve's outputs are kept:
    the gradient's program holds MJX's solve loops once (the forward pass),
    not a second time to recompute them in the backward pass."""
    step, p0 = one_step["fn"], one_step["p0"]

    def loops(policy):
        f = jax.checkpoint(lambda p: step(p, False), policy=policy)
        return _count(jax.make_jaxpr(jax.grad(f))(p0).jaxpr, "while")

    kept, default = loops(_physics.REMAT_POLICY), loops(None)
    assert kept > 0
    assert kept < default


@pytest.mark.slow
def test_implicit_equals_unrolled_where_both_converge(one_step):
    g_implicit = np.asarray(one_step["grad"](one_step["p0"], False))
    g_unrolled = np.asarray(one_step["grad"](one_step["p0"], True))
    assert np.all(np.isfinite(g_implicit))
    np.testing.assert_allclose(g_implicit, g_unrolled, rtol=1e-6, atol=1e-6 * np.abs(g_unrolled).max())


def test_one_step_gradient_matches_central_differences(one_step):
    f, p0 = one_step["f"], one_step["p0"]
    g = np.asarray(one_step["grad"](p0, False))
    h = 1e-6
    fd = np.array([(f(p0.at[i].add(h), False) - f(p0.at[i].add(-h), False)) / (2 * h) for i in range(p0.size)])
    assert np.linalg.norm(fd - g) <= 1e-5 * np.linalg.norm(fd)


# ------------------------------------------------------------- the full task


def _four_point(fb, flat, h, chunk):
    """Central differences of fb (batched over parameter vectors), O(h^4).

    ``chunk`` must divide the 4 n points: every call of fb has one shape (one compile)."""
    n = flat.size
    assert (4 * n) % chunk == 0, (n, chunk)
    pts = jnp.stack([flat.at[i].add(c * h) for i in range(n) for c in (-2, -1, 1, 2)])
    vals = np.concatenate([np.asarray(fb(pts[j : j + chunk])) for j in range(0, len(pts), chunk)]).reshape(n, 4)
    return (vals[:, 0] - 8 * vals[:, 1] + 8 * vals[:, 2] - vals[:, 3]) / (12 * h)


@pytest.mark.slow
def test_full_task_gradient_matches_central_differences(tuning_program):
    """The tuner's own gradient program (``jaxsync tune``'s defaults: the
    exact full-horizon gradient over 2000 steps, no truncation; batch 2) at a
    gain point no other test uses, on randomised scenarios: cosine >= 0.9999
    and relative error <= 1e-4 against 4-point central differences in all 22
    parameters."""
    loss, scen = tuning_program["loss"], tuning_program["scenarios"]
    # a point other than the defaults
    theta = jax.tree_util.tree_map(
        lambda x: x + 0.1 * jnp.cos(jnp.arange(x.size).reshape(x.shape) + 1.0), tuning_program["theta0"]
    )
    (value, _), grad = tuning_program["value_and_grad"](theta, scen)
    g = np.asarray(ravel_pytree(grad)[0])
    flat, unravel = ravel_pytree(theta)
    fb = jax.jit(jax.vmap(lambda th: loss(unravel(th), scen)[0]))
    # 88 points in 4 calls of 22 (x 2 scenarios: a vmap of 44, below the CPU limit of 64)
    fd = _four_point(fb, flat, 3e-4, chunk=22)  # the cost's sharp peak term: 1e-3 truncates at 3e-4
    cos = fd @ g / np.linalg.norm(fd) / np.linalg.norm(g)
    rel = np.linalg.norm(fd - g) / np.linalg.norm(fd)
    assert np.isfinite(value) and cos >= 0.9999 and rel <= 1e-4, (cos, rel)


def test_full_task_gradient_along_a_random_direction(tuning_program):
    """The default run's check of the tuner's own full-horizon gradient (the
    22-parameter check above is in the slow tier): at the same point, the
    derivative along a random direction, from central differences of the same
    program's values (no other compile), within 1e-4 of the gradient's norm."""
    scen, vg = tuning_program["scenarios"], tuning_program["value_and_grad"]
    theta = jax.tree_util.tree_map(
        lambda x: x + 0.1 * jnp.cos(jnp.arange(x.size).reshape(x.shape) + 1.0), tuning_program["theta0"]
    )
    (value, _), grad = vg(theta, scen)
    g = np.asarray(ravel_pytree(grad)[0])
    flat, unravel = ravel_pytree(theta)
    norm = np.linalg.norm(g)
    r = np.random.default_rng(3).standard_normal(g.size)
    v, h = r / np.linalg.norm(r), 1e-4
    plus, minus = (float(vg(unravel(flat + c * h * v), scen)[0][0]) for c in (1, -1))
    fd = (plus - minus) / (2 * h)
    assert abs(fd - g @ v) <= 1e-4 * norm, (fd, g @ v, norm)
    assert np.isfinite(value) and norm > 0 and abs(g @ v) > 1e-3 * norm


def test_forward_mode_agrees_with_reverse_mode(one_step):
    """jax.jvp through the implicit solve (custom_root supports both modes)."""
    p0 = one_step["p0"]
    v = jnp.asarray(np.random.default_rng(11).standard_normal(p0.size))
    g = one_step["grad"](p0, False)
    _, dv = one_step["jvp"](p0, v)
    assert abs(float(dv - g @ v)) <= 1e-9 * float(jnp.linalg.norm(g) * jnp.linalg.norm(v))


@pytest.mark.slow
def test_position_stack_gradient_along_random_directions(model):
    """The tuner's gradient on position-controlled arms (the servo on every
    substep, the command integrated through the damped least squares and
    delayed 1 and 3 periods, servo gains scaled 0.8 and 1.2; the short task):
    along two random directions, within 1e-4 of the gradient's norm of
    central differences of the same program's values."""
    cfg = tune_mod.TuneConfig(batch=2, task="short", actuation="position", delay=(1, 3), servo_spread=0.2)
    base = jaxsync.default_gains(model, "position")
    loss = loss_mod.make_loss(model, base, cfg)
    scen = sample_scenarios(
        jax.random.key(5), 2, training_base(cfg.training)[0], stratified=True, delay=(1, 3), servo_spread=0.2
    )
    assert sorted(np.asarray(scen.delay).tolist()) == [1.0, 3.0]
    theta = jax.tree_util.tree_map(
        lambda x: x + 0.1 * jnp.sin(jnp.arange(x.size).reshape(x.shape) + 2.0), cfg.problem.tuned.init(base)
    )
    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    (value, _), grad = vg(theta, scen)
    g = np.asarray(ravel_pytree(grad)[0])
    flat, unravel = ravel_pytree(theta)
    norm = np.linalg.norm(g)
    assert np.isfinite(value) and norm > 0
    rng = np.random.default_rng(4)
    for _ in range(2):
        r = rng.standard_normal(g.size)
        v, h = r / np.linalg.norm(r), 1e-4
        plus, minus = (float(vg(unravel(flat + c * h * v), scen)[0][0]) for c in (1, -1))
        fd = (plus - minus) / (2 * h)
        assert abs(fd - g @ v) <= 1e-4 * norm, (fd, g @ v, norm)
