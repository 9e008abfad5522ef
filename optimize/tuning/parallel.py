"""Data-parallel tuning: the training batch sharded over every device of every process.

When a run has more than one JAX device (several local GPUs, or several
processes joined by ``jaxsync.runtime.distributed``), ``tune`` evaluates its loss
here: each device takes its slice of the batch, computes the mean cost and
its gradient over that slice, and an all-reduce (``psum``) weights the slices
into the mean over the whole batch: the same value and gradient as one device
running the whole batch, to float64 rounding. ``jaxsync tune --batch B`` on N
processes trains on N x B scenarios (the scenarios of a one-process run with
batch N x B: every process draws the same batch from the same seed and keeps
its slice).

The results come back as host values in every process, so the optimiser
(Adam, L-BFGS, CMA-ES) runs unchanged, identically, in each: no parameter
ever needs sending.
"""

from __future__ import annotations

import itertools

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxsync._errors import ConfigError
from jaxsync.runtime import distributed as _distributed

_BARRIERS = itertools.count()


def active() -> bool:
    """True when the loss should be data-parallel (more than one device in the run)."""
    return jax.device_count() > 1


def batch_size(per_process: int) -> int:
    """The whole batch of a data-parallel run: ``per_process`` x the process count,
    which must split evenly over the run's devices."""
    total = per_process * jax.process_count()
    if total % jax.device_count():
        raise ConfigError(
            f"batch {per_process} per process does not split over this process's {jax.local_device_count()} "
            f"devices: use a multiple of {jax.local_device_count()}"
        )
    return total


def _mesh() -> Mesh:
    return Mesh(np.array(jax.devices()), ("batch",))


def shard(tree):
    """A batch (host values, the same in every process) as global arrays split over the 'batch' axis."""
    return _put(tree, NamedSharding(_mesh(), P("batch")))


def replicate(tree):
    """Host values (the same in every process) as global arrays held whole on every device."""
    return _put(tree, NamedSharding(_mesh(), P()))


def _put(tree, sharding):
    def one(x):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda i: host[i])

    return jax.tree_util.tree_map(one, tree)


def _local(tree):
    """Replicated global arrays as this process's own (host values on its first device)."""
    return jax.tree_util.tree_map(lambda x: jax.numpy.asarray(np.asarray(x)), tree)


def _weighted_psum(tree, n_local: int, n_total: int):
    return jax.tree_util.tree_map(lambda x: jax.lax.psum(x * (n_local / n_total), "batch"), tree)


def value_and_grad(loss, n_total: int):
    """``(theta, batch) -> ((mean cost, mean terms), gradient)`` over the whole
    batch, like ``jax.value_and_grad(loss, has_aux=True)``; ``batch`` holds host
    values of all ``n_total`` scenarios, the results are this process's."""

    def local(theta, s):
        n_local = jax.tree_util.tree_leaves(s)[0].shape[0]
        out = jax.value_and_grad(loss, has_aux=True)(theta, s)  # the mean over this device's slice
        return _weighted_psum(out, n_local, n_total)

    # check_vma off: MJX's solver mixes batched and unbatched cond branches (as the sweep's evaluator)
    fn = jax.jit(jax.shard_map(local, mesh=_mesh(), in_specs=(P(), P("batch")), out_specs=P(), check_vma=False))

    run = _compiled_together(fn, "tune: gradient compiled")

    def call(theta, batch):
        return _local(run(replicate(theta), shard(batch)))

    call.jitted = fn
    return call


def _compiled_together(fn, name: str):
    """``fn`` compiled ahead of its first call, then a barrier: the processes
    compile at their own pace (minutes here, not the same in each), but the
    first collective, whose CPU (gloo) set-up waits 30 s at most for the other
    processes, starts only once every process has its program."""

    compiled = None
    name = f"{name} #{next(_BARRIERS)}"  # a barrier's name is used once per run

    def run(*args):
        nonlocal compiled
        if compiled is None:
            compiled = fn.lower(*args).compile()
            _distributed.barrier(name)
        return compiled(*args)

    return run


def population_values(loss, unravel, n_total: int):
    """``(X, batch) -> costs``: the mean cost over the whole batch of every row of
    ``X`` (flat parameters; a CMA-ES population), as a host array."""

    def local(X, s):
        n_local = jax.tree_util.tree_leaves(s)[0].shape[0]
        costs = jax.vmap(lambda x: loss(unravel(x), s)[0])(X)
        return _weighted_psum(costs, n_local, n_total)

    fn = jax.jit(jax.shard_map(local, mesh=_mesh(), in_specs=(P(), P("batch")), out_specs=P(), check_vma=False))

    run = _compiled_together(fn, "tune: population compiled")

    def call(X, batch):
        return np.asarray(run(replicate(np.asarray(X)), shard(batch)))

    return call
