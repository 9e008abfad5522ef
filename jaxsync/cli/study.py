"""``jaxsync study``: every controller tuned the same way under the same compliance bound."""

from __future__ import annotations

import argparse

from jaxsync.cli._common import (
    ALL_CONTROLLERS,
    CONTROLLER_NAMES,
    add_convergence_arguments,
    add_model_argument,
    controller_list,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import add_stack_arguments, delay_of, parse_ft_filter


def _numbers(kind):
    """An argparse type: comma-separated numbers of ``kind`` (argparse names the option in its message)."""

    def parse(text):
        try:
            values = tuple(kind(t) for t in text.split(",") if t.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
        if not values:
            raise argparse.ArgumentTypeError(f"name at least one, got {text!r}")
        return values

    return parse


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.optimize.studies import study as _study
    from jaxsync.optimize.studies import study_report as _report
    from jaxsync.physics.model import load_model

    cfg = _study.StudyConfig(
        controllers=tuple(args.controllers),
        bounds=args.bounds,
        seeds=args.seeds,
        iterations=args.iterations,
        batch=args.batch,
        method=args.method,
        task=args.task,
        heldout_batch=args.heldout,
        validation_batch=args.validation_batch,
        validate_every=args.validate_every,
        plateau_tol=args.plateau_tol,
        plateau_validations=args.plateau_validations,
        bootstrap=args.bootstrap,
        grip_spread=args.grip_spread,
        actuation=args.actuation,
        control_rate=args.control_rate,
        distro=args.ros_distro,
        delay=delay_of(args),
        servo_spread=args.servo_spread,
        ft_filter=parse_ft_filter(args.ft_filter),
    ).validate()  # every input is checked before anything is written or compiled
    model = load_model(model_source(args), **model_options(args))
    n = len(cfg.controllers) * len(cfg.bounds) * len(cfg.seeds)
    print(
        f"study: {', '.join(cfg.controllers)}; bounds x {', '.join(map(str, cfg.bounds))}; seeds "
        f"{', '.join(map(str, cfg.seeds))}: {n} tuning runs of {cfg.tuning.loop.iterations} "
        f"{cfg.tuning.method.name} iterations, each scored on {cfg.tuning.data.heldout_batch} held-out scenarios",
        flush=True,
    )
    report = _study.run_study(
        model, cfg, args.out, resume=args.resume, restart=args.restart, report_only=args.report_only
    )
    for line in _report.table(report):
        print(line)
    if report["runs_done"] < report["runs"]:
        print(f"{report['runs_done']} of {report['runs']} tuning runs done: --resume continues the study")
    print(f"results in {args.out}: {', '.join(_report.FILES)}, runs/ ({report['wall_time_s'] / 60:.1f} min)")
    return 0


def add_parser(subparsers):
    p = subparsers.add_parser(
        "study",
        help="the fair comparison: every controller tuned the same way, under the same compliance bound",
        description="Tune each controller with the same method, budget, training seeds and cost, under "
        "each compliance bound (factors of the default classical controller's first-impact peak and "
        "apparent normal stiffness), and score all of them on one held-out set: medians and quartiles "
        "per controller and bound, ratios with bootstrap 95 % intervals, a Pareto plot. Resumable: "
        "each tuning run is kept (docs/study.md).",
    )
    p.add_argument(
        "--controllers",
        type=controller_list(minimum=2, known=ALL_CONTROLLERS),
        default=list(CONTROLLER_NAMES),
        help=f"comma-separated controllers (default all: {','.join(CONTROLLER_NAMES)}; ros2_admittance, "
        "ros2_controllers' admittance rule as deployed, with --actuation position)",
    )
    p.add_argument(
        "--bounds",
        type=_numbers(float),
        default=(0.7, 1.0, 1.5),
        help="compliance bounds as factors of the default classical controller's (0.7,1,1.5)",
    )
    p.add_argument("--seeds", type=_numbers(int), default=(0, 1, 2), help="training seeds (0,1,2)")
    p.add_argument("--iterations", type=positive(int), default=10, help="the cap on iterations per tuning run (10)")
    add_convergence_arguments(p)
    p.add_argument("--batch", type=positive(int), default=2, help="training scenarios per iteration (2)")
    p.add_argument("--method", default="lbfgs", help="tuning method, as jaxsync tune's --method (lbfgs)")
    p.add_argument("--task", default="full", choices=["full", "short"], help="training task (full)")
    p.add_argument("--heldout", type=positive(int), default=32, help="held-out scenarios (32)")
    p.add_argument("--validation-batch", type=positive(int), default=8, help="validation scenarios (8)")
    p.add_argument("--validate-every", type=int, default=5, help="iterations between validations (5)")
    p.add_argument("--bootstrap", type=positive(int), default=2000, help="bootstrap resamples (2000)")
    p.add_argument(
        "--grip-spread",
        type=float,
        default=0.2,
        help="the desired grip force randomised +- this share in every scenario (0.2: 8 to 12 N)",
    )
    p.add_argument("--out", default="results/study", help="output folder (results/study)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the study in --out (adding any new --controllers, --bounds or --seeds)",
    )
    p.add_argument("--restart", action="store_true", help="discard the study in --out and start over")
    p.add_argument(
        "--report-only",
        action="store_true",
        help="write the report of the runs finished so far and tune nothing (the same settings as the study's)",
    )
    add_stack_arguments(p, drawn=True)
    add_model_argument(p)
    p.set_defaults(func=run, interrupted_hint="finished tuning runs are kept; run again with --resume to continue")
    return p
