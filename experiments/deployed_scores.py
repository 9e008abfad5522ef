"""Gain files scored through the controller that will run them, on a robot's position stack (docs/deploy-tuning.md).

Each gains file given as LABEL=PATH is rolled out on the robot's 16
held-out scenarios of the position stack (the tuner's held-out seed, delays
0-3 periods, servo gains +-30 %) under each controller of ``--controllers``
(e.g. jaxsync's classical law, and ros2_controllers' admittance rule that a
ros2-admittance export of the same gains runs), with the position stack's
default gains as the reference; then 4 of the scenarios on MuJoCo C.
Prints and writes each row: settled peak resultant, grip error, drops,
chatter, first impact (mean and largest), and the MuJoCo C factor over the
defaults. ``--with NAME=VALUE[,NAME=VALUE]`` (repeatable) scores every
candidate, the defaults included, again with those gains set (e.g. the
command's feed-forward, ``--with ff_acc=0.0013``); ``--no-mujoco`` skips
MuJoCo C.

    python experiments/deployed_scores.py --robot mjcf/robots/ur5e_twice.yaml \\
        --controllers classical,ros2_admittance torque=results/tc/gains.json position=results/tp/gains.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from jaxsync.control import gains as _gains
from jaxsync.control.gains import default_gains
from jaxsync.io import gains_file
from jaxsync.optimize.tuning import loss as L
from jaxsync.optimize.tuning import scenarios as S
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim import crosscheck as C
from jaxsync.sim.actuation import Stack

KEYS = ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "chattering", "nonfinite", "first_impact_peak_N")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", required=True)
    p.add_argument("--controllers", default="classical,ros2_admittance")
    p.add_argument("--out", default=None, help="write the rows here as JSON")
    p.add_argument("--with", dest="variants", action="append", default=[], metavar="NAME=VALUE[,NAME=VALUE]")
    p.add_argument("--no-mujoco", action="store_true")
    p.add_argument("gains", nargs="+", metavar="LABEL=PATH")
    args = p.parse_args()
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    stack = Stack("position", None, (0, 3))
    cfg = TuneConfig(actuation="position", delay=(0, 3), servo_spread=0.3)
    held = S.heldout_scenarios(cfg.replace(scenario=S.model_overrides(model)))
    base = default_gains(model, "position")
    cands = {"position stack's defaults": base}
    cands |= {label: gains_file.load(path) for label, path in (g.split("=", 1) for g in args.gains)}
    for variant in args.variants:
        set_to = {k: float(v) for k, v in (kv.split("=", 1) for kv in variant.split(","))}
        plain = [(label, g) for label, g in cands.items() if "=" not in label]  # not another variant's
        cands |= {f"{label}, {variant}": _gains.from_dict(set_to, g) for label, g in plain}
    rows = {}
    for controller in args.controllers.split(","):
        ev = L.make_evaluator(model, 4.0, controller, **stack.rollout_options(model))
        for label, g in cands.items():
            s = L.eval_summary(ev(g, held))
            row = {k: s[k] for k in KEYS}
            impacts = [x for x in s["metrics"]["first_impact_peak_N"] if x is not None]
            row["first_impact_max_N"] = max(impacts, default=None)
            if label != "position stack's defaults" and not s["dropped"] and not args.no_mujoco:
                c = C.sim_to_sim(model, g, base, held, 4.0, n=4, controller=controller, stack=stack, log=lambda m: None)
                row["mujoco_check"] = {k: c.get(k) for k in ("factor_mjx", "factor_mujoco", "agree", "dropped")}
            rows[f"{controller}: {label}"] = row
            print(f"{controller}: {label}", json.dumps(row, default=str), flush=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
