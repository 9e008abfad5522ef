"""Tuners against each other on the same rollouts: Adam, L-BFGS, CMA-ES, CMA-ES then L-BFGS.

The same parameters, fixed training batch (per seed), held-out scenarios and
optimisation wall-clock budget for every method; on the 22-parameter problem
of ``jaxsync tune`` and on the 160-parameter gain-schedule problem
(``jaxsync.optimize.benchmarks.tuner_benchmark``). Each finished run is appended to
``runs.jsonl`` at once; a re-run with the same ``--out`` skips the runs
already there (an interrupted benchmark loses at most the run in progress).
Writes ``summary.json`` (median and range over seeds of the time to the
target held-out cost and of the best held-out cost), ``tuner_benchmark.png``
(held-out cost against wall time) and prints the table.

    python experiments/tuner_benchmark.py --budget 60 --seeds 0,1,2 --out results/tuner_benchmark
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=60.0, help="optimisation seconds per run (60)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (0,1,2)")
    p.add_argument("--problems", default="constant,schedule", help="constant, schedule (both)")
    p.add_argument("--methods", default="adam,lbfgs,cmaes,cmaes-lbfgs", help="methods (all four)")
    p.add_argument("--batch", type=int, default=4, help="training scenarios (4, as jaxsync tune)")
    p.add_argument("--heldout-batch", type=int, default=8, help="held-out scenarios (8)")
    p.add_argument("--popsize", type=int, default=16, help="CMA-ES population (16)")
    p.add_argument("--target", type=float, default=0.5, help="target: this fraction of the start's held-out cost")
    p.add_argument(
        "--sampling",
        choices=("stratified", "iid"),
        default="stratified",
        help="the fixed training batch: a Latin hypercube on the scenario ranges' ends (stratified, as jaxsync tune) "
        "or independent uniform draws (iid)",
    )
    p.add_argument("--out", default="results/tuner_benchmark")
    args = p.parse_args(argv)

    import jax

    import jaxsync

    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    from jaxsync._errors import ConfigError
    from jaxsync.io import results as _results
    from jaxsync.optimize.benchmarks import tuner_benchmark as B
    from jaxsync.optimize.tuning import methods as M

    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        problems = [s.strip() for s in args.problems.split(",") if s.strip()]
        names = [s.strip() for s in args.methods.split(",") if s.strip()]
        bad = [x for x in problems if x not in B.PROBLEMS] + [x for x in names if x not in M.METHODS]
        if bad or not seeds or not problems or not names:
            raise ConfigError(f"unknown or empty: {bad}; problems {list(B.PROBLEMS)}, methods {list(M.METHODS)}")
        if not args.budget > 0 or args.batch < 1 or args.heldout_batch < 1 or args.popsize < 2:
            raise ConfigError("--budget must be > 0, --batch and --heldout-batch >= 1, --popsize >= 2")
        if not 0 < args.target < 1:
            raise ConfigError(f"--target must lie in (0, 1), got {args.target}")
        _results.ensure_writable_dir(args.out)
    except (ConfigError, ValueError) as err:
        print(f"tuner_benchmark: {err}", file=sys.stderr)
        return 2
    jaxsync.enable_compilation_cache()
    cfg = B.BenchConfig(
        budget_s=args.budget,
        batch=args.batch,
        heldout_batch=args.heldout_batch,
        popsize=args.popsize,
        target=args.target,
        stratified=args.sampling == "stratified",
    )
    runs_path = os.path.join(args.out, "runs.jsonl")
    runs = []
    if os.path.exists(runs_path):
        with open(runs_path) as f:
            runs = [json.loads(line) for line in f if line.strip()]
        same = [r for r in runs if r.get("config") == vars(args) | {"out": None}]
        if len(same) != len(runs):
            print(f"tuner_benchmark: {runs_path} holds runs with other options; choose another --out", file=sys.stderr)
            return 2
    done = {(r["problem"], r["method"], r["seed"]) for r in runs}
    t0 = time.perf_counter()
    print("compiling the shared programs (minutes cold, seconds from the compilation cache)...", flush=True)
    programs = B.Programs(jaxsync.load_model(), cfg)
    compile_s = programs.compile()
    call_s = programs.call_seconds()
    print(
        f"one gradient {call_s['value_and_grad']:.2f} s, one value {call_s['training_value']:.2f} s (warm)", flush=True
    )
    todo = [(pr, m, s) for pr in problems for s in seeds for m in names if (pr, m, s) not in done]
    print(f"{len(todo)} runs of {args.budget:g} s to go ({len(done)} already in {runs_path})", flush=True)
    for k, (problem, method, seed) in enumerate(todo):
        print(f"[{k + 1}/{len(todo)}] {problem} {method} seed {seed}", flush=True)
        r = B.run_one(programs, problem, method, seed)
        r["config"] = vars(args) | {"out": None}
        runs.append(r)
        with open(runs_path, "a") as f:
            f.write(json.dumps(r) + "\n")
    summary = B.summarize(runs)
    _results.write_json(
        os.path.join(args.out, "summary.json"),
        {
            "summary": summary,
            "compile_s": compile_s,
            "call_s": call_s,
            "config": vars(args),
            "parameters": {k: v.size() for k, v in B.PROBLEMS.items()},
            "wall_time_s": time.perf_counter() - t0,
        },
    )
    B.plot(runs, os.path.join(args.out, "tuner_benchmark.png"))
    print(B.table(summary))
    print(f"results in {args.out}: runs.jsonl, summary.json, tuner_benchmark.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
