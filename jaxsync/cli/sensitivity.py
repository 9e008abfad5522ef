"""``jaxsync sensitivity``: how each headline metric responds to every gain, from reverse passes."""

from __future__ import annotations

from jaxsync.cli._common import (
    add_controller_argument,
    add_gains_argument,
    add_model_argument,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import add_stack_arguments, stack_of


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.optimize.studies import sensitivity as sens

    r = sens.run_sensitivity(
        model_source(args),
        gains=args.gains,
        any_model=args.any_model,
        **model_options(args),
        task=args.task,
        duration=args.duration,
        batch=args.batch,
        seed=args.seed,
        controller=args.controller,
        out=args.out,
        log=lambda m: print(m, flush=True),
        stack=stack_of(args),
    )
    print(sens.table(r.sensitivity))
    print(f"results in {args.out}: {', '.join(r.files)} ({r.seconds:.0f} s)")
    return 0


def add_parser(subparsers):
    p = subparsers.add_parser(
        "sensitivity",
        help="elasticity of each headline metric to every gain (reverse-mode derivatives)",
        description="At the given gains, the derivative of the settled peak resultant, the grip-force error "
        "and the synchronisation error (their smooth forms from the tuning cost) with respect to every gain, "
        "averaged over a batch of randomised scenarios, as elasticities; a table, a CSV, a JSON and a bar "
        "chart. See docs/sensitivity.md.",
    )
    add_model_argument(p)
    add_controller_argument(p)
    add_gains_argument(p, "gains JSON (default: the model's own)")
    p.add_argument("--batch", type=positive(int), default=8, help="randomised scenarios (8)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (0)")
    p.add_argument(
        "--task",
        default="full",
        choices=["full", "short"],
        help="the full task (default, as held out) or jaxsync.short_task() (2 s)",
    )
    p.add_argument("--duration", type=positive(float), default=None, help="rollout length, s (full 4, short 2)")
    add_stack_arguments(p)
    p.add_argument("--out", default="results/sensitivity", help="output folder (results/sensitivity)")
    p.set_defaults(func=run)
    return p
