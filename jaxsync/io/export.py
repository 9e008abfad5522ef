"""Gains out of the simulator: YAML and JSON with units, and ros2_control's admittance controller.

Formats (:data:`FORMATS`):

- ``json`` / ``yaml``: every gain under its jaxsync name, with the paper's
  symbol, its unit and its value (per arm rows right, left; per axis columns
  the pad frame's x, y, z, rx, ry, rz); a gain schedule as one such block per
  task phase. :func:`load` (and so ``jaxsync compare --gains``) reads them
  back to the same gains.
- ``ros2-admittance``: one parameter file per arm in the schema of ros2_controllers'
  ``admittance_controller`` (``<name>: ros__parameters:`` with ``admittance.selected_axes``,
  ``mass``, ``damping_ratio``, ``stiffness``, the control and sensor frames), converted to its
  conventions (axis order x, y, z, rx, ry, rz of the control frame, damping as the ratio zeta = D /
  (2 sqrt(M K))), and ``synchronisation.yaml`` with what the paper adds and the admittance
  controller has no parameter for (k_rk, k_lk, k_rl, k_ll, the inner position loop and the
  null-space gains), for a dual-arm controller to read. A schedule is exported one folder per phase
  (the admittance controller has none); :func:`load` reads such a folder back.

Example:
  >>> paths = export(jaxsync.default_gains(), "yaml", "results/export")  # doctest: +SKIP
  >>> load(paths[0])  # the same gains  # doctest: +SKIP
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np
import yaml

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import Gains
from jaxsync.control.joint_space import COMMAND_ALPHA
from jaxsync.io import results as _results
from jaxsync.io import sync_file as _sync
from jaxsync.io.ros2_target import (  # noqa: F401  (jaxsync.io.export's public names)
    ARMS,
    COMMAND_INTERFACES,
    COMPLIANCE_FRAMES,
    CONTROLLER_TYPE,
    DISTROS,
    KDL_PLUGIN,
    MASS_IN_CONTROL_FRAME,
    ArmTarget,
    Ros2Target,
    mass_axes,
    mass_in_base,
    ros2_target,
)
from jaxsync.physics.model import load_mj_model

FORMATS = ("yaml", "json", "ros2-admittance")
AXES = ("x", "y", "z", "rx", "ry", "rz")
# jaxsync name -> (the paper's symbol, unit)
MEANING = {
    "imp_mass": ("M_d (eqs. 8-10, 15)", "kg for x, y, z; kg m^2 for rx, ry, rz"),
    "imp_damping": ("B_d (eqs. 8-10, 15)", "N s/m for x, y, z; N m s/rad for rx, ry, rz"),
    "imp_stiffness": ("K_d (eqs. 8-10, 15)", "N/m for x, y, z; N m/rad for rx, ry, rz"),
    "k_rk": ("k_rk (eq. 13), right arm's relative-error factor", "1 (|k| <= 1)"),
    "k_lk": ("k_lk (eq. 13), left arm's relative-error factor", "1 (|k| <= 1)"),
    "k_rl": ("k_rl (eq. 17), right arm's compliant-offset factor", "1 (|k| <= 1)"),
    "k_ll": ("k_ll (eq. 17), left arm's compliant-offset factor", "1 (|k| <= 1)"),
    "kp_pos": ("K_p (eq. 18), inner position loop", "1/s^2"),
    "kd_pos": ("K_d of eq. 18 (velocity), inner position loop", "1/s"),
    "kp_null": ("null-space posture stiffness (eq. 18)", "1/s^2"),
    "kd_null": ("null-space posture damping (eq. 18)", "1/s"),
    "obj_mass": ("M_E, object-level impedance (object_impedance)", "kg for x, y, z; kg m^2 for rx, ry, rz"),
    "obj_damping": ("D_E, object-level impedance (object_impedance)", "N s/m for x, y, z; N m s/rad for rx, ry, rz"),
    "obj_stiffness": ("K_E, object-level impedance (object_impedance)", "N/m for x, y, z; N m/rad for rx, ry, rz"),
    "force_p": ("K_P, internal-force loop (task_space)", "m/N for x, y, z; rad/(N m) for rx, ry, rz"),
    "force_i": ("K_I, internal-force loop (task_space)", "m/(N s) for x, y, z; rad/(N m s) for rx, ry, rz"),
    "ff_vel": ("the joint command's feed-forward of the planned twist (position-controlled arms)", "s"),
    "ff_acc": ("the joint command's feed-forward of the planned acceleration (position-controlled arms)", "s^2"),
}
_FAMILY_INPUTS = ("the absolute errors' difference", "its own rule offset", "the other arm's rule offset",
                  "the other arm's wrench error over its admittance")  # fmt: skip
for _c, _what in zip(_gains.FAMILY_FIELDS, _FAMILY_INPUTS, strict=False):  # the coupling family (ros2_coupled)
    MEANING[_c] = (f"coupling family: each arm's gain on {_what}, pad frame", "1 (|c| <= 2)")
    MEANING[_c + "_a"] = (f"coupling family: the first-order filter on {_what}", "1 (0 < a <= 1)")
MEANING["cpl_block"] = ("coupling family: each channel's 6x6 pad-frame block off its diagonal, per arm", "1 (|x| <= 2)")
SYNC_FIELDS, BASELINE_FIELDS = _sync.FIELDS, _sync.BASELINE_FIELDS
HEADER = "jaxsync_gains"
ADMITTANCE_SOURCE = (
    "ros2_controllers admittance_controller, src/admittance_controller_parameters.yaml "
    "(https://github.com/ros-controls/ros2_controllers/tree/master/admittance_controller)"
)


def _block(g: Gains) -> dict:
    out = {}
    for name in Gains._fields:
        symbol, unit = MEANING[name]
        v = np.asarray(getattr(g, name), dtype=float)
        out[name] = {"paper": symbol, "unit": unit, "value": v.tolist() if v.ndim else float(v)}
    return out


def document(gains) -> dict:
    """The yaml/json document: ``{"jaxsync_gains": {...}}``."""
    doc = {"format": 1, "axes": list(AXES), "arms": list(ARMS)}
    if isinstance(gains, _schedule.Schedule):
        doc["schedule"] = {
            "blend_s": _schedule.BLEND_S,
            **{p: _block(_schedule.phase(gains, i)) for i, p in enumerate(_schedule.PHASES)},
        }
    else:
        doc["gains"] = _block(gains)
    return {HEADER: doc}


def _values(block: dict, where: str) -> dict:
    if not isinstance(block, dict):
        raise ConfigError(f"{where}: expected name: {{value: ...}} entries")
    out = {}
    for name, entry in block.items():
        if not isinstance(entry, dict) or "value" not in entry:
            raise ConfigError(f"{where}: gain {name!r} has no 'value'")
        out[name] = entry["value"]
    return out


def from_document(doc: dict, where: str = "gains"):
    """Gains (or a schedule) from :func:`document`'s form."""
    body = doc.get(HEADER)
    if not isinstance(body, dict) or ("gains" in body) == ("schedule" in body):
        raise ConfigError(f"{where}: expected '{HEADER}' with either 'gains' or 'schedule'")
    if "gains" in body:
        return _gains.from_dict(_values(body["gains"], where))
    sched = body["schedule"]
    d = {p: _values(sched.get(p, {}), f"{where}, phase {p}") for p in _schedule.PHASES}
    if "blend_s" in sched:
        d["blend_s"] = sched["blend_s"]
    return _schedule.from_dict(d)


# ------------------------------------------------------------------ ros2


def _yaml_list(v) -> str:
    return "[" + ", ".join(repr(bool(x)).lower() if isinstance(x, bool) else repr(float(x)) for x in v) + "]"


MASS_BOUNDS = _ra.MASS_BOUNDS  # admittance_controller_parameters.yaml's element_bounds
STIFFNESS_BOUNDS = _ra.STIFFNESS_BOUNDS


def check_admittance(g: Gains, phase: str | None = None) -> None:
    """Raise :class:`ConfigError` when the admittance controller cannot hold these
    impedance parameters: mass or stiffness outside its bounds, or a damping it
    cannot express as a ratio (zero stiffness: it computes D = 2 zeta sqrt(M K) = 0)."""
    when = f" (phase {phase})" if phase else ""
    for arm, name in enumerate(ARMS):
        m, b, k = (np.asarray(v, dtype=float)[arm] for v in (g.imp_mass, g.imp_damping, g.imp_stiffness))
        for axis, (mi, bi, ki) in enumerate(zip(m, b, k, strict=True)):
            where = f"{name} arm, axis {AXES[axis]}{when}"
            if not MASS_BOUNDS[0] <= mi <= MASS_BOUNDS[1]:
                raise ConfigError(
                    f"ros2-admittance: mass {mi:g} of the {where} is outside the admittance "
                    f"controller's bounds {list(MASS_BOUNDS)}"
                )
            if not STIFFNESS_BOUNDS[0] <= ki <= STIFFNESS_BOUNDS[1]:
                raise ConfigError(
                    f"ros2-admittance: stiffness {ki:g} of the {where} is outside the admittance "
                    f"controller's bounds {list(STIFFNESS_BOUNDS)}"
                )
            if ki == 0.0:  # jaxsync's damping is > 0
                raise ConfigError(
                    f"ros2-admittance: the {where} has zero stiffness and damping {bi:g}: the admittance "
                    "controller's damping_ratio cannot express it (D = 2 zeta sqrt(M K) = 0); "
                    "use --format yaml or json"
                )
            if not np.isfinite(bi) or bi < 0.0:
                raise ConfigError(f"ros2-admittance: damping {bi:g} of the {where} must be finite and >= 0")


def _admittance_yaml(g: Gains, arm: int, controller: str, phase: str | None, target: Ros2Target, warnings=()) -> str:
    name = ARMS[arm]
    t = target.arms[arm]
    order = list(t.axes)  # the control (tip) frame's axes, each carrying a pad-frame axis
    b = np.asarray(g.imp_damping, dtype=float)[arm][order]
    k = np.asarray(g.imp_stiffness, dtype=float)[arm][order]
    m = mass_in_base(g, arm, t, target.distro)
    # the controller forms D = 2 zeta sqrt(M K) entry by entry from the arrays as written
    zeta = b / (2.0 * np.sqrt(m * k))  # check_admittance: K > 0 here
    when = f", task phase '{phase}'" if phase else ""
    normal = ", ".join(f"{x:.6g}" for x in t.normal)
    lines = [
        *(f"# {w}" for w in warnings),
        f"# jaxsync gains for the {name} arm{when}, in the schema of {ADMITTANCE_SOURCE}",
        f"# ({target.distro}; docs/export.md cites the definition's commit). Every parameter without a default",
        *(
            [
                f"# is set. Axis order x, y, z, rx, ry, rz of the control frame, the pad link '{t.tip}' (jaxsync's pad",
                "# frame: z the pad normal), which pad_links.urdf fixes to the flange link: add it to your robot",
                "# description. The F/T reading must be expressed at the pad: give the sensor's driver the tool",
                f"# transform xyz {_numbers(t.sensor_to_pad[0])} m, rpy {_numbers(t.sensor_to_pad[1])} rad (the pad",
                "# in the sensor's frame), or the torque about the pad misses the lever arm (docs/export.md).",
            ]
            if t.pad_joint is not None
            else [
                f"# is set. Axis order x, y, z, rx, ry, rz of the control frame, the flange link '{t.tip}' (jaxsync's",
                f"# pad frame is that link's axes {list(t.axes[:3])} reordered; the pad normal in it is [{normal}]).",
            ]
        ),
        "# damping_ratio = D / (2 sqrt(M K)), the admittance controller's convention.",
        "# Not carried over (the admittance controller has no parameter for it): the paper's",
        "# synchronisation (absolute and relative errors between the arms, eqs. 12-17, k_rk k_lk k_rl",
        "# k_ll), the inner position loop and the null-space gains (eq. 18): synchronisation.yaml.",
        "# The grip force f_d is a task input, not a gain: "
        + (
            "publish it on ~/wrench_reference (geometry_msgs/WrenchStamped in the F/T sensor's frame:"
            if target.distro != "humble"
            else "Humble's admittance controller has no wrench set-point (Jazzy and later: ~/wrench_reference)."
        ),
        *([f"# force = f_d * [{normal}], docs/export.md)."] if target.distro != "humble" else []),
        *(
            ["# Rolling applies mass, stiffness and damping in the control frame: all in its axis order."]
            if MASS_IN_CONTROL_FRAME[target.distro]
            else [
                "# It applies stiffness and damping in the control frame but the mass per axis of kinematics.base:",
                "# mass is in the base's axis order, each pad axis's mass on the base axis it lies along at the",
                "# grasp (docs/export.md).",
            ]
        ),
        *(
            [
                f"# kinematics.base and fixed_world_frame are '{t.base}': the world's axes (z up), fixed to the arm's",
                f"# base link '{t.world_joint[0]}', which is turned from the world (pad_links.urdf): the controller",
                "# applies its mass per axis of kinematics.base and its gravity compensation along fixed_world_frame's",
                "# z, and jaxsync's loop runs both in the world.",
            ]
            if t.world_joint is not None
            else []
        ),
        *(
            [
                f"# fixed_world_frame is '{t.fixed_world}': Humble's KDL plugin roots the chain at your URDF's root",
                "# link (kinematics.base is not read) and the arm's base link is turned from the world: name that",
                "# root here; the mass and the gravity compensation are right when its axes are the world's (z up).",
            ]
            if t.fixed_world is not None and t.world_joint is None
            else []
        ),
        "# joint_damping is 0: jaxsync's law has none (the default, 5, adds joint-space",
        "# damping the tuned gains did not see). ft_sensor.filter_coefficient is the F/T filter the gains were",
        f"# simulated with ({target.filter_coefficient!r}; 1.0: unfiltered; the controller's default is 0.05).",
        "controller_manager:",
        "  ros__parameters:",
        f"    update_rate: {target.update_rate}  # Hz, the control rate the gains were tuned at",
        f"    {controller}:",
        f"      type: {CONTROLLER_TYPE}",
        f"{controller}:",
        "  ros__parameters:",
        f"    joints: [{', '.join(t.joints)}]",
        f"    command_interfaces: [{', '.join(target.command_interfaces)}]",
        "    state_interfaces: [position, velocity]",
        "    chainable_command_interfaces: [position, velocity]",
        "    kinematics:",
        f"      plugin_name: {KDL_PLUGIN[0]}",
        f"      plugin_package: {KDL_PLUGIN[1]}",
        f"      alpha: {COMMAND_ALPHA!r}  # the damped least squares' alpha, as jaxsync's position stack runs it",
        f"      base: {t.base}",
        f"      tip: {t.tip}",
        "    ft_sensor:",
        f"      name: {t.ft_sensor}  # the sensor's name in your ros2_control hardware description",
        "      frame:",
        f"        id: {t.tip}",
        f"      filter_coefficient: {target.filter_coefficient!r}",
        "    control:",
        "      frame:",
        f"        id: {t.tip}",
        "    fixed_world_frame:",
        "      frame:",
        f"        id: {t.fixed_world or t.base}",
        "    gravity_compensation:",
        "      frame:",
        f"        id: {t.tip}",
        "      CoG:",
        f"        pos: {_yaml_list(t.cog)}  # the simulated end effector's centre of mass, m",
        f"        force: {t.weight!r}  # its weight, N",
        "    admittance:",
        f"      selected_axes: {_yaml_list([True] * 6)}",
        f"      mass: {_yaml_list(m)}",
        f"      damping_ratio: {_yaml_list(zeta)}",
        f"      stiffness: {_yaml_list(k)}",
        "      joint_damping: 0.0",
    ]
    if target.distro == "humble":
        lines.append('    robot_description: ""  # Humble reads the URDF here: your launch file sets it')
        lines.append(f"    alpha: {COMMAND_ALPHA!r}  # Humble's KDL plugin reads this one, not kinematics.alpha")
    return "\n".join(lines) + "\n"


SYNC_SCHEMA, SYNC_NODE = _sync.SCHEMA, _sync.NODE  # synchronisation.yaml (jaxsync.io.sync_file)


def _sync_yaml(g: Gains, phase: str | None, target: Ros2Target, controller: str, warnings=()) -> str:
    axes = {f"pad_axes_{n}": target.arms[a].axes for a, n in enumerate(ARMS)}
    axes.update({f"mass_axes_{n}": mass_axes(target.arms[a], target.distro) for a, n in enumerate(ARMS)})
    return _sync.text(g, phase, target, controller, MEANING, axes, warnings)


def _numbers(v) -> str:
    return "[" + ", ".join(f"{x:.9g}" for x in v) + "]"


def pad_links_urdf(target: Ros2Target) -> str:
    """The links the files name that the robot's description lacks (URDF): each pad link (compliance at the
    pad) fixed to its flange link, and each world-aligned base link (an arm mounted at an angle) fixed to
    the arm's base link."""
    lines = [
        '<?xml version="1.0"?>',
        "<!-- jaxsync: the links the admittance files name that your robot description lacks; add them to it.",
        "     <arm>jaxsync_pad: the tip, control, sensor and gravity frame, fixed to the flange link at jaxsync's",
        "     pad (the face centre, z the pad normal). <arm>jaxsync_world: kinematics.base and fixed_world_frame",
        "     of an arm whose base link is turned from the world, fixed to that link with the world's axes",
        "     (z up), where the controller applies its mass and its gravity compensation. docs/export.md. -->",
        '<robot name="jaxsync_pads">',
    ]
    for t in target.arms:
        for child, joint in ((t.tip, t.pad_joint), (t.base, t.world_joint)):
            if joint is None:
                continue
            parent, (xyz, rpy) = joint
            lines += [
                f'  <link name="{child}"/>',
                f'  <joint name="{child}_joint" type="fixed">',
                f'    <parent link="{parent}"/>',
                f'    <child link="{child}"/>',
                f'    <origin xyz="{" ".join(repr(x) for x in xyz)}" rpy="{" ".join(repr(x) for x in rpy)}"/>',
                "  </joint>",
            ]
    return "\n".join([*lines, "</robot>"]) + "\n"


def _ros2(g: Gains, out: str, phase, target: Ros2Target, controller: str, warnings=(), sync_warnings=()) -> list[str]:
    check_admittance(g, phase)
    _results.ensure_writable_dir(out)
    paths = []
    if any(t.pad_joint is not None or t.world_joint is not None for t in target.arms):
        paths.append(os.path.join(out, "pad_links.urdf"))
        _results.atomic_write_text(paths[-1], pad_links_urdf(target))
    for arm, name in enumerate(ARMS):
        path = os.path.join(out, f"admittance_{name}.yaml")
        text = _admittance_yaml(g, arm, f"admittance_controller_{name}", phase, target, warnings)
        _results.atomic_write_text(path, text)
        paths.append(path)
    path = os.path.join(out, "synchronisation.yaml")
    _results.atomic_write_text(path, _sync_yaml(g, phase, target, controller, sync_warnings))
    return [*paths, path]


def _read_yaml(path: str):
    try:
        with open(path) as f:
            return yaml.safe_load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read YAML: {err}") from None


def _ros2_load(folder: str) -> Gains:
    per_arm = []
    for name in ARMS:
        path = os.path.join(folder, f"admittance_{name}.yaml")
        doc = _read_yaml(path)
        try:
            (params,) = [v for k, v in doc.items() if k != "controller_manager"]
            adm = params["ros__parameters"]["admittance"]
            m, zeta, k = (np.asarray(adm[key], dtype=float) for key in ("mass", "damping_ratio", "stiffness"))
        except (AttributeError, KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"{path}: not an admittance_controller parameter file ({err})") from None
        if not all(v.shape == (6,) for v in (m, zeta, k)):
            raise ConfigError(f"{path}: mass, damping_ratio and stiffness must have 6 entries")
        per_arm.append((m, zeta, k))
    path = os.path.join(folder, "synchronisation.yaml")
    doc = _read_yaml(path)
    try:
        sync = doc[SYNC_NODE]["ros__parameters"]
    except (KeyError, TypeError):
        raise ConfigError(f"{path}: expected {SYNC_NODE}: ros__parameters:") from None
    _sync.version(sync, path)
    fields = {}
    for name, (m, zeta, k) in zip(ARMS, per_arm, strict=True):
        axes = _axes(sync, f"pad_axes_{name}", list(range(6)), path)
        inv = np.argsort(axes)  # pad axis j sits at control-frame position inv[j]
        mass_order = _axes(sync, f"mass_axes_{name}", axes, path)
        d = (2.0 * zeta * np.sqrt(m * k))[inv]  # as the controller forms it, entry by entry; pad order
        tuned = np.asarray(sync.get(f"damping_{name}", d), dtype=float)
        if tuned.shape == (6,) and np.allclose(tuned, d, rtol=1e-12, atol=0.0):
            d = tuned  # the D the ratio was formed from, exactly (an edited damping_ratio wins)
        fields.setdefault("imp_mass", []).append(m[np.argsort(mass_order)])
        fields.setdefault("imp_stiffness", []).append(k[inv])
        fields.setdefault("imp_damping", []).append(d)
    d = {k: np.stack(v).tolist() for k, v in fields.items()}
    d.update({k: sync[k] for k in SYNC_FIELDS + BASELINE_FIELDS if k in sync})
    d.update(_sync.family_fields(sync, path))
    return _gains.from_dict(d)


def _axes(sync: dict, key: str, default, path: str) -> list:
    axes = sync.get(key, default)
    if not isinstance(axes, list) or sorted(axes) != list(range(6)):
        raise ConfigError(f"{path}: {key} must order the 6 axes 0-5, got {axes}")
    return axes


def export(gains, fmt: str, out: str, target=None, warnings=(), sync_warnings=(), controller=None) -> list[str]:
    """Write ``gains`` (constant or a schedule) in format ``fmt`` to folder ``out``; the paths written.
    ``target``: the robot the ros2-admittance files are for (``ros2_target``; the paper model's by default);
    ``warnings``: lines each admittance file opens with; ``sync_warnings``: synchronisation.yaml's;
    ``controller``: the one synchronisation.yaml names (None: ros2_synchronous where the paper's coupling is
    set, else ros2_admittance; the coupling family's gains need theirs named)."""
    if fmt not in FORMATS:
        raise ConfigError(f"fmt must be one of {list(FORMATS)}, got {fmt!r}", inputs=("fmt",))
    if fmt == "ros2-admittance":
        if target is None:
            target = ros2_target(load_mj_model())
        controller = _sync.controller_for(gains, controller)
        if isinstance(gains, _schedule.Schedule):
            for i, p in enumerate(_schedule.PHASES):  # every phase checked before anything is written
                check_admittance(_schedule.phase(gains, i), p)
            paths = []
            for i, p in enumerate(_schedule.PHASES):
                phase = _schedule.phase(gains, i)
                paths += _ros2(phase, os.path.join(out, p), p, target, controller, warnings, sync_warnings)
            return paths
        return _ros2(gains, out, None, target, controller, warnings, sync_warnings)
    _results.ensure_writable_dir(out)
    doc = document(gains)
    path = os.path.join(out, f"gains.{fmt}")
    if fmt == "json":
        _results.write_json(path, doc)
    else:
        head = "# jaxsync gains: every gain under its jaxsync name, with the paper's symbol and unit\n"
        _results.atomic_write_text(
            path, head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)
        )
    return [path]


def controller_of(folder: str) -> str | None:
    """The controller a ros2-admittance export names (``synchronisation.yaml``'s ``controller``; a schedule's
    first phase's), None where it names none (schema 2 and before) or ``folder`` is no such export."""
    for sub in ("", _schedule.PHASES[0]):
        path = os.path.join(folder, sub, "synchronisation.yaml")
        if os.path.exists(path):
            doc = _read_yaml(path)
            sync = doc.get(SYNC_NODE, {}).get("ros__parameters", {}) if isinstance(doc, dict) else {}
            return _sync.controller(sync, path) if isinstance(sync, dict) else None
    return None


def load(path: str):
    """Gains from an exported form: a ``gains.yaml`` export, or a ros2-admittance
    folder (a schedule: its folder of phase folders). JSON files are read by
    :func:`jaxsync.io.gains_file.load`, which calls this for the other forms."""
    if os.path.isdir(path):
        if all(os.path.isdir(os.path.join(path, p)) for p in _schedule.PHASES):
            per = [_ros2_load(os.path.join(path, p)) for p in _schedule.PHASES]
            return _schedule.Schedule(Gains(*(jnp.stack(v) for v in zip(*per, strict=True))))
        if os.path.exists(os.path.join(path, "synchronisation.yaml")):
            return _ros2_load(path)
        raise ConfigError(f"{path}: a folder of gains must hold a ros2-admittance export (synchronisation.yaml)")
    doc = _read_yaml(path)
    if not isinstance(doc, dict) or HEADER not in doc:
        raise ConfigError(f"{path}: expected a jaxsync gains export ('{HEADER}: ...')")
    return from_document(doc, path)
