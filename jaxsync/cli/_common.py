"""Argument types shared by the commands."""

from __future__ import annotations

import argparse

from jaxsync.control.names import ALL_CONTROLLERS
from jaxsync.control.names import CONTROLLERS as CONTROLLER_NAMES

# exit statuses beside 0 (done), 2 (bad input), 3 (internal error) and 130 (interrupted)
EXIT_DROPPED = 4  # the object was dropped: compare (files written) or tune (by the start, nothing tuned)
EXIT_SIM_TO_SIM = 5  # compare --mujoco-check: MuJoCo C and MJX disagree (files written)
EXIT_UNSTABLE = 6  # compare: a controller's pad forces chattered (unstable at these gains; files written)


def positive(kind):
    """An argparse type: ``kind(text)``, which must be > 0."""

    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        if v == float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        return v

    return parse


def controller_list(minimum: int = 1, known=CONTROLLER_NAMES):
    """An argparse type: comma-separated controller names, each ``known``,
    none twice, at least ``minimum``."""

    def parse(text):
        names = [n.strip() for n in text.split(",") if n.strip()]
        unknown = [n for n in names if n not in known]
        if unknown:
            raise argparse.ArgumentTypeError(f"unknown controller(s) {', '.join(unknown)}; known: {', '.join(known)}")
        if len(set(names)) != len(names):
            raise argparse.ArgumentTypeError(f"a controller is named twice in {text!r}")
        if len(names) < minimum:
            raise argparse.ArgumentTypeError(f"name at least {minimum} controllers, got {text!r}")
        return names

    return parse


def add_controller_argument(p: argparse.ArgumentParser, default: str = "synchronous", position: bool = False) -> None:
    """--controller; ``position``: also the controllers of position-controlled arms only (ros2_admittance)."""
    p.add_argument(
        "--controller",
        default=default,
        choices=list(ALL_CONTROLLERS if position else CONTROLLER_NAMES),
        help=f"the controller ({default}; docs/controller.md)",
    )


def add_model_argument(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--model", default=None, help="MJCF file in jaxsync's convention (default: the paper model)")
    g.add_argument(
        "--robot",
        default=None,
        metavar="FILE",
        help="robot file (YAML, docs/robots.md): any dual-arm robot from its own MJCF, the task scene composed "
        "around it",
    )
    p.add_argument(
        "--no-visual", action="store_true", help="with --robot: load without the robot's meshes (missing files)"
    )


def add_gains_argument(p: argparse.ArgumentParser, help: str, positional: bool = False) -> None:
    """``--gains`` (or a positional ``gains``) and ``--any-model``: gains files record the
    model they were tuned on, and a command refuses them on another one unless told."""
    if positional:
        p.add_argument("gains", nargs="?", default=None, help=help)
    else:
        p.add_argument("--gains", default=None, help=help)
    p.add_argument(
        "--any-model",
        action="store_true",
        help="use gains recorded as tuned on another model (robot file or MJCF) than the one loaded",
    )


def model_source(args) -> str | None:
    """The model a command loads: --robot's file, --model's, or None (the paper model)."""
    return getattr(args, "robot", None) or getattr(args, "model", None)


def model_options(args) -> dict:
    """load_model's keyword options from the model flags."""
    return {"visual": not getattr(args, "no_visual", False)}


def add_convergence_arguments(p: argparse.ArgumentParser) -> None:
    """When a tuning run has converged (``Loop.plateau_tol``, ``plateau_validations``; docs/tuning.md)."""
    p.add_argument(
        "--plateau-tol",
        type=float,
        default=0.0,
        metavar="REL",
        help="also converged, and stopped before the cap, when the validation figure moved by at most this "
        "share over the last --plateau-validations validations (0, off: L-BFGS's own convergence only; "
        "docs/convergence.md)",
    )
    p.add_argument(
        "--plateau-validations",
        type=positive(int),
        default=4,
        metavar="N",
        help="the validations the plateau spans (4: 20 iterations at --validate-every 5)",
    )


def add_distributed_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of a multi-process run (jaxsync.runtime.distributed, docs/scaling.md)."""
    g = p.add_argument_group(
        "multi-process runs (JAX's distributed runtime; docs/scaling.md)",
        "Start one process per host or GPU, each with the same command and its own --process-id, or let "
        "JAX detect the cluster (--distributed-auto under SLURM or Open MPI). --out must be on a file system "
        "every process sees.",
    )
    g.add_argument(
        "--coordinator", default=None, metavar="HOST:PORT", help="process 0's address ($JAXSYNC_COORDINATOR)"
    )
    g.add_argument("--num-processes", default=None, help="how many processes take part ($JAXSYNC_NUM_PROCESSES)")
    g.add_argument("--process-id", default=None, help="this process's index, 0 .. N-1 ($JAXSYNC_PROCESS_ID)")
    g.add_argument(
        "--distributed-auto",
        action="store_true",
        help="join a multi-process run that JAX detects from the cluster's environment (SLURM, Open MPI, ...)",
    )
