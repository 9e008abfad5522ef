"""The paper's comparison (section 5): classical vs synchronous on one scenario."""

from __future__ import annotations

import os
import sys
import time

import jax
import numpy as np

from jaxsync import _io, _metrics, _scenario, _schedule
from jaxsync._cache import compile_watch
from jaxsync._controller import CONTROLLERS
from jaxsync._errors import ConfigError
from jaxsync._rollout import rollout
from jaxsync._scenario import min_duration

SUMMARY_KEYS = (
    "settled_peak_resultant_N",
    "mean_grip_force_N",
    "grip_force_error_rel",
    "sync_error_rms_m",
    "dropped",
)


def check_duration(scenario, duration: float) -> None:
    """The rollout must reach the end of the settling time, where the settled window starts."""
    if duration < min_duration(scenario):
        raise ConfigError(
            f"--duration must be at least {min_duration(scenario):.2f} s for this scenario "
            f"(the hold phase starts at {float(sum(_scenario.phase_times(scenario)[2:])):.2f} s "
            f"and is measured after a {float(scenario.settle_time):.2f} s settling time), got {duration}"
        )


def run(
    model,
    gains,
    scenario,
    *,
    duration: float,
    backend: str = "mjx",
    log=lambda msg: print(msg, file=sys.stderr, flush=True),
):
    """Roll out both controllers; return ``{name: (trajectory, metrics)}``."""
    check_duration(scenario, duration)
    results = {}
    for i, name in enumerate(CONTROLLERS):
        compiles = " (compiled first, unless the compilation cache holds it)" if backend == "mjx" else ""
        log(f"[{i + 1}/2] {name}: rolling out {duration:g} s on {backend}{compiles}...")
        t0 = time.perf_counter()
        with compile_watch() as watch:
            traj = jax.block_until_ready(
                rollout(model, gains, scenario, controller=name, duration=duration, backend=backend)
            )
            m = _metrics.summarize(traj, scenario)
        log(f"[{i + 1}/2] {name}: done in {time.perf_counter() - t0:.1f} s{watch.describe()}, {outcome(m)}")
        results[name] = (traj, m)
    return results


def drop_time(m) -> float | None:
    """When the object was lost (s), None if it was held; ``m`` Metrics or their to_dict()."""
    get = m.get if isinstance(m, dict) else lambda k: getattr(m, k)
    if not bool(np.asarray(get("dropped"))):
        return None
    t = get("drop_time_s")
    return float(np.asarray(t)) if t is not None else float("nan")


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


def table(summary: dict) -> list[str]:
    """The lines jaxsync compare prints: the summary's metrics per controller
    (a dropped controller's settled metrics as 'dropped at t=... s') and the
    resultant ratio (n/a when either dropped the object)."""
    w = 22
    lines = [f"{'':28}" + "".join(f"{name:>{w}}" for name in CONTROLLERS)]
    for k in SUMMARY_KEYS:
        cells = []
        for name in CONTROLLERS:
            v, t = summary[name][k], drop_time(summary[name])
            if t is not None and k in SETTLED_KEYS:
                cells.append(f"{f'dropped at t={t:.2f} s':>{w}}")
            elif isinstance(v, bool) or v is None:
                cells.append(f"{str(v):>{w}}")
            else:
                cells.append(f"{v:>{w}.5g}")
        lines.append(f"{k:<28}" + "".join(cells))
    ratio = summary["resultant_ratio"]
    dropped = [n for n in CONTROLLERS if drop_time(summary[n]) is not None]
    if dropped:
        who = "both controllers" if len(dropped) == len(CONTROLLERS) else f"the {dropped[0]} controller"
        lines.append(f"resultant_ratio: n/a ({who} dropped the object)")
    else:
        lines.append(f"resultant_ratio (classical / synchronous): {ratio:.3f}" if ratio else "resultant_ratio: n/a")
    return lines


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    _io.save_figure(fig, path)
    plt.close(fig)


def write_results(out: str, results: dict, scenario, gains, options: dict, wall_time_s: float) -> dict:
    """summary.json, series.csv and the two force plots; returns the summary."""
    _io.ensure_writable_dir(out)
    summary: dict = {}
    columns: dict = {}
    all_series = {
        name: {k: np.asarray(v) for k, v in _metrics.series(traj, scenario).items()}
        for name, (traj, _) in results.items()
    }
    # one resultant scale for both plots, so they can be compared by eye (a drop's peak is no scale)
    held = [float(np.asarray(m.settled_peak_resultant_N)) for _, m in results.values() if drop_time(m) is None]
    ylim = 1.5 * max(held) if held and max(held) > 0 else None
    for name, (_, m) in results.items():
        summary[name] = _metrics.to_dict(m)
        se = all_series[name]
        if not columns:
            columns["time_s"] = se["time_s"].tolist()
            columns["phase"] = se["phase"].astype(int).tolist()
        for k, v in se.items():
            if k not in ("time_s", "phase"):
                columns[f"{name}_{k}"] = v.astype(float).tolist()
        path = os.path.join(out, f"forces_{name}.png")
        plot_forces(se, scenario, f"{name} controller", path, ylim, drop_time(m))
    c, s = summary["classical"]["settled_peak_resultant_N"], summary["synchronous"]["settled_peak_resultant_N"]
    # no ratio of settled peaks when either controller dropped the object: there was no settled grasp
    held = not any(drop_time(summary[name]) is not None for name in results)
    summary["resultant_ratio"] = (c / s) if held and s and s > 0 else None
    summary["scenario"] = {k: np.asarray(v).tolist() for k, v in scenario._asdict().items()}
    summary["gains"] = _schedule.to_file_dict(gains)  # constant gains by name, or {"schedule": ...}
    summary["options"] = options
    summary["wall_time_s"] = wall_time_s
    _io.write_csv(os.path.join(out, "series.csv"), columns)
    _io.write_json(os.path.join(out, "summary.json"), summary)
    return summary
