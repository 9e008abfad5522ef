"""The identification trajectory a user plays on the robot: per-joint steps and a chirp around a pose.

Each joint in turn, both arms at once (the same joint index), the other
joints held: a move to +A, hold, a move to -A, hold, back to the pose, hold
(the steps, raised-cosine moves under the speed and acceleration caps: they
show the delay and the stiffness), then a linear chirp from ``f0`` to ``f1``
Hz whose amplitude is cut to keep under both caps (it shows the damping).
Each joint's acceleration cap is ``TORQUE_SHARE`` of its torque limit over
its own inertia, so that the servo never saturates (a saturated servo says
nothing about its gains). Every command stays within the joint's range and
under the speed cap (checked on the sampled commands), and
the two arms keep a stated clearance (their collision geoms' distance along
the whole trajectory, without the object, which is not there when it is
played).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.physics.servo import joint_inertia
from jaxsync.sim.closed_loop import consts

GRASP_KEY = "grasp"
STEP_SHARE = 0.5  # of each joint's segment: the steps; the rest the chirp and a rest at the end
CLEARANCE_M = 0.02
TORQUE_SHARE = 0.2  # of a joint's torque limit its own inertia may take at the acceleration cap


@dataclasses.dataclass(frozen=True)
class Excitation:
    """Both arms' joint position commands at the control rate, in ``joints``' order (right arm, then left)."""

    joints: tuple[str, ...]
    times: np.ndarray  # (C,) s
    commands: np.ndarray  # (C, 2 n) rad
    pose: np.ndarray  # (2 n,) rad, where it starts and ends
    segments: tuple[tuple[int, float, float], ...]  # (joint index in each arm, start s, end s)
    amplitude: float  # rad
    speed: float  # rad/s
    accel: tuple[float, ...]  # rad/s^2, each joint's cap
    rate: float  # Hz
    chirp: tuple[float, float]  # Hz
    clearance: float  # m, the two arms' closest approach

    def describe(self) -> dict:
        n = len(self.joints) // 2
        return {
            "duration_s": float(self.times[-1]),
            "rate_Hz": self.rate,
            "samples": int(len(self.times)),
            "amplitude_rad": self.amplitude,
            "speed_cap_rad_per_s": self.speed,
            "acceleration_cap_rad_per_s2": [float(f"{a:.4g}") for a in self.accel],
            "largest_speed_rad_per_s": float(np.abs(np.diff(self.commands, axis=0)).max() * self.rate),
            "chirp_Hz": list(self.chirp),
            "arm_clearance_m": self.clearance,
            "joints": list(self.joints),
            "pose_rad": self.pose.tolist(),
            "segments": [
                {"joints": [self.joints[j], self.joints[n + j]], "start_s": t0, "end_s": t1}
                for j, t0, t1 in self.segments
            ],
            "excites": "each joint's servo stiffness (steps), damping (chirp) and the command delay (every onset); "
            "not contact, not the F/T sensor",
        }


def bag_joint_names(model) -> tuple[str, ...]:
    """The joints' names as the robot reports them: the robot file's (arm-prefixed where both
    arms use the same names), the MJCF's for an MJCF model. Right arm first."""
    robot = getattr(model, "robot", None)
    if robot is not None:
        right, left = (tuple(robot.joint_names[a]) for a in ("right", "left"))
        if not set(right) & set(left):
            return right + left
        return tuple(f"right_{j}" for j in right) + tuple(f"left_{j}" for j in left)
    m = model.mj_model
    return tuple(
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[i]))
        for a in model.index.arms
        for i in a.dof_adr
    )


def check_symmetric(model) -> None:
    """Calibration moves and fits the two arms joint by joint: they need as many joints each."""
    right, left = (len(a.dof_adr) for a in model.index.arms)
    if right != left:
        raise ConfigError(f"calibration needs two arms of as many joints, got {right} (right) and {left} (left)")


def pose_of(model, key: str = GRASP_KEY) -> np.ndarray:
    q = np.asarray(model.keyframe_qpos(key))
    return np.concatenate([q[list(a.qpos_adr)] for a in model.index.arms])


def _move(t, t0: float, T: float, x0: float, x1: float):
    """A raised-cosine move from x0 to x1 over [t0, t0 + T] (zero speed at both ends)."""
    u = np.clip((t - t0) / T, 0.0, 1.0)
    return x0 + (x1 - x0) * 0.5 * (1.0 - np.cos(np.pi * u))


def _segment(T: float, A: float, v: float, a: float, rate: float, f0: float, f1: float) -> np.ndarray:
    """One joint's offsets from the pose at the control rate: speed at most v, acceleration at most a."""
    t = np.arange(int(round(T * rate))) / rate
    move = lambda D: max(np.pi * D / (2.0 * v), np.pi * np.sqrt(D / (2.0 * a)))  # noqa: E731
    r1, r2 = move(A), move(2.0 * A)
    steps_T = STEP_SHARE * T
    hold = (steps_T - 2.0 * r1 - r2) / 3.0
    if hold < 0.05:
        raise ConfigError(
            f"duration: {T:.2f} s per joint is too short for steps of {A:g} rad at {v:g} rad/s and {a:.3g} rad/s^2 "
            f"(at least {(2 * r1 + r2 + 0.15) / STEP_SHARE:.2f} s per joint)",
            inputs=("duration",),
        )
    # the steps: 0 -> +A -> -A -> 0, each level held
    x = _move(t, 0.0, r1, 0.0, A)
    x = np.where(t >= r1 + hold, _move(t, r1 + hold, r2, A, -A), x)
    x = np.where(t >= r1 + r2 + 2 * hold, _move(t, r1 + r2 + 2 * hold, r1, -A, 0.0), x)
    # the chirp: a linear sweep f0 -> f1, its amplitude under the speed and acceleration caps, tapered
    c0, c1 = steps_T, 0.95 * T
    tc = np.clip(t - c0, 0.0, c1 - c0)
    Tc = c1 - c0
    f = f0 + (f1 - f0) * tc / Tc
    phase = 2.0 * np.pi * (f0 * tc + 0.5 * (f1 - f0) * tc**2 / Tc)
    w = 2.0 * np.pi * f
    amp = np.minimum(A, np.minimum(0.6 * v / w, 0.6 * a / w**2))
    taper = np.sin(np.pi * np.clip(tc / Tc, 0.0, 1.0)) ** 2
    chirp = amp * taper * np.sin(phase)
    return np.where((t >= c0) & (t < c1), chirp, x)


def accel_caps(model, share: float = TORQUE_SHARE) -> np.ndarray:
    """(n,) each joint's acceleration cap, rad/s^2: ``share`` of its torque limit over its own inertia
    at the grasp (the larger of the two arms')."""

    inertia = joint_inertia(model)  # (2, n)
    limit = np.asarray(consts(model).torque_limit, float).reshape(2, -1)
    return (share * limit / inertia).min(axis=0)


def excitation(
    model,
    *,
    duration: float = 20.0,
    amplitude: float = 0.05,
    speed: float = 0.5,
    rate: float = 500.0,
    chirp: tuple[float, float] = (0.5, 12.0),
    key: str = GRASP_KEY,
) -> Excitation:
    """Per-joint steps and a chirp around the pose ``key``, ``duration`` seconds in all (module docstring).

    Raises:
      ConfigError: an amplitude that leaves a joint's range, a duration too
        short for the steps, or arms that come closer than ``CLEARANCE_M``.
    """
    for name, value, lo, hi in (("duration", duration, 1.0, 3600.0), ("amplitude", amplitude, 1e-3, 0.5),
                                ("speed", speed, 1e-3, 5.0), ("rate", rate, 10.0, 10000.0)):  # fmt: skip
        if not (isinstance(value, int | float) and lo <= value <= hi):
            raise ConfigError(f"{name} must be in [{lo:g}, {hi:g}], got {value!r}", inputs=(name,))
    if not 0 < chirp[0] < chirp[1] <= rate / 10:
        raise ConfigError(f"chirp must be 0 < f0 < f1 <= rate/10 Hz, got {chirp}", inputs=("chirp",))
    m = model.mj_model
    check_symmetric(model)
    names = bag_joint_names(model)
    pose = pose_of(model, key)
    n = len(pose) // 2
    jids = [int(m.dof_jntid[i]) for a in model.index.arms for i in a.dof_adr]
    for k, jid in enumerate(jids):
        lo, hi = m.jnt_range[jid]
        if m.jnt_limited[jid] and not (lo < pose[k] - amplitude and pose[k] + amplitude < hi):
            raise ConfigError(
                f"amplitude {amplitude:g} rad takes joint {names[k]} ({pose[k]:.3f} rad at the pose) out of its "
                f"range [{lo:.3f}, {hi:.3f}]",
                inputs=("amplitude",),
            )
    seg_T = duration / n
    caps = accel_caps(model)
    C = int(round(seg_T * rate))
    commands = np.tile(pose, (n * C + 1, 1))
    segments = []
    for j in range(n):
        offsets = _segment(seg_T, amplitude, speed, float(caps[j]), rate, *chirp)
        rows = slice(j * C, (j + 1) * C)
        commands[rows, j] += offsets
        commands[rows, n + j] += offsets
        segments.append((j, j * C / rate, (j + 1) * C / rate))
    times = np.arange(len(commands)) / rate
    fastest = float(np.abs(np.diff(commands, axis=0)).max() * rate)
    if fastest > speed * (1 + 1e-9):  # the construction keeps under it; this says so on every file written
        raise ConfigError(f"the trajectory reaches {fastest:.3f} rad/s, over the speed cap {speed:g}")
    clearance = _clearance(model, commands[:: max(1, int(rate // 25))])
    if clearance < CLEARANCE_M:
        raise ConfigError(
            f"the arms come {clearance * 1000:.1f} mm close (under {CLEARANCE_M * 1000:g} mm) with amplitude "
            f"{amplitude:g} rad around the pose {key!r}: lower the amplitude",
            inputs=("amplitude",),
        )
    caps_t = tuple(float(c) for c in caps)
    band = (float(chirp[0]), float(chirp[1]))
    return Excitation(names, times, commands, pose, tuple(segments), float(amplitude), float(speed), caps_t,
                      float(rate), band, clearance)  # fmt: skip


def _arm_geoms(m, root: int) -> list[int]:
    def under(b):
        while b > 0:
            if b == root:
                return True
            b = int(m.body_parentid[b])
        return False

    # every geom of the arm, whether the task scene collides it or not: the robot's own arms do
    return [g for g in range(m.ngeom) if under(int(m.geom_bodyid[g]))]


def _clearance(model, commands: np.ndarray) -> float:
    """The two arms' collision geoms' smallest distance over the sampled commands (m)."""
    m = model.mj_model
    d = mujoco.MjData(m)
    # each arm's moving bodies: from its first joint's body down (arms may share a base or torso)
    right, left = (_arm_geoms(m, int(m.jnt_bodyid[m.dof_jntid[a.dof_adr[0]]])) for a in model.index.arms)
    qadr = [i for a in model.index.arms for i in a.qpos_adr]
    base = np.asarray(model.keyframe_qpos(GRASP_KEY))
    best = np.inf
    fromto = np.zeros(6)
    for q in commands:
        d.qpos[:] = base
        d.qpos[qadr] = q
        mujoco.mj_kinematics(m, d)
        for g1 in right:
            for g2 in left:
                best = min(best, mujoco.mj_geomDistance(m, d, g1, g2, 0.5, fromto))
    return float(best)


def write_csv(path, ex: Excitation) -> None:
    header = "time_s," + ",".join(ex.joints)
    np.savetxt(path, np.column_stack([ex.times, ex.commands]), delimiter=",", header=header, comments="", fmt="%.9g")
