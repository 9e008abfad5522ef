"""Loading the dual-arm MJCF model and resolving its names to ids, once.

Everything here runs eagerly in Python, before anything is traced: ``jit``-ed
code only ever sees the integer ids gathered in :class:`ModelIndex`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import os
from typing import Literal

import mujoco
import numpy as np
from mujoco import mjx

from jaxsync._errors import ConfigError, ModelFileError, ModelStructureError
from jaxsync.physics import compose as _compose
from jaxsync.physics import ik as _ik
from jaxsync.physics import step as _physics
from jaxsync.physics.inertia import arm_joint_ids
from jaxsync.physics.robot import is_robot_file, load_robot
from jaxsync.runtime import patches

ARMS = ("r", "l")
JOINTS_PER_ARM = 7  # the paper model's; a robot's arms have 6 or 7 (joints_per_arm)
ARM_JOINT_COUNTS = (6, 7)

SolverName = Literal["accurate", "unrolled"]

# Solver settings, both Newton on the model file's elliptic cone.
# ``accurate`` is jaxsync's one physics: MJX's converged solve (20 iterations,
# its ``while_loop``) for every rollout, compare, sweep, validation and
# training; gradients through it are implicit (``_physics.solve_implicit``:
# the implicit function theorem at the solve's optimality condition), exact
# for the converged physics. ``unrolled`` is a reference to compare against
# (the benchmark's "unrolled" gradient path): one outer iteration per
# ``mjx.solve`` call, the call unrolled ``SOLVER_UNROLL`` times per step and
# differentiated through (a single iteration launched the clamped ball off the
# pads; three matched the converged solve on the default gains). It needs
# ``jaxsync.runtime.patches.mjx_elliptic_gradient`` for finite gradients; it
# is a different physics on short in-contact horizons (docs/tuning.md).
SOLVERS: dict[str, dict[str, int]] = {
    "accurate": {"iterations": 20, "ls_iterations": 10},
    "unrolled": {"iterations": 1, "ls_iterations": 4},
}
SOLVER_UNROLL = {"unrolled": 3, "accurate": 1}


def default_model_path() -> str:
    """Path of the packaged paper model (works from a wheel or a checkout)."""
    return str(importlib.resources.files("jaxsync.mjcf").joinpath("dual_arm.xml"))


@dataclasses.dataclass(frozen=True)
class ArmIndex:
    """Static ids of one arm. Tuples of ints: hashable, never traced."""

    prefix: str
    qpos_adr: tuple[int, ...]
    dof_adr: tuple[int, ...]
    actuator_ids: tuple[int, ...]
    ee_body: int
    root_body: int  # body_rootid of the end effector (origin of its com-based vectors)
    pad_site: int
    ft_site: int
    pad_geom: int
    force_adr: int
    torque_adr: int
    contact_id: int  # index of the pad-object contact in MJX's static list
    object_is_geom1: bool  # the object is geom1 of that contact (force sign)


@dataclasses.dataclass(frozen=True)
class ModelIndex:
    """Static ids of the whole model."""

    right: ArmIndex
    left: ArmIndex
    object_body: int
    object_geom: int
    object_qpos_adr: int
    object_dof_adr: int
    stand_contact_id: int
    pad_pair_ids: tuple[int, int]  # rows of the <pair> arrays for the right and left pad
    ncon: int

    @property
    def arms(self) -> tuple[ArmIndex, ArmIndex]:
        return (self.right, self.left)


def joints_per_arm(m: mujoco.MjModel) -> int:
    """How many joints ``r_joint1``, ``r_joint2``, ... the model has (0 if none)."""
    return len(arm_joint_ids(m, "r"))


def required_names(n: int = JOINTS_PER_ARM) -> dict[str, list[str]]:
    """Every MJCF name jaxsync relies on, by kind (``n`` joints per arm)."""
    names: dict[str, list[str]] = {
        "body": ["object"],
        "joint": ["object_free"],
        "site": [],
        "geom": ["object", "stand"],
        "actuator": [],
        "sensor": [],
    }
    for a in ARMS:
        names["body"].append(f"{a}_ee")
        names["joint"] += [f"{a}_joint{k}" for k in range(1, n + 1)]
        names["actuator"] += [f"{a}_motor{k}" for k in range(1, n + 1)]
        names["site"] += [f"{a}_pad", f"{a}_ft", f"{a}_flange"]
        names["geom"].append(f"{a}_pad")
        names["sensor"] += [f"{a}_ft_force", f"{a}_ft_torque"]
    return names


_OBJ = {
    "body": mujoco.mjtObj.mjOBJ_BODY,
    "joint": mujoco.mjtObj.mjOBJ_JOINT,
    "site": mujoco.mjtObj.mjOBJ_SITE,
    "geom": mujoco.mjtObj.mjOBJ_GEOM,
    "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR,
    "sensor": mujoco.mjtObj.mjOBJ_SENSOR,
}


def _id(m: mujoco.MjModel, kind: str, name: str) -> int:
    return mujoco.mj_name2id(m, _OBJ[kind], name)


def _check_structure(m: mujoco.MjModel, path: str) -> None:
    n = joints_per_arm(m)
    n = n if n in ARM_JOINT_COUNTS else JOINTS_PER_ARM
    missing = [
        f"{kind} '{name}'" for kind, names in required_names(n).items() for name in names if _id(m, kind, name) < 0
    ]
    problems = []
    if missing:
        problems.append("missing " + ", ".join(missing))
    if _id(m, "joint", f"r_joint{n + 1}") >= 0 or _id(m, "joint", f"l_joint{n + 1}") >= 0:
        problems.append(f"more than {n} joints per arm (r_joint{n + 1}); jaxsync arms have 6 or 7")
    for a in ARMS:
        for k in range(1, n + 1):
            j = _id(m, "joint", f"{a}_joint{k}")
            if j >= 0 and m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                problems.append(f"joint '{a}_joint{k}' is not a hinge")
            act = _id(m, "actuator", f"{a}_motor{k}")
            if act >= 0 and j >= 0 and m.actuator_trnid[act, 0] != j:
                problems.append(f"actuator '{a}_motor{k}' does not drive '{a}_joint{k}'")
        for s, typ in (("force", mujoco.mjtSensor.mjSENS_FORCE), ("torque", mujoco.mjtSensor.mjSENS_TORQUE)):
            sid = _id(m, "sensor", f"{a}_ft_{s}")
            if sid >= 0 and m.sensor_type[sid] != typ:
                problems.append(f"sensor '{a}_ft_{s}' is not a {s} sensor")
        ft, pad, ee = _id(m, "site", f"{a}_ft"), _id(m, "site", f"{a}_pad"), _id(m, "body", f"{a}_ee")
        if ee >= 0 and ft >= 0 and m.site_bodyid[ft] != ee:
            problems.append(f"site '{a}_ft' is not on body '{a}_ee'")
        if ee >= 0 and pad >= 0 and m.site_bodyid[pad] != ee:
            problems.append(f"site '{a}_pad' is not on body '{a}_ee'")
        if ee >= 0 and np.any(m.body_parentid == ee):
            problems.append(f"body '{a}_ee' must be a leaf (its wrench compensation assumes it)")
    fj = _id(m, "joint", "object_free")
    if fj >= 0 and m.jnt_type[fj] != mujoco.mjtJoint.mjJNT_FREE:
        problems.append("joint 'object_free' is not a free joint")
    if problems:
        raise ModelStructureError(f"{path}: " + "; ".join(problems))


def _contact_index(geoms: np.ndarray, g1: int, g2: int, path: str) -> int:
    hits = [i for i, (a, b) in enumerate(geoms) if {int(a), int(b)} == {g1, g2}]
    if len(hits) != 1:
        raise ModelStructureError(
            f"{path}: expected exactly one contact between geoms {g1} and {g2} (an explicit <pair>), found {len(hits)}"
        )
    return hits[0]


def _pair_row(m: mujoco.MjModel, g1: int, g2: int, path: str) -> int:
    rows = [i for i in range(m.npair) if {int(m.pair_geom1[i]), int(m.pair_geom2[i])} == {g1, g2}]
    if len(rows) != 1:
        raise ModelStructureError(f"{path}: expected one <pair> of geoms {g1} and {g2}, found {len(rows)}")
    return rows[0]


def _build_index(m: mujoco.MjModel, mx: mjx.Model, path: str) -> ModelIndex:
    geoms = _physics.static_contact_geoms(mx)
    obj_geom = _id(m, "geom", "object")

    n = joints_per_arm(m)

    def arm(a: str) -> ArmIndex:
        joints = [_id(m, "joint", f"{a}_joint{k}") for k in range(1, n + 1)]
        pad_geom = _id(m, "geom", f"{a}_pad")
        return ArmIndex(
            prefix=a,
            qpos_adr=tuple(int(m.jnt_qposadr[j]) for j in joints),
            dof_adr=tuple(int(m.jnt_dofadr[j]) for j in joints),
            actuator_ids=tuple(_id(m, "actuator", f"{a}_motor{k}") for k in range(1, n + 1)),
            ee_body=_id(m, "body", f"{a}_ee"),
            root_body=int(m.body_rootid[_id(m, "body", f"{a}_ee")]),
            pad_site=_id(m, "site", f"{a}_pad"),
            ft_site=_id(m, "site", f"{a}_ft"),
            pad_geom=pad_geom,
            force_adr=int(m.sensor_adr[_id(m, "sensor", f"{a}_ft_force")]),
            torque_adr=int(m.sensor_adr[_id(m, "sensor", f"{a}_ft_torque")]),
            contact_id=_contact_index(geoms, obj_geom, pad_geom, path),
            object_is_geom1=bool(geoms[_contact_index(geoms, obj_geom, pad_geom, path), 0] == obj_geom),
        )

    fj = _id(m, "joint", "object_free")
    return ModelIndex(
        right=arm("r"),
        left=arm("l"),
        object_body=_id(m, "body", "object"),
        object_geom=obj_geom,
        object_qpos_adr=int(m.jnt_qposadr[fj]),
        object_dof_adr=int(m.jnt_dofadr[fj]),
        stand_contact_id=_contact_index(geoms, obj_geom, _id(m, "geom", "stand"), path),
        pad_pair_ids=tuple(_pair_row(m, obj_geom, _id(m, "geom", f"{a}_pad"), path) for a in ARMS),
        ncon=len(geoms),
    )


def _ee_summary(ee: dict | None) -> dict | None:
    """The end effector in units a reader can check against a datasheet."""
    if ee is None:
        return None
    return {"mass_kg": ee["mass"], "com_m": list(ee["com"]), "inertia_kg_m2": list(ee["inertia"]),
            "pad_offset_m": ee["pad_offset"]}  # fmt: skip


@dataclasses.dataclass(frozen=True, eq=False)
class RobotScene:
    """What composing a robot file gave: the robot, its arms and its task.

    ``joint_names``, ``links`` and ``torque_limits`` are keyed by arm side
    (``"right"``, ``"left"``); the joint names are the robot's own, in the
    order of jaxsync's ``r_joint1...`` (``l_joint1...``); ``links`` names each
    arm's base, flange and tip link in the robot's MJCF. ``poses`` is the
    solved grasp and approach (``jaxsync.physics.ik``), ``to_task`` the
    rotation ``R`` and translation ``t`` from the robot's world to the task
    frame, ``spec`` the composed ``MjSpec``, ``fingerprint`` a SHA-256 of the
    composed scene (the robot file, every MJCF it reads and jaxsync's
    additions): what a result or checkpoint records to say which robot it is.
    """

    name: str
    file: str
    joint_names: dict
    links: dict
    torque_limits: dict
    object_mass: float
    object_radius: float
    notes: tuple
    poses: dict
    to_task: dict
    spec: object = dataclasses.field(repr=False)
    fingerprint: str = ""
    servo: dict | None = None  # the robot file's ``servo:`` (jaxsync.physics.robot)
    position_servos: dict | None = None  # per arm, the MJCF's own position servos (jaxsync.physics.compose)
    sensor: dict | None = None  # the robot file's ``sensor:``, the wrist sensors' noise (a task default)
    end_effector: dict | None = None  # the end effector added at each flange (jaxsync.physics.robot.END_EFFECTOR)

    def summary(self) -> dict:
        """What composing the robot file decided, as plain data (no MjSpec)."""
        poses = self.poses
        return {
            "name": self.name,
            "file": self.file,
            "fingerprint": self.fingerprint,
            "joints": {arm: list(v) for arm, v in self.joint_names.items()},
            "torque_limits_Nm": {arm: list(v) for arm, v in self.torque_limits.items()},
            "object": {"mass_kg": self.object_mass, "radius_m": self.object_radius},
            "end_effector": _ee_summary(self.end_effector),
            "grasp_manipulability": {arm: poses[arm]["manipulability"] for arm in poses},
            "grasp_static_torque_share_max": {arm: max(poses[arm]["static_torque_share"]) for arm in poses},
            "notes": list(self.notes),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class DualArmModel:
    """The compiled model: MuJoCo C, its MJX copy and the static ids.

    ``robot`` is what a robot file composed (:class:`RobotScene`), None for an
    MJCF in jaxsync's convention (the paper model). ``fingerprint`` says which
    model it is: the composed scene's for a robot, the MJCF file's bytes
    otherwise. The model's default gains and scenario come from
    ``jaxsync.default_gains(model)`` and ``jaxsync.default_scenario(model)``.
    """

    path: str
    solver: str
    mj_model: mujoco.MjModel
    mjx_model: mjx.Model
    index: ModelIndex
    robot: RobotScene | None = None
    fingerprint: str = ""

    @property
    def name(self) -> str:
        """The robot's name, or the MJCF file's."""
        return self.robot.name if self.robot is not None else os.path.splitext(os.path.basename(self.path))[0]

    @property
    def solver_unroll(self) -> int:
        """One-iteration solves per physics step (see SOLVERS)."""
        return SOLVER_UNROLL[self.solver]

    def keyframe_qpos(self, name: str) -> np.ndarray:
        k = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_KEY, name)
        if k < 0:
            raise ModelStructureError(f"{self.path}: no keyframe '{name}'")
        return self.mj_model.key_qpos[k].copy()


def load_mj_model(path: str | os.PathLike | None = None, solver: str = "accurate") -> mujoco.MjModel:
    """Compile the MJCF file to a MuJoCo C model with the chosen solver settings."""
    path = str(path) if path is not None else default_model_path()
    _check_solver(solver)
    m, _ = _compile_model(path, visual=True)
    return _with_solver(m, solver)


def _check_solver(solver: str) -> None:
    if solver not in SOLVERS:
        raise ConfigError(f"solver must be one of {sorted(SOLVERS)}, got {solver!r}")


def _with_solver(m: mujoco.MjModel, solver: str) -> mujoco.MjModel:
    m.opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    for key, value in SOLVERS[solver].items():
        setattr(m.opt, key, value)
    return m


def _compile_model(path: str, visual: bool) -> tuple[mujoco.MjModel, RobotScene | None]:
    """An MJCF file in jaxsync's convention, or a robot file's composed scene (and its report)."""
    if not os.path.isfile(path):
        raise ModelFileError(f"{path}: no such {'robot' if is_robot_file(path) else 'MJCF'} file")
    if not os.access(path, os.R_OK):
        raise ModelFileError(f"{path}: file is not readable")
    if is_robot_file(path):
        m, report = compose_robot(path, visual=visual)
        _check_structure(m, path)
        return m, report
    try:
        m = mujoco.MjModel.from_xml_path(path)
    except (ValueError, OSError) as err:  # mujoco reports XML and compile errors as ValueError
        raise ModelFileError(f"{path}: cannot compile MJCF: {err}") from None
    _check_structure(m, path)
    return m, None


def compose_robot(path: str, visual: bool = True) -> tuple[mujoco.MjModel, RobotScene]:
    """A robot file's task scene (``jaxsync.physics.compose``) with its grasp and
    approach keyframes solved (``jaxsync.physics.ik``), compiled; and what
    composing it gave (:class:`RobotScene`)."""
    robot = load_robot(path)
    composed = _compose.compose(robot, visual=visual)
    m = composed.spec.compile()
    centre = m.body_pos[_id(m, "body", "object")].copy()
    poses = _ik.add_keyframes(
        m, composed.spec, centre, robot.object_radius, composed.torque_limits, _ik.CHECK_GRIP_FORCE,
        robot.object_mass, path, floor_z=float(composed.to_task[1][2]),
    )  # fmt: skip
    m = composed.spec.compile()
    scene = RobotScene(
        name=robot.name,
        file=robot.path,
        joint_names=composed.joint_names,
        links=composed.links,
        torque_limits=composed.torque_limits,
        object_mass=float(robot.object_mass),
        object_radius=float(robot.object_radius),
        notes=tuple(composed.notes),
        poses=poses,
        to_task={"R": composed.to_task[0].tolist(), "t": composed.to_task[1].tolist()},
        spec=composed.spec,
        fingerprint=hashlib.sha256(
            (composed.spec.to_xml() + (repr(sorted(robot.servo.items())) if robot.servo else "")).encode()
        ).hexdigest(),
        servo=robot.servo,
        position_servos=composed.position_servos,
        sensor=robot.sensor,
        end_effector=dict(robot.end_effector),
    )
    return m, scene


def load_model(path: str | os.PathLike | None = None, solver: str = "accurate", *, visual: bool = True) -> DualArmModel:
    """Load the dual-arm MJCF model for MuJoCo C and MJX.

    Args:
      path: an MJCF file in jaxsync's convention, or a robot file (YAML,
        ``jaxsync.physics.robot``: any robot from its own MJCF, the task
        scene composed around it); the packaged paper model when ``None``.
      solver: ``"accurate"`` (the default and jaxsync's one physics: Newton
        converged, differentiable by the implicit adjoint) or ``"unrolled"``
        (three one-iteration solves per step, differentiated through: a
        reference to compare against).
      visual: False drops a robot's mesh geoms (missing mesh files do not
        stop it from loading; bodies must carry their own inertials).

    Raises:
      ModelFileError: the file is missing, unreadable or does not compile.
      ModelStructureError: bodies, joints, sites, sensors, actuators or
        contact pairs that jaxsync needs are missing (all are named).
    """
    _check_solver(solver)
    path = str(path) if path is not None else default_model_path()
    m, report = _compile_model(path, visual)
    m = _with_solver(m, solver)
    patches.mjx_elliptic_gradient()
    mx = mjx.put_model(m, device=_physics.local_device(), impl="jax")
    index = _build_index(m, mx, path)
    if report is not None:
        fingerprint = report.fingerprint
    else:
        with open(path, "rb") as f:
            fingerprint = hashlib.sha256(f.read()).hexdigest()
    return DualArmModel(
        path=path, solver=solver, mj_model=m, mjx_model=mx, index=index, robot=report, fingerprint=fingerprint
    )


def as_model(model, solver: str = "accurate", *, visual: bool = True) -> DualArmModel:
    """``model`` itself when it is a :class:`DualArmModel`, else :func:`load_model`
    of it (an MJCF or robot file; None: the paper model): what a job takes."""
    if isinstance(model, DualArmModel):
        return model
    return load_model(model, solver, visual=visual)


def identity(model: DualArmModel) -> dict:
    """Which model this is, as results, gains files and checkpoints record it:
    its name, its file (a robot file, or the MJCF) and its fingerprint."""
    return {"name": model.name, "file": model.path, "fingerprint": model.fingerprint}


def same_model(recorded: dict | None, model: DualArmModel) -> bool:
    """Whether ``recorded`` (an :func:`identity`) names ``model``: the same
    fingerprint. None (a file that records no model) cannot be checked and passes."""
    return not recorded or recorded.get("fingerprint") == model.fingerprint


def describe_identity(recorded: dict) -> str:
    """``recorded`` (an :func:`identity`) in words, for messages."""
    return f"'{recorded.get('name')}' ({recorded.get('file')}, fingerprint {str(recorded.get('fingerprint'))[:12]})"


def summary(model: DualArmModel) -> dict:
    """A plain-dict description of a loaded model (``jaxsync info`` prints it)."""
    m = model.mj_model
    name = lambda obj, i: mujoco.mj_id2name(m, obj, i)  # noqa: E731
    arms = {}
    for arm in model.index.arms:
        arms[arm.prefix] = [name(mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[a])) for a in arm.dof_adr]
    return {
        "model": model.path,
        "bodies": m.nbody,
        "nq": m.nq,
        "nv": m.nv,
        "joints_per_arm": {k: len(v) for k, v in arms.items()},
        "arm_joints": arms,
        "actuators": m.nu,
        "sensors": [name(mujoco.mjtObj.mjOBJ_SENSOR, i) for i in range(m.nsensor)],
        "contact_pairs": [
            f"{name(mujoco.mjtObj.mjOBJ_GEOM, int(m.pair_geom1[i]))}-"
            f"{name(mujoco.mjtObj.mjOBJ_GEOM, int(m.pair_geom2[i]))}"
            for i in range(m.npair)
        ],
        "colliding_geoms_outside_pairs": int(((m.geom_contype != 0) | (m.geom_conaffinity != 0)).sum()),
        "object_mass_kg": float(m.body_subtreemass[model.index.object_body]),
        "object_radius_m": float(m.geom_size[model.index.object_geom][0]),
        "timestep_s": float(m.opt.timestep),
        "integrator": mujoco.mjtIntegrator(m.opt.integrator).name,
        "solver": f"{mujoco.mjtSolver(m.opt.solver).name} ({model.solver}: iterations={m.opt.iterations}, "
        f"ls_iterations={m.opt.ls_iterations})",
        "cone": mujoco.mjtCone(m.opt.cone).name,
        "fingerprint": model.fingerprint,
        **({"robot": model.robot.summary()} if model.robot is not None else {}),
    }
