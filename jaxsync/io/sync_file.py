"""``synchronisation.yaml``: what a dual-arm controller runs beside the two
admittance controllers of a ros2-admittance export (docs/synchronisation.md
names every key, schema :data:`SCHEMA`).

The admittance files hold each arm's mass, damping ratio and stiffness; this
file holds the rest of the update that jaxsync simulated: the controller it is
(``controller``), the paper's coupling factors, the joint-command loop and its
feed-forward, the axis orders the admittance files were written in, the tuned
damping, the baselines' gains, and for the coupling family
(``jaxsync.control.coupling``: ``ros2_coupled``, ``ros2_coupled_direct``)
where it enters, each channel's per-axis gain and filter per arm, and each
channel's 6x6 block off its diagonal. Every value is a ROS 2 parameter type (a
double, an integer, a string, a flat list).
"""

from __future__ import annotations

import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import coupling as _coupling
from jaxsync.control.joint_space import COMMAND_ALPHA
from jaxsync.control.names import FAMILY

SCHEMA = 3
"""The schema version: 2 added ff_vel and ff_acc; 3 added ``controller`` and the coupling family."""
NODE = "dual_arm_synchronisation"
ARMS = ("right", "left")
FIELDS = ("k_rk", "k_lk", "k_rl", "k_ll", "kp_pos", "kd_pos", "kp_null", "kd_null", "ff_vel", "ff_acc")
# the baselines' gains (jaxsync.control.baselines): no ros2 controller reads them; kept so the files read back whole
BASELINE_FIELDS = ("obj_mass", "obj_damping", "obj_stiffness", "force_p", "force_i")


def family_keys() -> list[tuple[str, str, int, str]]:
    """(key, Gains field, arm, kind) of every family entry the file holds: ``cpl_<channel>_<arm>`` (the gain
    per pad axis), ``cpl_<channel>_a_<arm>`` (the filter) and ``cpl_block_<channel>_<arm>`` (the 36 entries
    of the block, row-major: row the offset's pad axis, column the channel input's)."""
    keys = []
    for c, (gain, filt) in enumerate(zip(_coupling.GAIN_FIELDS, _coupling.FILTER_FIELDS, strict=True)):
        for arm, name in enumerate(ARMS):
            keys += [(f"{gain}_{name}", gain, arm, "gain"), (f"{filt}_{name}", filt, arm, "filter")]
            keys.append((f"cpl_block_{_coupling.CHANNELS[c]}_{name}", _coupling.BLOCK_FIELD, arm, f"block{c}"))
    return keys


def _gains_of(g):
    """The Gains of constant gains or of a schedule (its leaves stacked per phase)."""
    return getattr(g, "phases", g)


def family_set(g) -> bool:
    """Any phase's coupling family not at its defaults: a gain or a block entry not 0, a filter not 1."""
    g = _gains_of(g)
    return any(
        bool(np.any(np.asarray(getattr(g, k)) != (1.0 if k in _coupling.FILTER_FIELDS else 0.0)))
        for k in _coupling.FIELDS
    )


def paper_coupling_set(g) -> bool:
    """Any phase's k_rk, k_lk, k_rl or k_ll not 0."""
    return any(bool(np.any(np.asarray(getattr(_gains_of(g), k)) != 0.0)) for k in ("k_rk", "k_lk", "k_rl", "k_ll"))


def controller_for(g, controller: str | None) -> str:
    """The controller the files configure: a family controller as given (``controller``: the one the gains
    were tuned for or named), else ros2_synchronous where the paper's coupling is set (the dual-arm step
    couples the two rules, whatever law the gains were tuned for) and ros2_admittance where not. Gains that
    set the coupling family must name a family controller: its placement decides what a port runs."""
    if family_set(g) and controller not in FAMILY:
        got = f"controller {controller!r}" if controller else "no controller"
        raise ConfigError(
            f"ros2-admittance: these gains set the coupling family (a cpl_* gain or block not 0, or a filter not 1) "
            f"and name {got}: the family's placement is the controller's, one of {', '.join(FAMILY)} "
            "(jaxsync export --controller)",
            inputs=("controller",),
        )
    if controller in FAMILY:
        return controller
    return "ros2_synchronous" if paper_coupling_set(g) else "ros2_admittance"


def _flat(v) -> str:
    return "[" + ", ".join(repr(float(x)) for x in np.ravel(v)) + "]"


def text(g, phase, target, controller: str, meaning: dict, axes: dict, warnings=()) -> str:
    """The file for gains ``g`` (one phase), ``target`` (``jaxsync.io.ros2_target.Ros2Target``), the
    jaxsync ``controller`` the files configure; ``meaning``: each gain's (symbol, unit); ``axes``:
    {"pad_axes_<arm>" | "mass_axes_<arm>": the admittance files' axis orders}."""
    family = controller in FAMILY
    lines = [
        *(f"# {w}" for w in warnings),
        f"# jaxsync synchronisation.yaml, schema {SCHEMA} (docs/synchronisation.md names every key): what "
        + (f"{controller} adds (task phase '{phase}')" if phase else f"{controller} adds"),
        "# to the two admittance controllers of admittance_right.yaml and admittance_left.yaml, for a dual-arm",
        "# controller to read (docs/deploy.md gives its update"
        + ("; docs/coupling.md the coupling's): the coupling family's" if family else "): relative-error factors")
        + (" channels, filters and blocks," if family else " k_rk, k_lk (eq. 13),"),
        "# compliant-offset factors k_rl, k_ll (eq. 17), the joint-command loop kp_pos, kd_pos, kp_null, kd_null",
        "# and the joint command's feed-forward of the plan ff_vel, ff_acc.",
        f"{NODE}:",
        "  ros__parameters:",
        f"    schema_version: {SCHEMA}",
        f"    controller: {controller}  # the jaxsync controller these files configure",
        f"    ros_distro: {target.distro}",
        f"    update_rate: {target.update_rate}  # Hz",
        f"    controllers: [{', '.join(f'admittance_controller_{n}' for n in ARMS)}]  # right, left",
        f"    admittance_files: [{', '.join(f'admittance_{n}.yaml' for n in ARMS)}]",
    ]
    for name in FIELDS:
        symbol, unit = meaning[name]
        lines.append(f"    {name}: {float(np.asarray(getattr(g, name))).__repr__()}  # {symbol} [{unit}]")
    lines.append(
        f"    alpha: {COMMAND_ALPHA!r}  # the joint command's damped least squares, (J^T J + alpha I)^-1 J^T,"
        " the planned twist refined once"
    )
    lines.append("    # for each control-frame axis of admittance_<arm>.yaml, the jaxsync pad-frame axis it carries")
    lines += [f"    pad_axes_{name}: {list(axes[f'pad_axes_{name}'])}" for name in ARMS]
    lines.append("    # for each entry of admittance_<arm>.yaml's mass, the pad-frame axis whose mass it is")
    lines += [f"    mass_axes_{name}: {list(axes[f'mass_axes_{name}'])}" for name in ARMS]
    lines.append("    # the damping D (pad-frame axes) each damping_ratio was formed from, as tuned: read back")
    lines.append("    # where the ratio still gives it to rounding, so that the files re-simulate bit for bit")
    for arm, name in enumerate(ARMS):
        lines.append(f"    damping_{name}: {_flat(np.asarray(g.imp_damping, dtype=float)[arm])}")
    if family:
        lines += [
            "    # the coupling family (docs/coupling.md, 'One period, in order'): where its offset enters, the",
            "    # force channel's time T, then per channel (rel, own, other, force) and arm its gain per pad axis",
            "    # (x y z rx ry rz of that arm's planned pad frame), its filter y' = a u + (1 - a) y, and its 6x6",
            "    # block off the diagonal, row-major (row: the offset's axis, column: the input's)",
            f"    coupling_placement: {FAMILY[controller]}",
            f"    force_time: {_coupling.FORCE_TIME!r}  # s",
        ]
        for key, field, arm, kind in family_keys():
            v = np.asarray(getattr(g, field), dtype=float)
            v = v[int(kind[5:]), arm] if kind.startswith("block") else v[arm]
            lines.append(f"    {key}: {_flat(v)}")
    lines.append("    # the baselines' gains (docs/controller.md): no ros2 controller reads them; jaxsync does")
    for name in BASELINE_FIELDS:
        values = [float(x) for x in np.asarray(getattr(g, name), dtype=float)]
        lines.append(f"    {name}: {values!r}")
    return "\n".join(lines) + "\n"


def controller(sync: dict, path: str) -> str | None:
    """The controller a file names (schema 3), None before it named one."""
    name = sync.get("controller")
    if name is not None and not isinstance(name, str):
        raise ConfigError(f"{path}: controller must be a controller's name, got {name!r}")
    return name


def version(sync: dict, path: str) -> int:
    """The file's schema version, refused when this jaxsync does not know it (0: written before the schema
    had a version)."""
    v = sync.get("schema_version", 0)
    if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= SCHEMA:
        raise ConfigError(
            f"{path}: schema_version {v!r} is not one this jaxsync reads (0 to {SCHEMA}): a newer jaxsync wrote it"
        )
    return v


def family_fields(sync: dict, path: str) -> dict:
    """The coupling family's fields from a file that holds them (``coupling_placement``), else {} (the
    defaults: every gain and block 0, filters 1). A placement that is not the named controller's, or an
    entry of the wrong length, is refused."""
    placement = sync.get("coupling_placement")
    if placement is None:
        return {}
    name = controller(sync, path)
    if FAMILY.get(name) != placement:
        raise ConfigError(
            f"{path}: coupling_placement {placement!r} is not controller {name!r}'s "
            f"(one of {', '.join(f'{c}: {p}' for c, p in FAMILY.items())})"
        )
    gains = {f: np.zeros((2, 6)) for f in _coupling.GAIN_FIELDS}
    gains.update({f: np.ones((2, 6)) for f in _coupling.FILTER_FIELDS})
    block = np.zeros((len(_coupling.CHANNELS), 2, 6, 6))
    for key, field, arm, kind in family_keys():
        if key not in sync:
            raise ConfigError(f"{path}: {key} is missing (a coupling_placement names every family entry)")
        size = 36 if kind.startswith("block") else 6
        try:
            v = np.asarray(sync[key], dtype=float)
        except (TypeError, ValueError):
            v = np.zeros(0)
        if v.shape != (size,):
            raise ConfigError(f"{path}: {key} must be a list of {size} numbers, got {sync[key]!r}")
        if kind.startswith("block"):
            block[int(kind[5:]), arm] = v.reshape(6, 6)
        else:
            gains[field][arm] = v
    return {**{k: v.tolist() for k, v in gains.items()}, _coupling.BLOCK_FIELD: block.tolist()}
