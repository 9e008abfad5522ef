"""Batched parameter studies: ``jaxsync sweep`` (docs/sweep.md).

A sweep is a table of points, one column per ``--param``: a Cartesian grid of
the given values, or ``--samples N`` random points. Each point overrides leaves
of the base :class:`~jaxsync.Gains` and :class:`~jaxsync.Scenario`; a chunk of
points is evaluated by one jit-compiled, vmapped rollout that returns only the
metrics, sharded over every JAX device (``shard_map`` over a 1-D ``batch``
mesh). The chunk size is fixed for the whole sweep (the last chunk is padded),
so one compilation serves every chunk, and bounded so that XLA's memory
analysis of the compiled chunk stays within ``--memory-budget-gib``.

Each finished chunk is written atomically to ``chunks/chunk_NNNNN.npz`` next
to ``plan.json`` (the sweep's fingerprint); a re-run with the same arguments
reads finished chunks back instead of recomputing them.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import io
import json
import math
import os
import re
import shutil
import sys
import time

import numpy as np

from jaxsync import _gains, _io, _scenario
from jaxsync._errors import ConfigError
from jaxsync._gains import Gains
from jaxsync._scenario import Scenario

PLAN_VERSION = 1
AXES = {"x": 0, "y": 1, "z": 2, "rx": 3, "ry": 4, "rz": 5}
ARMS = {"r": 0, "right": 0, "l": 1, "left": 1}
VEC_AXES = {"x": 0, "y": 1, "z": 2}
PER_ARM_GAINS = ("imp_mass", "imp_damping", "imp_stiffness")
SCALAR_GAINS = tuple(f for f in Gains._fields if f not in PER_ARM_GAINS)
VECTOR_FIELDS = ("object_offset", "lift")
SCALAR_FIELDS = tuple(f for f in Scenario._fields if f not in VECTOR_FIELDS + ("noise_key",))
PHASE_FIELDS = ("t_close", "t_squeeze", "t_carry", "settle_time")
BOOL_METRICS = ("dropped", "nonfinite")
DEFAULT_PLOT_METRICS = ("settled_peak_resultant_N", "grip_force_error_rel")
DEFAULT_BUDGET_GIB = 2.0
DEFAULT_CHUNK_PER_DEVICE = {"cpu": 32}  # other platforms (GPU, TPU): 1024 per device
GIB = 1024.0**3


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
    if head in SCALAR_FIELDS and len(parts) == 1:
        return Target("scenario", head)
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
    ``--samples``, ``lo:hi`` (an interval to draw from)."""
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
        if random:
            interval = (lo, hi)
        elif len(parts) == 2:
            raise ConfigError(f"{where}: a range needs a point count, lo:hi:n (lo:hi alone is for --samples)")
        else:
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
    import jax

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


def _check_overlaps(params: list[Param], base_gains: Gains, base_scenario: Scenario) -> None:
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


def _validate_values(params: list[Param], base_gains: Gains, base_scenario: Scenario) -> None:
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


@dataclasses.dataclass
class Plan:
    params: list[Param]
    points: np.ndarray
    samples: int | None
    seed: int
    duration: float
    controller: str
    solver: str
    base_gains: Gains
    base_scenario: Scenario
    x64: bool

    @property
    def spec(self) -> dict:
        return {
            "version": PLAN_VERSION,
            "params": [p.describe() for p in self.params],
            "mode": "grid" if self.samples is None else "samples",
            "samples": self.samples,
            "seed": self.seed,
            "duration_s": self.duration,
            "controller": self.controller,
            "solver": self.solver,
            "x64": self.x64,
            "base_gains": _gains.to_dict(self.base_gains),
            "n_points": len(self.points),
            "points_sha256": hashlib.sha256(np.ascontiguousarray(self.points).tobytes()).hexdigest(),
        }

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.spec, sort_keys=True).encode()).hexdigest()[:16]


def make_plan(
    param_texts: list[str],
    *,
    samples: int | None = None,
    seed: int = 0,
    duration: float = 4.0,
    controller: str = "synchronous",
    solver: str = "accurate",
    base_gains: Gains | None = None,
    base_scenario: Scenario | None = None,
) -> Plan:
    """Parse and check everything that can be checked without compiling."""
    import jax

    from jaxsync._compare import min_duration

    if not param_texts:
        raise ConfigError("give at least one --param NAME=VALUES")
    if samples is not None and samples < 1:
        raise ConfigError(f"--samples must be a positive number of points, got {samples}")
    if controller not in ("synchronous", "classical"):
        raise ConfigError(f"--controller must be 'synchronous' or 'classical', got {controller!r}")
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ConfigError(f"--duration must be a positive number of seconds, got {duration}")
    params = [parse_param(t, random=samples is not None) for t in param_texts]
    names = [p.name for p in params]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"parameter(s) {dup} given more than once")
    base_gains = base_gains if base_gains is not None else _gains.default_gains()
    base_scenario = base_scenario if base_scenario is not None else _scenario.default_scenario()
    _check_overlaps(params, base_gains, base_scenario)
    _validate_values(params, base_gains, base_scenario)
    points = make_points(params, samples, seed)
    # the longest phases of any point need the longest rollout
    worst = {f: float(np.asarray(getattr(base_scenario, f))) for f in PHASE_FIELDS}
    for j, p in enumerate(params):
        if p.target.kind == "scenario" and p.target.field in PHASE_FIELDS:
            worst[p.target.field] = float(points[:, j].max())
    need = min_duration(base_scenario._replace(**{k: np.float64(v) for k, v in worst.items()}))
    if duration < need - 1e-9:
        raise ConfigError(
            f"--duration must be at least {need:.2f} s for this sweep (hold start + settling time + 0.2 s "
            f"of settled window for its longest phases), got {duration:g}"
        )
    return Plan(
        params,
        points,
        samples,
        int(seed),
        float(duration),
        controller,
        solver,
        base_gains,
        base_scenario,
        bool(jax.config.jax_enable_x64),
    )


# ----------------------------------------------------------------- evaluation


@functools.lru_cache(maxsize=4)
def _model(solver: str):
    from jaxsync._model import load_model

    return load_model(solver=solver)


def _mesh():
    import jax
    from jax.sharding import Mesh

    return Mesh(np.array(jax.devices()), ("batch",))


@functools.lru_cache(maxsize=8)
def _evaluator(solver: str, controller: str, duration: float, n_devices: int):
    """jit(shard_map(vmap(metrics of one rollout))) over the 'batch' mesh axis.

    Each device evaluates its slice of the chunk with a plain vmap: no
    communication, and the same per-environment arithmetic as one device.
    """
    import jax
    from jax.sharding import PartitionSpec as P

    from jaxsync._metrics import summarize
    from jaxsync._rollout import make_rollout

    fn = make_rollout(_model(solver), controller, duration)
    local = jax.vmap(lambda g, s: summarize(fn(g, s), s))
    if n_devices == 1:
        return jax.jit(local), fn.n_steps
    mesh = _mesh()
    sharded = jax.shard_map(
        local, mesh=mesh, in_specs=(P("batch"), P("batch")), out_specs=P("batch"), check_vma=False
    )  # MJX's solver mixes batched and unbatched cond branches
    return jax.jit(sharded), fn.n_steps


def _abstract(tree, chunk: int, sharding):
    import jax

    return jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((chunk,) + x.shape[1:], x.dtype, sharding=sharding), tree
    )


@functools.lru_cache(maxsize=8)
def _compiled(solver, controller, duration, chunk, n_devices, gdtypes, sdtypes):
    import jax

    fn, _ = _evaluator(solver, controller, duration, n_devices)
    sharding = _sharding() if n_devices > 1 else None
    g = Gains(*(jax.ShapeDtypeStruct((chunk,) + sh, dt, sharding=sharding) for sh, dt in gdtypes))
    s = Scenario(*(jax.ShapeDtypeStruct((chunk,) + sh, dt, sharding=sharding) for sh, dt in sdtypes))
    return fn.lower(g, s).compile()


def _sharding():
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    return NamedSharding(_mesh(), P("batch"))


def memory_bytes(compiled) -> int | None:
    """Per-device bytes XLA needs for one call (arguments, outputs, temporaries)."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend reports it
        return None
    if m is None:
        return None
    return int(
        m.argument_size_in_bytes
        + m.output_size_in_bytes
        + m.temp_size_in_bytes
        + m.generated_code_size_in_bytes
        - m.alias_size_in_bytes
    )


def _signature(tree):
    return tuple((tuple(np.shape(x)[1:]), np.asarray(x).dtype) for x in tree)


def _to_device(tree, n_devices: int):
    import jax

    if n_devices == 1:
        return jax.tree_util.tree_map(jax.numpy.asarray, tree)
    sh = _sharding()
    return jax.tree_util.tree_map(lambda x: jax.make_array_from_callback(x.shape, sh, lambda i: x[i]), tree)


def _gather(tree):
    import jax

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(np.asarray, tree)


def choose_chunk(
    plan: Plan, *, chunk: int | None, budget_gib: float, n_devices: int, platform: str, log=lambda m: None
):
    """Compile for a fixed chunk size within the memory budget.

    Returns (chunk, compiled, bytes per device). Starts from ``chunk`` (or a
    platform default), reads XLA's memory analysis of the compiled chunk and,
    while it exceeds the budget, shrinks the chunk (per-environment bytes
    measured at the larger size over-estimate those at the smaller, so the
    search never undershoots a chunk that fits). Raises ConfigError when not
    even one environment per device fits.
    """
    from jaxsync._rollout import cpu_vmap_limit

    budget = budget_gib * GIB
    per_dev_cap = DEFAULT_CHUNK_PER_DEVICE.get(platform, 1024)
    n = len(plan.points)
    max_useful = -(-n // n_devices)  # per device
    c = min(chunk // n_devices if chunk else per_dev_cap, max_useful)
    limit = cpu_vmap_limit()
    if limit and c > limit:
        log(f"{c} points per device can hang jaxlib's CPU LAPACK kernels (docs/performance.md): using {limit}")
        c = limit
    c = max(c, 1)
    g1, s1 = build_batch(plan.params, plan.points[:1], plan.base_gains, plan.base_scenario)
    sig = (_signature(g1), _signature(s1))
    tried = set()
    while True:
        t0 = time.perf_counter()
        compiled = _compiled(plan.solver, plan.controller, plan.duration, c * n_devices, n_devices, *sig)
        log(f"compiled the chunk function for {c * n_devices} points in {time.perf_counter() - t0:.1f} s")
        used = memory_bytes(compiled)
        if used is None:
            log("this backend gives no memory analysis: the budget is not checked")
            return c * n_devices, compiled, None
        if used <= budget:
            return c * n_devices, compiled, used
        tried.add(c)
        per_env = used / c
        fit = int(budget // per_env)
        if fit < 1 or fit in tried:
            raise ConfigError(
                f"the sweep would exceed --memory-budget-gib {budget_gib:g} even in chunks of one point per "
                f"device: one {plan.duration:g} s rollout needs about {per_env / 2**20:.1f} MiB "
                f"(XLA memory analysis); raise the budget or shorten --duration"
            )
        log(
            f"{c * n_devices} points need {used / GIB:.3f} GiB per device, over the "
            f"{budget_gib:g} GiB budget: trying {fit * n_devices}"
        )
        c = fit


# ----------------------------------------------------------------- output


def _chunk_path(out: str, i: int) -> str:
    return os.path.join(out, "chunks", f"chunk_{i:05d}.npz")


def _save_chunk(out: str, i: int, start: int, stop: int, metrics: dict) -> None:
    buf = io.BytesIO()
    np.savez(buf, start=start, stop=stop, **metrics)
    _io.atomic_write_bytes(_chunk_path(out, i), buf.getvalue())


def _load_chunk(out: str, i: int, start: int, stop: int, fields) -> dict | None:
    path = _chunk_path(out, i)
    if not os.path.exists(path):
        return None
    try:
        with np.load(path) as z:
            if int(z["start"]) != start or int(z["stop"]) != stop:
                return None
            got = {k: z[k].copy() for k in fields}
    except Exception:  # noqa: BLE001 - an unreadable chunk is recomputed
        return None
    if any(v.shape != (stop - start,) for v in got.values()):
        return None
    return got


def _prepare_out(out: str, plan: Plan, restart: bool) -> dict | None:
    """Create the folder; return the stored plan.json when resuming the same sweep."""
    _io.ensure_writable_dir(out)
    path = os.path.join(out, "plan.json")
    stored = None
    if os.path.exists(path):
        try:
            with open(path) as f:
                stored = json.load(f)
        except (OSError, json.JSONDecodeError):
            stored = None
        if stored is not None and stored.get("fingerprint") != plan.fingerprint and not restart:
            raise ConfigError(
                f"output folder {out!r} holds a different sweep (plan.json fingerprint "
                f"{stored.get('fingerprint')}, this one {plan.fingerprint}); pass --restart to discard it "
                "or choose another --out"
            )
    if restart or stored is None or stored.get("fingerprint") != plan.fingerprint:
        shutil.rmtree(os.path.join(out, "chunks"), ignore_errors=True)
        for f in ("results.csv", "summary.json", "heatmap.png", "line.png", "scatter.png", "plan.json"):
            if os.path.exists(os.path.join(out, f)):
                os.unlink(os.path.join(out, f))
        stored = None
    os.makedirs(os.path.join(out, "chunks"), exist_ok=True)
    return stored


def _read_plan(out: str, plan: Plan) -> dict | None:
    try:
        with open(os.path.join(out, "plan.json")) as f:
            stored = json.load(f)
    except (OSError, json.JSONDecodeError):
        return None
    return stored if stored.get("fingerprint") == plan.fingerprint else None


def write_csv(path: str, plan: Plan, metrics: dict) -> None:
    cols: dict[str, list] = {"point": list(range(len(plan.points)))}
    for j, p in enumerate(plan.params):
        col = plan.points[:, j]
        cols[p.name] = [int(v) for v in col] if p.target.integer else [float(v) for v in col]
    for k, v in metrics.items():
        cols[k] = [int(x) for x in v] if k in BOOL_METRICS else [float(x) for x in v]
    ok = ~(metrics["dropped"].astype(bool) | metrics["nonfinite"].astype(bool))
    cols["ok"] = [int(x) for x in ok]
    _io.write_csv(path, cols)


def _stats(x: np.ndarray) -> dict | None:
    x = x[np.isfinite(x)]
    if not len(x):
        return None
    return {"min": float(x.min()), "median": float(np.median(x)), "max": float(x.max()), "mean": float(x.mean())}


def summarize_sweep(plan: Plan, metrics: dict) -> dict:
    ok = ~(metrics["dropped"].astype(bool) | metrics["nonfinite"].astype(bool))
    out = {
        "n_points": len(plan.points),
        "n_ok": int(ok.sum()),
        "n_dropped": int(metrics["dropped"].astype(bool).sum()),
        "n_nonfinite": int(metrics["nonfinite"].astype(bool).sum()),
        "metrics_over_ok_points": {},
        "best_ok_point": {},
    }
    for k, v in metrics.items():
        if k in BOOL_METRICS or k.endswith("_time_s"):
            continue
        out["metrics_over_ok_points"][k] = _stats(v[ok].astype(float))
    for k in DEFAULT_PLOT_METRICS:
        if ok.any():
            i = int(np.flatnonzero(ok)[np.argmin(metrics[k][ok])])
            out["best_ok_point"][k] = {
                "point": i,
                **{p.name: float(plan.points[i, j]) for j, p in enumerate(plan.params) if p.swept},
                k: float(metrics[k][i]),
            }
    return out


def plot(out: str, plan: Plan, metrics: dict, plot_metrics) -> str | None:
    """heatmap.png (2 swept grid parameters), line.png (1), scatter.png (random samples)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    swept = [j for j, p in enumerate(plan.params) if p.swept]
    if not swept or len(swept) > 2 and plan.samples is not None:
        return None
    ok = ~(metrics["dropped"].astype(bool) | metrics["nonfinite"].astype(bool))
    axes_j = swept[:2]
    others = [plan.params[j].name for j in swept[2:]]
    note = f" (mean over {', '.join(others)})" if others else ""
    fig, axs = plt.subplots(1, len(plot_metrics), figsize=(5.2 * len(plot_metrics), 4.2), squeeze=False)
    if plan.samples is not None:
        name = "scatter.png"
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            x = plan.points[:, axes_j[0]]
            if len(axes_j) == 2:
                sc = ax.scatter(x[ok], plan.points[ok, axes_j[1]], c=metrics[k][ok], s=18, cmap="viridis")
                ax.scatter(x[~ok], plan.points[~ok, axes_j[1]], marker="x", c="r", s=18, label="dropped")
                fig.colorbar(sc, ax=ax, label=k)
                ax.set_ylabel(plan.params[axes_j[1]].name)
            else:
                ax.scatter(x[ok], metrics[k][ok], s=12)
                ax.set_ylabel(k)
            ax.set_xlabel(plan.params[axes_j[0]].name)
            ax.set_title(f"{k}, {len(x)} random points")
    elif len(axes_j) == 1:
        name = "line.png"
        j = axes_j[0]
        xs = np.asarray(plan.params[j].values)
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            ys = [
                np.mean(metrics[k][(plan.points[:, j] == v) & ok]) if ((plan.points[:, j] == v) & ok).any() else np.nan
                for v in xs
            ]
            ax.plot(xs, ys, "o-")
            ax.set_xlabel(plan.params[j].name)
            ax.set_ylabel(k)
            ax.set_title(f"{k}{note}", fontsize=9)
            ax.grid(alpha=0.3)
    else:
        name = "heatmap.png"
        ja, jb = axes_j
        va, vb = np.asarray(plan.params[ja].values), np.asarray(plan.params[jb].values)
        for ax, k in zip(axs[0], plot_metrics, strict=True):
            grid = np.full((len(vb), len(va)), np.nan)
            for a, x in enumerate(va):
                for b, y in enumerate(vb):
                    sel = (plan.points[:, ja] == x) & (plan.points[:, jb] == y) & ok
                    if sel.any():
                        grid[b, a] = metrics[k][sel].mean()
            im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
            fig.colorbar(im, ax=ax, label=k)
            step_a, step_b = max(1, len(va) // 11), max(1, len(vb) // 11)
            ax.set_xticks(range(0, len(va), step_a), [f"{v:g}" for v in va[::step_a]], rotation=45)
            ax.set_yticks(range(0, len(vb), step_b), [f"{v:g}" for v in vb[::step_b]])
            ax.set_xlabel(plan.params[ja].name)
            ax.set_ylabel(plan.params[jb].name)
            blank = " (blank: dropped)" if np.isnan(grid).any() else ""
            ax.set_title(f"{k}{note}{blank}", fontsize=9)
    fig.suptitle(f"{plan.controller} controller, {plan.duration:g} s rollouts", fontsize=10)
    fig.tight_layout()
    _io.save_figure(fig, os.path.join(out, name))
    plt.close(fig)
    return name


# ----------------------------------------------------------------- the run


def run(
    plan: Plan,
    out: str,
    *,
    chunk: int | None = None,
    budget_gib: float = DEFAULT_BUDGET_GIB,
    restart: bool = False,
    progress: bool = True,
    max_chunks: int | None = None,
    plot_metrics=DEFAULT_PLOT_METRICS,
    log=lambda m: print(m, file=sys.stderr, flush=True),
) -> dict:
    """Evaluate the plan into ``out``; returns summary.json's content (``complete`` False
    when ``max_chunks`` stopped it early)."""
    import jax

    from jaxsync._metrics import Metrics

    if chunk is not None and chunk < 1:
        raise ConfigError(f"--chunk must be a positive number of points, got {chunk}")
    if not budget_gib > 0:
        raise ConfigError(f"--memory-budget-gib must be positive, got {budget_gib}")
    for k in plot_metrics:
        if k not in Metrics._fields:
            raise ConfigError(f"--plot-metric {k!r} is not a metric; known: {list(Metrics._fields)}")
    t_start = time.perf_counter()
    main_proc = jax.process_index() == 0
    devices = jax.devices()
    n_dev = len(devices)
    if chunk is not None and chunk % n_dev:
        raise ConfigError(f"--chunk {chunk} must be a multiple of the {n_dev} devices the sweep is sharded over")
    stored = _prepare_out(out, plan, restart) if main_proc else None
    if jax.process_count() > 1:  # every process reads the same finished chunks (a shared --out)
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("jaxsync sweep: output folder ready")
        if not main_proc:
            stored = _read_plan(out, plan)
    n = len(plan.points)
    fields = Metrics._fields

    def bounds(i, c):
        return i * c, min(n, (i + 1) * c)

    # chunks already on disk (same plan) are read back, not recomputed
    c_stored = int(stored["chunk"]) if stored and stored.get("n_devices") == n_dev else None
    results: dict[int, dict] = {}
    if c_stored:
        if chunk is not None and chunk != c_stored:
            log(f"resuming with the stored chunk size {c_stored} (not --chunk {chunk})")
        for i in range(-(-n // c_stored)):
            got = _load_chunk(out, i, *bounds(i, c_stored), fields)
            if got is not None:
                results[i] = got
    elif stored and main_proc:
        shutil.rmtree(os.path.join(out, "chunks"), ignore_errors=True)
        os.makedirs(os.path.join(out, "chunks"), exist_ok=True)

    compile_s = 0.0
    used = None
    c = c_stored
    n_chunks = -(-n // c) if c else None
    if c is None or len(results) < n_chunks:
        platform = devices[0].platform
        t0 = time.perf_counter()
        if c is None:
            c, compiled, used = choose_chunk(
                plan, chunk=chunk, budget_gib=budget_gib, n_devices=n_dev, platform=platform, log=log
            )
        else:
            c, compiled, used = choose_chunk(
                plan, chunk=c, budget_gib=budget_gib, n_devices=n_dev, platform=platform, log=log
            )
            if c != c_stored:
                raise ConfigError(
                    f"the stored chunk size {c_stored} no longer fits --memory-budget-gib "
                    f"{budget_gib:g}; pass --restart"
                )
        compile_s = time.perf_counter() - t0
        n_chunks = -(-n // c)
    if main_proc:
        plan_doc = {
            "fingerprint": plan.fingerprint,
            "chunk": c,
            "n_chunks": n_chunks,
            "n_devices": n_dev,
            "spec": plan.spec,
        }
        _io.write_json(os.path.join(out, "plan.json"), plan_doc)

    todo = [i for i in range(n_chunks) if i not in results]
    loaded = n_chunks - len(todo)
    if loaded:
        log(f"resuming: {loaded} of {n_chunks} chunks read back from {os.path.join(out, 'chunks')}")
    if max_chunks is not None:
        todo = todo[:max_chunks]
    t_eval = time.perf_counter()
    computed = 0
    bar = None
    if progress and main_proc:
        from tqdm import tqdm

        bar = tqdm(
            total=n,
            initial=sum(len(r["dropped"]) for r in results.values()),
            unit="pt",
            desc="sweep",
            file=sys.stderr,
            dynamic_ncols=True,
        )
    n_steps = _evaluator(plan.solver, plan.controller, plan.duration, n_dev)[1]
    try:
        for i in todo:
            start, stop = bounds(i, c)
            idx = np.arange(start, start + c)
            idx = np.minimum(idx, stop - 1)  # pad the last chunk with copies of its last point
            g, s = build_batch(plan.params, plan.points[idx], plan.base_gains, plan.base_scenario)
            m = _gather(compiled(_to_device(g, n_dev), _to_device(s, n_dev)))
            got = {k: np.asarray(getattr(m, k))[: stop - start] for k in fields}
            if main_proc:
                _save_chunk(out, i, start, stop, got)
            results[i] = got
            computed += 1
            if bar is not None:
                bar.update(stop - start)
    finally:
        if bar is not None:
            bar.close()
    eval_s = time.perf_counter() - t_eval
    done_points = sum(stop - start for start, stop in (bounds(i, c) for i in todo[:computed]))
    timing = {
        "wall_s": time.perf_counter() - t_start,
        "compile_s": compile_s,
        "eval_s": eval_s,
        "chunks_computed": computed,
        "chunks_loaded": loaded,
        "points_per_s": done_points / eval_s if computed and eval_s > 0 else None,
        "env_steps_per_s": done_points * n_steps / eval_s if computed and eval_s > 0 else None,
    }
    if len(results) < n_chunks:
        log(
            f"stopped after {computed} new chunk(s) (--max-chunks): {len(results)} of {n_chunks} done; "
            "run the same command again to finish"
        )
        return {"complete": False, "chunks_done": len(results), "n_chunks": n_chunks, "timing": timing}
    metrics = {k: np.concatenate([results[i][k] for i in range(n_chunks)]) for k in fields}
    summary = {"complete": True, **summarize_sweep(plan, metrics)}
    if main_proc:
        write_csv(os.path.join(out, "results.csv"), plan, metrics)
        fig = plot(out, plan, metrics, plot_metrics)
        summary.update(
            {
                "sweep": plan.spec,
                "fingerprint": plan.fingerprint,
                "chunk": c,
                "n_chunks": n_chunks,
                "n_steps_per_rollout": n_steps,
                "devices": [str(d) for d in devices],
                "process_count": jax.process_count(),
                "memory": {
                    "budget_gib_per_device": budget_gib,
                    "chunk_gib_per_device": used / GIB if used is not None else None,
                },
                "timing": timing,
                "plot": fig,
                "files": ["results.csv", "summary.json", "plan.json", "chunks/"] + ([fig] if fig else []),
            }
        )
        _io.write_json(os.path.join(out, "summary.json"), summary)
    return summary


# ----------------------------------------------------------------- CLI


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
    from jaxsync.cli import _positive

    p = subparsers.add_parser(
        "sweep",
        help="batched parameter study over gains and scenario parameters (grid or random samples)",
        description="Evaluate the metrics of many rollouts, one per point of a Cartesian grid (or of "
        "--samples random points) over named gain and scenario parameters; batched with vmap, sharded over "
        "all JAX devices, resumable. Writes results.csv, summary.json, a heatmap (2 swept parameters) or a "
        "line plot (1) to --out. See docs/sweep.md.",
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUES",
        help="a parameter and its values: lo:hi:n (n points), a,b,c (a list), v (fixed), or lo:hi "
        "(with --samples). Names: gains (k_rk, imp_stiffness, imp_stiffness.z, "
        "imp_stiffness.r.z, ...), "
        "scenario fields (object_mass, lift.z, ...), noise_seed. Repeat for each parameter.",
    )
    p.add_argument("--samples", type=int, default=None, help="draw this many random points instead of the grid")
    p.add_argument("--seed", type=int, default=0, help="seed of the random points (0)")
    p.add_argument("--duration", type=_positive(float), default=4.0, help="seconds simulated per rollout (4)")
    p.add_argument("--controller", default="synchronous", choices=["synchronous", "classical"])
    p.add_argument("--solver", default="accurate", choices=["accurate", "differentiable"])
    p.add_argument("--gains", default=None, help="JSON file of base gains (default: built-in)")
    p.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="points per compiled batch, a multiple of the device count (default: 32 per CPU "
        "device, 1024 per accelerator, shrunk to fit the memory budget; at most 64 per CPU "
        "device (JAXSYNC_CPU_VMAP_LIMIT), see docs/performance.md)",
    )
    p.add_argument(
        "--memory-budget-gib",
        type=float,
        default=DEFAULT_BUDGET_GIB,
        help=f"memory per device for one chunk, GiB ({DEFAULT_BUDGET_GIB:g})",
    )
    p.add_argument("--out", default="results/sweep", help="output folder (results/sweep)")
    p.add_argument("--restart", action="store_true", help="discard a different or finished sweep in --out")
    p.add_argument(
        "--plot-metric",
        action="append",
        default=None,
        help=f"metric(s) to plot (default: {', '.join(DEFAULT_PLOT_METRICS)})",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--max-chunks", type=int, default=None, help=argparse.SUPPRESS)  # testing: stop early
    p.set_defaults(func=cmd_sweep, interrupted_hint="finished chunks are kept; run again to resume")
    return p


def cmd_sweep(args: argparse.Namespace) -> int:
    gains = _gains.load(args.gains) if args.gains else None
    plan = make_plan(
        args.param,
        samples=args.samples,
        seed=args.seed,
        duration=args.duration,
        controller=args.controller,
        solver=args.solver,
        base_gains=gains,
    )
    summary = run(
        plan,
        args.out,
        chunk=args.chunk,
        budget_gib=args.memory_budget_gib,
        restart=args.restart,
        progress=not args.no_progress,
        max_chunks=args.max_chunks,
        plot_metrics=tuple(args.plot_metric or DEFAULT_PLOT_METRICS),
    )
    if not summary["complete"]:
        return 0
    t = summary["timing"]
    print(
        f"{summary['n_points']} points ({summary['n_ok']} ok, {summary['n_dropped']} dropped, "
        f"{summary['n_nonfinite']} non-finite) in {t['wall_s']:.1f} s "
        f"(compile {t['compile_s']:.1f} s; {t['chunks_loaded']} chunk(s) read back)"
    )
    for k, best in summary["best_ok_point"].items():
        where = ", ".join(f"{n}={v:g}" for n, v in best.items() if n not in ("point", k))
        print(f"lowest {k}: {best[k]:.5g} at {where}")
    files = ", ".join(f for f in summary["files"] if f != "chunks/")
    print(f"results in {args.out}: {files}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point (``python -m jaxsync.optimize.sweep``), same as ``jaxsync sweep``."""
    from jaxsync.cli import main as cli_main

    return cli_main(["sweep", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
