"""The tuner benchmark's figures, on made-up runs (the runs themselves take
minutes each: experiments/tuner_benchmark.py)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxsync.optimize.benchmarks import tuner_benchmark as B


def _run(method, seed, curve, problem="constant", budget=10.0):
    h0 = curve[0][1]
    return {
        "problem": problem,
        "method": method,
        "seed": seed,
        "initial_heldout_cost": h0,
        "budget_s": budget,
        "target_cost": 0.5 * h0,
        "time_to_target_s": B.time_to(curve, 0.5 * h0),
        "best_heldout_cost": min(c for _, c in curve),
        "curve": curve,
        "iterations": len(curve) - 1,
        "gradient_calls": 3 * (len(curve) - 1) if method == "lbfgs" else 0,
        "value_calls": 2 * seed,
    }


RUNS = [
    # seed 0: lbfgs blows up first (40 after iteration 1), then reaches 1.0; cmaes reaches 2.0
    _run("lbfgs", 0, [(0, 10.0), (1, 8.0), (2, 40.0), (6, 1.0), (9, 1.05)]),
    _run("cmaes", 0, [(0, 10.0), (2, 6.0), (5, 4.0), (8, 2.0)]),
    # seed 1: both steady; cmaes the best (3.0), lbfgs within 10 % of it at 7 s
    _run("lbfgs", 1, [(0, 10.0), (1, 9.0), (4, 6.0), (7, 3.2)]),
    _run("cmaes", 1, [(0, 10.0), (3, 5.0), (9, 3.0)]),
]


def test_hard_target_budget_fractions_and_blow_ups_per_run():
    a = {(r["method"], r["seed"]): r for r in B.annotate(RUNS)}
    assert a["lbfgs", 0]["hard_target_cost"] == pytest.approx(1.1) and a["cmaes", 0]["time_to_hard_target_s"] is None
    assert a["lbfgs", 0]["time_to_hard_target_s"] == 6 and a["lbfgs", 1]["time_to_hard_target_s"] == 7
    assert a["lbfgs", 0]["worst_iterate_over_start"] == pytest.approx(4.0)  # 40 after its second iteration
    assert a["lbfgs", 1]["worst_iterate_over_start"] == pytest.approx(0.9)  # its first iterate, 9
    assert a["lbfgs", 0]["cost_at_25pct"] == 40.0  # the incumbent at 2.5 s: the blow-up
    assert a["lbfgs", 0]["cost_at_50pct"] == 40.0 and a["lbfgs", 0]["cost_at_100pct"] == 1.05
    assert a["cmaes", 1]["cost_at_50pct"] == 5.0


def test_summary_medians_spreads_and_counts():
    rows = {r["method"]: r for r in B.summarize(RUNS)}
    lb = rows["lbfgs"]
    assert lb["seeds"] == 2 and lb["seed_list"] == [0, 1] and lb["reached_hard"] == 2
    assert lb["above_start"] == 1 and lb["worst_iterate_over_start_max"] == pytest.approx(4.0)
    assert lb["time_to_hard_target_median_s"] == pytest.approx(6.5)
    assert lb["time_to_target_min_s"] == 6 and lb["time_to_target_max_s"] == 7
    assert lb["iterations_median"] == 3.5 and lb["gradient_calls_median"] == 10.5 and lb["value_calls_median"] == 1
    cm = rows["cmaes"]
    assert cm["reached_hard"] == 1 and not np.isfinite(cm["time_to_hard_target_max_s"])
    text = B.table(B.summarize(RUNS))
    assert "never" in text and "(1/2 > 1)" in text and "lbfgs" in text


def test_the_plot_draws_each_seed(tmp_path, monkeypatch):
    drawn = []
    plt = B._results.pyplot()
    monkeypatch.setattr(B._results, "save_figure", lambda fig, path: drawn.append(fig))
    B.plot(RUNS, str(tmp_path / "p.png"))
    (ax,) = drawn[0].axes
    assert len(ax.lines) == 2 * len(RUNS)  # a curve and the start's line per run
    plt.close("all")
