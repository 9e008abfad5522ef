"""``jaxsync export``'s job: gains from a file or a model's defaults, written in
a format (``jaxsync.io.export``) and read back.

Example:
  >>> from jaxsync.io.export_gains import export_gains
  >>> r = export_gains(None, "yaml", "results/export")  # doctest: +SKIP
  >>> r.same  # doctest: +SKIP
  True
"""

from __future__ import annotations

import os
from typing import NamedTuple

from jaxsync._errors import ConfigError
from jaxsync.control.gains import Gains
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.physics.model import DualArmModel, as_model
from jaxsync.sim import actuation as _actuation

ROS2_CONTROLLERS = ("classical", "synchronous")  # the laws a ros2-admittance export runs


class Exported(NamedTuple):
    """What :func:`export_gains` wrote."""

    paths: list[str]  # the files (ros2-admittance: each phase's folder of a schedule)
    kind: str  # "constant gains" or "a gain schedule"
    origin: str  # whose gains: the file, or "the default gains of ..."
    same: bool  # the export read back to the same gains (relative difference <= 1e-12)
    notes: list[str]  # what the ros2_control files cannot carry over as jaxsync runs it


def export_gains(
    gains=None,
    fmt: str = "yaml",
    out: str = "results/export",
    *,
    model=None,
    visual: bool = True,
    distro: str = "jazzy",
    command_interfaces=("position",),
    any_model: bool = False,
    actuation: str = "torque",
) -> Exported:
    """Write ``gains`` as ``fmt`` (``jaxsync.io.export.FORMATS``) to ``out``, then read the files back.

    ``gains``: a gains file (JSON, or an export), gains or a schedule; None:
    ``model``'s defaults. ``model``: a loaded model, or the MJCF or robot file
    to load (None: the paper model; ``visual`` False leaves a robot's meshes
    out); it is loaded when the gains are its defaults, when ros2-admittance
    files name its joints and links (for ``distro`` and the joint
    ``command_interfaces``), or when it is named, to refuse a gains file tuned
    on another model (unless ``any_model``). Every input is checked before
    anything is written. ``actuation``: the stack whose default gains are
    exported when ``gains`` is None ("position": held below the robot's joint
    servos, ``jaxsync.control.gains.position_loop_gains``).
    """
    _actuation.check(actuation)
    from_file = gains is not None and isinstance(gains, str | os.PathLike)
    tuned_for = gains_file.controller_of(gains) if from_file else None
    if fmt == "ros2-admittance" and tuned_for not in (None, *ROS2_CONTROLLERS):
        raise ConfigError(
            f"gains {gains} was tuned for the {tuned_for} controller, which ros2_controllers' admittance "
            f"controller cannot run (it is a per-arm admittance: the {' and '.join(ROS2_CONTROLLERS)} laws, the "
            "latter with synchronisation.yaml); export it as yaml or json",
            inputs=("gains",),
        )
    target, loaded = None, None
    if model is not None or fmt == "ros2-admittance" or gains is None:
        loaded = as_model(model, visual=visual)
        if from_file:  # gains tuned on another robot would be written with this one's names
            gains_file.check_model(gains, loaded, any_model)
        if fmt == "ros2-admittance":
            target = _export.ros2_target(
                loaded.mj_model, loaded.robot, distro=distro, command_interfaces=tuple(command_interfaces)
            )
    g = gains_file.load(gains) if from_file else gains_file.load_or_default(gains, loaded, actuation=actuation)
    paths = _export.export(g, fmt, out, target)
    back = gains_file.load(paths[0] if fmt != "ros2-admittance" else out)
    if from_file:
        origin = str(gains)
    elif gains is None:
        stack = " on position-controlled arms" if actuation == "position" else ""
        origin = f"the default gains of {_source_words(model)}{stack}"
    else:
        origin = "the given gains"
    return Exported(
        paths=paths,
        kind="a gain schedule" if not isinstance(g, Gains) else "constant gains",
        origin=origin,
        same=gains_file.same_gains(back, g),
        notes=_export.notes(g) if fmt == "ros2-admittance" else [],
    )


def _source_words(model) -> str:
    if isinstance(model, DualArmModel):
        return model.path
    return str(model) if model is not None else "the paper model"
