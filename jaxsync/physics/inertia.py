"""The arms' apparent inertia at the pads, on MuJoCo C at a keyframe.

Lambda^-1 = J M^-1 J^T is the operational-space inverse inertia of one arm at
its pad (J the 6 x n pad Jacobian, M the arm's block of the joint-space mass
matrix, armature included); its diagonal in the pad frame, inverted, is the
mass (kg) or rotational inertia (kg m^2) the pad presents along each of its
axes x, y, z (z: the normal) and about them. It sets how fast a force loop
through the pad may be (``jaxsync.control.gains.stability_ratio``).
"""

from __future__ import annotations

import mujoco
import numpy as np


def arm_joint_ids(m: mujoco.MjModel, side: str) -> list[int]:
    """The ids of an arm's joints ``{side}_joint1``, ``{side}_joint2``, ... in
    jaxsync's convention, as many as the model has (``side``: "r" or "l")."""
    ids = []
    while (j := mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{side}_joint{len(ids) + 1}")) >= 0:
        ids.append(j)
    return ids


def pad_apparent_inertia(m: mujoco.MjModel, key: str = "grasp") -> np.ndarray:
    """(2, 6) per arm (right, left), pad-frame axes x, y, z then rotations about them."""
    d = mujoco.MjData(m)
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key)
    if k >= 0:
        mujoco.mj_resetDataKeyframe(m, d, k)
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    out = []
    for p in ("r", "l"):
        dofs = [m.jnt_dofadr[j] for j in arm_joint_ids(m, p)]
        site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{p}_pad")
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jp, jr, site)
        J = np.concatenate([jp, jr])[:, dofs]
        inv = J @ np.linalg.solve(M[np.ix_(dofs, dofs)], J.T)
        R = d.site_xmat[site].reshape(3, 3)
        out.append(np.concatenate([1 / np.diag(R.T @ inv[:3, :3] @ R), 1 / np.diag(R.T @ inv[3:, 3:] @ R)]))
    return np.stack(out)


def pad_frames(m: mujoco.MjModel, key: str = "grasp") -> tuple[np.ndarray, np.ndarray]:
    """(positions (2, 3), frames (2, 3, 3)) of the pads (right, left) at keyframe ``key``."""
    d = mujoco.MjData(m)
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key)
    if k >= 0:
        mujoco.mj_resetDataKeyframe(m, d, k)
    mujoco.mj_kinematics(m, d)
    sites = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{p}_pad") for p in ("r", "l")]
    return np.stack([d.site_xpos[s].copy() for s in sites]), np.stack([d.site_xmat[s].reshape(3, 3) for s in sites])
