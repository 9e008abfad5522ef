"""The fair study: its statistics, its resumable runs, its command line."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from conftest import fake_study_parts

from jaxsync._errors import ConfigError
from jaxsync.cli import build_parser, main
from jaxsync.optimize.studies import study as study_mod
from jaxsync.optimize.studies import study_report as report_mod
from jaxsync.optimize.tuning import pipeline as pipeline_mod
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.sim.actuation import Stack
from jaxsync.sim.metrics import Metrics


def test_ratio_interval_finds_a_known_ratio_and_covers_it():
    rng = np.random.default_rng(0)
    den = rng.lognormal(np.log(0.01), 0.3, size=(3, 32))
    num = 2.0 * den * rng.lognormal(0.0, 0.05, size=den.shape)
    r = report_mod.ratio_interval(num, den, 500)
    assert r["ratio"] == pytest.approx(2.0, rel=0.05)
    lo, hi = r["ci95"]
    assert lo < 2.0 < hi and hi - lo < 0.6
    # a dropped scenario (NaN) is left out, not counted as zero
    num[0, 0] = np.nan
    assert report_mod.ratio_interval(num, den, 200)["ratio"] == pytest.approx(r["ratio"], rel=0.05)
    # nothing held: no ratio
    assert report_mod.ratio_interval(np.full((1, 4), np.nan), den[:1, :4], 100)["ratio"] is None


def _evaluation(peaks, dropped=None, impact=6.0, stiffness=2e4):
    n = len(peaks)
    dropped = np.zeros(n, bool) if dropped is None else np.asarray(dropped)
    metrics = {f: [0.01] * n for f in Metrics._fields}
    metrics.update(
        settled_peak_resultant_N=list(peaks),
        dropped=dropped.tolist(),
        nonfinite=[False] * n,
        chattering=[False] * n,
        first_impact_peak_N=[impact] * n,
        drop_time_s=[None] * n,
    )
    return {
        "metrics": metrics,
        "settled_peak_resultant_N": float(np.mean(np.asarray(peaks)[~dropped])) if (~dropped).any() else None,
        "apparent_stiffness_normal_N_per_m": stiffness,
        "apparent_stiffness_tangential_N_per_m": 2e3,
    }


def test_summarise_pools_seeds_and_leaves_dropped_scenarios_out():
    a = _evaluation([0.01, 0.02, 1.0], dropped=[False, False, True])
    b = _evaluation([0.03, 0.04, 0.05])
    row = report_mod.summarise([a, b], [True, False])
    assert row["dropped"] == 1 and row["scenarios"] == 6
    assert row["settled_peak_resultant_N"]["n"] == 5
    assert row["settled_peak_resultant_N"]["median"] == pytest.approx(0.03)
    assert row["within_bounds"] == 1 and row["runs"] == 2
    assert row["first_impact_peak_N"]["n"] == 6  # the first impact happened before the drop


@pytest.fixture
def fake_study(monkeypatch):
    """The tuning runs and the held-out rollouts replaced by stand-ins (conftest.fake_study_parts)."""
    return fake_study_parts(monkeypatch)


def test_an_interrupted_study_resumes_where_it_stopped(model, tmp_path, fake_study):
    calls, interrupt = fake_study
    cfg = study_mod.StudyConfig(
        controllers=("classical", "synchronous"), bounds=(0.7, 1.5), seeds=(0, 1), heldout_batch=4, bootstrap=200
    )
    out = str(tmp_path / "study")
    interrupt["at"] = 3
    with pytest.raises(KeyboardInterrupt):
        study_mod.run_study(model, cfg, out, log=lambda m: None)
    assert len(calls) == 3  # two runs done, the third lost
    partial = study_mod.run_study(model, cfg, out, report_only=True, log=lambda m: None)
    assert partial["runs_done"] == 2 and partial["runs"] == 8 and partial["bounds_reported"] == []
    assert {r["bound"] for r in partial["rows"]} == {None} and len(calls) == 3  # the defaults only; nothing tuned
    with pytest.raises(Exception, match="resume to continue it"):
        study_mod.run_study(model, cfg, out, log=lambda m: None)
    other = study_mod.StudyConfig(**{**cfg.__dict__, "batch": 3})
    with pytest.raises(Exception, match="batch differ"):
        study_mod.run_study(model, other, out, resume=True, log=lambda m: None)
    interrupt.clear()
    report = study_mod.run_study(model, cfg, out, resume=True, log=lambda m: None)
    assert len(calls) == 3 + 6  # the lost run again, and the five not started
    assert report["bounds_reported"] == [0.7, 1.5] and report["runs_done"] == 8
    jobs = [(c, b, s) for c, b, s, _ in calls]
    assert jobs[3] == jobs[2]  # the lost run, run again first
    assert len(set(jobs[3:])) == 6 and set(jobs) == set(jobs[3:]) | set(jobs[:2])
    # the bounds are factors of the default classical controller's first impact (6 N here)
    assert {round(c[1], 6) for c in calls} == {round(0.7 * 6.0, 6), round(1.5 * 6.0, 6)}
    for f in report_mod.FILES:
        assert (tmp_path / "study" / f).stat().st_size > 0
    rows = {(r["controller"], r["bound"]): r for r in report["rows"]}
    assert set(rows) == {(c, b) for c in cfg.controllers for b in (None, 0.7, 1.5)}
    np.testing.assert_allclose(rows[("synchronous", None)]["settled_peak_resultant_N"]["median"], 0.25 * 0.065)
    np.testing.assert_allclose(rows[("synchronous", 0.7)]["settled_peak_resultant_N"]["median"], 0.125 * 0.065)
    (ratio,) = [q for q in report["ratios"] if q["bound"] == 0.7]
    assert ratio["controller"] == "classical" and ratio["over"] == "synchronous"
    assert ratio["ratio"] == pytest.approx(4.0)
    lines = report_mod.table(report)
    assert any("classical / synchronous (bound x0.7): 4" in line for line in lines)


def _position_study(controllers, **kw):
    """A one-bound, one-seed study of ``controllers`` on position-controlled arms, delays 0-3."""
    return study_mod.StudyConfig(
        controllers=controllers,
        bounds=(1.0,),
        seeds=(0,),
        heldout_batch=4,
        bootstrap=100,
        actuation="position",
        delay=(0, 3),
        **kw,
    )


def test_a_position_stack_study_scores_and_tunes_on_its_stack(model, tmp_path, fake_study):
    """StudyConfig(actuation="position", delay, servo_spread): the defaults,
    the compliance reference and every tuning run are on that stack."""
    calls, seen = fake_study
    cfg = _position_study(("classical", "synchronous"), servo_spread=0.3, distro="humble")
    study_mod.run_study(model, cfg, str(tmp_path / "study"), log=lambda m: None)
    assert len(seen["stacks"]) == 3 and all(
        s == {"actuation": "position", "control_substeps": 1, "distro": "humble"} for s in seen["stacks"]
    )  # the defaults of both controllers, the reference
    assert seen["tune_stacks"] == [(Stack("position", None, (0, 3), "humble"), 0.3)] * 2 and len(calls) == 2
    with pytest.raises(ConfigError, match="servo_spread applies to position-controlled arms"):
        study_mod.StudyConfig(servo_spread=0.3).validate()
    # the deployed rule takes part on position-controlled arms, and is refused on the torque stack
    cfg.replace(controllers=("synchronous", "ros2_admittance")).validate()
    with pytest.raises(ConfigError, match="ros2_admittance.*position-controlled arms only"):
        study_mod.StudyConfig(controllers=("synchronous", "ros2_admittance")).validate()


def test_each_controller_of_a_study_starts_from_its_own_defaults(model, tmp_path, fake_study):
    """ros2_synchronous's defaults carry its own relative-error factor (0.25,
    jaxsync.control.gains.RULE_RELATIVE_FACTOR), the synchronous law's 0.5:
    the study scores and tunes each from its own."""
    _, seen = fake_study
    cfg = _position_study(("synchronous", "ros2_synchronous"))
    study_mod.run_study(model, cfg, str(tmp_path / "study"), log=lambda m: None)
    own = {"synchronous": 0.5, "ros2_synchronous": 0.25}
    assert seen["tuned_from_k_rk"] == own
    assert seen["evaluated_k_rk"] == {"classical": 0.5, **own}  # the defaults scored, the reference's too


def test_a_resumed_study_adds_bounds_seeds_and_controllers_and_tunes_only_those(model, tmp_path, fake_study):
    """--resume with more bounds, seeds or controllers than the study ran tunes
    the new runs only and reports them beside the old; one that leaves a saved
    entry out is another study, refused by name. A cost weight the saved
    study does not name counts at its default."""
    calls, _ = fake_study
    two = ("classical", "synchronous")
    cfg = study_mod.StudyConfig(controllers=two, bounds=(1.0,), seeds=(0,), heldout_batch=4, bootstrap=100)
    out = str(tmp_path / "study")
    study_mod.run_study(model, cfg, out, log=lambda m: None)
    assert [c[:3] for c in calls] == [("classical", 6.0, 0), ("synchronous", 6.0, 0)]
    saved = json.loads((tmp_path / "study" / "study.json").read_text())
    del saved["config"]["weights"]["friction_margin"]  # as a study saved before that weight existed
    (tmp_path / "study" / "study.json").write_text(json.dumps(saved))
    three = (*two, "task_space")
    more = study_mod.StudyConfig(**{**cfg.__dict__, "controllers": three, "bounds": (1.0, 1.5), "seeds": (0, 1)})
    report = study_mod.run_study(model, more, out, resume=True, log=lambda m: None)
    assert len(calls) == 12 and len({c[:3] for c in calls}) == 12  # the 10 new runs, the first two not again
    assert report["bounds_reported"] == [1.0, 1.5] and report["runs_done"] == 12
    assert {(r["controller"], r["bound"]) for r in report["rows"]} == {(c, b) for c in three for b in (None, 1.0, 1.5)}
    fewer = study_mod.StudyConfig(**{**more.__dict__, "bounds": (1.5,)})
    with pytest.raises(Exception, match="bounds differ"):
        study_mod.run_study(model, fewer, out, resume=True, log=lambda m: None)
    assert len(calls) == 12


def test_a_resumed_study_with_a_higher_cap_continues_the_unconverged_runs(model, tmp_path, fake_study):
    """Runs that stopped at their cap unconverged go on from their checkpoints when the study is resumed
    with more iterations (a setting a resumed study may change); converged runs are not tuned again, and
    the same cap continues nothing."""
    calls, seen = fake_study
    cfg = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0, 1),
                                heldout_batch=4, bootstrap=100, iterations=10)  # fmt: skip
    out = str(tmp_path / "study")
    seen["unconverged"] = True
    report = study_mod.run_study(model, cfg, out, log=lambda m: None)
    assert len(calls) == 4 and all(r["converged"] == 0 for r in report["rows"] if r["bound"] is not None)
    (q,) = [q for q in report["ratios"] if q["bound"] == 1.0]
    assert q["verdict"].startswith("none: runs not converged")
    study_mod.run_study(model, cfg, out, resume=True, log=lambda m: None)
    assert len(calls) == 4  # the same cap: nothing to continue
    seen["unconverged"] = False
    said = []
    report = study_mod.run_study(model, cfg.replace(iterations=30), out, resume=True, log=said.append)
    assert len(calls) == 8 and all(c[3] for c in calls[4:])  # each run resumed from its checkpoint
    assert sum("not converged in 10 iterations: continued" in m for m in said) == 4
    assert all(r["converged"] == 2 for r in report["rows"] if r["bound"] is not None)
    (q,) = [q for q in report["ratios"] if q["bound"] == 1.0]
    assert q["verdict"] in ("lower", "higher", "no difference")
    study_mod.run_study(model, cfg.replace(iterations=60), out, resume=True, log=lambda m: None)
    assert len(calls) == 8  # converged: a higher cap continues nothing


def test_study_cli_rejects_bad_input(tmp_path, capsys):
    out = tmp_path / "o"
    for args, msg in [
        (["--seeds", "1000"], "held-out"),
        (["--bounds", "0"], "positive factors"),
        (["--bounds", "1,1"], "twice"),
        (["--iterations", "0"], "must be positive"),
        (["--controllers", "classical"], "at least 2"),
        (["--controllers", "classical,nope"], "unknown controller"),
        (["--seeds", "a"], "argument --seeds: expected comma-separated numbers, got 'a'"),
        (["--seeds", ","], "argument --seeds: name at least one, got ','"),
        (["--grip-spread", "1.5"], "grip_spread must be a share in [0, 1), got 1.5 (--grip-spread)"),
        (["--delay", "0:3"], "delay applies to position-controlled arms"),
        (["--actuation", "position", "--control-rate", "300"], "divide the physics rate 500 Hz"),
    ]:
        try:
            rc = main(["study", "--out", str(out), *args])
        except (SystemExit, argparse.ArgumentError) as err:  # argparse's own
            rc = 2 if isinstance(err, argparse.ArgumentError) else err.code
            msg_text = str(err)
        else:
            msg_text = ""
        text = msg_text + capsys.readouterr().err
        assert rc == 2 and msg in text and "Traceback" not in text, (args, text[-400:])
        assert not out.exists(), args
    with pytest.raises(SystemExit):
        build_parser().parse_args(["study", "--help"])
    help_text = capsys.readouterr().out
    assert "95 % intervals" in " ".join(help_text.split()) and "%%" not in help_text
    p = build_parser().parse_args(["study"])
    assert p.controllers == ["classical", "synchronous", "object_impedance", "task_space"]
    assert p.bounds == (0.7, 1.0, 1.5) and p.seeds == (0, 1, 2) and p.heldout == 32 and p.grip_spread == 0.2


@pytest.mark.slow
def test_smoke_study_tunes_two_controllers(model, tmp_path):
    """The whole study, small: two controllers, one seed, one bound, two
    iterations on the short task, two held-out and two validation
    scenarios (one batch shape: one evaluation program per controller)."""
    cfg = study_mod.StudyConfig(
        controllers=("classical", "task_space"),
        bounds=(1.0,),
        seeds=(0,),
        iterations=2,
        batch=1,
        task="short",
        heldout_batch=2,
        validation_batch=2,
        validate_every=1,
        bootstrap=200,
    )
    report = study_mod.run_study(model, cfg, str(tmp_path / "s"), log=lambda m: None)
    rows = {(r["controller"], r["bound"]): r for r in report["rows"]}
    for c in cfg.controllers:
        for b in (None, 1.0):
            r = rows[(c, b)]
            assert r["dropped"] == 0 and r["scenarios"] == 2, (c, b)
            assert r["settled_peak_resultant_N"]["median"] > 1e-4, (c, b)
            assert r["first_impact_peak_N"]["median"] > 1.0, (c, b)
    assert rows[("classical", 1.0)]["runs"] == 1
    (q,) = [q for q in report["ratios"] if q["bound"] == 1.0]
    assert q["ratio"] is not None and q["ci95"][0] <= q["ratio"] <= q["ci95"][1]
    ref = json.loads((tmp_path / "s" / "reference.json").read_text())
    assert ref["controller"] == "classical" and ref["first_impact_peak_N"] > 1.0


def test_a_ratio_says_when_runs_ended_outside_the_bound():
    cfg = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0,), bootstrap=100)
    defaults = {"classical": _evaluation([0.06, 0.05, 0.07]), "synchronous": _evaluation([0.01, 0.012, 0.009])}
    inside = dict(_evaluation([0.03, 0.02, 0.04]), within_bounds=True)
    outside = dict(_evaluation([0.01, 0.012, 0.009]), within_bounds=False)
    runs = {("classical", 1.0, 0): {"heldout_after": inside}, ("synchronous", 1.0, 0): {"heldout_after": outside}}
    report = report_mod.build(
        cfg, {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 2e4}, defaults, runs
    )
    (q,) = [q for q in report["ratios"] if q["bound"] == 1.0]
    assert q["within_bounds"] == {"classical": [1, 1], "synchronous": [0, 1]}
    (line,) = [x for x in report_mod.table(report) if "(bound x1)" in x]
    assert "runs within the bound: classical 1/1, synchronous 0/1;" in line, line
    (line,) = [x for x in report_mod.table(report) if "(default gains)" in x]
    assert "within" not in line


def test_a_ctrl_c_lost_in_a_callback_stops_the_study_after_that_run(model, tmp_path, fake_study, capsys):
    """A Ctrl-C inside code that swallows exceptions still stops the study
    (exit 130) at the next safe point: the run it landed in is kept whole."""
    calls, interrupt = fake_study
    interrupt["ctrl_c_lost_at"] = 3
    out = str(tmp_path / "study")
    argv = ["study", "--controllers", "classical,synchronous", "--bounds", "0.7,1.5", "--seeds", "0,1"]
    argv += ["--heldout", "4", "--bootstrap", "200", "--out", out]
    assert main(argv) == 130
    assert "jaxsync study: interrupted" in capsys.readouterr().err
    assert len(calls) == 3
    cfg = study_mod.StudyConfig(
        controllers=("classical", "synchronous"), bounds=(0.7, 1.5), seeds=(0, 1), heldout_batch=4, bootstrap=200
    )
    assert study_mod.run_study(model, cfg, out, report_only=True, log=lambda m: None)["runs_done"] == 3


def test_the_table_shows_chattering_runs_beside_dropped_ones():
    cfg = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0,), bootstrap=100)
    chattering = _evaluation([0.01, 0.012, 0.009])
    chattering["metrics"]["chattering"] = [True, False, True]
    defaults = {"classical": _evaluation([0.06, 0.05, 0.07]), "synchronous": chattering}
    report = report_mod.build(cfg, {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 2e4}, defaults, {})
    lines = report_mod.table(report)
    head = lines[1].split()
    assert head[-6:] == ["dropped", "chattering", "in", "bounds", "converged", "exports"]
    (row,) = [x for x in lines if x.startswith("synchronous")]
    assert row.split()[-5:] == ["0/3", "2/3", "-", "-", "-"]


def _converged_run(peaks, converged):
    after = dict(_evaluation(peaks), within_bounds=True)
    return {"heldout_after": after, "convergence": {"converged": converged, "iterations": 40}}


@pytest.mark.parametrize(
    "classical_converged, verdict", [(True, "lower"), (False, "none: runs not converged (classical 0/2)")]
)
def test_a_verdict_is_drawn_from_converged_runs_only(classical_converged, verdict):
    """The classical runs score far below the synchronous ones: the ratio's
    interval excludes 1, and the verdict says so only when every run on both
    sides converged; a bound with an unconverged run gets no verdict and says
    which runs are short."""
    cfg = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0, 1), bootstrap=200)
    defaults = {"classical": _evaluation([0.06, 0.05, 0.07]), "synchronous": _evaluation([0.01, 0.012, 0.009])}
    runs = {("synchronous", 1.0, s): _converged_run([0.03, 0.031, 0.029], True) for s in (0, 1)}
    runs.update({("classical", 1.0, s): _converged_run([0.01, 0.011, 0.009], classical_converged) for s in (0, 1)})
    report = report_mod.build(
        cfg, {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 2e4}, defaults, runs
    )
    (q,) = [q for q in report["ratios"] if q["bound"] == 1.0]
    assert q["ci95"][1] < 1 and q["verdict"] == verdict
    rows = {(r["controller"], r["bound"]): r for r in report["rows"]}
    assert rows[("classical", 1.0)]["converged"] == (2 if classical_converged else 0)
    assert rows[("classical", 1.0)]["exports"] is None  # no run says (the torque stack)
    assert rows[("classical", 1.0)]["iterations"] == [40, 40]
    (line,) = [x for x in report_mod.table(report) if "(bound x1)" in x]
    assert line.endswith(f"verdict: {verdict}"), line


def test_a_row_counts_the_runs_whose_gains_export():
    """On the position stack each run's summary says whether jaxsync export writes its gains; a
    row counts them, and the table shows it beside convergence."""
    cfg = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0, 1), bootstrap=100)
    defaults = {"classical": _evaluation([0.06, 0.05, 0.07]), "synchronous": _evaluation([0.01, 0.012, 0.009])}
    runs = {}
    for c, exports in (("classical", (True, False)), ("synchronous", (True, True))):
        for s, ok in zip((0, 1), exports, strict=True):
            runs[(c, 1.0, s)] = _converged_run([0.01, 0.011, 0.009], True) | {"deployment": {"exports": ok}}
    report = report_mod.build(
        cfg, {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 2e4}, defaults, runs
    )
    rows = {(r["controller"], r["bound"]): r for r in report["rows"]}
    assert rows[("classical", 1.0)]["exports"] == 1 and rows[("synchronous", 1.0)]["exports"] == 2
    (line,) = [x for x in report_mod.table(report) if x.startswith("classical") and "x1" in x]
    assert line.split()[-2:] == ["2/2", "1/2"]


def test_the_reference_gains_count_as_within_their_own_bound():
    """The classical run at x1 that keeps its start: the start came back from
    the tuner's parametrisation with its stiffness moved by 4e-5 relative, and
    its held-out first-impact peak (another batch than the validation one
    that defines the bound) above the bound; it is counted within x1."""
    cfg = TuneConfig(controller="classical", max_impact_N=6.0, max_stiffness_N_per_m=20350.7)
    moved = {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 20351.6}
    assert pipeline_mod.bound_excess(moved, cfg) == pytest.approx(4.4e-5, rel=0.01)
    assert pipeline_mod.within_bounds(moved, cfg)
    assert not pipeline_mod.within_bounds({**moved, "apparent_stiffness_normal_N_per_m": 20380.0}, cfg)

    def run(excess, heldout_within):
        validation = [{"iteration": 0, "bound_excess": excess, "within_bounds": excess <= 0}]
        after = dict(_evaluation([0.03, 0.02, 0.04]), within_bounds=heldout_within)
        return {"heldout_after": after, "validation": validation, "selected_iteration": 0}

    study = study_mod.StudyConfig(controllers=("classical", "synchronous"), bounds=(1.0,), seeds=(0, 1), bootstrap=100)
    defaults = {"classical": _evaluation([0.06, 0.05, 0.07]), "synchronous": _evaluation([0.01, 0.012, 0.009])}
    runs = {("classical", 1.0, s): run(4.4e-5, heldout_within=False) for s in (0, 1)}
    runs.update({("synchronous", 1.0, s): run(0.01, heldout_within=True) for s in (0, 1)})
    report = report_mod.build(
        study, {"first_impact_peak_N": 6.0, "apparent_stiffness_normal_N_per_m": 2e4}, defaults, runs
    )
    rows = {(r["controller"], r["bound"]): r for r in report["rows"]}
    assert rows[("classical", 1.0)]["within_bounds"] == 2 and rows[("synchronous", 1.0)]["within_bounds"] == 0
    assert "validation scenarios" in report["bound_rule"] and "(1 + 0.001)" in report_mod.table(report)[0]


def test_the_plot_labels_a_controllers_coinciding_bounds_once():
    """A controller whose runs ended within the tighter bound sits at one point
    for both: one label, "x1, x1.5", not two drawn over each other."""

    def row(controller, bound, x, y):
        return {
            "controller": controller,
            "bound": bound,
            "settled_peak_resultant_N": {"median": y},
            "apparent_stiffness_normal_N_per_m": {"median": x},
        }

    rows = [
        row("rule", None, 2e4, 0.067),
        row("rule", 1.0, 1.51e4, 0.01373),
        row("rule", 1.5, 1.5101e4, 0.013731),
        row("synchronous", 1.0, 1.8e4, 0.041),
        row("synchronous", 1.5, 2.1e4, 0.022),
        row("classical", 1.0, 1.51e4, 0.01373),  # another controller at the same point keeps its own label
    ]
    labels = report_mod.bound_labels(rows, "apparent_stiffness_normal_N_per_m")
    assert [text for _, text in labels] == ["x1, x1.5", "x1", "x1.5", "x1"]
    assert labels[0][0] == (1.51e4, 0.01373)
