"""Runs that lose nothing and run nothing they should not: data-only
checkpoints, resuming every method, one run per folder, inputs checked before
any work, and clear endings for expected outcomes.

The tuning loop and the held-out rollouts are stand-ins here (the real ones
are tested in test_tune.py); what is tested is the plumbing around them.
"""

from __future__ import annotations

import json
import os
import pickle
import socket
import subprocess
import sys

import numpy as np
import pytest
from conftest import fake_heldout_metrics

from jaxsync._errors import ConfigError, DroppedObjectError, JaxsyncError
from jaxsync.cli import main
from jaxsync.control.gains import default_gains
from jaxsync.io import results as _results
from jaxsync.optimize.studies import sweep
from jaxsync.optimize.studies.sweep_spec import parse_param
from jaxsync.optimize.tuning import checkpoint, methods, pipeline, tune_state
from jaxsync.optimize.tuning import loss as loss_mod
from jaxsync.optimize.tuning import tune as tune_mod
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.methods import Oracle
from jaxsync.optimize.tuning.params import TuneSpec
from jaxsync.optimize.tuning.tune import TuneResult, method_of
from jaxsync.optimize.tuning.tune_report import change_text, summary_lines

QUICK = ["--iterations", "1", "--no-mujoco-check"]


def _quadratic():
    a = np.diag([1.0, 30.0, 300.0])
    return Oracle(
        value_and_grad=lambda x: (0.5 * x @ a @ x, a @ x),
        values=lambda xs: 0.5 * np.einsum("pi,ij,pj->p", xs, a, xs),
    )


# ------------------------------------------------------------ checkpoints


def test_a_checkpoint_is_data_and_a_pickle_is_refused_unread(tmp_path):
    """A file whose unpickling would run code is refused without being
    unpickled: the code does not run (here it would create a file)."""
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    path = tmp_path / "checkpoint.npz"
    path.write_bytes(pickle.dumps({"theta": Payload()}))
    with pytest.raises(ConfigError, match="not a jaxsync checkpoint"):
        checkpoint.load(str(path))
    assert not marker.exists()
    # an .npz whose arrays are pickled objects is refused too
    np.savez(path.with_suffix(".obj.npz"), x=np.array([Payload()], dtype=object))
    with pytest.raises(ConfigError, match="not a jaxsync checkpoint"):
        checkpoint.load(str(path.with_suffix(".obj.npz")))
    assert not marker.exists()


def test_checkpoints_keep_the_loops_types(tmp_path):
    state = {
        "theta": {"k_rk": np.float64(0.3) * np.ones(())},
        "kept": {5: {"k_rk": np.ones(3)}},
        "history": [{"iteration": 1, "cost": float("nan"), "term_grip": 2.5}],
        "fingerprint": {"weight": ["grip=3"], "pair": (1, 2), "gains": None},
        "count": np.int64(4),
    }
    checkpoint.save(str(tmp_path / "c.npz"), state)
    back = checkpoint.load(str(tmp_path / "c.npz"))
    assert back["kept"][5]["k_rk"].tolist() == [1.0, 1.0, 1.0] and type(back["count"]) is int
    assert back["fingerprint"] == state["fingerprint"] and back["history"][0]["iteration"] == 1
    assert np.isnan(back["history"][0]["cost"])


@pytest.mark.parametrize("name", ["cmaes", "cmaes-lbfgs", "lbfgs", "adam"])
def test_every_method_resumes_where_an_uninterrupted_run_goes(tmp_path, name):
    """Two steps, the state through a checkpoint file, two more: the same
    iterate, bit for bit, as four steps in one go (CMA-ES's state is replayed
    from its told costs; cmaes-lbfgs switches to L-BFGS after the resume)."""
    opts = {"generations": 3} if name == "cmaes-lbfgs" else {}
    method = methods.get(name, **opts)
    x0 = np.array([1.0, -0.5, 0.2])
    whole = method.init(x0, seed=3)
    for _ in range(4):
        whole, _ = method.step(whole, _quadratic())
    part = method.init(x0, seed=3)
    for _ in range(2):
        part, _ = method.step(part, _quadratic())
    checkpoint.save(str(tmp_path / "c.npz"), {"opt_state": method.to_data(part)})
    part = method.from_data(checkpoint.load(str(tmp_path / "c.npz"))["opt_state"])
    for _ in range(2):
        part, _ = method.step(part, _quadratic())
    np.testing.assert_array_equal(method.incumbent(part), method.incumbent(whole))


def test_a_cmaes_tuning_state_saves_and_resumes(tmp_path):
    """The tuner's own state of a CMA-ES run through save_state / resumed_state."""
    spec, base, method = TuneSpec(), default_gains(), methods.get("cmaes")
    state = tune_state.fresh_state(spec, base, method, seed=0)
    mstate, _ = method.step(state.opt_state, _quadratic_like(method.incumbent(state.opt_state)))
    state = state._replace(opt_state=mstate, iteration=1)
    path = str(tmp_path / "checkpoint.npz")
    tune_state.save_state(path, state, {"method": "cmaes"}, method)
    back = tune_state.resumed_state(path, {"method": "cmaes"}, spec, base, method)
    np.testing.assert_array_equal(method.incumbent(back.opt_state), method.incumbent(mstate))
    assert back.iteration == 1


def _quadratic_like(x0):
    n = len(x0)
    return Oracle(
        value_and_grad=lambda x: (float(np.sum((x - 1) ** 2)), 2 * (x - 1)),
        values=lambda xs: np.sum((np.asarray(xs) - 1) ** 2, axis=1) + 0 * n,
    )


def test_a_resume_names_the_options_that_differ(tmp_path):
    spec, base = TuneSpec(), default_gains()
    method = method_of(TuneConfig(method="adam"))
    state = tune_state.fresh_state(spec, base, method)
    path = str(tmp_path / "checkpoint.npz")
    tune_state.save_state(path, state, {"seed": 0, "batch": 4, "lr": 0.05}, method)
    with pytest.raises(ConfigError) as err:
        tune_state.resumed_state(path, {"seed": 7, "batch": 4, "lr": 0.05}, spec, base, method)
    assert "seed: 0 then, 7 now" in str(err.value) and "batch" not in str(err.value)


def test_a_cosine_run_resumed_with_other_iterations_is_refused(tmp_path):
    """Its learning rate decays over the first length: a longer resumed run
    would not be the longer run. A constant-rate run can be extended."""
    spec, base = TuneSpec(), default_gains()
    method = method_of(TuneConfig(method="adam", iterations=3))
    state = tune_state.fresh_state(spec, base, method)
    path = str(tmp_path / "checkpoint.npz")
    tune_state.save_state(path, state, None, method, 3)
    with pytest.raises(ConfigError, match="iterations 5, but the run .* decays its learning rate over 3"):
        tune_state.resumed_state(path, None, spec, base, method, 5)
    assert tune_state.resumed_state(path, None, spec, base, method, 3).iteration == 0
    tune_state.save_state(path, state, None, method, None)  # constant rate
    assert tune_state.resumed_state(path, None, spec, base, method, None).iteration == 0


# ----------------------------------------------------------------- one run per folder


def test_a_folder_is_held_by_one_run_at_a_time(tmp_path):
    out = str(tmp_path)
    with _results.run_lock(out, "tune") as path:
        assert os.path.exists(path)
        with pytest.raises(ConfigError, match=r"in use by another jaxsync tune \(process \d+"):
            with _results.run_lock(out, "sweep"):
                pass
    assert not os.path.exists(path)  # released
    # a lock left by a killed run on this host: named and taken over
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    with open(path, "w") as f:
        json.dump({"pid": gone.pid, "host": socket.gethostname(), "started": "then", "what": "tune"}, f)
    said = []
    with _results.run_lock(out, "tune", log=said.append):
        pass
    assert len(said) == 1 and f"process {gone.pid}" in said[0] and "killed" in said[0]


# ----------------------------------------------------------------- the command


@pytest.fixture
def stand_ins(monkeypatch):
    """The held-out rollouts and the loop replaced; ``calls["metrics"]`` sets
    what the held-out scoring sees (both scenarios held by default)."""
    calls = {
        "metrics": fake_heldout_metrics(),
        "evaluated": 0,
    }

    def evaluator(model, duration, controller="synchronous", **stack):
        def evaluate(g, s):
            calls["evaluated"] += 1
            return calls["metrics"]

        return evaluate

    def fake_tune(model, base, cfg, *, validate=None, out=None, **kw):
        calls["cfg"] = cfg
        calls["locked"] = os.path.exists(os.path.join(out, _results.LOCK))
        v0 = {"iteration": 0, **validate(base)} if validate else None
        row = {"iteration": 0, "cost": 2.0, "grad_norm": 1.0, "skipped": 0, "seconds": 0.1}
        return TuneResult(base, [row], [v0] if v0 else [], v0, base, None)

    monkeypatch.setattr(loss_mod, "make_evaluator", evaluator)
    monkeypatch.setattr(tune_mod, "tune", fake_tune)
    return calls


def _run_tune(model, out, gains=None, **settings):
    """``jaxsync tune``'s job (``pipeline.run_tune``) on the stand-ins: one
    iteration, no MuJoCo C check; returns the summary and the lines it logged."""
    said = []
    cfg = TuneConfig(**{"iterations": 1, **settings})
    summary = pipeline.run_tune(model, cfg, gains=gains, out=str(out), mujoco_check=False, log=said.append)
    return summary, "\n".join(said)


def test_tune_holds_its_folder_and_a_second_run_is_refused(model, tmp_path, stand_ins):
    out = tmp_path / "run"
    _run_tune(model, out)
    assert stand_ins["locked"] and not (out / _results.LOCK).exists()
    other = tmp_path / "busy"
    other.mkdir()
    (other / _results.LOCK).write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))
    stand_ins["evaluated"] = 0
    with pytest.raises(JaxsyncError, match="in use by another jaxsync"):
        _run_tune(model, other)
    assert stand_ins["evaluated"] == 0  # refused before any rollout
    assert sorted(p.name for p in other.iterdir()) == [_results.LOCK]  # the other run's lock left alone


def test_a_sweep_into_a_folder_in_use_is_refused(tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / _results.LOCK).write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))
    assert main(["sweep", "--param", "k_rk=0:0.5:2", "--out", str(out), "--no-progress"]) == 2
    assert "in use by another jaxsync" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [_results.LOCK]


def test_a_start_that_drops_the_object_everywhere_stops_before_tuning(model, tmp_path, stand_ins):
    stand_ins["metrics"] = stand_ins["metrics"]._replace(dropped=np.ones(2, bool))
    out = tmp_path / "run"
    with pytest.raises(DroppedObjectError, match="drop the object .* held-out scenarios") as err:
        _run_tune(model, out)
    assert err.value.inputs == ("gains",)  # the command line names --gains
    assert "cfg" not in stand_ins  # the budget is not spent
    assert list(out.iterdir()) == []  # nothing of value written, nothing to block the next run


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"method": "polyak_sgd"}, "steps from (updates, state, params) alone"),
        ({"method": "tree_utils"}, "'tree_utils'"),
        ({"truncate_every": -5}, "truncate_every must be a positive number of steps"),
    ],
)
def test_options_are_checked_before_any_work(model, tmp_path, stand_ins, settings, message):
    out = tmp_path / "run"
    with pytest.raises(ConfigError) as err:
        _run_tune(model, out, **settings)
    assert message in str(err.value) and len(str(err.value).splitlines()) == 1
    assert stand_ins["evaluated"] == 0 and not out.exists()


def test_a_run_that_fails_leaves_no_results_that_block_the_corrected_command(model, tmp_path, stand_ins, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("a bug")

    monkeypatch.setattr(tune_mod, "tune", broken)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="a bug"):
        _run_tune(model, out)
    assert list(out.iterdir()) == []  # heldout_before.json was of no value without a run behind it


def test_the_start_moved_into_the_bands_is_said(model, tmp_path, stand_ins):
    gains = tmp_path / "g.json"
    g = {k: np.asarray(v).tolist() for k, v in default_gains()._asdict().items()}
    gains.write_text(json.dumps({**g, "k_rk": 1.0}))
    out = tmp_path / "run"
    summary, said = _run_tune(model, out, gains=str(gains))
    assert "moved into the tuning bands: k_rk: 1 -> 0.999" in said
    assert json.loads((out / "summary.json").read_text())["start_moved_into_bands"] == ["k_rk: 1 -> 0.999"]


def test_a_zero_stiffness_start_is_refused_when_tuned_in_log_space():
    g = default_gains()
    with pytest.raises(ConfigError, match="imp_stiffness > 0"):
        TuneSpec().init(g._replace(imp_stiffness=g.imp_stiffness * 0))
    TuneSpec(tuned=("k_rk", "k_lk")).init(g._replace(imp_stiffness=g.imp_stiffness * 0))  # not tuned: fine


def test_a_grid_count_with_samples_gives_the_values_drawn_from():
    """``lo:hi:n`` with --samples: the n grid values, drawn from as a list is
    (the count is not ignored); ``lo:hi``: the interval."""
    p = parse_param("k_rl=0.2:0.8:3", random=True)
    assert p.values == (0.2, 0.5, 0.8) and p.interval is None
    assert parse_param("k_rl=0.2:0.8", random=True).interval == (0.2, 0.8)
    points = sweep.make_plan(["k_rl=0.2:0.8:3"], samples=40, seed=1).points[:, 0]
    assert set(np.round(points, 12)) == {0.2, 0.5, 0.8}


def test_an_unchanged_score_says_unchanged():
    assert change_text(0.01, 0.01) == " (unchanged)"
    assert change_text(0.010001, 0.01) == " (unchanged)"
    assert change_text(0.0102, 0.01) == " (1.02x lower)"


def test_kept_gains_worse_than_the_start_are_said(model, tmp_path, stand_ins, monkeypatch):
    """validate_every 0 keeps the last iterate, whatever it scores: the
    summary and its lines say when it is worse than the start."""
    stand_in = tune_mod.tune

    def worse_after(*a, **k):
        result = stand_in(*a, **k)
        m = stand_ins["metrics"]
        stand_ins["metrics"] = m._replace(settled_peak_resultant_N=5.5 * m.settled_peak_resultant_N)
        return result

    monkeypatch.setattr(tune_mod, "tune", worse_after)
    out = tmp_path / "run"
    summary, _ = _run_tune(model, out, validate_every=0)
    said = "\n".join(summary_lines(summary, str(out)))
    assert "WARNING: the kept gains (the last iterate: validate_every 0 selects none) score worse" in said
    assert "settled peak resultant 0.01500 -> 0.08250 N (5.50x)" in said
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kept_worse_than_start"] == ["settled peak resultant 0.01500 -> 0.08250 N (5.50x)"]


def test_kept_gains_no_worse_than_the_start_say_nothing(model, tmp_path, stand_ins):
    out = tmp_path / "run"
    summary, _ = _run_tune(model, out, validate_every=0)
    assert not any("WARNING" in line for line in summary_lines(summary, str(out)))
    assert json.loads((out / "summary.json").read_text())["kept_worse_than_start"] == []
