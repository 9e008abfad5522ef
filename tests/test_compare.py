"""The paper's comparison: summary files, the claims on three scenarios, and CLI input errors."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from conftest import TEST_DURATION
from PIL import Image

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import compliance as _compliance
from jaxsync.control import gains as _gains
from jaxsync.control.gains import default_gains
from jaxsync.io import render as _render
from jaxsync.io import results as _results
from jaxsync.optimize.studies import compare as _compare
from jaxsync.optimize.studies.compare_video import VIDEO_FPS, compare_video
from jaxsync.runtime.cache import _COMPILE_EVENT, _RETRIEVAL_EVENT, compile_watch
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import crosscheck as _crosscheck
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.scenario import default_scenario


def _cli(*args, cwd):
    exe = os.path.join(os.path.dirname(sys.executable), "jaxsync")
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def test_compare_writes_a_well_formed_summary(tmp_path, rollouts, model):
    s = rollouts["scenario"]
    names = ("classical", "synchronous", "object_impedance", "task_space")
    results = {name: (rollouts[name], _metrics.summarize(rollouts[name], s)) for name in names}
    limits = np.full((2, 7), 1e9)
    stiffness = {n: _compliance.stiffness_at_pad(model, n, rollouts["gains"]) for n in names}
    summary = _compare.write_results(
        str(tmp_path), results, s, rollouts["gains"], {"test": True}, 1.0, limits, stiffness
    )
    assert summary["classical"]["torque_limit_share_right"] == 0.0  # nothing near a 1e9 N m limit
    for f in ("summary.json", "series.csv", "forces_classical.png", "forces_synchronous.png"):
        assert (tmp_path / f).stat().st_size > 0, f
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    assert on_disk["controllers"] == list(names)
    for name in names:
        for key in _compare.SUMMARY_KEYS:
            assert key in on_disk[name]
        assert isinstance(on_disk[name]["dropped"], bool)
        ratio = on_disk["classical"]["settled_peak_resultant_N"] / on_disk[name]["settled_peak_resultant_N"]
        if name != "classical":
            assert on_disk["resultant_ratios"][name] == pytest.approx(ratio)
    ratio = on_disk["classical"]["settled_peak_resultant_N"] / on_disk["synchronous"]["settled_peak_resultant_N"]
    assert on_disk["resultant_ratio"] == pytest.approx(ratio)
    # the synchronous controller at the default gains: 4 times the classical one's stiffness at a pad
    k = {n: on_disk[n]["apparent_stiffness_normal_N_per_m"] for n in names}
    assert k["synchronous"] == pytest.approx(4 * k["classical"], rel=1e-6)
    lines = _compare.table(on_disk)
    assert sum("resultant_ratio (classical / " in line for line in lines) == 3
    with open(tmp_path / "series.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(rollouts["classical"].time)
    assert {"time_s", "classical_resultant_force_N", "synchronous_right_normal_force_N"} <= set(rows[0])
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]  # atomic writes left nothing behind


@pytest.mark.slow
@pytest.mark.parametrize(
    "overrides",
    [{}, {"object_mass": 0.8, "mass_estimate": 0.8}, {"object_offset": [0.0, 0.008, 0.0]}],
    ids=["default", "mass-0.8kg", "offset-8mm"],
)
def test_paper_claims(model, overrides):
    """The paper's result on the default task and two others: the synchronous
    controller's settled peak resultant force is at least 4 times smaller,
    both hold the grip force within 2 % of f_d, and the object is not dropped."""
    s = default_scenario(**overrides)
    res = _compare.run(model, default_gains(), s, duration=4.0, log=lambda m: None, controllers=jaxsync.CONTROLLERS)
    m = {k: jax.tree_util.tree_map(np.asarray, v[1]) for k, v in res.items()}
    for name in jaxsync.CONTROLLERS:  # the baselines too hold the ball, at their defaults, without chatter
        assert not m[name].dropped and not m[name].nonfinite and not m[name].chattering, name
        assert m[name].grip_force_error_rel < 0.02, name
    # both show a real effect, not numerical noise
    assert m["synchronous"].settled_peak_resultant_N > 1e-3
    assert m["classical"].settled_peak_resultant_N >= 4 * m["synchronous"].settled_peak_resultant_N
    if not overrides:  # the README's numbers (jaxsync compare on the defaults)
        np.testing.assert_allclose(m["classical"].settled_peak_resultant_N, 0.0560, rtol=0.01)
        np.testing.assert_allclose(m["synchronous"].settled_peak_resultant_N, 0.00758, rtol=0.01)


def test_compare_rejects_bad_input(tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    bad_gains = tmp_path / "g.json"
    bad_gains.write_text('{"k_rk": 3}')
    cases = [
        (["--duration", "1.0"], "duration must be at least 2.70 s for this scenario"),
        (["--duration", "1.0"], "got 1.0 (--duration)"),
        (["--duration", "-2"], "must be positive"),
        (["--object-mass", "0"], "must be positive"),
        (["--object-offset", "0.5"], "object_offset"),
        (["--gains", str(bad_gains)], "k_rk"),
        (["--gains", str(tmp_path / "missing.json")], "no such file"),
        (["--out", str(blocker / "sub")], "cannot be written"),
        (["--delay", "2"], "delay applies to position-controlled arms"),
        (["--actuation", "position", "--delay", "0:3"], "one scenario runs one delay"),
        (["--actuation", "position", "--delay", "-1"], "within 0..8"),
        (["--actuation", "position", "--control-rate", "300"], "divide the physics rate 500 Hz"),
        (["--actuation", "velocity"], "invalid choice: 'velocity'"),
        (["--controllers", "classical,ros2_admittance"], "'ros2_admittance' runs on position-controlled arms only"),
    ]
    for args, message in cases:  # in this process (the console script itself: tests/test_model.py)
        try:
            rc = main(["compare", "--out", str(tmp_path / "o"), *args])
        except SystemExit as exit_:  # argparse's own errors
            rc = exit_.code
        err = capsys.readouterr().err
        assert rc == 2, args
        assert message in err, (args, err)
        assert "Traceback" not in err, args
        assert not (tmp_path / "o").exists(), args  # a rejected run creates no output folder


def test_render_cli_and_compare_video(tmp_path, model, rollouts, capsys):
    """``jaxsync render`` writes a non-blank PNG; the comparison video has one
    frame per 1/25 s of slowed-down rollout, its rendering counted on stderr
    (skipped without an OpenGL backend)."""
    try:
        _render.select_gl_backend()
    except _render.RenderUnavailableError as err:
        pytest.skip(f"no OpenGL backend: {err}")
    out = _cli("render", "--out", str(tmp_path), "--width", "320", "--height", "240", cwd=tmp_path)
    assert out.returncode == 0, out.stderr

    img = np.asarray(Image.open(tmp_path / "grasp.png"))
    assert img.shape == (240, 320, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 50

    s = rollouts["scenario"]
    results = {n: (rollouts[n], _metrics.summarize(rollouts[n], s)) for n in ("classical", "synchronous")}
    path = compare_video(model, results, s, str(tmp_path), speed=2.0, width=96, height=72)
    n_states = len(rollouts["classical"].time)
    expected = len(_render.frame_indices(n_states, VIDEO_FPS, 0.002, 2.0))
    err = capsys.readouterr().err
    for k, name in enumerate(("classical", "synchronous")):
        assert f"[video {k + 1}/2] rendering {name}: frame {expected}/{expected}" in err, err
    if path.endswith(".gif"):
        with Image.open(path) as gif:
            assert gif.n_frames <= expected and gif.n_frames > expected // 2  # Pillow merges identical frames
            assert gif.size == (2 * 96 + 4, 72)
    assert os.path.getsize(path) > 0


def test_infinite_duration_and_bad_cache_dir_are_clear_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["compare", "--duration", "inf", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2 and "finite" in capsys.readouterr().err
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["--cache-dir", str(blocker / "xla"), "info"]) == 2
    err = capsys.readouterr().err
    assert "compilation cache folder" in err and "Traceback" not in err


def _dropped(m, t=1.25):
    """These metrics as if the object had been lost at ``t``."""
    return m._replace(dropped=np.asarray(True), drop_time_s=np.asarray(t))


def test_a_drop_is_marked_not_measured(tmp_path, rollouts, monkeypatch):
    """When a controller drops the object its settled peak and the ratio mean
    nothing: the progress line and the table say when it dropped, the ratio
    is null, and the plot marks the drop (no settled peak line)."""
    s = rollouts["scenario"]
    results = {name: (rollouts[name], _metrics.summarize(rollouts[name], s)) for name in ("classical", "synchronous")}
    results["classical"] = (results["classical"][0], _dropped(results["classical"][1]))
    figures = {}
    save = _results.save_figure
    monkeypatch.setattr(
        _results, "save_figure", lambda fig, path: (figures.update({os.path.basename(path): fig}), save(fig, path))
    )
    summary = _compare.write_results(str(tmp_path), results, s, rollouts["gains"], {}, 1.0)
    assert summary["resultant_ratio"] is None
    assert json.loads((tmp_path / "summary.json").read_text())["resultant_ratio"] is None
    assert _compare.outcome(results["classical"][1]) == "dropped the object at t=1.250 s"
    assert _compare.outcome(results["synchronous"][1]).startswith("settled peak resultant 0.00")
    lines = _compare.table(summary)
    peak_row = next(line for line in lines if line.startswith("settled_peak_resultant_N"))
    assert "dropped at t=1.25 s" in peak_row and peak_row.count("dropped") == 1
    assert lines[-1] == "resultant_ratio (classical / synchronous): n/a (the classical controller dropped the object)"

    def marks(fig):
        return [
            line.get_label()
            for ax in fig.axes
            for line in ax.get_lines()
            if "dropped" in line.get_label() or "settled peak" in line.get_label()
        ]

    assert marks(figures["forces_classical.png"]) == ["dropped at t=1.25 s"]
    assert list(figures["forces_classical.png"].axes[1].get_lines()[-1].get_xdata()) == [1.25, 1.25]
    assert marks(figures["forces_synchronous.png"])[0].startswith("settled peak")


def test_a_comparison_with_a_drop_lists_the_video_and_says_so(tmp_path, model, rollouts, monkeypatch, capsys):
    """run_comparison with a dropped object: the files are written, the drop is
    in the result, no settled peak quoted for the dropped controller; the video
    (rendering replaced by a stand-in) is listed last. The rollouts are the
    session's (no compiling). Gains tuned for a controller that is not compared
    come with a note, said before the rollouts with the stability ratio."""
    trajs = {id(rollouts[n]): n for n in ("classical", "synchronous")}
    monkeypatch.setattr(_compare, "rollout", lambda model, gains, s, *, controller, **kw: rollouts[controller])
    summarize = _metrics.summarize
    monkeypatch.setattr(
        _metrics,
        "summarize",
        lambda traj, s: _dropped(summarize(traj, s)) if trajs.get(id(traj)) == "classical" else summarize(traj, s),
    )
    monkeypatch.setattr(_compare, "select_gl_backend", lambda: "egl")
    monkeypatch.setattr(
        _compare, "compare_video", lambda model, results, s, out, speed, **kw: os.path.join(out, "compare.mp4")
    )
    gains = tmp_path / "gains.json"
    gains.write_text(json.dumps({"gains": _gains.to_dict(default_gains()), "controller": "task_space"}))
    out, said = tmp_path / "o", []
    r = _compare.run_comparison(model, gains=str(gains), out=str(out), video_speed=0.5, say=said.append)
    captured = capsys.readouterr()
    progress = [line for line in captured.err.splitlines() if line.startswith("[1/2] classical: done")]
    assert progress and "dropped the object at t=1.250 s" in progress[0] and "settled peak" not in progress[0]
    assert "(the first run compiles)" not in captured.err
    assert r.dropped == {"classical": 1.25} and r.unstable == [] and r.sim_to_sim_agree is None
    table = "\n".join(_compare.table(r.summary))
    assert "resultant_ratio (classical / synchronous): n/a" in table and "dropped at t=1.25 s" in table
    assert ", ".join(r.files).endswith("forces_synchronous.png, compare.mp4")
    assert json.loads((out / "summary.json").read_text())["resultant_ratio"] is None
    for f in ("summary.json", "series.csv", "forces_classical.png", "forces_synchronous.png"):
        assert (out / f).stat().st_size > 0
    assert r.notes == [
        f"{gains} was tuned for the task_space controller, which is not among the controllers compared "
        "(classical, synchronous)"
    ]
    assert said[0] == f"note: {r.notes[0]}" and said[1].startswith("normal-axis stability ratio")
    right, left = r.stability_ratio
    assert f"right {right:.2f}, left {left:.2f}" in said[1] and right == pytest.approx(1.31, abs=0.01)


def test_a_position_stack_comparison_runs_its_delay_gains_and_records_the_stack(model, monkeypatch):
    """run_comparison(stack=...): the scenario carries the stack's one delay, the
    baseline is the position stack's defaults, and summary.json's options name
    the stack and its servo (paper_comparison replaced by a stand-in)."""
    seen = {}

    def fake(m, g, scenario, out, **kw):
        seen.update(gains=g, scenario=scenario, **kw)
        return {}, []

    monkeypatch.setattr(_compare, "paper_comparison", fake)
    stack = _actuation.Stack("position", None, (3, 3))
    _compare.run_comparison(model, stack=stack, say=lambda m: None)
    assert float(seen["scenario"].delay) == 3.0 and seen["stack"] is stack
    assert seen["options"]["stack"] == stack.to_dict(model) and seen["options"]["stack"]["servo"]["source"]
    assert float(seen["gains"].kp_pos) == float(default_gains(model, "position").kp_pos)
    # the rule plus the coupling runs its own defaults, and says so where the synchronous law shares them
    for controllers, said in (
        (("ros2_admittance", "ros2_synchronous"), False),
        (("synchronous", "ros2_synchronous"), True),
    ):
        lines = []
        _compare.run_comparison(model, stack=stack, controllers=controllers, say=lines.append)
        assert float(seen["gains"].k_rk) == 0.25 == -float(seen["gains"].k_lk)
        assert any("synchronous runs ros2_synchronous's default gains" in x for x in lines) is said, lines


def test_the_comparison_scenario_takes_the_values_given(model):
    """--object-mass and the rest as run_comparison's overrides: the mass
    estimate follows the mass, the offset is along the clamping axis, the
    seed draws the sensor noise."""
    s = _compare.comparison_scenario(model, seed=3, object_mass=0.8, object_offset=0.008, force_noise=0.2)
    assert float(s.object_mass) == float(s.mass_estimate) == 0.8 and float(s.force_noise) == 0.2
    np.testing.assert_array_equal(np.asarray(s.object_offset), [0.0, 0.008, 0.0])
    np.testing.assert_array_equal(np.asarray(s.noise_key), jax.random.key_data(jax.random.key(3)))
    assert float(s.grip_force) == float(default_scenario(model).grip_force)
    with pytest.raises(ConfigError, match="not object_radius"):
        _compare.run_comparison(model, overrides={"object_radius": 0.2})
    with pytest.raises(ConfigError, match="^duration must be at least") as err:
        _compare.run_comparison(model, duration=1.0, say=lambda m: None)
    assert err.value.inputs == ("duration",)


def _summary(tmp_path, rollouts, dropped: bool = False) -> dict:
    s = rollouts["scenario"]
    results = {name: (rollouts[name], _metrics.summarize(rollouts[name], s)) for name in ("classical", "synchronous")}
    if dropped:
        results["classical"] = (results["classical"][0], _dropped(results["classical"][1]))
    return _compare.write_results(str(tmp_path / "written"), results, s, rollouts["gains"], {}, 1.0)


def test_compare_cli_calls_the_job_prints_it_and_exits_by_it(tmp_path, rollouts, monkeypatch, capsys):
    """jaxsync compare: its flags become run_comparison's arguments (the job
    replaced by a stand-in that returns what it is given); the table, the files
    and the video are printed; exit status 4 on a drop, 6 on chatter."""
    calls = []
    files = ["summary.json", "series.csv", "forces_classical.png", "forces_synchronous.png", "compare.mp4"]
    summary = _summary(tmp_path, rollouts, dropped=True)
    comparison = _compare.Comparison(summary, files, (1.3, 1.3), [], {"classical": 1.25}, [], None)

    def job(model, **kw):
        calls.append((model, kw))
        return comparison

    monkeypatch.setattr(_compare, "run_comparison", job)
    out = tmp_path / "o"
    argv = ["compare", "--out", str(out), "--video", "--object-offset", "0.008", "--seed", "3"]
    assert main(argv) == 4
    captured = capsys.readouterr()
    ((model, kw),) = calls
    assert model is None and kw["gains"] is None and not kw["any_model"] and kw["visual"]
    assert kw["overrides"] == {"object_mass": None, "grip_force": None, "object_offset": 0.008, "force_noise": None}
    assert (kw["seed"], kw["duration"], kw["out"], kw["backend"]) == (3, 4.0, str(out), "mjx")
    assert kw["controllers"] == ("classical", "synchronous") and kw["video_speed"] == 0.5
    assert kw["mujoco_check"] is None and kw["options"]["object_offset"] == 0.008 and "func" not in kw["options"]
    assert kw["stack"] == _actuation.Stack()  # torque, every physics step, no delay
    assert "resultant_ratio (classical / synchronous): n/a" in captured.out and "dropped at t=1.25 s" in captured.out
    assert captured.out.strip().splitlines()[-1].endswith("forces_synchronous.png, compare.mp4")
    last = captured.err.strip().splitlines()[-1]
    assert "the classical controller dropped the object at t=1.250 s" in last and "exit status 4" in last
    comparison = _compare.Comparison(_summary(tmp_path, rollouts), files[:4], (1.3, 1.3), [], {}, ["synchronous"], None)
    comparison.summary["synchronous"]["force_chatter_N"] = 2.5
    assert main(["compare", "--out", str(out), "--controllers", "synchronous,classical", "--no-visual"]) == 6
    assert calls[-1][1]["controllers"] == ("synchronous", "classical") and not calls[-1][1]["visual"]
    argv = ["compare", "--out", str(out), "--actuation", "position", "--delay", "2", "--control-rate", "250"]
    main([*argv, "--ros-distro", "humble"])
    assert calls[-1][1]["stack"] == _actuation.Stack("position", 250.0, (2, 2), "humble")
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "the synchronous controller's pad forces chattered (RMS change per step 2.5 N > 1 N)" in last
    assert "exit status 6" in last


def test_compile_watch_tells_compiling_from_a_cache_read():
    """The progress line says what happened: compiling, a program read back
    from the persistent cache, or neither (already compiled in this process;
    only small eager programs compiled, which the cache does not keep). The
    events as jax reports them (a cache read is timed inside its compile event)."""
    with compile_watch() as w:  # a big program read back from the cache
        jax.monitoring.record_event_duration_secs(_RETRIEVAL_EVENT, 2.9)
        jax.monitoring.record_event_duration_secs(_COMPILE_EVENT, 3.0)
    assert w.cache_hits == 1 and w.compile_s == 0
    assert w.describe() == " (compiled program read from the compilation cache)"
    with compile_watch() as w:
        jax.monitoring.record_event_duration_secs(_COMPILE_EVENT, 42.0)
        for _ in range(20):  # eager operations: small programs, compiled in every process
            jax.monitoring.record_event_duration_secs(_COMPILE_EVENT, 0.1)
    assert w.describe() == " (42.0 s of it compiling; the compilation cache keeps it for later runs)"
    f = jax.jit(lambda x: x * 3.0 + 1.0)
    f(1.0)
    with compile_watch() as w:  # already compiled here: nothing to say
        f(2.0)
    assert w.compile_s == 0 and w.cache_hits == 0 and w.describe() == ""
    jax.monitoring.record_event_duration_secs(_COMPILE_EVENT, 5.0)  # outside the block: not counted
    assert w.compile_s == 0


def test_sim_to_sim_check_mjx_beside_mujoco_c(model, rollouts, shared_rollout, monkeypatch):
    """Gains against a baseline on MJX and on MuJoCo C with the
    same jitted control law. MJX's side is the session's own rollout to the last
    digit; MuJoCo C lands within 5 % of it; the factors agree and the table says
    so; a disagreement or a drop is flagged with a WARNING line."""
    s, g = rollouts["scenario"], rollouts["gains"]
    g2 = g._replace(k_rl=jax.numpy.asarray(0.2), k_ll=jax.numpy.asarray(0.2))
    batch = jax.tree_util.tree_map(lambda x: jax.numpy.asarray(x)[None], s)
    monkeypatch.setattr(_crosscheck, "rollout", shared_rollout)  # the same rollouts, run once for the session
    check = _crosscheck.sim_to_sim(model, g2, g, batch, TEST_DURATION, n=4, log=lambda m: None)
    assert check["scenarios"] == 1 and check["scenarios_lost"] == []
    assert check["mjx_before_N"] == float(_metrics.summarize(rollouts["synchronous"], s).settled_peak_resultant_N)
    for which in ("before", "after"):
        assert check[f"mujoco_{which}_N"] == pytest.approx(check[f"mjx_{which}_N"], rel=0.05)
        assert check[f"mujoco_{which}_N"] != check[f"mjx_{which}_N"]  # another engine did roll it out
    assert check["factor_mjx"] == pytest.approx(check["mjx_before_N"] / check["mjx_after_N"])
    assert abs(check["factor_mjx"] - 1.0) > 0.05  # the two gains differ measurably, else the check proves nothing
    lines = _crosscheck.sim_to_sim_table(check)
    assert check["agree"] and lines[-1].startswith("sim-to-sim: the improvement factors agree within 10 %"), lines
    assert json.loads(json.dumps(check)) == check  # summary.json takes it as it is

    per = json.loads(json.dumps(check["per_scenario"]))
    per["mujoco_after"][0]["settled_peak_resultant_N"] *= 1.5  # MuJoCo C's factor 1/1.5 of MJX's
    off = _crosscheck.sim_to_sim_verdict(per, 1, TEST_DURATION)
    assert not off["agree"] and off["difference"] == pytest.approx((1 + check["difference"]) / 1.5 - 1)
    assert _crosscheck.sim_to_sim_table(off)[-1].startswith("WARNING: sim-to-sim check failed: the improvement factor")
    per["mujoco_after"][0]["settled_peak_resultant_N"] /= 1.5
    per["mujoco_before"][0]["lost"] = True
    lost = _crosscheck.sim_to_sim_verdict(per, 1, TEST_DURATION)
    assert not lost["agree"] and lost["factor_mujoco"] is None and "dropped" in _crosscheck.sim_to_sim_table(lost)[-1]


def test_comparison_mujoco_check_records_a_disagreement(tmp_path, model, rollouts, monkeypatch):
    """run_comparison(mujoco_check=N): the check runs on tune's held-out scenarios
    and horizon, its table shows both engines' factors, summary.json records it,
    and the result says whether the engines agree (the rollouts are the session's,
    the check a stand-in: no compiling)."""
    monkeypatch.setattr(_compare, "rollout", lambda model, gains, s, *, controller, **kw: rollouts[controller])
    row = lambda peak: [{"settled_peak_resultant_N": peak, "grip_force_error_rel": 0.003, "lost": False}]  # noqa: E731
    per = {"mjx_before": row(0.01), "mjx_after": row(0.001), "mujoco_before": row(0.01), "mujoco_after": row(0.004)}
    seen = {}

    def fake(model, gains, baseline, scenarios, duration, *, n, **kw):
        seen.update(n=n, duration=duration, count=int(jax.tree_util.tree_leaves(scenarios)[0].shape[0]))
        return _crosscheck.sim_to_sim_verdict(per, 1, duration)

    monkeypatch.setattr(_crosscheck, "sim_to_sim", fake)
    out = tmp_path / "o"
    quiet = {"say": lambda m: None, "log": lambda m: None}
    r = _compare.run_comparison(model, out=str(out), mujoco_check=4, **quiet)
    assert seen == {"n": 4, "duration": 4.0, "count": 16}  # tune's held-out scenarios and horizon
    text = "\n".join(_crosscheck.sim_to_sim_table(r.summary["sim_to_sim"], "the default gains"))
    assert "10.00x" in text and "2.50x" in text and "WARNING: sim-to-sim check failed" in text
    assert r.sim_to_sim_agree is False and r.dropped == {}
    assert json.loads((out / "summary.json").read_text())["sim_to_sim"]["agree"] is False
    per["mujoco_after"] = row(0.00105)  # 5 % apart: within the tolerance
    r = _compare.run_comparison(model, out=str(out), mujoco_check=2, **quiet)
    assert seen["n"] == 2 and r.sim_to_sim_agree is True
    assert "agree within 10 %" in "\n".join(_crosscheck.sim_to_sim_table(r.summary["sim_to_sim"]))


def test_compare_cli_prints_the_mujoco_check_and_exits_5_on_a_disagreement(tmp_path, rollouts, monkeypatch, capsys):
    """compare --mujoco-check: the check's table is printed, and a disagreement
    ends in a one-line WARNING and exit status 5 (the job replaced by a stand-in)."""
    row = lambda peak: [{"settled_peak_resultant_N": peak, "grip_force_error_rel": 0.003, "lost": False}]  # noqa: E731
    per = {"mjx_before": row(0.01), "mjx_after": row(0.001), "mujoco_before": row(0.01), "mujoco_after": row(0.004)}
    summary, calls = _summary(tmp_path, rollouts), []

    def job(model, **kw):
        calls.append(kw["mujoco_check"])
        summary["sim_to_sim"] = check = _crosscheck.sim_to_sim_verdict(per, 1, 4.0)
        return _compare.Comparison(summary, ["summary.json"], (1.3, 1.3), [], {}, [], check["agree"])

    monkeypatch.setattr(_compare, "run_comparison", job)
    out = tmp_path / "o"
    assert main(["compare", "--out", str(out), "--mujoco-check"]) == 5
    captured = capsys.readouterr()
    assert "10.00x" in captured.out and "2.50x" in captured.out and "WARNING: sim-to-sim check failed" in captured.out
    last = captured.err.strip().splitlines()[-1]
    assert last.startswith("jaxsync compare: WARNING: the MuJoCo C check failed") and "exit status 5" in last
    per["mujoco_after"] = row(0.00105)  # 5 % apart: within the tolerance
    assert main(["compare", "--out", str(out), "--mujoco-check", "2"]) == 0
    assert calls == [4, 2] and "agree within 10 %" in capsys.readouterr().out
