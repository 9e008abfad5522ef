"""Orientation errors on SO(3): a gradient-safe log and exp map.

Never subtract Euler angles or quaternions component-wise: the error between
two rotations is the rotation vector of their relative rotation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_EPS = 1e-9


def hat(w: jax.Array) -> jax.Array:
    """(3,) -> (3, 3) skew-symmetric matrix, hat(w) @ v = w x v."""
    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def log(rot: jax.Array) -> jax.Array:
    """Rotation matrix (3, 3) -> rotation vector (3,), angle in [0, pi).

    theta = atan2(|w|, (tr R - 1)/2) with w = vee(R - R^T)/2 = sin(theta) axis;
    theta / sin(theta) is replaced by its series 1 + theta^2/6 near zero, so
    the value and the gradient stay finite at the identity (MJX's safe-norm
    pattern). Rotations near pi are not expected as tracking errors; there
    the result is clamped rather than NaN.
    """
    w = 0.5 * jnp.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    s2 = jnp.sum(w * w)
    small = s2 < _EPS**2
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    c = 0.5 * (jnp.trace(rot) - 1.0)
    theta = jnp.arctan2(s, c)
    scale = jnp.where(small, 1.0 + s2 / 6.0, theta / jnp.maximum(s, _EPS))
    return scale * w


def exp(w: jax.Array) -> jax.Array:
    """Rotation vector (3,) -> rotation matrix (3, 3) (Rodrigues), safe at zero."""
    t2 = jnp.sum(w * w)
    small = t2 < _EPS**2
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / jnp.where(small, 1.0, t2))
    k = hat(w)
    return jnp.eye(3) + a * k + b * (k @ k)


def rotation_error(rot_desired: jax.Array, rot: jax.Array) -> jax.Array:
    """World-frame rotation vector (3,) that takes ``rot`` to ``rot_desired``."""
    return log(rot_desired @ rot.T)
