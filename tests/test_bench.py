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
