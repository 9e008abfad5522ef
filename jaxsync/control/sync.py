"""Absolute and relative errors and the synchronous offsets (paper eqs. 12-14, 16, 17)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxsync.control import so3 as _so3


def absolute_error(pos_d: jax.Array, rot_d: jax.Array, pos: jax.Array, rot: jax.Array) -> jax.Array:
    """delta_i = x_id - x_i  (eq. 12), (6,): position difference and the SO(3)
    rotation vector from the actual to the planned pad orientation, world frame.

    Args: pos_d, pos (3,); rot_d, rot (3, 3).
    """
    return jnp.concatenate([pos_d - pos, _so3.rotation_error(rot_d, rot)])


def relative_compensation(delta: jax.Array, k_rk: jax.Array, k_lk: jax.Array) -> jax.Array:
    """delta_rk = k_rk (delta_r - delta_l), delta_lk = k_lk (delta_r - delta_l)   (eq. 13).

    Args: delta (2, 6) rows right, left. Returns (2, 6).
    """
    rel = delta[0] - delta[1]
    return jnp.stack([k_rk * rel, k_lk * rel])


def rigid_transport(r_ij: jax.Array) -> jax.Array:
    """(6, 6) map of a small displacement of pad j, carried through the rigid
    object, to the displacement of pad i, where r_ij = p_i - p_j:
    dp_i = dp_j + dtheta_j x r_ij, dtheta_i = dtheta_j."""
    top = jnp.concatenate([jnp.eye(3), -_so3.hat(r_ij)], axis=1)
    bottom = jnp.concatenate([jnp.zeros((3, 3)), jnp.eye(3)], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


# How eq. 16's cross term T_ij e_j is read (docs/controller.md):
#   "squeeze" (jaxsync's default): T_ij = -I. e_i - e_j keeps the part of the
#       two compliant offsets that changes the squeeze (the grip force stays
#       under force control) and cancels their common part, the one that
#       would move the object as one body (which sensor noise and force
#       imbalances would otherwise shake). No lever-arm term: with it
#       (T_ij = -transport), differential pad rotations leaked into a common
#       translation of both pads and the tangential resultant grew.
#   "rigid": T_ij = +transport (rigid_transport), the original design
#       note's reading (docs/controller.md): keeps the rigid-body part, cancels
#       the squeeze part. Measured: it does not hold the grip force.
#   "none": no cross term.
CROSS_TERMS = ("squeeze", "rigid", "none")


def cross_mapped(values: jax.Array, pads: jax.Array, cross_term: str) -> jax.Array:
    """x_ild = e_i + T_ij e_j for both arms (eq. 16), applied to (2, 6) offsets
    (or their rates and accelerations: the map is linear). ``pads``: (2, 3)
    planned pad positions, which fix the lever arm r_ij of the rigid reading."""
    if cross_term == "none":
        return values
    if cross_term == "squeeze":
        return jnp.stack([values[0] - values[1], values[1] - values[0]])
    t_rl = rigid_transport(pads[0] - pads[1])
    t_lr = rigid_transport(pads[1] - pads[0])
    return jnp.stack([values[0] + t_rl @ values[1], values[1] + t_lr @ values[0]])


def synchronous_offset(delta_k: jax.Array, k_il: jax.Array, mapped: jax.Array) -> jax.Array:
    """x_ik - x_id = delta_ik + k_il x_ild   (eqs. 14, 17), (2, 6).

    Args: delta_k (2, 6) from :func:`relative_compensation`; k_il (2,) = (k_rl,
    k_ll); mapped (2, 6) x_ild from :func:`cross_mapped`.
    """
    return delta_k + k_il[:, None] * mapped
