"""``jaxsync export``: gains out of the simulator (YAML, JSON, ros2_control's admittance controller)."""

from __future__ import annotations

from jaxsync.control import gains as _gains
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io.export import FORMATS


def run(args) -> int:
    # the input is checked before anything is written
    gains = gains_file.load(args.gains)
    paths = _export.export(gains, args.format, args.out)
    back = gains_file.load(paths[0] if args.format != "ros2-admittance" else args.out)
    same = gains_file.same_gains(back, gains)
    kind = "a gain schedule" if not isinstance(gains, _gains.Gains) else "constant gains"
    print(f"exported {kind} from {args.gains} as {args.format}: " + ", ".join(paths))
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
    p.add_argument("gains", help="gains file (JSON, or an export: gains.yaml, a ros2-admittance folder)")
    p.add_argument("--format", required=True, choices=list(FORMATS), help="output format")
    p.add_argument("--out", default="results/export", help="output folder (results/export)")
    p.set_defaults(func=run)
    return p
