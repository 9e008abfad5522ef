"""``jaxsync bench --quick``: bench.json has every key, with positive numbers,
for both gradient paths; the table marks every target met or missed.

A benchmark reports; it never fails the suite on speed (targets are printed
and recorded, not asserted). ``--quick`` runs the benchmark's code with a small
stand-in for the gradient programs (they compile in minutes each); the
gradient programs themselves are the tuner's and are tested in test_tune and
test_gradient.
"""

from __future__ import annotations

import json

import pytest

from jaxsync.cli import main
from jaxsync.optimize.benchmark import table, targets

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
    "tune_step_peak_rss_warm_gib",
)


def run_cli(argv: list[str]) -> int:
    """``jaxsync bench ...`` in this process."""
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
    assert set(r["paths"]) == {"implicit", "unrolled"}
    for p in ("implicit", "unrolled"):
        assert r["paths"][p]["grad_s"] > 0 and r["paths"][p]["grad_over_forward"] > 0
    assert r["grad_s_over_unrolled"] == pytest.approx(
        r["paths"]["implicit"]["grad_s"] / r["paths"]["unrolled"]["grad_s"]
    )
    assert r["details"]["forward_and_gradient"]["implicit"]["grad_finite"]
    assert all(t["judged"] is False and isinstance(t["met"], bool) for t in r["targets"].values())
    assert r["mjx_env_steps_per_s"] and all(v > 0 for v in r["mjx_env_steps_per_s"].values())
    m = r["machine"]
    assert m["cpu_cores"] >= 1 and m["jax_backend"] and m["jax"] and m["mujoco"]
    assert "cpu_model" in m
    out = capsys.readouterr().out
    assert "gradient / forward" in out and "bench.json" in out
    # the run's XLA settings are recorded; XLA's default emitters are measured in full runs only
    assert "--xla_cpu_use_fusion_emitters=false" in r["xla_flags"]
    assert r["grad_compile_cold_xla_default_s"] is None and r["tune_step_peak_rss_xla_default_gib"] is None


def test_table_marks_missed_targets_also_in_quick_mode():
    path = dict(
        label="x",
        forward_s=1.0,
        grad_s=5.0,
        grad_over_forward=5.0,
        grad_compile_cold_s=100.0,
        grad_compile_warm_s=2.0,
        tune_step_peak_rss_gib=1.0,
    )
    unrolled = {**path, "grad_compile_cold_s": None, "grad_compile_warm_s": None, "tune_step_peak_rss_gib": None}
    r = {
        "mjx_env_steps_per_s": {"1": 1000.0},
        "mjx_best_batch": 1,
        "mujoco_c_env_steps_per_s": 500.0,
        "bare_mj_step_per_s": 9000.0,
        "mjx_over_mujoco_c": 2.0,
        "grad_over_forward": 5.0,
        "grad_s_over_unrolled": 1.0,
        "grad_compile_cold_s": 100.0,
        "grad_compile_warm_s": 2.0,
        "grad_compile_warm_persistent_cache_only_s": 3.0,
        "tune_step_peak_rss_gib": 1.0,
        "tune_step_peak_rss_warm_gib": 0.5,
        "grad_compile_cold_xla_default_s": 159.25,
        "tune_step_peak_rss_xla_default_gib": 2.5,
        "xla_flags": "--xla_cpu_use_fusion_emitters=false",
        "paths": {"implicit": path, "unrolled": unrolled},
    }
    for judged in (True, False):
        r["targets"] = targets(r, judged=judged)
        rows = {line.split("  ")[0]: line for line in table(r).splitlines()}
        assert "MISSED" in rows["gradient / forward"] and "MISSED" in rows["gradient compile cold, s"]
        assert "MISSED" in rows["MJX best (batch 1) / MuJoCo C"]
        assert (
            " met" in rows["gradient compile warm (as the CLI), s"]
            and " met" in rows["gradient s, implicit / unrolled"]
        )
        assert ("not a benchmark" in rows["gradient / forward"]) is (not judged)
        assert "159.2" in rows["with XLA's default CPU emitters: gradient compile cold, s"]
        assert "2.50" in rows["with XLA's default CPU emitters: tuning step peak RSS (compiling), GiB"]
        assert table(r).splitlines()[-1].endswith("XLA_FLAGS: --xla_cpu_use_fusion_emitters=false")
