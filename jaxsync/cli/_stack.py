"""The position-stack flags every rolling-out command shares: --actuation,
--control-rate, --delay, --ros-distro, and in the drawn commands
--servo-spread and --ft-filter."""

from __future__ import annotations

import argparse

from jaxsync._errors import ConfigError
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

    return Stack.of(args.actuation, args.control_rate, delay_of(args), args.ros_distro)


def _range(text, name: str, kind, allowed: str, check):
    """``"A"`` or ``"lo:hi"`` -> (lo, hi) of ``kind``, passed by the library's ``check``; a ConfigError
    names ``name``, what it takes and the text as typed."""
    parts = str(text).split(":")
    try:
        pair = (kind(parts[0]), kind(parts[-1])) if len(parts) in (1, 2) else None
    except ValueError:
        pair = None
    if pair is not None:
        try:
            return check(pair)
        except ConfigError:
            pass
    raise ConfigError(f"{name} must be {allowed}, got {text!r}", inputs=(name,))


def parse_delay(text) -> tuple[int, int]:
    """--delay ``"N"`` or ``"lo:hi"`` control periods -> (lo, hi), checked by the stack's own rule."""
    from jaxsync.sim.actuation import check_delay  # here, not at the top: `jaxsync --help` stays fast
    from jaxsync.sim.scenario import MAX_DELAY  # here, not at the top: `jaxsync --help` stays fast

    allowed = f"whole control periods N or a range lo:hi within 0..{MAX_DELAY}"
    return _range(text, "delay", int, allowed, check_delay)


def parse_ft_filter(text, one: bool = False) -> tuple[float, float]:
    """--ft-filter ``"A"`` or ``"lo:hi"`` -> (lo, hi); ``one``: a single coefficient only."""
    from jaxsync.sim.actuation import check_ft_filter  # here, not at the top: `jaxsync --help` stays fast

    lo, hi = _range(text, "ft_filter", float, "a filter coefficient A or a range lo:hi within 0.001..1 (1: "
                    "unfiltered)", check_ft_filter)  # fmt: skip
    if one and lo != hi:
        raise ConfigError(f"ft_filter: one coefficient here, got the range {text!r}", inputs=("ft_filter",))
    return lo, hi


def delay_of(args, actuation: str | None = None) -> tuple[int, int]:
    """--delay as given, else the robot file's delay for position-controlled arms, else 0."""
    from jaxsync.physics.compose import robot_delay  # here, not at the top: `jaxsync --help` stays fast

    if args.delay is not None:
        return parse_delay(args.delay)
    if (actuation or args.actuation) != "position":
        return 0, 0
    n = robot_delay(model_source(args), args.control_rate)
    return n, n
