"""``jaxsync sensitivity``: how each headline metric responds to every gain, from reverse passes."""

from __future__ import annotations

import os
import time

from jaxsync.cli._common import add_model_argument, positive


def run(args) -> int:
    import jax

    from jaxsync.control import gains as _gains
    from jaxsync.io import gains_file
    from jaxsync.io import results as _results
    from jaxsync.optimize import sensitivity as sens
    from jaxsync.optimize.scenarios import sample_scenarios
    from jaxsync.physics.model import load_model
    from jaxsync.sim.scenario import default_scenario, min_duration, short_task

    # every input is checked before anything is written
    gains = gains_file.load_constant(args.gains, "jaxsync sensitivity") if args.gains else _gains.default_gains()
    base = short_task() if args.task == "short" else default_scenario()
    duration = args.duration if args.duration is not None else (2.0 if args.task == "short" else 4.0)
    if duration < min_duration(base):
        from jaxsync._errors import ConfigError

        raise ConfigError(
            f"--duration must be at least {min_duration(base):g} s for the {args.task} task (its settled "
            f"window starts at {min_duration(base) - 0.2:g} s), got {duration:g}"
        )
    model = load_model(args.model)
    _results.ensure_writable_dir(args.out)
    scen = sample_scenarios(jax.random.key(args.seed), args.batch, base)
    print(
        f"sensitivities at {'the gains of ' + args.gains if args.gains else 'the default gains'}: "
        f"{args.batch} randomised scenarios (seed {args.seed}), {duration:g} s; one forward pass and one "
        "reverse pass per metric (the first run compiles the gradient: minutes on a small CPU)",
        flush=True,
    )
    t0 = time.perf_counter()
    s = sens.sensitivity(model, gains, scen, duration)
    dt = time.perf_counter() - t0
    print(sens.table(s))
    rows = s.rows()
    _results.write_csv(os.path.join(args.out, "sensitivity.csv"), {k: [r[k] for r in rows] for k in rows[0]})
    _results.write_json(
        os.path.join(args.out, "sensitivity.json"),
        {
            "metrics": dict(zip(sens.METRICS, s.values.tolist(), strict=True)),
            "rows": rows,
            "elasticity": "d log metric / d log gain; for k_rk, k_lk, k_rl, k_ll: d log metric / d k",
            "metric_forms": "smooth forms of the tuning cost (optimize/cost.py smooth_metrics), mean over scenarios",
            "gains": _gains.to_dict(gains),
            "batch": args.batch,
            "seed": args.seed,
            "duration_s": duration,
            "seconds": dt,
        },
    )
    sens.plot(s, os.path.join(args.out, "sensitivity.png"), title=f"{args.batch} scenarios, {duration:g} s")
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
    p.add_argument("--gains", default=None, help="gains JSON (default: the built-in gains)")
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
