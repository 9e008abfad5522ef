"""The synchronous controller's update on position-controlled arms, written from docs/deploy.md alone.

A port's reading of "The synchronous controller on position-controlled
arms, one update in order" and of docs/golden.md's file layout, in NumPy: it
imports nothing of jaxsync, reads the golden files with the standard
library's ``csv`` and ``json``, and recomputes each row's outputs from the
row's inputs. A test compares them with the recorded outputs, so that the
documents and the files cannot drift apart.
"""

from __future__ import annotations

import csv
import json
import os

import numpy as np

ARMS = ("right", "left")


def read(folder: str):
    """(inputs, outputs, meta): each CSV as {column: float array}, golden.json as a dict."""
    tables = []
    for name in ("inputs.csv", "outputs.csv"):
        with open(os.path.join(folder, name), newline="") as f:
            rows = list(csv.reader(f))
        header, body = rows[0], np.array(rows[1:], dtype=float)
        tables.append({c: body[:, i] for i, c in enumerate(header)})
    with open(os.path.join(folder, "golden.json")) as f:
        meta = json.load(f)
    return tables[0], tables[1], meta


def _vec(table, prefix, k, n):
    return np.array([table[f"{prefix}[{i}]"][k] for i in range(n)])


def _mat(table, prefix, k, rows, cols):
    return np.array([[table[f"{prefix}[{r}][{c}]"][k] for c in range(cols)] for r in range(rows)])


def _hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_log(R):
    """The rotation vector of R (angle in [0, pi))."""
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.linalg.norm(w)
    theta = np.arctan2(s, 0.5 * (np.trace(R) - 1.0))
    return w * (theta / s if s > 1e-12 else 1.0 + s * s / 6.0)


def so3_exp(w):
    """Rodrigues' formula."""
    t = np.linalg.norm(w)
    K = _hat(w)
    if t < 1e-12:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(t) / t * K + (1.0 - np.cos(t)) / t**2 * K @ K


def gains_of(meta):
    """The gains as golden.json holds them (the yaml export's form: each gain's ``value``)."""
    return {k: np.asarray(v["value"], dtype=float) for k, v in meta["jaxsync_gains"]["gains"].items()}


def sensed(inputs, k: int, meta) -> dict:
    """Row k's sensed arms and reference, per arm: q, the pad's pose, Jacobian and wrench, and the planned
    pad pose, twist, acceleration, wrench and rest posture."""
    n = len(meta["joints"]["right"])
    return {
        arm: {
            "q": _vec(inputs, f"{arm}.q", k, n),
            "p": _vec(inputs, f"{arm}.pad_pos", k, 3),
            "R": _mat(inputs, f"{arm}.pad_rot", k, 3, 3),
            "J": _mat(inputs, f"{arm}.jac", k, 6, n),
            "f": _vec(inputs, f"{arm}.wrench", k, 6),
            "p_d": _vec(inputs, f"ref.{arm}.pad_pos", k, 3),
            "R_d": _mat(inputs, f"ref.{arm}.pad_rot", k, 3, 3),
            "v_d": _vec(inputs, f"ref.{arm}.pad_vel", k, 6),
            "a_d": _vec(inputs, f"ref.{arm}.pad_acc", k, 6),
            "f_d": _vec(inputs, f"ref.{arm}.wrench", k, 6),
            "q_rest": _vec(inputs, f"ref.{arm}.q_rest", k, n),
        }
        for arm in ARMS
    }


def step(inputs, k: int, meta) -> dict:
    """Row k's outputs from row k's inputs: {column: value} for command, sent and the state."""
    g = gains_of(meta)
    dt, a, alpha = meta["dt_s"], meta["ft_filter"], meta["alpha"]
    n = len(meta["joints"]["right"])
    lam = 2.0 * g["kp_pos"] / g["kd_pos"]
    mu = g["kp_null"] / g["kd_null"]
    x = sensed(inputs, k, meta)
    for i, arm in enumerate(ARMS):
        x[arm].update(
            {
                "q_cmd": np.array([inputs[f"command_in[{i * n + j}]"][k] for j in range(n)]),
                "h": _vec(inputs, f"state_in.wrench_filter[{i}]", k, 6),
                "e": _vec(inputs, f"state_in.impedance.offset[{i}]", k, 6),
                "de": _vec(inputs, f"state_in.impedance.rate[{i}]", k, 6),
            }
        )
    out = {}
    # 1. the force error through the F/T filter (world frame)
    for arm in ARMS:
        s = x[arm]
        s["h"] = a * (s["f"] - s["f_d"]) + (1.0 - a) * s["h"]
    # 2. absolute errors (eq. 12)
    delta = {arm: np.concatenate([x[arm]["p_d"] - x[arm]["p"], so3_log(x[arm]["R_d"] @ x[arm]["R"].T)]) for arm in ARMS}
    # 3. relative compensation (eq. 13)
    rel = delta["right"] - delta["left"]
    delta_k = {"right": g["k_rk"] * rel, "left": g["k_lk"] * rel}
    # 4. each arm's admittance filter in its planned pad frame, implicit in B and K; state in the world frame
    for i, arm in enumerate(ARMS):
        s = x[arm]
        Rd = s["R_d"]
        local = lambda v, R=Rd: np.concatenate([R.T @ v[:3], R.T @ v[3:]])  # noqa: E731
        world = lambda v, R=Rd: np.concatenate([R @ v[:3], R @ v[3:]])  # noqa: E731
        M, B, K = g["imp_mass"][i], g["imp_damping"][i], g["imp_stiffness"][i]
        e, de, h = local(s["e"]), local(s["de"]), local(s["h"])
        de_new = (M / dt * de + h - K * e) / (M / dt + B + K * dt)
        s["e"], s["de"] = world(e + dt * de_new), world(de_new)
    # 5. the cross term (the squeeze reading)
    cross = {"right": x["right"]["e"] - x["left"]["e"], "left": x["left"]["e"] - x["right"]["e"]}
    cross_rate = {"right": x["right"]["de"] - x["left"]["de"], "left": x["left"]["de"] - x["right"]["de"]}
    k_il = {"right": g["k_rl"], "left": g["k_ll"]}
    commands, sent = [], []
    for arm in ARMS:
        s = x[arm]
        # 6. offsets (eqs. 14, 17)
        o = delta_k[arm] + k_il[arm] * cross[arm]
        do = k_il[arm] * cross_rate[arm]
        # 7. the targets
        p_t, R_t, v_t = s["p_d"] + o[:3], so3_exp(o[3:]) @ s["R_d"], s["v_d"] + do
        # 8. the joint command
        J = s["J"]
        dls = np.linalg.solve(J.T @ J + alpha * np.eye(n), J.T)
        v = v_t + lam * np.concatenate([p_t - s["p"], so3_log(R_t @ s["R"].T)])
        null = (np.eye(n) - dls @ J) @ (mu * (s["q_rest"] - s["q_cmd"]))
        rate = dls @ v + dls @ (s["v_d"] - J @ (dls @ s["v_d"])) + null
        q_cmd = s["q_cmd"] + dt * rate
        commands.append(q_cmd)
        # 9. what the servo gets
        sent.append(q_cmd + dls @ (g["ff_vel"] * s["v_d"] + g["ff_acc"] * s["a_d"]))
    for j, v in enumerate(np.concatenate(commands)):
        out[f"command[{j}]"] = v
    for j, v in enumerate(np.concatenate(sent)):
        out[f"sent[{j}]"] = v
    for i, arm in enumerate(ARMS):
        for c in range(6):
            out[f"state.wrench_filter[{i}][{c}]"] = x[arm]["h"][c]
            out[f"state.impedance.offset[{i}][{c}]"] = x[arm]["e"][c]
            out[f"state.impedance.rate[{i}][{c}]"] = x[arm]["de"][c]
    return out
