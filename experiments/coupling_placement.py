"""Where ros2_synchronous (the rule plus the coupling) adds the coupling, and what holds the ball (docs/deploy.md).

``ros2_synchronous`` runs ros2_controllers' admittance rule per arm and adds
the paper's coupling o_i = k_ik (delta_r - delta_l) + k_il (e_i - e_j)
through the reference the rule offsets; the reference joints follow it
through the position stack's kinematic loop (lambda = 2 kp_pos / kd_pos),
a time 1 / lambda late. This script scores a robot's ros2_synchronous
defaults on its 16 held-out scenarios (delays 0-3 periods, servo gains
+-30 %, unfiltered) with the coupling placed four ways:

- ``replaced`` (jaxsync's): the reference's target carries o_i - e_i, so
  the command's offset is the paper's synchronous law, o_i alone (2 k_il e_i
  in the squeeze, the rule's own at k_il = 1/2);
- ``reference``: the target carries o_i, and the command e_i + o_i: in the
  squeeze (1 + 2 k_il) times the rule's own offset;
- ``direct``: o_i mapped through the command's damped least squares J# onto
  the rule's reference joints in the same period (q_ref + J# o_i, its rate
  J# o_i dot), the reference loop following the plan alone;
- ``direct_replaced``: both.

and prints, per placement, the drops, chatter, the mean settled peak
resultant over the scenarios kept, the grip error and the first impact.
``--set`` changes scalar gains (e.g. ``k_rk=0.5,k_lk=-0.5``, the
synchronous law's factors). The placements replace
``jaxsync.control.ros2_loop``'s functions in this process only.
Deterministic: no timing.

    python experiments/coupling_placement.py --robot mjcf/robots/iiwa14_pair.yaml
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.control import ros2_admittance as RA
from jaxsync.control import ros2_loop as RL
from jaxsync.control import so3
from jaxsync.control.gains import default_gains
from jaxsync.control.joint_space import COMMAND_ALPHA
from jaxsync.optimize.tuning import scenarios as S
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim import metrics as M
from jaxsync.sim.rollout import make_rollout

PLACEMENTS = ("replaced", "reference", "direct", "direct_replaced")
SHIPPED, STEP = RL.coupled_reference, RL.step


def _reference(gains, state, arms, ref, cross_term="squeeze"):
    """jaxsync's target plus the rules' own offsets e_i (and their rates): the plan plus o_i."""
    out = SHIPPED(gains, state, arms, ref, cross_term)
    e = [arms[i].jac @ state.rule.joint_pos[i] for i in range(2)]
    e_dot = [arms[i].jac @ state.rule.joint_vel[i] for i in range(2)]
    return out._replace(
        pad_pos=out.pad_pos + jnp.stack([x[:3] for x in e]),
        pad_rot=jnp.stack([so3.exp(e[i][3:]) @ out.pad_rot[i] for i in range(2)]),
        pad_vel=out.pad_vel + jnp.stack(e_dot),
    )


def _direct(gains, state, arms, ref, dt, distro="jazzy", coupled=False, cross_term="squeeze", ft_filter=1.0):
    """``ros2_loop.step`` with the coupling put onto the rule's reference joints
    through J# in the same period; the reference loop follows the plan."""
    rule = RA.admittance_rule(distro)
    target = RL.coupled_reference(gains, state, arms, ref, cross_term)
    out, q_refs, rules, offsets = [], [], [], []
    for i in range(2):
        arm = arms[i]
        q_ref, rate = RL.reference_step(gains, arm, state.q_ref[i], ref, i, dt)
        o = jnp.concatenate([target.pad_pos[i] - ref.pad_pos[i], so3.rotation_error(target.pad_rot[i], ref.pad_rot[i])])
        jac = arm.jac
        dls = jnp.linalg.solve(jac.T @ jac + COMMAND_ALPHA * jnp.eye(jac.shape[1]), jac.T)
        w_ref = None if distro == "humble" else -RL._in_pad(arm.pad_rot, ref.wrench[i])
        command, rs = rule.step(
            RL.params(gains, i, ref.pad_rot[i], distro, ft_filter),
            jax.tree_util.tree_map(lambda x, i=i: x[i], state.rule),
            RL.kinematics(arm, q_ref + dls @ o),
            RL._in_pad(arm.pad_rot, arm.wrench),
            RA.JointPoint(q_ref + dls @ o, rate + dls @ (target.pad_vel[i] - ref.pad_vel[i]), jnp.zeros_like(rate)),
            dt,
            wrench_reference=w_ref,
        )
        out.append(command.positions)
        q_refs.append(q_ref)
        rules.append(rs)
        offsets.append(arm.jac @ rs.joint_pos)
    new = RL.Ros2State(q_ref=jnp.stack(q_refs), rule=jax.tree_util.tree_map(lambda *x: jnp.stack(x), *rules))
    return jnp.concatenate(out), new, jnp.stack(offsets)


def _place(name: str) -> None:
    RL.coupled_reference = SHIPPED if "replaced" in name else _reference
    RL.step = _direct if name.startswith("direct") else STEP


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="mjcf/dual_arm.xml")
    p.add_argument("--placements", default=",".join(PLACEMENTS))
    p.add_argument("--set", default="", metavar="NAME=VALUE,...", help="scalar gains changed from the defaults")
    args = p.parse_args()
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    cfg = TuneConfig(actuation="position", delay=(0, 3), servo_spread=0.3)
    held = S.heldout_scenarios(cfg.replace(scenario=S.model_overrides(model)))
    g = default_gains(model, "position", "ros2_synchronous")
    for item in filter(None, args.set.split(",")):
        name, value = item.split("=")
        g = g._replace(**{name: np.asarray(getattr(g, name)) * 0.0 + float(value)})
    for name in args.placements.split(","):
        if name not in PLACEMENTS:
            p.error(f"--placements: {name!r} is not one of {', '.join(PLACEMENTS)}")
        _place(name)
        fn = make_rollout(model, controller="ros2_synchronous", duration=4.0, actuation="position")
        m = jax.vmap(M.summarize)(jax.jit(jax.vmap(lambda s, fn=fn: fn(g, s)))(held), held)
        kept = ~(np.asarray(m.dropped) | np.asarray(m.nonfinite))
        mean = lambda x, kept=kept: float(np.asarray(x)[kept].mean()) if kept.any() else None  # noqa: E731
        row = {
            "dropped": int((~kept).sum()),
            "chattering": int(np.asarray(m.chattering).sum()),
            "settled_peak_resultant_N": mean(m.settled_peak_resultant_N),
            "grip_force_error_rel": mean(m.grip_force_error_rel),
            "first_impact_peak_N": mean(m.first_impact_peak_N),
        }
        print(f"{name} {args.set}", json.dumps(row), flush=True)
    _place("replaced")


if __name__ == "__main__":
    main()
