"""Sensitivities of the headline metrics to every gain, from reverse passes.

At given gains, the derivative of each headline metric (settled peak
resultant, grip-force error, synchronisation error; the smooth forms of
``cost.smooth_metrics``), averaged over a batch of randomised scenarios, with
respect to every entry of the gains pytree. One forward rollout of the batch,
then one reverse pass per metric (``jax.vjp``, its pullback vmapped over the
three metrics). Reported as elasticities: d log metric / d log gain for the
positive gains (impedance and inner-loop gains: the percent change of the
metric per percent change of the gain), and d log metric / d k for the signed
synchronisation factors k_rk, k_lk, k_rl, k_ll (the relative change of the
metric per unit of k).

Example:
  >>> from jaxsync.optimize.studies.sensitivity import sensitivity
  >>> s = sensitivity(jaxsync.load_model(), jaxsync.default_gains(), batch=4)  # doctest: +SKIP
  >>> s.rows()[0]  # doctest: +SKIP
"""

from __future__ import annotations

import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control.names import CONTROLLERS
from jaxsync.io import gains_file
from jaxsync.io import results as _results
from jaxsync.optimize.tuning.cost import smooth_metrics
from jaxsync.optimize.tuning.params import FEED
from jaxsync.optimize.tuning.scenarios import sample_scenarios
from jaxsync.physics.model import as_model, identity
from jaxsync.runtime import programs
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.actuation import TORQUE, Stack
from jaxsync.sim.rollout import make_rollout
from jaxsync.sim.scenario import default_scenario, min_duration, short_task

SMOOTH_PEAK_N = 0.002  # N: the settled peak's log-sum-exp temperature (a slope of the peak's smooth form)
METRICS = ("settled_peak_resultant_N", "grip_force_error_rel", "sync_error_rms_m")
# elasticity per unit k (and per s, s^2 of the command's feed-forward, 0 by default), not per log value
SIGNED = ("k_rk", "k_lk", "k_rl", "k_ll", "ff_vel", "ff_acc")
_AXES = ("x", "y", "z", "rx", "ry", "rz")
_ARMS = ("right", "left")


def entry_names() -> list[str]:
    """One name per scalar entry of the gains pytree, in ``ravel`` order
    (per-arm arrays: ``imp_stiffness[right,z]``)."""
    g = _gains.default_gains()
    names = []
    for field, v in zip(g._fields, g, strict=True):
        shape = np.shape(v)
        if shape == ():
            names.append(field)
        elif shape == (2, 6):
            names += [f"{field}[{a},{x}]" for a in _ARMS for x in _AXES]
        elif shape == (6,):
            names += [f"{field}[{x}]" for x in _AXES]
        else:  # pragma: no cover - a new gains shape
            names += [f"{field}[{i}]" for i in range(int(np.prod(shape)))]
    return names


def metrics_function(
    model, duration: float, start: str | None = None, controller: str = "synchronous", stack: Stack = TORQUE
):
    """``f(gains, scenarios) -> (3,)``: each smooth metric's mean over the batch, on ``stack``."""
    kw = {} if start is None else {"start": start}
    kw.update(stack.rollout_options(model))
    fn = make_rollout(model, controller, duration, remat=True, passes="tree", **kw)

    def one(g, s):
        m = smooth_metrics(fn(g, s), s, SMOOTH_PEAK_N)
        return jnp.stack([m[k] for k in METRICS])

    def f(g, scenarios):
        return jax.vmap(one, in_axes=(None, 0))(g, scenarios).mean(0)

    return f


def derivatives_function(f):
    """jit: ``(gains, scenarios) -> (values (3,), d value_i / d gains (pytree, leading axis 3))``:
    one forward pass and one reverse pass per metric."""

    def run(g, scenarios):
        values, pullback = jax.vjp(lambda g: f(g, scenarios), g)
        (grads,) = jax.vmap(pullback)(jnp.eye(len(METRICS), dtype=values.dtype))
        return values, grads

    return jax.jit(run)


@programs.memoize(maxsize=8)
def program(model, duration: float, start: str | None = None, controller: str = "synchronous", stack: Stack = TORQUE):
    """The jitted derivatives of one configuration, built once per process
    (the command line and the library share it)."""
    return derivatives_function(metrics_function(model, duration, start, controller, stack))


class Sensitivity(NamedTuple):
    """Metric values (3,), gains entries (n,), derivatives and elasticities (3, n)."""

    names: list
    gains: np.ndarray
    values: np.ndarray
    derivative: np.ndarray  # d metric / d gain
    elasticity: np.ndarray  # d log metric / d log gain (d log metric / d k for SIGNED)

    def rows(self) -> list[dict]:
        """One dict per gain entry: its value, then each metric's elasticity and derivative."""
        out = []
        for j, name in enumerate(self.names):
            row = {"gain": name, "value": float(self.gains[j])}
            for i, m in enumerate(METRICS):
                row[f"elasticity_{m}"] = float(self.elasticity[i, j])
                row[f"derivative_{m}"] = float(self.derivative[i, j])
            out.append(row)
        return out


def elasticities(names, gains_flat, values, derivative) -> np.ndarray:
    """d log m / d log g = g / m dm/dg for the positive gains; d log m / d k = 1 / m dm/dk for the signed k's."""
    signed = np.array([n in SIGNED for n in names])
    scale = np.where(signed, 1.0, gains_flat)[None, :]
    return derivative * scale / values[:, None]


def sensitivity(
    model,
    gains,
    scenarios,
    duration: float,
    start: str | None = None,
    controller: str = "synchronous",
    stack: Stack = TORQUE,
) -> Sensitivity:
    """The sensitivities at ``gains`` over a batch of ``scenarios`` (leading
    axis), of the gains ``controller`` reads (``jaxsync.control.gains.USED``)
    and the joint-space law's (on position-controlled arms with jaxsync's
    laws: its feed-forward ff_vel, ff_acc too), on the arms' ``stack``."""

    fn = program(model, float(duration), start, controller, stack)
    values, grads = jax.block_until_ready(fn(gains, scenarios))
    flat, _ = ravel_pytree(gains)
    deriv = np.stack(
        [np.asarray(ravel_pytree(jax.tree_util.tree_map(lambda x, i=i: x[i], grads))[0]) for i in range(3)]
    )
    names = entry_names()
    values, flat = np.asarray(values), np.asarray(flat)
    read = set(_gains.USED[controller]) | {"kp_pos", "kd_pos", "kp_null", "kd_null"}
    if stack.actuation == "position" and controller in CONTROLLERS:  # the command's feed-forward
        read |= set(FEED)
    keep = np.array([n.split("[")[0] in read for n in names])
    names, flat, deriv = [n for n, k in zip(names, keep, strict=True) if k], flat[keep], deriv[:, keep]
    return Sensitivity(names, flat, values, deriv, elasticities(names, flat, values, deriv))


# ----------------------------------------------------------------- report

_LABELS = {
    "settled_peak_resultant_N": "settled peak resultant",
    "grip_force_error_rel": "grip-force error",
    "sync_error_rms_m": "synchronisation error",
}


def table(s: Sensitivity) -> str:
    """The elasticities as a text table, one row per gain entry."""
    head = f"{'gain':<26} {'value':>10}  " + "  ".join(f"{_LABELS[m]:>22}" for m in METRICS)
    lines = [head]
    for j, name in enumerate(s.names):
        cells = "  ".join(f"{s.elasticity[i, j]:>22.4g}" for i in range(len(METRICS)))
        lines.append(f"{name:<26} {s.gains[j]:>10.4g}  {cells}")
    vals = "  ".join(f"{v:>22.4g}" for v in s.values)
    lines.append(f"{'metric (smooth form)':<26} {'':>10}  {vals}")
    return "\n".join(lines)


def plot(s: Sensitivity, path: str, title: str = "") -> None:
    """One panel per metric: a horizontal bar per gain entry (its elasticity)."""
    plt = _results.pyplot()

    n = len(s.names)
    fig, axes = plt.subplots(1, len(METRICS), figsize=(4.2 * len(METRICS), 0.22 * n + 1.6), sharey=True)
    y = np.arange(n)
    signed = np.array([nm in SIGNED for nm in s.names])
    for i, (ax, m) in enumerate(zip(axes, METRICS, strict=True)):
        e = s.elasticity[i]
        ax.barh(y[~signed], e[~signed], color=np.where(e[~signed] >= 0, "C3", "C0"), height=0.7)
        ax.barh(y[signed], e[signed], color="0.4", height=0.7)
        ax.axvline(0, color="k", lw=0.6)
        ax.set_title(f"{_LABELS[m]}\n(value {s.values[i]:.4g})", fontsize=9)
        ax.grid(axis="x", alpha=0.3)
        ax.set_xlabel("elasticity")
    axes[0].set_yticks(y)
    axes[0].set_yticklabels(s.names, fontsize=7)
    axes[0].invert_yaxis()
    fig.suptitle(
        (title + "\n" if title else "")
        + "d log metric / d log gain (red: raising the gain raises the metric); grey: d log metric / d k",
        fontsize=9,
    )
    fig.tight_layout()
    _results.save_figure(fig, path)
    plt.close(fig)


def write_results(
    out: str,
    s: Sensitivity,
    gains,
    *,
    batch: int,
    seed: int,
    duration: float,
    seconds: float,
    scenario=None,
    model: dict | None = None,
    stack: dict | None = None,
) -> list:
    """``sensitivity.csv`` (a row per gain entry), ``sensitivity.json`` (the
    same with the metrics and the run's settings) and ``sensitivity.png``;
    returns the file names."""
    rows = s.rows()
    _results.write_csv(os.path.join(out, "sensitivity.csv"), {k: [r[k] for r in rows] for k in rows[0]})
    _results.write_json(
        os.path.join(out, "sensitivity.json"),
        {
            "metrics": dict(zip(METRICS, s.values.tolist(), strict=True)),
            "rows": rows,
            "elasticity": "d log metric / d log gain; for k_rk, k_lk, k_rl, k_ll: d log metric / d k",
            "metric_forms": "smooth forms of the tuning cost (tuning/cost.py smooth_metrics), mean over scenarios",
            "gains": _gains.to_dict(gains),
            "scenario_base": _scenario.to_dict(scenario) if scenario is not None else None,
            "model": model,
            "stack": stack,
            "batch": batch,
            "seed": seed,
            "duration_s": duration,
            "seconds": seconds,
        },
    )
    plot(s, os.path.join(out, "sensitivity.png"), title=f"{batch} scenarios, {duration:g} s")
    return ["sensitivity.csv", "sensitivity.json", "sensitivity.png"]


def check_duration(base, duration: float, name: str = "duration", task: str = "this task") -> None:
    """ConfigError unless ``duration`` reaches ``base``'s settled window."""
    if duration < min_duration(base):
        raise ConfigError(
            f"{name} must be at least {min_duration(base):g} s for {task} (its settled "
            f"window starts at {min_duration(base) - 0.2:g} s), got {duration:g}",
            inputs=(name,),
        )


def study(
    model,
    gains,
    base,
    *,
    batch: int,
    seed: int,
    duration: float,
    out: str,
    at: str = "the given gains",
    log=print,
    controller: str = "synchronous",
    stack: Stack = TORQUE,
) -> Sensitivity:
    """``jaxsync sensitivity``'s job: the sensitivities of the smooth metrics
    to every gain entry over ``batch`` randomised scenarios around ``base``
    (a :class:`~jaxsync.Scenario`; on a position ``stack`` each draws its
    delay from the stack's range), written to ``out`` (:func:`write_results`)."""
    check_duration(base, duration)
    _results.ensure_writable_dir(out)
    scen = sample_scenarios(jax.random.key(seed), batch, base, delay=stack.delay)
    log(
        f"sensitivities of the {controller} controller at {at}: {batch} randomised scenarios (seed {seed}), "
        f"{duration:g} s; one forward pass and one reverse pass per metric (the first run compiles the "
        "gradient: minutes on a small CPU)"
    )
    t0 = time.perf_counter()
    s = sensitivity(model, gains, scen, duration, controller=controller, stack=stack)
    seconds = time.perf_counter() - t0
    write_results(
        out,
        s,
        gains,
        batch=batch,
        seed=seed,
        duration=duration,
        seconds=seconds,
        scenario=base,
        model=identity(model),
        stack=stack.to_dict(model),
    )
    return s


TASKS = ("full", "short")  # default_scenario, short_task
TASK_DURATION = {"full": 4.0, "short": 2.0}  # s, the default rollout of each


class SensitivityRun(NamedTuple):
    """What :func:`run_sensitivity` computed and wrote."""

    sensitivity: Sensitivity
    files: list[str]  # written to the output folder
    seconds: float  # wall time of the whole job


def run_sensitivity(
    model=None,
    *,
    gains=None,
    any_model: bool = False,
    visual: bool = True,
    task: str = "full",
    duration: float | None = None,
    batch: int = 8,
    seed: int = 0,
    controller: str = "synchronous",
    out: str = "results/sensitivity",
    log=print,
    stack: Stack = TORQUE,
) -> SensitivityRun:
    """``jaxsync sensitivity``'s job from what a user names: :func:`study` on
    ``model``'s full task (``default_scenario``) or its short one (``short_task``).

    ``model``: a loaded model, or the MJCF or robot file to load (None: the
    paper model; ``visual`` False leaves a robot's meshes out). ``gains``: a
    file of constant gains (refused when it was tuned on another model, unless
    ``any_model``) or :class:`~jaxsync.Gains`; None: the model's defaults.
    ``duration``: the rollout, s (None: 4 for the full task, 2 for the short one).
    ``stack``: the arms' stack (a delay range: drawn per scenario); the
    default gains are that stack's. Every input is checked before ``out`` is
    written.
    """
    if task not in TASKS:
        raise ConfigError(f"task must be one of {', '.join(TASKS)}, got {task!r}", inputs=("task",))
    model = as_model(model, visual=visual)
    from_file = isinstance(gains, str | os.PathLike)
    if from_file:
        gains_file.check_model(gains, model, any_model)
        g = gains_file.load_constant(gains, "the sensitivity study")
    else:
        g = gains if gains is not None else _gains.default_gains(model, stack.actuation, controller)
        if not isinstance(g, _gains.Gains):
            raise ConfigError(
                "gains must be constant gains: the sensitivity study takes no schedule", inputs=("gains",)
            )
    base = short_task(model) if task == "short" else default_scenario(model)
    duration = duration if duration is not None else TASK_DURATION[task]
    check_duration(base, duration, "duration", f"the {task} task")
    stack.substeps(model)  # a control rate that divides the physics rate: before any folder
    t0 = time.perf_counter()
    s = study(
        model,
        g,
        base,
        batch=batch,
        seed=seed,
        duration=duration,
        out=out,
        at="the gains of " + str(gains) if from_file else "the default gains" if gains is None else "the given gains",
        log=log,
        controller=controller,
        stack=stack,
    )
    files = ["sensitivity.csv", "sensitivity.json", "sensitivity.png"]
    return SensitivityRun(s, files, time.perf_counter() - t0)
