"""The sharded evaluator of a sweep: one compiled, vmapped, sharded chunk function.

A chunk of points is evaluated by one jit-compiled, vmapped rollout that
returns only the metrics, sharded over this process's JAX devices
(``shard_map`` over a 1-D ``batch`` mesh); in a multi-process run each
process evaluates whole chunks of its own (``sweep.run``), so no chunk needs
another process. The chunk size is fixed for the whole sweep (the last
chunk is padded), so one compilation serves every chunk, and bounded so that
XLA's memory analysis of the compiled chunk stays within the memory budget.
"""

from __future__ import annotations

import time

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxsync._errors import ConfigError
from jaxsync.control.gains import Gains
from jaxsync.optimize.studies.sweep_plan import Plan, loaded_model
from jaxsync.optimize.studies.sweep_spec import build_batch
from jaxsync.runtime import programs
from jaxsync.sim.metrics import summarize
from jaxsync.sim.rollout import cpu_vmap_limit, make_rollout
from jaxsync.sim.scenario import Scenario

DEFAULT_BUDGET_GIB = 2.0
DEFAULT_CHUNK_PER_DEVICE = {"cpu": 32}  # other platforms (GPU, TPU): 1024 per device
GIB = 1024.0**3


_model = loaded_model


def _mesh():

    return Mesh(np.array(jax.local_devices()), ("batch",))


@programs.memoize(maxsize=8)
def evaluator(
    solver: str,
    controller: str,
    duration: float,
    n_devices: int,
    model: str | None = None,
    visual: bool = True,
    actuation: str = "torque",
    control_substeps: int = 1,
    distro: str = "jazzy",
):
    """jit(shard_map(vmap(metrics of one rollout))) over the 'batch' mesh axis,
    on the arms' stack (``actuation``, ``control_substeps``, ``distro``).

    Each device evaluates its slice of the chunk with a plain vmap: no
    communication, and the same per-environment arithmetic as one device.
    """

    fn = make_rollout(
        _model(solver, model, visual),
        controller,
        duration,
        actuation=actuation,
        control_substeps=control_substeps,
        distro=distro,
    )
    local = jax.vmap(lambda g, s: summarize(fn(g, s), s))
    if n_devices == 1:
        return jax.jit(local), fn.n_steps
    mesh = _mesh()
    sharded = jax.shard_map(
        local, mesh=mesh, in_specs=(P("batch"), P("batch")), out_specs=P("batch"), check_vma=False
    )  # MJX's solver mixes batched and unbatched cond branches
    return jax.jit(sharded), fn.n_steps


@programs.memoize(maxsize=8)
def _compiled(
    solver,
    controller,
    duration,
    chunk,
    n_devices,
    gdtypes,
    sdtypes,
    model=None,
    visual=True,
    stack=("torque", 1, "jazzy"),
):

    fn, _ = evaluator(solver, controller, duration, n_devices, model, visual, *stack)
    sharding = _sharding() if n_devices > 1 else None
    g = Gains(*(jax.ShapeDtypeStruct((chunk,) + sh, dt, sharding=sharding) for sh, dt in gdtypes))
    s = Scenario(*(jax.ShapeDtypeStruct((chunk,) + sh, dt, sharding=sharding) for sh, dt in sdtypes))
    return fn.lower(g, s).compile()


def _sharding():

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


def to_device(tree, n_devices: int):

    if n_devices == 1:
        return jax.tree_util.tree_map(jax.numpy.asarray, tree)
    sh = _sharding()
    return jax.tree_util.tree_map(lambda x: jax.make_array_from_callback(x.shape, sh, lambda i: x[i]), tree)


def gather(tree):

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
        compiled = _compiled(
            plan.solver,
            plan.controller,
            plan.duration,
            c * n_devices,
            n_devices,
            *sig,
            plan.model,
            plan.visual,
            plan.stack_options,
        )
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
