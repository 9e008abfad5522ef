"""The robot facts a ros2-admittance export names: each arm's joints, links,
frames and axes (:func:`ros2_target`), and where the admittance controller
applies the impedance mass (:func:`mass_in_base`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control.gains import Gains
from jaxsync.control.names import DISTROS
from jaxsync.control.ros2_admittance import MASS_IN_CONTROL_FRAME  # PR #1139: Rolling's mass in the control frame
from jaxsync.physics import robot_names
from jaxsync.physics.inertia import arm_joint_ids

ARMS = ("right", "left")

COMMAND_INTERFACES = ("position", "velocity")
COMPLIANCE_FRAMES = ("flange", "pad")
KDL_PLUGIN = ("kinematics_interface_kdl/KinematicsInterfaceKDL", "kinematics_interface")  # name, package
CONTROLLER_TYPE = "admittance_controller/AdmittanceController"


@dataclasses.dataclass(frozen=True)
class ArmTarget:
    """What one arm's admittance controller needs from the robot (``ros2_target``)."""

    joints: tuple[str, ...]
    base: str  # kinematics.base and the fixed world frame: the link the arm is mounted on
    tip: str  # kinematics.tip, the control, sensor and gravity-compensation frame: the flange's link
    axes: tuple[int, ...]  # for each of the tip frame's 6 axes, the pad-frame axis it carries
    cog: tuple[float, float, float]  # the end effector's centre of mass in the tip frame, m
    weight: float  # the end effector's weight, N (what jaxsync's wrist sensor compensates)
    normal: tuple[float, float, float]  # the pad normal (into the object) in the tip frame
    ft_sensor: str
    # for each of kinematics.base's 6 axes, the pad axis it carries at the grasp (None: no signed permutation)
    base_axes: tuple[int, ...] | None = None
    # compliance at the pad: the pad link the files name, a fixed joint from the flange link (parent, xyz, rpy),
    # and the pad pose in the F/T sensor's frame (xyz, rpy) for the sensor's tool transform
    pad_joint: tuple | None = None
    sensor_to_pad: tuple | None = None
    # an arm whose base link is turned from the world: the world-aligned link the files name as kinematics.base
    # and fixed_world_frame, fixed to the base link (parent, xyz, rpy); fixed_world: fixed_world_frame's link
    world_joint: tuple | None = None
    fixed_world: str | None = None


@dataclasses.dataclass(frozen=True)
class Ros2Target:
    arms: tuple[ArmTarget, ArmTarget]
    distro: str = "jazzy"
    command_interfaces: tuple[str, ...] = ("position",)
    update_rate: int = 500  # Hz: the control rate the gains were tuned at
    filter_coefficient: float = 1.0  # ft_sensor.filter_coefficient: the F/T filter the gains were simulated with


def _signed_permutation(R: np.ndarray, what: str) -> tuple[int, ...]:
    """Row i (a tip-frame axis) carries pad axis argmax |R[i]|; refused unless R is a signed permutation."""
    idx = np.argmax(np.abs(R), axis=1)
    if not (np.allclose(np.abs(R[np.arange(3), idx]), 1.0, atol=1e-6) and len(set(idx.tolist())) == 3):
        raise ConfigError(
            f"ros2-admittance: the {what}'s pad frame is not aligned with its flange link's axes (up to a "
            "signed permutation), so its per-axis gains have no per-axis form in that link's frame: give the "
            "robot file a flange body whose axes match the flange site"
        )
    return tuple(int(i) for i in idx)


def ros2_target(m, robot: dict | None = None, *, distro: str = "jazzy", command_interfaces=("position",),
                ft_sensors=None, compliance_at: str = "pad") -> Ros2Target:  # fmt: skip
    """The robot facts the admittance controller's parameters take, from a
    loaded model's MuJoCo C model ``m`` and its robot report (``None``: the
    paper model's MJCF names). A robot file's names are its own, each arm's
    joints and links (base, tip: every frame the files name) with the arm's
    ``ros_prefix`` before them. ``compliance_at="pad"``: the tip, control,
    sensor and gravity frames are a pad link (``<arm>_jaxsync_pad`` after the
    prefix) fixed to the flange link at the pad, with jaxsync's pad axes, so
    that the controller's compliance is centred where jaxsync's is."""
    # imported here, not at the top: the export of yaml/json gains needs no MuJoCo
    import mujoco  # noqa: PLC0415

    if distro not in DISTROS:
        raise ConfigError(f"distro must be one of {list(DISTROS)}, got {distro!r}", inputs=("distro",))
    if compliance_at not in COMPLIANCE_FRAMES:
        raise ConfigError(
            f"compliance_at must be one of {list(COMPLIANCE_FRAMES)}, got {compliance_at!r}",
            inputs=("compliance_at",),
        )
    bad = [c for c in command_interfaces if c not in COMMAND_INTERFACES]
    if bad or not command_interfaces:
        raise ConfigError(
            f"command_interfaces must name position and/or velocity (the joint commands the admittance "
            f"controller writes), got {list(command_interfaces)}",
            inputs=("command_interfaces",),
        )
    d = mujoco.MjData(m)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "grasp")
    if key >= 0:  # the pad's axes in the base at the grasp: where the mass is applied
        mujoco.mj_resetDataKeyframe(m, d, key)
    mujoco.mj_kinematics(m, d)
    ident = lambda kind, name: mujoco.mj_name2id(m, kind, name)  # noqa: E731
    arms = []
    for side, name in (("r", "right"), ("l", "left")):
        ee = ident(mujoco.mjtObj.mjOBJ_BODY, f"{side}_ee")
        pad = ident(mujoco.mjtObj.mjOBJ_SITE, f"{side}_pad")
        tip_id = int(m.body_parentid[ee]) if robot is not None else ee
        R_tip = d.xmat[tip_id].reshape(3, 3)
        R_pad = d.site_xmat[pad].reshape(3, 3)
        R = R_tip.T @ R_pad  # pad axes (columns) in the tip frame
        at_pad = compliance_at == "pad"
        perm = (0, 1, 2) if at_pad else _signed_permutation(R, f"{name} arm")
        cog = R_tip.T @ (d.xipos[ee] - d.xpos[tip_id])
        pad_joint = sensor_to_pad = None
        if at_pad:
            flange = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, tip_id)
            ft = ident(mujoco.mjtObj.mjOBJ_SITE, f"{side}_ft")
            R_ft = d.site_xmat[ft].reshape(3, 3)
            pad_joint = (flange, _pose(R_tip, d.xpos[tip_id], R_pad, d.site_xpos[pad]))
            sensor_to_pad = _pose(R_ft, d.site_xpos[ft], R_pad, d.site_xpos[pad])
            cog = R_pad.T @ (d.xipos[ee] - d.site_xpos[pad])
        if robot is not None:
            ros = robot_names.ros_prefix(m, name)  # arms.<side>.ros_prefix; a base of "world" is everyone's
            joints, links = tuple(ros + j for j in robot.joint_names[name]), robot.links[name]
            base, tip = links["base"] if links["base"] == "world" else ros + links["base"], ros + links["tip"]
            if at_pad:
                pad_joint = (tip, pad_joint[1])
        else:
            jids = arm_joint_ids(m, side)
            joints = tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in jids)
            base = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.body_parentid[m.jnt_bodyid[jids[0]]]))
            tip = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, ee)
            ros = ""
        base_body = int(m.body_parentid[m.jnt_bodyid[arm_joint_ids(m, side)[0]]])
        R_base = d.xmat[base_body].reshape(3, 3)
        world_joint = fixed_world = None
        if not np.allclose(R_base, np.eye(3), atol=1e-9):
            # the controller applies its mass per axis of kinematics.base and its gravity compensation along
            # fixed_world_frame's z; the loop runs both in the world (jaxsync.control.ros2_loop)
            if distro == "humble":  # its KDL plugin roots the chain at the URDF's root link, whatever base says
                fixed_world = "world"
            else:
                world_joint = (base, _pose(R_base, d.xpos[base_body], np.eye(3), d.xpos[base_body]))
                base = fixed_world = f"{ros or name + '_'}jaxsync_world"
            R_base = np.eye(3)
        in_base = R_base.T @ d.site_xmat[pad].reshape(3, 3)
        idx = np.argmax(np.abs(in_base), axis=1)
        aligned = np.allclose(np.abs(in_base[np.arange(3), idx]), 1.0, atol=1e-6) and len(set(idx.tolist())) == 3
        base_axes = tuple(int(i) for i in idx) + tuple(3 + int(i) for i in idx) if aligned else None
        sensor = (ft_sensors or {}).get(name, f"{name}_ft_sensor")
        arms.append(
            ArmTarget(
                joints,
                base,
                f"{ros or name + '_'}jaxsync_pad" if at_pad else tip,
                perm + tuple(3 + i for i in perm),
                tuple(float(x) for x in cog),
                float(m.body_mass[ee] * 9.81),
                (0.0, 0.0, 1.0) if at_pad else tuple(float(x) for x in R[:, 2]),
                sensor,
                base_axes,
                pad_joint,
                sensor_to_pad,
                world_joint,
                fixed_world,
            )  # fmt: skip
        )
    return Ros2Target(tuple(arms), distro, tuple(command_interfaces), int(round(1.0 / m.opt.timestep)))


def _pose(R_parent, p_parent, R_child, p_child) -> tuple:
    """(xyz, rpy) of a child frame in its parent's, as URDF writes a fixed joint's
    origin: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = R_parent.T @ R_child
    xyz = R_parent.T @ (p_child - p_parent)
    clean = lambda v: tuple(round(float(x), 12) + 0.0 for x in v)  # noqa: E731 -- no -0.0 or 1e-17 noise
    return clean(xyz), clean(rpy_of(R))


def rpy_of(R: np.ndarray) -> tuple[float, float, float]:
    """URDF's roll, pitch, yaw of a rotation matrix (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    if abs(R[2, 0]) < 1.0 - 1e-12:
        return float(np.arctan2(R[2, 1], R[2, 2])), pitch, float(np.arctan2(R[1, 0], R[0, 0]))
    return float(np.arctan2(-R[1, 2], R[1, 1])), pitch, 0.0  # gimbal lock: all of the rotation in roll


def mass_axes(t: ArmTarget, distro: str) -> tuple[int, ...]:
    """For each entry of the written ``admittance.mass``, the pad axis whose mass
    it is: the control frame's order on Rolling, the base's elsewhere (the
    control frame's where the pad is not aligned with the base: then only a
    mass equal per block is written, the same in every frame)."""
    if MASS_IN_CONTROL_FRAME[distro] or t.base_axes is None:
        return t.axes
    return t.base_axes


def mass_in_base(g: Gains, arm: int, t: ArmTarget, distro: str = "jazzy") -> np.ndarray:
    """Arm ``arm``'s admittance mass (6,) in the frame the admittance controller
    applies it: per axis of ``kinematics.base`` on Jazzy, Kilted and Humble,
    each pad axis's mass on the base axis the pad axis lies along at the grasp
    (``ArmTarget.base_axes``); in the control frame on Rolling. Where the pad
    frame is not aligned with the base only a mass equal on the axes of each
    block is the same in every frame; other masses are refused, naming the
    axes."""
    m = np.asarray(g.imp_mass, dtype=float)[arm]
    if MASS_IN_CONTROL_FRAME[distro]:
        return m[list(t.axes)]
    if t.base_axes is not None:
        return m[list(t.base_axes)]
    for block, names in ((slice(0, 3), "x, y, z"), (slice(3, 6), "rx, ry, rz")):
        if not np.allclose(m[block], m[block][0], rtol=1e-9, atol=0.0):
            values = ", ".join(f"{v:.4g}" for v in m[block])
            raise ConfigError(
                f"ros2-admittance: the {ARMS[arm]} arm's pad frame is not aligned with kinematics.base "
                f"'{t.base}' at the grasp, where the admittance controller applies its mass per base axis: "
                f"no diagonal mass there gives the tuned one on pad axes {names} ({values}); "
                "tune with one mass per block (jaxsync tune --isotropic; TuneSpec(isotropic=True) in Python)"
            )
    return m
