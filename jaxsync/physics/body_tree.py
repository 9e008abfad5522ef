"""The body tree's passes of MJX's position and velocity stages, vectorised.

MJX walks the tree with its generic ``scan.body_tree``, level by level, and
writes every quaternion and spatial-vector operation scalar by scalar: on the
dual-arm model its kinematics alone was a third of a physics step's program
and about half of the time XLA spent compiling the backward pass of the
position stage (docs/performance.md). Here, with the same formulas and the
same fields to rounding (tests/test_sensing.py):

- :func:`kinematics` (``qpos`` with its quaternions normalised, ``xanchor``,
  ``xaxis``, ``xpos``, ``xquat``, ``xmat``, ``xipos``, ``ximat``, geom and
  site frames): each tree level a few batched operations on its bodies;
- :func:`com_pos`, :func:`crb_body`, :func:`com_vel`, :func:`bias_force`,
  :func:`jac`, :func:`jac_dot`: a pass from the leaves up (subtree sums) or
  from the root down (motion accumulated along each chain) is one product
  with a static 0/1 matrix of the tree (:func:`tree_matrices`), every body
  and dof at once.

:func:`kinematics_plan` says whether a model's tree fits (at most one joint
per body, no mocap bodies); ``_physics`` runs MJX's own stages otherwise.
Pure JAX over ``mjx.Model`` fields; MJX's private modules stay in ``_physics``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

_FREE, _BALL, _SLIDE, _HINGE = (
    int(t)
    for t in (
        mujoco.mjtJoint.mjJNT_FREE,
        mujoco.mjtJoint.mjJNT_BALL,
        mujoco.mjtJoint.mjJNT_SLIDE,
        mujoco.mjtJoint.mjJNT_HINGE,
    )
)

# quat_mul(u, v)[i] = sum_jk _QMUL[i, j, k] u[j] v[k] (w, x, y, z)
_QMUL = np.zeros((4, 4, 4))
for _i, _j, _k, _sign in (
    (0, 0, 0, 1), (0, 1, 1, -1), (0, 2, 2, -1), (0, 3, 3, -1),
    (1, 0, 1, 1), (1, 1, 0, 1), (1, 2, 3, 1), (1, 3, 2, -1),
    (2, 0, 2, 1), (2, 1, 3, -1), (2, 2, 0, 1), (2, 3, 1, 1),
    (3, 0, 3, 1), (3, 1, 2, 1), (3, 2, 1, -1), (3, 3, 0, 1),
):  # fmt: skip
    _QMUL[_i, _j, _k] = _sign

# quat_to_mat(q).ravel()[i] = sum_jk _QMAT[i, j, k] q[j] q[k] (MJX's formula on the outer product)
_QMAT = np.zeros((9, 4, 4))
for _row, _terms in enumerate(
    (
        ((0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)),
        ((1, 2, 2), (0, 3, -2)),
        ((1, 3, 2), (0, 2, 2)),
        ((1, 2, 2), (0, 3, 2)),
        ((0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)),
        ((2, 3, 2), (0, 1, -2)),
        ((1, 3, 2), (0, 2, -2)),
        ((2, 3, 2), (0, 1, 2)),
        ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)),
    )
):
    for _j, _k, _c in _terms:
        _QMAT[_row, _j, _k] = _c


# cross(u, v)[i] = sum_jk _CROSS[i, j, k] u[j] v[k]
_CROSS = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _CROSS[_i, _j, _k], _CROSS[_i, _k, _j] = 1.0, -1.0


def quat_mul(u: jax.Array, v: jax.Array) -> jax.Array:
    """Batched quaternion product (..., 4) x (..., 4), MJX's ``math.quat_mul``."""
    return jnp.einsum("ijk,...j,...k->...i", _QMUL, u, v)


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Batched rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    return jnp.einsum("ijk,...j,...k->...i", _QMAT, q, q).reshape(*q.shape[:-1], 3, 3)


def rotate(v: jax.Array, q: jax.Array) -> jax.Array:
    """Batched ``math.rotate``: vectors (..., 3) rotated by unit quaternions (..., 4)."""
    s, u = q[..., :1], q[..., 1:]
    uv = jnp.sum(u * v, axis=-1, keepdims=True)
    uu = jnp.sum(u * u, axis=-1, keepdims=True)
    return 2.0 * uv * u + (s * s - uu) * v + 2.0 * s * jnp.einsum("ijk,...j,...k->...i", _CROSS, u, v)


def normalize(x: jax.Array) -> jax.Array:
    """Batched ``math.normalize`` along the last axis (a zero vector stays finite)."""
    n = jnp.linalg.norm(x, axis=-1, keepdims=True)
    return x / (n + 1e-6 * (n == 0.0))


def _rows(x: jax.Array, rows: np.ndarray) -> jax.Array:
    """``x[rows]`` for static rows: a slice when they are a contiguous range, a
    broadcast when they are all one row, else a gather (fewer operations for
    XLA to compile, and fewer scatters in the backward pass)."""
    rows = np.asarray(rows, dtype=int)
    if rows.size and (rows == rows[0]).all():
        return jnp.broadcast_to(x[rows[0]], (rows.size, *x.shape[1:]))
    if rows.size and (np.diff(rows) == 1).all():
        return jax.lax.slice_in_dim(x, int(rows[0]), int(rows[-1]) + 1)
    return x.at[rows].get(mode="promise_in_bounds", unique_indices=len(set(rows.tolist())) == rows.size)


@functools.lru_cache(maxsize=8)
def _plan_cached(parent: tuple, jntnum: tuple, jntadr: tuple, jnt_type: tuple, qposadr: tuple) -> tuple | None:
    nbody = len(parent)
    if any(n > 1 for n in jntnum):
        return None
    depth = [0] * nbody
    for b in range(1, nbody):
        depth[b] = depth[parent[b]] + 1
    where = {0: (0, 0)}  # body -> (chunk, row in chunk); chunk 0 is the world body
    levels, order, nchunk = [], [0], 1
    for level in range(1, max(depth, default=0) + 1):
        groups = {}
        for b in range(1, nbody):
            if depth[b] == level:
                kind = jnt_type[jntadr[b]] if jntnum[b] else -1
                groups.setdefault(kind, []).append(b)
        level_groups = []
        for kind, bodies in sorted(groups.items()):
            chunks = {where[parent[b]][0] for b in bodies}
            if len(chunks) == 1:  # the parents' rows in the one chunk that holds them
                source = (chunks.pop(), np.array([where[parent[b]][1] for b in bodies]))
            else:  # rows in the concatenation of every chunk so far
                sizes = np.cumsum([0] + [sum(1 for v in where.values() if v[0] == c) for c in range(nchunk)])
                source = (None, np.array([sizes[where[parent[b]][0]] + where[parent[b]][1] for b in bodies]))
            start = len(order)
            level_groups.append((kind, np.arange(start, start + len(bodies)), source))
            for i, b in enumerate(bodies):
                where[b] = (nchunk, i)
            order.extend(bodies)
            nchunk += 1
        levels.append(tuple(level_groups))
    order = np.array(order)
    joints = np.array([jntadr[b] for b in order if jntnum[b]], dtype=int)
    joint_rows = np.cumsum([0] + [jntnum[b] for b in order])  # row in `joints` of each body's joint
    return (
        tuple(levels),
        order,
        np.argsort(order),
        joints,
        joint_rows,
        np.array([qposadr[j] for j in joints], dtype=int),
    )


def kinematics_plan(m: mjx.Model) -> tuple | None:
    """The static level-by-level plan of :func:`kinematics` for ``m``, or None
    when MJX's own kinematics has to run (a body with several joints, or
    mocap bodies)."""
    if m.nmocap:
        return None
    return _plan_cached(
        tuple(int(p) for p in np.asarray(m.body_parentid)),
        tuple(int(n) for n in np.asarray(m.body_jntnum)),
        tuple(int(a) for a in np.asarray(m.body_jntadr)),
        tuple(int(t) for t in np.asarray(m.jnt_type)),
        tuple(int(a) for a in np.asarray(m.jnt_qposadr)),
    )


def kinematics(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.kinematics`` (same fields, same formulas), level by level."""
    plan = kinematics_plan(m)
    if plan is None:
        raise ValueError("kinematics: the model's tree is not covered (see kinematics_plan); use MJX's")
    levels, order, unorder, joints, joint_rows, qadr_all = plan
    # the model's constants in the plan's order, once: each group reads a slice
    body_pos, body_quat = _rows(m.body_pos, order), _rows(m.body_quat, order)
    jnt_pos, jnt_axis = _rows(m.jnt_pos, joints), _rows(m.jnt_axis, joints)
    qpos = d.qpos
    pos_chunks, quat_chunks = [body_pos[:1]], [body_quat[:1]]
    anchors, axes = [], []
    for groups in levels:
        for kind, rows, (chunk, parent_rows) in groups:
            if chunk is None:
                parent_pos = _rows(jnp.concatenate(pos_chunks), parent_rows)
                parent_quat = _rows(jnp.concatenate(quat_chunks), parent_rows)
            else:
                parent_pos, parent_quat = _rows(pos_chunks[chunk], parent_rows), _rows(quat_chunks[chunk], parent_rows)
            pos = parent_pos + rotate(_rows(body_pos, rows), parent_quat)
            quat = quat_mul(parent_quat, _rows(body_quat, rows))
            if kind >= 0:
                jrows = joint_rows[rows]
                qadr = qadr_all[jrows]
            if kind == _FREE:
                free = qpos[qadr[:, None] + np.arange(7)]
                anchor, axis = free[:, :3], jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), (len(rows), 3))
                pos, quat = free[:, :3], normalize(free[:, 3:])
                qpos = qpos.at[qadr[:, None] + np.arange(3, 7)].set(quat)
            elif kind >= 0:
                jpos, jaxis = _rows(jnt_pos, jrows), _rows(jnt_axis, jrows)
                anchor, axis = rotate(jpos, quat) + pos, rotate(jaxis, quat)
                if kind == _BALL:
                    qloc = normalize(qpos[qadr[:, None] + np.arange(4)])
                    qpos = qpos.at[qadr[:, None] + np.arange(4)].set(qloc)
                    quat = quat_mul(quat, qloc)
                    pos = anchor - rotate(jpos, quat)
                elif kind == _HINGE:
                    half = 0.5 * (_rows(qpos, qadr) - _rows(m.qpos0, qadr))[:, None]
                    qloc = jnp.concatenate([jnp.cos(half), jaxis * jnp.sin(half)], axis=-1)
                    quat = quat_mul(quat, qloc)
                    pos = anchor - rotate(jpos, quat)
                elif kind == _SLIDE:
                    pos = pos + axis * (_rows(qpos, qadr) - _rows(m.qpos0, qadr))[:, None]
                else:
                    raise RuntimeError(f"unrecognized joint type: {kind}")
                anchors.append(anchor)
                axes.append(axis)
            if kind == _FREE:
                anchors.append(anchor)
                axes.append(axis)
            pos_chunks.append(pos)
            quat_chunks.append(quat)
    xpos = _rows(jnp.concatenate(pos_chunks), unorder)
    xquat = _rows(jnp.concatenate(quat_chunks), unorder)
    xmat = quat_to_mat(xquat)
    if anchors:
        jorder = np.argsort(joints)
        xanchor, xaxis = _rows(jnp.concatenate(anchors), jorder), _rows(jnp.concatenate(axes), jorder)
    else:
        xanchor, xaxis = jnp.zeros((0, 3)), jnp.zeros((0, 3))

    def local_to_global(body, local_pos, local_quat):
        quat = _rows(xquat, body)
        return _rows(xpos, body) + rotate(local_pos, quat), quat_to_mat(quat_mul(quat, local_quat))

    xipos, ximat = local_to_global(np.arange(m.nbody), m.body_ipos, m.body_iquat)
    d = d.replace(qpos=qpos, xanchor=xanchor, xaxis=xaxis, xpos=xpos, xquat=xquat, xmat=xmat, xipos=xipos, ximat=ximat)
    if m.ngeom:
        geom_xpos, geom_xmat = local_to_global(np.asarray(m.geom_bodyid), m.geom_pos, m.geom_quat)
        d = d.replace(geom_xpos=geom_xpos, geom_xmat=geom_xmat)
    if m.nsite:
        site_xpos, site_xmat = local_to_global(np.asarray(m.site_bodyid), m.site_pos, m.site_quat)
        d = d.replace(site_xpos=site_xpos, site_xmat=site_xmat)
    return d


# ------------------------------------------------ the tree's sums as matrices

# what a dof is, for the per-dof formulas
_DOF_HINGE, _DOF_SLIDE, _DOF_BALL, _DOF_FREE_LIN, _DOF_FREE_ROT = range(5)


@functools.lru_cache(maxsize=8)
def _tree_cached(parent: tuple, dof_body: tuple, dof_kind: tuple, dof_first: tuple) -> tuple:
    nbody, nv = len(parent), len(dof_body)
    ancestor = np.eye(nbody)  # ancestor[b, a] = 1 when a is b or one of its ancestors
    for b in range(1, nbody):
        ancestor[b] = ancestor[parent[b]]
        ancestor[b, b] = 1.0
    chain = ancestor[:, list(dof_body)] if nv else np.zeros((nbody, 0))
    before = np.zeros((nv, nv))
    for i in range(nv):
        if dof_kind[i] == _DOF_FREE_LIN:
            continue  # MJX sets its cdof_dot to zero
        before[i] = chain[parent[dof_body[i]]]
        if dof_kind[i] == _DOF_FREE_ROT:  # crossed with the velocity after the joint's translation
            before[i, dof_first[i] : dof_first[i] + 3] = 1.0
    return ancestor.T.copy(), chain, before, np.array(dof_kind)


def tree_matrices(m: mjx.Model) -> tuple:
    """Static matrices of the body tree of ``m`` (at most one joint per body):

    - ``subtree`` (nbody, nbody): [a, b] = 1 when b is in a's subtree; a pass
      from the leaves to the root (MJX's ``scan.body_tree(..., reverse=True)``)
      is one product with it;
    - ``chain`` (nbody, nv): [b, i] = 1 when dof i moves body b; a pass from
      the root accumulating per-dof motions is one product with it;
    - ``before`` (nv, nv): [i, j] = 1 when dof j's motion is in the velocity
      that dof i's ``cdof_dot`` crosses (MJX's ``com_vel``: the ancestors'
      dofs, and for a free joint's rotation its translation);
    - the kind of each dof (``_DOF_*``).
    """
    jnt_type, dof_jnt, dofadr = np.asarray(m.jnt_type), np.asarray(m.dof_jntid), np.asarray(m.jnt_dofadr)
    kinds, firsts = [], []
    for i in range(m.nv):
        t, first = int(jnt_type[dof_jnt[i]]), int(dofadr[dof_jnt[i]])
        if t == _FREE:
            kinds.append(_DOF_FREE_LIN if i - first < 3 else _DOF_FREE_ROT)
        else:
            kinds.append({_HINGE: _DOF_HINGE, _SLIDE: _DOF_SLIDE, _BALL: _DOF_BALL}[t])
        firsts.append(first)
    return _tree_cached(
        tuple(int(p) for p in np.asarray(m.body_parentid)),
        tuple(int(b) for b in np.asarray(m.dof_bodyid)),
        tuple(kinds),
        tuple(firsts),
    )


def cross(u: jax.Array, v: jax.Array) -> jax.Array:
    """Batched cross product (..., 3)."""
    return jnp.einsum("ijk,...j,...k->...i", _CROSS, u, v)


def motion_cross(u: jax.Array, v: jax.Array) -> jax.Array:
    """Batched ``math.motion_cross`` of spatial motions (..., 6) [rotation, translation]."""
    return jnp.concatenate(
        [cross(u[..., :3], v[..., :3]), cross(u[..., 3:], v[..., :3]) + cross(u[..., :3], v[..., 3:])], -1
    )


def motion_cross_force(v: jax.Array, f: jax.Array) -> jax.Array:
    """Batched ``math.motion_cross_force`` (..., 6)."""
    return jnp.concatenate(
        [cross(v[..., :3], f[..., :3]) + cross(v[..., 3:], f[..., 3:]), cross(v[..., :3], f[..., 3:])], -1
    )


_TRI = np.array([[0, 3, 4], [3, 1, 5], [4, 5, 2]])  # cinert's (xx, yy, zz, xy, xz, yz) as a matrix


def inert_mul(i: jax.Array, v: jax.Array) -> jax.Array:
    """Batched ``math.inert_mul``: com-based inertias (..., 10) times motions (..., 6)."""
    inr, pos, mass = i[..., _TRI], i[..., 6:9], i[..., 9:]
    ang = jnp.einsum("...ij,...j->...i", inr, v[..., :3]) + cross(pos, v[..., 3:])
    return jnp.concatenate([ang, mass * v[..., 3:] - cross(pos, v[..., :3])], -1)


def com_pos(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.com_pos``: ``subtree_com``, ``cinert``, ``cdof``; the
    subtree sums as one product, every body and dof at once."""
    subtree, _, _, kind = tree_matrices(m)
    mass = m.body_mass
    total = subtree @ mass
    subtree_com = (subtree @ (d.xipos * mass[:, None])) / jnp.maximum(total, mujoco.mjMINVAL)[:, None]
    subtree_com = jnp.where((total < mujoco.mjMINVAL)[:, None], d.xipos, subtree_com)
    root_com = _rows(subtree_com, np.asarray(m.body_rootid))
    off = d.xipos - root_com
    inert = jnp.einsum("bij,bj,bkj->bik", d.ximat, m.body_inertia, d.ximat)
    inert = inert + mass[:, None, None] * (
        jnp.sum(off * off, -1)[:, None, None] * np.eye(3) - off[:, :, None] * off[:, None, :]
    )
    iu = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])
    cinert = jnp.concatenate([inert[:, iu[0], iu[1]], off * mass[:, None], mass[:, None]], -1)
    # per dof: the motion axis a, and [a, a x offset] (rotation) or [0, a] (translation)
    dof_body, dof_jnt = np.asarray(m.dof_bodyid), np.asarray(m.dof_jntid)
    col = np.arange(m.nv) - np.asarray(m.jnt_dofadr)[dof_jnt]  # the dof's column in its joint
    rot3 = (kind == _DOF_BALL) | (kind == _DOF_FREE_ROT)
    axis = _rows(d.xaxis, dof_jnt)
    if rot3.any():
        frame = jnp.swapaxes(_rows(d.xmat, dof_body), -1, -2)[
            np.arange(m.nv), np.where(kind == _DOF_FREE_ROT, col - 3, col) % 3
        ]
        axis = jnp.where(rot3[:, None], frame, axis)
    if (kind == _DOF_FREE_LIN).any():
        axis = jnp.where((kind == _DOF_FREE_LIN)[:, None], np.eye(3)[col % 3], axis)
    offset = _rows(root_com, dof_body) - _rows(d.xanchor, dof_jnt)
    rotational = ((kind == _DOF_HINGE) | rot3)[:, None]
    cdof = jnp.concatenate([jnp.where(rotational, axis, 0.0), jnp.where(rotational, cross(axis, offset), axis)], -1)
    return d.replace(subtree_com=subtree_com, cdof=cdof).tree_replace({"_impl.cinert": cinert})


def crb_body(m: mjx.Model, d: mjx.Data) -> jax.Array:
    """MJX's composite inertias (``smooth.crb``'s ``crb``): subtree sums of ``cinert``, the world's zero."""
    subtree = tree_matrices(m)[0]
    return (subtree @ d._impl.cinert).at[0].set(0.0)


def com_vel(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.com_vel``: ``cvel`` (accumulated down the tree, one
    product) and ``cdof_dot`` (each dof's motion crossed with the velocity
    before it)."""
    _, chain, before, _ = tree_matrices(m)
    motion = d.cdof * d.qvel[:, None]
    cvel = chain @ motion
    cdof_dot = motion_cross(before @ motion, d.cdof)
    return d.replace(cvel=cvel, cdof_dot=cdof_dot)


def bias_force(m: mjx.Model, d: mjx.Data, gravity: jax.Array) -> jax.Array:
    """MJX's ``smooth.rne`` without accelerations (``qfrc_bias``): each body's
    ``cacc`` from ``gravity`` (6,) ([0, -g], or zero) and cdof_dot qvel down the
    tree, its inertial wrench, the wrenches summed up the tree."""
    subtree, chain, _, _ = tree_matrices(m)
    cacc = gravity + chain @ (d.cdof_dot * d.qvel[:, None])
    cinert = d._impl.cinert
    frc = inert_mul(cinert, cacc) + motion_cross_force(d.cvel, inert_mul(cinert, d.cvel))
    cfrc = subtree @ frc
    return jnp.sum(d.cdof * _rows(cfrc, np.asarray(m.dof_bodyid)), -1)


def jac(m: mjx.Model, d: mjx.Data, point: jax.Array, body_id: int) -> tuple[jax.Array, jax.Array]:
    """MJX's ``support.jac`` ((nv, 3) translational and rotational Jacobians of a
    point on a body) with the chain's mask static."""
    mask = tree_matrices(m)[1][body_id][:, None]
    offset = point - d.subtree_com[int(np.asarray(m.body_rootid)[body_id])]
    return (d.cdof[:, 3:] + cross(d.cdof[:, :3], offset)) * mask, d.cdof[:, :3] * mask


def jac_dot(m: mjx.Model, d: mjx.Data, point: jax.Array, body_id: int) -> tuple[jax.Array, jax.Array]:
    """MJX's ``support.jac_dot`` (their time derivatives) with the chain's mask static."""
    _, chain, _, kind = tree_matrices(m)
    mask = chain[body_id][:, None]
    offset = point - d.subtree_com[int(np.asarray(m.body_rootid)[body_id])]
    cvel = d.cvel[body_id]
    pvel_lin = cvel[3:] - cross(offset, cvel[:3])
    cdof_dot = d.cdof_dot
    quat = (kind == _DOF_BALL) | (kind == _DOF_FREE_ROT)
    if quat.any():  # MJX uses the body's own velocity for quaternion dofs
        cdof_dot = jnp.where(quat[:, None], motion_cross(_rows(d.cvel, np.asarray(m.dof_bodyid)), d.cdof), cdof_dot)
    jacp = cdof_dot[:, 3:] + cross(cdof_dot[:, :3], offset) + cross(d.cdof[:, :3], pvel_lin)
    return jacp * mask, cdof_dot[:, :3] * mask
