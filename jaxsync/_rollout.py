"""Closed-loop rollouts: one jit-compiled ``lax.scan`` over MJX steps.

``make_rollout`` returns a pure function ``(gains, scenario) -> Trajectory``
that can be jitted, vmapped over gains and scenarios, and differentiated.
``rollout`` is the convenient, cached, jitted entry point; its
``backend="mujoco"`` runs the very same jitted control law against MuJoCo C
(one environment, no gradient), so the two engines can be compared.
"""

from __future__ import annotations

import functools
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxsync import _controller, _physics, _scenario
from jaxsync._controller import ControllerOptions, Reference
from jaxsync._errors import ConfigError
from jaxsync._gains import Gains
from jaxsync._model import DualArmModel
from jaxsync._scenario import Scenario
from jaxsync._sensing import ArmState, compensate_wrist_wrench, sense

START_KEY = "approach"
REST_KEY = "grasp"


class Trajectory(NamedTuple):
    """What a rollout records, one row per control step (leading axis T).

    Times are the start of each control period. Forces on the object are
    those the contacts exerted during that period (from its constraint solve).
    """

    time: jax.Array  # (T,)
    qpos: jax.Array  # (T, nq) state at the start of the period
    qvel: jax.Array  # (T, nv)
    obj_pos: jax.Array  # (T, 3)
    obj_vel: jax.Array  # (T, 3)
    plan_obj_pos: jax.Array  # (T, 3) z_d
    plan_obj_acc: jax.Array  # (T, 3)
    plan_grip_force: jax.Array  # (T,) ramped f_d
    phase: jax.Array  # (T,) 0 close, 1 squeeze, 2 carry, 3 hold
    pad_pos: jax.Array  # (T, 2, 3) actual pad positions
    plan_pad_pos: jax.Array  # (T, 2, 3) x_id
    pad_normal: jax.Array  # (T, 2, 3) actual pad normals
    pad_forces: jax.Array  # (T, 2, 3) true force of each pad on the object
    wrist_wrench: jax.Array  # (T, 2, 6) compensated (noisy) wrist wrench the controller used
    torque: jax.Array  # (T, 14)
    offset: jax.Array  # (T, 2, 6) x_ik - x_id
    delta: jax.Array  # (T, 2, 6) absolute errors (eq. 12)
    impedance_offset: jax.Array  # (T, 2, 6) e_i


class _Consts(NamedTuple):
    """Per-model constants, computed once in Python (never traced)."""

    pad_rot: np.ndarray  # (2, 3, 3) planned pad orientation (grasp keyframe)
    q_rest: np.ndarray  # (2, 7)
    qpos0: np.ndarray  # (nq,) start (approach keyframe)
    act_order: np.ndarray  # (14,) actuator index of each torque
    noise_scale_mask: np.ndarray  # (nsensordata, 2) 1 where the entry is a force / torque
    torque_limit: np.ndarray  # (14,)


def _consts(model: DualArmModel) -> _Consts:
    m, idx = model.mj_model, model.index
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos(REST_KEY)
    mujoco.mj_kinematics(m, d)
    pad_rot = np.stack([d.site_xmat[a.pad_site].reshape(3, 3) for a in idx.arms])
    q_rest = np.stack([d.qpos[list(a.qpos_adr)] for a in idx.arms])
    mask = np.zeros((m.nsensordata, 2))
    for a in idx.arms:
        mask[a.force_adr : a.force_adr + 3, 0] = 1
        mask[a.torque_adr : a.torque_adr + 3, 1] = 1
    act = np.array([i for a in idx.arms for i in a.actuator_ids])
    order = np.argsort(act)  # torque vector (arm-major) -> ctrl vector
    return _Consts(
        pad_rot=pad_rot,
        q_rest=q_rest,
        qpos0=model.keyframe_qpos(START_KEY),
        act_order=order,
        noise_scale_mask=mask,
        torque_limit=m.actuator_ctrlrange[act, 1].copy(),
    )


def initial_qpos(model: DualArmModel, consts: _Consts, s: Scenario) -> jax.Array:
    """Arms at the approach keyframe; the object on the stand, off the nominal centre by ``object_offset``."""
    qa = model.index.object_qpos_adr
    centre = _scenario.nominal_centre(s) + s.object_offset
    return jnp.asarray(consts.qpos0).at[qa : qa + 3].set(centre)


def _reference(s: Scenario, consts: _Consts, pl: _scenario.Plan) -> Reference:
    normals = jnp.asarray(consts.pad_rot[:, :, 2])
    zeros = jnp.zeros((2, 3))
    return Reference(
        pad_pos=pl.pad_pos,
        pad_rot=jnp.asarray(consts.pad_rot),
        pad_vel=jnp.concatenate([pl.pad_vel, zeros], axis=1),
        pad_acc=jnp.concatenate([pl.pad_acc, zeros], axis=1),
        wrench=_scenario.desired_wrench(s, pl, normals),
        q_rest=jnp.asarray(consts.q_rest),
    )


def _noise(s: Scenario, consts: _Consts, step: jax.Array) -> jax.Array:
    key = jax.random.wrap_key_data(jnp.asarray(s.noise_key, dtype=jnp.uint32))
    n = jax.random.normal(jax.random.fold_in(key, step), (consts.noise_scale_mask.shape[0],))
    mask = jnp.asarray(consts.noise_scale_mask)
    return n * (mask[:, 0] * s.force_noise + mask[:, 1] * s.torque_noise)


def _control(options, gains, s, consts, cstate, arms, pad_start, t, dt):
    """Plan, desired wrench and one controller step: shared by both backends."""
    normals = jnp.asarray(consts.pad_rot[:, :, 2])
    pl = _scenario.plan(s, t, pad_start, normals)
    ref = _reference(s, consts, pl)
    tau, cstate, info = _controller.step(options, gains, cstate, arms, ref, dt)
    tau = jnp.clip(tau, -consts.torque_limit, consts.torque_limit)
    return tau, cstate, info, pl


def make_rollout(
    model: DualArmModel,
    controller: str = "synchronous",
    duration: float = 4.0,
    control_substeps: int = 1,
    cross_term: str = "squeeze",
    remat: bool = False,
    truncate_every: int | None = None,
    start: str = START_KEY,
):
    """Build ``fn(gains, scenario) -> Trajectory`` for one static configuration.

    Args:
      model: from :func:`jaxsync.load_model` (its solver setting is used).
      controller: "classical" or "synchronous".
      duration: seconds simulated.
      control_substeps: physics steps per control period (1: control at the
        simulation rate, 500 Hz for the paper model).
      cross_term: reading of eq. 16's cross term (see jaxsync._sync).
      remat: ``jax.checkpoint`` the scan body (for long reverse-mode gradients).
      truncate_every: if set, stop gradients through the simulator and
        controller state every this many control steps (truncated
        backpropagation in windows; the forward values are unchanged).
      start: keyframe the arms start from: "approach" (pads 30 mm off, the
        paper's task) or "grasp" (pads touching: short horizons in contact).
    """
    if start not in (START_KEY, REST_KEY):
        raise ConfigError(f"start must be {START_KEY!r} or {REST_KEY!r}, got {start!r}")
    if truncate_every is not None and truncate_every < 1:
        raise ConfigError(f"truncate_every must be a positive number of steps, got {truncate_every}")
    options = ControllerOptions(kind=controller, cross_term=cross_term)
    if control_substeps < 1 or int(control_substeps) != control_substeps:
        raise ConfigError(f"control_substeps must be a positive integer, got {control_substeps}")
    sim_dt = float(model.mj_model.opt.timestep)
    dt = sim_dt * control_substeps
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ConfigError(f"duration must be at least one control period ({dt} s), got {duration}")
    consts = _consts(model)._replace(qpos0=model.keyframe_qpos(start))
    index = model.index
    unroll = model.solver_unroll
    d_template = _physics.put_data(model.mj_model, mujoco.MjData(model.mj_model))

    def fn(gains: Gains, s: Scenario) -> Trajectory:
        mx = _scenario.apply_to_model(model.mjx_model, s, index)
        d0 = d_template.replace(qpos=initial_qpos(model, consts, s))
        d0 = _physics.before_control(mx, d0)
        pad_start = jnp.stack([d0.site_xpos[a.pad_site] for a in index.arms])

        def body(carry, k):
            if truncate_every is not None:
                cut = (k % truncate_every == 0) & (k > 0)
                carry = jax.tree_util.tree_map(
                    lambda x: (
                        jnp.where(cut, jax.lax.stop_gradient(x), x) if jnp.issubdtype(x.dtype, jnp.inexact) else x
                    ),
                    carry,
                )
            d, cstate = carry
            t = k * dt
            d = _physics.before_control(mx, d)
            noisy = d.replace(sensordata=d.sensordata + _noise(s, consts, k))
            sensed = sense(mx, noisy, index)
            arms = (sensed.right, sensed.left)
            tau, cstate, info, pl = _control(options, gains, s, consts, cstate, arms, pad_start, t, dt)
            ctrl = tau[consts.act_order]
            d = _physics.after_control(mx, d, ctrl, unroll)
            for _ in range(control_substeps - 1):
                d = _physics.after_control(mx, _physics.before_control(mx, d), ctrl, unroll)
            forces = jnp.stack([_physics.contact_force_on(mx, d, a.contact_id, a.object_is_geom1) for a in index.arms])
            row = Trajectory(
                time=t,
                qpos=noisy.qpos,
                qvel=noisy.qvel,
                obj_pos=sensed.obj.pos,
                obj_vel=sensed.obj.linvel,
                plan_obj_pos=pl.obj_pos,
                plan_obj_acc=pl.obj_acc,
                plan_grip_force=pl.grip_force,
                phase=pl.phase,
                pad_pos=jnp.stack([a.pad_pos for a in arms]),
                plan_pad_pos=pl.pad_pos,
                pad_normal=jnp.stack([a.pad_rot[:, 2] for a in arms]),
                pad_forces=forces,
                wrist_wrench=jnp.stack([a.wrench for a in arms]),
                torque=tau,
                offset=info.offset,
                delta=info.delta,
                impedance_offset=cstate.impedance.offset,
            )
            return (d, cstate), row

        if remat:
            body = jax.checkpoint(body)
        _, traj = jax.lax.scan(body, (d0, _controller.init()), jnp.arange(n_steps))
        return traj

    fn.n_steps = n_steps
    fn.dt = dt
    fn.options = options
    return fn


@functools.lru_cache(maxsize=32)
def _jitted(model, controller, duration, control_substeps, cross_term):
    return jax.jit(make_rollout(model, controller, duration, control_substeps, cross_term))


def rollout(
    model: DualArmModel,
    gains: Gains,
    scenario: Scenario,
    *,
    controller: str = "synchronous",
    duration: float = 4.0,
    control_substeps: int = 1,
    cross_term: str = "squeeze",
    backend: str = "mjx",
) -> Trajectory:
    """Run one closed-loop rollout (or a batch: vmap ``make_rollout`` instead).

    ``backend="mjx"`` compiles once per static configuration and model;
    ``backend="mujoco"`` steps MuJoCo C with the same jitted control law.
    """
    if backend == "mjx":
        return _jitted(model, controller, float(duration), int(control_substeps), cross_term)(gains, scenario)
    if backend == "mujoco":
        return rollout_mujoco(
            model,
            gains,
            scenario,
            controller=controller,
            duration=duration,
            control_substeps=control_substeps,
            cross_term=cross_term,
        )
    raise ConfigError(f"backend must be 'mjx' or 'mujoco', got {backend!r}")


# ---------------------------------------------------------------- MuJoCo C


def _sense_arm_c(m: mujoco.MjModel, d: mujoco.MjData, arm, raw: np.ndarray, full_m: np.ndarray) -> ArmState:
    dofs = list(arm.dof_adr)
    p = d.site_xpos[arm.pad_site].copy()
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jp, jr, arm.pad_site)
    djp, djr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacDot(m, d, djp, djr, p, arm.ee_body)
    jac = np.vstack([jp, jr])
    return ArmState(
        q=d.qpos[list(arm.qpos_adr)].copy(),
        qd=d.qvel[dofs].copy(),
        pad_pos=p,
        pad_rot=d.site_xmat[arm.pad_site].reshape(3, 3).copy(),
        pad_vel=jac @ d.qvel,
        jac=jac[:, dofs],
        jac_dot_qd=np.concatenate([djp @ d.qvel, djr @ d.qvel]),
        mass=full_m[np.ix_(dofs, dofs)],
        bias=d.qfrc_bias[dofs].copy(),
        wrist_raw=raw,
        wrench=np.asarray(
            _compensate_jit(
                raw,
                d.site_xmat[arm.ft_site].reshape(3, 3),
                d.site_xpos[arm.ft_site],
                d.subtree_com[arm.root_body],
                d.cinert[arm.ee_body],
                d.cvel[arm.ee_body],
                d.cacc[arm.ee_body],
                p,
            )
        ),
    )


_compensate_jit = jax.jit(compensate_wrist_wrench)


def _pad_forces_c(m, d, index) -> np.ndarray:
    out = np.zeros((2, 3))
    f6 = np.zeros(6)
    for i, arm in enumerate(index.arms):
        for c in range(d.ncon):
            con = d.contact[c]
            if {con.geom1, con.geom2} == {arm.pad_geom, index.object_geom} and con.efc_address >= 0:
                mujoco.mj_contactForce(m, d, c, f6)
                f = con.frame.reshape(3, 3).T @ f6[:3]  # on geom2
                out[i] += f if con.geom2 == index.object_geom else -f
    return out


def rollout_mujoco(
    model: DualArmModel,
    gains: Gains,
    scenario: Scenario,
    *,
    controller: str = "synchronous",
    duration: float = 4.0,
    control_substeps: int = 1,
    cross_term: str = "squeeze",
) -> Trajectory:
    """The same control law against MuJoCo C (mj_step1 / mj_step2), one environment."""
    options = ControllerOptions(kind=controller, cross_term=cross_term)
    consts = _consts(model)
    m = mujoco.MjModel.from_xml_path(model.path)  # a private copy we can change
    m.opt.iterations, m.opt.ls_iterations = model.mj_model.opt.iterations, model.mj_model.opt.ls_iterations
    m.opt.solver, m.opt.cone = model.mj_model.opt.solver, model.mj_model.opt.cone
    idx = model.index
    s = jax.tree_util.tree_map(np.asarray, scenario)
    b, g = idx.object_body, idx.object_geom
    m.body_mass[b] = float(s.object_mass)
    m.body_inertia[b] = 2.0 / 3.0 * float(s.object_mass) * float(s.object_radius) ** 2
    m.geom_size[g, 0] = float(s.object_radius)
    for p in idx.pad_pair_ids:
        m.pair_solref[p, 0] = float(s.contact_timeconst)
        m.pair_friction[p, :2] = float(s.friction)
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(initial_qpos(model, consts, scenario))
    mujoco.mj_forward(m, d)
    # acceleration-stage quantities start as MJX's do: zero
    d.sensordata[:] = 0.0
    d.cacc[:] = 0.0
    pad_start = jnp.asarray(np.stack([d.site_xpos[a.pad_site] for a in idx.arms]))
    dt = float(m.opt.timestep) * control_substeps
    n_steps = int(round(duration / dt))

    @jax.jit
    def control(gains, s, cstate, arms, k):
        return _control(options, gains, s, consts, cstate, arms, pad_start, k * dt, dt)

    noise = jax.jit(lambda s, k: _noise(s, consts, k))
    cstate = _controller.init()
    full_m = np.zeros((m.nv, m.nv))
    rows = []
    for k in range(n_steps):
        mujoco.mj_step1(m, d)
        raw_all = d.sensordata + np.asarray(noise(scenario, k))
        mujoco.mj_fullM(m, d, full_m)
        arms = tuple(
            _sense_arm_c(
                m,
                d,
                a,
                np.concatenate([raw_all[a.force_adr : a.force_adr + 3], raw_all[a.torque_adr : a.torque_adr + 3]]),
                full_m,
            )
            for a in idx.arms
        )
        tau, cstate, info, pl = control(gains, scenario, cstate, arms, k)
        qpos, qvel = d.qpos.copy(), d.qvel.copy()
        va = idx.object_dof_adr
        d.ctrl[:] = np.asarray(tau)[consts.act_order]
        mujoco.mj_step2(m, d)
        for _ in range(control_substeps - 1):
            mujoco.mj_step(m, d)
        rows.append(
            Trajectory(
                time=k * dt,
                qpos=qpos,
                qvel=qvel,
                obj_pos=qpos[idx.object_qpos_adr : idx.object_qpos_adr + 3],
                obj_vel=qvel[va : va + 3],
                plan_obj_pos=pl.obj_pos,
                plan_obj_acc=pl.obj_acc,
                plan_grip_force=pl.grip_force,
                phase=pl.phase,
                pad_pos=np.stack([a.pad_pos for a in arms]),
                plan_pad_pos=pl.pad_pos,
                pad_normal=np.stack([a.pad_rot[:, 2] for a in arms]),
                pad_forces=_pad_forces_c(m, d, idx),
                wrist_wrench=np.stack([a.wrench for a in arms]),
                torque=tau,
                offset=info.offset,
                delta=info.delta,
                impedance_offset=cstate.impedance.offset,
            )
        )
    return jax.tree_util.tree_map(lambda *x: jnp.asarray(np.stack([np.asarray(v) for v in x])), *rows)


def steps_for(duration: float, model: DualArmModel, control_substeps: int = 1) -> int:
    return int(round(duration / (model.mj_model.opt.timestep * control_substeps)))


def cpu_vmap_limit() -> int | None:
    """The largest vmap batch that is safe on this backend, None if unlimited.

    jaxlib's CPU LAPACK kernels (the batched Cholesky of MJX's Newton solver)
    split large batches over XLA's intra-op thread pool and block waiting for
    the pieces; when as many of them run at once as the pool has threads they
    wait for each other for ever (gdb: every pool thread in
    ``lapack_dpotrf_ffi`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``).
    Measured on 2 cores with jaxlib 0.10.2: batch 64 runs, 128 and 256 hang.
    Not checked on other jaxlib versions, so the cap applies to every CPU
    backend; ``JAXSYNC_CPU_VMAP_LIMIT`` overrides it (0: no cap).
    """
    if jax.default_backend() != "cpu":
        return None
    env = os.environ.get("JAXSYNC_CPU_VMAP_LIMIT")
    if env is not None:
        try:
            n = int(env)
        except ValueError:
            raise ConfigError(f"JAXSYNC_CPU_VMAP_LIMIT must be a whole number (0: no cap), got {env!r}") from None
        return n if n > 0 else None
    return 64
