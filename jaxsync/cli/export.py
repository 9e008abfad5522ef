"""``jaxsync export``: gains out of the simulator (YAML, JSON, ros2_control's admittance controller)."""

from __future__ import annotations

import sys

from jaxsync.cli._common import (
    ALL_CONTROLLERS,
    add_gains_argument,
    add_model_argument,
    model_options,
    model_source,
    positive,
)
from jaxsync.cli._stack import delay_of, parse_ft_filter
from jaxsync.io.export import COMMAND_INTERFACES, COMPLIANCE_FRAMES, DISTROS, FORMATS
from jaxsync.io.export_gains import export_gains
from jaxsync.io.golden import golden_job


def run(args) -> int:
    if args.format == "golden":
        return _golden(args)
    given = (("--steps", args.steps), ("--control-rate", args.control_rate))
    given += (("--controller", None if args.format == "ros2-admittance" else args.controller),)
    given += (("--delay", None if args.delay in (None, "0") or args.format == "ros2-admittance" else 1),)
    given += (("--ft-filter", None if args.ft_filter == "1" or args.format == "ros2-admittance" else 1),)
    if any(v is not None for _, v in given):
        flags = ", ".join(f for f, v in given if v is not None)
        print(f"jaxsync export: error: {flags}: not for --format {args.format} (--steps, --control-rate: golden "
              "only; --controller, --delay, --ft-filter: ros2-admittance and golden)", file=sys.stderr)  # fmt: skip
        return 2
    r = export_gains(
        args.gains, args.format, args.out, model=model_source(args), **model_options(args), distro=args.ros_distro,
        command_interfaces=[x.strip() for x in args.command_interfaces.split(",") if x.strip()],
        any_model=args.any_model, actuation=args.actuation or "torque", force=args.force,
        compliance_at=args.compliance_at, ft_filter=parse_ft_filter(args.ft_filter, one=True)[0],
        controller=args.controller, delay=delay_of(args, "position"), log=lambda line: print(line, file=sys.stderr),
    )  # fmt: skip
    print(f"exported {r.kind} from {r.origin} as {args.format}: " + ", ".join(r.paths))
    print("read back: " + ("the same gains, bit for bit" if r.same else "DIFFERENT gains"))
    for line in r.notes:
        print(f"note: {line}")
    return 0 if r.same else 1


def _golden(args) -> int:
    r = golden_job(
        args.gains,
        args.out,
        model=model_source(args),
        **model_options(args),
        controller=args.controller,
        steps=1000 if args.steps is None else args.steps,
        actuation=args.actuation or "position",
        control_rate=args.control_rate,
        delay=delay_of(args, args.actuation or "position"),
        distro=args.ros_distro,
        any_model=args.any_model,
        ft_filter=parse_ft_filter(args.ft_filter, one=True)[0],
    )
    d = r.delay
    print(f"wrote {r.controller}'s golden files ({d} period{'s' * (d != 1)} of delay): " + ", ".join(r.paths))
    said = "gives the recorded outputs" if r.exact else "DIFFERS from the recorded outputs"
    print(f"replayed: jaxsync's step on the recorded inputs {said} (largest difference {r.worst:.3g})")
    return 0 if r.exact else 1


def add_parser(subparsers):
    p = subparsers.add_parser(
        "export",
        help="write gains for other tools: yaml, json (with units), ros2-admittance (ros2_control)",
        description="Export a gains file (jaxsync tune's gains.json, a schedule, or an earlier export) as YAML "
        "or JSON with every gain's paper symbol and unit, or as ros2_controllers admittance_controller "
        "parameter files (one per arm) plus the synchronisation gains; each export reads back "
        "(jaxsync compare --gains takes it). See docs/export.md.",
    )
    add_gains_argument(
        p,
        "gains file (JSON, or an export: gains.yaml, a ros2-admittance folder); without it, the default "
        "gains of --robot's robot (or of the paper model)",
        positional=True,
    )
    p.add_argument(
        "--format",
        required=True,
        choices=[*FORMATS, "golden"],
        help="output format; golden: a rollout's control periods, what the controller read and wrote, for a "
        "port's unit test (docs/golden.md)",
    )
    p.add_argument(
        "--actuation",
        choices=["torque", "position"],
        default=None,
        help="without a gains file: the default gains of this stack (position: joint commands through the "
        "robot's servo) (torque; golden: position, the only one it records)",
    )
    add_model_argument(p)
    p.add_argument(
        "--ros-distro",
        default="jazzy",
        choices=list(DISTROS),
        help="ros2-admittance: the ROS 2 release the files are for (jazzy); Rolling applies the mass in the "
        "control frame, the others per axis of kinematics.base",
    )
    p.add_argument(
        "--command-interfaces",
        default="position",
        help=f"ros2-admittance: the joint command interfaces, comma-separated, of {list(COMMAND_INTERFACES)} "
        "(position)",
    )
    p.add_argument(
        "--compliance-at",
        choices=list(COMPLIANCE_FRAMES),
        default="pad",
        help="ros2-admittance: the frame the controller's compliance is centred at: a pad link the files name and "
        "pad_links.urdf fixes to the flange, where jaxsync simulated it (default), or the flange link",
    )
    p.add_argument(
        "--ft-filter",
        default="1",
        metavar="A",
        help="ros2-admittance: ft_sensor.filter_coefficient, the F/T filter the gains were tuned with; golden: the "
        "one the recorded scenario runs (1: unfiltered)",
    )
    force_help = "ros2-admittance: write gains the rule would run unstably or within its margin, with a WARNING"
    p.add_argument("--force", action="store_true", help=force_help + " in each file (refused otherwise)")
    g = p.add_argument_group("golden", "the rollout --format golden records (MuJoCo C, the comparison scenario)")
    g.add_argument("--steps", type=positive(int), default=None, help="control periods recorded (1000)")
    g.add_argument(
        "--controller",
        default=None,
        choices=list(ALL_CONTROLLERS),
        help="golden: the controller recorded (the one the gains file was tuned for, else synchronous); "
        "ros2-admittance: the one the files configure (the gains file's; the coupling family's gains need "
        "ros2_coupled or ros2_coupled_direct)",
    )
    g.add_argument(
        "--delay",
        default=None,
        metavar="N|LO:HI",
        help="control periods of command delay (the robot file's, else 0); ros2-admittance: the delays a coupled "
        "loop is checked at",
    )
    g.add_argument("--control-rate", type=positive(float), default=None, metavar="HZ", help="(the physics rate)")
    p.add_argument("--out", default="results/export", help="output folder (results/export)")
    p.set_defaults(func=run)
    return p
