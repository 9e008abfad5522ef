"""The coupled loop's stability margin of a coupling, at each delay, on a robot.

The gains are a gains file (``--gains``) or the robot's position-stack
defaults for the rule; ``--set`` puts coupling gains on them, per channel
and pad axis, on both arms (e.g. ``cpl_other:z=-1.01,cpl_own:z=-0.14``).
Prints and writes ``jaxsync.sim.loop_stability.loop_margin`` at every delay:
the spectral radius, with the coupling x1.5, the rule alone, the verdict.

    python experiments/coupling_loop_margin.py --robot mjcf/robots/ur5e_twice.yaml \\
        --set cpl_other:z=-1.01,cpl_own:z=-0.14 --delays 0:3 --out results/loop_margin_ur5e
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

import jaxsync
from jaxsync.io import gains_file
from jaxsync.sim import loop_stability as _ls

AXES = ("x", "y", "z", "rx", "ry", "rz")


def _with(g, spec: str):
    for item in filter(None, spec.split(",")):
        name, rest = item.split(":")
        axis, value = rest.split("=")
        g = g._replace(**{name: getattr(g, name).at[:, AXES.index(axis)].set(float(value))})
    return g


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default=None, help="a robot file (the paper model without)")
    p.add_argument("--gains", default=None, help="a gains file (the rule's position-stack defaults without)")
    p.add_argument("--controller", default="ros2_coupled")
    p.add_argument("--set", default="", help="channel:axis=value,... on both arms")
    p.add_argument("--delays", default="0:3")
    p.add_argument("--out", default="results/loop_margin")
    args = p.parse_args()
    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    model = jaxsync.load_model(args.robot, visual=False) if args.robot else jaxsync.load_model()
    base = gains_file.load(args.gains) if args.gains else jaxsync.default_gains(model, "position", "ros2_admittance")
    g = _with(base, args.set)
    lo, hi = (int(x) for x in args.delays.split(":"))
    rows = []
    for delay in range(lo, hi + 1):
        start = time.perf_counter()
        r = _ls.loop_margin(model, g, args.controller, delay=delay)
        rows.append(
            {**{k: v for k, v in r._asdict().items() if k != "removed"}, "seconds": time.perf_counter() - start}
        )
        print(r.phrase, f"({rows[-1]['seconds']:.1f} s)", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "loop_margin.json"), "w") as f:
        json.dump({"robot": args.robot, "gains": args.gains, "set": args.set, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
