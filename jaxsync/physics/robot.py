"""A robot file: a dual-arm robot described in terms of its own MJCF.

A robot file is YAML (schema version 1, docs/robots.md)::

    version: 1
    name: my_robot
    model: robot.xml              # one MJCF holding both arms (paths relative to this file)
    arms:
      right: {joints: [j1, j2, j3, j4, j5, j6, j7], flange: right_flange_site}
      left:  {joints: [...], flange: left_flange_site}
    object: {position: [x, y, z], radius: 0.1, mass: 0.5}

or, one single-arm MJCF used twice, each arm with its own ``model`` and
``base`` ({pos: [x, y, z], quat: [w, x, y, z]}, in the robot's frame). Per
arm, optionally: ``torque_limits`` (N m per joint, for models that carry
none) and ``actuators`` (the model's torque motors to take the limits from,
one per joint) and ``ros_prefix`` (put before every joint and link name of
the arm's ROS export, e.g. ``right_``, as multi-arm ros2_control descriptions
prefix each arm). ``flange`` names a site or a body whose +z axis points out
of the flange, away from the arm. Optional at the top: ``clamp_axis`` ([x, y, z], horizontal: the
line the pads close along, from the right pad towards the left; default:
the horizontal direction from the right arm's base to the left arm's),
``stand`` (true: a stand under the object, the default) and ``servo`` (each
joint's position servo, for ``actuation="position"``: ``{stiffness: [...],
damping: [...]}``, N m/rad and N m s/rad per joint, or ``{bandwidth: HZ,
damping_ratio: 1.0}``, or per arm ``{right: {stiffness: [...], damping:
[...]}, left: {...}}`` as ``jaxsync calibrate`` writes it; without gains the
servo is the MJCF's own position actuators, ``jaxsync.physics.servo``; and
its structure, ``weight_compensation: true|false`` and
``velocity_feedforward: true|false``, false unless stated) and
``delay`` (``{periods: N, control_rate: HZ}``: the control periods a
position command waits before the servo acts on it, at that rate; the
default ``--delay`` of position-controlled jobs on this robot) and
``joint_dynamics`` (per arm, ``{damping: [...], frictionloss: [...],
armature: [...]}``, each optional, one value per joint: N m s/rad, N m and
kg m^2 that replace the MJCF's, as ``jaxsync calibrate --fit`` writes them)
and ``sensor`` (``{force_noise: N, torque_noise: N m}``, each optional: the
wrist sensors' white noise, the task's in place of 0.1 N and 0.005 N m, as
``jaxsync calibrate --wrench-topics`` writes it) and ``end_effector``
(``{mass: kg, com: [x, y, z], inertia: [ixx, iyy, izz], pad_offset: m}``,
each optional, in the flange's frame: the sensor plate and pad jaxsync adds
at each flange, :data:`END_EFFECTOR` where unstated).

:func:`load_robot` validates everything it can without compiling the MJCF
(the composer, ``jaxsync.physics.compose``, checks the rest against the
model) and names the key and what is allowed in every message.
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np
import yaml

from jaxsync._errors import ConfigError

SCHEMA_VERSION = 1
ARM_NAMES = ("right", "left")
_TOP_KEYS = {
    "version",
    "name",
    "model",
    "arms",
    "object",
    "clamp_axis",
    "stand",
    "servo",
    "delay",
    "joint_dynamics",
    "sensor",
    "end_effector",
}
# joint_dynamics: each field's unit and the MJCF joint attribute it replaces
JOINT_DYNAMICS = {"damping": "N m s/rad", "frictionloss": "N m", "armature": "kg m^2"}
_SERVO_FORMS = ({"stiffness", "damping"}, {"bandwidth", "damping_ratio"})
STRUCTURE_KEYS = ("weight_compensation", "velocity_feedforward")
"""The servo's structure a robot file states (``jaxsync.physics.servo``); unstated: false."""
_ARM_KEYS = {"model", "base", "joints", "flange", "torque_limits", "actuators", "ros_prefix"}
_ROS_PREFIX = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_OBJECT_KEYS = {"position", "radius", "mass"}
END_EFFECTOR = {"mass": 0.3, "com": (0.0, 0.0, 0.02), "inertia": (3e-4, 3e-4, 4e-4), "pad_offset": 0.036}
"""The end effector jaxsync adds at each flange unless the robot file says otherwise (``end_effector``):
mass (kg), centre of mass (m, flange frame), principal inertia about it (kg m^2, flange axes) and the pad
face's distance from the flange along its +z (m): an F/T sensor's plate and a pad."""


@dataclasses.dataclass(frozen=True)
class ArmSpec:
    """One arm: its joints (6 or 7 hinges, base to flange), flange, limits."""

    joints: tuple[str, ...]
    flange: str
    model: str | None = None  # absolute path of its own MJCF (single-arm form)
    base_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    torque_limits: tuple[float, ...] | None = None
    actuators: tuple[str, ...] | None = None
    ros_prefix: str = ""  # put before every joint and link name the arm's ROS files name


@dataclasses.dataclass(frozen=True)
class Robot:
    """A validated robot file (:func:`load_robot`)."""

    name: str
    path: str  # the robot file
    right: ArmSpec
    left: ArmSpec
    object_position: tuple[float, float, float]
    object_radius: float = 0.1
    object_mass: float = 0.5
    model: str | None = None  # absolute path of the bimanual MJCF
    clamp_axis: tuple[float, float, float] | None = None
    stand: bool = True
    # {"stiffness": (n,), "damping": (n,)}, {"bandwidth": Hz, "damping_ratio": z}, per arm, or none of
    # these (the MJCF's actuators), with "weight_compensation"/"velocity_feedforward" where stated
    servo: dict | None = None
    # or {"right": {"stiffness": (n,), "damping": (n,)}, "left": {...}}
    delay: tuple[int, float] | None = None  # (control periods, at control_rate Hz)
    joint_dynamics: dict | None = None  # {"right": {"damping": (n,), ...}, "left": {...}}, fields optional
    sensor: dict | None = None  # {"force_noise": N, "torque_noise": N m}, each optional
    # {"mass": kg, "com": (3,) m, "inertia": (3,) kg m^2, "pad_offset": m}: END_EFFECTOR with the file's keys
    end_effector: dict = dataclasses.field(default_factory=lambda: dict(END_EFFECTOR))

    @property
    def arms(self) -> tuple[ArmSpec, ArmSpec]:
        return (self.right, self.left)


def _where(path: str, key: str) -> str:
    return f"{path}: {key}"


def _numbers(value, n: int | None, path: str, key: str, what: str) -> tuple[float, ...]:
    if not isinstance(value, list | tuple) or (n is not None and len(value) != n):
        size = f"{n} numbers" if n is not None else "a list of numbers"
        raise ConfigError(f"{_where(path, key)} must be {size} ({what}), got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise ConfigError(f"{_where(path, key)} must hold finite numbers ({what}), got {value!r}")
        out.append(float(v))
    return tuple(out)


def _names(value, path: str, key: str) -> tuple[str, ...]:
    if not isinstance(value, list | tuple) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{_where(path, key)} must be a list of names, got {value!r}")
    if len(set(value)) != len(value):
        raise ConfigError(f"{_where(path, key)} names a joint twice: {list(value)}")
    return tuple(value)


def _file(value, root: str, path: str, key: str) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{_where(path, key)} must be an MJCF file name, got {value!r}")
    full = value if os.path.isabs(value) else os.path.join(root, value)
    if not os.path.isfile(full):
        raise ConfigError(f"{_where(path, key)}: no such MJCF file {full!r} (paths are relative to the robot file)")
    return os.path.abspath(full)


def _unknown(keys, allowed, path: str, where: str) -> None:
    extra = sorted(set(keys) - allowed)
    if extra:
        raise ConfigError(f"{_where(path, where)}: unknown key(s) {extra}; allowed: {sorted(allowed)}")


def _arm(doc, name: str, root: str, path: str, bimanual: bool) -> ArmSpec:
    key = f"arms.{name}"
    if not isinstance(doc, dict):
        raise ConfigError(f"{_where(path, key)} must be a mapping with joints and flange, got {doc!r}")
    _unknown(doc, _ARM_KEYS, path, key)
    for need in ("joints", "flange"):
        if need not in doc:
            raise ConfigError(f"{_where(path, key)}: missing '{need}'")
    joints = _names(doc["joints"], path, f"{key}.joints")
    if len(joints) not in (6, 7):
        raise ConfigError(
            f"{_where(path, key + '.joints')} must name 6 or 7 hinge joints (base to flange), got {len(joints)}"
        )
    if not isinstance(doc["flange"], str) or not doc["flange"]:
        raise ConfigError(f"{_where(path, key + '.flange')} must name a site or a body, got {doc['flange']!r}")
    model = None
    if "model" in doc:
        if bimanual:
            raise ConfigError(
                f"{_where(path, key + '.model')}: the file's top-level 'model' holds both arms; give either one "
                "'model' at the top or one per arm"
            )
        model = _file(doc["model"], root, path, f"{key}.model")
    elif not bimanual:
        raise ConfigError(f"{_where(path, key)}: missing 'model' (no top-level 'model' holds both arms)")
    pos, quat = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
    if "base" in doc:
        base = doc["base"]
        if not isinstance(base, dict):
            raise ConfigError(f"{_where(path, key + '.base')} must be {{pos: [x, y, z], quat: [w, x, y, z]}}")
        _unknown(base, {"pos", "quat"}, path, f"{key}.base")
        if "pos" in base:
            pos = _numbers(base["pos"], 3, path, f"{key}.base.pos", "m, in the robot's frame")
        if "quat" in base:
            quat = _numbers(base["quat"], 4, path, f"{key}.base.quat", "w, x, y, z")
            norm = float(np.linalg.norm(quat))
            if norm < 1e-9:
                raise ConfigError(f"{_where(path, key + '.base.quat')} must not be zero")
            quat = tuple(float(q) / norm for q in quat)
    limits = None
    if "torque_limits" in doc:
        limits = _numbers(doc["torque_limits"], len(joints), path, f"{key}.torque_limits", "N m, one per joint")
        if min(limits) <= 0:
            raise ConfigError(f"{_where(path, key + '.torque_limits')} must be positive, got {list(limits)}")
    actuators = None
    if "actuators" in doc:
        actuators = _names(doc["actuators"], path, f"{key}.actuators")
        if len(actuators) != len(joints):
            raise ConfigError(
                f"{_where(path, key + '.actuators')} must name one torque motor per joint "
                f"({len(joints)}), got {len(actuators)}"
            )
    ros_prefix = doc.get("ros_prefix", "")
    if not isinstance(ros_prefix, str) or (ros_prefix and not _ROS_PREFIX.fullmatch(ros_prefix)):
        raise ConfigError(
            f"{_where(path, key + '.ros_prefix')} must be a ROS name prefix (a letter, then letters, digits or _), "
            f"got {ros_prefix!r}"
        )
    return ArmSpec(joints, doc["flange"], model, pos, quat, limits, actuators, ros_prefix)


def load_robot(path: str | os.PathLike) -> Robot:
    """Read and validate a robot file (schema in the module docstring).

    Raises:
      ConfigError: a missing, unknown or malformed key, named with what is
        allowed; a model file that does not exist.

    Example:
      >>> robot = jaxsync.load_robot("mjcf/robots/iiwa14_twice.yaml")
      >>> len(robot.right.joints)
      7
    """
    path = str(path)
    if not os.path.isfile(path):
        raise ConfigError(f"{path}: no such robot file")
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: a robot file is a YAML mapping (docs/robots.md), got {type(doc).__name__}")
    _unknown(doc, _TOP_KEYS, path, "top level")
    version = doc.get("version", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise ConfigError(f"{_where(path, 'version')}: this jaxsync reads robot files of version 1, got {version!r}")
    for need in ("arms", "object"):
        if need not in doc:
            raise ConfigError(f"{path}: missing '{need}'")
    root = os.path.dirname(os.path.abspath(path))
    name = doc.get("name", os.path.splitext(os.path.basename(path))[0])
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{_where(path, 'name')} must be a non-empty string, got {name!r}")
    model = _file(doc["model"], root, path, "model") if "model" in doc else None
    arms = doc["arms"]
    if not isinstance(arms, dict) or set(arms) != set(ARM_NAMES):
        got = sorted(arms) if isinstance(arms, dict) else arms
        raise ConfigError(f"{_where(path, 'arms')} must have exactly the keys right and left, got {got!r}")
    right, left = (_arm(arms[a], a, root, path, model is not None) for a in ARM_NAMES)
    obj = doc["object"]
    if not isinstance(obj, dict):
        raise ConfigError(f"{_where(path, 'object')} must be {{position: [x, y, z], radius: r, mass: m}}")
    _unknown(obj, _OBJECT_KEYS, path, "object")
    if "position" not in obj:
        raise ConfigError(f"{_where(path, 'object')}: missing 'position' (m, the ball's centre in the robot's frame)")
    position = _numbers(obj["position"], 3, path, "object.position", "m, in the robot's frame")
    values = {}
    for key, default, lo, hi in (("radius", 0.1, 0.01, 0.5), ("mass", 0.5, 0.01, 20.0)):
        v = obj.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
            unit = "m" if key == "radius" else "kg"
            raise ConfigError(f"{_where(path, 'object.' + key)} must be a number in [{lo}, {hi}] {unit}, got {v!r}")
        values[key] = float(v)
    axis = None
    if "clamp_axis" in doc:
        axis = np.array(_numbers(doc["clamp_axis"], 3, path, "clamp_axis", "a horizontal direction"))
        if np.linalg.norm(axis[:2]) < 1e-9 or abs(axis[2]) > 1e-6 * np.linalg.norm(axis):
            raise ConfigError(f"{_where(path, 'clamp_axis')} must be horizontal (z = 0) and non-zero, got {axis}")
        axis = tuple(float(a) for a in axis / np.linalg.norm(axis))
    stand = doc.get("stand", True)
    if not isinstance(stand, bool):
        raise ConfigError(f"{_where(path, 'stand')} must be true or false, got {stand!r}")
    servo = _servo_doc(doc["servo"], (right, left), path) if "servo" in doc else None
    delay = _delay(doc["delay"], path) if "delay" in doc else None
    dynamics = _joint_dynamics(doc["joint_dynamics"], (right, left), path) if "joint_dynamics" in doc else None
    sensor = _sensor(doc["sensor"], path) if "sensor" in doc else None
    ee = _end_effector(doc["end_effector"], path) if "end_effector" in doc else dict(END_EFFECTOR)
    return Robot(
        name, os.path.abspath(path), right, left, position, values["radius"], values["mass"], model, axis, stand,
        servo, delay, dynamics, sensor, ee,
    )  # fmt: skip


def _end_effector(doc, path: str) -> dict:
    """``end_effector``: {mass, com, inertia, pad_offset}, each optional (END_EFFECTOR's value where absent)."""
    form = "{mass: kg, com: [x, y, z] m, inertia: [ixx, iyy, izz] kg m^2, pad_offset: m}"
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f"{_where(path, 'end_effector')} must be {form}, each key optional, got {doc!r}")
    _unknown(doc, set(END_EFFECTOR), path, "end_effector")
    out = dict(END_EFFECTOR)
    for key, (lo, hi, unit) in {"mass": (0.01, 20.0, "kg"), "pad_offset": (0.005, 0.5, "m")}.items():
        if key in doc:
            v = doc[key]
            if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
                where = _where(path, "end_effector." + key)
                raise ConfigError(f"{where} must be a number in [{lo}, {hi}] {unit}, got {v!r}")
            out[key] = float(v)
    if "com" in doc:
        com = _numbers(doc["com"], 3, path, "end_effector.com", "m, in the flange's frame")
        if np.linalg.norm(com) > 0.5:
            where = _where(path, "end_effector.com")
            raise ConfigError(f"{where} must lie within 0.5 m of the flange, got {list(com)}")
        out["com"] = tuple(com)
    if "inertia" in doc:
        what = "kg m^2, principal moments about the centre of mass"
        i = _numbers(doc["inertia"], 3, path, "end_effector.inertia", what)
        a, b, c = sorted(i)
        if a <= 0 or a + b < c:
            raise ConfigError(
                f"{_where(path, 'end_effector.inertia')} must be three positive principal moments, each at most "
                f"the sum of the other two (a rigid body's), got {list(i)}"
            )
        out["inertia"] = tuple(i)
    return out


def _sensor(doc, path: str) -> dict:
    """``sensor``: {force_noise: N, torque_noise: N m}, each optional, in [0, 10]."""
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f"{_where(path, 'sensor')} must be {{force_noise: N, torque_noise: N m}}, got {doc!r}")
    _unknown(doc, {"force_noise", "torque_noise"}, path, "sensor")
    for key, v in doc.items():
        if isinstance(v, bool) or not isinstance(v, int | float) or not 0 <= v <= 10:
            raise ConfigError(f"{_where(path, 'sensor.' + key)} must be a standard deviation in [0, 10], got {v!r}")
    return {key: float(v) for key, v in doc.items()}


def _joint_dynamics(doc, arms, path: str) -> dict:
    """``joint_dynamics``: per arm, {damping, frictionloss, armature}, each optional, one value >= 0 per joint."""
    where = _where(path, "joint_dynamics")
    if not isinstance(doc, dict) or not doc or not set(doc) <= set(ARM_NAMES):
        form = "{right: {damping|frictionloss|armature: [...]}, left: ...}"
        raise ConfigError(f"{where} must be {form}, got {doc!r}")
    out = {}
    for arm_name, arm in zip(ARM_NAMES, arms, strict=True):
        fields = doc.get(arm_name) or {}
        if not isinstance(fields, dict):
            raise ConfigError(f"{where}.{arm_name} must map damping, frictionloss or armature to lists, got {fields!r}")
        _unknown(fields, set(JOINT_DYNAMICS), path, f"joint_dynamics.{arm_name}")
        out[arm_name] = {}
        for field, unit in JOINT_DYNAMICS.items():
            if field in fields:
                key = f"joint_dynamics.{arm_name}.{field}"
                values = _numbers(fields[field], len(arm.joints), path, key, f"{unit}, one per joint")
                if min(values) < 0:
                    raise ConfigError(f"{_where(path, key)} must be >= 0, got {list(values)}")
                out[arm_name][field] = values
    return out


def _delay(doc, path: str) -> tuple[int, float]:
    """``delay``: {periods: N, control_rate: HZ}."""
    where = _where(path, "delay")
    if not isinstance(doc, dict) or set(doc) != {"periods", "control_rate"}:
        raise ConfigError(f"{where} must be {{periods: N, control_rate: HZ}}, got {doc!r}")
    n, rate = doc["periods"], doc["control_rate"]
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= 8:
        raise ConfigError(f"{where}.periods must be a whole number of control periods in 0..8, got {n!r}")
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not 1 <= rate <= 100000:
        raise ConfigError(f"{where}.control_rate must be a rate in [1, 100000] Hz, got {rate!r}")
    return int(n), float(rate)


def _servo_doc(doc, arms, path: str) -> dict:
    """``servo``: the gains (per joint, a bandwidth, or per arm; or none: the
    MJCF's own position actuators) and the structure
    (``weight_compensation``, ``velocity_feedforward``: true or false each)."""
    if not isinstance(doc, dict):
        raise ConfigError(f"{_where(path, 'servo')} must be a mapping, got {doc!r}")
    doc = dict(doc)
    structure = {}
    for key in STRUCTURE_KEYS:
        if key in doc:
            v = doc.pop(key)
            if not isinstance(v, bool):
                raise ConfigError(f"{_where(path, 'servo.' + key)} must be true or false, got {v!r}")
            structure[key] = v
    right, left = arms
    if not doc:
        if not structure:
            raise ConfigError(f"{_where(path, 'servo')} is empty: give the gains, the structure, or both")
        return structure
    if set(doc) & set(ARM_NAMES):
        _unknown(doc, set(ARM_NAMES), path, "servo")
        missing = [a for a in ARM_NAMES if a not in doc]
        if missing:
            raise ConfigError(f"{_where(path, 'servo')}: per arm, both arms: missing {missing[0]!r}")
        servo = {}
        for arm_name, arm in zip(ARM_NAMES, arms, strict=True):
            one = _servo(doc[arm_name], len(arm.joints), path, f"servo.{arm_name}")
            if "stiffness" not in one:
                raise ConfigError(f"{_where(path, 'servo.' + arm_name)}: per arm, stiffness and damping per joint")
            servo[arm_name] = one
        return {**servo, **structure}
    servo = _servo(doc, len(right.joints), path)
    if len(left.joints) != len(right.joints):
        raise ConfigError(f"{_where(path, 'servo')}: one servo for both arms needs arms of as many joints")
    return {**servo, **structure}


def _servo(doc, n: int, path: str, key: str = "servo") -> dict:
    """``servo``: per-joint stiffness and damping, or a bandwidth (both arms alike)."""
    forms = (
        "{stiffness: [N m/rad per joint], damping: [N m s/rad per joint]}, {bandwidth: Hz, damping_ratio: z} "
        "or {right: {stiffness: [...], damping: [...]}, left: {...}}"
    )
    if not isinstance(doc, dict) or ("stiffness" in doc) == ("bandwidth" in doc):
        raise ConfigError(f"{_where(path, key)} must be {forms}, got {doc!r}")
    form = _SERVO_FORMS[0] if "stiffness" in doc else _SERVO_FORMS[1]
    _unknown(doc, form, path, key)
    if "stiffness" in doc:
        if "damping" not in doc:
            raise ConfigError(f"{_where(path, key)}: missing 'damping' (N m s/rad, one per joint)")
        kp = _numbers(doc["stiffness"], n, path, f"{key}.stiffness", "N m/rad, one per joint")
        kv = _numbers(doc["damping"], n, path, f"{key}.damping", "N m s/rad, one per joint")
        if min(kp) <= 0 or min(kv) < 0:
            raise ConfigError(f"{_where(path, key)}: stiffness must be > 0 and damping >= 0, got {kp}, {kv}")
        return {"stiffness": kp, "damping": kv}
    out = {}
    for key, default, lo, hi, unit in (("bandwidth", None, 0.1, 500.0, "Hz"), ("damping_ratio", 1.0, 0.05, 10.0, "")):
        v = doc.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
            raise ConfigError(f"{_where(path, 'servo.' + key)} must be a number in [{lo}, {hi}] {unit}, got {v!r}")
        out[key] = float(v)
    return out


def is_robot_file(path) -> bool:
    """A path that names a robot file (YAML) rather than an MJCF model."""
    return str(path).lower().endswith((".yaml", ".yml"))
