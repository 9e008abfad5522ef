"""The servo read from recorded joint efforts, where the recording has them.

A position-controlled joint's servo applies (``jaxsync.physics.servo``)

    tau = clip(k (q_cmd - q) + b (f dq_cmd - dq) + w c(q, dq), +-tau_max)

with ``q_cmd`` the command acting after the delay and ``c`` the arm's bias
forces (gravity and Coriolis). For a structure (w, f) and a delay, tau - w c
is linear in (k, b) on every sample inside the limit, so where the
recording's joint states carry each joint's torque (``JointState.effort``,
what ros2_control's ``joint_state_broadcaster`` publishes from the effort
state interface) every structure and delay is fitted in closed form, one
joint at a time, in milliseconds, with no rollout. Samples at the torque
limit (``SATURATED`` of it) carry no information on the gains and are left
out; their share is reported per joint.

``calibrate`` fits the recorded motion (``jaxsync.calibrate.fit``); this is
a second, independent reading of the same arm from another signal. Where
the two disagree on the delay, the structure or a gain beyond what the
motion fit claims to determine, the calibration is not trusted
(``fit.problems``).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jaxsync.calibrate.replay import Replay
from jaxsync.physics.servo import STRUCTURES

SATURATED = 0.98  # a sample with |tau| at this share of the joint's limit or above: at the limit
MIN_SAMPLES = 50  # unsaturated samples a joint needs for its two gains
SMOOTH_S = 0.05  # s: both sides of the regression averaged over this window (the servo's law is linear and
# time-invariant, so averaging keeps it) before the fit: the velocity's noise, in a regressor, would pull the
# damping low by its variance over the tracking error's (tens of per cent at 500 Hz, measured)


@dataclasses.dataclass(frozen=True)
class EffortFit:
    """The servo the efforts say, ((2 n,) arrays, right arm then left)."""

    structure: str
    delay: int
    stiffness: np.ndarray  # N m/rad
    damping: np.ndarray  # N m s/rad
    rms: np.ndarray  # N m: each joint's residual torque at the chosen structure and delay
    saturated: np.ndarray  # each joint's share of samples at its torque limit
    costs: dict  # (structure, delay) -> sum over joints of the mean square residual, (N m)^2

    def margin(self, over: str = "structure") -> float | None:
        """How much worse the best other structure (``over="structure"``) or delay ("delay") explains the
        efforts (0.3: 30 %), None where there is no other."""
        best = self.costs[(self.structure, self.delay)]
        if over == "structure":
            others = [c for (s, _), c in self.costs.items() if s != self.structure]
        else:
            others = [c for (s, d), c in self.costs.items() if s == self.structure and d != self.delay]
        return min(others) / max(best, 1e-300) - 1.0 if others else None

    def to_dict(self, joints) -> dict:
        return {
            "structure": self.structure,
            "delay_periods": self.delay,
            "structure_margin": self.margin("structure"),
            "delay_margin": self.margin("delay"),
            "joints": {
                name: {
                    "stiffness_N m/rad": float(self.stiffness[k]),
                    "damping_N m s/rad": float(self.damping[k]),
                    "residual_rms_Nm": float(self.rms[k]),
                    "saturated_share": float(self.saturated[k]),
                }
                for k, name in enumerate(joints)
            },
        }


def bias_forces(replay: Replay, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """(S, 2 n) the arms' bias forces c(q, dq) (gravity and Coriolis, N m) at each sample, the rest of the
    scene at the grasp keyframe (contacts off)."""
    m, d, pc = replay.m, replay.d, replay.pc
    out = np.empty_like(q)
    for i in range(len(q)):
        d.qpos[:] = replay.base_qpos
        d.qpos[pc.qpos_adr] = q[i]
        d.qvel[:] = 0.0
        d.qvel[pc.dof_adr] = dq[i]
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fwdVelocity(m, d)
        out[i] = d.qfrc_bias[pc.dof_adr]
    return out


def fit_efforts(model, rec, delays=range(0, 5), structures=None) -> EffortFit:
    """Each structure and delay fitted to ``rec.effort`` by linear least squares, joint by joint; the one
    with the least residual chosen. ``rec`` a ``jaxsync.io.bags.Recording`` with efforts."""
    if rec.effort is None:
        raise ValueError("the recording carries no joint efforts")
    replay = Replay(model)
    q, tau = np.asarray(rec.q, float), np.asarray(rec.effort, float)
    dq = np.asarray(rec.dq, float) if rec.dq is not None else np.gradient(q, rec.state_times, axis=0)
    c = bias_forces(replay, q, dq)
    limit = np.asarray(replay.limit, float)
    at_limit = np.abs(tau) >= SATURATED * limit
    width = max(1, int(round(SMOOTH_S / float(np.median(np.diff(rec.state_times))))))
    smooth = lambda x: _boxcar(x, width)  # noqa: E731
    inside = smooth(at_limit.astype(float)) == 0.0  # no sample of the window at the limit
    inside[: width // 2 + 1] = inside[-(width // 2 + 1) :] = False  # the averages the ends cut short
    period = rec.command_period
    names = list(STRUCTURES) if structures is None else list(structures)
    costs, fits = {}, {}
    n = q.shape[1]
    for delay in delays:
        cmd, vel = replay.acting(rec.state_times, rec.command_times, rec.commands, int(delay), period)
        e, v, dv = smooth(cmd - q), smooth(vel), smooth(dq)
        for name in names:
            w, f = (float(x) for x in STRUCTURES[name])
            y = smooth(tau - w * c)
            k, b, ms = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.inf)
            for j in range(n):
                rows = inside[:, j]
                if rows.sum() < MIN_SAMPLES:
                    continue
                X = np.column_stack([e[rows, j], f * v[rows, j] - dv[rows, j]])
                sol, *_ = np.linalg.lstsq(X, y[rows, j], rcond=None)
                k[j], b[j] = sol
                r = y[rows, j] - X @ sol
                ms[j] = float(np.mean(r**2))
            costs[(name, int(delay))] = float(np.sum(ms))
            fits[(name, int(delay))] = (k, b, np.sqrt(ms))
    best = min(costs, key=costs.get)
    k, b, rms = fits[best]
    return EffortFit(best[0], best[1], k, b, rms, at_limit.mean(axis=0), costs)


def _boxcar(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average of ``width`` samples along axis 0 (the ends averaged over what there is)."""
    if width <= 1:
        return np.asarray(x, float)
    kernel = np.ones(width) / width
    return np.apply_along_axis(lambda col: np.convolve(col, kernel, mode="same"), 0, np.asarray(x, float))


def disagreements(ef: EffortFit, cal, shares: dict) -> list[str]:
    """Where the efforts' reading of the arm contradicts ``cal`` (a ``fit.Calibration``), one phrase each:
    another delay or structure, or a stiffness or damping off by more than its share in ``shares``."""
    out = []
    if ef.delay != cal.delay or ef.structure != cal.structure:
        out.append(
            f"the joint efforts say the {ef.structure} servo at delay {ef.delay}, the motion the {cal.structure} "
            f"one at delay {cal.delay}"
        )
    for field, share in shares.items():
        mine, theirs = getattr(ef, field), getattr(cal.fitted, field)
        rel = np.abs(mine - theirs) / np.abs(theirs)
        off = [(j, r) for j, r in zip(cal.joints, rel, strict=True) if not np.isfinite(r) or r > share]
        if off:
            j, r = max(off, key=lambda x: x[1] if np.isfinite(x[1]) else np.inf)
            k = list(cal.joints).index(j)
            out.append(
                f"the joint efforts and the motion disagree on the {field} of {len(off)} joint(s) by more than "
                f"{share:.0%} (worst {j}: {mine[k]:.4g} against {theirs[k]:.4g})"
            )
    return out
