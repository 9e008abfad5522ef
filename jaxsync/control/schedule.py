"""Gain schedules: gains that change with the task's phase.

A :class:`Schedule` holds one set of :class:`~jaxsync.Gains` per phase of the
task (close, squeeze, carry, hold: ``jaxsync.sim.scenario.plan``'s phases),
every leaf with a leading axis of 4. At time ``t`` the controller runs with

    g(t) = sum_p w_p(t) g_p,

where the weights step from one phase to the next across each phase
boundary with a quintic smoothstep of width :data:`BLEND_S` centred on the
boundary (C2: the rollout stays differentiable in the gains and in time). Away
from a boundary one weight is exactly 1 and the others exactly 0, so the gains
are that phase's (to rounding); a schedule whose phases are equal is the
constant gains, bit for bit. Both rollout backends evaluate a schedule in the same
place (``jaxsync.sim.closed_loop.control``), so MJX and MuJoCo C run the same law.

Example:
  >>> sched = constant(jaxsync.default_gains())            # 4 equal phases
  >>> sched = sched._replace(phases=sched.phases._replace(k_rk=jnp.array([0.5, 0.3, 0.2, 0.1])))
  >>> at(sched, jnp.array([0.6, 1.0, 2.2]), 3.0).k_rk  # after the hold starts (2.2 s): its gains
  Array(0.1, dtype=float64)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control.gains import Gains

PHASES = ("close", "squeeze", "carry", "hold")
BLEND_S = 0.05  # width of the blend across each phase boundary, s


class Schedule(NamedTuple):
    """Per-phase gains: every leaf of ``phases`` has a leading axis of len(PHASES)."""

    phases: Gains


def constant(g: Gains) -> Schedule:
    """The schedule whose every phase is ``g``."""
    return Schedule(Gains(*(jnp.broadcast_to(v, (len(PHASES),) + jnp.shape(v)) for v in g)))


def phase(sched: Schedule, i: int) -> Gains:
    """Phase ``i``'s gains."""
    return Gains(*(v[i] for v in sched.phases))


def _smoothstep(x):
    u = jnp.clip(x, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def weights(bounds: jax.Array, t) -> jax.Array:
    """(4,) phase weights at time ``t``: non-negative, summing to 1.

    ``bounds``: (3,) the starts of squeeze, carry and hold (s), e.g.
    ``jnp.stack(jaxsync.sim.scenario.phase_times(scenario))``."""
    up = _smoothstep((t - bounds) / BLEND_S + 0.5)  # 0 before a boundary, 1 after
    ones = jnp.ones((1,), dtype=up.dtype)
    after = jnp.concatenate([ones, up])  # phase p has begun
    ended = jnp.concatenate([up, 0.0 * ones])  # phase p has ended
    return after - ended


def at(gains, bounds: jax.Array, t) -> Gains:
    """The gains in force at time ``t``: ``gains`` itself when constant.
    ``bounds``: (3,) the phases' boundaries, as :func:`weights` takes them.

    Written as the first phase's gains plus each later phase's change, faded
    in across its boundary: equal phases add exact zeros, so a constant
    schedule gives the constant gains bit for bit, also inside the blends."""
    if not isinstance(gains, Schedule):
        return gains
    up = _smoothstep((t - bounds) / BLEND_S + 0.5)  # (3,) 0 before each boundary, 1 after

    def blend(v):
        steps = v[1:] - v[:-1]  # (3, ...) the change at each boundary
        return v[0] + jnp.tensordot(up, steps, axes=1)

    return Gains(*(blend(v) for v in gains.phases))


# ------------------------------------------------------------------ files


def validate(sched: Schedule) -> Schedule:
    """Each phase's gains checked as constant gains are (ConfigError naming the phase)."""
    for i, name in enumerate(PHASES):
        try:
            _gains.validate(phase(sched, i))
        except ConfigError as err:
            raise ConfigError(f"schedule phase '{name}': {err}") from None
    return sched


def to_dict(sched: Schedule) -> dict:
    """``{"phases": [...], "blend_s": ..., "close": {gains}, ...}``: each phase's gains in full."""
    d = {"phases": list(PHASES), "blend_s": BLEND_S}
    for i, name in enumerate(PHASES):
        d[name] = _gains.to_dict(phase(sched, i))
    return d


def from_dict(d: dict, base: Gains | None = None) -> Schedule:
    """A schedule from :func:`to_dict`'s form; a phase's missing gains keep ``base``
    (default gains), and the optional ``"all"`` entry sets gains for every phase
    before the phases' own entries."""
    if not isinstance(d, dict):
        raise ConfigError(f"a schedule must be a JSON object with the phases {list(PHASES)}, got {d!r}")
    unknown = sorted(set(d) - set(PHASES) - {"phases", "blend_s", "all"})
    if unknown:
        raise ConfigError(f"schedule: unknown entries {unknown}; allowed: {list(PHASES)}, 'all', 'phases', 'blend_s'")
    if "phases" in d and list(d["phases"]) != list(PHASES):
        raise ConfigError(f"schedule: phases must be {list(PHASES)} in this order, got {d['phases']!r}")
    if "blend_s" in d and not np.isclose(float(d["blend_s"]), BLEND_S):
        raise ConfigError(f"schedule: blend_s is fixed at {BLEND_S} s in this version, got {d['blend_s']!r}")
    common = _gains.from_dict(d.get("all", {}), base)
    per = []
    for name in PHASES:
        try:
            per.append(_gains.from_dict(d.get(name, {}), common))
        except ConfigError as err:
            raise ConfigError(f"schedule phase '{name}': {err}") from None
    return Schedule(Gains(*(jnp.stack(v) for v in zip(*per, strict=True))))


def to_file_dict(gains) -> dict:
    """The ``"gains"`` entry of a gains file: constant gains by name, or ``{"schedule": ...}``."""
    return {"schedule": to_dict(gains)} if isinstance(gains, Schedule) else _gains.to_dict(gains)


def classical_equivalent(gains):
    """:func:`jaxsync.classical_equivalent` for constant gains or each phase of a schedule."""
    if isinstance(gains, Schedule):
        return Schedule(_gains.classical_equivalent(gains.phases))
    return _gains.classical_equivalent(gains)
