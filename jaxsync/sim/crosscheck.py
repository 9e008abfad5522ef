"""The MuJoCo C cross-check: the same gains, scenarios and jitted control law on MJX
and on MuJoCo C, and whether the improvement factors they give agree."""

from __future__ import annotations

import sys
import time

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.rollout import rollout

# the largest relative difference between the improvement factors on MuJoCo C and on MJX
# that passes; beyond it, or when a rollout dropped the object, the check is flagged
SIM_TOLERANCE = 0.10
BACKENDS = {"mjx": "MJX", "mujoco": "MuJoCo C"}


def sim_to_sim(
    model,
    gains,
    baseline,
    scenarios,
    duration: float,
    *,
    n: int = 4,
    tolerance: float = SIM_TOLERANCE,
    log=lambda msg: print(msg, file=sys.stderr, flush=True),
    mjx_rows: dict | None = None,
    controller: str = "synchronous",
    stack=None,
) -> dict:
    """``gains`` against ``baseline`` (e.g. tuned against default gains) on MJX and on
    MuJoCo C, with the same jitted control law of ``controller`` (``rollout(backend=...)``),
    on the first ``n`` of ``scenarios`` (a batched :class:`~jaxsync.Scenario`, e.g.
    ``jaxsync.optimize.tuning.scenarios.heldout_scenarios``), one rollout at a time.

    The improvement factor on each engine is mean settled peak resultant of
    ``baseline`` / that of ``gains`` over the scenarios where no rollout dropped the
    object. ``agree`` is False, and ``problems`` says why, when the factor on MuJoCo C
    differs from MJX's by more than ``tolerance`` (relative), or when a rollout dropped
    the object or went non-finite. The dict keeps the keys of ``jaxsync tune``'s check
    (``mjx_before_N``: ``baseline`` on MJX, ``mujoco_after_N``: ``gains`` on MuJoCo C,
    ``factor_mjx``, ``factor_mujoco``, ``agree``, ``tolerance``, ``scenarios``) and adds
    the grip force errors and each scenario's values.

    ``mjx_rows`` (``{"before": rows, "after": rows}``, either or both; rows as
    :func:`metric_rows` makes them) are MJX's metrics of the same scenarios and
    duration that the caller already has (``jaxsync tune``'s held-out scoring):
    those rollouts are not run again. ``stack``: the
    :class:`~jaxsync.sim.actuation.Stack` both engines run (None: torque).

    Example:
      >>> from jaxsync.optimize.tuning import scenarios, tune
      >>> held = scenarios.heldout_scenarios(tune.TuneConfig())
      >>> c = sim_to_sim(model, tuned, jaxsync.default_gains(), held, 4.0)  # doctest: +SKIP
      >>> c["factor_mjx"], c["factor_mujoco"], c["agree"]  # doctest: +SKIP
      (9.88, 9.18, True)
    """
    count = int(jax.tree_util.tree_leaves(scenarios)[0].shape[0])
    n = min(int(n), count)
    if n < 1:
        raise ConfigError("the sim-to-sim check needs at least one scenario")
    per: dict = {}
    given = mjx_rows or {}
    stack_options = {} if stack is None else stack.rollout_options(model)
    for backend in BACKENDS:
        for which, g in (("before", baseline), ("after", gains)):
            if backend == "mjx" and len(given.get(which) or []) >= n:
                per[f"{backend}_{which}"] = list(given[which][:n])
                continue
            rows = []
            t0 = time.perf_counter()
            for i in range(n):
                s = jax.tree_util.tree_map(lambda x, i=i: x[i], scenarios)
                m = _metrics.summarize(
                    jax.block_until_ready(
                        rollout(model, g, s, controller=controller, duration=duration, backend=backend, **stack_options)
                    ),
                    s,
                )
                rows.append(
                    {
                        "settled_peak_resultant_N": float(m.settled_peak_resultant_N),
                        "grip_force_error_rel": float(m.grip_force_error_rel),
                        "lost": bool(m.dropped) or bool(m.nonfinite),
                    }
                )
            name = "the baseline gains" if which == "before" else "the gains"
            log(f"sim-to-sim: {name} on {BACKENDS[backend]}, {n} scenarios, {time.perf_counter() - t0:.1f} s")
            per[f"{backend}_{which}"] = rows
    return sim_to_sim_verdict(per, n, duration, tolerance)


def metric_rows(m) -> list[dict]:
    """A batch of metrics as :func:`sim_to_sim`'s per-scenario rows."""
    a = _metrics.to_arrays(m)
    lost = np.asarray(a["dropped"]) | np.asarray(a["nonfinite"])
    return [
        {
            "settled_peak_resultant_N": float(a["settled_peak_resultant_N"][i]),
            "grip_force_error_rel": float(a["grip_force_error_rel"][i]),
            "lost": bool(lost[i]),
        }
        for i in range(len(lost))
    ]


def sim_to_sim_verdict(per: dict, n: int, duration: float, tolerance: float = SIM_TOLERANCE) -> dict:
    """:func:`sim_to_sim`'s result from its rollouts' metrics: ``per[f"{backend}_{before|after}"]``
    a list of ``{"settled_peak_resultant_N", "grip_force_error_rel", "lost"}`` per scenario."""
    lost = [i for i in range(n) if any(rows[i]["lost"] for rows in per.values())]
    kept = [i for i in range(n) if i not in lost]
    out: dict = {"scenarios": n, "duration_s": float(duration), "tolerance": float(tolerance), "scenarios_lost": lost}
    problems = []
    if lost:
        problems.append(f"the object was dropped (or the rollout went non-finite) in scenario(s) {lost}")
    for key, rows in per.items():
        out[f"{key}_N"] = float(np.mean([rows[i]["settled_peak_resultant_N"] for i in kept])) if kept else None
        grip = [rows[i]["grip_force_error_rel"] for i in kept]
        out[f"{key}_grip_force_error_rel"] = float(np.mean(grip)) if kept else None
    for backend in BACKENDS:
        before, after = out[f"{backend}_before_N"], out[f"{backend}_after_N"]
        ok = before is not None and after is not None and after > 0 and np.isfinite(before / after)
        out[f"factor_{backend}"] = before / after if ok else None
    f_mjx, f_c = out["factor_mjx"], out["factor_mujoco"]
    out["difference"] = f_c / f_mjx - 1.0 if f_mjx and f_c else None
    if out["difference"] is None:
        problems.append("no improvement factor on both engines")
    elif abs(out["difference"]) > tolerance:
        problems.append(
            f"the improvement factor on MuJoCo C ({f_c:.2f}x) is {100 * abs(out['difference']):.0f} % "
            f"{'below' if out['difference'] < 0 else 'above'} MJX's ({f_mjx:.2f}x), over the "
            f"{100 * tolerance:.0f} % tolerance"
        )
    out["agree"] = not problems
    out["problems"] = problems
    out["per_scenario"] = per
    return out


def sim_to_sim_table(check: dict, gains_name: str = "these gains", baseline_name: str = "default") -> list[str]:
    """The lines ``jaxsync compare --mujoco-check`` prints: both engines side by side, the
    improvement factors, and the verdict (a ``WARNING`` line when they disagree)."""
    w = 14

    def cell(v, fmt):
        return f"{'n/a' if v is None else format(v, fmt):>{w}}"

    n = check["scenarios"]
    lines = [
        f"sim-to-sim: {gains_name} against the {baseline_name} gains on {n} held-out scenario{'s' * (n != 1)} "
        f"({check['duration_s']:g} s), the same jitted control law on both engines",
        f"{'':40}" + "".join(f"{b:>{w}}" for b in BACKENDS.values()),
    ]
    rows = [
        (f"settled peak resultant, {baseline_name} [N]", "before_N", ".5f"),
        (f"settled peak resultant, {gains_name} [N]", "after_N", ".5f"),
        (f"grip force error, {baseline_name}", "before_grip_force_error_rel", ".2%"),
        (f"grip force error, {gains_name}", "after_grip_force_error_rel", ".2%"),
    ]
    for label, key, fmt in rows:
        lines.append(f"{label:<40}" + "".join(cell(check[f"{b}_{key}"], fmt) for b in BACKENDS))
    factors = [None if check[f"factor_{b}"] is None else f"{check[f'factor_{b}']:.2f}x" for b in BACKENDS]
    lines.append(f"{'improvement factor (lower peak)':<40}" + "".join(cell(f, "") for f in factors))
    tol = f"{100 * check['tolerance']:.0f} %"
    if check["agree"]:
        d = check["difference"]
        lines.append(
            f"sim-to-sim: the improvement factors agree within {tol} "
            f"(MuJoCo C {100 * abs(d):.1f} % {'below' if d < 0 else 'above'} MJX)"
        )
    else:
        lines.append(f"WARNING: sim-to-sim check failed: {'; '.join(check['problems'])} (docs/export.md)")
    return lines
