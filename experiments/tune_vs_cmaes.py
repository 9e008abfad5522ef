"""Gradient tuning (Adam through MJX) against CMA-ES, for the same wall-clock budget.

Both methods optimise the same parameters (optimize/params.py, unconstrained
theta), on the same batched rollouts (the training task, jaxsync's one
solver setting with its exact gradient, batches of randomised scenarios seeded by iteration), and are
scored on the same held-out scenarios (another seed). Each method gets the
same optimisation wall time; compile time and the held-out scoring are not
counted (they are reported). Writes ``tune_vs_cmaes.json`` (each method's
time to reach the target cost, its best held-out cost and curve) and
``tune_vs_cmaes.png``.

    python experiments/tune_vs_cmaes.py --budget 600 --out results/tune_vs_cmaes
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxsync.optimize.loop import apply_update

import jaxsync
from jaxsync import (
    CostWeights,
    TuneConfig,
    TuneSpec,
    _io,  # atomic result files
    make_loss,
    sample_scenarios,
    short_task,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=600.0, help="optimisation seconds per method (600)")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--heldout-batch", type=int, default=4)
    p.add_argument("--popsize", type=int, default=8, help="CMA-ES population (8)")
    p.add_argument("--sigma", type=float, default=0.3, help="CMA-ES initial step in theta (0.3)")
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--target", type=float, default=0.5, help="target = this fraction of the initial held-out cost")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/tune_vs_cmaes")
    args = p.parse_args(argv)
    try:
        import cma
    except ImportError:
        print("tune_vs_cmaes: needs the 'cma' package: pip install 'jaxsync[baseline]'", file=sys.stderr)
        return 2
    jax.config.update("jax_enable_x64", True)
    jaxsync.enable_compilation_cache()
    _io.ensure_writable_dir(args.out)

    model = jaxsync.load_model()
    spec, base = TuneSpec(), jaxsync.default_gains()
    cfg = TuneConfig(
        batch=args.batch, learning_rate=args.lr, iterations=10_000, schedule="constant", seed=args.seed, task="short"
    )
    loss = make_loss(model, spec, base, cfg, CostWeights())
    theta0 = spec.init(base)
    x0, unravel = ravel_pytree(theta0)
    value = jax.jit(lambda x, s: loss(unravel(x), s)[0])
    value_and_grad = jax.jit(jax.value_and_grad(lambda th, s: loss(th, s)[0]))
    held = sample_scenarios(jax.random.key(10_000 + args.seed), args.heldout_batch, short_task())
    batch_of = lambda i: sample_scenarios(jax.random.fold_in(jax.random.key(args.seed), i), args.batch, short_task())  # noqa: E731

    t = time.perf_counter()
    initial = float(value(x0, held))
    jax.block_until_ready(value_and_grad(theta0, batch_of(0)))
    compile_s = time.perf_counter() - t
    target = args.target * initial
    print(f"initial held-out cost {initial:.4g}, target {target:.4g} (compile {compile_s:.0f} s)", flush=True)

    results = {}
    # --- gradient (Adam)
    opt = cfg.optimizer_transform()
    theta, state = theta0, opt.init(theta0)
    used, curve, best, i = 0.0, [(0.0, initial)], initial, 0
    while used < args.budget:
        t = time.perf_counter()
        v, g = value_and_grad(theta, batch_of(i))
        theta, state = jax.block_until_ready(apply_update(opt, theta, state, v, g))[:2]  # skips a non-finite step
        used += time.perf_counter() - t
        h = float(value(ravel_pytree(theta)[0], held))
        best = min(best, h)
        curve.append((used, best))
        print(f"adam   {used:7.1f} s  iteration {i:3d}  held-out {h:.4g}  best {best:.4g}", flush=True)
        i += 1
    results["adam"] = {"curve": curve, "best_heldout_cost": best, "iterations": i}

    # --- CMA-ES (same batches: generation g uses batch g)
    es = cma.CMAEvolutionStrategy(
        np.asarray(x0), args.sigma, {"popsize": args.popsize, "seed": args.seed + 1, "verbose": -9}
    )
    used, curve, best, gen = 0.0, [(0.0, initial)], initial, 0
    while used < args.budget:
        t = time.perf_counter()
        xs = es.ask()
        s = batch_of(gen)
        fs = [float(value(jnp.asarray(x), s)) for x in xs]
        es.tell(xs, [f if np.isfinite(f) else 1e12 for f in fs])
        used += time.perf_counter() - t
        h = float(value(jnp.asarray(es.mean), held))
        best = min(best, h)
        curve.append((used, best))
        print(f"cmaes  {used:7.1f} s  generation {gen:3d}  held-out {h:.4g}  best {best:.4g}", flush=True)
        gen += 1
    results["cmaes"] = {
        "curve": curve,
        "best_heldout_cost": best,
        "generations": gen,
        "rollouts_per_generation": args.popsize * args.batch,
    }

    for r in results.values():
        hit = [tt for tt, c in r["curve"] if c <= target]
        r["time_to_target_s"] = hit[0] if hit else None
    summary = {
        "initial_heldout_cost": initial,
        "target_cost": target,
        "budget_s": args.budget,
        "compile_s": compile_s,
        "methods": results,
        "options": vars(args),
    }
    _io.write_json(f"{args.out}/tune_vs_cmaes.json", summary)  # atomic writes

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, r in results.items():
        c = np.array(r["curve"])
        ax.step(
            c[:, 0],
            c[:, 1],
            where="post",
            label=f"{name} (to target: {r['time_to_target_s'] and round(r['time_to_target_s'])} s)",
        )
    ax.axhline(target, color="k", ls=":", lw=0.8, label="target")
    ax.set_xlabel("optimisation wall time [s] (compile excluded)")
    ax.set_ylabel("best held-out cost")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    _io.save_figure(fig, f"{args.out}/tune_vs_cmaes.png")
    for name, r in results.items():
        print(f"{name}: best held-out cost {r['best_heldout_cost']:.4g}, time to target {r['time_to_target_s']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
