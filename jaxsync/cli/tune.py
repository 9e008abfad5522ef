"""``jaxsync tune``: gradient-based gain tuning, evaluated on held-out scenarios before and after."""

from __future__ import annotations

import functools

from jaxsync.cli._common import (
    add_controller_argument,
    add_convergence_arguments,
    add_distributed_arguments,
    add_gains_argument,
    add_model_argument,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import add_stack_arguments, delay_of, parse_ft_filter
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.methods import BATCH_METHODS
from jaxsync.optimize.tuning.params import DEFAULT_TUNED_FOR, TUNABLE


def config_from_args(args):
    """The TuneConfig the flags describe (checked by the library)."""
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.optimize.tuning.config import Problem, TuneConfig
    from jaxsync.optimize.tuning.cost import parse_weights
    from jaxsync.optimize.tuning.params import spec_for

    names = lambda text: [t.strip() for t in text.split(",") if t.strip()] if text else []  # noqa: E731
    spec = spec_for(args.controller, names(args.tune), names(args.freeze), per_arm=args.per_arm,
                    isotropic=args.isotropic, schedule=args.per_phase)  # fmt: skip
    problem = Problem(args.controller, spec, parse_weights(args.weight), args.max_impact, args.max_stiffness)
    settings = ("iterations", "batch", "schedule", "seed", "heldout_seed", "heldout_batch", "checkpoint_every",
                "validate_every", "validation_seed", "validation_batch", "task", "popsize", "sampling",
                "plateau_tol", "plateau_validations")  # fmt: skip
    return TuneConfig(
        problem=problem,
        method=args.method,
        learning_rate=args.lr,
        clip_norm=args.clip,
        truncate_every=args.truncate_every or None,
        actuation=args.actuation,
        control_rate=args.control_rate,
        distro=args.ros_distro,
        delay=delay_of(args),
        servo_spread=args.servo_spread,
        ft_filter=parse_ft_filter(args.ft_filter),
        **{k: getattr(args, k) for k in settings},
    )


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.optimize.tuning import pipeline, starts
    from jaxsync.optimize.tuning.tune_report import summary_lines

    job = pipeline.run_tune if args.starts == 1 else functools.partial(starts.run_tune, starts=args.starts)
    summary = job(
        model_source(args),
        config_from_args(args),
        gains=args.gains,
        any_model=args.any_model,
        **model_options(args),
        out=args.out,
        resume=args.resume,
        restart=args.restart,
        mujoco_check=args.mujoco_check,
        options={k: v for k, v in vars(args).items() if k not in ("func", "interrupted_hint")},
        log=lambda m: print(m, flush=True),
    )
    if summary is not None:  # None: another process than the first of a multi-process run, which wrote nothing
        print("\n".join(summary_lines(summary, args.out)))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tune",
        help="tune the synchronisation and impedance gains by gradient through MJX rollouts",
        description="Gradient-based gain tuning on batches of randomised scenarios, evaluated on held-out "
        "scenarios before and after (docs/tuning.md).",
    )
    add_controller_argument(p, position=True)
    bound = "bound the mean first-impact peak pad force, N", "bound the apparent stiffness along the pad normal, N/m"
    p.add_argument("--max-impact", type=positive(float), metavar="N", help=f"{bound[0]} (docs/metrics.md)")
    p.add_argument("--max-stiffness", type=positive(float), metavar="N_PER_M", help=f"{bound[1]} (docs/metrics.md)")
    p.add_argument("--iterations", type=int, default=300, help="the cap on optimisation steps (300)")
    add_convergence_arguments(p)
    p.add_argument("--batch", type=int, default=4, help="randomised scenarios per step (4; per process)")
    starts = "K tuning runs on training seeds --seed, --seed+1, ..., in OUT/seed_<s>, the best validated kept (1)"
    p.add_argument("--starts", type=positive(int), default=1, metavar="K", help=starts)
    p.add_argument(
        "--method",
        default="lbfgs",
        help=f"{', '.join(BATCH_METHODS)} (one training batch at a time; lbfgs, the default, measured fastest, "
        "docs/tuning.md) or a first-order optax optimiser by name (adam, sgd, ...: a fresh batch every "
        "iteration; --lr, --schedule and --clip steer it)",
    )
    p.add_argument("--lr", type=float, default=0.05, help="first-order methods: learning rate (0.05)")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "constant"], help="first-order: (cosine)")
    p.add_argument("--clip", type=float, default=1.0, help="first-order: global-norm gradient clipping (1.0)")
    p.add_argument("--popsize", type=int, default=16, help="CMA-ES population (16)")
    tunable = f"synchronous {','.join(DEFAULT_TUNED_FOR['synchronous'])}; any of {','.join(TUNABLE)}"
    p.add_argument("--tune", help="comma-separated parameters to tune (default: the controller's own, and kp_pos on "
                   f"position-controlled arms whose servo limits the joint-command loop; {tunable})")  # fmt: skip
    p.add_argument("--freeze", help="comma-separated parameters to keep fixed")
    p.add_argument("--per-arm", action="store_true", help="separate impedance parameters per arm")
    p.add_argument("--per-phase", action="store_true", help="a gain schedule: every tuned parameter per task phase")
    p.add_argument("--isotropic", action="store_true", help="one impedance value for translations, one for rotations")
    p.add_argument(
        "--no-mujoco-check",
        dest="mujoco_check",
        action="store_false",
        help="skip rolling the gains before and after out on MuJoCo C (4 held-out scenarios; about a minute)",
    )
    p.add_argument(
        "--truncate-every",
        type=int,
        default=0,
        help="truncate backpropagation into windows of this many steps (0: the exact gradient, docs/tuning.md)",
    )
    for name, default, what in (
        ("seed", 0, "training scenarios seed"),
        ("heldout-seed", 1000, "held-out scenarios seed"),
        ("heldout-batch", 16, "held-out scenarios"),
        ("checkpoint-every", 5, "checkpoint period, iterations"),
        ("validate-every", 5, "validate the iterate every N iterations, keep the best (0: keep the last)"),
        ("validation-seed", 500, "validation scenarios seed"),
        ("validation-batch", 16, "validation scenarios"),
    ):
        p.add_argument(f"--{name}", type=int, default=default, help=f"{what} ({default})")
    task = "training task: 'full' (the 4 s task the held-out scenarios use) or 'short' (2 s) (full)"
    p.add_argument("--task", default="full", choices=["full", "short"], help=task)
    p.add_argument(
        "--sampling",
        default="stratified",
        choices=["stratified", "iid"],
        help="training batches: 'stratified' holds each scenario range's ends, 'iid' draws independently",
    )
    weights = f"a cost weight (repeatable): {', '.join(CostWeights._fields)} (docs/tuning.md)"
    p.add_argument("--weight", action="append", metavar="NAME=VALUE", help=weights)
    add_stack_arguments(p, drawn=True)
    add_gains_argument(p, "start from this gains file (default: the model's own)")
    add_model_argument(p)
    add_distributed_arguments(p)
    p.add_argument("--out", default="results/tune", help="output folder (results/tune)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out")
    p.add_argument("--restart", action="store_true", help="discard the tuning run in --out and start over")
    p.set_defaults(func=run)
