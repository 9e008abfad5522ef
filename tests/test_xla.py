"""jaxsync's XLA settings (jaxsync.runtime.xla): set by scripts before JAX starts, never at import."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import jax.numpy as jnp
import pytest

import jaxsync
from jaxsync.runtime import xla as _xla

# compiles a few fused elementwise operations and prints what set_xla_flags()
# returned, $XLA_FLAGS, and a hash of XLA's compiled module (the CPU fusion
# emitters wrap each elementwise operation on its own: the text differs)
_PROBE = """
import hashlib, os, sys
import jaxsync
ok = jaxsync.set_xla_flags() if sys.argv[1] == "set" else None
import jax, jax.numpy as jnp
def f(x):
    return jnp.sum(jnp.sin(x) * jnp.cos(x[::-1]) + jnp.tanh(x) ** 2, axis=0)
text = jax.jit(f).lower(jnp.ones((64, 64))).compile().as_text()
print(ok, os.environ.get("XLA_FLAGS", ""), hashlib.sha1(text.encode()).hexdigest(), sep="|")
"""


def _probe(call: str, xla_flags: str | None) -> tuple[str, str, str]:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, call], env=env, capture_output=True, text=True, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr[-2000:]  # XLA aborts on a flag it does not know
    ok, flags, digest = out.stdout.strip().splitlines()[-1].split("|")
    return ok, flags, digest


def test_flags_reach_xla_and_a_users_own_setting_wins():
    _, _, plain = _probe("no", None)  # XLA's defaults
    ok, flags, ours = _probe("set", None)
    assert ok == "True"
    assert flags.split() == [f"--{k}={v}" for k, v in _xla.FLAGS.items()]
    assert ours != plain, "the flags did not change what XLA compiled"
    ok, flags, theirs = _probe("set", "--xla_cpu_use_fusion_emitters=true")
    assert ok == "True" and flags == "--xla_cpu_use_fusion_emitters=true"
    assert theirs == plain


def test_after_the_backend_started_nothing_changes_and_it_warns(monkeypatch):
    jnp.ones(1).block_until_ready()  # the backend has started in this process
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    with pytest.warns(UserWarning, match="before the first JAX computation"):
        assert jaxsync.set_xla_flags() is False
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert jaxsync.set_xla_flags() is True  # already there: nothing to add, nothing to warn about


def test_the_test_process_runs_with_jaxsyncs_flags():
    # conftest calls set_xla_flags() before any JAX computation, as the command line does
    present = os.environ.get("XLA_FLAGS", "").split()
    assert all(f"--{k}={v}" in present for k, v in _xla.FLAGS.items())
