"""Test configuration: float64, the persistent compilation cache, shared models.

Every jitted function is compiled once per session through the fixtures here.
"""

from __future__ import annotations

import jax
import pytest

from jaxsync._cache import enable_compilation_cache

jax.config.update("jax_enable_x64", True)
enable_compilation_cache()


@pytest.fixture(scope="session")
def model():
    import jaxsync

    return jaxsync.load_model(solver="accurate")


@pytest.fixture(scope="session")
def diff_model():
    import jaxsync

    return jaxsync.load_model(solver="differentiable")


@pytest.fixture(scope="session")
def forward_sense(model):
    """jit(mjx.forward, then sense): one compile for the session."""
    from mujoco import mjx

    import jaxsync

    index = model.index

    @jax.jit
    def fn(mx, d):
        d = mjx.forward(mx, d)
        return d, jaxsync.sense(mx, d, index)

    return fn
