"""The position-stack flags every rolling-out command shares: --actuation,
--control-rate, --delay, --ros-distro, and in the drawn commands
--servo-spread and --ft-filter."""

from __future__ import annotations

import argparse

from jaxsync.cli._common import model_source, positive
from jaxsync.control.names import DEFAULT_DISTRO, DISTROS


def add_stack_arguments(p: argparse.ArgumentParser, drawn: bool = False) -> None:
    """--actuation, --delay, --control-rate: the arms' stack (``jaxsync.sim.actuation.Stack``);
    ``drawn`` (commands whose scenarios are randomised): --servo-spread too."""
    p.add_argument(
        "--actuation",
        choices=["torque", "position"],
        default="torque",
        help="torque: joint torque motors (default); position: joint position commands through the robot's servo",
    )
    p.add_argument(
        "--delay",
        default=None,
        metavar="N|LO:HI",
        help="control periods a position command waits before the servo acts on it (default: the robot file's "
        "delay, else 0; a range where scenarios are drawn)",
    )
    p.add_argument(
        "--control-rate",
        type=positive(float),
        default=None,
        metavar="HZ",
        help="the controller's rate; must divide the physics rate (default: the physics rate, 500 Hz)",
    )
    p.add_argument(
        "--ros-distro",
        choices=list(DISTROS),
        default=DEFAULT_DISTRO,
        help=f"controller ros2_admittance: the ros2_controllers release whose admittance rule runs ({DEFAULT_DISTRO})",
    )
    if drawn:
        p.add_argument(
            "--servo-spread",
            type=float,
            default=0.0,
            metavar="SHARE",
            help="position arms: every scenario's servo gains scaled by 1 +- SHARE, drawn (0; e.g. 0.3)",
        )
        p.add_argument(
            "--ft-filter",
            default="1",
            metavar="A|LO:HI",
            help="position arms: the F/T filter coefficient every controller reads the wrench through (the "
            "admittance rule's), or a range drawn log-uniform per scenario (1: unfiltered; e.g. 0.05:1)",
        )


def stack_of(args):
    """The parsed stack flags as a ``Stack`` (a JaxsyncError names a bad one)."""
    from jaxsync.sim.actuation import Stack  # here, not at the top: `jaxsync --help` stays fast

    return Stack.of(args.actuation, args.control_rate, delay_text(args), args.ros_distro)


def delay_text(args, actuation: str | None = None) -> str:
    """--delay as given, else the robot file's delay for position-controlled arms, else "0"."""
    from jaxsync.sim.actuation import robot_delay  # here, not at the top: `jaxsync --help` stays fast

    if args.delay is not None:
        return args.delay
    if (actuation or args.actuation) != "position":
        return "0"
    return robot_delay(model_source(args), args.control_rate)
