"""The study's figures: medians and spreads, ratios with bootstrap intervals, the Pareto plot."""

from __future__ import annotations

import os

import numpy as np

from jaxsync.io import results as _results
from jaxsync.optimize.tuning.pipeline import BOUND_MARGIN

FILES = ("report.json", "study.csv", "pareto.png")
# what is reported per controller and bound: per-scenario metrics, then per-gains figures
SCENARIO_METRICS = (
    "settled_peak_resultant_N",
    "internal_force_error_rms_N",
    "grip_force_error_rel",
    "object_error_rms_m",
    "first_impact_peak_N",
)
GAINS_METRICS = ("apparent_stiffness_normal_N_per_m", "apparent_stiffness_tangential_N_per_m")
LABELS = {
    "settled_peak_resultant_N": "settled peak resultant, N",
    "internal_force_error_rms_N": "internal-force error (RMS), N",
    "grip_force_error_rel": "grip error",
    "object_error_rms_m": "tracking error (object, RMS), m",
    "first_impact_peak_N": "first-impact peak, N",
    "apparent_stiffness_normal_N_per_m": "apparent stiffness, normal, N/m",
    "apparent_stiffness_tangential_N_per_m": "apparent stiffness, tangential, N/m",
}
RATIO_SEED = 0


BOUND_RULE = (
    f"in bounds: the selected iterate's mean first-impact peak on the validation scenarios (the batch that "
    f"defines the bound) and its apparent normal stiffness, each at most the bound x (1 + {BOUND_MARGIN:g})"
)


def run_within_bounds(run: dict) -> bool:
    """Whether a tuning run (its ``summary.json``) ended within its bound, judged
    as the bound is defined: the selected iterate's figures on the validation
    scenarios (the reference's first-impact peak is their mean) against the
    bound x (1 + ``BOUND_MARGIN``); a run without validation by its held-out
    figures."""
    selected = run.get("selected_iteration")
    for v in run.get("validation") or []:
        if v.get("iteration") == selected:
            if v.get("bound_excess") is not None:
                return v["bound_excess"] <= BOUND_MARGIN
            return bool(v.get("within_bounds", True))
    return bool(run["heldout_after"].get("within_bounds", True))


def run_converged(run: dict) -> bool:
    """Whether a tuning run (its ``summary.json``) converged by the tuner's
    criterion (``optimize.tuning.tune_state.convergence_record``); a run that
    does not say, did not."""
    return bool((run.get("convergence") or {}).get("converged", False))


def run_iterations(run: dict) -> int:
    """The iterations a tuning run took."""
    return int((run.get("convergence") or {}).get("iterations", run.get("iterations", 0)))


def verdict(ratio: dict, converged: dict) -> str:
    """What a ratio's interval says, drawn only from converged runs:
    'lower' or 'higher' (the interval excludes 1), 'no difference', or why
    there is none ('not converged: ...', 'n/a')."""
    short = {name: kn for name, kn in converged.items() if kn[0] < kn[1]}
    if short:
        return "none: runs not converged (" + ", ".join(f"{n} {k}/{m}" for n, (k, m) in short.items()) + ")"
    lo, hi = ratio["ci95"]
    if ratio["ratio"] is None or lo is None:
        return "n/a"
    return "lower" if hi < 1 else "higher" if lo > 1 else "no difference"


def reference_controller(controllers) -> str:
    """What the ratios divide by: the synchronous controller when in the study, else the first."""
    return "synchronous" if "synchronous" in controllers else controllers[0]


def _arrays(evaluations: list[dict]) -> dict:
    """(seeds, scenarios) arrays of each scenario metric, NaN where the object
    was dropped or the rollout diverged; per-gains figures (seeds,)."""
    out = {}
    lost = np.array([np.asarray(e["metrics"]["dropped"]) | np.asarray(e["metrics"]["nonfinite"]) for e in evaluations])
    for k in SCENARIO_METRICS:
        v = np.array([[np.nan if x is None else x for x in e["metrics"][k]] for e in evaluations], dtype=float)
        if k != "first_impact_peak_N":  # the first impact precedes any drop
            v[lost] = np.nan
        out[k] = v
    for k in GAINS_METRICS:
        out[k] = np.array([e.get(k, np.nan) for e in evaluations], dtype=float)
    out["dropped"] = lost
    out["chattering"] = np.array([np.asarray(e["metrics"]["chattering"]) for e in evaluations])
    return out


def _stats(v: np.ndarray) -> dict:
    v = v[np.isfinite(v)]
    if not v.size:
        return {"median": None, "q25": None, "q75": None, "n": 0}
    q25, med, q75 = np.percentile(v, [25, 50, 75])
    return {"median": float(med), "q25": float(q25), "q75": float(q75), "n": int(v.size)}


def summarise(evaluations: list[dict], bounded: list[bool] | None = None) -> dict:
    """Median and quartiles of each metric over every seed's held-out scenarios."""
    a = _arrays(evaluations)
    row = {k: _stats(a[k].ravel()) for k in SCENARIO_METRICS + GAINS_METRICS}
    row["scenarios"] = int(a["dropped"].size)
    row["dropped"] = int(a["dropped"].sum())
    row["chattering"] = int(a["chattering"].sum())
    if bounded is not None:
        row["within_bounds"] = int(sum(bounded))
        row["runs"] = len(bounded)
    return row


def ratio_interval(num: np.ndarray, den: np.ndarray, n: int, seed: int = RATIO_SEED) -> dict:
    """median(num) / median(den) of two (seeds, scenarios) arrays (NaN: not
    held) with a bootstrap 95 % interval: seeds and scenarios resampled with
    replacement, paired (the same training seed and held-out scenario for
    both), ``n`` times."""

    def ratio(a, b):
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        if not a.size or not b.size or np.median(b) <= 0:
            return np.nan
        return float(np.median(a) / np.median(b))

    point = ratio(num, den)
    rng = np.random.default_rng(seed)
    seeds, scen = num.shape
    draws = []
    for _ in range(n):
        i = rng.integers(0, seeds, seeds)[:, None]
        j = rng.integers(0, scen, scen)[None, :]
        draws.append(ratio(num[i, j], den[i, j]))
    draws = np.asarray(draws)
    draws = draws[np.isfinite(draws)]
    lo, hi = np.percentile(draws, [2.5, 97.5]) if draws.size else (np.nan, np.nan)
    clean = lambda x: None if not np.isfinite(x) else float(x)  # noqa: E731
    return {"ratio": clean(point), "ci95": [clean(lo), clean(hi)], "resamples": int(draws.size)}


def build(cfg, reference: dict, defaults: dict, runs: dict) -> dict:
    """The report: per controller at default gains and at each bound, and the
    ratios against the reference controller (settled peak resultant)."""
    ref = reference_controller(cfg.controllers)
    report = {"config": cfg.describe(), "compliance_reference": reference, "ratio_reference": ref, "rows": []}
    report["bound_rule"] = BOUND_RULE
    peaks = {}
    for c in cfg.controllers:
        row = {"controller": c, "bound": None, **summarise([defaults[c]])}
        report["rows"].append(row)
        peaks[(c, None)] = _arrays([defaults[c]])["settled_peak_resultant_N"]
    # a bound is reported once every controller's every seed is done there
    bounds = [b for b in cfg.bounds if all((c, b, s) in runs for c in cfg.controllers for s in cfg.seeds)]
    report["bounds_reported"] = bounds
    report["runs_done"] = len(runs)
    report["runs"] = len(cfg.controllers) * len(cfg.bounds) * len(cfg.seeds)
    for b in bounds:
        for c in cfg.controllers:
            done = [runs[(c, b, s)] for s in cfg.seeds]
            evals = [r["heldout_after"] for r in done]
            row = {"controller": c, "bound": b, **summarise(evals, [run_within_bounds(r) for r in done])}
            row["converged"] = int(sum(run_converged(r) for r in done))
            deployed = [r.get("deployment") for r in done]  # position stack: whether jaxsync export writes them
            row["exports"] = None if None in deployed else int(sum(d["exports"] for d in deployed))
            row["iterations"] = [run_iterations(r) for r in done]
            row["bounds"] = done[0].get("bounds")
            report["rows"].append(row)
            peaks[(c, b)] = _arrays(evals)["settled_peak_resultant_N"]
    report["ratios"] = []
    for b in (None, *bounds):
        for c in cfg.controllers:
            if c == ref:
                continue
            r = ratio_interval(peaks[(c, b)], peaks[(ref, b)], cfg.bootstrap)
            entry = {"controller": c, "over": ref, "bound": b, **r}
            if b is not None:  # how many of each side's runs ended within the bound
                rows = {x["controller"]: x for x in report["rows"] if x["bound"] == b}
                entry["within_bounds"] = {n: [rows[n]["within_bounds"], rows[n]["runs"]] for n in (c, ref)}
                entry["converged"] = {n: [rows[n]["converged"], rows[n]["runs"]] for n in (c, ref)}
                entry["verdict"] = verdict(entry, entry["converged"])
            report["ratios"].append(entry)
    return report


def _fmt(s: dict, fmt: str = ".4g") -> str:
    if s["median"] is None:
        return "n/a"
    return f"{s['median']:{fmt}} [{s['q25']:{fmt}}, {s['q75']:{fmt}}]"


def table(report: dict) -> list[str]:
    """The lines ``jaxsync study`` prints: a row per controller and bound, then the ratios."""
    lines = [
        "median [quartiles] over the training seeds' held-out scenarios; bound: x the default classical "
        "controller's first-impact peak and apparent normal stiffness ('default': untuned); " + BOUND_RULE
    ]
    head = f"{'controller':<18}{'bound':>8}{'settled peak, N':>30}{'internal err, N':>28}{'impact, N':>26}"
    head += f"{'stiffness, N/m':>16}{'dropped':>10}{'chattering':>12}{'in bounds':>11}{'converged':>11}{'exports':>9}"
    lines.append(head)
    for r in report["rows"]:
        bound = "default" if r["bound"] is None else f"x{r['bound']:g}"
        inb = f"{r['within_bounds']}/{r['runs']}" if "runs" in r else "-"
        conv = f"{r['converged']}/{r['runs']}" if "converged" in r else "-"
        exports = f"{r['exports']}/{r['runs']}" if r.get("exports") is not None else "-"
        stiff = r["apparent_stiffness_normal_N_per_m"]["median"]
        stiff = f"{stiff:.4g}" if stiff is not None else "n/a"
        dropped = f"{r['dropped']}/{r['scenarios']}"
        chattering = f"{r['chattering']}/{r['scenarios']}"
        lines.append(
            f"{r['controller']:<18}{bound:>8}{_fmt(r['settled_peak_resultant_N']):>30}"
            f"{_fmt(r['internal_force_error_rms_N']):>28}{_fmt(r['first_impact_peak_N']):>26}"
            f"{stiff:>16}{dropped:>10}{chattering:>12}{inb:>11}{conv:>11}{exports:>9}"
        )
    for q in report["ratios"]:
        bound = "default gains" if q["bound"] is None else f"bound x{q['bound']:g}"
        if q["ratio"] is None:
            lines.append(f"settled peak {q['controller']} / {q['over']} ({bound}): n/a")
            continue
        lo, hi = q["ci95"]
        ci = f"[{lo:.3g}, {hi:.3g}]" if lo is not None else "[n/a]"
        note = ""
        within = q.get("within_bounds")
        if within and any(k < n for k, n in within.values()):
            note = "; runs within the bound: " + ", ".join(f"{name} {k}/{n}" for name, (k, n) in within.items())
        if "verdict" in q:
            note += f"; verdict: {q['verdict']}"
        lines.append(f"settled peak {q['controller']} / {q['over']} ({bound}): {q['ratio']:.3g} (95 % CI {ci}){note}")
    return lines


def write(out: str, report: dict) -> None:
    """report.json, study.csv (a row per controller and bound) and pareto.png."""
    _results.write_json(os.path.join(out, "report.json"), report)
    cols: dict = {"controller": [], "bound": []}
    for r in report["rows"]:
        cols["controller"].append(r["controller"])
        cols["bound"].append("default" if r["bound"] is None else r["bound"])
        for k in SCENARIO_METRICS + GAINS_METRICS:
            for stat in ("median", "q25", "q75"):
                cols.setdefault(f"{k}_{stat}", []).append(r[k][stat])
        for k in ("dropped", "chattering", "scenarios"):
            cols.setdefault(k, []).append(r[k])
        cols.setdefault("within_bounds", []).append(r.get("within_bounds"))
        cols.setdefault("converged", []).append(r.get("converged"))
        cols.setdefault("exports", []).append(r.get("exports"))
    _results.write_csv(os.path.join(out, "study.csv"), cols)
    pareto_plot(report, os.path.join(out, "pareto.png"))


def bound_labels(rows: list[dict], xkey: str, rtol: float = 0.01) -> list[tuple[tuple[float, float], str]]:
    """Each tuned point's label on the plot against ``xkey``: its bound
    ("x1.5"), one label for a controller's bounds whose points coincide
    within ``rtol`` (runs that ended within the tighter bound: "x1, x1.5")."""
    out: list[tuple[tuple[float, float], list[str], str]] = []
    for r in rows:
        y, x = r["settled_peak_resultant_N"]["median"], r[xkey]["median"]
        if r["bound"] is None or y is None or x is None:
            continue
        for (px, py), names, controller in out:
            if controller == r["controller"] and abs(px - x) <= rtol * abs(px) and abs(py - y) <= rtol * abs(py):
                names.append(f"x{r['bound']:g}")
                break
        else:
            out.append(((x, y), [f"x{r['bound']:g}"], r["controller"]))
    return [(point, ", ".join(names)) for point, names, _ in out]


def pareto_plot(report: dict, path: str) -> None:
    """Settled peak resultant (median, quartiles as bars) against the apparent
    normal stiffness and the first-impact peak: one colour per controller,
    hollow at default gains, larger markers for looser bounds."""
    plt = _results.pyplot()
    from matplotlib import ticker  # here: matplotlib loads through jaxsync.io.results.pyplot (its backend set)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    names = list(dict.fromkeys(r["controller"] for r in report["rows"]))
    colours = {n: f"C{i}" for i, n in enumerate(names)}
    bounds = sorted({r["bound"] for r in report["rows"] if r["bound"] is not None})
    for ax, xkey in zip(axes, ("apparent_stiffness_normal_N_per_m", "first_impact_peak_N"), strict=True):
        for r in report["rows"]:
            y, x = r["settled_peak_resultant_N"], r[xkey]
            if y["median"] is None or x["median"] is None:
                continue
            size = 40 if r["bound"] is None else 30 + 50 * bounds.index(r["bound"])
            face = "none" if r["bound"] is None else colours[r["controller"]]
            yerr = [[y["median"] - y["q25"]], [y["q75"] - y["median"]]]
            ax.errorbar(x["median"], y["median"], yerr=yerr, fmt="none", ecolor=colours[r["controller"]], alpha=0.5)
            ax.scatter(x["median"], y["median"], s=size, facecolors=face, edgecolors=colours[r["controller"]])
        for (x, y), text in bound_labels(report["rows"], xkey):
            ax.annotate(text, (x, y), fontsize=7, xytext=(4, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # plain numbers at 1, 2, 5 per decade (a range under a decade stays legible)
            axis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(ticker.NullFormatter())
        ax.set_xlabel(LABELS[xkey])
        ax.grid(True, which="both", alpha=0.3)
    ref = report["compliance_reference"]
    axes[0].axvline(ref["apparent_stiffness_normal_N_per_m"], color="0.5", ls=":", lw=1)
    axes[1].axvline(ref["first_impact_peak_N"], color="0.5", ls=":", lw=1)
    axes[0].set_ylabel(LABELS["settled_peak_resultant_N"])
    for n in names:
        axes[1].scatter([], [], color=colours[n], label=n)
    axes[1].scatter([], [], facecolors="none", edgecolors="k", label="default gains")
    axes[1].legend(fontsize=8, loc="best")
    fig.suptitle("each controller tuned under each compliance bound (dotted: the default classical controller)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
