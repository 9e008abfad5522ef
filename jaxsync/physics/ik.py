"""The grasp and approach poses of a composed scene, by inverse kinematics.

Both pads' full pose is fixed: the pad face centred on the clamp axis (world
y) touching the ball (``grasp``) or 30 mm off it (``approach``), its normal
(pad z) along the clamp axis into the ball, its x axis pointing down, so
the two pads' frames agree up to the half-turn about x that faces them at
each other (a roll mismatch between the pads is a wrist torque on the
clamped ball). Damped least squares on MuJoCo C (``mj_jacSite``), the joints
kept a margin inside their ranges, from several starts (the file's zero pose,
mid-range and seeded random ones); among the solutions that reach the pose,
one with no joint at the edge of its margin is preferred (the squeeze and
the lift move the joints from there), then one that keeps every link of the
arm at least 5 cm above the robot's floor (collisions are off in the task scene, so nothing else would
keep an elbow out of the floor), then the best manipulability. Checked: manipulability and the
static torque at the grasp (gravity, half the ball's weight and the grip
force) against each joint's limit, and that no geom of the arm reaches into
the ball at the grasp (a pad mounted facing back into the wrist would clamp
with the wrist). Joints are named in messages as the robot file names them
(``jaxsync.physics.robot_names``).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.physics import robot_names
from jaxsync.physics.inertia import arm_joint_ids

APPROACH_GAP = 0.03  # m between pad face and ball in the approach pose (the paper model's)
MARGIN = 0.1  # rad inside each joint's range (or 5 % of the range if that is less)
TOLERANCE = 1e-6  # m and rad
STARTS = 24
MIN_MANIPULABILITY = 1e-3  # sqrt(det(J J^T)) of the 6 x n pad Jacobian; 0 at a singularity
CHECK_GRIP_FORCE = 10.0  # N: the default task's grip force, for the static torque check
TORQUE_SHARE = 0.8  # the grasp may use at most this share of any joint's torque limit statically


def pad_rotation(side: str) -> np.ndarray:
    """The pad frame (columns x, y, z in world axes) of the right or left pad at the grasp."""
    x = np.array([0.0, 0.0, -1.0])
    z = np.array([0.0, 1.0, 0.0]) if side == "r" else np.array([0.0, -1.0, 0.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclasses.dataclass
class Pose:
    q: np.ndarray
    position_error: float
    rotation_error: float
    manipulability: float
    binding: list[str]


def _rotvec(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, R.reshape(9))
    v = np.zeros(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


def _solve(m, d, qadr, dadr, site, target_p, target_R, q0, lo, hi, iters=300):
    q = np.clip(q0.copy(), lo, hi)
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    lam = 1e-2
    for _ in range(iters):
        d.qpos[qadr] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        ep = target_p - d.site_xpos[site]
        er = _rotvec(target_R @ d.site_xmat[site].reshape(3, 3).T)
        if np.linalg.norm(ep) < TOLERANCE and np.linalg.norm(er) < TOLERANCE:
            break
        mujoco.mj_jacSite(m, d, jp, jr, site)
        J = np.concatenate([jp[:, dadr], jr[:, dadr]])
        e = np.concatenate([ep, er])
        dq = J.T @ np.linalg.solve(J @ J.T + lam**2 * np.eye(6), e)
        step = np.linalg.norm(dq)
        if step > 0.3:
            dq *= 0.3 / step
        q = np.clip(q + dq, lo, hi)
    d.qpos[qadr] = q
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    mujoco.mj_jacSite(m, d, jp, jr, site)
    J = np.concatenate([jp[:, dadr], jr[:, dadr]])
    ep = float(np.linalg.norm(target_p - d.site_xpos[site]))
    er = float(np.linalg.norm(_rotvec(target_R @ d.site_xmat[site].reshape(3, 3).T)))
    return q, ep, er, float(np.sqrt(max(np.linalg.det(J @ J.T), 0.0)))


def _ranges(m, jids):
    lo, hi = [], []
    for j in jids:
        if m.jnt_limited[j]:
            a, b = m.jnt_range[j]
            margin = min(MARGIN, 0.05 * (b - a))
            lo.append(a + margin)
            hi.append(b - margin)
        else:
            lo.append(-2 * np.pi)
            hi.append(2 * np.pi)
    return np.array(lo), np.array(hi)


FLOOR_CLEARANCE = 0.05  # m


def _lowest_link(m, d, jids) -> float:
    return float(min(d.xpos[m.jnt_bodyid[j]][2] for j in jids[1:]))


def solve_pad_pose(
    m: mujoco.MjModel, side: str, target_p, target_R, q_start=None, label: str = "", floor_z: float | None = None
) -> Pose:
    """The arm's joint angles that put its pad site at (target_p, target_R)."""
    jids = arm_joint_ids(m, side)
    qadr = np.array([m.jnt_qposadr[j] for j in jids])
    dadr = np.array([m.jnt_dofadr[j] for j in jids])
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{side}_pad")
    lo, hi = _ranges(m, jids)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    starts = [np.asarray(q_start)] if q_start is not None else []
    starts += [np.zeros(len(jids)), 0.5 * (lo + hi)]
    starts += [rng.uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi)) for _ in range(STARTS)]
    best = None
    for q0 in starts:
        q, ep, er, w = _solve(m, d, qadr, dadr, site, np.asarray(target_p), np.asarray(target_R), q0, lo, hi)
        reached = ep + er < 2 * TOLERANCE
        low = floor_z is not None and _lowest_link(m, d, jids) < floor_z + FLOOR_CLEARANCE
        at_margin = int(np.sum((q <= lo + 1e-6) | (q >= hi - 1e-6)))  # a joint with no room left to move
        key = (0.0 if reached else round(ep + er, 7), at_margin, bool(low), -w)
        if best is None or key < best[0]:
            best = (key, q, ep, er, w)
        if q_start is not None and ep + er < 2 * TOLERANCE:
            break  # continuing from a solved pose: the nearest solution is the one wanted
    _, q, ep, er, w = best
    full_lo, full_hi = (np.array([m.jnt_range[j][i] for j in jids]) for i in (0, 1))
    binding = [
        f"{robot_names.joint_name(m, j)} ({'lower' if abs(qi - a) < abs(qi - b) else 'upper'})"
        for j, qi, a, b, lo_i, hi_i in zip(jids, q, full_lo, full_hi, lo, hi, strict=True)
        if m.jnt_limited[j] and (qi <= lo_i + 1e-6 or qi >= hi_i - 1e-6)
    ]
    return Pose(q, ep, er, w, binding)


def grasp_targets(centre, radius: float, gap: float = 0.0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Pad site targets (position, rotation) for both arms, ``gap`` off the ball's surface."""
    c = np.asarray(centre, dtype=float)
    return {
        "r": (c - np.array([0.0, radius + gap, 0.0]), pad_rotation("r")),
        "l": (c + np.array([0.0, radius + gap, 0.0]), pad_rotation("l")),
    }


def static_torque_share(m: mujoco.MjModel, qpos, limits: dict[str, tuple[float, ...]], grip_force: float,
                        object_mass: float) -> dict[str, np.ndarray]:  # fmt: skip
    """|tau| / limit per joint holding the grasp statically: gravity on the arm
    and its pad, half the ball's weight and the grip force at each pad."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    out = {}
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for side, lim in limits.items():
        p = "r" if side == "right" else "l"
        dadr = [m.jnt_dofadr[j] for j in arm_joint_ids(m, p)]
        site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{p}_pad")
        mujoco.mj_jacSite(m, d, jp, jr, site)
        normal = d.site_xmat[site].reshape(3, 3)[:, 2]
        # the wrench the arm must apply at the pad: push the grip force into the ball, carry half its weight
        f = grip_force * normal + 0.5 * object_mass * 9.81 * np.array([0.0, 0.0, 1.0])
        tau = d.qfrc_bias[dadr] + jp[:, dadr].T @ f
        out[side] = np.abs(tau) / np.asarray(lim)
    return out


OBJECT_OVERLAP = 0.005  # m: how far an arm's geom may reach into the object at the grasp


def _check_clear_of_object(m: mujoco.MjModel, side: str, q, label: str) -> None:
    """At the grasp the pad's normal points into the object; the arm behind the pad must stay out of
    it (a flange whose +z does not point out of the arm puts the wrist into the object)."""
    arm, jids = robot_names.SIDES[side], arm_joint_ids(m, side)
    d = mujoco.MjData(m)  # the object at its place in the model (qpos0)
    d.qpos[[m.jnt_qposadr[j] for j in jids]] = q
    mujoco.mj_kinematics(m, d)
    obj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "object")
    ee, root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"{side}_ee"), int(m.jnt_bodyid[jids[0]])
    fromto, deepest = np.zeros(6), (0.0, -1)
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        while b not in (0, root, ee):
            b = int(m.body_parentid[b])
        if b == root:  # on the arm (not elsewhere, not the end effector's own pad)
            deepest = min(deepest, (mujoco.mj_geomDistance(m, d, g, obj, 0.1, fromto), g))
    if deepest[0] < -OBJECT_OVERLAP:
        body = robot_names.body_name(m, arm, int(m.geom_bodyid[deepest[1]]))
        raise ConfigError(
            f"{label}: arms.{arm}: at the grasp the arm's body '{body}' is inside the object "
            f"({-1000 * deepest[0]:.0f} mm deep): the pad faces the object along the flange's +z, which must "
            f"point out of the arm, away from its last links (arms.{arm}.flange)"
        )


def add_keyframes(m: mujoco.MjModel, spec: mujoco.MjSpec, centre, radius: float, limits, grip_force: float,
                  object_mass: float, label: str, floor_z: float | None = None) -> dict:  # fmt: skip
    """Solve both poses for both arms, check them, add the keyframes to ``spec``; a report."""
    report = {}
    qpos = {"grasp": m.qpos0.copy(), "approach": m.qpos0.copy()}
    obj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_free")
    oadr = m.jnt_qposadr[obj]
    for key in qpos:
        qpos[key][oadr : oadr + 7] = [*centre, 1, 0, 0, 0]
    for side, arm in (("r", "right"), ("l", "left")):
        pose = solve_pad_pose(m, side, *grasp_targets(centre, radius)[side], label=label, floor_z=floor_z)
        if pose.position_error > 1e-4 or pose.rotation_error > 1e-3:
            limits_text = ", ".join(pose.binding) if pose.binding else "none"
            raise ConfigError(
                f"{label}: arms.{arm}: the grasp pose is out of reach: the pad stays "
                f"{pose.position_error * 1000:.1f} mm short, its orientation {np.degrees(pose.rotation_error):.1f} "
                f"deg off; joint limits binding: {limits_text} (move the object or the arm's base)"
            )
        if pose.manipulability < MIN_MANIPULABILITY:
            raise ConfigError(
                f"{label}: arms.{arm}: the grasp pose is singular (manipulability {pose.manipulability:.2g} < "
                f"{MIN_MANIPULABILITY}): move the object or the arm's base"
            )
        _check_clear_of_object(m, side, pose.q, label)
        approach = solve_pad_pose(m, side, *grasp_targets(centre, radius, APPROACH_GAP)[side], q_start=pose.q)
        if approach.position_error > 1e-4 or approach.rotation_error > 1e-3:
            raise ConfigError(
                f"{label}: arms.{arm}: the approach pose ({APPROACH_GAP * 1000:.0f} mm off the ball) is out of "
                f"reach by {approach.position_error * 1000:.1f} mm"
            )
        adr = [m.jnt_qposadr[j] for j in arm_joint_ids(m, side)]
        qpos["grasp"][adr] = pose.q
        qpos["approach"][adr] = approach.q
        report[arm] = {
            "grasp_q": pose.q.tolist(),
            "approach_q": approach.q.tolist(),
            "manipulability": pose.manipulability,
            "position_error_m": pose.position_error,
        }
    share = static_torque_share(m, qpos["grasp"], limits, grip_force, object_mass)
    for arm, s in share.items():
        report[arm]["static_torque_share"] = s.tolist()
        k = int(np.argmax(s))
        if s[k] > TORQUE_SHARE:
            joint = robot_names.joint_name(m, arm_joint_ids(m, arm[0])[k])
            raise ConfigError(
                f"{label}: arms.{arm}: holding the grasp takes {100 * s[k]:.0f} % of the torque limit of joint "
                f"'{joint}' statically (at most {100 * TORQUE_SHARE:.0f} %): a lighter object, another pose, or a "
                "stronger arm"
            )
    for key, q in qpos.items():
        spec.add_key(name=key, qpos=q.tolist())
    return report
