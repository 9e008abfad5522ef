"""The tuning gradient's cost, the implicit path against the unrolled one, in one run.

implicit: jaxsync's physics (MJX's converged solve) with the implicit
          adjoint, the exact full-horizon gradient (what ``jaxsync tune`` runs);
unrolled: three one-iteration Newton solves per step, differentiated
          through, with the gradient truncated every 100 steps (a reference).
Both: the tuning cost of one rollout of the short task (2 s, 1000 steps),
rematerialised scan, batch 1, float64. Forward and value_and_grad of each
path are timed alternately (best of N) so that a change in load hits all
alike; the ratio is gradient / forward of the same physics. Writes
``gradient_cost.json``.

    python experiments/gradient_cost.py --repeats 5 --out results/gradient_cost
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp

import jaxsync
from jaxsync.optimize.tuning.cost import CostWeights, cost


def time_alternately(rolls: dict, gains: dict, s, repeats: int) -> tuple[dict, dict]:
    """Per name: the tuning cost of ``rolls[name](gains[name], s)`` and its value_and_grad, jitted and
    called once each (the compile, printed), then both timed for every name in turn, ``repeats`` rounds,
    so that a change in load hits all alike. Returns ({name: (forward, gradient)}, {name: {"forward":
    [s, ...], "gradient": [s, ...]}})."""
    fns = {}
    for name, roll in rolls.items():

        def loss(gains, s, roll=roll):
            return cost(roll(gains, s), s, CostWeights())

        g = gains[name]
        t0 = time.perf_counter()
        fwd = jax.jit(loss)
        jax.block_until_ready(fwd(g, s))
        t1 = time.perf_counter()
        grad = jax.jit(jax.value_and_grad(loss))
        jax.block_until_ready(grad(g, s))
        t2 = time.perf_counter()
        fns[name] = (fwd, grad)
        print(f"{name}: first forward call {t1 - t0:.1f} s, first gradient call {t2 - t1:.1f} s", flush=True)
    times = {name: {"forward": [], "gradient": []} for name in fns}
    for _ in range(repeats):
        for name, (fwd, grad) in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fwd(gains[name], s))
            t1 = time.perf_counter()
            jax.block_until_ready(grad(gains[name], s))
            t2 = time.perf_counter()
            times[name]["forward"].append(t1 - t0)
            times[name]["gradient"].append(t2 - t1)
    return fns, times


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--duration", type=float, default=2.0)
    p.add_argument("--out", default="results/gradient_cost")
    args = p.parse_args()
    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    jaxsync.enable_compilation_cache()
    s, g = jaxsync.short_task(), jaxsync.default_gains()
    paths = {
        "unrolled (1-iteration solves, truncated every 100 steps)": (jaxsync.load_model(solver="unrolled"), 100),
        "implicit (converged solve, implicit adjoint, exact)": (jaxsync.load_model(), None),
    }
    rolls = {
        name: jaxsync.make_rollout(model, "synchronous", args.duration, remat=True, passes="tree", truncate_every=trunc)
        for name, (model, trunc) in paths.items()
    }
    fns, times = time_alternately(rolls, dict.fromkeys(rolls, g), s, args.repeats)
    result = {"duration_s": args.duration, "repeats": args.repeats, "load_average": os.getloadavg(), "paths": {}}
    for name, t in times.items():
        f, gr = min(t["forward"]), min(t["gradient"])
        value, grad = fns[name][1](g, s)
        finite = bool(all(jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(grad)))
        result["paths"][name] = {
            "forward_s": f,
            "gradient_s": gr,
            "gradient_over_forward": gr / f,
            "cost": float(value),
            "gradient_finite": finite,
        }
        print(f"{name}: forward {f:.3f} s, gradient {gr:.3f} s, ratio {gr / f:.2f}, cost {float(value):.5g}")
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "gradient_cost.json")
    with open(path + ".tmp", "w") as fh:
        json.dump(result, fh, indent=2)
    os.replace(path + ".tmp", path)
    print(f"load average after: {os.getloadavg()}; written {path}")


if __name__ == "__main__":
    main()
