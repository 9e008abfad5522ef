"""What the coupling family costs the tuning gradient, against the rule alone, in one run.

The tuning cost's value_and_grad through one rollout of the short task (2 s,
the position stack, a delay of ``--delay`` periods, rematerialised scan, the
tree passes: what ``jaxsync tune`` differentiates), batch 1, float64, for
``ros2_admittance`` (the rule alone) and ``ros2_coupled`` with every channel
of the largest family on (gains, filters and the full 6x6 blocks away from
their defaults, so that no branch is constant). The gradient is taken with respect to the whole gain
pytree either way. Forward and gradient of both are timed alternately,
best of ``--repeats``, so that a change in load hits both alike; the
figure is the family's gradient time over the rule's. Writes JSON.

    python experiments/coupling_gradient_cost.py --repeats 7 --out results/coupling_gradient_cost
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from gradient_cost import time_alternately  # experiments/: the same timing harness

import jaxsync
from jaxsync.control import coupling as C


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="mjcf/dual_arm.xml")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--duration", type=float, default=2.0)
    p.add_argument("--delay", type=float, default=2.0)
    p.add_argument("--out", default="results/coupling_gradient_cost")
    args = p.parse_args()
    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    jaxsync.enable_compilation_cache()
    model = jaxsync.load_model(args.robot, visual=False)
    s = jaxsync.short_task()._replace(delay=np.float64(args.delay))
    rule = jaxsync.default_gains(model, "position", "ros2_admittance")
    rng = np.random.default_rng(0)
    family = rule._replace(
        **{f: jnp.asarray(rng.uniform(-0.2, 0.2, (2, 6))) for f in C.GAIN_FIELDS},
        **{f: jnp.asarray(rng.uniform(0.5, 0.95, (2, 6))) for f in C.FILTER_FIELDS},
        cpl_block=jnp.asarray(rng.uniform(-0.05, 0.05, (4, 2, 6, 6)) * (1.0 - np.eye(6))),
    )
    cases = {"ros2_admittance": rule, "ros2_coupled": family}
    rolls = {
        name: jaxsync.make_rollout(model, name, args.duration, remat=True, passes="tree", actuation="position")
        for name in cases
    }
    fns, times = time_alternately(rolls, cases, s, args.repeats)
    result = {
        "robot": args.robot,
        "duration_s": args.duration,
        "delay": args.delay,
        "repeats": args.repeats,
        "load_average": os.getloadavg(),
        "controllers": {},
    }
    for name, t in times.items():
        value, grad = fns[name][1](cases[name], s)
        family_grad = {f: float(jnp.max(jnp.abs(getattr(grad, f)))) for f in C.FIELDS}
        if name == "ros2_coupled" and min(family_grad.values()) == 0.0:
            raise SystemExit(f"a family gradient is 0 ({family_grad}): the figure would not time the family")
        traj = jaxsync.make_rollout(model, name, args.duration, actuation="position")(cases[name], s)
        m = jaxsync.summarize(traj, s)
        result["controllers"][name] = {
            "dropped": bool(m.dropped),
            "settled_peak_resultant_N": float(m.settled_peak_resultant_N),
            "forward_s": min(t["forward"]),
            "gradient_s": min(t["gradient"]),
            "gradient_over_forward": min(t["gradient"]) / min(t["forward"]),
            "cost": float(value),
            "largest_family_gradient": family_grad,
        }
    rc = result["controllers"]
    result["family_gradient_over_rule_gradient"] = (
        rc["ros2_coupled"]["gradient_s"] / rc["ros2_admittance"]["gradient_s"]
    )
    result["per_round_ratio"] = [
        c / r for c, r in zip(times["ros2_coupled"]["gradient"], times["ros2_admittance"]["gradient"], strict=True)
    ]
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "coupling_gradient_cost.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
