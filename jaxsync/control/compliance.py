"""How stiff a controller makes the arm feel at the pad (docs/metrics.md).

The apparent stiffness along a pad axis: a force step of 1 N on the right
pad along that axis (its planned pad frame), the left pad's wrench at its set
point, the plan at rest; the pads follow the controller's reference
exactly (the joint-space law's own compliance, 1 / (Lambda kp_pos), is in
series with it and the same for every controller). After ``PROBE_TIME`` the
pad has moved by dx; the apparent stiffness is 1 N / dx. An integrating
force loop (the normal axis at the default gains) still has a finite figure:
how far it has yielded in that time. Pure JAX: the tuner bounds it.

Controllers whose offsets depend on the pads' own positions (the
synchronous controller's absolute errors delta_i = x_id - x_i) are solved
at each period with the pads at their reference (delta_i = -offset_i): the
offsets are affine in delta, so offset = (I + J)^-1 offset(delta = 0),
J = d offset / d delta.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.control import controller as _controller
from jaxsync.physics.inertia import pad_frames

PROBE_TIME = 0.1  # s: of the order of a contact's first impact and of the task's phases
NORMAL, TANGENTIAL = 2, (0, 1)  # pad-frame axes


def probe_geometry(model) -> tuple[np.ndarray, np.ndarray]:
    """(pad positions (2, 3), pad frames (2, 3, 3)) at the grasp keyframe, the
    geometry the probe applies its force in."""
    return pad_frames(model.mj_model, "grasp")


def displacement(kind: str, gains, pads_pos, pads_rot, dt: float, axis: int, cross_term: str = "squeeze"):
    """() the right pad's displacement along its pad-frame ``axis`` (m) after
    ``PROBE_TIME`` under a 1 N step along that axis."""
    options = _controller.ControllerOptions(kind=kind, cross_term=cross_term)
    pads_pos, pads_rot = jnp.asarray(pads_pos), jnp.asarray(pads_rot)
    ref = _controller.Reference(
        pad_pos=pads_pos,
        pad_rot=pads_rot,
        pad_vel=jnp.zeros((2, 6)),
        pad_acc=jnp.zeros((2, 6)),
        wrench=jnp.zeros((2, 6)),
        q_rest=jnp.zeros((2, 1)),
    )
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be a translation of the pad frame (0, 1, 2), got {axis}")
    direction = pads_rot[0][:, axis]
    force = jnp.zeros((2, 6)).at[0, :3].set(direction)

    def offsets_at(delta, state):
        # pads placed so that their absolute errors are delta (rotations to first order)
        pos = pads_pos - delta[:, :3]
        pads = _controller.Pads(pos=pos, rot=pads_rot, wrench=force)
        (off, _, _), new, _, _ = _controller.offsets(options, gains, state, pads, ref, dt)
        return off, new

    def period(state, _):
        def with_state(d):
            off, new = offsets_at(d, state)
            return off, (off, new)

        # one pass gives the offsets at delta = 0, the new state and d offset / d delta
        jac, (off0, new) = jax.jacfwd(with_state, has_aux=True)(jnp.zeros((2, 6)))
        jac = jac.reshape(12, 12)
        off = jnp.linalg.solve(jnp.eye(12) + jac, off0.reshape(12)).reshape(2, 6)
        return new, off

    n = int(round(PROBE_TIME / dt))
    _, offs = jax.lax.scan(period, _controller.init(), None, length=n)
    return offs[-1, 0, :3] @ direction


def apparent_stiffness(kind: str, gains, pads_pos, pads_rot, dt: float, cross_term: str = "squeeze") -> dict:
    """{"normal": N/m, "tangential": N/m (the stiffer of the two tangential
    axes)} at the right pad (see the module's docstring). Differentiable in ``gains``."""
    dx = [displacement(kind, gains, pads_pos, pads_rot, dt, a, cross_term) for a in (NORMAL, *TANGENTIAL)]
    stiff = [1.0 / jnp.maximum(d, 1e-12) for d in dx]
    return {"normal": stiff[0], "tangential": jnp.maximum(stiff[1], stiff[2])}


def stiffness_at_pad(model, controller: str, gains) -> dict | None:
    """The apparent stiffness at the right pad of constant ``gains`` on
    ``model`` at the grasp, N/m by axis (:func:`apparent_stiffness`, jitted).
    For the controllers of position-controlled arms, whose offsets come from
    joint space, the probe reads a Cartesian stand-in: the same mass, damping
    and spring at the pad (ros2_synchronous: the synchronous law, whose offset
    its command carries at rest)."""
    pos, rot = probe_geometry(model)
    dt = float(model.mj_model.opt.timestep)
    k = jax.jit(lambda g: apparent_stiffness(controller, g, pos, rot, dt))(gains)
    return {axis: float(v) for axis, v in k.items()}
