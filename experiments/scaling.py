"""One process against several on this machine: sweep throughput and tuning
time per iteration (docs/scaling.md).

Starts ``jaxsync sweep`` and ``jaxsync tune`` as 1 and as N local processes
(JAX's distributed runtime, a coordinator on 127.0.0.1, CPU, one device per
process) and reads their summaries:

- sweep: points per second of the evaluation (the slowest process's
  evaluation time; compile excluded), the same points for every process count;
- tune: the median seconds of an iteration after the first (which compiles)
  at a fixed batch per process, so N processes train on N times the batch.

Each configuration runs twice and the second run is reported: the first
fills the persistent compilation cache. Run it alone on the machine:

    python experiments/scaling.py --processes 1,2 --out results/scaling
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time

FAST = ["--param", "t_close=0.3", "--param", "t_squeeze=0.4", "--param", "t_carry=0.5", "--param", "settle_time=0.3"]
FAST += ["--param", "lift.x=0.02", "--param", "lift.z=0.05", "--duration", "1.7"]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(argv: list[str], n: int, log_dir: str, timeout: float = 3600) -> float:
    """``jaxsync ARGV`` as n processes of one run (n = 1: a plain process); wall seconds."""
    port = _port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = []
    t0 = time.perf_counter()
    for k in range(n):
        dist = (
            ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n), "--process-id", str(k)] if n > 1 else []
        )
        log = open(os.path.join(log_dir, f"n{n}_p{k}.log"), "w")  # noqa: SIM115
        procs.append((subprocess.Popen(["jaxsync", *argv, *dist], stdout=log, stderr=subprocess.STDOUT, env=env), log))
    try:
        for p, _ in procs:
            if p.wait(timeout=timeout) != 0:
                raise RuntimeError(f"jaxsync {' '.join(argv)} as {n} processes failed; logs in {log_dir}")
    finally:
        for p, log in procs:
            if p.poll() is None:
                p.kill()
            log.close()
    return time.perf_counter() - t0


def sweep(n: int, points_side: int, chunk: int, out: str) -> dict:
    argv = ["sweep", *FAST, "--param", f"k_rk=-0.5:0.5:{points_side}", "--param", "object_mass=0.4:0.8:4"]
    argv += ["--chunk", str(chunk), "--no-progress", "--out", out]
    for _ in range(2):  # the first run fills the compilation cache
        wall = launch([*argv, "--restart"], n, os.path.dirname(out))
    s = json.load(open(os.path.join(out, "summary.json")))
    t = s["timing"]
    return {
        "processes": n,
        "points": s["n_points"],
        "wall_s": wall,
        "compile_s": t["compile_s"],
        "eval_s": t["eval_s"],
        "points_per_s": t["points_per_s"],
        "env_steps_per_s": t["env_steps_per_s"],
    }


def tune(n: int, batch: int, iterations: int, out: str) -> dict:
    argv = ["tune", "--task", "short", "--method", "adam", "--batch", str(batch), "--iterations", str(iterations)]
    argv += ["--validate-every", "0", "--heldout-batch", "1", "--no-mujoco-check", "--out", out]
    for _ in range(2):
        wall = launch([*argv, "--restart"], n, os.path.dirname(out))
    import csv

    with open(os.path.join(out, "history.csv")) as f:
        secs = [float(r["seconds"]) for r in csv.DictReader(f)][1:]  # the first iteration compiles
    return {
        "processes": n,
        "batch_per_process": batch,
        "total_batch": batch * n,
        "iteration_s_median": statistics.median(secs),
        "iteration_s": secs,
        "wall_s": wall,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--processes", default="1,2", help="process counts (1,2)")
    ap.add_argument("--points-side", type=int, default=16, help="k_rk values; x 4 masses = the sweep's points (16)")
    ap.add_argument("--chunk", type=int, default=16, help="points per chunk (16)")
    ap.add_argument("--batch", type=int, default=2, help="tuning scenarios per process (2)")
    ap.add_argument("--iterations", type=int, default=4, help="tuning iterations (4)")
    ap.add_argument("--out", default="results/scaling")
    ap.add_argument("--what", default="sweep,tune", help="what to measure (sweep,tune)")
    args = ap.parse_args(argv)
    ns = [int(x) for x in args.processes.split(",")]
    os.makedirs(args.out, exist_ok=True)
    res = {"sweep": [], "tune": [], "cpu_count": os.cpu_count()}
    for n in ns if "sweep" in args.what else []:
        r = sweep(n, args.points_side, args.chunk, os.path.join(args.out, f"sweep_n{n}"))
        print(
            f"sweep, {n} process(es): {r['points']} points, {r['points_per_s']:.2f} points/s "
            f"({r['env_steps_per_s']:.0f} env-steps/s; eval {r['eval_s']:.1f} s, wall {r['wall_s']:.1f} s)",
            flush=True,
        )
        res["sweep"].append(r)
    for n in ns if "tune" in args.what else []:
        r = tune(n, args.batch, args.iterations, os.path.join(args.out, f"tune_n{n}"))
        print(
            f"tune, {n} process(es), batch {args.batch} each ({r['total_batch']} in all): "
            f"{r['iteration_s_median']:.2f} s per iteration (median of {len(r['iteration_s'])})",
            flush=True,
        )
        res["tune"].append(r)
    with open(os.path.join(args.out, "scaling.json"), "w") as f:
        json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
