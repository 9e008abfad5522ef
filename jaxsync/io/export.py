"""Gains out of the simulator: YAML and JSON with units, and ros2_control's admittance controller.

Formats (:data:`FORMATS`):

- ``json`` / ``yaml``: every gain under its jaxsync name, with the paper's
  symbol, its unit and its value (per arm rows right, left; per axis columns
  the pad frame's x, y, z, rx, ry, rz); a gain schedule as one such block per
  task phase. :func:`load` (and so ``jaxsync compare --gains``) reads them
  back to the same gains.
- ``ros2-admittance``: one parameter file per arm in the schema of
  ros2_controllers' ``admittance_controller`` (``<name>: ros__parameters:``
  with ``admittance.selected_axes``, ``mass``, ``damping_ratio``,
  ``stiffness``, the control and sensor frames), converted to its conventions
  (axis order x, y, z, rx, ry, rz of the control frame, damping as the ratio
  zeta = D / (2 sqrt(M K))), and ``synchronisation.yaml`` with what the paper
  adds and the admittance controller has no parameter for (k_rk, k_lk, k_rl,
  k_ll, the inner position loop and the null-space gains), for a dual-arm
  controller to read. The admittance controller has no gain schedules: a
  schedule is exported one folder per phase. :func:`load` reads such a folder
  back.

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
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import Gains
from jaxsync.io import results as _results

FORMATS = ("yaml", "json", "ros2-admittance")
AXES = ("x", "y", "z", "rx", "ry", "rz")
ARMS = ("right", "left")
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
}
SYNC_FIELDS = ("k_rk", "k_lk", "k_rl", "k_ll", "kp_pos", "kd_pos", "kp_null", "kd_null")
HEADER = "jaxsync_gains"
# the MJCF's frames (mjcf/dual_arm.xml): the pad site the impedance acts in, the wrist sensor site
FRAMES = {"right": ("r_pad", "r_ft"), "left": ("l_pad", "l_ft")}
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


# admittance_controller_parameters.yaml's element_bounds
MASS_BOUNDS = (1e-4, 1e6)
STIFFNESS_BOUNDS = (0.0, 1e8)


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


# a mass spread between the axes of one block (x, y, z or rx, ry, rz) worth a note, relative
MASS_SPREAD_NOTE = 0.01


def notes(gains) -> list[str]:
    """What the user should know about exporting these gains to the admittance controller
    beyond what every export says (docs/export.md): at most one line, when M_d differs
    between the axes of a block by more than :data:`MASS_SPREAD_NOTE`."""
    phases = (
        [(p, _schedule.phase(gains, i)) for i, p in enumerate(_schedule.PHASES)]
        if isinstance(gains, _schedule.Schedule)
        else [(None, gains)]
    )
    worst = (0.0, "")
    for phase, g in phases:
        m = np.asarray(g.imp_mass, dtype=float)
        for arm, name in enumerate(ARMS):
            for part, cols in (("x, y, z", slice(0, 3)), ("rx, ry, rz", slice(3, 6))):
                v = m[arm, cols]
                spread = float(v.max() / v.min() - 1.0)
                if spread > worst[0]:
                    when = f", phase {phase}" if phase else ""
                    worst = (spread, f"{name} arm, {part}{when}: {', '.join(f'{x:.4g}' for x in v)}")
    if worst[0] <= MASS_SPREAD_NOTE:
        return []
    return [
        f"M_d differs between the axes of a block by up to {100 * worst[0]:.0f} % ({worst[1]}): the admittance "
        "controller applies its mass per axis of kinematics.base, not of the control frame, so it matches "
        "jaxsync only while the pad frame is aligned with the base frame (docs/export.md)"
    ]


def _admittance_yaml(g: Gains, arm: int, controller: str, phase: str | None) -> str:
    name = ARMS[arm]
    m = np.asarray(g.imp_mass, dtype=float)[arm]
    b = np.asarray(g.imp_damping, dtype=float)[arm]
    k = np.asarray(g.imp_stiffness, dtype=float)[arm]
    zeta = b / (2.0 * np.sqrt(m * k))  # check_admittance: K > 0 here
    pad, ft = FRAMES[name]
    when = f", task phase '{phase}'" if phase else ""
    return "\n".join(
        [
            f"# jaxsync gains for the {name} arm{when}, in the schema of {ADMITTANCE_SOURCE}.",
            "# Axis order x, y, z, rx, ry, rz of the control frame (jaxsync's pad frame: z along the pad",
            "# normal). damping_ratio = D / (2 sqrt(M K)), the admittance controller's convention.",
            "# Not carried over (the admittance controller has no parameter for it): the paper's",
            "# synchronisation (absolute and relative errors between the arms, eqs. 12-17, k_rk k_lk k_rl",
            "# k_ll), the inner position loop and the null-space gains (eq. 18): synchronisation.yaml;",
            "# the desired contact wrench f_d (a task input, not a gain: the admittance controller has no",
            "# wrench set-point). It applies stiffness and damping in the control frame but the mass per",
            "# axis of kinematics.base (docs/export.md). joint_damping is set to 0: jaxsync's law has none",
            "# (the controller's default, 5, adds joint-space damping the tuned gains did not see).",
            "# Fill in joints, interfaces, kinematics and robot_description for your robot.",
            f"{controller}:",
            "  ros__parameters:",
            "    control:",
            "      frame:",
            f"        id: {pad}",
            "    ft_sensor:",
            "      frame:",
            f"        id: {ft}",
            "    admittance:",
            f"      selected_axes: {_yaml_list([True] * 6)}",
            f"      mass: {_yaml_list(m)}",
            f"      damping_ratio: {_yaml_list(zeta)}",
            f"      stiffness: {_yaml_list(k)}",
            "      joint_damping: 0.0",
            "",
        ]
    )


def _sync_yaml(g: Gains, phase: str | None) -> str:
    lines = [
        "# jaxsync: what the paper's synchronous controller adds to two admittance controllers"
        + (f" (task phase '{phase}')" if phase else ""),
        "# (docs/controller.md): relative-error factors k_rk, k_lk (eq. 13), compliant-offset factors",
        "# k_rl, k_ll (eq. 17), the inner position loop kp_pos, kd_pos and the null-space gains (eq. 18).",
        "dual_arm_synchronisation:",
        "  ros__parameters:",
    ]
    for name in SYNC_FIELDS:
        symbol, unit = MEANING[name]
        lines.append(f"    {name}: {float(np.asarray(getattr(g, name))).__repr__()}  # {symbol} [{unit}]")
    return "\n".join(lines) + "\n"


def _ros2(g: Gains, out: str, phase: str | None) -> list[str]:
    check_admittance(g, phase)
    _results.ensure_writable_dir(out)
    paths = []
    for arm, name in enumerate(ARMS):
        path = os.path.join(out, f"admittance_{name}.yaml")
        _results.atomic_write_text(path, _admittance_yaml(g, arm, f"admittance_controller_{name}", phase))
        paths.append(path)
    path = os.path.join(out, "synchronisation.yaml")
    _results.atomic_write_text(path, _sync_yaml(g, phase))
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
    fields = {}
    for name in ARMS:
        path = os.path.join(folder, f"admittance_{name}.yaml")
        doc = _read_yaml(path)
        try:
            (params,) = doc.values()
            adm = params["ros__parameters"]["admittance"]
            m, zeta, k = (np.asarray(adm[key], dtype=float) for key in ("mass", "damping_ratio", "stiffness"))
        except (AttributeError, KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"{path}: not an admittance_controller parameter file ({err})") from None
        if not all(v.shape == (6,) for v in (m, zeta, k)):
            raise ConfigError(f"{path}: mass, damping_ratio and stiffness must have 6 entries")
        fields.setdefault("imp_mass", []).append(m)
        fields.setdefault("imp_stiffness", []).append(k)
        fields.setdefault("imp_damping", []).append(2.0 * zeta * np.sqrt(m * k))
    path = os.path.join(folder, "synchronisation.yaml")
    doc = _read_yaml(path)
    try:
        sync = doc["dual_arm_synchronisation"]["ros__parameters"]
    except (KeyError, TypeError):
        raise ConfigError(f"{path}: expected dual_arm_synchronisation: ros__parameters:") from None
    d = {k: np.stack(v).tolist() for k, v in fields.items()}
    d.update({k: sync[k] for k in SYNC_FIELDS if k in sync})
    return _gains.from_dict(d)


def export(gains, fmt: str, out: str) -> list[str]:
    """Write ``gains`` (constant or a schedule) in format ``fmt`` to folder ``out``; the paths written."""
    if fmt not in FORMATS:
        raise ConfigError(f"--format must be one of {list(FORMATS)}, got {fmt!r}")
    if fmt == "ros2-admittance":
        if isinstance(gains, _schedule.Schedule):
            for i, p in enumerate(_schedule.PHASES):  # every phase checked before anything is written
                check_admittance(_schedule.phase(gains, i), p)
            paths = []
            for i, p in enumerate(_schedule.PHASES):
                paths += _ros2(_schedule.phase(gains, i), os.path.join(out, p), p)
            return paths
        return _ros2(gains, out, None)
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
