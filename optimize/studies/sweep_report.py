"""A finished sweep's report: results.csv, the summary's statistics and the plots."""

from __future__ import annotations

import os

import numpy as np

from jaxsync.io import results as _results
from jaxsync.optimize.studies.sweep_plan import Plan
from jaxsync.sim.metrics import BOOL_METRICS

DEFAULT_PLOT_METRICS = ("settled_peak_resultant_N", "grip_force_error_rel")


def _ok(metrics: dict) -> np.ndarray:
    """The points whose metrics mean something: held, finite, not chattering."""
    bad = metrics["dropped"].astype(bool) | metrics["nonfinite"].astype(bool)
    if "chattering" in metrics:
        bad = bad | metrics["chattering"].astype(bool)
    return ~bad


def write_csv(path: str, plan: Plan, metrics: dict) -> None:
    cols: dict[str, list] = {"point": list(range(len(plan.points)))}
    for j, p in enumerate(plan.params):
        col = plan.points[:, j]
        cols[p.name] = [int(v) for v in col] if p.target.integer else [float(v) for v in col]
    for k, v in metrics.items():
        cols[k] = [int(x) for x in v] if k in BOOL_METRICS else [float(x) for x in v]
    ok = _ok(metrics)
    cols["ok"] = [int(x) for x in ok]
    _results.write_csv(path, cols)


def _stats(x: np.ndarray) -> dict | None:
    x = x[np.isfinite(x)]
    if not len(x):
        return None
    return {"min": float(x.min()), "median": float(np.median(x)), "max": float(x.max()), "mean": float(x.mean())}


def summarize_sweep(plan: Plan, metrics: dict) -> dict:
    ok = _ok(metrics)
    out = {
        "n_points": len(plan.points),
        "n_ok": int(ok.sum()),
        "n_dropped": int(metrics["dropped"].astype(bool).sum()),
        "n_nonfinite": int(metrics["nonfinite"].astype(bool).sum()),
        "n_chattering": int(metrics["chattering"].astype(bool).sum()) if "chattering" in metrics else 0,
        "metrics_over_ok_points": {},
        "best_ok_point": {},
    }
    for k, v in metrics.items():
        if k in BOOL_METRICS or k.endswith("_time_s"):
            continue
        out["metrics_over_ok_points"][k] = _stats(v[ok].astype(float))
    for k in DEFAULT_PLOT_METRICS:
        if ok.any():
            i = int(np.flatnonzero(ok)[np.argmin(metrics[k][ok])])
            out["best_ok_point"][k] = {
                "point": i,
                **{p.name: float(plan.points[i, j]) for j, p in enumerate(plan.params) if p.swept},
                k: float(metrics[k][i]),
            }
    return out


NOTHING_TO_PLOT = (
    "every point dropped the object or went non-finite:\nno settled metric to plot (results.csv has them all)"
)


def _nothing_to_plot(ax) -> None:
    """A note in place of an empty plot (every point dropped)."""
    ax.text(0.5, 0.5, NOTHING_TO_PLOT, transform=ax.transAxes, ha="center", va="center", fontsize=9, color="r")


def plot(out: str, plan: Plan, metrics: dict, plot_metrics) -> str | None:
    """heatmap.png (2 swept grid parameters), line.png (1), scatter.png (random samples)."""
    plt = _results.pyplot()

    swept = [j for j, p in enumerate(plan.params) if p.swept]
    if not swept or len(swept) > 2 and plan.samples is not None:
        return None
    ok = _ok(metrics)
    axes_j = swept[:2]
    others = [plan.params[j].name for j in swept[2:]]
    note = f" (mean over {', '.join(others)})" if others else ""
    fig, axs = plt.subplots(1, len(plot_metrics), figsize=(5.2 * len(plot_metrics), 4.2), squeeze=False)
    if plan.samples is not None:
        name = "scatter.png"
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            x = plan.points[:, axes_j[0]]
            if len(axes_j) == 2:
                sc = ax.scatter(x[ok], plan.points[ok, axes_j[1]], c=metrics[k][ok], s=18, cmap="viridis")
                ax.scatter(x[~ok], plan.points[~ok, axes_j[1]], marker="x", c="r", s=18, label="dropped")
                fig.colorbar(sc, ax=ax, label=k)
                ax.set_ylabel(plan.params[axes_j[1]].name)
            else:
                ax.scatter(x[ok], metrics[k][ok], s=12)
                ax.set_ylabel(k)
            ax.set_xlabel(plan.params[axes_j[0]].name)
            ax.set_title(f"{k}, {len(x)} random points")
            if not ok.any():
                _nothing_to_plot(ax)
    elif len(axes_j) == 1:
        name = "line.png"
        j = axes_j[0]
        xs = np.asarray(plan.params[j].values)
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            ys = [
                np.mean(metrics[k][(plan.points[:, j] == v) & ok]) if ((plan.points[:, j] == v) & ok).any() else np.nan
                for v in xs
            ]
            ax.plot(xs, ys, "o-")
            ax.set_xlabel(plan.params[j].name)
            ax.set_ylabel(k)
            gaps = " (gaps: dropped)" if np.isnan(ys).any() else ""
            ax.set_title(f"{k}{note}{gaps}", fontsize=9)
            ax.grid(alpha=0.3)
            if np.isnan(ys).all():
                ax.set_xlim(xs.min() - 0.5 * (np.ptp(xs) or 1), xs.max() + 0.5 * (np.ptp(xs) or 1))
                _nothing_to_plot(ax)
    else:
        name = "heatmap.png"
        ja, jb = axes_j
        va, vb = np.asarray(plan.params[ja].values), np.asarray(plan.params[jb].values)
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            grid = np.full((len(vb), len(va)), np.nan)
            for a, x in enumerate(va):
                for b, y in enumerate(vb):
                    sel = (plan.points[:, ja] == x) & (plan.points[:, jb] == y) & ok
                    if sel.any():
                        grid[b, a] = metrics[k][sel].mean()
            im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
            fig.colorbar(im, ax=ax, label=k)
            step_a, step_b = max(1, len(va) // 11), max(1, len(vb) // 11)
            ax.set_xticks(range(0, len(va), step_a), [f"{v:g}" for v in va[::step_a]], rotation=45)
            ax.set_yticks(range(0, len(vb), step_b), [f"{v:g}" for v in vb[::step_b]])
            ax.set_xlabel(plan.params[ja].name)
            ax.set_ylabel(plan.params[jb].name)
            blank = " (blank: dropped)" if np.isnan(grid).any() else ""
            ax.set_title(f"{k}{note}{blank}", fontsize=9)
            if np.isnan(grid).all():
                _nothing_to_plot(ax)
    fig.suptitle(f"{plan.controller} controller, {plan.duration:g} s rollouts", fontsize=10)
    fig.tight_layout()
    _results.save_figure(fig, os.path.join(out, name))
    plt.close(fig)
    return name
