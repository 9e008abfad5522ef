"""``jaxsync bench --quick``: bench.json has every key, with positive numbers.

A benchmark reports; it never fails the suite on speed (targets are printed
and recorded, not asserted).
"""

from __future__ import annotations

import json

import pytest

KEYS = (
    "mujoco_c_env_steps_per_s",
    "bare_mj_step_per_s",
    "forward_s",
    "grad_s",
    "grad_over_forward",
    "grad_compile_cold_s",
    "grad_compile_warm_s",
    "grad_compile_warm_persistent_cache_only_s",
    "tune_step_peak_rss_gib",
)


def run_cli(argv: list[str]) -> int:
    """``jaxsync bench ...`` in this process."""
    from jaxsync.cli import main

    return main(argv)


def test_bench_rejects_bad_batch_sizes(tmp_path, capsys):
    assert run_cli(["bench", "--out", str(tmp_path), "--batch-sizes", "1,x"]) == 2
    assert "--batch-sizes" in capsys.readouterr().err
    assert run_cli(["bench", "--out", str(tmp_path), "--batch-sizes", "0"]) == 2


@pytest.mark.slow
def test_quick_bench_writes_every_key(tmp_path, capsys):
    assert run_cli(["bench", "--quick", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "bench.json").read_text())
    for key in KEYS:
        assert isinstance(r[key], (int, float)) and r[key] > 0, key
    assert r["mjx_env_steps_per_s"] and all(v > 0 for v in r["mjx_env_steps_per_s"].values())
    m = r["machine"]
    assert m["cpu_cores"] >= 1 and m["jax_backend"] and m["jax"] and m["mujoco"]
    assert "cpu_model" in m
    out = capsys.readouterr().out
    assert "gradient / forward" in out and "bench.json" in out


def test_traced_function_kept_on_disk(tmp_path):
    """jaxsync._cache.traced_on_disk: exported once, read back by a later call,
    same results as plain jit; a different key or shape is a different file."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxsync import _cache
    from jaxsync._gains import default_gains

    def f(g, x):
        return {"y": jnp.sin(x) * g.k_rl, "s": jnp.sum(x**2)}

    args = (default_gains(), jnp.arange(3.0))
    d = str(tmp_path)
    a = _cache.traced_on_disk(f, args, "k1", cache_dir=d)
    files = sorted(p.name for p in tmp_path.glob("jaxsync-export-*.bin"))
    assert len(files) == 1
    b = _cache.traced_on_disk(f, args, "k1", cache_dir=d)  # read back
    assert sorted(p.name for p in tmp_path.glob("jaxsync-export-*.bin")) == files
    ref = jax.jit(f)(*args)
    for out in (a(*args), b(*args)):
        np.testing.assert_array_equal(np.asarray(out["y"]), np.asarray(ref["y"]))
        assert float(out["s"]) == float(ref["s"])
    _cache.traced_on_disk(f, args, "k2", cache_dir=d)
    _cache.traced_on_disk(f, (args[0], jnp.arange(4.0)), "k1", cache_dir=d)
    assert len(list(tmp_path.glob("jaxsync-export-*.bin"))) == 3
