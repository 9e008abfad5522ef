"""Each joint's position servo, for arms that take joint position commands.

A position-controlled arm's joints follow their commands through the robot's
own joint controller. jaxsync models it as what MuJoCo's ``<position>``
actuator computes, plus the compensation of the arm's own weight that every
vendor's joint position interface makes:

    tau_j = clip(k_j (q_cmd,j - q_j) + c_j(q, qd), +-tau_max,j) - b_j qd_j

with k_j the stiffness (N m/rad), b_j the damping (N m s/rad), c the
model's bias forces (gravity and Coriolis) and tau_max the joint's torque
limit. The damping acts through MuJoCo's joint damping, which its Euler
integrator integrates implicitly (stable at any gain; the clip holds the
rest of the torque only). Where the numbers come from, in this order:

1. a robot file's ``servo:`` (``jaxsync.physics.robot``): per-joint
   stiffness and damping, or a bandwidth and damping ratio;
2. the robot's MJCF: its own position actuators on the arm's joints, their
   gains as written (``jaxsync.physics.compose``);
3. the paper model: :data:`PAPER_SERVO`.

A bandwidth f (Hz) and ratio zeta give k_j = I_j w^2 and b_j = 2 zeta I_j w,
w = 2 pi f, with I_j the joint's own inertia (the mass matrix's diagonal,
armature included) at the grasp: each joint alone a second-order loop of
natural frequency f.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jaxsync._errors import ConfigError

PAPER_SERVO = {"bandwidth": 25.0, "damping_ratio": 1.0}
"""The paper model's servo. The paper puts each joint under its own joint
controller and gives no gains; 25 Hz, critically damped, is a stated
assumption in the range of industrial arms' joint position loops (tens of
Hz) (docs/deploy.md). A robot file states its own (``servo:``) or its MJCF
has one."""

GRASP_KEY = "grasp"


@dataclasses.dataclass(frozen=True)
class Servo:
    """Both arms' joint servos: (2, n) stiffness and damping, and where they come from."""

    stiffness: np.ndarray  # (2, n) N m/rad
    damping: np.ndarray  # (2, n) N m s/rad
    source: str

    def to_dict(self) -> dict:
        return {
            "stiffness_Nm_per_rad": self.stiffness.tolist(),
            "damping_Nms_per_rad": self.damping.tolist(),
            "source": self.source,
        }


def joint_inertia(model) -> np.ndarray:
    """(2, n) each arm joint's own inertia I_j (kg m^2, armature included) at the grasp."""
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos(GRASP_KEY)
    mujoco.mj_forward(m, d)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    return np.stack([np.diag(full)[list(a.dof_adr)] for a in model.index.arms])


def from_bandwidth(model, bandwidth: float, damping_ratio: float = 1.0, source: str = "") -> Servo:
    """k_j = I_j w^2, b_j = 2 zeta I_j w (w = 2 pi ``bandwidth``)."""
    inertia = joint_inertia(model)
    w = 2.0 * np.pi * float(bandwidth)
    src = source or f"{bandwidth:g} Hz, damping ratio {damping_ratio:g}"
    return Servo(inertia * w * w, 2.0 * float(damping_ratio) * inertia * w, src)


def servo_of(model) -> Servo:
    """The servo a model's joints follow position commands through (module docstring).

    Raises:
      ConfigError: a robot whose file states no ``servo:`` and whose MJCF has
        no position actuator on some arm joint.
    """
    robot = getattr(model, "robot", None)
    if robot is None:
        return from_bandwidth(model, source=f"the paper model's stated servo, {PAPER_SERVO['bandwidth']:g} Hz, "
                              f"damping ratio {PAPER_SERVO['damping_ratio']:g}", **PAPER_SERVO)  # fmt: skip
    if robot.servo is not None:
        if "bandwidth" in robot.servo:
            return from_bandwidth(model, robot.servo["bandwidth"], robot.servo["damping_ratio"],
                                  f"{robot.file}: servo, {robot.servo['bandwidth']:g} Hz")  # fmt: skip
        if "right" in robot.servo:  # per arm (what jaxsync calibrate writes)
            kp, kv = (np.array([robot.servo[a][k] for a in ("right", "left")]) for k in ("stiffness", "damping"))
        else:
            kp, kv = (np.array([robot.servo[k]] * 2) for k in ("stiffness", "damping"))
        return Servo(kp, kv, f"{robot.file}: servo")
    servos = robot.position_servos or {}
    missing = [arm for arm in ("right", "left") if servos.get(arm) is None]
    if missing:
        raise ConfigError(
            f"robot {robot.name}: no joint servo known for position actuation: the {' and '.join(missing)} arm's "
            "MJCF has no position actuator on every joint; state one in the robot file: servo: {stiffness: "
            "[N m/rad per joint], damping: [N m s/rad per joint]} or servo: {bandwidth: HZ}"
        )
    kp = np.array([[k for k, _ in servos[arm]] for arm in ("right", "left")])
    kv = np.array([[b for _, b in servos[arm]] for arm in ("right", "left")])
    return Servo(kp, kv, f"the MJCF's position actuators ({robot.name})")
