"""Tuners measured against each other on the same rollouts.

Every method (``optimize.methods``) gets the same parameters, the same fixed
training batch (per seed), the same held-out scenarios and the same
wall-clock budget of optimisation (L-BFGS, once converged on the batch, goes
on with the seed's fresh batches, as in ``jaxsync tune``; it stops when it
has converged on its last); compiling and held-out scoring are not
counted (they are reported). After every iteration the method's incumbent is
scored on the held-out scenarios; a run's *time to target* is the first
optimisation time at which that held-out cost is at or below the target (a
fraction of the held-out cost of the starting gains).

Two problems on the same programs:

- ``constant``: the 22 parameters of ``jaxsync tune`` (TuneSpec()): k_rk,
  k_lk, k_rl, k_ll and per-axis impedance mass, stiffness and damping ratio
  shared by the arms;
- ``schedule``: those per arm and per task phase (TuneSpec(per_arm=True,
  schedule=True)): 160 parameters.

The constant problem is the schedule problem with its parameters tied (every
phase and both arms equal): one linear map ``x160 = T x22`` and its transpose
for the gradient, so both problems run on one set of compiled programs
(value and gradient on the training batch, the value alone on it (L-BFGS's
backtracking trials), the population's values, the held-out value).
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxsync.control import gains as _gains
from jaxsync.io import results as _results
from jaxsync.optimize.tuning import methods as _methods
from jaxsync.optimize.tuning.config import Problem, TuneConfig
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.loss import make_loss
from jaxsync.optimize.tuning.params import TuneSpec
from jaxsync.optimize.tuning.scenarios import sample_scenarios
from jaxsync.sim import scenario as _scenario

PROBLEMS = {
    "constant": TuneSpec(),
    "schedule": TuneSpec(per_arm=True, schedule=True),
}


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    budget_s: float = 60.0  # optimisation wall time per run
    batch: int = 4  # training scenarios (fixed per seed), as jaxsync tune
    heldout_batch: int = 8
    heldout_seed: int = 10_000
    popsize: int = 16  # CMA-ES population: popsize x batch rollouts per generation
    target: float = 0.5  # target held-out cost = this x the starting gains' held-out cost
    task: str = "short"  # the training and held-out task ("short": 2 s; "full": 4 s)
    max_iterations: int = 10_000
    stratified: bool = True  # the fixed training batch holds the ranges' ends (sample_scenarios), as jaxsync tune's


class Programs:
    """The compiled programs both problems share, and the two problems' oracles."""

    def __init__(self, model, cfg: BenchConfig, base=None, weights: CostWeights | None = None):
        self.cfg = cfg
        base = base if base is not None else _gains.default_gains()
        self.spec = PROBLEMS["schedule"]
        problem = Problem(spec=self.spec, weights=weights or CostWeights())
        tcfg = TuneConfig(problem=problem, batch=cfg.batch, task=cfg.task, truncate_every=None)
        loss = make_loss(model, base, tcfg)  # differentiated: jaxsync's tree passes
        forward = make_loss(model, base, tcfg, differentiated=False)  # MJX's passes
        theta0 = self.spec.init(base)
        self.x0, unravel = ravel_pytree(theta0)
        self.x0 = np.asarray(self.x0)
        f = lambda x, s: loss(unravel(x), s)[0]  # noqa: E731
        f_forward = lambda x, s: forward(unravel(x), s)[0]  # noqa: E731
        self.value_and_grad = jax.jit(jax.value_and_grad(f))
        self.values = jax.jit(jax.vmap(f_forward, in_axes=(0, None)))
        self.value = jax.jit(f_forward)
        self.base_scenario = _scenario.short_task() if cfg.task == "short" else _scenario.default_scenario()
        self.heldout = sample_scenarios(jax.random.key(cfg.heldout_seed), cfg.heldout_batch, self.base_scenario)
        # the tie map of the constant problem: x160 = T @ x22
        spec22 = PROBLEMS["constant"]
        th22 = spec22.init(base)
        x22, unravel22 = ravel_pytree(th22)
        shapes = jax.tree_util.tree_map(jnp.shape, theta0)

        def tie(x):
            th = unravel22(x)
            return ravel_pytree({k: jnp.broadcast_to(v, shapes[k]) for k, v in th.items()})[0]

        eye = np.eye(x22.size)
        self.tie = np.stack([np.asarray(tie(jnp.asarray(e))) for e in eye], axis=1)  # (160, 22)
        assert np.allclose(self.tie @ np.asarray(x22), self.x0)
        self.x0_constant = np.asarray(x22)

    def training(self, seed: int, k: int = 0):
        """The fixed training batch of a seed; ``k`` > 0: the k-th fresh one (L-BFGS's renewals)."""
        key = jax.random.key(seed) if k == 0 else jax.random.fold_in(jax.random.key(seed), k)
        return sample_scenarios(key, self.cfg.batch, self.base_scenario, stratified=self.cfg.stratified)

    def to_full(self, problem: str, x) -> np.ndarray:
        return self.tie @ x if problem == "constant" else np.asarray(x)

    def start(self, problem: str) -> np.ndarray:
        return self.x0_constant if problem == "constant" else self.x0

    def oracle(self, problem: str, seed: int) -> _methods.Oracle:
        """The training objective on the seed's batch; it can renew to the seed's fresh batches."""
        T = self.tie if problem == "constant" else None
        batch = {"scen": self.training(seed)}

        def vg(x):
            f, g = self.value_and_grad(jnp.asarray(self.to_full(problem, x)), batch["scen"])
            g = np.asarray(g)
            return float(f), (T.T @ g if T is not None else g)

        def values(X):
            full = np.stack([self.to_full(problem, x) for x in X])
            return np.asarray(self.values(jnp.asarray(full), batch["scen"]))

        def value(x):
            return float(self.value(jnp.asarray(self.to_full(problem, x)), batch["scen"]))

        def renew(k):
            batch["scen"] = self.training(seed, k)

        return _methods.Oracle(value_and_grad=vg, values=values, value=value, renew=renew)

    def heldout_cost(self, problem: str, x) -> float:
        return float(self.value(jnp.asarray(self.to_full(problem, x)), self.heldout))

    def compile(self, log=print) -> dict:
        """Compile (or load from the cache) the four programs; seconds each."""
        scen = self.training(0)
        out = {}
        for name, call in (
            ("value_and_grad", lambda: self.value_and_grad(jnp.asarray(self.x0), scen)),
            ("population_values", lambda: self.values(jnp.asarray(np.stack([self.x0] * self.cfg.popsize)), scen)),
            ("training_value", lambda: self.value(jnp.asarray(self.x0), scen)),
            ("heldout_value", lambda: self.value(jnp.asarray(self.x0), self.heldout)),
        ):
            out[name] = _seconds(call)
            log(f"  compiled {name} in {out[name]:.1f} s")
        return out

    def call_seconds(self, repeats: int = 3) -> dict:
        """Median seconds of one warm call on the training batch: the gradient
        (with its value) and the value alone (a line-search trial's two prices)."""
        scen, x = self.training(0), jnp.asarray(self.x0)
        calls = {"value_and_grad": lambda: self.value_and_grad(x, scen), "training_value": lambda: self.value(x, scen)}
        return {name: float(np.median([_seconds(call) for _ in range(repeats)])) for name, call in calls.items()}


def _seconds(call) -> float:
    """Wall seconds of ``call()`` to its result."""
    t = time.perf_counter()
    jax.block_until_ready(call())
    return time.perf_counter() - t


def run_one(programs: Programs, problem: str, method: str, seed: int, log: Callable = print, **options) -> dict:
    """One method on one problem with one seed, for ``programs.cfg.budget_s`` of optimisation."""
    cfg = programs.cfg
    m = _methods.get(method, **options) if method != "cmaes" else _methods.get(method, popsize=cfg.popsize, **options)
    if method == "cmaes-lbfgs":
        m = dataclasses.replace(m, cmaes=_methods.CMAES(popsize=cfg.popsize))
    oracle = programs.oracle(problem, seed)
    x0 = programs.start(problem)
    h0 = programs.heldout_cost(problem, x0)
    state = m.init(x0, seed)
    load_before = os.getloadavg()[0]
    used, curve, rows = 0.0, [(0.0, h0)], []
    best = h0
    for i in range(cfg.max_iterations):
        if used >= cfg.budget_s:
            break
        t = time.perf_counter()
        state, row = m.step(state, oracle)
        x = m.incumbent(state)
        used += time.perf_counter() - t
        h = programs.heldout_cost(problem, x)
        best = min(best, h) if np.isfinite(h) else best
        curve.append((used, h))
        rows.append({"iteration": i, "seconds": used, "heldout_cost": h, **row})
        log(f"  {problem:8s} {method:11s} seed {seed}  {used:6.1f} s  it {i:3d}  held-out {h:.4g}  best {best:.4g}")
        if row.get("converged"):
            break
    target = cfg.target * h0
    hit = next((tt for tt, c in curve if c <= target), None)
    return {
        "problem": problem,
        "method": method,
        "seed": seed,
        "initial_heldout_cost": h0,
        "budget_s": cfg.budget_s,
        "target_cost": target,
        "time_to_target_s": hit,
        "best_heldout_cost": best,
        "final_heldout_cost": curve[-1][1],
        "iterations": len(rows),
        "gradient_calls": oracle.gradient_calls,
        "value_calls": oracle.value_calls,
        "forward_rollouts_population": oracle.forward_rollouts * cfg.batch,
        "training_batches": oracle.batch + 1,
        "curve": curve,
        "history": rows,
        "x": np.asarray(m.incumbent(state)).tolist(),
        "load_average_1min": [load_before, os.getloadavg()[0]],  # > ~2.2 on 2 cores: something else ran
    }


HARD_TOLERANCE = 0.10
"""The hard target of a seed: within this fraction of the best held-out cost
any method reached on that problem and seed."""
FRACTIONS = (0.25, 0.5, 1.0)  # of the budget, where the held-out cost is reported


def cost_at(curve, t: float) -> float:
    """The incumbent's held-out cost at optimisation time ``t``: the last point of
    ``curve`` ((seconds, cost) pairs from (0, start)) at or before ``t``."""
    c = [cost for time_s, cost in curve if time_s <= t]
    return float(c[-1]) if c else float(curve[0][1])


def time_to(curve, target: float) -> float | None:
    """The first optimisation time at which the held-out cost is at or below ``target``."""
    return next((float(t) for t, c in curve if c <= target), None)


def annotate(runs: list[dict]) -> list[dict]:
    """Each run with the figures that compare methods on its seed: the hard
    target (``HARD_TOLERANCE`` above the best held-out cost any method reached
    on that problem and seed) and the time to it, the held-out cost at 25, 50
    and 100 % of the budget, and the worst held-out cost of any iterate (the
    first one's on) as a multiple of the start's (above 1: the tuner made what
    is held out worse than where it started)."""
    best: dict = {}
    for r in runs:
        key = (r["problem"], r["seed"])
        best[key] = min(best.get(key, np.inf), r["best_heldout_cost"])
    out = []
    for r in runs:
        budget = float(r.get("budget_s") or r["curve"][-1][0])
        hard = (1 + HARD_TOLERANCE) * best[(r["problem"], r["seed"])]
        iterates = [c for _, c in r["curve"][1:]]
        worst = max(iterates, default=r["initial_heldout_cost"])
        out.append(
            {
                **r,
                "hard_target_cost": hard,
                "time_to_hard_target_s": time_to(r["curve"], hard),
                **{f"cost_at_{round(100 * f)}pct": cost_at(r["curve"], f * budget) for f in FRACTIONS},
                "worst_iterate_over_start": float(worst / r["initial_heldout_cost"]),
            }
        )
    return out


def _spread(values) -> dict:
    v = np.asarray(values, dtype=float)
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}


def summarize(runs: list[dict]) -> list[dict]:
    """Per problem and method, over seeds: how many reached each target, the
    time to the half-cost and to the hard target (median, min, max; a run that
    missed counts as infinitely slow), the best held-out cost, the held-out
    cost at 25, 50 and 100 % of the budget, and the worst held-out cost of any
    iterate over the start's (with how many seeds went above 1)."""
    runs = annotate(runs)
    out = []
    keys = sorted({(r["problem"], r["method"]) for r in runs}, key=lambda k: (k[0], _methods.METHODS.index(k[1])))
    for problem, method in keys:
        rs = [r for r in runs if r["problem"] == problem and r["method"] == method]
        tt = [r["time_to_target_s"] if r["time_to_target_s"] is not None else np.inf for r in rs]
        th = [r["time_to_hard_target_s"] if r["time_to_hard_target_s"] is not None else np.inf for r in rs]
        worst = [r["worst_iterate_over_start"] for r in rs]
        row = {
            "problem": problem,
            "method": method,
            "seeds": len(rs),
            "seed_list": sorted(r["seed"] for r in rs),
            "reached": int(np.isfinite(tt).sum()),
            "reached_hard": int(np.isfinite(th).sum()),
            "above_start": int(sum(w > 1 for w in worst)),
            "worst_iterate_over_start_max": float(max(worst)),
            "training_batches": [int(r.get("training_batches", 1)) for r in rs],  # per seed (L-BFGS renews)
            # what the budget bought, medians over seeds
            "iterations_median": float(np.median([r["iterations"] for r in rs])),
            "gradient_calls_median": float(np.median([r["gradient_calls"] for r in rs])),
            "value_calls_median": float(np.median([r.get("value_calls", 0) for r in rs])),
        }
        for name, values in (
            ("time_to_target", tt),
            ("time_to_hard_target", th),
            ("best_heldout", [r["best_heldout_cost"] for r in rs]),
            *((f"cost_at_{round(100 * f)}pct", [r[f"cost_at_{round(100 * f)}pct"] for r in rs]) for f in FRACTIONS),
        ):
            sp = _spread(values)
            suffix = "_s" if name.startswith("time") else ""
            row.update({f"{name}_{k}{suffix}": v for k, v in sp.items()})
        out.append(row)
    return out


def table(summary: list[dict]) -> str:
    """The summary as text: medians with [min, max] over seeds."""

    def s(v):
        return "never" if not np.isfinite(v) else f"{v:.1f}"

    def span(r, name, fmt):
        sfx = "_s" if name.startswith("time") else ""
        m, lo, hi = (r[f"{name}_{k}{sfx}"] for k in ("median", "min", "max"))
        return f"{fmt(m)} [{fmt(lo)}, {fmt(hi)}]"

    def g(v):
        return f"{v:.3g}"

    lines = [
        f"{'problem':9s} {'method':12s} {'to half, s':>22s} {'to hard (10 %), s':>22s} {'cost at 25 %':>22s}"
        f" {'cost at 50 %':>22s} {'cost at 100 %':>22s} {'worst iterate / start':>24s}"
    ]
    for r in summary:
        worst = f"{g(r['worst_iterate_over_start_max'])} ({r['above_start']}/{r['seeds']} > 1)"
        lines.append(
            f"{r['problem']:9s} {r['method']:12s} {span(r, 'time_to_target', s):>22s}"
            f" {span(r, 'time_to_hard_target', s):>22s} {span(r, 'cost_at_25pct', g):>22s}"
            f" {span(r, 'cost_at_50pct', g):>22s} {span(r, 'cost_at_100pct', g):>22s}"
            f" {worst:>24s}"
        )
    return "\n".join(lines)


def plot(runs: list[dict], path: str, target_fraction: float | None = None) -> None:
    """Each seed's held-out cost of the incumbent against optimisation wall time
    (thin lines, one colour per method; the start dashed), one panel per problem."""
    plt = _results.pyplot()
    problems = [p for p in PROBLEMS if any(r["problem"] == p for r in runs)]
    fig, axes = plt.subplots(1, len(problems), figsize=(6.5 * len(problems), 4.2), squeeze=False)
    colors = dict(zip(_methods.METHODS, ("C0", "C1", "C2", "C3"), strict=True))
    for ax, problem in zip(axes[0], problems, strict=True):
        seen = set()
        for r in runs:
            if r["problem"] != problem:
                continue
            c = np.array(r["curve"], dtype=float)
            label = r["method"] if r["method"] not in seen else None
            seen.add(r["method"])
            ax.step(c[:, 0], c[:, 1], where="post", color=colors[r["method"]], alpha=0.7, lw=1.0, label=label)
            ax.axhline(r["initial_heldout_cost"], color="k", ls="--", lw=0.6)
        n = PROBLEMS[problem].size()
        ax.set_title(f"{problem} gains ({n} parameters), one line per seed")
        ax.set_xlabel("optimisation wall time [s] (compiling and scoring excluded)")
        ax.set_ylabel("held-out cost of the incumbent")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(title="dashed: the start")
    _results.save_figure(fig, path)
