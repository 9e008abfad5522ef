"""The tuning gradient on other robots against the paper model: its cost in forward rollouts and its cold compile.

For each model (the paper model and each robot file given), in a fresh
process without the persistent compilation cache: the tuning cost of one
short-task rollout (2 s, 1000 steps, the implicit path ``jaxsync tune``
runs, rematerialised scan, batch 1, float64) at the model's default gains;
the first gradient call's time (trace and compile: the cold compile), then
forward and gradient timed alternately, best of N; the ratio is gradient /
forward. Writes ``robot_cost.json`` and prints each model's figures and its
ratios to the paper model's.

    python experiments/robot_cost.py mjcf/robots/iiwa14_twice.yaml --out results/robot_cost
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def measure(model_path: str | None, repeats: int, duration: float) -> dict:
    import jax

    import jaxsync
    from jaxsync.control.gains import default_gains
    from jaxsync.optimize.tuning.cost import CostWeights, cost

    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    model = jaxsync.load_model(model_path)
    s, g = jaxsync.short_task(model), default_gains(model)
    roll = jaxsync.make_rollout(model, "synchronous", duration, remat=True, passes="tree")

    def loss(gains, s):
        return cost(roll(gains, s), s, CostWeights())

    grad = jax.jit(jax.value_and_grad(loss))
    t0 = time.perf_counter()
    jax.block_until_ready(grad(g, s))
    cold = time.perf_counter() - t0
    fwd = jax.jit(loss)
    jax.block_until_ready(fwd(g, s))
    f, gr = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fwd(g, s))
        t1 = time.perf_counter()
        jax.block_until_ready(grad(g, s))
        t2 = time.perf_counter()
        f.append(t1 - t0)
        gr.append(t2 - t1)
    return {
        "model": model_path or "paper model",
        "joints_per_arm": len(model.index.right.dof_adr),
        "first_gradient_call_s": cold,
        "forward_s": min(f),
        "gradient_s": min(gr),
        "gradient_over_forward": min(gr) / min(f),
        "load_average": os.getloadavg(),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("robots", nargs="*", help="robot files (the paper model is always measured first)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--duration", type=float, default=2.0)
    p.add_argument("--out", default="results/robot_cost")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child is not None:
        print(json.dumps(measure(args.child or None, args.repeats, args.duration)))
        return 0
    for r in args.robots:
        if not os.path.isfile(r):
            print(f"robot_cost: no such robot file {r!r}", file=sys.stderr)
            return 2
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    rows = []
    for model in ["", *args.robots]:
        print(f"measuring {model or 'the paper model'} in a fresh process...", flush=True)
        cmd = [sys.executable, __file__, "--child", model, "--repeats", str(args.repeats)]
        cmd += ["--duration", str(args.duration)]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            print(done.stderr[-2000:], file=sys.stderr)
            return 1
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    paper = rows[0]
    for r in rows:
        r["cost_over_paper"] = r["gradient_over_forward"] / paper["gradient_over_forward"]
        r["cold_compile_over_paper"] = r["first_gradient_call_s"] / paper["first_gradient_call_s"]
        print(
            f"{r['model']}: {r['joints_per_arm']} joints per arm, first gradient call "
            f"{r['first_gradient_call_s']:.1f} s ({r['cold_compile_over_paper']:.2f}x the paper model's), "
            "gradient / forward "
            f"{r['gradient_over_forward']:.2f} ({r['cost_over_paper']:.2f}x)"
        )
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "robot_cost.json")
    with open(path + ".tmp", "w") as fh:
        json.dump({"duration_s": args.duration, "repeats": args.repeats, "models": rows}, fh, indent=2)
    os.replace(path + ".tmp", path)
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
