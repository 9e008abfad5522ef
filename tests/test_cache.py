"""The persistent caches: traced functions kept on disk, keyed by every source file they depend on."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import core, pjit

import jaxsync.mjcf
import jaxsync.optimize.tuning.cost
import jaxsync.optimize.tuning.tune
from jaxsync.control.gains import default_gains
from jaxsync.runtime import cache as _cache
from jaxsync.runtime import patches


def test_traced_function_kept_on_disk(tmp_path):
    """jaxsync.runtime.cache.traced_on_disk: exported once, held in memory for a second
    call in the same process, read back from disk once forgotten (a later
    process), same results as plain jit; a different key or shape is a
    different file."""

    def f(g, x):
        return {"y": jnp.sin(x) * g.k_rl, "s": jnp.sum(x**2)}

    args = (default_gains(), jnp.arange(3.0))
    d = str(tmp_path)
    a = _cache.traced_on_disk(f, args, "k1", cache_dir=d)
    files = sorted(p.name for p in tmp_path.glob("jaxsync-export-*.bin"))
    assert len(files) == 1
    assert _cache.traced_on_disk(f, args, "k1", cache_dir=d) is a  # held: nothing read or compiled again
    _cache.forget_loaded()
    b = _cache.traced_on_disk(f, args, "k1", cache_dir=d)  # read back
    assert b is not a
    assert sorted(p.name for p in tmp_path.glob("jaxsync-export-*.bin")) == files
    ref = jax.jit(f)(*args)
    for out in (a(*args), b(*args)):
        np.testing.assert_array_equal(np.asarray(out["y"]), np.asarray(ref["y"]))
        assert float(out["s"]) == float(ref["s"])
    _cache.traced_on_disk(f, args, "k2", cache_dir=d)
    _cache.traced_on_disk(f, (args[0], jnp.arange(4.0)), "k1", cache_dir=d)
    assert len(list(tmp_path.glob("jaxsync-export-*.bin"))) == 3


def test_fingerprint_covers_the_cost_the_loss_and_the_model():
    """The cost and the loss (jaxsync.optimize) and the model (jaxsync.mjcf) are
    hashed wherever they are installed from: in a checkout or an editable
    install they live outside jaxsync/ (the bug: only jaxsync/ was hashed)."""
    files = _cache.source_files()
    for module in (jaxsync.optimize.tuning.cost, jaxsync.optimize.tuning.tune, _cache):
        assert os.path.realpath(module.__file__) in files, module.__name__
    model = os.path.join(os.path.dirname(jaxsync.mjcf.__file__), "dual_arm.xml")
    assert os.path.realpath(model) in files


def test_editing_the_cost_changes_the_key(tmp_path, monkeypatch):
    """Edit a copy of the cost's source: the fingerprint, and so the file the
    traced function is kept in, changes; the unedited copy gives the same key."""
    copy = tmp_path / "cost.py"
    copy.write_bytes(open(jaxsync.optimize.tuning.cost.__file__, "rb").read())
    files = [*(f for f in _cache.source_files() if not f.endswith(os.sep + "cost.py")), str(copy)]
    monkeypatch.setattr(_cache, "source_files", lambda: files)
    before = _cache._source_fingerprint()
    assert _cache._source_fingerprint() == before
    args = (default_gains(), jnp.arange(3.0))
    cache = tmp_path / "cache"
    cache.mkdir()
    _cache.traced_on_disk(lambda g, x: x * g.k_rl, args, "k", cache_dir=str(cache))
    copy.write_text(copy.read_text().replace("GRIP_SCALE = 0.01", "GRIP_SCALE = 0.02"))
    assert _cache._source_fingerprint() != before
    _cache.traced_on_disk(lambda g, x: x * g.k_rl, args, "k", cache_dir=str(cache))
    assert len(list(cache.glob("jaxsync-export-*.bin"))) == 2


def test_dead_code_elimination_is_memoised_for_the_whole_process():
    """``stable_lowering`` (on with the persistent cache, as here): the same
    inner jaxpr pruned the same way is the same object even after more other
    prunings than JAX's own cache keeps (2048), so a program lowered after a
    big trace is the module it would be in a fresh process (its cache key)."""
    assert patches.stable_lowering()
    closed = jax.make_jaxpr(lambda x: (jnp.sin(x), jnp.cos(x)))(1.0)
    first = pjit._dce_jaxpr_pjit(closed, (True, False))[0]
    assert len(first.jaxpr.outvars) == 1
    others = [core.ClosedJaxpr(closed.jaxpr, closed.consts) for _ in range(2100)]
    for other in others:  # each a new key: JAX's bounded cache alone evicts `closed`
        pjit._dce_jaxpr_pjit(other, (True, False))
    assert pjit._dce_jaxpr_pjit(closed, (True, False))[0] is first
