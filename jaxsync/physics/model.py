"""Loading the dual-arm MJCF model and resolving its names to ids, once.

Everything here runs eagerly in Python, before anything is traced: ``jit``-ed
code only ever sees the integer ids gathered in :class:`ModelIndex`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
from typing import Literal

import mujoco
import numpy as np
from mujoco import mjx

from jaxsync._errors import ConfigError, ModelFileError, ModelStructureError
from jaxsync.physics import step as _physics
from jaxsync.runtime import patches

ARMS = ("r", "l")
JOINTS_PER_ARM = 7

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


def required_names() -> dict[str, list[str]]:
    """Every MJCF name jaxsync relies on, by kind."""
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
        names["joint"] += [f"{a}_joint{k}" for k in range(1, JOINTS_PER_ARM + 1)]
        names["actuator"] += [f"{a}_motor{k}" for k in range(1, JOINTS_PER_ARM + 1)]
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
    missing = [
        f"{kind} '{name}'" for kind, names in required_names().items() for name in names if _id(m, kind, name) < 0
    ]
    problems = []
    if missing:
        problems.append("missing " + ", ".join(missing))
    for a in ARMS:
        for k in range(1, JOINTS_PER_ARM + 1):
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

    def arm(a: str) -> ArmIndex:
        joints = [_id(m, "joint", f"{a}_joint{k}") for k in range(1, JOINTS_PER_ARM + 1)]
        pad_geom = _id(m, "geom", f"{a}_pad")
        return ArmIndex(
            prefix=a,
            qpos_adr=tuple(int(m.jnt_qposadr[j]) for j in joints),
            dof_adr=tuple(int(m.jnt_dofadr[j]) for j in joints),
            actuator_ids=tuple(_id(m, "actuator", f"{a}_motor{k}") for k in range(1, JOINTS_PER_ARM + 1)),
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


@dataclasses.dataclass(frozen=True, eq=False)
class DualArmModel:
    """The compiled model: MuJoCo C, its MJX copy and the static ids."""

    path: str
    solver: str
    mj_model: mujoco.MjModel
    mjx_model: mjx.Model
    index: ModelIndex

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
    if solver == "differentiable":
        raise ConfigError(
            "solver 'differentiable' is gone: the 'accurate' solver is differentiable (implicit adjoint of its "
            "converged solve) and is the one to use; 'unrolled' (one-iteration solves) is a reference"
        )
    if solver not in SOLVERS:
        raise ConfigError(f"solver must be one of {sorted(SOLVERS)}, got {solver!r}")
    if not os.path.isfile(path):
        raise ModelFileError(f"{path}: no such MJCF file")
    if not os.access(path, os.R_OK):
        raise ModelFileError(f"{path}: MJCF file is not readable")
    try:
        m = mujoco.MjModel.from_xml_path(path)
    except (ValueError, OSError) as err:  # mujoco reports XML and compile errors as ValueError
        raise ModelFileError(f"{path}: cannot compile MJCF: {err}") from None
    _check_structure(m, path)
    m.opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    for key, value in SOLVERS[solver].items():
        setattr(m.opt, key, value)
    return m


def load_model(path: str | os.PathLike | None = None, solver: str = "accurate") -> DualArmModel:
    """Load the dual-arm MJCF model for MuJoCo C and MJX.

    Args:
      path: an MJCF file; the packaged paper model when ``None``.
      solver: ``"accurate"`` (the default and jaxsync's one physics: Newton
        converged, differentiable by the implicit adjoint) or ``"unrolled"``
        (three one-iteration solves per step, differentiated through: a
        reference to compare against).

    Raises:
      ModelFileError: the file is missing, unreadable or does not compile.
      ModelStructureError: bodies, joints, sites, sensors, actuators or
        contact pairs that jaxsync needs are missing (all are named).
    """
    m = load_mj_model(path, solver)
    patches.mjx_elliptic_gradient()
    path = str(path) if path is not None else default_model_path()
    mx = mjx.put_model(m, device=_physics.local_device(), impl="jax")
    return DualArmModel(path=path, solver=solver, mj_model=m, mjx_model=mx, index=_build_index(m, mx, path))


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
    }
