"""Each joint's position servo, for arms that take joint position commands.

A position-controlled arm's joints follow their commands through the robot's
own joint controller. jaxsync simulates it as

    tau_j = clip(k_j (clip(q_cmd,j, lo_j, hi_j) - q_j) + b_j (f dq_cmd,j - dq_j) + w c_j(q, dq), +-tau_max,j)

with k_j the stiffness (N m/rad), b_j the damping (N m s/rad), (lo_j, hi_j)
the command's range, c the model's bias forces (gravity and Coriolis),
tau_max the joint's torque limit, and the **structure** (w, f):

- ``weight_compensation`` (w = 1): the servo adds the arm's bias forces, as
  vendors' joint position interfaces compensate the arm's weight;
- ``velocity_feedforward`` (f = 1): its damping acts on the velocity error,
  the command carrying its velocity (the difference of successive commands);
  without it (f = 0) the damping acts on the joint's velocity, MuJoCo's
  ``<position>`` actuator's ``kv``.

Both false is MuJoCo's ``<position>`` actuator **as written**: what a
robot's MJCF position actuators compute (MuJoCo's body ``gravcomp``, where
the MJCF sets it, stays MuJoCo's, as written). The damping acts through
MuJoCo's joint damping, which its Euler integrator integrates implicitly
(stable at any gain; ``jaxsync.sim.actuation.servo_torque``). Where the numbers
come from, in this order:

1. a robot file's ``servo:`` (``jaxsync.physics.robot``): per-joint
   stiffness and damping, or a bandwidth and damping ratio, and the
   structure (each false unless stated);
2. the robot's MJCF: its own position actuators on the arm's joints, their
   gains and control ranges as written (``jaxsync.physics.compose``), as
   written (both false) unless the robot file's ``servo:`` states the
   structure;
3. the paper model: :data:`PAPER_SERVO`, with both (:data:`PAPER_STRUCTURE`).

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

PAPER_STRUCTURE = {"weight_compensation": True, "velocity_feedforward": True}
"""The paper model's servo structure: the paper's joint controllers hold
their commands against the arm's weight and track the command's velocity
(a stated assumption, docs/servo.md)."""

STRUCTURES = {
    "as_written": (False, False),
    "weight_compensated": (True, False),
    "feedforward": (True, True),
}
"""Named structures, (weight_compensation, velocity_feedforward): MuJoCo's
``<position>`` actuator as written; with the arm's weight compensated; and
with the command's velocity fed forward as well."""

GRASP_KEY = "grasp"


def structure_name(weight_compensation: bool, velocity_feedforward: bool) -> str:
    """The :data:`STRUCTURES` name of a structure, or ``velocity_feedforward_only``."""
    for name, flags in STRUCTURES.items():
        if flags == (bool(weight_compensation), bool(velocity_feedforward)):
            return name
    return "velocity_feedforward_only"


@dataclasses.dataclass(frozen=True)
class Servo:
    """Both arms' joint servos: (2, n) stiffness and damping, the structure,
    the commands' range and where they come from."""

    stiffness: np.ndarray  # (2, n) N m/rad
    damping: np.ndarray  # (2, n) N m s/rad
    source: str
    weight_compensation: bool = False
    velocity_feedforward: bool = False
    command_range: np.ndarray | None = None  # (2, n, 2) rad, +-inf where unlimited; None: none

    @property
    def structure(self) -> str:
        return structure_name(self.weight_compensation, self.velocity_feedforward)

    def with_structure(self, weight_compensation: bool, velocity_feedforward: bool) -> Servo:
        return dataclasses.replace(
            self, weight_compensation=bool(weight_compensation), velocity_feedforward=bool(velocity_feedforward)
        )

    def to_dict(self) -> dict:
        out = {
            "stiffness_Nm_per_rad": self.stiffness.tolist(),
            "damping_Nms_per_rad": self.damping.tolist(),
            "weight_compensation": self.weight_compensation,
            "velocity_feedforward": self.velocity_feedforward,
            "structure": self.structure,
            "source": self.source,
        }
        if self.command_range is not None and np.isfinite(self.command_range).any():
            rng = np.where(np.isfinite(self.command_range), self.command_range, None)
            out["command_range_rad"] = rng.tolist()
        return out


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
      ConfigError: a robot whose file states no servo gains and whose MJCF has
        no position actuator on some arm joint.
    """
    robot = getattr(model, "robot", None)
    if robot is None:
        src = (f"the paper model's stated servo, {PAPER_SERVO['bandwidth']:g} Hz, damping ratio "
               f"{PAPER_SERVO['damping_ratio']:g}, weight-compensated with velocity feed-forward")  # fmt: skip
        return from_bandwidth(model, source=src, **PAPER_SERVO).with_structure(*PAPER_STRUCTURE.values())
    stated = robot.servo or {}
    structure = (bool(stated.get("weight_compensation", False)), bool(stated.get("velocity_feedforward", False)))
    said = " (structure stated)" if {"weight_compensation", "velocity_feedforward"} & set(stated) else ""
    if "bandwidth" in stated:
        servo = from_bandwidth(model, stated["bandwidth"], stated["damping_ratio"],
                               f"{robot.file}: servo, {stated['bandwidth']:g} Hz{said}")  # fmt: skip
        return servo.with_structure(*structure)
    if "right" in stated or "stiffness" in stated:
        if "right" in stated:  # per arm (what jaxsync calibrate writes)
            kp, kv = (np.array([stated[a][k] for a in ("right", "left")]) for k in ("stiffness", "damping"))
        else:
            kp, kv = (np.array([stated[k]] * 2) for k in ("stiffness", "damping"))
        return Servo(kp, kv, f"{robot.file}: servo{said}").with_structure(*structure)
    servos = robot.position_servos or {}
    missing = [arm for arm in ("right", "left") if servos.get(arm) is None]
    if missing:
        raise ConfigError(
            f"robot {robot.name}: no joint servo known for position actuation: the {' and '.join(missing)} arm's "
            "MJCF has no position actuator on every joint; state one in the robot file: servo: {stiffness: "
            "[N m/rad per joint], damping: [N m s/rad per joint], weight_compensation: true|false, "
            "velocity_feedforward: true|false} or servo: {bandwidth: HZ, ...}"
        )
    table = np.array([[list(j) for j in servos[arm]] for arm in ("right", "left")], dtype=float)
    written = "as written" if not said else "their structure stated in the robot file"
    src = f"the MJCF's position actuators ({robot.name}), {written}"
    return Servo(table[..., 0], table[..., 1], src, *structure, command_range=table[..., 2:4])
