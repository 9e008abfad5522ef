"""The paper's comparison (section 5): classical vs synchronous (or any controllers) on one scenario."""

from __future__ import annotations

import os
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import compliance as _compliance
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import default_gains, stability_ratio
from jaxsync.control.names import ALL_CONTROLLERS, check_actuation
from jaxsync.io import gains_file
from jaxsync.io import results as _results
from jaxsync.optimize.studies.compare_video import compare_video
from jaxsync.optimize.tuning import scenarios as _scenarios
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.physics.inertia import pad_apparent_inertia
from jaxsync.physics.model import as_model, identity
from jaxsync.runtime.cache import compile_watch
from jaxsync.runtime.gl import select_gl_backend
from jaxsync.sim import crosscheck as _crosscheck
from jaxsync.sim import metrics as _metrics
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.actuation import TORQUE, Stack
from jaxsync.sim.metrics import drop_time
from jaxsync.sim.rollout import rollout
from jaxsync.sim.scenario import min_duration

PAPER = ("classical", "synchronous")  # the paper's pair: compare's default

SUMMARY_KEYS = (
    "settled_peak_resultant_N",
    "mean_grip_force_N",
    "grip_force_error_rel",
    "sync_error_rms_m",
    "force_chatter_N",
    "first_impact_peak_N",
    "apparent_stiffness_normal_N_per_m",
    "apparent_stiffness_tangential_N_per_m",
    "dropped",
    "chattering",
    "torque_limit_share_right",
    "torque_limit_share_left",
)


def check_duration(scenario, duration: float) -> None:
    """The rollout must reach the end of the settling time, where the settled window starts."""
    if duration < min_duration(scenario):
        raise ConfigError(
            f"duration must be at least {min_duration(scenario):.2f} s for this scenario "
            f"(the hold phase starts at {float(sum(_scenario.phase_times(scenario)[2:])):.2f} s "
            f"and is measured after a {float(scenario.settle_time):.2f} s settling time), got {duration}",
            inputs=("duration",),
        )


def run(
    model,
    gains,
    scenario,
    *,
    duration: float,
    backend: str = "mjx",
    controllers: tuple[str, ...] = PAPER,
    log=lambda msg: print(msg, file=sys.stderr, flush=True),
    stack: Stack = TORQUE,
):
    """Roll out each controller on ``stack``; return ``{name: (trajectory, metrics)}``."""
    check_duration(scenario, duration)
    controllers = check_controllers(controllers, stack)
    results = {}
    for i, name in enumerate(controllers):
        compiles = " (compiled first, unless the compilation cache holds it)" if backend == "mjx" and i == 0 else ""
        log(f"[{i + 1}/{len(controllers)}] {name}: rolling out {duration:g} s on {backend}{compiles}...")
        t0 = time.perf_counter()
        with compile_watch() as watch:
            traj = jax.block_until_ready(
                rollout(
                    model,
                    gains,
                    scenario,
                    controller=name,
                    duration=duration,
                    backend=backend,
                    **stack.rollout_options(model),
                )
            )
            m = _metrics.summarize(traj, scenario)
        took = f"{time.perf_counter() - t0:.1f} s{watch.describe()}"
        log(f"[{i + 1}/{len(controllers)}] {name}: done in {took}, {outcome(m)}")
        results[name] = (traj, m)
    return results


def outcome(m) -> str:
    """'settled peak resultant 0.0076 N', or 'dropped the object at t=1.234 s' (then
    the settled-window metrics describe no grasp and are not quoted)."""
    t = drop_time(m)
    if t is not None:
        return f"dropped the object at t={t:.3f} s"
    get = m.get if isinstance(m, dict) else lambda k: getattr(m, k)
    return f"settled peak resultant {float(np.asarray(get('settled_peak_resultant_N'))):.4f} N"


# the metrics of the settled window: what they measure is gone once the object dropped
SETTLED_KEYS = ("settled_peak_resultant_N", "mean_grip_force_N", "grip_force_error_rel", "sync_error_rms_m")


def controllers_of(summary: dict) -> list[str]:
    """The controllers a comparison's summary holds, in its order."""
    return list(summary.get("controllers") or [n for n in ALL_CONTROLLERS if n in summary])


def check_controllers(controllers, stack: Stack = TORQUE) -> tuple[str, ...]:
    """At least two distinct known controller names that run on ``stack``, as a tuple (else ConfigError)."""
    names = tuple(controllers)
    unknown = [n for n in names if n not in ALL_CONTROLLERS]
    if unknown:
        raise ConfigError(f"unknown controller(s) {unknown}; known: {', '.join(ALL_CONTROLLERS)}")
    if len(names) < 2 or len(set(names)) != len(names):
        raise ConfigError(f"--controllers must name at least two different controllers, got {', '.join(names)}")
    check_actuation(names, stack.actuation)
    return names


def table(summary: dict) -> list[str]:
    """The lines jaxsync compare prints: the summary's metrics per controller
    (a dropped controller's settled metrics as 'dropped at t=... s') and the
    resultant ratios (n/a when either dropped the object)."""
    w = 22
    names = controllers_of(summary)
    lines = [f"{'':38}" + "".join(f"{name:>{w}}" for name in names)]
    for k in SUMMARY_KEYS:
        cells = []
        for name in names:
            v, t = summary[name].get(k), drop_time(summary[name])
            if t is not None and k in SETTLED_KEYS:
                cells.append(f"{f'dropped at t={t:.2f} s':>{w}}")
            elif isinstance(v, bool) or v is None:
                cells.append(f"{str(v):>{w}}")
            else:
                cells.append(f"{v:>{w}.5g}")
        lines.append(f"{k:<38}" + "".join(cells))
    first = names[0]
    for name in names[1:]:
        ratio = summary["resultant_ratios"].get(name)
        dropped = [n for n in (first, name) if drop_time(summary[n]) is not None]
        label = f"resultant_ratio ({first} / {name})"
        if dropped:
            who = "both controllers" if len(dropped) == 2 else f"the {dropped[0]} controller"
            lines.append(f"{label}: n/a ({who} dropped the object)")
        else:
            lines.append(f"{label}: {ratio:.3f}" if ratio else f"{label}: n/a")
    return lines


def chattering(summary: dict) -> list[str]:
    """The controllers whose pad forces chattered in the settled window (``jaxsync.sim.metrics.chattering``)."""
    return [n for n in controllers_of(summary) if summary[n].get("chattering")]


def plot_forces(
    series: dict,
    scenario,
    title: str,
    path: str,
    resultant_ylim: float | None = None,
    drop_time_s: float | None = None,
) -> None:
    """Each arm's normal contact force and the resultant force against time (paper Figs. 4, 5);
    a drop (``drop_time_s``) is marked on both panels, and then no settled peak is drawn."""
    plt = _results.pyplot()

    t = series["time_s"]
    _, t_carry, t_hold = (float(x) for x in _scenario.phase_times(scenario))
    t_settled = t_hold + float(scenario.settle_time)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    ax1.plot(t, series["right_normal_force_N"], label="right arm", lw=1)
    ax1.plot(t, series["left_normal_force_N"], label="left arm", lw=1, ls="--")
    ax1.axhline(float(scenario.grip_force), color="k", lw=0.6, ls=":", label="f_d")
    ax1.set_ylabel("contact force [N]")
    ax1.legend(loc="lower right")
    ax1.set_title(title)
    # before the lift the stand carries the object: the resultant is only defined from then on
    carried = np.where(series["phase"] >= 2, series["resultant_force_N"], np.nan)
    ax2.plot(t, carried, color="C3", lw=0.8, label="|sum of pad forces - m (z''_d - g)|")
    mask = t >= t_settled
    if mask.any() and drop_time_s is None:
        peak = series["resultant_force_N"][mask].max()
        ax2.axhline(peak, color="C3", lw=0.6, ls=":", label=f"settled peak {peak:.4f} N")
    if resultant_ylim:
        ax2.set_ylim(0, resultant_ylim)
    ax2.set_ylabel("resultant force [N]")
    ax2.set_xlabel("time [s]")
    ax2.legend(loc="upper right")
    for ax in (ax1, ax2):
        for x in (t_carry, t_hold, t_settled):
            ax.axvline(x, color="0.6", lw=0.6)
        ax.grid(alpha=0.3)
    ax1.text(t_carry, ax1.get_ylim()[1], " lift", va="top", fontsize=8, color="0.4")
    ax1.text(t_hold, ax1.get_ylim()[1], " hold", va="top", fontsize=8, color="0.4")
    if drop_time_s is not None:
        label = f"dropped at t={drop_time_s:.2f} s"
        for ax in (ax1, ax2):
            ax.axvline(drop_time_s, color="r", lw=1.2, ls="--", label=label if ax is ax2 else None)
        ax1.text(drop_time_s, ax1.get_ylim()[0], f" {label}", va="bottom", fontsize=9, color="r")
        ax1.set_title(f"{title}: the object was dropped", color="r")
        ax2.legend(loc="upper right")
    _results.save_figure(fig, path)
    plt.close(fig)


def torque_limits(model) -> np.ndarray:
    """(2, n) each arm's torque limits, N m (its motors' control ranges)."""
    m = model.mj_model
    return np.stack([np.abs(m.actuator_ctrlrange[list(a.actuator_ids)]).max(-1) for a in model.index.arms])


def write_results(
    out: str,
    results: dict,
    scenario,
    gains,
    options: dict,
    wall_time_s: float,
    limits=None,
    stiffness=None,
    model: dict | None = None,
) -> dict:
    """summary.json, series.csv and each controller's force plot; returns the summary. With
    ``limits`` ((2, n), N m) each controller's share of steps at a torque limit, per arm;
    with ``stiffness`` ({name: {"normal", "tangential"}}) each one's apparent stiffness at the pad."""
    _results.ensure_writable_dir(out)
    summary: dict = {}
    columns: dict = {}
    all_series = {
        name: {k: np.asarray(v) for k, v in _metrics.series(traj, scenario).items()}
        for name, (traj, _) in results.items()
    }
    # one resultant scale for both plots, so they can be compared by eye (a drop's peak is no scale)
    held = [float(np.asarray(m.settled_peak_resultant_N)) for _, m in results.values() if drop_time(m) is None]
    ylim = 1.5 * max(held) if held and max(held) > 0 else None
    for name, (traj, m) in results.items():
        summary[name] = _metrics.to_dict(m)
        if limits is not None:
            share = _metrics.torque_limit_share(traj.torque, limits)
            summary[name]["torque_limit_share_right"], summary[name]["torque_limit_share_left"] = map(float, share)
        for axis, value in ((stiffness or {}).get(name) or {}).items():
            summary[name][f"apparent_stiffness_{axis}_N_per_m"] = float(value)
        se = all_series[name]
        if not columns:
            columns["time_s"] = se["time_s"].tolist()
            columns["phase"] = se["phase"].astype(int).tolist()
        for k, v in se.items():
            if k not in ("time_s", "phase"):
                columns[f"{name}_{k}"] = v.astype(float).tolist()
        path = os.path.join(out, f"forces_{name}.png")
        plot_forces(se, scenario, f"{name} controller", path, ylim, drop_time(m))
    names = list(results)
    summary["controllers"] = names
    summary["resultant_ratios"] = {}
    for name in names[1:]:
        c, s = summary[names[0]]["settled_peak_resultant_N"], summary[name]["settled_peak_resultant_N"]
        # no ratio of settled peaks when either controller dropped the object: there was no settled grasp
        held = not any(drop_time(summary[n]) is not None for n in (names[0], name))
        summary["resultant_ratios"][name] = (c / s) if held and s and s > 0 else None
    summary["resultant_ratio"] = summary["resultant_ratios"][names[1]]  # the first two's (the paper's pair)
    summary["scenario"] = _scenario.to_dict(scenario)
    summary["gains"] = _schedule.to_file_dict(gains)  # constant gains by name, or {"schedule": ...}
    if model is not None:
        summary["model"] = model  # which model ran: jaxsync.physics.model.identity
    summary["options"] = options
    summary["wall_time_s"] = wall_time_s
    _results.write_csv(os.path.join(out, "series.csv"), columns)
    _results.write_json(os.path.join(out, "summary.json"), summary)
    return summary


def paper_comparison(
    model,
    gains,
    scenario,
    out: str,
    *,
    duration: float = 4.0,
    backend: str = "mjx",
    options: dict | None = None,
    video_speed: float | None = None,
    mujoco_check: int = 0,
    controllers: tuple[str, ...] = PAPER,
    log=lambda msg: print(msg, file=sys.stderr, flush=True),
    stack: Stack = TORQUE,
) -> tuple[dict, list[str]]:
    """``jaxsync compare``'s job: the controllers on ``scenario``, written to ``out``.

    Writes ``summary.json``, ``series.csv`` and each controller's force plot
    (:func:`write_results`); with ``video_speed``, ``compare.mp4`` (or a GIF)
    at that speed; with ``mujoco_check`` = N, ``gains`` and the default gains
    on N of ``jaxsync tune``'s held-out scenarios on MJX and MuJoCo C with
    the last controller (:func:`jaxsync.sim.crosscheck.sim_to_sim`, recorded as
    ``summary["sim_to_sim"]``). Every input is checked before ``out`` is
    created. ``stack``: the arms' actuation, control rate and delay (``jaxsync.sim.actuation.Stack``; the
    scenario carries the delay), which each controller must run on. Returns the summary and the files.
    """
    check_duration(scenario, duration)
    controllers = check_controllers(controllers, stack)
    if video_speed is not None:  # say now, not after the rollouts, when no OpenGL backend can render it
        select_gl_backend()
    _results.ensure_writable_dir(out)
    t0 = time.perf_counter()
    results = run(
        model, gains, scenario, duration=duration, backend=backend, controllers=controllers, log=log, stack=stack
    )
    # a schedule has one stiffness per phase: none recorded
    constant = not isinstance(gains, _schedule.Schedule)
    stiffness = {n: _compliance.stiffness_at_pad(model, n, gains) if constant else None for n in controllers}
    took, extra = time.perf_counter() - t0, {"stiffness": stiffness, "model": identity(model)}
    summary = write_results(out, results, scenario, gains, options or {}, took, limits=torque_limits(model), **extra)
    files = ["summary.json", "series.csv"] + [f"forces_{n}.png" for n in controllers]
    if video_speed is not None:
        files.append(os.path.basename(compare_video(model, results, scenario, out, speed=video_speed, log=log)))
    if mujoco_check:
        # jaxsync tune's held-out scenarios (with the model's object) and evaluation horizon
        cfg = TuneConfig(scenario=_scenarios.model_overrides(model))
        held = _scenarios.heldout_scenarios(cfg)
        held = held._replace(delay=jnp.full_like(held.delay, float(stack.delay[0])))
        summary["sim_to_sim"] = _crosscheck.sim_to_sim(
            model,
            gains,
            default_gains(model, stack.actuation, controllers[-1]),
            held,
            cfg.training.eval_duration,
            n=mujoco_check,
            log=log,
            controller=controllers[-1],
            stack=stack,
        )
        _results.write_json(os.path.join(out, "summary.json"), summary)
    return summary, files


# ------------------------------------------------------ the job from its inputs

SCENARIO_OVERRIDES = ("object_mass", "grip_force", "object_offset", "force_noise")


def comparison_scenario(
    model=None,
    *,
    seed: int = 0,
    object_mass: float | None = None,
    grip_force: float | None = None,
    object_offset: float | None = None,
    force_noise: float | None = None,
):
    """``model``'s task (``default_scenario``) with the values given: the object's
    mass, kg (the controllers' mass estimate follows it), the desired grip force
    f_d, N, where the object starts off the nominal grasp centre along the
    clamping axis, m, the wrist force noise std, N; the sensor noise drawn from ``seed``."""
    overrides = {}
    if object_mass is not None:
        overrides["object_mass"] = object_mass
    if grip_force is not None:
        overrides["grip_force"] = grip_force
    if object_offset is not None:
        overrides["object_offset"] = [0.0, object_offset, 0.0]
    if force_noise is not None:
        overrides["force_noise"] = force_noise
    overrides["noise_key"] = np.asarray(jax.random.key_data(jax.random.key(seed)))
    if "object_mass" in overrides:
        overrides["mass_estimate"] = overrides["object_mass"]
    return _scenario.default_scenario(model, **overrides)


class Comparison(NamedTuple):
    """What :func:`run_comparison` measured and wrote."""

    summary: dict  # summary.json's content
    files: list[str]  # written to the output folder
    stability_ratio: tuple[float, float]  # right, left: (M + B dt + K dt^2) / apparent inertia, normal axis
    notes: list[str]  # about the inputs (gains tuned for a controller that is not compared)
    dropped: dict[str, float]  # controller: when it dropped the object, s
    unstable: list[str]  # controllers whose pad forces chattered in the settled window
    sim_to_sim_agree: bool | None  # the MuJoCo C check's verdict; None without the check


def run_comparison(
    model=None,
    *,
    gains=None,
    any_model: bool = False,
    visual: bool = True,
    overrides: dict | None = None,
    seed: int = 0,
    duration: float = 4.0,
    out: str = "results/compare",
    backend: str = "mjx",
    controllers: tuple[str, ...] = PAPER,
    video_speed: float | None = None,
    mujoco_check: int | None = None,
    options: dict | None = None,
    stack: Stack = TORQUE,
    say=print,
    log=lambda msg: print(msg, file=sys.stderr, flush=True),
) -> Comparison:
    """``jaxsync compare``'s job from what a user names: :func:`paper_comparison`
    on ``model``'s task.

    ``model``: a loaded model, or the MJCF or robot file to load (None: the
    paper model; ``visual`` False leaves a robot's meshes out). ``gains``: a
    gains file (refused when it was tuned on another model, unless
    ``any_model``), gains or a schedule; None: the model's defaults.
    ``overrides``: :func:`comparison_scenario`'s values by name (``seed`` draws
    the sensor noise). ``say`` gets the lines to read before the rollouts:
    each note and the normal-axis stability ratio. ``options``: what
    summary.json records as the run's options (this call's, by default).
    ``stack``: the arms' actuation, control rate and delay (one delay: one
    scenario); summary.json records it under ``stack``, with the servo.
    """
    unknown = sorted(set(overrides or {}) - set(SCENARIO_OVERRIDES))
    if unknown:
        raise ConfigError(f"overrides may set {', '.join(SCENARIO_OVERRIDES)}, not {', '.join(unknown)}")
    model = as_model(model, visual=visual)
    from_file = isinstance(gains, str | os.PathLike)
    delay = stack.scenario_delay()
    own = "ros2_synchronous" if "ros2_synchronous" in controllers else None  # its own relative-error factor
    g = gains_file.load_or_default(gains, model, any_model, stack.actuation, own)
    tuned_for = gains_file.controller_of(gains) if from_file else None
    shared = gains is None and own is not None and "synchronous" in controllers
    notes = [f"synchronous runs {own}'s default gains here (k_rk = -k_lk = {float(g.k_rk):g})"] * shared
    if tuned_for is not None and tuned_for not in controllers:
        notes.append(
            f"{gains} was tuned for the {tuned_for} controller, which is not among the controllers compared "
            f"({', '.join(controllers)})"
        )
    ratio = stability_ratio(g, pad_apparent_inertia(model.mj_model), float(model.mj_model.opt.timestep))
    for note in notes:
        say(f"note: {note}")
    say(
        f"normal-axis stability ratio (M + B dt + K dt^2) / apparent inertia: right {ratio[0]:.2f}, left "
        f"{ratio[1]:.2f} (above 1 stable against a stiff contact; docs/robots.md)"
    )
    scenario = comparison_scenario(model, seed=seed, **(overrides or {}))._replace(delay=jnp.asarray(float(delay)))
    check_duration(scenario, duration)
    if options is None:
        options = {
            "model": model.path,
            "gains": str(gains) if from_file else None,
            "any_model": any_model,
            **{k: (overrides or {}).get(k) for k in SCENARIO_OVERRIDES},
            "seed": seed,
            "duration": duration,
            "out": out,
            "backend": backend,
            "controllers": list(controllers),
            "video_speed": video_speed,
            "mujoco_check": mujoco_check,
        }
    options = {**options, "stack": stack.to_dict(model)}
    summary, files = paper_comparison(
        model,
        g,
        scenario,
        out,
        duration=duration,
        backend=backend,
        options=options,
        video_speed=video_speed,
        mujoco_check=mujoco_check,
        controllers=tuple(controllers),
        log=log,
        stack=stack,
    )
    dropped = {n: t for n in controllers_of(summary) if (t := drop_time(summary[n])) is not None}
    check = summary.get("sim_to_sim")
    return Comparison(
        summary,
        files,
        (float(ratio[0]), float(ratio[1])),
        notes,
        dropped,
        chattering(summary),
        None if check is None else bool(check["agree"]),
    )
