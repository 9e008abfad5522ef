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
