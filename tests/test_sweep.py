"""``jaxsync sweep``: parameter parsing, batches, bad input, resuming, sharding, outputs."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tempfile

import jax
import numpy as np
import pytest
from conftest import ctrl_c_in_a_gc_callback

from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.io import results as _results
from jaxsync.optimize.studies import sweep, sweep_report
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.actuation import Stack
from jaxsync.sim.rollout import cpu_vmap_limit

# The tests' task (jaxsync.short_task, tests/conftest.py) as fixed sweep parameters, 1.7 s rollouts.
FAST = [
    "--param",
    "t_close=0.3",
    "--param",
    "t_squeeze=0.4",
    "--param",
    "t_carry=0.5",
    "--param",
    "settle_time=0.3",
    "--param",
    "lift.x=0.02",
    "--param",
    "lift.z=0.05",
    "--duration",
    "1.7",
]
GRID = ["--param", "k_rk=-0.5:0.5:2", "--param", "object_mass=0.5,0.6", "--chunk", "2", "--no-progress"]


def run_cli(argv: list[str]) -> int:
    """``jaxsync sweep ...`` in this process."""
    return main(argv)


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


# ----------------------------------------------------------------- no compiling


def test_grid_lists_and_names():
    p = sweep.parse_param("k_rk=-1:1:5")
    assert p.values == (-1.0, -0.5, 0.0, 0.5, 1.0) and p.swept
    assert sweep.parse_param("object_mass=0.5,1,2").values == (0.5, 1.0, 2.0)
    assert not sweep.parse_param("grip_force=12").swept  # one value: a fixed override
    assert sweep.parse_param("k_rk=-1:1", random=True).interval == (-1.0, 1.0)
    plan = sweep.make_plan(
        [
            "k_rk=-1:1:3",
            "object_mass=0.5,1",
            "imp_stiffness.z=30,60",
            "imp_damping.l.x=90",
            "lift.z=0.05",
            "noise_seed=3",
        ],
        duration=4.0,
    )
    assert plan.points.shape == (12, 6)
    assert plan.points[:4, 0].tolist() == [-1.0] * 4  # the first parameter varies slowest
    g, s = sweep.build_batch(plan.params, plan.points, plan.base_gains, plan.base_scenario)
    assert g.k_rk.shape == (12,) and g.imp_stiffness.shape == (12, 2, 6)
    np.testing.assert_array_equal(g.imp_stiffness[:, :, 2], np.repeat(plan.points[:, 2:3], 2, axis=1))
    assert g.imp_stiffness[0, 0, 0] == 1500.0  # other axes keep the base gains
    assert g.imp_damping[0, 1, 0] == 90.0 and g.imp_damping[0, 0, 0] != 90.0
    np.testing.assert_array_equal(s.mass_estimate, s.object_mass)  # the controller knows the mass
    assert s.lift[0].tolist() == [0.05, 0.0, 0.05]
    assert s.noise_key[0].tolist() == np.asarray(jax.random.key_data(jax.random.key(3))).tolist()


def test_random_samples_are_seeded_and_in_range():
    args = ["k_rk=-1:1", "k_lk=-1:1:11", "object_mass=0.5,1,2", "noise_seed=0:9"]
    a = sweep.make_plan(args, samples=50, seed=7)
    b = sweep.make_plan(args, samples=50, seed=7)
    c = sweep.make_plan(args, samples=50, seed=8)
    assert a.points.shape == (50, 4)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.fingerprint == b.fingerprint != c.fingerprint
    assert np.all(np.abs(a.points[:, :2]) <= 1)
    assert set(a.points[:, 2]) <= {0.5, 1.0, 2.0}
    assert set(a.points[:, 3]) <= set(range(10)) and np.all(a.points[:, 3] == np.round(a.points[:, 3]))


def test_a_position_stack_sweep_sweeps_the_delay_and_servo_and_records_the_stack():
    """On position-controlled arms a sweep may vary the delay (whole periods)
    and the servo scale; the plan's rollouts run that stack, its base is the
    stack's one delay and defaults, and its spec (the resume fingerprint) says so."""
    stack = Stack("position", None, (2, 2))
    plan = sweep.make_plan(["delay=0:3:4", "servo_scale=0.7,1.3"], duration=4.0, stack=stack)
    assert plan.stack_options == ("position", 1, "jazzy") and len(plan.points) == 8
    g, scen = sweep.build_batch(plan.params, plan.points, plan.base_gains, plan.base_scenario)
    assert sorted(set(np.asarray(scen.delay).tolist())) == [0.0, 1.0, 2.0, 3.0]
    assert sorted(set(np.asarray(scen.servo_scale).tolist())) == [0.7, 1.3]
    assert plan.spec["stack"]["actuation"] == "position" and plan.spec["stack"]["servo"]["source"]
    base = sweep.make_plan(["k_rk=0,0.5"], duration=4.0, stack=stack)
    assert float(base.base_scenario.delay) == 2.0
    torque = sweep.make_plan(["k_rk=0,0.5"], duration=4.0)
    assert torque.fingerprint != base.fingerprint and torque.stack_options == ("torque", 1, "jazzy")
    # the deployed rule on its release: part of the stack and of the fingerprint; refused on torque arms
    humble = sweep.make_plan(
        ["k_rk=0,0.5"], duration=4.0, stack=Stack("position", None, (2, 2), "humble"), controller="ros2_admittance"
    )
    assert humble.stack_options == ("position", 1, "humble") and humble.fingerprint != base.fingerprint
    with pytest.raises(ConfigError, match="ros2_admittance.*position-controlled arms only"):
        sweep.make_plan(["k_rk=0,0.5"], duration=4.0, controller="ros2_admittance")
    samples = sweep.make_plan(["delay=0:3"], samples=40, seed=1, duration=4.0, stack=stack)
    assert set(samples.points[:, 0].tolist()) == {0.0, 1.0, 2.0, 3.0}  # whole periods, drawn


@pytest.mark.parametrize(
    "args, message",
    [
        (["--param", "k_zz=0:1:3"], "unknown parameter 'k_zz'"),
        (["--param", "imp_stiffness.w=1"], "unknown parameter 'imp_stiffness.w'"),
        (["--param", "lift=0.1"], "name one component"),
        (["--param", "k_rk=1:0:5"], "empty range"),
        (["--param", "k_rk=0:1:0"], "empty range"),
        (["--param", "k_rk="], "empty range"),
        (["--param", "k_rk=0:1:x"], "must be a whole number"),
        (["--param", "k_rk=a:1:3"], "'a' is not a number"),
        (["--param", "k_rk=0,,1"], "malformed list"),
        (["--param", "k_rk=0:1:2:3"], "malformed range"),
        (["--param", "k_rk"], "expected NAME=VALUES"),
        (["--param", "k_rk=0:1"], "needs a point count"),
        (["--param", "k_rk=-2:1:4"], "gain 'k_rk' must lie in"),
        (["--param", "object_mass=0,1"], "scenario 'object_mass' must lie in"),
        (["--param", "noise_seed=1.5"], "whole numbers"),
        (["--param", "k_rk=0,1", "--param", "k_rk=0"], "more than once"),
        (["--param", "imp_stiffness=50", "--param", "imp_stiffness.z=60"], "both set imp_stiffness"),
        (["--param", "k_rk=0,1", "--samples", "0"], "--samples must be a positive"),
        (["--param", "k_rk=0,1", "--duration", "2"], "--duration must be at least 2.70"),
        (["--param", "t_carry=1.2,3", "--duration", "4"], "--duration must be at least 4.50"),
        ([], "give at least one --param"),
        (["--param", "delay=0,1"], "apply to position-controlled arms (actuation='position')"),
        (["--param", "delay=0,1"], "(--param, --actuation)"),
        (["--actuation", "position", "--param", "delay=0.5,1"], "whole numbers"),
        (["--actuation", "position", "--param", "delay=0,9"], "delay"),
        (["--actuation", "position", "--delay", "0:2", "--param", "k_rk=0,1"], "one scenario runs one delay"),
    ],
)
def test_bad_input_is_a_clear_error(tmp_path, capsys, args, message):
    rc = run_cli(["sweep", "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    assert rc != 0, args
    assert message in err, (args, err)
    assert "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_folder_holding_a_sweep_needs_resume_or_restart(tmp_path, capsys):
    """As with jaxsync tune's checkpoint: a sweep already in --out is continued
    (--resume) or discarded (--restart), never taken over silently; checked
    before anything is compiled or removed."""
    out = tmp_path / "o"
    out.mkdir()
    plan = sweep.make_plan(["k_rk=0,1"], duration=4.0)
    (out / "plan.json").write_text(json.dumps({"fingerprint": plan.fingerprint, "chunk": 2, "n_chunks": 1}))
    (out / "results.csv").write_text("x\n")
    for extra, message in [
        ([], "pass --resume to continue it"),
        (["--resume", "--restart"], "give one of them"),
    ]:
        assert run_cli(["sweep", "--param", "k_rk=0,1", "--out", str(out), *extra]) == 2, extra
        err = capsys.readouterr().err
        assert message in err and "--restart" in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1
    assert (out / "results.csv").exists() and (out / "plan.json").exists()  # nothing removed
    assert run_cli(["sweep", "--param", "k_rk=0,1", "--out", str(tmp_path / "new"), "--resume"]) == 2
    assert "no sweep to continue" in capsys.readouterr().err


@pytest.mark.parametrize("params", [["k_rk=0,0.5,1"], ["k_rk=0,1", "object_mass=0.5,0.6"]], ids=["line", "heatmap"])
def test_a_plot_where_every_point_dropped_says_so(tmp_path, monkeypatch, params):
    """Not an empty plot: a note that every point dropped the object."""
    plan = sweep.make_plan(params, duration=4.0)
    n = len(plan.points)
    metrics = {k: np.full(n, np.nan) if k.endswith("_time_s") else np.ones(n) for k in _metrics.Metrics._fields}
    metrics.update(dropped=np.ones(n, bool), nonfinite=np.zeros(n, bool), drop_time_s=np.full(n, 1.5))
    figures = []
    monkeypatch.setattr(_results, "save_figure", lambda fig, path: figures.append(fig))
    name = sweep_report.plot(str(tmp_path), plan, metrics, sweep.DEFAULT_PLOT_METRICS)
    assert name == ("line.png" if len(params) == 1 else "heatmap.png")
    (fig,) = figures
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert len(panels) == len(sweep.DEFAULT_PLOT_METRICS)
    for ax in panels:
        assert any("every point dropped the object" in t.get_text() for t in ax.texts), ax.get_title()


# ----------------------------------------------------------------- compiled runs


def compile_ahead():
    """The sweep's chunk function (tests/conftest.py: compiled ahead in a second process)."""
    with tempfile.TemporaryDirectory() as tmp:
        assert run_cli(["sweep", *FAST, *GRID, "--out", os.path.join(tmp, "sweep")]) == 0


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "full"
    assert run_cli(["sweep", *FAST, *GRID, "--out", str(out)]) == 0
    return out


def test_sweep_writes_results_summary_and_heatmap(uninterrupted):
    rows = _rows(uninterrupted / "results.csv")
    assert len(rows) == 4
    assert [(float(r["k_rk"]), float(r["object_mass"])) for r in rows] == [
        (-0.5, 0.5),
        (-0.5, 0.6),
        (0.5, 0.5),
        (0.5, 0.6),
    ]
    for key in ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "nonfinite", "ok"):
        assert key in rows[0]
    assert all(r["ok"] == "1" and r["dropped"] == "0" for r in rows)
    assert all(0 < float(r["settled_peak_resultant_N"]) < 1 for r in rows)
    summary = json.loads((uninterrupted / "summary.json").read_text())
    assert summary["complete"] and summary["n_points"] == 4 and summary["n_ok"] == 4
    assert summary["chunk"] == 2 and summary["n_chunks"] == 2 and summary["plot"] == "heatmap.png"
    assert (uninterrupted / "heatmap.png").stat().st_size > 0
    assert sorted(os.listdir(uninterrupted / "chunks")) == ["chunk_00000.npz", "chunk_00001.npz", "computed_p0.jsonl"]
    assert not [p for p in os.listdir(uninterrupted) if p.startswith(".tmp")]


def test_sweep_point_equals_the_direct_rollout(uninterrupted, rollouts):
    """The point k_rk = 0.5, object_mass = 0.5 is the tests' task with the
    default gains: its metrics, from a vmapped chunk, are those of the single
    rollout (tests/conftest.py)."""
    (row,) = [r for r in _rows(uninterrupted / "results.csv") if (r["k_rk"], r["object_mass"]) == ("0.5", "0.5")]
    want = _metrics.to_dict(_metrics.summarize(rollouts["synchronous"], rollouts["scenario"]))
    for k in ("settled_peak_resultant_N", "mean_grip_force_N", "grip_force_error_rel", "sync_error_rms_m"):
        np.testing.assert_allclose(float(row[k]), want[k], rtol=1e-5, err_msg=k)


def test_resume_reads_finished_chunks_back(uninterrupted, tmp_path):
    out = tmp_path / "resumed"
    assert run_cli(["sweep", *FAST, *GRID, "--out", str(out), "--max-chunks", "1"]) == 0  # "interrupted"
    assert sorted(os.listdir(out / "chunks")) == ["chunk_00000.npz", "computed_p0.jsonl"]
    assert not (out / "results.csv").exists()
    first = (out / "chunks" / "chunk_00000.npz").stat().st_mtime_ns
    assert run_cli(["sweep", *FAST, *GRID, "--out", str(out), "--resume"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["chunks_loaded"] == 1 and summary["timing"]["chunks_computed"] == 1
    assert (out / "chunks" / "chunk_00000.npz").stat().st_mtime_ns == first  # read, not recomputed
    assert (out / "results.csv").read_bytes() == (uninterrupted / "results.csv").read_bytes()
    # a finished sweep re-run recomputes nothing
    assert run_cli(["sweep", *FAST, *GRID, "--out", str(out), "--resume"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["chunks_computed"] == 0 and summary["timing"]["compile_s"] == 0


def test_a_different_sweep_in_the_same_folder_needs_restart(uninterrupted, tmp_path, capsys):
    out = tmp_path / "other"
    assert run_cli(["sweep", *FAST, *GRID, "--out", str(out), "--max-chunks", "0"]) == 0
    changed = ["--param", "k_rk=-0.5,0.5", "--chunk", "2", "--no-progress"]  # one swept parameter
    assert run_cli(["sweep", *FAST, *changed, "--out", str(out)]) == 2
    assert "holds a different sweep" in capsys.readouterr().err
    assert run_cli(["sweep", *FAST, *changed, "--out", str(out), "--restart"]) == 0
    assert (out / "line.png").stat().st_size > 0  # a 1-D sweep: a line plot
    assert len(_rows(out / "results.csv")) == 2


def test_memory_budget_too_small_even_for_one(tmp_path, capsys):
    rc = run_cli(["sweep", *FAST, *GRID, "--out", str(tmp_path / "o"), "--memory-budget-gib", "1e-6"])
    err = capsys.readouterr().err
    assert rc == 2
    assert not (tmp_path / "o").exists()  # a rejected run leaves no empty output folder
    assert "exceed --memory-budget-gib 1e-06 even in chunks of one" in err


@pytest.mark.slow
def test_sharded_over_two_devices_equals_unsharded(uninterrupted, tmp_path):
    out = tmp_path / "sharded"
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    code = "import sys; from jaxsync.cli import main; sys.exit(main(['sweep', *sys.argv[1:]]))"
    proc = subprocess.run(
        [sys.executable, "-c", code, *FAST, *GRID, "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
        cwd=tmp_path,  # not the source checkout: python -c puts the cwd first on sys.path
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["devices"] == ["cpu:0", "cpu:1"]
    a, b = _rows(uninterrupted / "results.csv"), _rows(out / "results.csv")
    assert a[0].keys() == b[0].keys() and len(a) == len(b)
    for ra, rb in zip(a, b, strict=True):
        for k in ra:
            np.testing.assert_allclose(float(ra[k]), float(rb[k]), rtol=1e-9, err_msg=k)


def test_chunk_must_split_over_devices(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(jax, "local_devices", lambda *a: ["d0", "d1"])
    with pytest.raises(ConfigError, match="multiple of the 2 devices"):
        sweep.run(sweep.make_plan(["k_rk=0,1"]), str(tmp_path), chunk=3)


def test_cpu_chunks_stay_below_the_lapack_deadlock(monkeypatch):
    monkeypatch.delenv("JAXSYNC_CPU_VMAP_LIMIT", raising=False)
    if jax.default_backend() == "cpu":
        assert cpu_vmap_limit() == 64
        monkeypatch.setenv("JAXSYNC_CPU_VMAP_LIMIT", "0")
        assert cpu_vmap_limit() is None
        monkeypatch.setenv("JAXSYNC_CPU_VMAP_LIMIT", "many")
        with pytest.raises(ConfigError, match="JAXSYNC_CPU_VMAP_LIMIT"):
            cpu_vmap_limit()
        monkeypatch.delenv("JAXSYNC_CPU_VMAP_LIMIT")
    assert sweep.DEFAULT_CHUNK_PER_DEVICE["cpu"] <= (cpu_vmap_limit() or 10**9)


def test_a_ctrl_c_lost_in_a_callback_stops_the_sweep_after_that_chunk(tmp_path, monkeypatch, capsys):
    """A Ctrl-C inside code that swallows exceptions still stops the sweep
    (exit 130) after the chunk it landed in, every finished chunk on disk.
    The compiled chunk is a stand-in (the compiled runs are tested below)."""
    calls = []

    def chunk_fn(g, s):
        calls.append(len(calls))
        if len(calls) == 2:
            ctrl_c_in_a_gc_callback()  # Python's own handler: lost, and the sweep goes on
        fields = {k: np.full(1, 0.01) for k in _metrics.Metrics._fields}
        fields.update({k: np.full(1, np.nan) for k in _metrics.Metrics._fields if k.endswith("_time_s")})
        fields.update(dropped=np.zeros(1, bool), nonfinite=np.zeros(1, bool), chattering=np.zeros(1, bool))
        return _metrics.Metrics(**fields)

    monkeypatch.setattr(sweep, "_compile", lambda plan, c_stored, chunk, *a: (c_stored or chunk, chunk_fn, None, 0.0))
    monkeypatch.setattr(sweep, "evaluator", lambda *a: (None, 100))
    out = tmp_path / "sweep"
    argv = ["sweep", "--param", "k_rk=-0.5:0.5:2", "--param", "object_mass=0.5,0.6", "--chunk", "1"]
    argv += ["--no-progress", "--out", str(out)]
    assert run_cli(argv) == 130
    assert "jaxsync sweep: interrupted" in capsys.readouterr().err
    assert len(calls) == 2 and not (out / "summary.json").exists()
    assert run_cli([*argv, "--resume"]) == 0
    assert len(calls) == 4  # the two chunks left, the two finished read back
