"""The coupling family's period (ros2_coupled, ros2_coupled_direct), written from docs/coupling.md alone.

A port's reading of "One period, in order (for a port)" and of docs/golden.md's
file layout, in NumPy: it imports nothing of jaxsync (the golden files' reader
and SO(3) maps are those of ``golden_numpy``, which imports nothing of it
either) and recomputes from each row's inputs the family's filters, its offset
o_i and rate, the reference joints q_ref the CLIK advances toward the target,
and the reference joints the rule runs on. The rule itself (docs/ros2-rule.md)
is not recomputed: its new offset is read from the row's outputs.
"""

from __future__ import annotations

import numpy as np
from golden_numpy import _vec, gains_of, sensed, so3_exp, so3_log

ARMS = ("right", "left")
CHANNELS = ("rel", "own", "other", "force")
FORCE_TIME = 0.1  # s, T of the force channel's scale
PLACEMENT = {"ros2_coupled": "reference", "ros2_coupled_direct": "direct"}


def _pad(R, v):
    """A world 6-vector in the frame R, each 3-block rotated alone."""
    return np.concatenate([R.T @ v[:3], R.T @ v[3:]])


def _world(R, v):
    return np.concatenate([R @ v[:3], R @ v[3:]])


def _row(inputs, k, meta):
    n = len(meta["joints"]["right"])
    x = sensed(inputs, k, meta)
    for i, arm in enumerate(ARMS):
        x[arm].update(
            {
                "q_ref": _vec(inputs, f"state_in.ros2.q_ref[{i}]", k, n),
                "dq": _vec(inputs, f"state_in.ros2.rule.joint_pos[{i}]", k, n),
                "dq_dot": _vec(inputs, f"state_in.ros2.rule.joint_vel[{i}]", k, n),
                "y": np.array([_vec(inputs, f"state_in.coupling.value[{c}][{i}]", k, 6) for c in range(4)]),
                "y_dot": np.array([_vec(inputs, f"state_in.coupling.rate[{c}][{i}]", k, 6) for c in range(4)]),
            }
        )
    return x


def step(inputs, k: int, meta) -> tuple[dict, np.ndarray]:
    """Row k's family outputs from row k's inputs: ({column: value} for
    state.coupling.value, state.coupling.rate, coupling_offset,
    coupling_offset_rate and state.ros2.q_ref; the (2, n) reference joints the
    rule runs on, which the rule's command is plus its new offset)."""
    g = gains_of(meta)
    dt, alpha = meta["dt_s"], meta["alpha"]
    placement = PLACEMENT[meta["controller"]]
    n = len(meta["joints"]["right"])
    lam = 2.0 * g["kp_pos"] / g["kd_pos"]
    mu = g["kp_null"] / g["kd_null"]
    x = _row(inputs, k, meta)
    # 1. absolute errors from the sensed pads (eq. 12)
    delta = {a: np.concatenate([x[a]["p_d"] - x[a]["p"], so3_log(x[a]["R_d"] @ x[a]["R"].T)]) for a in ARMS}
    # 2. the rules' offsets of the last period through this period's Jacobian
    e = {a: x[a]["J"] @ x[a]["dq"] for a in ARMS}
    e_dot = {a: x[a]["J"] @ x[a]["dq_dot"] for a in ARMS}
    # 3. the force errors, unfiltered
    eps = {a: x[a]["f"] - x[a]["f_d"] for a in ARMS}
    out, q_rule = {}, []
    for i, arm in enumerate(ARMS):
        other = ARMS[1 - i]
        s, R_d = x[arm], x[arm]["R_d"]
        kb = g["imp_stiffness"][i] + g["imp_damping"][i] / FORCE_TIME
        scale = np.where(kb > 0, 1.0 / np.where(kb > 0, kb, 1.0), 0.0)
        # 4. the channels' inputs and rates in arm i's planned pad frame
        u = np.array(
            [
                _pad(R_d, delta[arm] - delta[other]),
                _pad(R_d, e[arm]),
                _pad(R_d, e[other]),
                scale * _pad(R_d, eps[other]),
            ]
        )
        u_dot = np.array([np.zeros(6), _pad(R_d, e_dot[arm]), _pad(R_d, e_dot[other]), np.zeros(6)])
        # 5. the filters
        a = np.array([g[f"cpl_{c}_a"][i] for c in CHANNELS])
        y = a * u + (1.0 - a) * s["y"]
        y_dot = a * u_dot + (1.0 - a) * s["y_dot"]
        # 6. the offset: the gains on the diagonal, the block off it
        c = np.array([g[f"cpl_{ch}"][i] for ch in CHANNELS])
        X = g["cpl_block"][:, i] * (1.0 - np.eye(6))
        o_bar = sum(c[m] * y[m] + X[m] @ y[m] for m in range(4))
        o_dot_bar = sum(c[m] * y_dot[m] + X[m] @ y_dot[m] for m in range(4))
        o, o_dot = _world(R_d, o_bar), _world(R_d, o_dot_bar)
        # 7. the target of the reference joints
        if placement == "reference":
            p_t, R_t, v_t = s["p_d"] + o[:3], so3_exp(o[3:]) @ R_d, s["v_d"] + o_dot
        else:
            p_t, R_t, v_t = s["p_d"], R_d, s["v_d"]
        # 8. q_ref one period on: the CLIK closed on the pad pose at q_ref (first order)
        J = s["J"]
        d = J @ (s["q"] - s["q_ref"])
        p_hat, R_hat = s["p"] - d[:3], so3_exp(-d[3:]) @ s["R"]
        dls = np.linalg.solve(J.T @ J + alpha * np.eye(n), J.T)
        v = v_t + lam * np.concatenate([p_t - p_hat, so3_log(R_t @ R_hat.T)])
        rate = dls @ v + (np.eye(n) - dls @ J) @ (mu * (s["q_rest"] - s["q_ref"]))
        q_ref = s["q_ref"] + dt * rate
        # 9. the reference joints the rule runs on
        q_rule.append(q_ref + dls @ o if placement == "direct" else q_ref)
        for ch in range(4):
            for ax in range(6):
                out[f"state.coupling.value[{ch}][{i}][{ax}]"] = y[ch, ax]
                out[f"state.coupling.rate[{ch}][{i}][{ax}]"] = y_dot[ch, ax]
        for ax in range(6):
            out[f"coupling_offset[{i}][{ax}]"] = o[ax]
            out[f"coupling_offset_rate[{i}][{ax}]"] = o_dot[ax]
        for j in range(n):
            out[f"state.ros2.q_ref[{i}][{j}]"] = q_ref[j]
    return out, np.array(q_rule)
