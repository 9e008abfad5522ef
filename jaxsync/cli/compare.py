"""``jaxsync compare``: the paper's comparison, classical vs synchronous on one scenario."""

from __future__ import annotations

import argparse
import sys

from jaxsync.cli._common import (
    ALL_CONTROLLERS,
    EXIT_DROPPED,
    EXIT_SIM_TO_SIM,
    EXIT_UNSTABLE,
    add_gains_argument,
    add_model_argument,
    controller_list,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import add_stack_arguments, stack_of


def run(args: argparse.Namespace) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.optimize.studies import compare as _compare
    from jaxsync.sim.crosscheck import sim_to_sim_table
    from jaxsync.sim.metrics import CHATTER_THRESHOLD_N

    r = _compare.run_comparison(
        model_source(args),
        gains=args.gains,
        any_model=args.any_model,
        **model_options(args),
        overrides={k: getattr(args, k) for k in _compare.SCENARIO_OVERRIDES},
        seed=args.seed,
        duration=args.duration,
        out=args.out,
        backend=args.backend,
        controllers=tuple(args.controllers),
        video_speed=args.video_speed if args.video else None,
        mujoco_check=args.mujoco_check,
        options={k: v for k, v in vars(args).items() if k not in ("func",)},
        stack=stack_of(args),
    )
    for line in _compare.table(r.summary):
        print(line)
    check = r.summary.get("sim_to_sim")
    if check is not None:
        for line in sim_to_sim_table(check, "these gains" if args.gains else "the default gains"):
            print(line)
    print(f"results in {args.out}: {', '.join(r.files)}")
    if r.dropped:
        print(
            "jaxsync compare: "
            + "; ".join(f"the {n} controller dropped the object at t={t:.3f} s" for n, t in r.dropped.items())
            + ": the settled metrics of a dropped object do not apply and there is no resultant ratio "
            f"(exit status {EXIT_DROPPED})",
            file=sys.stderr,
        )
        return EXIT_DROPPED
    if r.sim_to_sim_agree is False:
        print(
            "jaxsync compare: WARNING: the MuJoCo C check failed: "
            + "; ".join(check["problems"])
            + f" (exit status {EXIT_SIM_TO_SIM})",
            file=sys.stderr,
        )
        return EXIT_SIM_TO_SIM
    if r.unstable:
        print(
            "jaxsync compare: WARNING: "
            + "; ".join(
                f"the {n} controller's pad forces chattered (RMS change per step "
                f"{r.summary[n]['force_chatter_N']:.3g} N > {CHATTER_THRESHOLD_N:g} N): unstable at these gains, "
                "its force metrics mean little"
                for n in r.unstable
            )
            + f" (exit status {EXIT_UNSTABLE}; docs/metrics.md)",
            file=sys.stderr,
        )
        return EXIT_UNSTABLE
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "compare",
        help="the paper's comparison: classical vs synchronous controller on one scenario",
        description="Roll out the classical impedance and the synchronous controller with the same "
        "impedance parameters on the same scenario; write summary.json, series.csv and force plots.",
        epilog=f"Exit status: 0 done; 2 bad input; {EXIT_DROPPED} a controller dropped the object (the files are "
        "written, the drop marked in the table and plots, resultant_ratio null in summary.json); 3 internal error; "
        f"{EXIT_SIM_TO_SIM} --mujoco-check: MuJoCo C disagrees with MJX (files written); {EXIT_UNSTABLE} a "
        "controller's pad forces chattered (files written); 130 interrupted.",
    )
    p.add_argument(
        "--controllers",
        type=controller_list(minimum=2, known=ALL_CONTROLLERS),
        default=["classical", "synchronous"],
        help="comma-separated controllers to roll out, the first the reference of the ratios "
        f"(default classical,synchronous; any of {', '.join(ALL_CONTROLLERS)}; the ros2_ ones with "
        "--actuation position only)",
    )
    p.add_argument("--duration", type=positive(float), default=4.0, help="seconds simulated (default 4)")
    add_stack_arguments(p)
    p.add_argument("--grip-force", type=positive(float), default=None, help="desired grip force f_d, N (10)")
    p.add_argument("--object-mass", type=positive(float), default=None, help="object mass, kg (0.5)")
    p.add_argument(
        "--object-offset",
        type=float,
        default=None,
        help="where the object starts off the nominal grasp centre along the clamping axis, m (0.003)",
    )
    p.add_argument("--force-noise", type=float, default=None, help="wrist force noise std, N (0.1)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed (0)")
    add_gains_argument(
        p, "gains file: JSON, or a jaxsync export (gains.yaml, a ros2-admittance folder); default: the model's own"
    )
    p.add_argument("--out", default="results/compare", help="output folder (results/compare)")
    p.add_argument("--backend", default="mjx", choices=["mjx", "mujoco"], help="physics engine (mjx)")
    p.add_argument(
        "--mujoco-check",
        type=positive(int),
        nargs="?",
        const=4,
        default=None,
        metavar="N",
        help="also roll these gains and the default gains out on N (4) of jaxsync tune's held-out scenarios (4 s) "
        "on MJX and on MuJoCo C with the same jitted control law, and print both engines' metrics and improvement "
        f"factors; a WARNING and exit status {EXIT_SIM_TO_SIM} when the factors differ by more than 10 %% "
        "or an object was dropped (docs/export.md)",
    )
    add_model_argument(p)
    p.add_argument("--video", action="store_true", help="also render both rollouts side by side to a video")
    p.add_argument("--video-speed", type=positive(float), default=0.5, help="playback speed of the video (0.5)")
    p.set_defaults(func=run)
