"""``jaxsync excite``: the identification trajectory to play on the robot (docs/calibrate.md)."""

from __future__ import annotations

import argparse

from jaxsync.cli._common import add_model_argument, model_options, model_source, positive


def run(args: argparse.Namespace) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.calibrate.jobs import excite_job
    from jaxsync.physics.model import load_model

    model = load_model(model_source(args), **model_options(args))
    about = excite_job(
        args.out, model, duration=args.duration, amplitude=args.amplitude, speed=args.speed, rate=args.rate,
        chirp=tuple(args.chirp), command_topic=args.command_topic, storage=args.storage,
    )  # fmt: skip
    print(f"wrote {args.out}/excitation ({args.storage} bag), excitation.csv, excitation.yaml")
    print(f"  {about['duration_s']:.1f} s at {about['rate_Hz']:g} Hz on {about['command_topic']} "
          f"({about['message_type']}, joints in this order: {', '.join(about['joints'])})")  # fmt: skip
    print(f"  each joint in turn, both arms at once: steps of +-{about['amplitude_rad']:g} rad, then a chirp "
          f"{about['chirp_Hz'][0]:g}-{about['chirp_Hz'][1]:g} Hz; speed at most {about['largest_speed_rad_per_s']:.3f} "
          f"rad/s; the arms keep {about['arm_clearance_m'] * 1000:.0f} mm apart")  # fmt: skip
    print(f"  excites {about['excites']}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "excite",
        help="write an identification trajectory (rosbag2 + CSV) to play on the robot for jaxsync calibrate",
        description="Per-joint steps and a chirp around the grasp pose, each joint in turn (both arms at once), "
        "the other joints held: a rosbag2 of position commands to play on the robot with a stock position "
        "controller while recording its joint states (docs/calibrate.md).",
    )
    add_model_argument(p)
    p.add_argument("--out", required=True, help="a new folder for the bag, the CSV and what it excites")
    p.add_argument("--duration", type=positive(float), default=20.0, help="seconds in all (20)")
    p.add_argument("--amplitude", type=positive(float), default=0.1, help="rad about the pose (0.1)")
    p.add_argument("--speed", type=positive(float), default=0.5, help="speed cap, rad/s (0.5)")
    p.add_argument("--rate", type=positive(float), default=500.0, help="command rate, Hz (500)")
    p.add_argument("--chirp", type=positive(float), nargs=2, default=[0.5, 12.0], metavar=("F0", "F1"),
                   help="the chirp's frequencies, Hz (0.5 12)")  # fmt: skip
    p.add_argument("--command-topic", default="/forward_position_controller/commands",
                   help="the position controller's command topic (/forward_position_controller/commands)")  # fmt: skip
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="bag storage (mcap)")
    p.set_defaults(func=run)
