"""``jaxsync export``'s job: gains from a file or a model's defaults, written in
a format (``jaxsync.io.export``) and read back.

Example:
  >>> from jaxsync.io.export_gains import export_gains
  >>> r = export_gains(None, "yaml", "results/export")  # doctest: +SKIP
  >>> r.same  # doctest: +SKIP
  True
"""

from __future__ import annotations

import dataclasses
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import Gains
from jaxsync.control.names import FAMILY
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io import sync_file as _sync
from jaxsync.physics import robot_names
from jaxsync.physics.model import DualArmModel, as_model
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import loop_stability as _loop
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.scenario import default_scenario

ROS2_CONTROLLERS = (
    "classical",
    "synchronous",
    "ros2_admittance",
    "ros2_synchronous",
    *FAMILY,
)  # the laws a ros2-admittance export runs
LOOP_CHECKED = ("ros2_synchronous", *FAMILY)  # the files couple the two rules: the loop is checked


class Exported(NamedTuple):
    """What :func:`export_gains` wrote."""

    paths: list[str]  # the files (ros2-admittance: each phase's folder of a schedule)
    kind: str  # "constant gains" or "a gain schedule"
    origin: str  # whose gains: the file, or "the default gains of ..."
    same: bool  # the export read back to the same gains, bit for bit
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
    force: bool = False,
    compliance_at: str = "pad",
    ft_filter: float = 1.0,
    controller: str | None = None,
    delay=0,
    log=None,
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
    servos, ``jaxsync.control.gains.position_loop_gains``, with masses the
    admittance rule runs stably). A ros2-admittance export is refused when
    the admittance rule would run an axis of any phase unstable or within its
    margin at the exported update rate (:func:`deployed_stability`); with
    ``force`` it is written, each file and the notes saying so in a WARNING.
    ``compliance_at="pad"`` (the default): the files name a pad link
    (``pad_links.urdf`` fixes it to the flange) as tip, control, sensor and
    gravity frame, so that the compliance is centred at the pad as simulated;
    "flange": at the flange link, a note giving the distance. What the
    deployed controller still does otherwise than the loop simulated it is
    in the notes, with its size. ``ft_filter``: the
    files' ``ft_sensor.filter_coefficient`` (the rule's F/T filter the gains
    were tuned with, ``Scenario.ft_filter``; 1: unfiltered). ``controller``:
    the one the ros2-admittance files configure (None: the one a gains file
    was tuned for; gains that set the coupling family must name theirs,
    ``ros2_coupled`` or ``ros2_coupled_direct``). Where the files couple the
    two rules (ros2_synchronous and the family) with gains tuned for that
    coupled rule or named so by ``controller``, the coupled loop is checked
    about the hold at every command ``delay`` (an int or (lo, hi) control
    periods; ``jaxsync.sim.loop_stability``, every coupling gain x1.5 too)
    and refused unless stable with that margin (``force``: written with a
    WARNING); ``log`` (a callable taking a line, or None) hears that it runs.
    """
    _actuation.check(actuation)
    from_file = gains is not None and isinstance(gains, str | os.PathLike)
    recorded = gains_file.controller_of(gains) if from_file else None
    if controller is not None and recorded in FAMILY and recorded != controller:  # the placement is the tuned one
        raise ConfigError(
            f"gains {gains} were tuned for the {recorded} controller, not {controller}", inputs=("controller",)
        )
    tuned_for = controller or recorded
    if fmt == "ros2-admittance" and tuned_for not in (None, *ROS2_CONTROLLERS):
        raise ConfigError(
            f"gains {gains} was tuned for the {tuned_for} controller, which ros2_controllers' admittance "
            f"controller cannot run (it is a per-arm admittance: {', '.join(ROS2_CONTROLLERS)}, the synchronous "
            "law with synchronisation.yaml); export it as yaml or json",
            inputs=("gains",),
        )
    target, loaded = None, None
    period = gains_file.deployed_period_of(gains) if from_file else None  # tuned through the rule at it
    if model is not None or fmt == "ros2-admittance" or gains is None:
        loaded = as_model(model, visual=visual)
        if from_file:  # gains tuned on another robot would be written with this one's names
            gains_file.check_model(gains, loaded, any_model)
        if fmt == "ros2-admittance":
            target = _export.ros2_target(
                loaded.mj_model,
                loaded.robot,
                distro=distro,
                command_interfaces=tuple(command_interfaces),
                compliance_at=compliance_at,
            )
            target = dataclasses.replace(target, filter_coefficient=_actuation.check_ft_filter(ft_filter, one=True)[0])
            if period is not None:  # the rate the rule was tuned at, not the default
                target = dataclasses.replace(target, update_rate=_update_rate(period, f"gains {gains}"))
    g = gains_file.load(gains) if from_file else gains_file.load_or_default(gains, loaded, actuation=actuation)
    names = _sync.controller_for(g, tuned_for) if fmt == "ros2-admittance" else None
    warnings = []
    if fmt == "ros2-admittance":
        problems = deployed_stability(g, 1.0 / target.update_rate)
        if problems and not force:
            more = f" (and {len(problems) - 2} more axes or phases)" if len(problems) > 2 else ""
            raise ConfigError(
                "ros2-admittance: the admittance rule (explicit in D and K) would run "
                + "; ".join(problems[:2])
                + more
                + ". Tune through the rule (jaxsync tune --actuation position --controller ros2_admittance, "
                "or another of the rule's controllers: their masses are held within this margin), export a "
                "stack's defaults (actuation='position'), or force it (docs/deploy.md)",
                inputs=("gains", "force"),
            )
        warnings = [f"WARNING: the admittance rule runs {p}" for p in problems]
        if tuned_for in ("classical", "synchronous"):  # stable as a recurrence, but in the loop?
            warnings.append(
                f"WARNING: {gains} was tuned for jaxsync's {tuned_for} law, not through the admittance rule these "
                "files configure; the rule in the loop can run the same gains differently "
                "(docs/deploy-tuning.md): check them through it (jaxsync compare --actuation position --controllers "
                f"ros2_admittance --gains {gains}) or tune with --controller ros2_admittance"
            )
    coupling = []
    if fmt == "ros2-admittance" and names == "ros2_synchronous" and tuned_for != "ros2_synchronous":
        check = f" --gains {gains}" if from_file else ""
        coupling.append(
            "WARNING: synchronisation.yaml's coupling (k_rk, k_lk, k_rl, k_ll) was not tuned through the admittance "
            "rule it couples, and the rule plus a coupling can run unstably where the rule alone is stable "
            f"(docs/ros2-rule.md): check them together (jaxsync compare --actuation position --controllers "
            f"ros2_synchronous{check}, with the robot's --robot; or this export with --controller ros2_synchronous, "
            "which checks the coupled loop's stability) or tune with --controller ros2_synchronous"
        )
    if fmt == "ros2-admittance" and _fed_forward(g):
        coupling.append(
            "WARNING: the joint command's feed-forward (ff_vel, ff_acc) is in synchronisation.yaml only: "
            "ros2_controllers' admittance controller has none, so the two admittance files alone run without it "
            "(docs/deploy.md gives the step a port adds)"
        )
    if fmt == "ros2-admittance" and names in LOOP_CHECKED and tuned_for in LOOP_CHECKED:
        if log is not None:
            log(f"checking the {names} loop's stability about the hold (compiles on first use, about a minute)")
        rate = None if period is None else target.update_rate  # None: the physics rate
        problems, fine = coupled_loop_stability(loaded, g, names, delay, distro, control_rate=rate)
        if problems and not force:
            raise ConfigError(
                f"ros2-admittance: {problems[0]}"
                + (f" (and {len(problems) - 1} more delays or phases)" if len(problems) > 1 else "")
                + ". The coupling would make the deployed loop unstable or leave it within its margin (stable "
                "with every coupling gain x1.5 asked): lower the coupling, tune it at these delays, or force it "
                "(docs/loop-stability.md)",
                inputs=("gains", "delay", "force"),
            )
        coupling += [f"WARNING: {p}" for p in problems] + fine
    paths = _export.export(
        g, fmt, out, target, warnings=tuple(warnings), sync_warnings=tuple(coupling), controller=names
    )
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
        same=gains_file.same_gains(back, g, rtol=0.0),
        notes=warnings + coupling + (_ros2_notes(loaded, target, distro) if fmt == "ros2-admittance" else []),
    )


def _ros2_notes(model, target, distro: str) -> list[str]:
    """What a ros2-admittance user should know beyond the files: the release's gaps, names jaxsync chose,
    and where the deployed controller differs from the loop jaxsync simulated, with the size."""
    notes = _distro_notes(distro)
    notes += [n for n in getattr(getattr(model, "robot", None), "notes", ()) if robot_names.PREFIXED in n]
    notes += [_inertia_note(model, target)]
    if target.arms[0].pad_joint is None:
        notes.append(
            "the compliance is centred at the flange link, "
            + " and ".join(f"{d * 1000:.0f} mm" for d in _flange_to_pad(model))
            + " (right, left) from the pad jaxsync simulated it at: a tangential force there also turns the "
            "flange (the default, --compliance-at pad, centres it at the pad)"
        )
    if any(t.world_joint is not None for t in target.arms):
        notes.append(
            "an arm's base link is turned from the world: kinematics.base and fixed_world_frame name a world-aligned "
            "link fixed to it (pad_links.urdf: add it to your robot description)"
        )
    if any(t.fixed_world is not None and t.world_joint is None for t in target.arms):
        notes.append(
            "Humble roots the chain at your URDF's root link: fixed_world_frame is written as 'world', which must "
            "be that root with the world's axes (z up), or the mass and the gravity compensation turn with it"
        )
    return notes


def _inertia_note(model, target) -> str:
    """The end effector's inertia: jaxsync's wrist sensing removes it, the controller's gravity compensation
    only its weight; sized by the task's planned acceleration."""
    s = default_scenario(model)
    zeros = jnp.zeros((2, 3))
    times = jnp.linspace(0.0, float(s.t_close + s.t_squeeze + s.t_carry), 2001)
    acc = jax.vmap(lambda t: _scenario.plan(s, t, zeros, zeros).obj_acc)(times)
    peak = float(jnp.max(jnp.linalg.norm(acc, axis=1)))
    mass = max(t.weight for t in target.arms) / 9.81
    return (
        f"the controller compensates the end effector's weight only (gravity_compensation), jaxsync's wrist sensing "
        f"also its inertia: {mass:.3g} kg, {mass * peak:.3g} N at the task's peak planned acceleration "
        f"{peak:.3g} m/s^2 (lifting and carrying; none while holding, where the settled peak is measured)"
    )


def _flange_to_pad(model) -> list[float]:
    """Each arm's distance (m) from its flange link's origin to its pad, at the grasp."""
    m = model.mj_model
    d = mujoco.MjData(m)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "grasp")
    if key >= 0:
        mujoco.mj_resetDataKeyframe(m, d, key)
    mujoco.mj_kinematics(m, d)
    out = []
    for side in ("r", "l"):
        ee = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"{side}_ee")
        flange = int(m.body_parentid[ee]) if getattr(model, "robot", None) is not None else ee
        pad = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{side}_pad")
        out.append(float(np.linalg.norm(d.site_xpos[pad] - d.xpos[flange])))
    return out


def _phases(gains) -> list[tuple[str | None, Gains]]:
    """(phase name, its gains) of a schedule; [(None, gains)] for constant gains."""
    if isinstance(gains, _schedule.Schedule):
        return [(p, _schedule.phase(gains, i)) for i, p in enumerate(_schedule.PHASES)]
    return [(None, gains)]


def coupled_loop_stability(
    model, gains, controller: str, delay=0, distro: str = "jazzy", control_rate: float | None = None
) -> tuple[list, list]:
    """(problems, the rest): :func:`jaxsync.sim.loop_stability.loop_margin`'s phrase for each phase of
    ``gains`` and each ``delay`` (int or (lo, hi)) at ``control_rate`` (None: the physics rate), split by
    whether the loop is stable with its margin."""
    lo, hi = _actuation.check_delay(delay)
    problems, fine = [], []
    for phase, g in _phases(gains):
        for d in range(lo, hi + 1):
            r = _loop.loop_margin(model, g, controller, delay=d, control_rate=control_rate, distro=distro)
            phrase = r.phrase + (f", phase {phase}" if phase else "")
            (fine if r.verdict == _loop.VERDICTS[0] else problems).append(phrase)
    return problems, fine


def _fed_forward(g) -> bool:
    """Any phase's ff_vel or ff_acc nonzero."""
    return any(
        float(np.max(np.abs(np.asarray(getattr(p, k))))) > 0.0 for _, p in _phases(g) for k in ("ff_vel", "ff_acc")
    )


def _distro_notes(distro: str) -> list[str]:
    if distro != "humble":
        return []
    return [
        "Humble's admittance controller has no wrench set-point (~/wrench_reference is Jazzy's and later): "
        "it cannot be told the grip force f_d the gains were tuned to hold; it complies toward zero force "
        "unless your reference trajectory squeezes the object"
    ]


def _source_words(model) -> str:
    if isinstance(model, DualArmModel):
        return model.path
    return str(model) if model is not None else "the paper model"


def _update_rate(period: float, what: str) -> int:
    """The controller's ``update_rate`` (an integer of Hz) for the control period ``what`` was tuned at."""
    rate = 1.0 / period if period > 0 else float("nan")
    if not (np.isfinite(rate) and abs(rate - round(rate)) <= 1e-9 * rate and round(rate) >= 1):
        raise ConfigError(
            f"{what} was tuned through the rule at a control period of {period} s, which is no whole "
            "number of Hz: ros2_control's update_rate cannot run it",
            inputs=("gains",),
        )
    return int(round(rate))


def export_check(gains, controller: str, period: float | None = None) -> dict | None:
    """Whether ``jaxsync export --format ros2-admittance`` writes ``gains``
    tuned for ``controller`` without ``--force`` on the per-axis checks
    (:func:`deployed_stability` and the controller's bounds) at ``period``
    (None: the default ``update_rate``): {"format", "update_rate_hz",
    "exports", "problems"}; None for a controller that format cannot run.
    A coupled loop's check (``--delay``) is the export's own."""
    if controller not in ROS2_CONTROLLERS:
        return None
    rate = _update_rate(period, f"a {controller} run") if period is not None else _export.Ros2Target.update_rate
    try:
        problems = deployed_stability(gains, 1.0 / rate)
    except ConfigError as err:  # outside what the controller can hold at all
        problems = [str(err)]
    return {"format": "ros2-admittance", "update_rate_hz": rate, "exports": not problems, "problems": problems}


def deployed_stability(gains, dt: float) -> list[str]:
    """Each axis, arm and phase of ``gains`` that ros2_controllers' admittance
    rule would run at control period ``dt`` unstable or within its margin
    (``jaxsync.control.ros2_admittance.stability_index`` above 1 /
    ``DEPLOY_MARGIN``; joint_damping 0, as exported), as one phrase each,
    worst first; [] when every axis is within it. Gains the controller cannot
    hold at all (``jaxsync.io.export.check_admittance``) raise first."""
    phases = _phases(gains)
    found = []
    for phase, g in phases:
        _export.check_admittance(g, phase)  # what the controller cannot hold at all, said first
        when = f", phase {phase}" if phase else ""
        m, d, k = (np.asarray(v, dtype=float) for v in (g.imp_mass, g.imp_damping, g.imp_stiffness))
        index = _ra.stability_index(m, d, k, dt)
        for arm, axis in zip(*np.nonzero(index * _ra.DEPLOY_MARGIN > 1.0 + 1e-12), strict=True):
            state = "unstable" if index[arm, axis] >= 1.0 else "within its margin"
            found.append(
                (
                    float(index[arm, axis]),
                    f"the {_export.ARMS[arm]} arm's pad axis {_export.AXES[axis]}{when} {state}: dt D/M = "
                    f"{dt * d[arm, axis] / m[arm, axis]:.3g}, dt^2 K/M = {dt * dt * k[arm, axis] / m[arm, axis]:.3g}, "
                    f"(2 dt D/M + dt^2 K/M) / 4 = {index[arm, axis]:.3f} (stable below 1; the margin asks <= "
                    f"{1 / _ra.DEPLOY_MARGIN:.3f}; M = {m[arm, axis]:.4g} at dt = {dt:g} s)",
                )
            )
    return [text for _, text in sorted(found, key=lambda f: -f[0])]
