"""Recordings jaxsync's model did not make: a robot's joint servo written here from its definition.

Imports MuJoCo and NumPy only, nothing of jaxsync's servo, replay or
calibrate code. The servo is what a position-controlled arm's joint
controller computes, applied as a generalised force (``qfrc_applied``) on
MuJoCo C at its own step and integrator:

    tau = clip(k (q_cmd - q) + b (f dq_cmd - dq) + w c(q, dq), +-limit)

with ``c`` the arm's bias forces, ``limit`` the joint's torque limit: the
limit clips the torque the servo would apply and nothing else. Three
structures (``STRUCTURES``): ``as_written``, a MuJoCo ``<position>``
actuator (w = 0, f = 0: no compensation, damping on the joint's velocity);
``weight_compensated`` (w = 1, f = 0); ``feedforward`` (w = 1, f = 1: what
jaxsync's position stack assumes by default). A command stamped at t acts ``delay`` command periods later;
its velocity is its difference with the one before over the period. The
joint's own damping, friction loss and armature stay MuJoCo's.

Also two test robots with joint torque limits and friction loss as published
arm models carry them (the figures only, no model file copied;
:data:`LIMITED`):

- ``fr3``: Menagerie's Franka FR3 (``franka_fr3/fr3.xml``):
  actuatorfrcrange +-87 N m on joints 1-4 and +-12 N m on joints 5-7,
  friction loss 1.137 N m on joints 1-4 and 0.763, 0.44, 0.248 N m on
  joints 5-7, armature 0.195 and 0.074 kg m^2, and its servos' kp 4500,
  4500, 3500, 3500, 2000, 2000, 2000 N m/rad with kv a tenth of each, on the
  iiwa-like test arm's kinematics;
- ``ur5e``: the UR5e-like test arm with Menagerie's UR5e
  (``universal_robots_ur5e/ur5e.xml``, commit 1b428b0): the maximum joint
  torques it cites from Universal Robots, +-150 N m on joints 1-3 and
  +-28 N m on joints 4-6, as the joints' torque limits; its servos' kp 3500
  on joints 1-3 and 3000 on joints 4-6; its damping, 200 and 15 N m s/rad
  (a joint damping there), as the servo's; armature 0.1 kg m^2; and, since
  that file has none, the friction loss Menagerie's UFactory xArm7
  (``ufactory_xarm7/xarm7.xml``, commit 4f04d62) gives its joints, 1 N m.
"""

from __future__ import annotations

import copy
import dataclasses
import pathlib

import mujoco
import numpy as np
import yaml

ROBOTS = pathlib.Path(__file__).resolve().parent.parent / "mjcf" / "robots"


@dataclasses.dataclass(frozen=True)
class Figures:
    """A published arm's joint figures, per joint, on one of the shipped test arms."""

    arm: str  # the test arm's MJCF in mjcf/robots
    pair: str  # the robot file that places it twice
    joints: tuple[str, ...]
    limits: tuple[float, ...]  # N m
    frictionloss: tuple[float, ...]  # N m
    armature: tuple[float, ...]  # kg m^2
    kp: tuple[float, ...]  # N m/rad
    kv: tuple[float, ...]  # N m s/rad


_IIWA_JOINTS = tuple(f"joint{k}" for k in range(1, 8))
_UR5E_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
_FR3_KP = (4500.0, 4500.0, 3500.0, 3500.0, 2000.0, 2000.0, 2000.0)
LIMITED = {
    "fr3": Figures(
        "iiwa14_like_arm.xml", "iiwa14_twice.yaml", _IIWA_JOINTS,
        limits=(87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0),
        frictionloss=(1.137, 1.137, 1.137, 1.137, 0.763, 0.44, 0.248),
        armature=(0.195, 0.195, 0.195, 0.195, 0.074, 0.074, 0.074),
        kp=_FR3_KP, kv=tuple(k / 10 for k in _FR3_KP),
    ),
    "ur5e": Figures(
        "ur5e_like_arm.xml", "ur5e_twice.yaml", _UR5E_JOINTS,
        limits=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
        frictionloss=(1.0,) * 6,
        armature=(0.1,) * 6,
        kp=(3500.0, 3500.0, 3500.0, 3000.0, 3000.0, 3000.0),
        kv=(200.0, 200.0, 200.0, 15.0, 15.0, 15.0),
    ),
}  # fmt: skip
# (w, f) of the servo law above
STRUCTURES = {"as_written": (0.0, 0.0), "weight_compensated": (1.0, 0.0), "feedforward": (1.0, 1.0)}


def limited_robot(folder: pathlib.Path, figures: str = "fr3") -> pathlib.Path:
    """A robot file (and its arm MJCF) in ``folder``: a test arm twice with a published arm's joint
    torque limits (``actuatorfrcrange``), friction loss and armature, and its servo gains stated
    (``figures``: a key of :data:`LIMITED`)."""
    fig = LIMITED[figures]
    spec = mujoco.MjSpec.from_file(str(ROBOTS / fig.arm))
    for act in list(spec.actuators):
        spec.delete(act)  # the servo is stated in the robot file
    for k, name in enumerate(fig.joints):
        joint = spec.joint(name)
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.actfrcrange = [-fig.limits[k], fig.limits[k]]
        joint.frictionloss = fig.frictionloss[k]
        joint.armature = fig.armature[k]
    (folder / f"limited_{figures}_arm.xml").write_text(spec.to_xml())
    doc = yaml.safe_load((ROBOTS / fig.pair).read_text())
    doc["name"] = f"limited_{figures}_pair"
    for arm in doc["arms"].values():
        arm["model"] = f"limited_{figures}_arm.xml"
        arm.pop("torque_limits", None)  # the MJCF's joints carry them
    doc["servo"] = {"stiffness": list(fig.kp), "damping": list(fig.kv)}
    path = folder / f"limited_{figures}_pair.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def arm_joints(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(qpos addresses, dof addresses) of the hinge joints in ``m`` (the arms'), in the model's order."""
    hinges = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    return np.array([m.jnt_qposadr[j] for j in hinges]), np.array([m.jnt_dofadr[j] for j in hinges])


def commands(q0: np.ndarray, period: float, duration: float, speed: float, seed: int = 0):
    """Position commands every ``period`` s around ``q0``: each joint a sum of two sines with a
    joint speed up to about ``speed`` rad/s, ramped in over the first second. Returns (times, (T, n))."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration + 1e-12, period)
    n = len(q0)
    f = rng.uniform(0.3, 1.2, (2, n))
    phase = rng.uniform(0, 2 * np.pi, (2, n))
    amp = speed / (2 * np.pi * f.sum(axis=0))  # the two sines' speeds add up to ``speed`` at most
    ramp = np.clip(t / 1.0, 0.0, 1.0)[:, None]
    wave = sum(np.sin(2 * np.pi * f[i] * t[:, None] + phase[i]) - np.sin(phase[i]) for i in range(2))
    return t, q0 + ramp * amp * wave


def record(
    m0: mujoco.MjModel,
    q0_full: np.ndarray,
    kp: np.ndarray,
    kv: np.ndarray,
    limit: np.ndarray,
    command_times: np.ndarray,
    cmds: np.ndarray,
    delay: int,
    *,
    timestep: float = 2.5e-4,
    integrator: str = "RK4",
    structure: str = "feedforward",
    efforts: bool = False,
):
    """The arms of ``m0`` (contacts off, its own actuators off) following ``cmds`` through the servo
    above. ``kp``, ``kv``, ``limit``: (n,) in the order of :func:`arm_joints`. Returns (times, q, dq)
    sampled at the command times (after the first), and with ``efforts`` each sample's joint torques:
    the servo's at that state, under the command acting from then on (what a joint's effort reads)."""
    w, f = STRUCTURES[structure]
    m = copy.deepcopy(m0)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ACTUATION)
    qadr, dadr = arm_joints(m)

    def servo(d, cmd, vel):
        mujoco.mj_forward(m, d)  # the bias forces at this state
        tau = kp * (cmd - d.qpos[qadr]) + kv * (f * vel - d.qvel[dadr]) + w * d.qfrc_bias[dadr]
        d.qfrc_applied[dadr] = np.clip(tau, -limit, limit)
        return d.qfrc_applied[dadr].copy()

    out = _play(m, q0_full, command_times, cmds, delay, timestep, integrator, servo, per_step=True, efforts=efforts)
    return out if efforts else out[:3]


def record_actuators(
    spec: mujoco.MjSpec,
    q0_full: np.ndarray,
    kp: np.ndarray,
    kv: np.ndarray,
    command_times: np.ndarray,
    cmds: np.ndarray,
    delay: int,
    *,
    timestep: float = 2.5e-4,
    integrator: str = "implicitfast",
    structure: str = "feedforward",
    efforts: bool = False,
):
    """The same servo as MuJoCo's own actuators on the scene ``spec`` (its actuators replaced): per arm
    joint a ``<position>`` actuator (kp, kv: the damping on the joint's velocity, integrated implicitly
    under implicitfast), a motor carrying kv dq_cmd (feed-forward), and MuJoCo's gravity compensation
    through the actuators (``gravcomp``, ``actuatorgravcomp``: gravity only, not Coriolis). The joints'
    ``actuatorfrcrange`` clips the sum, which is the servo's torque. Returns (times, q, dq) as
    :func:`record`, in the order of :func:`arm_joints`, and with ``efforts`` each sample's joint torques
    (MuJoCo's ``qfrc_actuator`` under the command acting from then on)."""
    w, f = STRUCTURES[structure]
    spec = spec.copy()
    for act in list(spec.actuators):
        spec.delete(act)
    m0 = spec.compile()
    hinges = [j for j in range(m0.njnt) if m0.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    names = [mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, j) for j in hinges]
    for k, name in enumerate(names):
        servo = spec.add_actuator(name=f"servo {name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        servo.set_to_position(kp=float(kp[k]), kv=float(kv[k]))
        servo.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        ff = spec.add_actuator(name=f"ff {name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        ff.set_to_motor()
        ff.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        spec.joint(name).actgravcomp = bool(w)
    if w:
        for body in spec.bodies:
            if body.name not in ("world", "object"):
                body.gravcomp = 1.0
    m = spec.compile()
    servo_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"servo {n}") for n in names])
    ff_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"ff {n}") for n in names])

    _, dadr = arm_joints(m)

    def servo(d, cmd, vel):
        d.ctrl[servo_ids] = cmd
        d.ctrl[ff_ids] = f * kv * vel
        if efforts:
            mujoco.mj_forward(m, d)
            return d.qfrc_actuator[dadr].copy()
        return None

    out = _play(m, q0_full, command_times, cmds, delay, timestep, integrator, servo, per_step=False, efforts=efforts)
    return out if efforts else out[:3]


def _play(m, q0_full, command_times, cmds, delay, timestep, integrator, servo, per_step: bool, efforts=False):
    """``m`` (contacts off) from ``q0_full`` with the arms at the first command, each command acting
    ``delay`` periods after its stamp; ``servo(d, command, its velocity)`` before every physics step
    (``per_step``) or once per command period. Returns (times, q, dq) at the command times after the first,
    and with ``efforts`` the torques ``servo`` returns at each of them under the next command."""
    m.opt.timestep = timestep
    m.opt.integrator = int(getattr(mujoco.mjtIntegrator, f"mjINT_{integrator.upper()}"))
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    qadr, dadr = arm_joints(m)
    d = mujoco.MjData(m)
    d.qpos[:] = q0_full
    d.qpos[qadr] = cmds[0]
    mujoco.mj_forward(m, d)
    period = float(command_times[1] - command_times[0])
    per = int(round(period / timestep))
    out_q, out_dq, out_tau = [], [], []
    for i in range(1, len(command_times)):
        k = max(0, i - 1 - delay)  # the command acting during (t_{i-1}, t_i]
        vel = (cmds[k] - cmds[max(0, k - 1)]) / period
        for step in range(per):
            if per_step or step == 0:
                servo(d, cmds[k], vel)
            mujoco.mj_step(m, d)
        out_q.append(d.qpos[qadr].copy())
        out_dq.append(d.qvel[dadr].copy())
        if efforts:
            k = max(0, i - delay)  # the command acting from t_i on
            out_tau.append(servo(d, cmds[k], (cmds[k] - cmds[max(0, k - 1)]) / period))
    if efforts:
        return command_times[1:], np.array(out_q), np.array(out_dq), np.array(out_tau)
    return command_times[1:], np.array(out_q), np.array(out_dq)


def noisy(q: np.ndarray, dq: np.ndarray, noise_q: float, noise_dq: float, seed: int = 0):
    """The samples with white Gaussian noise of the given sizes (rad, rad/s)."""
    rng = np.random.default_rng(seed)
    return q + noise_q * rng.standard_normal(q.shape), dq + noise_dq * rng.standard_normal(dq.shape)
