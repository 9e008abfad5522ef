"""The MuJoCo C rollout: the same jitted control law stepping ``mj_step1`` / ``mj_step2``.

One environment, no gradient: a check of MJX against MuJoCo C on the very
same task (``jaxsync.sim.closed_loop``) and controller, and a baseline for speed.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxsync.control import controller as _controller
from jaxsync.control import ros2_loop as _ros2_loop
from jaxsync.control.controller import ControllerOptions
from jaxsync.control.gains import Gains
from jaxsync.physics.model import DualArmModel
from jaxsync.physics.sensing import ArmState, compensate_wrist_wrench
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import closed_loop as _closed_loop
from jaxsync.sim import scenario as _scenario
from jaxsync.sim import trajectory as _trajectory
from jaxsync.sim.scenario import Scenario
from jaxsync.sim.trajectory import Trajectory


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
    actuation: str = "torque",
    distro: str = "jazzy",
    on_control=None,
) -> Trajectory:
    """The same control law against MuJoCo C (mj_step1 / mj_step2), one environment.

    ``on_control`` (position-controlled arms): called each control period k
    with ``(k, arms, ref, command_in, state_in, command, state, sent)``, what the
    controller read and wrote (``sent``: the command plus the plan's
    feed-forward, what the servo gets) (``jaxsync.io.golden`` records them).

    Example:
      >>> model, s = jaxsync.load_model(), jaxsync.short_task()
      >>> c = rollout_mujoco(model, jaxsync.default_gains(), s, duration=2.0)
      >>> x = jaxsync.rollout(model, jaxsync.default_gains(), s, duration=2.0)
      >>> float(abs(c.obj_pos - x.obj_pos).max()) < 1e-3  # doctest: +SKIP
      True
    """
    options = ControllerOptions(kind=controller, cross_term=cross_term, distro=distro)
    _ros2_loop.check_actuation(controller, _actuation.check(actuation))
    consts = _closed_loop.consts(model)
    m = copy.deepcopy(model.mj_model)  # a private copy we can change (a robot file's composed scene too)
    m.opt.iterations, m.opt.ls_iterations = model.mj_model.opt.iterations, model.mj_model.opt.ls_iterations
    m.opt.solver, m.opt.cone = model.mj_model.opt.solver, model.mj_model.opt.cone
    idx = model.index
    _scenario.apply_to_mj_model(m, scenario, idx)
    position = _actuation.check(actuation) == "position"
    if position:  # the servo's damping, MuJoCo's joint damping (jaxsync.sim.actuation)
        pc = _actuation.position_consts(model)
        scale = float(scenario.servo_scale)
        for name, where, value in _actuation.model_updates(pc, scale):
            getattr(m, name)[where] = value
        command = jnp.asarray(_closed_loop.initial_command(model, consts))
        buffer = _actuation.initial_buffer(command)
        delay = int(_actuation.delay_steps(scenario))
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(_closed_loop.initial_qpos(model, consts, scenario))
    mujoco.mj_forward(m, d)
    # acceleration-stage quantities start as MJX's do: zero
    d.sensordata[:] = 0.0
    d.cacc[:] = 0.0
    pad_start = jnp.asarray(np.stack([d.site_xpos[a.pad_site] for a in idx.arms]))
    dt = float(m.opt.timestep) * control_substeps
    n_steps = int(round(duration / dt))

    @jax.jit
    def control(gains, s, cstate, arms, k):
        return _closed_loop.control(options, gains, s, consts, cstate, arms, pad_start, k * dt, dt)

    @jax.jit
    def control_position(gains, s, cstate, arms, k, command, buffer):
        command, sent, cstate, info, pl, ref = _closed_loop.control_position(
            options, gains, s, consts, cstate, arms, pad_start, k * dt, dt, command
        )
        return command, sent, _actuation.push(buffer, sent), cstate, info, pl, ref

    noise = jax.jit(lambda s, k: _closed_loop.noise(s, consts, k))
    cstate = _controller.init(jnp.asarray(_closed_loop.initial_command(model, consts)))
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
        qpos, qvel = d.qpos.copy(), d.qvel.copy()
        va = idx.object_dof_adr
        if position:
            before = (command, cstate)
            command, sent, buffer, cstate, info, pl, ref = control_position(
                gains, scenario, cstate, arms, k, command, buffer
            )
            if on_control is not None:
                on_control(k, arms, ref, *before, command, cstate, sent)
            acting, acting_vel = (np.asarray(x) for x in _actuation.acting(buffer, delay, dt))
            for sub in range(control_substeps):
                if sub:
                    mujoco.mj_step1(m, d)
                tau, motor = _actuation.servo_torque(
                    pc, d.qpos, d.qvel, d.qfrc_bias, acting, acting_vel, scale, consts.torque_limit, np
                )
                d.ctrl[:] = motor[consts.act_order]
                mujoco.mj_step2(m, d)
        else:
            tau, cstate, info, pl = control(gains, scenario, cstate, arms, k)
            d.ctrl[:] = np.asarray(tau)[consts.act_order]
            mujoco.mj_step2(m, d)
            for _ in range(control_substeps - 1):
                mujoco.mj_step(m, d)
        obj_pos = qpos[idx.object_qpos_adr : idx.object_qpos_adr + 3]
        forces = _pad_forces_c(m, d, idx)
        rows.append(
            _trajectory.row(
                k * dt,
                qpos,
                qvel,
                obj_pos,
                qvel[va : va + 3],
                pl,
                arms,
                forces,
                tau,
                info,
                cstate,
                np.stack,
                limit=consts.torque_limit,
            )
        )
    return jax.tree_util.tree_map(lambda *x: jnp.asarray(np.stack([np.asarray(v) for v in x])), *rows)
