"""JAX's persistent compilation cache, for the CLI, scripts and tests.

Not called at import (no side effects on import); entry points call it.
"""

from __future__ import annotations

import os

import jax

ENV_VAR = "JAXSYNC_CACHE_DIR"


def default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME", os.path.join(os.path.expanduser("~"), ".cache"))
    return os.path.join(base, "jaxsync", "xla")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Point JAX's persistent compilation cache at ``path``.

    ``path`` defaults to ``$JAXSYNC_CACHE_DIR`` or ``~/.cache/jaxsync/xla``;
    the string ``"off"`` disables it. Returns the directory used, or None.
    """
    path = path or os.environ.get(ENV_VAR) or default_cache_dir()
    if path == "off":
        return None
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


# ------------------------------------------------------------- traced functions


def _source_fingerprint() -> str:
    """Hash of jaxsync's own source files and the versions it traces against:
    a traced function kept on disk is valid only for exactly this code."""
    import hashlib
    import importlib.metadata as md

    h = hashlib.sha256()
    root = os.path.dirname(os.path.abspath(__file__))
    for dirpath, _, files in sorted(os.walk(root)):
        for name in sorted(files):
            if name.endswith((".py", ".xml")):
                with open(os.path.join(dirpath, name), "rb") as f:
                    h.update(name.encode() + f.read())
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx"):
        try:
            h.update(f"{dist}={md.version(dist)}".encode())
        except md.PackageNotFoundError:
            h.update(dist.encode())
    return h.hexdigest()


def _register_export_types() -> None:
    from jax import export

    from jaxsync._gains import Gains
    from jaxsync._scenario import Scenario

    for cls, name in ((Gains, "jaxsync.Gains"), (Scenario, "jaxsync.Scenario")):
        try:
            export.register_namedtuple_serialization(cls, serialized_name=name)
        except ValueError:
            pass  # already registered


def traced_on_disk(fn, args: tuple, key: str, log=None, cache_dir: str | None = None):
    """``jax.jit(fn)``, with its traced and lowered form kept on disk (``jax.export``).

    Tracing and differentiating a rollout of this model costs about 15 s of
    Python each time a process starts, which the persistent XLA cache cannot
    save (docs/performance.md). The exported form is stored next to that cache,
    under a hash of ``key``, the argument shapes, jaxsync's source files and the
    JAX and MuJoCo versions; a later process deserialises it instead of tracing
    (and the XLA compile then hits the persistent cache). Without a persistent
    cache, without the ``flatbuffers`` package, or if exporting fails, this is
    plain ``jax.jit(fn)``. ``cache_dir`` overrides the folder.
    """
    import hashlib

    jitted = jax.jit(fn)
    cache = cache_dir or jax.config.jax_compilation_cache_dir
    if not cache:
        return jitted
    try:
        import flatbuffers  # noqa: F401
        from jax import export
    except ImportError:
        return jitted
    avals = jax.tree_util.tree_map(lambda x: (jax.numpy.shape(x), str(jax.numpy.result_type(x))), args)
    digest = hashlib.sha256(f"{key}|{avals}|{jax.tree_util.tree_structure(args)}|{_source_fingerprint()}".encode())
    path = os.path.join(cache, f"jaxsync-export-{digest.hexdigest()[:32]}.bin")
    try:
        _register_export_types()
        if os.path.exists(path):
            with open(path, "rb") as f:
                exp = export.deserialize(bytearray(f.read()))
        else:
            exp = export.export(jitted)(*args)
            from jaxsync._io import atomic_write_bytes

            atomic_write_bytes(path, exp.serialize())
        return jax.jit(exp.call)
    except Exception as err:  # noqa: BLE001  (an optimisation only: fall back to tracing)
        if log is not None:
            log(f"(not keeping the traced function on disk: {type(err).__name__}: {err})")
        return jitted
