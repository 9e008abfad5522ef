"""Runs over many processes on JAX's own distributed runtime (docs/scaling.md).

``jaxsync sweep`` and ``jaxsync tune`` run as one process per host (or per
GPU) when :func:`initialize` is called before any JAX computation: with
``coordinator``, ``num_processes`` and ``process_id`` (flags, or the
environment variables ``JAXSYNC_COORDINATOR``, ``JAXSYNC_NUM_PROCESSES``,
``JAXSYNC_PROCESS_ID``), or with ``auto`` through
``jax.distributed.initialize()``'s own cluster detection (SLURM, Open MPI,
and the other clusters JAX knows). No launcher of jaxsync's own: each process
is started by the cluster (``srun``) or by hand, and they meet at the
coordinator.

What the processes share beyond the device collectives (the tuner's gradient
average) goes through the coordination service that
``jax.distributed.initialize`` starts: a barrier and a key-value store, behind
:func:`barrier` and :func:`share` here (JAX's client, a private object,
reached in this module only; pinned with the JAX version in pyproject.toml).
"""

from __future__ import annotations

import json
import os
import sys

import jax
from jax._src import distributed as _jax_distributed  # JAX's client: read, never changed

from jaxsync._errors import ConfigError

ENV = {
    "coordinator": "JAXSYNC_COORDINATOR",
    "num_processes": "JAXSYNC_NUM_PROCESSES",
    "process_id": "JAXSYNC_PROCESS_ID",
}
# seconds without a heartbeat after which the coordination service declares a
# process lost and stops the others (JAX's default: 100)
HEARTBEAT_ENV = "JAXSYNC_HEARTBEAT_TIMEOUT_S"
_WAIT_MS = 7 * 24 * 3600 * 1000  # a barrier waits for the slowest process's share of the work


def _int(name: str, text, lo: int) -> int:
    try:
        v = int(text)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be an integer, got {text!r}") from None
    if v < lo:
        raise ConfigError(f"{name} must be at least {lo}, got {v}")
    return v


def settings(coordinator=None, num_processes=None, process_id=None, auto: bool = False, environ=None) -> dict | None:
    """The checked arguments of ``jax.distributed.initialize`` (None: one process).

    Flags win over the environment variables. The three explicit settings come
    together or not at all; ``auto`` leaves them to JAX's cluster detection
    (they may still be given: they override what it detects)."""
    env = os.environ if environ is None else environ
    got = {
        "coordinator": coordinator if coordinator is not None else env.get(ENV["coordinator"]) or None,
        "num_processes": num_processes if num_processes is not None else env.get(ENV["num_processes"]) or None,
        "process_id": process_id if process_id is not None else env.get(ENV["process_id"]) or None,
    }
    given = [k for k, v in got.items() if v is not None]
    if not given and not auto:
        return None
    if not auto and len(given) < 3:
        missing = [f"--{k.replace('_', '-')} (or {ENV[k]})" for k in got if got[k] is None]
        raise ConfigError(
            f"a multi-process run needs the coordinator, the process count and this process's id together: "
            f"missing {', '.join(missing)}; or pass --distributed-auto to let JAX detect the cluster (SLURM, Open MPI)"
        )
    out: dict = {}
    if got["coordinator"] is not None:
        host, sep, port = str(got["coordinator"]).rpartition(":")
        if not sep or not host:
            raise ConfigError(f"--coordinator must be HOST:PORT, got {got['coordinator']!r}")
        _int("the coordinator's port", port, 1)
        out["coordinator_address"] = str(got["coordinator"])
    if got["num_processes"] is not None:
        out["num_processes"] = _int("--num-processes", got["num_processes"], 1)
    if got["process_id"] is not None:
        out["process_id"] = _int("--process-id", got["process_id"], 0)
        if "num_processes" in out and out["process_id"] >= out["num_processes"]:
            raise ConfigError(
                f"--process-id must be below --num-processes ({out['num_processes']}), got {out['process_id']}"
            )
    if env.get(HEARTBEAT_ENV):
        out["heartbeat_timeout_seconds"] = _int(HEARTBEAT_ENV, env[HEARTBEAT_ENV], 1)
    return out


def initialize(coordinator=None, num_processes=None, process_id=None, auto: bool = False) -> bool:
    """Join the processes of a multi-process run; False (nothing done) for a
    run of one process. Call it before any JAX computation.

    Example (two processes on one machine, each with its own id):
      >>> initialize("127.0.0.1:12355", 2, 0)  # doctest: +SKIP
      True
    """
    kw = settings(coordinator, num_processes, process_id, auto)
    if kw is None:
        return False
    try:
        jax.distributed.initialize(**kw)
    except (RuntimeError, ValueError) as err:
        raise ConfigError(f"could not join the multi-process run ({kw}): {err}") from None
    return True


def active() -> bool:
    """True once this process has joined a multi-process run."""
    if "jax" not in sys.modules:
        return False
    return _jax_distributed.global_state.client is not None


def abandon(rc: int) -> None:
    """End a failed process of a multi-process run now, with status ``rc``.

    A normal exit waits at JAX's shutdown barrier for every other process (up
    to 5 minutes) while they may wait for this one; leaving without it lets
    the coordination service see the process gone and stop the others within
    its heartbeat timeout (JAXSYNC_HEARTBEAT_TIMEOUT_S, JAX's default 100 s)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)


def process_index() -> int:
    return jax.process_index()


def process_count() -> int:
    return jax.process_count()


def is_main() -> bool:
    """True in the process that writes a run's shared results (process 0)."""
    return process_index() == 0


def _client():
    client = _jax_distributed.global_state.client
    if client is None:
        raise RuntimeError("jax.distributed is not initialised")
    return client


def barrier(name: str, timeout_s: float | None = None) -> None:
    """Wait until every process has reached the barrier ``name`` (no-op for one process)."""
    if process_count() == 1:
        return
    ms = _WAIT_MS if timeout_s is None else int(timeout_s * 1000)
    _client().wait_at_barrier(f"jaxsync:{name}", ms)


def share(name: str, value=None):
    """Process 0's ``value`` (JSON), returned in every process (no-op for one process)."""
    if process_count() == 1:
        return value
    key = f"jaxsync:{name}"
    if is_main():
        _client().key_value_set(key, json.dumps(value))
        return value
    return json.loads(_client().blocking_key_value_get(key, _WAIT_MS))


def gather(name: str, value) -> list:
    """Every process's ``value`` (JSON), in process order, returned in every process."""
    if process_count() == 1:
        return [value]
    client = _client()
    client.key_value_set(f"jaxsync:{name}/{process_index()}", json.dumps(value))
    return [json.loads(client.blocking_key_value_get(f"jaxsync:{name}/{i}", _WAIT_MS)) for i in range(process_count())]


def describe() -> dict:
    """This process's place in the run, for summaries."""
    return {
        "process_index": jax.process_index(),
        "process_count": jax.process_count(),
        "local_devices": [str(d) for d in jax.local_devices()],
        "devices": jax.device_count(),
    }
