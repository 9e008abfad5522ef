"""``jaxsync sensitivity``: reverse-mode elasticities against central
differences, and the command's files and errors (one compiled program shared
by the library test and the command)."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.optimize.studies import sensitivity as _sensitivity
from jaxsync.optimize.studies.sensitivity import (
    METRICS,
    Sensitivity,
    SensitivityRun,
    elasticities,
    metrics_function,
    run_sensitivity,
    sensitivity,
    table,
)
from jaxsync.optimize.tuning.scenarios import sample_scenarios
from jaxsync.sim.actuation import Stack

DURATION = 1.7  # the short task's shortest horizon with a settled window
BATCH = 2


@pytest.fixture(scope="module")
def computed(model):
    scen = sample_scenarios(jax.random.key(0), BATCH, jaxsync.short_task())  # the command's --seed 0
    return scen, sensitivity(model, _gains.default_gains(), scen, DURATION)


@pytest.mark.slow
def test_elasticities_match_central_differences(model, computed):
    """Seven gain entries (three signed k's, four positive gains of both arms
    and the inner loop), each metric: 4-point central differences in log gain
    (in k for the signed factors) against the reverse-mode elasticities,
    relative error at most 1e-4 per metric over the entries. The step is
    1e-4: at 1e-3 the differences themselves drift by up to 4e-4 (measured)."""
    scen, s = computed
    assert s.values.shape == (3,) and s.elasticity.shape == (3, len(s.names)) == (3, 44)
    assert np.all(np.isfinite(s.elasticity)) and np.all(s.values > 0)
    f = jax.jit(metrics_function(model, DURATION))
    flat, unravel = ravel_pytree(_gains.default_gains())
    # same forward values: two programs (the forward pass, and the vjp's primal) that XLA compiles
    # apart and may sum in another order, and the force chatter (a difference of successive steps)
    # carries that rounding through 850 steps: hence rtol 1e-8, not agreement to the last digits
    np.testing.assert_allclose(np.asarray(f(unravel(flat), scen)), s.values, rtol=1e-8, atol=0)
    checked = ["k_rk", "k_lk", "k_rl", "imp_stiffness[right,z]", "imp_damping[left,z]", "imp_mass[right,x]", "kp_pos"]
    cols = [s.names.index(name) for name in checked]
    h = 1e-4
    fd = []
    for name, j in zip(checked, cols, strict=True):
        signed = name.startswith("k_")

        def at(c, j=j, signed=signed):
            x = flat.at[j].add(c * h) if signed else flat.at[j].multiply(np.exp(c * h))
            return np.log(np.asarray(f(unravel(x), scen)))

        fd.append((at(-2) - 8 * at(-1) + 8 * at(1) - at(2)) / (12 * h))  # d log m / d log g (d k)
    fd = np.array(fd).T  # (3 metrics, entries)
    for i, m in enumerate(METRICS):
        e = s.elasticity[i, cols]
        assert np.linalg.norm(fd[i] - e) <= 1e-4 * np.linalg.norm(fd[i]), (m, fd[i], e)
    # a real effect, not noise: the peak and the grip error respond to the synchronisation factor k_rl
    assert abs(s.elasticity[0, s.names.index("k_rl")]) > 1 and abs(s.elasticity[1, s.names.index("k_rl")]) > 1


def test_elasticity_scaling():
    names = ["k_rk", "kp_pos"]
    e = elasticities(names, np.array([0.5, 200.0]), np.array([2.0]), np.array([[3.0, 0.01]]))
    np.testing.assert_allclose(e, [[1.5, 1.0]])  # k: (1/m) dm/dk; positive gain: (g/m) dm/dg


def test_the_feed_forward_is_read_on_position_arms_per_unit(model, monkeypatch):
    """On position-controlled arms jaxsync's laws read the command's
    feed-forward (0 by default): its entries are kept, their elasticity per
    unit (an elasticity per log value would be 0 at 0); on the torque stack
    and for the rule they are left out. The program is a stand-in whose
    derivative is 1 for every entry."""

    def program(model, duration, start, controller, stack):
        return lambda g, s: (np.full(3, 2.0), jax.tree_util.tree_map(lambda x: np.ones((3, *np.shape(x))), g))

    monkeypatch.setattr(_sensitivity, "program", program)
    g = _gains.default_gains()
    on = sensitivity(model, g, None, DURATION, stack=Stack("position", None, (0, 0)))
    assert on.names[-2:] == ["ff_vel", "ff_acc"] and len(on.names) == 46
    np.testing.assert_array_equal(on.elasticity[:, -2:], 0.5)  # (1/m) dm/dff
    for controller, stack in (("synchronous", Stack()), ("ros2_admittance", Stack("position", None, (0, 0)))):
        off = sensitivity(model, g, None, DURATION, controller=controller, stack=stack)
        assert "ff_acc" not in off.names and "ff_vel" not in off.names


@pytest.mark.slow
def test_job_writes_table_csv_json_and_chart(model, computed, tmp_path):
    out = tmp_path / "sens"
    r = run_sensitivity(model, task="short", duration=DURATION, batch=BATCH, out=str(out), log=lambda m: None)
    _, s = computed
    res = json.loads((out / "sensitivity.json").read_text())
    assert [row["gain"] for row in res["rows"]] == s.names
    np.testing.assert_array_equal([res["metrics"][m] for m in res["metrics"]], s.values)
    np.testing.assert_array_equal([row["elasticity_settled_peak_resultant_N"] for row in res["rows"]], s.elasticity[0])
    header = (out / "sensitivity.csv").read_text().splitlines()[0].split(",")
    assert header[:2] == ["gain", "value"] and len(header) == 2 + 2 * 3
    assert (out / "sensitivity.png").stat().st_size > 10_000
    assert "imp_stiffness[right,z]" in table(r.sensitivity) and "sensitivity.png" in r.files
    np.testing.assert_array_equal(r.sensitivity.elasticity, s.elasticity)


def test_command_calls_the_job_and_prints_its_table(tmp_path, monkeypatch, capsys):
    """jaxsync sensitivity: its flags become run_sensitivity's arguments (the job
    replaced by a stand-in), and the table and the files are printed."""
    names = ["k_rk", "imp_stiffness[right,z]"]
    s = Sensitivity(names, np.array([0.5, 300.0]), np.ones(3), np.zeros((3, 2)), np.full((3, 2), 0.25))
    calls = []

    def job(model, **kw):
        calls.append((model, kw))
        return SensitivityRun(s, ["sensitivity.csv", "sensitivity.json", "sensitivity.png"], 12.0)

    monkeypatch.setattr(_sensitivity, "run_sensitivity", job)
    out = tmp_path / "sens"
    argv = ["sensitivity", "--task", "short", "--duration", str(DURATION), "--batch", str(BATCH), "--out", str(out)]
    assert main([*argv, "--gains", "g.json", "--any-model", "--controller", "classical", "--seed", "5"]) == 0
    ((model, kw),) = calls
    assert model is None and kw.pop("log") is not None
    assert kw == {
        "gains": "g.json",
        "any_model": True,
        "visual": True,
        "task": "short",
        "duration": DURATION,
        "batch": BATCH,
        "seed": 5,
        "controller": "classical",
        "out": str(out),
        "stack": Stack(),
    }
    text = capsys.readouterr().out
    assert "imp_stiffness[right,z]" in text and "sensitivity.png" in text and "(12 s)" in text
    assert main(["sensitivity", "--out", str(out)]) == 0
    assert calls[-1][1]["task"] == "full" and calls[-1][1]["duration"] is None  # the job's default for the task
    assert main(["sensitivity", "--out", str(out), "--actuation", "position", "--delay", "0:3"]) == 0
    assert calls[-1][1]["stack"] == Stack("position", None, (0, 3))


def test_job_defaults_and_its_errors_in_its_own_words(model, tmp_path):
    """run_sensitivity names its parameters in what it refuses, before writing anything."""
    with pytest.raises(ConfigError, match="^duration must be at least 1.7 s for the short task") as err:
        run_sensitivity(model, task="short", duration=1.0, out=str(tmp_path / "o"))
    assert err.value.inputs == ("duration",)
    with pytest.raises(ConfigError, match="^task must be one of full, short"):
        run_sensitivity(model, task="long", out=str(tmp_path / "o"))
    schedule = _schedule.constant(_gains.default_gains())
    with pytest.raises(ConfigError, match="^gains must be constant gains"):
        run_sensitivity(model, gains=schedule, out=str(tmp_path / "o"))
    path = tmp_path / "schedule.json"
    path.write_text(json.dumps({"gains": _schedule.to_file_dict(schedule)}))
    with pytest.raises(ConfigError, match="the sensitivity study takes constant gains"):
        run_sensitivity(model, gains=str(path), out=str(tmp_path / "o"))
    assert not (tmp_path / "o").exists()
    assert _sensitivity.TASK_DURATION == {"full": 4.0, "short": 2.0}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--batch", "0"], "--batch"),
        (["--task", "short", "--duration", "1.0"], "duration must be at least 1.7 s"),
        (["--task", "short", "--duration", "1.0"], "(--duration)"),
        (["--gains", "/nonexistent/gains.json"], "gains"),
    ],
)
def test_command_rejects_bad_input_before_writing(tmp_path, capsys, extra, message):
    out = tmp_path / "never"
    try:
        code = main(["sensitivity", "--out", str(out), *extra])
    except SystemExit as e:  # argparse's own checks
        code = e.code
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
