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
import os
import types

import pytest

import jaxsync
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.optimize.benchmarks.benchmark import table, targets

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


def _stand_in_model(source):
    """What bench.json records of a model (its identity; no robot: the paper's defaults)."""
    return types.SimpleNamespace(name="stand-in", path=source, fingerprint="0" * 64, robot=None)


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


def _stand_ins(monkeypatch, bm, load, fg, compile_times, tune_step, pair=None):
    """The benchmark's measurements replaced: the given ones and fixed figures for the rest."""
    monkeypatch.setattr(bm, "load_model", load)
    monkeypatch.setattr(bm, "mjx_throughput", lambda *a, **k: {"rates": {"1": 100.0}})
    monkeypatch.setattr(bm, "mujoco_c_throughput", lambda *a, **k: {"rate": 50.0, "rate_including_setup": 40.0})
    monkeypatch.setattr(bm, "bare_mj_step", lambda *a, **k: 1000.0)
    monkeypatch.setattr(bm, "forward_and_gradient", fg)
    monkeypatch.setattr(bm, "paired_forward_and_gradient", pair)
    monkeypatch.setattr(bm, "compile_times", compile_times)
    monkeypatch.setattr(bm, "tune_step_memory", tune_step)
    monkeypatch.setattr(bm, "warm_compile_s", lambda comp: comp["warm"]["total_s"])


def test_bench_robot_measures_the_robot_and_the_paper_model_for_the_ratios(tmp_path, monkeypatch, capsys):
    """``jaxsync bench --robot FILE``: every measurement gets the robot (as an
    absolute path: the children run elsewhere), a last section measures the
    paper model's gradient and cold compile, and the ratios and their targets
    are the robot's figures over the paper model's (stand-in measurements)."""
    from jaxsync.optimize.benchmarks import benchmark as bm

    seen = []
    loaded = []

    def fake_load(source, solver, visual=True):
        loaded.append((source, visual))
        return _stand_in_model(source)

    def fake_fg(path, duration, repeats, log, small=False, source=None, visual=True):
        seen.append(("fg", path, source))
        ratio = {None: 2.0}.get(source, 3.0)
        return {"forward_s": 1.0, "grad_s": ratio, "grad_over_forward": ratio, "label": path, "grad_finite": True}

    def fake_pair(duration, rounds, log, small=False, source=None, visual=True):
        from jaxsync.optimize.benchmarks.benchmark_measure import ratio_of_ratios

        seen.append(("pair", "implicit", source))
        # three rounds; the paper model's gradient fast in the last: the ratio
        # of the best times (3.0) is not the rounds' median (1.5)
        times = {
            "robot": {"forward": [1.0] * 3, "grad": [3.0] * 3},
            "paper": {"forward": [1.0] * 3, "grad": [2.0, 2.0, 1.0]},
        }
        models = {
            m: {"forward_s": 1.0, "grad_s": t["grad"][0], "grad_over_forward": t["grad"][0]} for m, t in times.items()
        }
        return {"models": models, "ratio_of_ratios": ratio_of_ratios(times)}

    def fake_compile(path, duration, small, log, exported=True, source=None, visual=True, warm=True):
        seen.append(("compile", path, source, warm))
        c = {"total_s": 40.0 if source is None else 50.0}
        return {"cold": c} if not warm else {"cold": c, "warm": {"total_s": 3.0}}

    def fake_tune(path, batch, task, small, log, warm=True, xla_flags=None, source=None, visual=True):
        seen.append(("tune", path, source))
        return {"peak_rss_gib": 1.0, "warm": {"peak_rss_gib": 0.5}}

    _stand_ins(monkeypatch, bm, fake_load, fake_fg, fake_compile, fake_tune, fake_pair)
    robot = "mjcf/robots/iiwa14_twice.yaml"
    assert run_cli(["bench", "--quick", "--robot", robot, "--no-visual", "--out", str(tmp_path)]) == 0
    absolute = os.path.abspath(robot)
    assert loaded == [(absolute, False)]
    # the robot alone in sections 1-6; in section 7 the robot against the paper
    # model in the same rounds, then the paper model's cold compile (source None)
    assert seen[-2:] == [("pair", "implicit", absolute), ("compile", "implicit", None, False)]
    assert {c[0] for c in seen[:-2]} == {"fg", "compile", "tune"} and all(c[2] == absolute for c in seen[:-2])
    r = json.loads((tmp_path / "bench.json").read_text())
    assert r["model"] == absolute
    # what ran: the loaded model's identity, its default gains and scenario
    assert r["model_identity"] == {"name": "stand-in", "file": absolute, "fingerprint": "0" * 64}
    assert r["gains"] == _gains.to_dict(jaxsync.default_gains())
    assert r["scenario_base"]["object_mass"] == 0.5
    assert r["grad_over_forward_over_paper"] == pytest.approx(1.5)
    assert r["paper_model"]["ratio_of_ratios"]["per_round"] == pytest.approx([1.5, 1.5, 3.0])
    assert r["grad_compile_cold_over_paper"] == pytest.approx(1.25)
    assert r["targets"]["grad_over_forward_over_paper"]["met"] is False
    assert r["targets"]["grad_compile_cold_over_paper"]["met"] is True
    out = capsys.readouterr().out
    rows = {line.split("  ")[0]: line for line in out.splitlines()}
    assert "MISSED" in rows["this model's gradient / forward over the paper model's, median of the rounds"]
    assert "1.25" in rows["this model's cold compile over the paper model's"]
    assert "3.00" in rows["this model's gradient / forward, in the same rounds"]
    assert rows["the same: quartiles over the rounds; ratio of the best times"].split()[-2:] == ["1.50-2.25", "3.00"]
    assert out.splitlines()[0] == f"model: {absolute}"


def test_bench_without_a_robot_has_no_paper_ratios(monkeypatch, tmp_path):
    """The paper model's own bench records no ratios (None) and prints none."""
    from jaxsync.optimize.benchmarks import benchmark as bm

    fg = {"forward_s": 1.0, "grad_s": 2.0, "grad_over_forward": 2.0, "label": "x", "grad_finite": True}
    _stand_ins(
        monkeypatch,
        bm,
        lambda source, solver, visual=True: _stand_in_model(source),
        lambda *a, **k: fg,
        lambda *a, **k: {"cold": {"total_s": 40.0}, "warm": {"total_s": 3.0}},
        lambda *a, **k: {"peak_rss_gib": 1.0, "warm": {"peak_rss_gib": 0.5}},
    )
    r = bm.run(str(tmp_path), quick=True, log=lambda m: None)
    assert r["model"] == "paper model" and r["paper_model"] is None
    assert r["grad_over_forward_over_paper"] is None and "grad_over_forward_over_paper" not in r["targets"]
    assert "over the paper model" not in bm.table(r)


def test_ratio_of_ratios_takes_each_programs_best_and_reports_the_rounds():
    """The target's figure is the ratio of the best times; a slow call in one
    round moves the per-round figures, not it; unequal rounds are refused."""
    from jaxsync.optimize.benchmarks.benchmark_measure import ratio_of_ratios

    times = {
        "robot": {"forward": [0.2, 0.2, 0.3], "grad": [0.9, 0.8, 0.8]},
        "paper": {"forward": [0.2, 0.25, 0.2], "grad": [0.6, 0.6, 1.2]},
    }
    rr = ratio_of_ratios(times)
    assert rr["robot_grad_over_forward"] == pytest.approx(4.0)
    assert rr["paper_grad_over_forward"] == pytest.approx(3.0)
    assert rr["of_best"] == pytest.approx(4.0 / 3.0)
    assert rr["per_round"] == pytest.approx([1.5, 4.0 / 2.4, (0.8 / 0.3) / 6.0])
    assert rr["per_round_median"] == pytest.approx(1.5)
    assert rr["per_round_quartiles"][0] < 1.5 < rr["per_round_quartiles"][1]
    times["paper"]["grad"] = [0.6, 0.6]
    with pytest.raises(ValueError, match="same number of rounds"):
        ratio_of_ratios(times)


def test_paired_timing_alternates_the_models_round_by_round(monkeypatch):
    """Each round times all four programs, the robot's first in even rounds and
    the paper model's first in odd ones (stand-in programs record the order)."""
    from jaxsync.optimize.benchmarks import benchmark_measure as m

    calls = []

    def fake_functions(path, duration, small, source, visual):
        name = "paper" if source is None else "robot"
        assert path == "implicit"
        return (lambda: calls.append((name, "f"))), (lambda: calls.append((name, "g"))), (), 10

    monkeypatch.setattr(m, "gradient_functions", fake_functions)
    out = m.paired_forward_and_gradient(0.1, 3, lambda msg: None, source="robot.yaml")
    # compiles (one call each), then three rounds
    rounds = [calls[4 + 4 * i : 8 + 4 * i] for i in range(3)]
    assert calls[:4] == [("robot", "f"), ("robot", "g"), ("paper", "f"), ("paper", "g")] and len(calls) == 16
    assert [r[0][0] for r in rounds] == ["robot", "paper", "robot"]
    assert all(sorted(r) == sorted(calls[:4]) for r in rounds)
    assert out["rounds"] == 3 and len(out["ratio_of_ratios"]["per_round"]) == 3
    assert set(out["models"]) == {"robot", "paper"}


def test_bench_position_stack_times_its_gradient_beside_the_torque_stacks(model, monkeypatch, tmp_path):
    """``jaxsync bench --actuation position --delay 2``: a last section times the
    position stack's forward and gradient with the torque stack's in the same
    rounds (stand-in timings); the ratio of their costs in forward rollouts is
    the target's figure; the stack and its servo are recorded."""
    from jaxsync.optimize.benchmarks import benchmark as bm
    from jaxsync.optimize.benchmarks.benchmark_measure import ratio_of_ratios
    from jaxsync.sim.actuation import Stack

    fg = {"forward_s": 1.0, "grad_s": 2.0, "grad_over_forward": 2.0, "label": "x", "grad_finite": True}
    _stand_ins(
        monkeypatch,
        bm,
        lambda source, solver, visual=True: model,
        lambda *a, **k: fg,
        lambda *a, **k: {"cold": {"total_s": 40.0}, "warm": {"total_s": 3.0}},
        lambda *a, **k: {"peak_rss_gib": 1.0, "warm": {"peak_rss_gib": 0.5}},
    )
    seen = []

    def fake_stacks(duration, rounds, log, stack, small=False, source=None, visual=True):
        seen.append(stack)
        times = {
            "position": {"forward": [1.0, 1.1, 1.0], "grad": [2.6, 2.9, 2.4]},
            "torque": {"forward": [0.9, 0.9, 0.9], "grad": [1.8, 1.8, 1.8]},
        }
        stacks = {m: {"grad_over_forward": min(t["grad"]) / min(t["forward"])} for m, t in times.items()}
        return {"stacks": stacks, "ratio_of_ratios": ratio_of_ratios(times, "position", "torque")}

    monkeypatch.setattr(bm, "paired_stacks", fake_stacks)
    stack = Stack("position", None, (2, 2))
    r = bm.run(str(tmp_path), quick=True, log=lambda m: None, stack=stack)
    assert seen == [stack]
    # per round: (2.6/1.0)/(2.0) = 1.3, (2.9/1.1)/2.0 = 1.318, (2.4/1.0)/2.0 = 1.2: median 1.3
    assert r["position_grad_over_forward_over_torque"] == pytest.approx(1.3)
    assert r["targets"]["position_grad_over_forward_over_torque"]["met"] is True
    assert r["position_stack"]["stack"]["delay"] == [2, 2] and r["position_stack"]["stack"]["servo"]["source"]
    rows = {line.split("  ")[0]: line for line in bm.table(r).splitlines()}
    assert "2.40" in rows["position stack: gradient / forward, in the same rounds"]
    assert "1.30" in rows["position stack's gradient / forward over the torque stack's, median of the rounds"]
    plain = bm.run(str(tmp_path), quick=True, log=lambda m: None)
    assert plain["position_stack"] is None and "position_grad_over_forward_over_torque" not in plain["targets"]


def test_bench_refuses_a_stack_it_cannot_run(tmp_path, capsys):
    for args, message in [
        (["--actuation", "position", "--delay", "0:3"], "one scenario runs one delay"),
        (["--delay", "1"], "delay applies to position-controlled arms"),
    ]:
        assert run_cli(["bench", "--out", str(tmp_path / "b"), *args]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
        assert not (tmp_path / "b").exists()
