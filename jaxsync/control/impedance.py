"""Classical impedance: one admittance filter per arm (paper eqs. 8-11, 15)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class ImpedanceState(NamedTuple):
    """The compliant offset of each arm: (2, 6) e_i and de_i, world frame,
    [translation; rotation vector]."""

    offset: jax.Array
    rate: jax.Array


def init() -> ImpedanceState:
    return ImpedanceState(offset=jnp.zeros((2, 6)), rate=jnp.zeros((2, 6)))


def step(
    state: ImpedanceState,
    mass: jax.Array,
    damping: jax.Array,
    stiffness: jax.Array,
    frames: jax.Array,
    force_error: jax.Array,
    dt: float,
) -> tuple[ImpedanceState, jax.Array]:
    """Integrate both arms' admittance filters over one control period (eq. 15).

    Implicit in damping and stiffness: with de' the new rate and e' = e + dt de',
    M (de' - de)/dt = f - B de' - K e'. Explicit Euler needs dt B/M < 2 and
    the soft, heavily damped normal axis (B/M ~ 1000/s) breaks that at 500 Hz;
    this form is stable for any positive M, B, K and converges to the same
    continuous filter. Works per axis in the planned pad frame.

    Shapes: (2, 6) per arm, ``frames`` (2, 3, 3). Returns the new state and
    the filter accelerations dde = (de' - de)/dt, world frame, (2, 6).
    """

    def one(mass, damping, stiffness, frame, offset, rate, force_error):
        to_local = lambda v: jnp.concatenate([frame.T @ v[:3], frame.T @ v[3:]])  # noqa: E731
        to_world = lambda v: jnp.concatenate([frame @ v[:3], frame @ v[3:]])  # noqa: E731
        e, de, f = to_local(offset), to_local(rate), to_local(force_error)
        de_new = (mass / dt * de + f - stiffness * e) / (mass / dt + damping + stiffness * dt)
        e_new = e + dt * de_new
        return to_world(e_new), to_world(de_new), to_world((de_new - de) / dt)

    offset, rate, dde = jax.vmap(one)(mass, damping, stiffness, frames, state.offset, state.rate, force_error)
    return ImpedanceState(offset=offset, rate=rate), dde


def step_response(mass: float, damping: float, stiffness: float, force: float, t):
    """Analytic response e(t) of M e'' + B e' + K e = F, e(0) = e'(0) = 0 (for tests)."""

    t = np.asarray(t, dtype=float)
    wn = np.sqrt(stiffness / mass)
    zeta = damping / (2 * np.sqrt(stiffness * mass))
    final = force / stiffness
    if zeta < 1:
        wd = wn * np.sqrt(1 - zeta**2)
        return final * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t)))
    if zeta == 1:
        return final * (1 - np.exp(-wn * t) * (1 + wn * t))
    r1 = -wn * (zeta - np.sqrt(zeta**2 - 1))
    r2 = -wn * (zeta + np.sqrt(zeta**2 - 1))
    return final * (1 + (r2 * np.exp(r1 * t) - r1 * np.exp(r2 * t)) / (r1 - r2))
