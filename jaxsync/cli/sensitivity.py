"""``jaxsync sensitivity``: how each headline metric responds to every gain, from reverse passes."""

from __future__ import annotations

import time

from jaxsync.cli._common import (
    add_controller_argument,
    add_gains_argument,
    add_model_argument,
    model_options,
    model_source,
    positive,
)


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.control import gains as _gains
    from jaxsync.io import gains_file
    from jaxsync.optimize.studies import sensitivity as sens
    from jaxsync.physics.model import load_model
    from jaxsync.sim.scenario import default_scenario, short_task

    # every input is checked before anything is written
    model = load_model(model_source(args), **model_options(args))
    if args.gains:
        gains_file.check_model(args.gains, model, args.any_model)
    gains = gains_file.load_constant(args.gains, "jaxsync sensitivity") if args.gains else _gains.default_gains(model)
    base = short_task(model) if args.task == "short" else default_scenario(model)
    duration = args.duration if args.duration is not None else (2.0 if args.task == "short" else 4.0)
    sens.check_duration(base, duration, "--duration", f"the {args.task} task")
    where = "the gains of " + args.gains if args.gains else "the default gains"
    t0 = time.perf_counter()
    s = sens.study(
        model,
        gains,
        base,
        batch=args.batch,
        seed=args.seed,
        duration=duration,
        out=args.out,
        at=where,
        log=lambda m: print(m, flush=True),
        controller=args.controller,
    )
    print(sens.table(s))
    dt = time.perf_counter() - t0
    print(f"results in {args.out}: sensitivity.csv, sensitivity.json, sensitivity.png ({dt:.0f} s)")
    return 0


def add_parser(subparsers):
    p = subparsers.add_parser(
        "sensitivity",
        help="elasticity of each headline metric to every gain (reverse-mode derivatives)",
        description="At the given gains, the derivative of the settled peak resultant, the grip-force error "
        "and the synchronisation error (their smooth forms from the tuning cost) with respect to every gain, "
        "averaged over a batch of randomised scenarios, as elasticities; a table, a CSV, a JSON and a bar "
        "chart. See docs/tuning.md.",
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
    p.add_argument("--out", default="results/sensitivity", help="output folder (results/sensitivity)")
    p.set_defaults(func=run)
    return p
