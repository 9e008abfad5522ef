"""A family of couplings between the two arms, on top of ros2_controllers'
admittance rule: the controllers ``"ros2_coupled"`` and
``"ros2_coupled_direct"`` (docs/coupling.md).

Each arm runs the stock rule (``jaxsync.control.ros2_loop``); the coupling is
one small step beside it that offsets the target the rule's reference joints
follow. Per arm i (j the other), in arm i's planned pad frame R_i (x, y
tangential, z the pad normal, then rotations about them), four channels, each
a per-axis gain c and a first-order filter a (y' = a u + (1 - a) y; a = 1
passes the input through):

  ``rel``    u = R_i^T (delta_i - delta_j), the absolute errors' difference
             (eq. 12: delta_i = x_id - x_i from the sensed pads; the paper's
             relative error, taken from arm i's side);
  ``own``    u = R_i^T e_i, the arm's own rule offset e_i = J_i dq_i;
  ``other``  u = R_i^T e_j, the other arm's rule offset;
  ``force``  u = R_i^T (f_j - f_jd) / (K_i + B_i / T), T = ``FORCE_TIME``,
             the other arm's wrench error over arm i's own admittance as it
             shows over T (per axis: a spring K_i yields 1 / K_i, a damper
             B_i about T / B_i; 0 where both are 0): c = 1 yields to the other
             arm's force error about as far as arm i's rule yields to its
             own within T.

The offset is o_i = R_i sum_c (c ⊙ y_c + X_c y_c), its rate alike with y'_c
(the full 6x6 block of a channel per arm: the gain c its diagonal,
``cpl_block`` X_c its off-diagonal part, 0 by default; the rates of the own
and other channels are the rule offsets' rates J dq dot, filtered alike;
rel and force carry none). Where it enters (``PLACEMENTS``, the
controller's name says which: ``jaxsync.control.names.FAMILY``):

  ``reference`` (``ros2_coupled``): the target of arm i's reference joints is the plan plus
             o_i, so the command is q_ref + dq_i: once the reference has
             caught up (a time 1 / lambda, lambda = 2 kp_pos / kd_pos) the
             pad's offset is e_i + o_i;
  ``direct`` (``ros2_coupled_direct``): o_i goes onto the rule's reference joints through the damped
             least squares J# in the same period, the reference following
             the plan alone.

Special cases (tests check both): every gain 0 is the rule alone
(``ros2_admittance``, whatever the filters); ``rel`` = (k_rk, -k_lk) per
arm, ``own`` = k_il - 1, ``other`` = -k_il, filters 1 and the reference
placement is ``ros2_synchronous`` with its squeeze cross term (o_i = k_ik
(delta_r - delta_l) + k_il (e_i - e_j) - e_i).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

CHANNELS = ("rel", "own", "other", "force")
GAIN_FIELDS = tuple(f"cpl_{c}" for c in CHANNELS)
FILTER_FIELDS = tuple(f"cpl_{c}_a" for c in CHANNELS)
BLOCK_FIELD = "cpl_block"
"""(4, 2, 6, 6): each channel's off-diagonal pad-frame block per arm (channels
as ``CHANNELS``, rows right then left); the diagonal is the channel's gain
``cpl_<channel>``, so the block's own diagonal must be 0."""
FIELDS = GAIN_FIELDS + FILTER_FIELDS + (BLOCK_FIELD,)
OFF_DIAGONAL = 1.0 - np.eye(6)  # NumPy: importing jaxsync must not start JAX's backend
PLACEMENTS = ("reference", "direct")
FORCE_TIME = 0.1
"""s: the time over which the force channel's scale is arm i's admittance (the
compliance probe's, ``jaxsync.control.compliance.PROBE_TIME``)."""
GAIN_MAX = 2.0
"""|c| <= 2 per channel and axis: the paper's own-offset factor k_il - 1 lies
in (-2, 0) for |k_il| < 1."""


class CouplingState(NamedTuple):
    """Each channel's filtered input and rate, (4, 2, 6): channels as
    ``CHANNELS``, rows right then left, each arm's planned pad frame."""

    value: jax.Array
    rate: jax.Array


def init(dtype=None) -> CouplingState:
    z = jnp.zeros((len(CHANNELS), 2, 6), dtype=dtype)
    return CouplingState(value=z, rate=z)


def to_pad(rot: jax.Array, v: jax.Array) -> jax.Array:
    """(6,) world-frame [translation; rotation] into the frame ``rot``."""
    return jnp.concatenate([rot.T @ v[:3], rot.T @ v[3:]])


def from_pad(rot: jax.Array, v: jax.Array) -> jax.Array:
    """(6,) frame ``rot`` -> world."""
    return jnp.concatenate([rot @ v[:3], rot @ v[3:]])


def inputs(gains, delta, e, e_dot, force_error, pad_rot):
    """The channels' inputs and rates, (4, 2, 6) each, from the absolute
    errors ``delta`` (2, 6), the rule offsets ``e`` and rates ``e_dot``
    (2, 6), the pads' wrench errors ``force_error`` f_i - f_id (2, 6), all
    world frame, and the planned pad rotations ``pad_rot`` (2, 3, 3)."""
    k = gains.imp_stiffness + gains.imp_damping / FORCE_TIME
    safe = jnp.where(k > 0, k, 1.0)
    inv_k = jnp.where(k > 0, 1.0 / safe, 0.0)
    zero = jnp.zeros_like(e)
    rows, rates = [], []
    for i in range(2):
        j = 1 - i
        rot = pad_rot[i]
        rows.append(
            jnp.stack(
                [
                    to_pad(rot, delta[i] - delta[j]),
                    to_pad(rot, e[i]),
                    to_pad(rot, e[j]),
                    to_pad(rot, force_error[j]) * inv_k[i],
                ]
            )
        )
        rates.append(jnp.stack([zero[i], to_pad(rot, e_dot[i]), to_pad(rot, e_dot[j]), zero[i]]))
    return jnp.stack(rows, axis=1), jnp.stack(rates, axis=1)


def step(gains, state: CouplingState, u, u_dot, pad_rot):
    """One period of the filters and the offset: returns (o (2, 6), its rate
    (2, 6), world frame, the new state)."""
    a = jnp.stack([getattr(gains, f) for f in FILTER_FIELDS])
    new = CouplingState(value=a * u + (1.0 - a) * state.value, rate=a * u_dot + (1.0 - a) * state.rate)
    return *offset(gains, new, pad_rot), new


def offset(gains, state: CouplingState, pad_rot):
    """o_i = R_i sum_c (c ⊙ y_c + X_c y_c) and its rate alike with the filtered
    rates, (2, 6) each, world frame, from the filters' ``state`` and the
    planned pad rotations ``pad_rot`` (2, 3, 3)."""
    c = jnp.stack([getattr(gains, f) for f in GAIN_FIELDS])
    x = getattr(gains, BLOCK_FIELD) * OFF_DIAGONAL
    o = jnp.sum(c * state.value, axis=0) + jnp.einsum("cirk,cik->ir", x, state.value)
    o_dot = jnp.sum(c * state.rate, axis=0) + jnp.einsum("cirk,cik->ir", x, state.rate)
    off = jnp.stack([from_pad(pad_rot[i], o[i]) for i in range(2)])
    off_vel = jnp.stack([from_pad(pad_rot[i], o_dot[i]) for i in range(2)])
    return off, off_vel


def of_synchronous(gains):
    """``gains`` with the family set to ros2_synchronous's coupling (squeeze
    cross term): rel = (k_rk, -k_lk), own = k_il - 1, other = -k_il per arm,
    every axis, filters 1."""
    full = lambda right, left: jnp.stack(  # noqa: E731
        [jnp.full(6, right, dtype=gains.imp_mass.dtype), jnp.full(6, left, dtype=gains.imp_mass.dtype)]
    )
    one = jnp.ones_like(gains.imp_mass)
    return gains._replace(
        cpl_rel=full(gains.k_rk, -gains.k_lk),
        cpl_own=full(gains.k_rl - 1.0, gains.k_ll - 1.0),
        cpl_other=full(-gains.k_rl, -gains.k_ll),
        cpl_force=jnp.zeros_like(gains.imp_mass),
        cpl_rel_a=one,
        cpl_own_a=one,
        cpl_other_a=one,
        cpl_force_a=one,
        cpl_block=jnp.zeros_like(gains.cpl_block),
    )
