"""How the joint command's damped least squares leaks the carry into the pad normal (docs/deploy.md).

On position-controlled arms jaxsync's laws turn the compliant pad target
into a joint command rate through J# = (J^T J + alpha I)^-1 J^T
(``jaxsync.control.joint_space.command_rate``). Along a weak singular
direction of J (singular value s) the task-space gain is s^2 / (s^2 +
alpha), not 1: part of the planned carry velocity is lost there, and the
part of that direction that lies along the pad normal moves the pads
apart while the object is carried. jaxsync refines the planned twist's
share by one step of iterative refinement. This script scores the
position stack's default gains on a robot's 16 held-out scenarios (delays
0-3, servo gains +-30 %) under each command variant:

- ``shipped``: the command as jaxsync computes it, J# v + J# (I - J J#)
  x_plan_dot (task-space gain 1 - (alpha / (s^2 + alpha))^2 for the plan,
  still bounded near a singularity; the compliance's rates and the
  feedback through J# alone, so the command at rest is that of J# v);
- ``unrefined``: J# v alone (alpha = 0.01, ``kinematics.alpha``'s default);
- ``refined``: the whole of v refined, J# v + J# (v - J J# v);
- ``alpha_1e-4``: J# v with alpha = 1e-4.

and prints, per controller, the drops, chatter, the mean settled peak
resultant over the scenarios kept and the mean grip error. The variants
replace ``command_rate`` for jaxsync's laws in this process only
(ros2_controllers' rule in the loop keeps its own reference). Deterministic:
no timing.

    python experiments/command_leak.py --robot mjcf/robots/iiwa14_pair.yaml

``--trace N``: instead, held-out scenario N with the servo as stated under
the classical law and the variant ``--variants`` names first, every 0.05 s:
each pad's grip (normal force on the object), its contact depth (ball
radius less the distance from the ball's centre to the pad's plane), the
pads' lag behind the plan along the carry (world x) and the grip the
controller senses.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.control import joint_space as JS
from jaxsync.control import so3
from jaxsync.control.gains import default_gains
from jaxsync.optimize.tuning import scenarios as S
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim import metrics as M
from jaxsync.sim.rollout import make_rollout

SHIPPED = JS.command_rate
VARIANTS = ("shipped", "unrefined", "refined", "alpha_1e-4")


def _variant(name: str):
    if name == "shipped":
        return SHIPPED
    if name == "unrefined":
        return lambda *args, plan_vel=None, **kw: SHIPPED(*args, **kw)
    if name == "alpha_1e-4":
        return lambda *args, plan_vel=None, alpha=None: SHIPPED(*args, alpha=1e-4)

    def rate(arm, command, pos_ref, rot_ref, vel_ref, q_rest, kp, kd, kp_null, kd_null, **_):
        err = jnp.concatenate([pos_ref - arm.pad_pos, so3.rotation_error(rot_ref, arm.pad_rot)])
        v = vel_ref + (2.0 * kp / kd) * err
        return SHIPPED(arm, command, pos_ref, rot_ref, vel_ref, q_rest, kp, kd, kp_null, kd_null, plan_vel=v)

    return rate


def _in_laws_only(rate):
    """``command_rate`` for jaxsync's laws: the variant where the call carries
    the planned twist (``step_position``), the shipped one for the rule's
    reference (``ros2_loop``, no ``plan_vel``)."""

    def call(*args, **kw):
        return rate(*args, **kw) if "plan_vel" in kw else SHIPPED(*args, **kw)

    return call


def _trace(model, g, i: int) -> None:
    cfg = TuneConfig(actuation="position", delay=(0, 3), servo_spread=0.0)
    s = jax.tree_util.tree_map(lambda x: x[i], S.heldout_scenarios(cfg.replace(scenario=S.model_overrides(model))))
    mass, friction = float(s.object_mass), float(s.friction)
    print(f"scenario {i}: delay {float(s.delay):g}, object {mass:.3f} kg, friction {friction:.2f}")
    t = jax.jit(make_rollout(model, controller="classical", duration=4.0, actuation="position"))(g, s)
    normal = np.asarray(t.pad_normal)
    grip = np.einsum("tij,tij->ti", np.asarray(t.pad_forces), normal)
    sensed = np.einsum("tij,tij->ti", -np.asarray(t.wrist_wrench)[..., :3], normal)
    depth = float(s.object_radius) - np.einsum(
        "tij,tij->ti", normal, np.asarray(t.obj_pos)[:, None] - np.asarray(t.pad_pos)
    )
    lag = (np.asarray(t.plan_pad_pos) - np.asarray(t.pad_pos))[..., 0]
    for k in range(0, len(grip), 25):
        print(
            f"{float(t.time[k]):5.2f} s phase {int(t.phase[k])}  grip {grip[k, 0]:6.2f} {grip[k, 1]:6.2f} N  "
            f"depth {depth[k, 0] * 1e3:5.2f} {depth[k, 1] * 1e3:5.2f} mm  lag {lag[k, 0] * 1e3:5.1f} "
            f"{lag[k, 1] * 1e3:5.1f} mm  sensed {sensed[k, 0]:6.2f} {sensed[k, 1]:6.2f} N"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", required=True)
    p.add_argument("--controllers", default="classical,synchronous")
    p.add_argument("--servo-spread", type=float, default=0.3)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--trace", type=int, default=None, metavar="N")
    args = p.parse_args()
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    cfg = TuneConfig(actuation="position", delay=(0, 3), servo_spread=args.servo_spread)
    held = S.heldout_scenarios(cfg.replace(scenario=S.model_overrides(model)))
    g = default_gains(model, "position")
    if args.trace is not None:
        JS.command_rate = _in_laws_only(_variant(args.variants.split(",")[0]))
        _trace(model, g, args.trace)
        JS.command_rate = SHIPPED
        return
    for name in args.variants.split(","):
        JS.command_rate = _in_laws_only(_variant(name))  # read at trace time by the position stack
        for controller in args.controllers.split(","):
            fn = make_rollout(model, controller=controller, duration=4.0, actuation="position")
            traj = jax.jit(jax.vmap(lambda s, fn=fn: fn(g, s)))(held)
            m = jax.vmap(M.summarize)(traj, held)
            drop = np.asarray(m.dropped)
            kept = ~drop
            row = {
                "dropped": np.flatnonzero(drop).tolist(),
                "chattering": int(np.asarray(m.chattering).sum()),
                "settled_peak_resultant_N": float(np.asarray(m.settled_peak_resultant_N)[kept].mean()),
                "grip_force_error_rel": float(np.asarray(m.grip_force_error_rel)[kept].mean()),
            }
            print(f"{name} {controller}", json.dumps(row), flush=True)
    JS.command_rate = SHIPPED


if __name__ == "__main__":
    main()
