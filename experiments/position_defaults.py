"""Each controller at a robot's position-stack default gains, under F/T filters and changed gains (docs/deploy.md).

Rolls the position stack's default gains out on a robot's 16 held-out
scenarios (the tuner's held-out seed, delays 0-3 periods, servo gains +-30
%) under each controller of ``--controllers``, with the F/T filter every
controller there reads the force error through fixed at each coefficient
of ``--filters`` (``ft_sensor.filter_coefficient`` = a, each new sample's
weight; 1: unfiltered; ros2_controllers' default 0.05, a time constant of
about dt / a), and with the scalar gains of ``--set`` changed (e.g.
``k_rl=0.25,k_ll=0.25``). ``--gains LABEL=PATH`` (repeatable) rolls gains
files out beside the defaults; ``--delays 0,1,2,3`` runs every scenario
again at each of those delays instead of its own draw. Prints per
controller, gains, coefficient (and delay) the settled peak resultant over
the scenarios kept, the grip error, drops, non-finite runs, chatter and
the first impact, and the largest share of control steps in any
scenario with a joint at its torque limit. Deterministic: no timing.

    python experiments/position_defaults.py --robot mjcf/dual_arm.xml --filters 1,0.2,0.05
    python experiments/position_defaults.py --robot mjcf/robots/ur5e_twice.yaml --filters 1 --delays 0,1,2,3
    python experiments/position_defaults.py --robot mjcf/robots/iiwa14_pair.yaml \
        --controllers ros2_synchronous --filters 1 --set k_rl=0,k_ll=0
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from jaxsync.control.gains import default_gains
from jaxsync.io import gains_file
from jaxsync.optimize.tuning import loss as L
from jaxsync.optimize.tuning import scenarios as S
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags

# printed per row: means over the scenarios kept (neither dropped nor non-finite), and the counts
KEYS = ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "nonfinite", "chattering", "first_impact_peak_N")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="mjcf/dual_arm.xml")
    p.add_argument("--controllers", default="classical,synchronous,ros2_admittance,ros2_synchronous")
    p.add_argument("--filters", default="1,0.2,0.05")
    p.add_argument("--set", default="", metavar="NAME=VALUE,...", help="scalar gains changed from the defaults")
    p.add_argument("--gains", action="append", default=[], metavar="LABEL=PATH", help="gains files beside the defaults")
    p.add_argument("--any-model", action="store_true", help="score gains tuned on another model (robot file)")
    p.add_argument("--delays", default="", metavar="N,...", help="every scenario at each of these delays (periods)")
    args = p.parse_args()
    if any("=" not in item for item in args.gains):
        p.error(f"--gains takes LABEL=PATH, got {args.gains}")
    if args.delays and not all(d.isdigit() for d in args.delays.split(",")):
        p.error(f"--delays takes whole periods >= 0, comma-separated, got {args.delays!r}")
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    cfg = TuneConfig(actuation="position", delay=(0, 3), servo_spread=0.3)
    held = S.heldout_scenarios(cfg.replace(scenario=S.model_overrides(model)))
    delays = args.delays.split(",") if args.delays else [None]
    runs = [(float(a), d) for a in args.filters.split(",") for d in delays]
    for controller in args.controllers.split(","):
        candidates = {"defaults": default_gains(model, "position", controller)}  # ros2_synchronous: its own
        for item in args.gains:
            label, path = item.split("=", 1)
            candidates[label] = gains_file.load_for(path, model, any_model=args.any_model)
        evaluate = L.make_evaluator(model, 4.0, controller, actuation="position")
        for label, g in candidates.items():
            for item in filter(None, args.set.split(",")):
                name, value = item.split("=")
                g = g._replace(**{name: np.asarray(getattr(g, name)) * 0.0 + float(value)})
            for a, d in runs:
                scenarios = held._replace(ft_filter=np.full_like(np.asarray(held.ft_filter), a))
                if d is not None:
                    scenarios = scenarios._replace(delay=np.full_like(np.asarray(held.delay), float(d)))
                summary = L.eval_summary(evaluate(g, scenarios))
                row = {k: summary[k] for k in KEYS}
                share = [summary["metrics"][f"torque_limit_share_{arm}"] for arm in ("right", "left")]
                row["torque_limit_share_max"] = max(x for xs in share for x in xs if x is not None)
                at = "" if d is None else f" delay={d}"
                print(f"{controller} {label} a={a:g}{at} {args.set}", json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
