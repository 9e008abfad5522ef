"""``jaxsync export``: gains out of the simulator (YAML, JSON, ros2_control's admittance controller)."""

from __future__ import annotations

from jaxsync._errors import ConfigError
from jaxsync.cli._common import add_gains_argument, add_model_argument, model_options, model_source
from jaxsync.control import gains as _gains
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io.export import COMMAND_INTERFACES, DISTROS, FORMATS

ROS2_CONTROLLERS = ("classical", "synchronous")  # the laws a ros2-admittance export runs


def run(args) -> int:
    # the input is checked before anything is written
    source = model_source(args)
    tuned_for = gains_file.controller_of(args.gains) if args.gains is not None else None
    if args.format == "ros2-admittance" and tuned_for not in (None, *ROS2_CONTROLLERS):
        raise ConfigError(
            f"--gains {args.gains} was tuned for the {tuned_for} controller, which ros2_controllers' admittance "
            f"controller cannot run (it is a per-arm admittance: the {' and '.join(ROS2_CONTROLLERS)} laws, the "
            "latter with synchronisation.yaml); export it as yaml or json"
        )
    target, model = None, None
    if source is not None or args.format == "ros2-admittance" or args.gains is None:
        # the library is imported here, not at the top: `jaxsync --help` stays fast
        from jaxsync.physics.model import load_model

        model = load_model(source, **model_options(args))
        if args.gains is not None:  # gains tuned on another robot would be written with this one's names
            gains_file.check_model(args.gains, model, args.any_model)
        if args.format == "ros2-admittance":
            interfaces = tuple(x.strip() for x in args.command_interfaces.split(",") if x.strip())
            target = _export.ros2_target(
                model.mj_model, model.robot, distro=args.ros_distro, command_interfaces=interfaces
            )
    gains = gains_file.load(args.gains) if args.gains is not None else _gains.default_gains(model)
    paths = _export.export(gains, args.format, args.out, target)
    back = gains_file.load(paths[0] if args.format != "ros2-admittance" else args.out)
    same = gains_file.same_gains(back, gains)
    kind = "a gain schedule" if not isinstance(gains, _gains.Gains) else "constant gains"
    what = args.gains if args.gains is not None else f"the default gains of {source or 'the paper model'}"
    print(f"exported {kind} from {what} as {args.format}: " + ", ".join(paths))
    print("read back: " + ("the same gains (relative difference <= 1e-12)" if same else "DIFFERENT gains"))
    if args.format == "ros2-admittance":
        for line in _export.notes(gains):
            print(f"note: {line}")
    return 0 if same else 1


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
    add_model_argument(p)
    p.add_argument(
        "--ros-distro",
        default="jazzy",
        choices=list(DISTROS),
        help="ros2-admittance: the ROS 2 release the files are for (jazzy: also Kilted and Rolling) (jazzy)",
    )
    p.add_argument(
        "--command-interfaces",
        default="position",
        help=f"ros2-admittance: the joint command interfaces, comma-separated, of {list(COMMAND_INTERFACES)} "
        "(position)",
    )
    p.add_argument("--out", default="results/export", help="output folder (results/export)")
    p.set_defaults(func=run)
    return p
