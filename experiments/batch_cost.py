"""What a tuning step costs at each training batch: is batching several runs a lever on this machine?

For each batch size, ``jaxsync tune``'s own loss on the paper model (the
default job: synchronous, the full 4 s task) is compiled forward-only (what
L-BFGS's line search evaluates) and with its exact gradient (what each
iteration takes), then timed at three points (best of three). Several tuning
runs vmapped into one program would cost what one run at their summed batch
costs: the throughput per scenario, against batch 4's, is the most such
batching could give. Writes ``batch_cost.json``; run it alone on the machine.

    python experiments/batch_cost.py --batches 4,8,16,32 --out results/batch_cost
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

import jaxsync
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.loss import make_loss
from jaxsync.optimize.tuning.scenarios import training_base, training_batch


def _timed(fn, *args) -> float:
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t


def measure(model, base, batch: int, repeats: int) -> dict:
    cfg = TuneConfig(batch=batch)
    theta = cfg.problem.tuned.init(base)
    scenarios = training_batch(cfg, 0, training_base(cfg.training)[0])
    forward = jax.jit(make_loss(model, base, cfg, differentiated=False))
    gradient = jax.jit(jax.value_and_grad(make_loss(model, base, cfg), has_aux=True))
    row = {"batch": batch, "compile_forward_s": _timed(forward, theta, scenarios)}
    row["compile_gradient_s"] = _timed(gradient, theta, scenarios)
    moved = [jax.tree_util.tree_map(lambda v, r=r: v + 1e-3 * r, theta) for r in range(1, repeats + 1)]
    row["forward_s"] = min(_timed(forward, p, scenarios) for p in moved)
    row["gradient_s"] = min(_timed(gradient, p, scenarios) for p in moved)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", default="4,8,16,32", help="training batch sizes (4,8,16,32)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per program, the best kept (3)")
    p.add_argument("--out", default="results/batch_cost")
    args = p.parse_args()
    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    jaxsync.enable_compilation_cache()
    model, base = jaxsync.load_model(), jaxsync.default_gains()
    rows = []
    for b in (int(x) for x in args.batches.split(",")):
        rows.append(measure(model, base, b, args.repeats))
        print(json.dumps(rows[-1]), flush=True)
    ref = rows[0]
    for r in rows:
        scale = r["batch"] / ref["batch"]
        r["forward_throughput_over_first"] = scale * ref["forward_s"] / r["forward_s"]
        r["gradient_throughput_over_first"] = scale * ref["gradient_s"] / r["gradient_s"]
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "batch_cost.json"), "w") as f:
        json.dump({"rows": rows, "devices": [str(d) for d in jax.devices()]}, f, indent=1)
    print(f"{'batch':>5} {'forward s':>10} {'gradient s':>11} {'fwd thr.':>9} {'grad thr.':>10}")
    for r in rows:
        print(f"{r['batch']:>5} {r['forward_s']:>10.3f} {r['gradient_s']:>11.3f} "
              f"{r['forward_throughput_over_first']:>8.2f}x {r['gradient_throughput_over_first']:>9.2f}x")  # fmt: skip


if __name__ == "__main__":
    main()
