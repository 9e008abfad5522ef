"""Two controllers of the dual-arm literature, as offsets of the planned pad poses.

Both read the same sensing as the paper's controllers (each pad's pose and
the wrench the object exerts on it, ``jaxsync.physics.sensing``) and end in
the same joint-space law (eqs. 18, 19, ``jaxsync.control.joint_space``):
each returns the compliant offset x_ic - x_id of each pad, its rate and its
acceleration, world frame, [translation; rotation vector], (2, 6).

**Object-level impedance with an internal impedance** ("object_impedance";
F. Caccavale, P. Chiacchio, A. Marino, L. Villani, "Six-DOF impedance
control of dual-arm cooperative manipulators", IEEE/ASME Trans.
Mechatronics 13(5), 2008). The wrench error h~ = h - h_d of both pads (12,)
splits through the grasp matrix W = [W_r W_l] (the paper's eq. 7; W_i maps
a wrench at pad i to the object's reference point o, the planned pads'
midpoint: f_o = f_i, m_o = m_i + r_i x f_i with r_i = p_id - p_o) into

    h_E = W h~                           the external wrench on the object (6,)
    h_I = (I - W^+ W) h~                 the internal wrenches, W^+ = W^T (W W^T)^-1

An external impedance moves the object's compliant frame,
M_E dx_o'' + D_E dx_o' + K_E dx_o = h_E (object frame: the right pad's
planned frame), carried rigidly to each pad (dp_i = dp_o + dtheta_o x r_i);
an internal impedance per pad, M_I dx_i'' + D_I dx_i' + K_I dx_i = h_I,i
(pad frame), adds to it: x_ic - x_id = T_i dx_o + dx_i. Gains: obj_mass,
obj_damping, obj_stiffness (M_E, D_E, K_E) and imp_mass, imp_damping,
imp_stiffness (M_I, D_I, K_I).

**Cooperative task space with an internal-force loop** ("task_space"; P.
Chiacchio, S. Chiaverini, B. Siciliano, "Direct and inverse kinematics for
coordinated motion tasks of a two-manipulator system", ASME J. Dyn. Syst.
Meas. Control 118(4), 1996; F. Caccavale, P. Chiacchio, S. Chiaverini,
"Task-space regulation of cooperative manipulators", Automatica 36(6),
2000). The absolute variable x_a = (x_r + x_l)/2 tracks its plan (no
compliance); the relative variable x_rel = x_l - x_r is corrected by a PI
loop on the internal wrench, shared equally by the two pads:

    x_ic - x_id = K_P h_I,i + K_I int h_I,i dt     (pad frame, per axis)

(since h_I,r = -h_I,l for forces, the pads move apart by the relative
correction and the absolute variable does not move). The reference rate is
K_I h_I,i (the proportional part's derivative, a derivative of the sensor
noise, is left out) and the reference acceleration zero. Gains: force_p,
force_i (K_P, K_I).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxsync.control import so3 as _so3


class ObjectState(NamedTuple):
    """The object-level impedance's compliant frame, dx_o and its rate (6,), object frame."""

    offset: jax.Array
    rate: jax.Array


def init_object() -> ObjectState:
    return ObjectState(offset=jnp.zeros(6), rate=jnp.zeros(6))


def grasp_matrix(pads: jax.Array, centre: jax.Array) -> jax.Array:
    """W (6, 12): pad wrenches [f_r, m_r, f_l, m_l] (about each pad) -> the
    wrench about ``centre`` (eq. 7). ``pads`` (2, 3)."""

    def one(p):
        top = jnp.concatenate([jnp.eye(3), jnp.zeros((3, 3))], axis=1)
        bottom = jnp.concatenate([_so3.hat(p - centre), jnp.eye(3)], axis=1)
        return jnp.concatenate([top, bottom], axis=0)

    return jnp.concatenate([one(pads[0]), one(pads[1])], axis=1)


def split_wrenches(wrench_error: jax.Array, pads: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(h_E (6,) about the pads' midpoint, h_I (2, 6)) of pad wrench errors (2, 6)."""
    centre = pads.mean(axis=0)
    w = grasp_matrix(pads, centre)
    h = wrench_error.reshape(12)
    h_e = w @ h
    h_i = h - w.T @ jnp.linalg.solve(w @ w.T, h_e)
    return h_e, h_i.reshape(2, 6)


def transport_to_pads(dx: jax.Array, pads: jax.Array) -> jax.Array:
    """(2, 6) the displacement of each pad when the object frame at the pads'
    midpoint moves by ``dx`` (6,) (world frame), the grasp rigid."""
    centre = pads.mean(axis=0)
    return jnp.stack([jnp.concatenate([dx[:3] + jnp.cross(dx[3:], p - centre), dx[3:]]) for p in pads])


def _to_local(frame, v):
    return jnp.concatenate([frame.T @ v[:3], frame.T @ v[3:]])


def _to_world(frame, v):
    return jnp.concatenate([frame @ v[:3], frame @ v[3:]])


def object_step(
    state: ObjectState, mass, damping, stiffness, frame, h_e, dt
) -> tuple[ObjectState, jax.Array, jax.Array, jax.Array]:
    """One period of the external impedance (implicit in D_E and K_E, like
    ``jaxsync.control.impedance.step``). Returns the new state and dx_o, its
    rate and acceleration in the world frame (6,) each."""
    f = _to_local(frame, h_e)
    e, de = state.offset, state.rate
    de_new = (mass / dt * de + f - stiffness * e) / (mass / dt + damping + stiffness * dt)
    e_new = e + dt * de_new
    dde = (de_new - de) / dt
    return (
        ObjectState(offset=e_new, rate=de_new),
        _to_world(frame, e_new),
        _to_world(frame, de_new),
        _to_world(frame, dde),
    )


def task_space_offsets(force_p, force_i, integral, h_i, frames, dt):
    """The internal-force loop: (offsets, rates, accelerations (2, 6), the new
    integral of h_I (2, 6), world frame). ``frames`` (2, 3, 3) planned pad frames."""
    integral = integral + dt * h_i

    def one(frame, h, z):
        off = _to_world(frame, force_p * _to_local(frame, h) + force_i * _to_local(frame, z))
        rate = _to_world(frame, force_i * _to_local(frame, h))
        return off, rate

    off, rate = jax.vmap(one)(frames, h_i, integral)
    return off, rate, jnp.zeros_like(off), integral
