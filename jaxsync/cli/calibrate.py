"""``jaxsync calibrate``: each joint's servo and the command delay, fitted to a rosbag2 recording."""

from __future__ import annotations

import argparse
import sys

from jaxsync._errors import ConfigError
from jaxsync.cli._common import add_model_argument, model_options, model_source, positive


def _names(text):
    return [s for s in text.split(",") if s] if text else None


def run(args: argparse.Namespace) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.calibrate.jobs import calibrate_job
    from jaxsync.physics.model import load_model

    lo, _, hi = args.delays.partition(":")
    try:
        delays = range(int(lo), int(hi or lo) + 1)
    except ValueError:
        msg = f"delays must be N or LO:HI control periods, got {args.delays!r}"
        raise ConfigError(msg, inputs=("delays",)) from None
    if not delays or delays.start < 0 or delays.stop > 9:
        raise ConfigError(f"delays must be N or LO:HI with 0 <= LO <= HI <= 8, got {args.delays!r}", inputs=("delays",))
    fields = ("stiffness", "damping") + tuple(_names(args.fit) or ())
    model = load_model(model_source(args), **model_options(args))
    out = calibrate_job(
        args.out, model, args.bag, state_topic=args.state_topic, command_topic=_topics(args.command_topic),
        joints=_names(args.joints), command_joints=_names(args.command_joints), min_samples=args.min_samples,
        report=not args.no_report, delays=delays, fields=fields, window=args.window, timestep=args.timestep,
        wrench_topics=tuple(_names(args.wrench_topics) or ()), force=args.force,
        structures=_names(args.structures),
        progress=lambda text: print(f"  {text}", file=sys.stderr, flush=True),
    )  # fmt: skip
    cal = out["calibration"]
    print(f"{args.bag}: {out['duration_s']:.1f} s, {out['state_samples']} joint states, {cal.windows} windows, "
          f"fitted in {cal.seconds:.0f} s")  # fmt: skip
    margin = cal.structure_margin
    versus = ", ".join(f"{k}: {v:.4g}" for k, v in cal.structure_costs.items())
    print(
        f"servo structure: {cal.structure}"
        + (f" (the next {1 + margin:.3g}x its cost on held-out windows: {versus})" if margin is not None else "")
    )
    print(f"delay: {cal.delay} control periods of {cal.period * 1000:.3g} ms "
          f"(cost by delay: {', '.join(f'{k}: {v:.4g}' for k, v in cal.delay_costs.items())})")  # fmt: skip
    print(f"{'joint':<22}{'stiffness N m/rad':>28}{'damping N m s/rad':>26}{'RMS error mrad':>22}")
    for k, name in enumerate(cal.joints):
        ks, bs = cal.intervals.get("stiffness"), cal.intervals.get("damping")
        print(f"{name:<22}{cal.nominal.stiffness[k]:>9.4g} -> {cal.fitted.stiffness[k]:<8.5g} +-{ks[k]:<7.2g}"
              f"{cal.nominal.damping[k]:>8.4g} -> {cal.fitted.damping[k]:<7.4g} +-{bs[k]:<6.2g}"
              f"{cal.rms_before[k] * 1e3:>9.3f} -> {cal.rms_after[k] * 1e3:.3f}")  # fmt: skip
    ef = cal.efforts
    if ef is not None:
        worst = float(ef.saturated.max())
        limit = f"; up to {worst:.0%} of a joint's samples at its torque limit (left out)" if worst else ""
        print(f"joint efforts: the {ef.structure} servo at delay {ef.delay}; stiffness "
              f"{', '.join(f'{v:.4g}' for v in ef.stiffness)} N m/rad, damping "
              f"{', '.join(f'{v:.4g}' for v in ef.damping)} N m s/rad{limit}")  # fmt: skip
        if cal.from_efforts:
            print(f"gains from the efforts (the motion leaves them open): {', '.join(cal.from_efforts)}")
    if out["noise"] is not None:
        print(f"wrist sensors' noise while still: {out['noise'].force_noise:.4g} N, {out['noise'].torque_noise:.4g} "
              f"N m ({out['noise'].still_s:.1f} s still)")  # fmt: skip
    print(
        f"wrote {args.out}/calibration.yaml (the robot-file lines), calibration.json, calibration.png"
        + ("" if args.no_report else ", report/report.html")
    )
    for problem in cal.problems:
        print(f"WARNING: {problem} (written as asked, --force)", file=sys.stderr)
    if cal.poor:
        print(
            f"WARNING: the fitted model does not explain the motion of {', '.join(cal.poor)} (RMS error over "
            f"10 % of the joint's motion): see calibration.png before using these numbers",
            file=sys.stderr,
        )
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit each joint's servo and the command delay to a rosbag2 recording (docs/calibrate.md)",
        description="Replays the recorded position commands through the position stack's servo and delay and "
        "fits each joint's servo stiffness and damping and the delay (whole control periods) with MuJoCo's "
        "identification toolbox (mujoco.sysid); writes the robot-file lines --robot reads.",
    )
    add_model_argument(p)
    p.add_argument("--bag", required=True, help="the recording: a rosbag2 folder (MCAP or SQLite) or its file")
    p.add_argument("--out", required=True, help="a new folder for the results")
    p.add_argument("--force", action="store_true",
                   help="write a calibration the recording does not support, each reason a WARNING (default: "
                   "refuse, exit 2, nothing written)")  # fmt: skip
    p.add_argument("--state-topic", default="/joint_states", help="sensor_msgs/JointState topic (/joint_states)")
    p.add_argument("--command-topic", default="/forward_position_controller/commands", metavar="TOPIC|R,L",
                   help="the commands: std_msgs/Float64MultiArray or trajectory_msgs/JointTrajectory; R,L: one "
                   "controller per arm, the right arm's topic first, each in its own arm's joint order")  # fmt: skip
    p.add_argument(
        "--joints",
        default=None,
        metavar="A,B,...",
        help="the arm joints' names in the recording, right arm then left (default: the robot file's)",
    )
    p.add_argument(
        "--command-joints",
        default=None,
        metavar="A,B,...",
        help="the order of a Float64MultiArray's entries (the controller's joints; default --joints)",
    )
    p.add_argument("--wrench-topics", default=None, metavar="R,L",
                   help="each wrist sensor's WrenchStamped topic, right arm's first: their noise")  # fmt: skip
    p.add_argument("--delays", default="0:4", metavar="N|LO:HI", help="candidate delays, control periods (0:4)")
    p.add_argument("--fit", default=None, metavar="FIELDS",
                   help="also fit joint_damping, frictionloss and/or armature (comma-separated)")  # fmt: skip
    p.add_argument("--structures", default=None, metavar="NAMES",
                   help="candidate servo structures, comma-separated: as_written (MuJoCo's <position>), "
                        "weight_compensated, feedforward (weight-compensated, the command's velocity fed forward); "
                        "each fitted, the best on held-out windows kept (default: all three)")  # fmt: skip
    p.add_argument("--window", type=positive(float), default=0.5, help="seconds per window (0.5)")
    p.add_argument(
        "--timestep",
        type=positive(float),
        default=None,
        help="the replay's physics step, s (default: the model's; finer where the servo is fast for it)",
    )
    p.add_argument("--min-samples", type=int, default=500, help="fewest messages per topic (500)")
    p.add_argument("--no-report", action="store_true", help="skip the toolbox's HTML report")
    p.set_defaults(func=run)


def _topics(text: str):
    """--command-topic: one topic, or "R,L" (right arm's, left arm's) as a pair."""
    names = _names(text) or []
    if len(names) == 2:
        return tuple(names)
    if len(names) != 1:
        raise ConfigError(f"command_topic must be one topic or two, R,L (right arm's first), got {text!r}",
                          inputs=("command_topic",))  # fmt: skip
    return names[0]
