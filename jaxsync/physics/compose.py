"""The task scene composed from a robot file with ``mujoco.MjSpec``.

The user's MJCF is read, never edited: its arms are attached to a new scene
(both from one bimanual file, or one single-arm file twice at the robot
file's bases), and jaxsync adds what its task needs, in the names the rest of
jaxsync reads (``jaxsync.physics.model.required_names``):

- at each flange, an end effector body ``r_ee``/``l_ee``: the wrist F/T site
  ``*_ft`` with force and torque sensors, a pad (0.3 kg, its face 36 mm out:
  ``jaxsync.physics.robot.END_EFFECTOR``, or the robot file's
  ``end_effector``) and its contact surface (the paper model's pad), the pad
  frame site ``*_pad`` (z out of the pad face);
- the object on a free joint where the robot file puts it, a stand (a plane)
  under it, and the explicit pad-object and stand-object contact pairs;
  every other collision off;
- torque motors ``*_motor1..n`` on the named joints, in place of the file's
  actuators (limits from the named ``actuators``, ``torque_limits``, the
  joint's ``actuatorfrcrange`` or the force range of the actuator the file
  had on that joint; otherwise an error naming the joint); every other joint
  welded, the file's tendons, equalities, sensors, contact pairs and
  keyframes dropped (each named in the notes);
- jaxsync's physics options (timestep 2 ms, Euler, Newton, elliptic cone),
  with a note where the robot's file asked for others;
- the ``approach`` and ``grasp`` keyframes, solved by inverse kinematics
  (``jaxsync.physics.ik``);
- the robot file's own joint names and each arm's ROS prefix, for messages
  and exports (``jaxsync.physics.robot_names``).

The flange is checked before anything is solved: a site or body of the arm on
or below its last joint, whose +z points out of the arm (a frame turned back
into the wrist would clamp the object with the wrist). The robot's file is
attached with the scene's own ``<size>`` (a note names what it set).

The scene is placed in jaxsync's task frame: the robot is moved (a rotation
about the vertical and a shift, which change no physics) so that the clamp
axis is world y (from the right pad towards the left) and the object's
centre is at the nominal grasp centre of ``jaxsync.sim.scenario``. What the
arms' own bodies and joints carry (inertias, armature, damping, friction
loss, joint ranges) is kept.
"""

from __future__ import annotations

import dataclasses
import difflib
import os

import mujoco
import numpy as np

from jaxsync._errors import ConfigError, ModelFileError
from jaxsync.physics import robot_names
from jaxsync.physics.robot import ARM_NAMES, Robot, is_robot_file, load_robot

TASK_CENTRE_XY = (0.65, 0.0)  # jaxsync.sim.scenario.NOMINAL_XY
STAND_TOP_Z = 0.8  # jaxsync.sim.scenario.STAND_TOP_Z
PREFIX = {"right": "r", "left": "l"}
PAD_SPHERE = 0.5  # m: the contact surface is this sphere's cap (jaxsync's paper model, mjcf/dual_arm.xml)
PAD_PAIR = {
    "condim": 3,
    "friction": [1, 1, 0.005, 0.0001, 0.0001],
    "solref": [0.02, 1],
    "solimp": [0.95, 0.99, 0.001, 0.5, 2],
}
STAND_PAIR = {
    "condim": 3,
    "friction": [0.5, 0.5, 0.005, 0.0001, 0.0001],
    "solref": [0.01, 1],
    "solimp": [0.95, 0.99, 0.001, 0.5, 2],
}
PHYSICS = {
    "timestep": 0.002,
    "integrator": mujoco.mjtIntegrator.mjINT_EULER,
    "solver": mujoco.mjtSolver.mjSOL_NEWTON,
    "cone": mujoco.mjtCone.mjCONE_ELLIPTIC,
    "iterations": 20,
    "ls_iterations": 10,
}
# <size> attributes the scene sets for itself; MuJoCo warns of each a robot's file sets otherwise when attached
SIZES = ("memory", "nstack", "njmax", "nconmax", "nkey", "nuserdata", "nemax", "nuser_body", "nuser_jnt",
         "nuser_geom", "nuser_site", "nuser_cam", "nuser_tendon", "nuser_actuator", "nuser_sensor")  # fmt: skip
FLANGE_BEHIND = 0.5  # cos of the angle above which a joint of the arm lies in front of the flange: backwards


@dataclasses.dataclass
class Composed:
    """The composed scene and what composing it decided."""

    spec: mujoco.MjSpec
    robot: Robot
    joint_names: dict[str, tuple[str, ...]]  # the robot's own joint names per arm ("right", "left")
    links: dict[str, dict[str, str]]  # per arm, the robot's own body names: "base" (of the chain), "tip" (flange)
    torque_limits: dict[str, tuple[float, ...]]
    # per arm, each joint's (stiffness, damping, lowest command, highest command)
    # of the file's own position actuator (N m/rad, N m s/rad, rad; +-inf where
    # its control is not limited), None where some joint has none
    position_servos: dict[str, tuple[tuple[float, float, float, float], ...] | None]
    to_task: tuple[np.ndarray, np.ndarray]  # (R, t): p_task = R @ p_robot + t
    notes: list[str]


def _load_spec(path: str, visual: bool) -> mujoco.MjSpec:
    try:
        spec = mujoco.MjSpec.from_file(path)
    except (ValueError, OSError) as err:
        raise ModelFileError(f"{path}: cannot read MJCF: {err}") from None
    if not visual:
        for g in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]:
            body = g.parent
            if not body.explicitinertial:
                raise ModelFileError(
                    f"{path}: body '{body.name}' takes its mass from mesh geom '{g.name}'; without the meshes "
                    "(--no-visual) it would have none: give the body an <inertial> or keep the meshes"
                )
            spec.delete(g)
        for m in list(spec.meshes):
            spec.delete(m)
        for m in list(spec.materials):
            m.textures = [""] * len(m.textures)
        for t in list(spec.textures):
            spec.delete(t)
    return spec


def _compile(spec: mujoco.MjSpec, what: str) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as err:
        hint = " (missing mesh files? --no-visual loads the robot without them)" if "file" in str(err) else ""
        raise ModelFileError(f"{what}: cannot compile: {err}{hint}") from None


def _mat_quat(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, dtype=float).reshape(9))
    return q


def _quat_mat(q) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, dtype=float))
    return m.reshape(3, 3)


def _attach(scene: mujoco.MjSpec, child: mujoco.MjSpec, prefix: str, frame, sizes: set[str]) -> None:
    """Attach ``child`` with the scene's own <size> (MuJoCo would warn of every one that differs, and
    keep the scene's); the attributes the file set are added to ``sizes``, for one note."""
    for key in SIZES:
        if getattr(child, key) != getattr(scene, key):
            sizes.add(key)
            setattr(child, key, getattr(scene, key))
    scene.attach(child, prefix=prefix, frame=frame)


def _frames(scene: mujoco.MjSpec, robot: Robot, visual: bool, sizes: set[str]) -> dict[str, tuple]:
    """Attach the robot's arm(s) to ``scene``: {arm: (frame, prefix of its names, (pos, quat) of its base)}."""
    out = {}
    if robot.model is not None:
        frame = scene.worldbody.add_frame(name="robot")
        _attach(scene, _load_spec(robot.model, visual), "robot/", frame, sizes)
        for a in ARM_NAMES:
            out[a] = (frame, "robot/", (np.zeros(3), np.array([1.0, 0, 0, 0])))
        return out
    for a, arm in zip(ARM_NAMES, robot.arms, strict=True):
        frame = scene.worldbody.add_frame(name=f"{a}_base")
        _attach(scene, _load_spec(arm.model, visual), f"{a}/", frame, sizes)
        out[a] = (frame, f"{a}/", (np.asarray(arm.base_pos), np.asarray(arm.base_quat)))
    return out


def _task_transform(robot: Robot, bases: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with p_task = R p_robot + t: clamp axis -> world y, object centre -> the nominal centre."""
    if robot.clamp_axis is not None:
        axis = np.asarray(robot.clamp_axis, dtype=float)
    else:
        axis = bases["left"] - bases["right"]
        axis[2] = 0.0
        if np.linalg.norm(axis) < 1e-6:
            raise ConfigError(
                f"{robot.path}: the two arms' bases are one above the other: give clamp_axis (horizontal, from "
                "the right pad towards the left)"
            )
    y = axis / np.linalg.norm(axis)
    z = np.array([0.0, 0.0, 1.0])
    x = np.cross(y, z)
    R = np.stack([x, y, z])  # rows: the task axes in the robot's frame
    c_task = np.array([*TASK_CENTRE_XY, STAND_TOP_Z + robot.object_radius])
    t = c_task - R @ np.asarray(robot.object_position, dtype=float)
    return R, t


def _drives(m: mujoco.MjModel, a: int, jids: list[int]) -> bool:
    return m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and int(m.actuator_trnid[a, 0]) in jids


def _limits(m: mujoco.MjModel, arm, prefix: str, jids: list[int], label: str) -> tuple[float, ...]:
    if arm.torque_limits is not None:
        return tuple(arm.torque_limits)
    out = []
    for k, (name, j) in enumerate(zip(arm.joints, jids, strict=True)):
        lim = None
        if arm.actuators is not None:
            a = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, prefix + arm.actuators[k])
            if a < 0:
                on_arm = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i).removeprefix(prefix)
                          for i in range(m.nu) if _drives(m, i, jids)]  # fmt: skip
                raise ConfigError(
                    f"{label}.actuators: no actuator '{arm.actuators[k]}' in the model; the arm's actuators: {on_arm}"
                )
            if not _drives(m, a, [j]):
                raise ConfigError(f"{label}.actuators: '{arm.actuators[k]}' does not drive joint '{name}'")
            gear = abs(float(m.actuator_gear[a, 0]))
            if m.actuator_forcelimited[a]:
                lim = float(np.max(np.abs(m.actuator_forcerange[a])))
            elif m.actuator_ctrllimited[a] and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED:
                lim = gear * abs(float(m.actuator_gainprm[a, 0])) * float(np.max(np.abs(m.actuator_ctrlrange[a])))
        if lim is None and m.jnt_actfrclimited[j]:
            lim = float(np.max(np.abs(m.jnt_actfrcrange[j])))
        if lim is None:
            on = [a for a in range(m.nu) if m.actuator_trntype[a] == 0 and m.actuator_trnid[a, 0] == j]
            ranged = [float(np.max(np.abs(m.actuator_forcerange[a]))) for a in on if m.actuator_forcelimited[a]]
            lim = max(ranged) if ranged else None
        if lim is None or not lim > 0:
            raise ConfigError(
                f"{label}: joint '{name}' has no torque limit (no actuatorfrcrange, no actuator forcerange on it): "
                f"give {label.rsplit(': ', 1)[-1]}.torque_limits (N m, one per joint)"
            )
        out.append(lim)
    return tuple(out)


def _position_servos(m: mujoco.MjModel, jids: list[int]) -> tuple[tuple[float, float, float, float], ...] | None:
    """Each joint's position servo as the file writes it: an actuator on the
    joint with a fixed gain kp and an affine bias (0, -kp, -kv), MuJoCo's
    ``<position>`` (or the ``<general>`` that spells it out). Through a gear g
    the joint sees stiffness g^2 kp and damping g^2 kv, and a control range
    (lo, hi) limits the joint's command to (lo, hi) / g. None if a joint has none."""
    out = []
    for j in jids:
        found = None
        for a in range(m.nu):
            gain, bias = m.actuator_gainprm[a], m.actuator_biasprm[a]
            if (
                _drives(m, a, [j])
                and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
                and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE
                and gain[0] > 0
                and bias[0] == 0
                and np.isclose(bias[1], -gain[0])
                and bias[2] <= 0
            ):
                g = float(m.actuator_gear[a, 0])
                lo, hi = (m.actuator_ctrlrange[a] / g) if m.actuator_ctrllimited[a] else (-np.inf, np.inf)
                found = (g * g * float(gain[0]), -g * g * float(bias[2]), float(min(lo, hi)), float(max(lo, hi)))
                break
        if found is None:
            return None
        out.append(found)
    return tuple(out)


def _is_below(m: mujoco.MjModel, b: int, ancestor: int) -> bool:
    while b not in (0, ancestor):
        b = int(m.body_parentid[b])
    return b == ancestor


def _unknown_flange(m: mujoco.MjModel, arm, prefix: str, jids: list[int], label: str) -> ConfigError:
    """The error for a flange the model does not have, naming the sites and bodies that could be meant."""
    last = int(m.jnt_bodyid[jids[-1]])
    bodies = [int(m.jnt_bodyid[j]) for j in jids[-3:]]
    bodies = list(dict.fromkeys(bodies + [b for b in range(m.nbody) if b != last and _is_below(m, b, last)]))
    sites = [i for i in range(m.nsite) if int(m.site_bodyid[i]) in bodies]
    name = lambda obj, i: (mujoco.mj_id2name(m, obj, i) or "").removeprefix(prefix)  # noqa: E731
    kinds = ((mujoco.mjtObj.mjOBJ_SITE, m.nsite), (mujoco.mjtObj.mjOBJ_BODY, m.nbody))
    known = [mujoco.mj_id2name(m, obj, i) or "" for obj, n in kinds for i in range(n)]
    close = difflib.get_close_matches(arm.flange, [k.removeprefix(prefix) for k in known if k.startswith(prefix)], 3)
    meant = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ";"
    return ConfigError(
        f"{label}.flange: no site or body '{arm.flange}' in the model{meant} the arm's last bodies: "
        f"{[name(mujoco.mjtObj.mjOBJ_BODY, b) for b in bodies]}, sites on them: "
        f"{[name(mujoco.mjtObj.mjOBJ_SITE, i) for i in sites]}"
    )


def _check_flange(m: mujoco.MjModel, d: mujoco.MjData, arm, prefix: str, label: str) -> None:
    """The flange exists, sits on or below the arm's last joint, and its +z points out of the arm:
    the nearest joint of the arm more than 1 cm from it must not lie in front of it (the wrist
    between the pad and the object)."""
    jids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, prefix + n) for n in arm.joints]
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, prefix + arm.flange)
    bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, prefix + arm.flange)
    if sid >= 0:
        body, p, z = int(m.site_bodyid[sid]), d.site_xpos[sid], d.site_xmat[sid].reshape(3, 3)[:, 2]
    elif bid >= 0:
        body, p, z = bid, d.xpos[bid], d.xmat[bid].reshape(3, 3)[:, 2]
    else:
        raise _unknown_flange(m, arm, prefix, jids, label)
    if not _is_below(m, body, int(m.jnt_bodyid[jids[-1]])):
        raise ConfigError(f"{label}.flange '{arm.flange}' is not on or below the arm's last joint '{arm.joints[-1]}'")
    for name, j in zip(reversed(arm.joints), reversed(jids), strict=True):
        v = d.xanchor[j] - p
        if np.linalg.norm(v) > 0.01:
            if v @ z > FLANGE_BEHIND * np.linalg.norm(v):
                raise ConfigError(
                    f"{label}.flange '{arm.flange}': its +z points back into the arm (joint '{name}' lies "
                    f"{1000 * float(v @ z):.0f} mm in front of it along +z): name a site or body whose +z points "
                    "out of the flange, away from the wrist"
                )
            return


def _add_end_effector(scene: mujoco.MjSpec, body, pos, quat, p: str, spec: dict) -> None:
    """The end effector ``spec`` (``jaxsync.physics.robot.END_EFFECTOR``'s keys) at the flange frame (pos, quat)."""
    body.add_site(name=f"{p}_flange", pos=pos, quat=quat, size=[0.01, 0.01, 0.01])
    ee = body.add_body(name=f"{p}_ee", pos=pos, quat=quat)
    ee.explicitinertial = True
    ee.mass = spec["mass"]
    ee.ipos = list(spec["com"])
    ee.inertia = list(spec["inertia"])
    face = spec["pad_offset"]
    ee.add_site(name=f"{p}_ft", size=[0.012, 0.012, 0.012], rgba=[1, 0.5, 0, 1])
    plain = {"contype": 0, "conaffinity": 0, "density": 0}
    plate = min(0.01, face / 2 - 0.004)  # the sensor plate's half-height, below the pad
    ee.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.035, plate, 0], pos=[0, 0, plate],
                rgba=[0.9, 0.5, 0.1, 1], **plain)  # fmt: skip
    ee.add_geom(name=f"{p}_pad_visual", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.05, 0.008, 0],
                pos=[0, 0, max(face - 0.008, 2 * plate + 0.008)], rgba=[0.15, 0.15, 0.15, 1], **plain)  # fmt: skip
    ee.add_geom(name=f"{p}_pad", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[PAD_SPHERE, 0, 0],
                pos=[0, 0, face - PAD_SPHERE], group=3, rgba=[0.15, 0.15, 0.15, 0.2], **plain)  # fmt: skip
    ee.add_site(name=f"{p}_pad", pos=[0, 0, face], size=[0.01, 0.01, 0.01])
    scene.add_sensor(name=f"{p}_ft_force", type=mujoco.mjtSensor.mjSENS_FORCE,
                     objtype=mujoco.mjtObj.mjOBJ_SITE, objname=f"{p}_ft")  # fmt: skip
    scene.add_sensor(name=f"{p}_ft_torque", type=mujoco.mjtSensor.mjSENS_TORQUE,
                     objtype=mujoco.mjtObj.mjOBJ_SITE, objname=f"{p}_ft")  # fmt: skip


def compose(robot: Robot, *, visual: bool = True) -> Composed:
    """The task scene for ``robot`` (keyframes not yet solved: :func:`jaxsync.physics.ik.add_keyframes`)."""
    notes: list[str] = []
    scene = mujoco.MjSpec()
    scene.modelname = f"jaxsync_{robot.name}"
    scene.compiler.degree = False
    scene.visual.global_.offwidth, scene.visual.global_.offheight = 1280, 960
    asked = _load_spec(robot.model or robot.right.model, visual=True).option
    plain = mujoco.MjSpec().option  # MuJoCo's defaults: what a file that asks nothing gets
    for key in PHYSICS:  # the file's own options while attaching (MuJoCo warns of every conflict)
        setattr(scene.option, key, getattr(asked, key))
    sizes: set[str] = set()
    frames = _frames(scene, robot, visual, sizes)
    if sizes:
        notes.append(f"the robot's file sets <size> {', '.join(sorted(sizes))}; the task scene sizes its own")
    for key, value in PHYSICS.items():
        enum = type(value) if not isinstance(value, int | float) else None
        text = lambda v, enum=enum: enum(v).name.split("_", 1)[1].lower() if enum else f"{v:g}"  # noqa: E731
        mine, theirs = int(value) if not isinstance(value, float) else value, getattr(asked, key)
        if theirs != getattr(plain, key) and theirs != mine:
            notes.append(f"the robot's file asks for {key} {text(theirs)}; the scene runs jaxsync's ({text(value)})")
        setattr(scene.option, key, value)
    scene.option.gravity = [0, 0, -9.81]
    # what the robot's file brings that the task scene does not run
    for kind, items in (("keyframe", scene.keys), ("sensor", scene.sensors), ("tendon", scene.tendons),
                        ("equality", scene.equalities), ("contact pair", scene.pairs),
                        ("contact exclude", scene.excludes)):  # fmt: skip
        items = list(items)
        if items:
            notes.append(f"dropped the file's {len(items)} {kind}(s)")
        for it in items:
            scene.delete(it)
    # names and limits, read on the robot as given (robot frame)
    m0 = _compile(scene, robot.path)
    joint_names, limits, jids_all, links, servos = {}, {}, set(), {}, {}
    for a, arm in zip(ARM_NAMES, robot.arms, strict=True):
        prefix = frames[a][1]
        label = f"{robot.path}: arms.{a}"
        jids = []
        for name in arm.joints:
            j = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_JOINT, prefix + name)
            if j < 0:
                have = [mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, i)[len(prefix):] for i in range(m0.njnt)
                        if (mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, i) or "").startswith(prefix)]  # fmt: skip
                raise ConfigError(f"{label}.joints: no joint '{name}' in the model; its joints: {have}")
            if m0.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise ConfigError(f"{label}.joints: '{name}' is not a hinge joint (jaxsync arms are 6 or 7 hinges)")
            jids.append(j)
        bodies = [int(m0.jnt_bodyid[j]) for j in jids]
        for k in range(1, len(bodies)):
            b = bodies[k]
            while b not in (0, bodies[k - 1]):
                b = int(m0.body_parentid[b])
            if b != bodies[k - 1]:
                raise ConfigError(f"{label}.joints must run from the base to the flange, one chain; "
                                  f"'{arm.joints[k]}' is not below '{arm.joints[k - 1]}'")  # fmt: skip
        joint_names[a] = tuple(arm.joints)
        limits[a] = _limits(m0, arm, prefix, jids, label)
        servos[a] = _position_servos(m0, jids)
        name = lambda b: mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_BODY, b) or "world"  # noqa: E731
        base = name(int(m0.body_parentid[bodies[0]]))
        links[a] = {"base": base.removeprefix(prefix) if base != "world" else "world"}
        jids_all.update(jids)
    # the bases (the body of each arm's first joint) and the flanges, in the robot's frame
    d0 = mujoco.MjData(m0)
    mujoco.mj_kinematics(m0, d0)
    bases = {}
    for a, arm in zip(ARM_NAMES, robot.arms, strict=True):
        frame, prefix, (bpos, bquat) = frames[a]
        j = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_JOINT, prefix + arm.joints[0])
        bases[a] = bpos + _quat_mat(bquat) @ d0.xpos[m0.jnt_bodyid[j]]
        _check_flange(m0, d0, arm, prefix, f"{robot.path}: arms.{a}")
    R, t = _task_transform(robot, bases)
    for a in ARM_NAMES:
        frame, prefix, (bpos, bquat) = frames[a]
        if robot.model is not None and a == "left":
            break  # one frame carries both arms
        frame.pos = R @ bpos + t
        frame.quat = _mat_quat(R @ _quat_mat(bquat))
    # actuators: torque motors on the named joints only; other joints welded
    for act in list(scene.actuators):
        scene.delete(act)
    welded = []
    for j in range(m0.njnt):
        if j not in jids_all:
            welded.append(mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, j))
    for name in welded:
        scene.delete(scene.joint(name))
    if welded:
        notes.append(f"welded the joints jaxsync does not control: {welded}")
    for a, arm in zip(ARM_NAMES, robot.arms, strict=True):
        p, prefix = PREFIX[a], frames[a][1]
        for k, name in enumerate(arm.joints, start=1):
            joint = scene.joint(prefix + name)
            joint.name = f"{p}_joint{k}"
            for field, values in (robot.joint_dynamics or {}).get(a, {}).items():  # the robot file's, over the MJCF's
                if field == "damping":  # MuJoCo's damping: linear, then polynomial terms (kept)
                    joint.damping = [values[k - 1], *list(joint.damping)[1:]]
                else:
                    setattr(joint, field, values[k - 1])
            act = scene.add_actuator(name=f"{p}_motor{k}", target=f"{p}_joint{k}",
                                     trntype=mujoco.mjtTrn.mjTRN_JOINT)  # fmt: skip
            act.set_to_motor()
            act.ctrllimited = True
            act.ctrlrange = [-limits[a][k - 1], limits[a][k - 1]]
        # the end effector at the flange (a site's frame, or a body's own)
        site = scene.site(prefix + arm.flange)  # _check_flange found it, a site or a body
        if site is not None:
            sid = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_SITE, prefix + arm.flange)
            body, pos, quat = site.parent, m0.site_pos[sid].copy(), m0.site_quat[sid].copy()
        else:
            body, pos, quat = scene.body(prefix + arm.flange), np.zeros(3), np.array([1.0, 0, 0, 0])
        _add_end_effector(scene, body, pos, quat, p, robot.end_effector)
        links[a]["tip"] = body.name.removeprefix(prefix)
    for g in scene.geoms:
        g.contype, g.conaffinity = 0, 0
    # the object, the stand, the floor (drawn only)
    c = np.array([*TASK_CENTRE_XY, STAND_TOP_Z + robot.object_radius])
    obj = scene.worldbody.add_body(name="object", pos=c)
    obj.add_freejoint(name="object_free")
    obj.add_geom(name="object", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[robot.object_radius, 0, 0],
                 mass=robot.object_mass, rgba=[0.2, 0.7, 0.3, 1], contype=0, conaffinity=0)  # fmt: skip
    obj.add_site(name="object_center", size=[0.01, 0.01, 0.01])
    floor_z = float(t[2])  # the robot frame's z = 0
    scene.worldbody.add_geom(name="stand", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.15, 0.15, 0.01],
                             pos=[c[0], c[1], STAND_TOP_Z], rgba=[0.55, 0.45, 0.35, 1], contype=0,
                             conaffinity=0)  # fmt: skip
    if floor_z < STAND_TOP_Z - 0.02:
        half = (STAND_TOP_Z - floor_z) / 2
        scene.worldbody.add_geom(name="stand_column", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.03, half, 0],
                                 pos=[c[0], c[1], floor_z + half], rgba=[0.55, 0.45, 0.35, 1], contype=0,
                                 conaffinity=0)  # fmt: skip
    scene.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2, 2, 0.05],
                             pos=[0, 0, floor_z], rgba=[0.9, 0.9, 0.9, 1], contype=0, conaffinity=0)  # fmt: skip
    scene.worldbody.add_light(pos=[0.5, -1.5, 3 + floor_z], dir=[-0.2, 0.6, -1], diffuse=[0.8, 0.8, 0.8])
    scene.worldbody.add_light(pos=[0.5, 1.5, 3 + floor_z], dir=[-0.2, -0.6, -1], diffuse=[0.4, 0.4, 0.4])
    for p in ("r", "l"):
        scene.add_pair(name=f"{p}_pad_object", geomname1="object", geomname2=f"{p}_pad", **PAD_PAIR)
    scene.add_pair(name="stand_object", geomname1="object", geomname2="stand", **STAND_PAIR)
    ros = robot_names.ros_prefixes(robot, links, notes)
    robot_names.record(scene, {a: {"joints": list(arm.joints), "prefix": frames[a][1], "ros_prefix": ros[a]}
                               for a, arm in zip(ARM_NAMES, robot.arms, strict=True)})  # fmt: skip
    return Composed(scene, robot, joint_names, links, limits, servos, (R, t), notes)


def model_file(robot: Robot) -> str:
    """Where a robot's composed scene is written next to the results (for MuJoCo's viewer)."""
    return os.path.splitext(os.path.basename(robot.path))[0] + "_scene.xml"


def robot_delay(source, control_rate: float | None = None) -> int:
    """The delay a robot file states (``delay: {periods, control_rate}``), in whole periods of
    ``control_rate`` (None: the composed scene's physics rate); 0 for an MJCF file or no source."""
    if source is None or not is_robot_file(source):
        return 0
    robot = load_robot(source)
    if robot.delay is None:
        return 0
    periods, rate = robot.delay
    rate_here = 1.0 / PHYSICS["timestep"] if control_rate is None else float(control_rate)
    return int(round(periods * rate_here / rate))
