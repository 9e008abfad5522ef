"""``jaxsync sweep``: a batched parameter study over gains and scenario parameters."""

from __future__ import annotations

import argparse

from jaxsync.cli._common import (
    add_controller_argument,
    add_distributed_arguments,
    add_model_argument,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import add_stack_arguments, stack_of
from jaxsync.optimize.studies.sweep_eval import DEFAULT_BUDGET_GIB
from jaxsync.optimize.studies.sweep_report import DEFAULT_PLOT_METRICS


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "sweep",
        help="batched parameter study over gains and scenario parameters (grid or random samples)",
        description="Evaluate the metrics of many rollouts, one per point of a Cartesian grid (or of "
        "--samples random points) over named gain and scenario parameters; batched with vmap, sharded over "
        "all JAX devices, and over many processes (--coordinator ...), resumable (--resume). Writes results.csv, "
        "summary.json, a heatmap (2 swept parameters) or a "
        "line plot (1) to --out. See docs/sweep.md.",
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUES",
        help="a parameter and its values: lo:hi:n (n points), a,b,c (a list), v (fixed), or lo:hi "
        "(with --samples). Names: gains (k_rk, imp_stiffness, imp_stiffness.z, "
        "imp_stiffness.r.z, ...), "
        "scenario fields (object_mass, lift.z, ...), noise_seed. Repeat for each parameter.",
    )
    p.add_argument("--samples", type=int, default=None, help="draw this many random points instead of the grid")
    p.add_argument("--seed", type=int, default=0, help="seed of the random points (0)")
    p.add_argument("--duration", type=positive(float), default=4.0, help="seconds simulated per rollout (4)")
    add_controller_argument(p, position=True)
    p.add_argument("--solver", default="accurate", choices=["accurate", "unrolled"])
    p.add_argument("--gains", default=None, help="JSON file of base gains (default: built-in)")
    p.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="points per compiled batch, a multiple of the device count (default: 32 per CPU "
        "device, 1024 per accelerator, shrunk to fit the memory budget; at most 64 per CPU "
        "device (JAXSYNC_CPU_VMAP_LIMIT), see docs/performance.md)",
    )
    p.add_argument(
        "--memory-budget-gib",
        type=float,
        default=DEFAULT_BUDGET_GIB,
        help=f"memory per device for one chunk, GiB ({DEFAULT_BUDGET_GIB:g})",
    )
    p.add_argument("--out", default="results/sweep", help="output folder (results/sweep)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the same sweep in --out (its finished chunks are read back)",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="discard the sweep in --out and start over; without --resume or --restart, a folder holding a "
        "sweep is an error",
    )
    p.add_argument(
        "--plot-metric",
        action="append",
        default=None,
        help=f"metric(s) to plot (default: {', '.join(DEFAULT_PLOT_METRICS)})",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--max-chunks", type=int, default=None, help=argparse.SUPPRESS)  # testing: stop early
    add_stack_arguments(p)
    add_model_argument(p)
    add_distributed_arguments(p)
    p.set_defaults(func=run, interrupted_hint="finished chunks are kept; run again with --resume to continue")
    return p


def run(args: argparse.Namespace) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.io import gains_file
    from jaxsync.optimize.studies import sweep

    source = model_source(args)
    gains = gains_file.load_constant(args.gains, "jaxsync sweep") if args.gains else None  # None: the model's own
    plan = sweep.make_plan(
        args.param,
        samples=args.samples,
        seed=args.seed,
        duration=args.duration,
        controller=args.controller,
        solver=args.solver,
        base_gains=gains,
        model=source,
        visual=model_options(args)["visual"],
        stack=stack_of(args),
    )
    summary = sweep.run(
        plan,
        args.out,
        chunk=args.chunk,
        budget_gib=args.memory_budget_gib,
        restart=args.restart,
        resume=args.resume,
        progress=not args.no_progress,
        max_chunks=args.max_chunks,
        plot_metrics=tuple(args.plot_metric or DEFAULT_PLOT_METRICS),
    )
    if not summary["complete"] or "process_index" in summary:  # stopped early, or not process 0
        return 0
    t = summary["timing"]
    print(
        f"{summary['n_points']} points ({summary['n_ok']} ok, {summary['n_dropped']} dropped, "
        f"{summary['n_nonfinite']} non-finite, {summary.get('n_chattering', 0)} chattering) in {t['wall_s']:.1f} s "
        f"(compile {t['compile_s']:.1f} s; {t['chunks_loaded']} chunk(s) read back)"
    )
    for k, best in summary["best_ok_point"].items():
        where = ", ".join(f"{n}={v:g}" for n, v in best.items() if n not in ("point", k))
        print(f"lowest {k}: {best[k]:.5g} at {where}")
    files = ", ".join(f for f in summary["files"] if f != "chunks/")
    print(f"results in {args.out}: {files}")
    return 0
