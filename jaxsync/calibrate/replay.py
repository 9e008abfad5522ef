"""Recorded position commands replayed through the position stack's servo and delay, on MuJoCo C.

The same servo law the position stack simulates (``jaxsync.sim.actuation.
servo_torque``, in the servo's structure: ``jaxsync.physics.servo``):
on every physics step the servo holds the command of ``delay`` control
periods ago (the latest command received by then) and its velocity (its
difference with the one before, over the command period). The arms move
without the object (it is not there while a calibration trajectory is
played), so contacts are off.

The same code writes the recordings the tests and the benchmark fit: a
replay on a model with another physics step and integrator, a known servo
and delay, and sensor noise.
"""

from __future__ import annotations

import copy
import dataclasses
import os

import mujoco
import numpy as np

from jaxsync.physics.servo import joint_inertia, servo_of
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import closed_loop as _closed_loop

FIELDS = ("stiffness", "damping", "joint_damping", "frictionloss", "armature")
UNITS = {"stiffness": "N m/rad", "damping": "N m s/rad", "joint_damping": "N m s/rad", "frictionloss": "N m",
         "armature": "kg m^2"}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Joints:
    """Each arm joint's servo and joint parameters, (2 n,) each in the position stack's order (right, then left)."""

    stiffness: np.ndarray
    damping: np.ndarray
    joint_damping: np.ndarray
    frictionloss: np.ndarray
    armature: np.ndarray

    def replace(self, **kw) -> Joints:
        return dataclasses.replace(self, **{k: np.asarray(v, float) for k, v in kw.items()})


class Replay:
    """A model of the arms for replaying commands (contacts off, the motors' range opened)."""

    def __init__(
        self, model, timestep: float | None = None, integrator: str | None = None, structure: tuple | None = None
    ):
        """``structure``: (weight_compensation, velocity_feedforward) to replay
        with (``jaxsync.physics.servo.STRUCTURES``); default the model's servo's."""
        self.model = model
        servo = servo_of(model)
        if structure is not None:
            servo = servo.with_structure(*structure)
        self.servo = servo
        m = copy.deepcopy(model.mj_model)
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        if timestep is not None:
            m.opt.timestep = float(timestep)
        if integrator is not None:
            m.opt.integrator = int(getattr(mujoco.mjtIntegrator, f"mjINT_{integrator.upper()}"))
        self.pc = _actuation.position_consts(model, servo)
        for name, where, value in _actuation.model_updates(self.pc, 1.0):
            getattr(m, name)[where] = value
        self.m = m
        self.d = mujoco.MjData(m)
        self.limit = np.asarray(_closed_loop.consts(model).torque_limit, float)
        self.base_qpos = np.asarray(model.keyframe_qpos("grasp"), float)

    @property
    def timestep(self) -> float:
        return float(self.m.opt.timestep)

    def nominal(self) -> Joints:
        """What the model holds: the position stack's servo and the MJCF's joint parameters."""
        servo, m, dofs = self.servo, self.model.mj_model, self.pc.dof_adr
        return Joints(
            servo.stiffness.reshape(-1).astype(float),
            servo.damping.reshape(-1).astype(float),
            np.asarray(m.dof_damping)[dofs].astype(float),
            np.asarray(m.dof_frictionloss)[dofs].astype(float),
            np.asarray(m.dof_armature)[dofs].astype(float),
        )

    def state(self, q, dq, t: float) -> np.ndarray:
        """A ``mjSTATE_FULLPHYSICS`` state: the arms at (q, dq) at time t, the rest at the grasp keyframe."""
        m, d = self.m, self.d
        mujoco.mj_resetData(m, d)
        d.qpos[:] = self.base_qpos
        d.qpos[self.pc.qpos_adr] = q
        d.qvel[self.pc.dof_adr] = dq
        d.time = t
        out = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
        mujoco.mj_getState(m, d, out, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        return out

    def acting(self, times: np.ndarray, command_times: np.ndarray, commands: np.ndarray, delay: int, period: float):
        """The command the servo holds at each of ``times`` after ``delay`` periods, and its velocity
        (a command stamped at ``t``, to the microsecond, acts from ``t`` on)."""
        k = np.searchsorted(command_times, times + 1e-6, side="right") - 1 - int(delay)
        k = np.clip(k, 0, len(commands) - 1)
        prev = np.clip(k - 1, 0, len(commands) - 1)
        return commands[k], (commands[k] - commands[prev]) / period

    def run(self, joints: Joints, state: np.ndarray, n_steps: int, command_times, commands, delay: int, period: float):
        """``n_steps`` physics steps from ``state``: (times after each step, q, dq), each (n_steps, ...)."""
        m, d, pc = self.m, self.d, self.pc
        dofs, qadr, acts = pc.dof_adr, pc.qpos_adr, pc.actuator_ids
        m.dof_damping[dofs] = joints.joint_damping + joints.damping
        m.dof_frictionloss[dofs] = joints.frictionloss
        m.dof_armature[dofs] = joints.armature
        mujoco.mj_setState(m, d, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        h = float(m.opt.timestep)
        t0 = float(d.time)
        times = t0 + h * np.arange(n_steps)
        cmd, vel = self.acting(times, command_times, commands, delay, period)
        cmd = np.clip(cmd, pc.command_lo, pc.command_hi)
        k, b, lim, w = joints.stiffness, joints.damping, self.limit, pc.weight
        ff = k * cmd + b * (pc.feedforward * vel)  # the servo's terms that do not depend on the state
        weighted = bool(np.any(w))
        qs, ds, us = _view(qadr), _view(dofs), _view(acts)
        qpos, qvel, bias, ctrl = d.qpos, d.qvel, d.qfrc_bias, d.ctrl
        t1, t2, nlim = np.empty(len(dofs)), np.empty(len(dofs)), -lim
        q_out, dq_out = np.empty((n_steps, len(dofs))), np.empty((n_steps, len(dofs)))
        for i in range(n_steps):
            mujoco.mj_step1(m, d)
            dq = qvel[ds]
            np.multiply(k, qpos[qs], out=t1)
            np.subtract(ff[i], t1, out=t1)
            np.multiply(b, dq, out=t2)
            t1 -= t2
            if weighted:
                t1 += w * bias[ds]
            np.clip(t1, nlim, lim, out=t1)  # tau = clip(k (q_cmd - q) + b (f dq_cmd - dq) + w c, +-limit)
            t1 += t2  # the damping b dq' acts implicitly (jaxsync.sim.actuation)
            ctrl[us] = t1
            mujoco.mj_step2(m, d)
            q_out[i], dq_out[i] = qpos[qs], qvel[ds]
        return times + h, q_out, dq_out


def _view(index: np.ndarray):
    """A slice where the indices run contiguously (a view, cheaper than fancy indexing), else the indices."""
    index = np.asarray(index)
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


def record(
    model,
    joints: Joints,
    command_times: np.ndarray,
    commands: np.ndarray,
    delay: int,
    *,
    timestep: float = 0.0005,
    integrator: str = "implicitfast",
    rate: float | None = None,
    noise_q: float = 1e-4,
    noise_dq: float = 5e-3,
    seed: int = 0,
):
    """A recording of ``commands`` played on the arms: states sampled at ``rate`` (the command rate),
    with Gaussian noise (rad, rad/s). Returns (state times, q, dq)."""
    period = float(np.median(np.diff(command_times)))
    rate = rate or 1.0 / period
    replay = Replay(model, timestep=timestep, integrator=integrator)
    q0 = commands[0]
    n_steps = int(round((command_times[-1] - command_times[0]) / replay.timestep))
    state = replay.state(q0, np.zeros_like(q0), float(command_times[0]))
    t, q, dq = replay.run(joints, state, n_steps, command_times, commands, delay, period)
    every = max(1, int(round(1.0 / (rate * replay.timestep))))
    t, q, dq = t[every - 1 :: every], q[every - 1 :: every], dq[every - 1 :: every]
    rng = np.random.default_rng(seed)
    return t, q + noise_q * rng.standard_normal(q.shape), dq + noise_dq * rng.standard_normal(dq.shape)


class NativeReplay:
    """The same replay in MuJoCo's own terms, for ``mujoco.rollout`` (C, threaded): per joint a
    position actuator (k), a velocity feed-forward actuator (b, its control the command's velocity,
    where the structure feeds it forward) and the joint's damping b; where the structure compensates
    the arms' weight, through their actuators (MuJoCo's ``gravcomp`` with ``actuatorgravcomp``). It
    leaves out what :class:`Replay` adds beyond that: the compensation of Coriolis and centrifugal
    forces (at the excitation's speeds a few micro-radians of tracking on this machine's test
    robots, docs/calibrate.md) and the clip of the servo's torque to the joint's limit (a motion
    within the limits reaches neither)."""

    def __init__(
        self, model, spec, timestep: float | None = None, threads: int | None = None, structure: tuple | None = None
    ):
        self.exact = Replay(model, timestep=timestep, structure=structure)
        pc = self.exact.pc
        weighted = bool(np.any(pc.weight))
        m0 = model.mj_model
        joint_names = [mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, int(m0.dof_jntid[i])) for i in pc.dof_adr]
        spec = spec.copy()
        for name in joint_names:
            p = spec.add_actuator(name=f"jaxsync_servo_p {name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            p.set_to_position(kp=1.0)
            p.ctrllimited = 0
            f = spec.add_actuator(name=f"jaxsync_servo_ff {name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            f.set_to_motor()
            f.ctrllimited = 0
            if weighted:
                spec.joint(name).actgravcomp = 1
        roots = {int(a.root_body) for a in model.index.arms}
        for b in range(1, m0.nbody if weighted else 1):
            c = b
            while c > 0 and c not in roots:
                c = int(m0.body_parentid[c])
            if c in roots:
                spec.body(mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_BODY, b)).gravcomp = 1.0
        m = spec.compile()
        # the joints' actuator force range opened, as the position stack opens it
        # (jaxsync.sim.actuation.model_updates): MuJoCo would clip the sum of the
        # servo's actuators, their weight compensation and the feed-forward that
        # the implicit damping cancels, and brake the joint above limit / damping
        jids = np.asarray(m.dof_jntid)[pc.dof_adr]
        m.jnt_actfrcrange[jids, 0], m.jnt_actfrcrange[jids, 1] = -_actuation.UNCLAMPED, _actuation.UNCLAMPED
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        m.opt.timestep = self.exact.m.opt.timestep
        m.opt.integrator = self.exact.m.opt.integrator
        self.m = m
        self.p_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"jaxsync_servo_p {n}")
                               for n in joint_names])  # fmt: skip
        self.ff_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"jaxsync_servo_ff {n}")
                                for n in joint_names])  # fmt: skip
        self.dofs, self.qadr = pc.dof_adr, pc.qpos_adr
        self.datas = [mujoco.MjData(m) for _ in range(threads or min(2, os.cpu_count() or 1))]
        self._schedules: dict = {}  # each window's controls per delay (_controls)

    @property
    def timestep(self) -> float:
        return float(self.m.opt.timestep)

    def with_joints(self, joints: Joints):
        m = copy.copy(self.m)
        m.actuator_gainprm[self.p_ids, 0] = joints.stiffness
        m.actuator_biasprm[self.p_ids, 1] = -joints.stiffness
        m.actuator_gainprm[self.ff_ids, 0] = joints.damping
        m.dof_damping[self.dofs] = joints.joint_damping + joints.damping
        m.dof_frictionloss[self.dofs] = joints.frictionloss
        m.dof_armature[self.dofs] = joints.armature
        return m

    def run_many(self, jobs, n_steps: int, delay: int, period: float):
        """``jobs``: (Joints, state, command times, commands) each; returns (times, q, dq) per job.
        The same Joints object (by identity) builds one model; a window's commands (its command-times
        array, by identity, and start) are scheduled once per delay and kept."""
        from mujoco import rollout  # only here: the threaded rollout of MuJoCo's Python bindings

        models, states, controls, times = [], [], [], []
        cache: dict[int, object] = {}
        for joints, state, ct, cmds in jobs:
            key = id(joints)
            if key not in cache:
                cache[key] = self.with_joints(joints)
            models.append(cache[key])
            states.append(state)
            t, u = self._controls(state, ct, cmds, n_steps, delay, period)
            controls.append(u)
            times.append(t)
        # one thread pool for the process: a pool per call cost 5 ms beside the 35 ms of a fit's rollout
        out, _ = rollout.rollout(models, self.datas, np.asarray(states), np.asarray(controls), persistent_pool=True)
        nq = self.m.nq
        return [(t, s[:, 1 + self.qadr], s[:, 1 + nq + self.dofs]) for t, s in zip(times, out, strict=True)]

    def _controls(self, state, ct, cmds, n_steps: int, delay: int, period: float):
        """(times after each step, the actuators' controls) of one window: they depend on the window and
        the delay alone, not on the gains, so each is computed once (the command times kept with it, so
        that their identity stays theirs)."""
        key = (id(ct), float(state[0]), int(delay), int(n_steps), float(period))
        hit = self._schedules.get(key)
        if hit is not None and hit[0] is ct:
            return hit[1], hit[2]
        t = float(state[0]) + self.timestep * np.arange(n_steps)
        cmd, vel = self.exact.acting(t, ct, cmds, delay, period)
        u = np.zeros((n_steps, self.m.nu))
        pc = self.exact.pc
        u[:, self.p_ids], u[:, self.ff_ids] = np.clip(cmd, pc.command_lo, pc.command_hi), pc.feedforward * vel
        self._schedules[key] = (ct, t + self.timestep, u)
        return t + self.timestep, u


def replay_step(model, wh: float = 0.1) -> float:
    """The replay's physics step: the model's, divided until the stiffest servo joint's w h <= ``wh``
    (a 25 Hz servo is fast for a 2 ms explicit step: fitted there, its gains come out tens of percent
    off; docs/calibrate-accuracy.md)."""
    w = float(np.sqrt(servo_of(model).stiffness / joint_inertia(model)).max())
    step = float(model.mj_model.opt.timestep)
    return step / max(1, int(np.ceil(w * step / wh)))
