"""The ``jaxsync`` command line: the root parser and the entry point.

One module per command (``info``, ``compare``, ``tune``, ``study``, ``sensitivity``, ``export``, ``sweep``, ``bench``,
``render``), each with ``add_parser(subparsers)`` and ``run(args) -> int``.
Imports run one way: the command line imports the library and
``jaxsync.optimize``; nothing in them imports the command line.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback

import jax

from jaxsync._errors import DroppedObjectError, JaxsyncError
from jaxsync.cli._common import EXIT_DROPPED
from jaxsync.io import results as _results
from jaxsync.runtime import distributed as _distributed
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags

COMMANDS = (
    "info",
    "compare",
    "tune",
    "study",
    "sensitivity",
    "export",
    "sweep",
    "bench",
    "render",
    "excite",
    "calibrate",
)


def _setup_jax(args: argparse.Namespace) -> None:
    set_xla_flags()  # before anything starts JAX's backend (a command run in-process may find it started)
    jax.config.update("jax_enable_x64", not getattr(args, "float32", False))
    enable_compilation_cache(getattr(args, "cache_dir", None))
    if hasattr(args, "coordinator"):  # a command that can run over many processes (sweep, tune)
        _distributed.initialize(args.coordinator, args.num_processes, args.process_id, args.distributed_auto)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable dual-arm contact-force synchronous control with JAX and MuJoCo MJX.",
        epilog="Exit status: 0 done; 2 bad input (a one-line message; an output folder the run created is "
        "removed again if it stayed empty); 3 internal error; 4 the object was dropped (compare: by a controller; "
        "tune: by the starting gains in every held-out scenario, before any tuning); 5 compare --mujoco-check: "
        "MuJoCo C and MJX disagree; "
        "130 interrupted.",
    )
    parser.add_argument(
        "--cache-dir",
        default=None,
        help="JAX persistent compilation cache (default $JAXSYNC_CACHE_DIR or ~/.cache/jaxsync/xla; 'off').",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"jaxsync.cli.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _results.forget_created_dirs()
    rc = 1
    try:
        rc = _run(args)
        return rc
    finally:
        if rc != 0:  # a rejected or failed run leaves no empty output folder behind
            _results.remove_created_dirs()
            if _distributed.active():  # the other processes stop too, without waiting minutes for this one
                if sys.exc_info()[0] is not None:  # JAXSYNC_DEBUG's traceback, before leaving
                    traceback.print_exc()
                _distributed.abandon(rc)


FLAGS = {
    "learning_rate": "--lr",
    "clip_norm": "--clip",
    "max_impact_N": "--max-impact",
    "max_stiffness_N_per_m": "--max-stiffness",
    "heldout_batch": "--heldout-batch",
    "spec": "--tune",
    "frozen": "--freeze",
    "name": "--method",
    "weights": "--weight",
    "distro": "--ros-distro",
    "fmt": "--format",
}
"""The command line's flag for a library parameter, where it is not ``--`` and the name with dashes."""


def flags_text(err: JaxsyncError) -> str:
    """' (--resume, --restart)': the flags of the parameters an error names (``JaxsyncError.inputs``)."""
    if not getattr(err, "inputs", ()):
        return ""
    flags = [FLAGS.get(name, "--" + name.replace("_", "-")) for name in err.inputs]
    return " (" + ", ".join(dict.fromkeys(flags)) + ")"


def _run(args: argparse.Namespace) -> int:
    """The command, its errors as one line and an exit status."""
    try:
        _setup_jax(args)
        return args.func(args)
    except DroppedObjectError as err:
        print(f"jaxsync {args.command}: {err}{flags_text(err)}", file=sys.stderr)
        return EXIT_DROPPED
    except JaxsyncError as err:
        print(f"jaxsync {args.command}: error: {err}{flags_text(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        hint = getattr(args, "interrupted_hint", None)
        print(f"jaxsync {args.command}: interrupted" + (f" ({hint})" if hint else ""), file=sys.stderr)
        return 130
    except Exception as err:  # an unexpected failure: say what, keep the traceback opt-in
        if os.environ.get("JAXSYNC_DEBUG"):
            raise
        print(
            f"jaxsync {args.command}: internal error: {type(err).__name__}: {err}\n"
            "(set JAXSYNC_DEBUG=1 for the traceback, and please report it)",
            file=sys.stderr,
        )
        return 3


if __name__ == "__main__":
    sys.exit(main())
