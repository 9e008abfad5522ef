"""``jaxsync export``: gains out of the simulator (YAML, JSON, ros2_control's admittance controller)."""

from __future__ import annotations


def run(args) -> int:
    from jaxsync.control import gains as _gains
    from jaxsync.io import export as _export
    from jaxsync.io import gains_file

    # the input is checked before anything is written
    gains = gains_file.load(args.gains)
    paths = _export.export(gains, args.format, args.out)
    back = gains_file.load(paths[0] if args.format != "ros2-admittance" else args.out)
    same = all(
        bool((abs(a - b) <= 1e-12 * abs(b) + 1e-300).all()) for a, b in zip(_leaves(back), _leaves(gains), strict=True)
    )
    kind = "a gain schedule" if not isinstance(gains, _gains.Gains) else "constant gains"
    print(f"exported {kind} from {args.gains} as {args.format}: " + ", ".join(paths))
    print("read back: " + ("the same gains (relative difference <= 1e-12)" if same else "DIFFERENT gains"))
    if args.format == "ros2-admittance":
        for line in _export.notes(gains):
            print(f"note: {line}")
    return 0 if same else 1


def _leaves(g):
    import jax
    import numpy as np

    return [np.asarray(v, dtype=float) for v in jax.tree_util.tree_leaves(g)]


def add_parser(subparsers):
    from jaxsync.io.export import FORMATS

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
