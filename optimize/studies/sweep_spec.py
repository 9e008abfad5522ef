"""The parameter grammar of sweeps: names, values and how a point becomes a batch.

A sweep is a table of points, one column per ``--param NAME=VALUES``. A name
picks a leaf of :class:`~jaxsync.Gains` or :class:`~jaxsync.Scenario` (or an
entry of one: ``imp_stiffness.r.z``, ``lift.z``) or the noise seed; VALUES is a
grid (``lo:hi:n``, ``a,b,c``, ``v``) or, with ``--samples``, an interval.
:func:`build_batch` writes the points into batched gains and scenarios.
"""

from __future__ import annotations

import dataclasses
import math
import re

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control.gains import Gains
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.scenario import Scenario

AXES = {"x": 0, "y": 1, "z": 2, "rx": 3, "ry": 4, "rz": 5}
ARMS = {"r": 0, "right": 0, "l": 1, "left": 1}
VEC_AXES = {"x": 0, "y": 1, "z": 2}
PER_ARM_GAINS = ("imp_mass", "imp_damping", "imp_stiffness") + _gains.FAMILY_FIELDS
AXIS_GAINS = ("obj_mass", "obj_damping", "obj_stiffness", "force_p", "force_i")  # (6,): one per axis
SCALAR_GAINS = tuple(f for f in Gains._fields if f not in PER_ARM_GAINS + AXIS_GAINS)
VECTOR_FIELDS = ("object_offset", "lift")
# the position stack's fields (delay, servo scale): swept on position-controlled arms only (make_plan)
POSITION_FIELDS = ("delay", "servo_scale", "ft_filter")
SCALAR_FIELDS = tuple(f for f in Scenario._fields if f not in VECTOR_FIELDS + ("noise_key",))
PHASE_FIELDS = ("t_close", "t_squeeze", "t_carry", "settle_time")


# ----------------------------------------------------------------- parameters


@dataclasses.dataclass(frozen=True)
class Target:
    """Where a parameter goes: a gain or scenario leaf, or the noise seed."""

    kind: str  # "gain", "scenario" or "noise_seed"
    field: str
    index: tuple = ()  # index into the leaf (no batch axis); () the whole leaf
    integer: bool = False


@dataclasses.dataclass(frozen=True)
class Param:
    """One ``--param``: a set of grid values, or an interval for random samples."""

    name: str
    target: Target
    values: tuple | None  # grid values (sorted as given)
    interval: tuple | None  # (lo, hi) for random samples

    @property
    def swept(self) -> bool:
        return self.interval is not None or len(self.values) > 1

    def describe(self) -> dict:
        d = {"name": self.name}
        if self.values is not None:
            d["values"] = list(self.values)
        if self.interval is not None:
            d["interval"] = list(self.interval)
        return d


def known_names() -> str:
    return (
        f"gains {', '.join(SCALAR_GAINS)}; per-arm gains {', '.join(PER_ARM_GAINS)} "
        f"(all entries, or NAME.AXIS / NAME.ARM.AXIS with AXIS in {'/'.join(AXES)} and ARM r/l); "
        f"per-axis gains {', '.join(AXIS_GAINS)} (all entries, or NAME.AXIS); "
        f"scenario {', '.join(SCALAR_FIELDS)}; {', '.join(f + '.x/.y/.z' for f in VECTOR_FIELDS)}; noise_seed"
    )


def resolve_name(name: str) -> Target:
    """Map a parameter name to the leaf it sets (ConfigError for unknown names)."""
    parts = name.split(".")
    head = parts[0]
    bad = ConfigError(f"unknown parameter {name!r}; known: {known_names()}")
    if head == "noise_seed" and len(parts) == 1:
        return Target("noise_seed", "noise_key", (), integer=True)
    if head in SCALAR_GAINS and len(parts) == 1:
        return Target("gain", head)
    if head in PER_ARM_GAINS:
        if len(parts) == 1:
            return Target("gain", head, (slice(None), slice(None)))
        if len(parts) == 2 and parts[1] in AXES:
            return Target("gain", head, (slice(None), AXES[parts[1]]))
        if len(parts) == 3 and parts[1] in ARMS and parts[2] in AXES:
            return Target("gain", head, (ARMS[parts[1]], AXES[parts[2]]))
        raise bad
    if head in AXIS_GAINS:
        if len(parts) == 1:
            return Target("gain", head, (slice(None),))
        if len(parts) == 2 and parts[1] in AXES:
            return Target("gain", head, (AXES[parts[1]],))
        raise bad
    if head in SCALAR_FIELDS and len(parts) == 1:
        return Target("scenario", head, integer=head == "delay")  # whole control periods
    if head in VECTOR_FIELDS:
        if len(parts) == 2 and parts[1] in VEC_AXES:
            return Target("scenario", head, (VEC_AXES[parts[1]],))
        raise ConfigError(f"parameter {name!r}: {head} is a vector, name one component: {head}.x, {head}.y or {head}.z")
    raise bad


_NUMBER = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def _number(text: str, where: str) -> float:
    if not _NUMBER.match(text):
        raise ConfigError(f"{where}: {text.strip()!r} is not a number")
    return float(text)


def parse_param(text: str, random: bool = False) -> Param:
    """Parse ``NAME=VALUES``. VALUES: ``lo:hi:n`` (n points, ends included),
    ``a,b,c`` (a list), ``v`` (one value: a fixed override) or, with
    ``--samples``, ``lo:hi`` (an interval to draw from); with ``--samples`` a
    list or ``lo:hi:n`` gives the values drawn from, each equally likely."""
    if "=" not in text:
        raise ConfigError(f"--param {text!r}: expected NAME=VALUES, e.g. k_rk=-1:1:11 or object_mass=0.5,1,2")
    name, spec = (s.strip() for s in text.split("=", 1))
    where = f"--param {name}={spec}"
    target = resolve_name(name)
    if not spec:
        raise ConfigError(f"{where}: empty range: no values given")
    values = interval = None
    if ":" in spec:
        parts = spec.split(":")
        if len(parts) not in (2, 3):
            raise ConfigError(f"{where}: malformed range, expected lo:hi:n (or lo:hi with --samples)")
        lo, hi = _number(parts[0], where), _number(parts[1], where)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ConfigError(f"{where}: range ends must be finite")
        if lo > hi:
            raise ConfigError(f"{where}: empty range: lo {lo:g} is above hi {hi:g}")
        if len(parts) == 3:
            n_text = parts[2].strip()
            if not re.fullmatch(r"[-+]?\d+", n_text):
                raise ConfigError(f"{where}: the point count {n_text!r} must be a whole number")
            n = int(n_text)
            if n < 1:
                raise ConfigError(f"{where}: empty range: {n} points")
            if n == 1 and lo != hi:
                raise ConfigError(f"{where}: one point cannot span [{lo:g}, {hi:g}]; give a single value")
        if random and len(parts) == 2:
            interval = (lo, hi)
        elif len(parts) == 2:
            raise ConfigError(f"{where}: a range needs a point count, lo:hi:n (lo:hi alone is for --samples)")
        else:  # a grid; with --samples, the n values drawn from (as from a list)
            values = tuple(float(v) for v in np.linspace(lo, hi, n))
    else:
        items = spec.split(",")
        if any(not s.strip() for s in items):
            raise ConfigError(f"{where}: malformed list (an empty item)")
        values = tuple(_number(s, where) for s in items)
        if len(set(values)) != len(values):
            raise ConfigError(f"{where}: repeated values in the list")
        if random and len(values) > 1:
            pass  # lists are drawn from uniformly
    if target.integer:
        check = values if values is not None else interval
        if any(v != int(v) or v < 0 or v >= 2**32 for v in check):
            raise ConfigError(f"{where}: {name} takes whole numbers in [0, 2^32)")
        if values is not None:
            values = tuple(float(int(v)) for v in values)
    return Param(name, target, values, interval)


def _assign(leaf: np.ndarray, index: tuple, col: np.ndarray) -> None:
    """leaf[:, *index] = col, col (B,) broadcast over what the index leaves."""
    sel = (slice(None),) + tuple(index)
    dst = leaf[sel]
    leaf[sel] = col.reshape(col.shape + (1,) * (dst.ndim - 1))


def _noise_keys(seeds: np.ndarray) -> np.ndarray:

    out = np.empty((len(seeds), 2), dtype=np.uint32)
    cache: dict[int, np.ndarray] = {}
    for i, sd in enumerate(seeds.astype(np.int64)):
        k = int(sd)
        if k not in cache:
            cache[k] = np.asarray(jax.random.key_data(jax.random.key(k)), dtype=np.uint32)
        out[i] = cache[k]
    return out


def build_batch(params: list[Param], points: np.ndarray, base_gains: Gains, base_scenario: Scenario):
    """(Gains, Scenario) numpy pytrees with a leading axis, one row per point.

    ``object_mass`` also sets ``mass_estimate`` (the controller knows the mass)
    unless ``mass_estimate`` is a parameter too.
    """
    n = len(points)
    rows = lambda v: np.array(np.broadcast_to(np.asarray(v), (n,) + np.shape(v)))  # noqa: E731
    g = {k: rows(v) for k, v in base_gains._asdict().items()}
    s = {k: rows(v) for k, v in base_scenario._asdict().items()}
    names = {p.target.field for p in params if p.target.kind == "scenario"}
    for j, p in enumerate(params):
        col = points[:, j]
        t = p.target
        if t.kind == "gain":
            _assign(g[t.field], t.index, col)
        elif t.kind == "scenario":
            _assign(s[t.field], t.index, col)
            if t.field == "object_mass" and "mass_estimate" not in names:
                s["mass_estimate"][:] = col
        else:
            s["noise_key"][:] = _noise_keys(col)
    return Gains(**g), Scenario(**s)


def check_overlaps(params: list[Param], base_gains: Gains, base_scenario: Scenario) -> None:
    owner: dict[str, list[tuple[str, np.ndarray]]] = {}
    for p in params:
        t = p.target
        ref = (base_gains if t.kind == "gain" else base_scenario)._asdict()[t.field]
        mask = np.zeros(np.shape(ref), dtype=bool)
        mask[t.index if t.index else ...] = True
        key = f"{t.kind}:{t.field}"
        for other, om in owner.get(key, []):
            if np.any(om & mask):
                raise ConfigError(f"parameters {other!r} and {p.name!r} both set {t.field}; give each entry once")
        owner.setdefault(key, []).append((p.name, mask))


def validate_values(params: list[Param], base_gains: Gains, base_scenario: Scenario) -> None:
    """Every grid value (or both interval ends) within the gain and scenario bounds."""
    for j, p in enumerate(params):
        check = p.values if p.values is not None else p.interval
        pts = np.zeros((len(check), len(params)))
        for i, other in enumerate(params):  # the others at a legal value of theirs
            pts[:, i] = (other.values or other.interval)[0]
        pts[:, j] = check
        g, s = build_batch(params, pts, base_gains, base_scenario)
        try:
            for row in range(len(check)):
                _gains.validate(Gains(*(v[row] for v in g)))
            _scenario.validate(s)  # its checks take a batch
        except ConfigError as err:
            raise ConfigError(f"--param {p.name}: {err}") from None


def make_points(params: list[Param], samples: int | None, seed: int) -> np.ndarray:
    """(P, n_params) the points: a Cartesian grid (first parameter slowest) or random samples."""
    if samples is None:
        grids = np.meshgrid(*[np.asarray(p.values) for p in params], indexing="ij")
        return np.stack([x.reshape(-1) for x in grids], axis=1)
    rng = np.random.default_rng(seed)
    cols = []
    for p in params:
        if p.interval is not None:
            lo, hi = p.interval
            if p.target.integer:
                col = rng.integers(int(lo), int(hi), size=samples, endpoint=True).astype(float)
            else:
                col = rng.uniform(lo, hi, size=samples)
        else:
            col = np.asarray(p.values)[rng.integers(0, len(p.values), size=samples)]
        cols.append(col)
    return np.stack(cols, axis=1)
