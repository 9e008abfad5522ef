"""``jaxsync bench``: how fast the simulator, its gradient and its compilation are.

Parses, runs ``jaxsync.optimize.benchmarks.benchmark.run`` (every measurement, written to
``bench.json``) and prints its table; docs/performance.md discusses the numbers.
"""

from __future__ import annotations

import argparse

from jaxsync._errors import ConfigError
from jaxsync.cli._common import add_model_argument, model_options, model_source
from jaxsync.cli._stack import add_stack_arguments, stack_of


def _batch_list(text: str) -> list[int]:
    try:
        sizes = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--batch-sizes must be comma-separated whole numbers, got {text!r}") from None
    if not sizes or any(b < 1 for b in sizes):
        raise ConfigError(f"--batch-sizes must be positive whole numbers, got {text!r}")
    return sizes


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "bench",
        help="measure simulation throughput, gradient cost, compile times and memory",
        description="Benchmark MJX against MuJoCo C, the gradient against the forward rollout, compile times "
        "and the memory of a tuning step, in one run; writes bench.json and prints a table. With --robot, "
        "all of it on that robot, and its gradient's cost and cold compile against the paper model's. With "
        "--actuation position, also the position stack's gradient cost against the torque stack's, in the same "
        "rounds. See docs/performance.md.",
    )
    p.add_argument("--out", default="results/bench", help="output folder (results/bench)")
    p.add_argument("--quick", action="store_true", help="tiny horizons and batches: a smoke test, not a benchmark")
    p.add_argument("--batch-sizes", default=None, help="MJX batch sizes, comma-separated (1,16,64,256)")
    add_stack_arguments(p)
    add_model_argument(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    sizes = _batch_list(args.batch_sizes) if args.batch_sizes is not None else None
    stack = stack_of(args)
    from jaxsync.optimize.benchmarks import benchmark  # inside: the command line's start-up time (`jaxsync --help`)

    source = model_source(args)
    r = benchmark.run(args.out, quick=args.quick, batch_sizes=sizes, source=source, stack=stack, **model_options(args))
    print(benchmark.table(r))
    print(f"bench.json in {args.out} ({r['wall_time_s']:.0f} s)")
    return 0
