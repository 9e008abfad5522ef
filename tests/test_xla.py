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
# "lacking": jaxsync's flags plus one no jaxlib knows (as JAX 0.11's lacks the
# fusion-emitter switch): set_xla_flags must leave it out, say so, and XLA start
_PROBE = """
import hashlib, os, sys, warnings
import jaxsync
from jaxsync.runtime import xla
if sys.argv[1] == "lacking":
    xla.FLAGS = {**xla.FLAGS, "xla_cpu_no_such_flag_in_any_release": "true"}
with warnings.catch_warnings(record=True) as said:
    warnings.simplefilter("always")
    ok = xla.set_xla_flags() if sys.argv[1] != "no" else None
import jax, jax.numpy as jnp
def f(x):
    return jnp.sum(jnp.sin(x) * jnp.cos(x[::-1]) + jnp.tanh(x) ** 2, axis=0)
text = jax.jit(f).lower(jnp.ones((64, 64))).compile().as_text()
words = " ".join(str(w.message) for w in said).replace("|", "/")
print(ok, os.environ.get("XLA_FLAGS", ""), hashlib.sha1(text.encode()).hexdigest(), words, sep="|")
"""


def _probes(*calls: tuple[str, str | None]) -> list[tuple[str, str, str, str]]:
    """Each ``(call, $XLA_FLAGS)`` in its own process, all at once (each mostly imports JAX)."""
    procs = []
    for call, xla_flags in calls:
        env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        if xla_flags is not None:
            env["XLA_FLAGS"] = xla_flags
        env["JAX_PLATFORMS"] = "cpu"
        cmd = [sys.executable, "-c", _PROBE, call]
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=300)
        assert p.returncode == 0, stderr[-2000:]  # XLA aborts on a flag it does not know
        ok, flags, digest, said = stdout.strip().splitlines()[-1].split("|")
        out.append((ok, flags, digest, said))
    return out


def test_flags_reach_xla_a_flag_this_jaxlib_lacks_is_left_out_and_a_users_own_setting_wins():
    defaults, lacking, users = _probes(("no", None), ("lacking", None), ("set", "--xla_cpu_use_fusion_emitters=true"))
    plain = defaults[2]  # XLA's defaults
    ok, flags, ours, said = lacking
    assert ok == "False" and "--xla_cpu_no_such_flag_in_any_release" in said and "does not know" in said
    assert flags.split() == [f"--{k}={v}" for k, v in _xla.FLAGS.items()]  # the known ones, not the made-up one
    assert ours != plain, "the flags did not change what XLA compiled"
    ok, flags, theirs, _ = users
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


def test_the_pinned_jaxlib_knows_every_flag_and_a_made_up_one_is_unknown():
    libs = _xla.xla_libraries()
    assert libs, "no XLA library found beside jaxlib"
    assert all(_xla.flag_known(k, libs) for k in _xla.FLAGS)
    assert not _xla.flag_known("xla_cpu_no_such_flag_in_any_release", libs)
    # a prefix of a real flag is not that flag
    assert not _xla.flag_known("xla_cpu_use_fusion", libs)
    assert not _xla.flag_known("xla_cpu_use_fusion_emitters", [])


def test_importing_jaxsync_does_not_start_jaxs_backend(tmp_path):
    """set_xla_flags() must run before the backend starts; a module that builds
    a jax array at import time would start it and the flags would be lost."""
    code = (
        "import jax._src.xla_bridge as xb, jaxsync, jaxsync.optimize.tuning.pipeline, jaxsync.cli;"
        "print(len(xb._backends))"
    )
    # run outside the checkout, so that the package imported is the installed one
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "0", out.stdout + out.stderr
