"""``jaxsync export``: gains out of the simulator (YAML, JSON, ros2_control's admittance controller)."""

from __future__ import annotations

from jaxsync.cli._common import add_gains_argument, add_model_argument, model_options, model_source
from jaxsync.io.export import COMMAND_INTERFACES, DISTROS, FORMATS
from jaxsync.io.export_gains import export_gains


def run(args) -> int:
    r = export_gains(
        args.gains,
        args.format,
        args.out,
        model=model_source(args),
        **model_options(args),
        distro=args.ros_distro,
        command_interfaces=[x.strip() for x in args.command_interfaces.split(",") if x.strip()],
        any_model=args.any_model,
        actuation=args.actuation,
        force=args.force,
    )
    print(f"exported {r.kind} from {r.origin} as {args.format}: " + ", ".join(r.paths))
    print("read back: " + ("the same gains, bit for bit" if r.same else "DIFFERENT gains"))
    for line in r.notes:
        print(f"note: {line}")
    return 0 if r.same else 1


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
    p.add_argument("--format", required=True, choices=list(FORMATS), help="output format")
    p.add_argument(
        "--actuation",
        choices=["torque", "position"],
        default="torque",
        help="without a gains file: the default gains of this stack (position: joint commands through the "
        "robot's servo) (torque)",
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
        "--force",
        action="store_true",
        help="ros2-admittance: write gains the admittance rule would run unstably or within its margin, with a "
        "WARNING in each file (refused otherwise)",
    )
    p.add_argument("--out", default="results/export", help="output folder (results/export)")
    p.set_defaults(func=run)
    return p
