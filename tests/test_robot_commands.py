"""Every command that takes ``--robot`` runs that robot's own defaults: its raised
gains and its object, never the paper model's, and records them in what it writes.

The test robot is the UR5e-like pair holding a smaller, heavier ball than the
paper's (0.8 kg, 0.08 m against 0.5 kg, 0.1 m); its default gains are raised
above the paper's (the normal-axis mass its pads need at the grasp).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import yaml
from conftest import fake_study_parts

import jaxsync
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.io import gains_file
from jaxsync.runtime.gl import RenderUnavailableError, select_gl_backend

ROBOTS = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots")
MASS, RADIUS = 0.8, 0.08


@pytest.fixture(scope="module")
def robot_file(tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp("robot")
    doc = yaml.safe_load(open(os.path.join(ROBOTS, "ur5e_twice.yaml")))
    doc["object"]["mass"], doc["object"]["radius"] = MASS, RADIUS
    for arm in doc["arms"].values():
        arm["model"] = os.path.join(ROBOTS, arm["model"])
    path = folder / "small_ball.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


@pytest.fixture(scope="module")
def robot(robot_file):
    return jaxsync.load_model(robot_file, visual=False)


def _same_gains(recorded: dict, model) -> bool:
    return gains_file.same_gains(_gains.from_dict(recorded), _gains.default_gains(model))


def _object_of(scenario: dict) -> tuple[float, float]:
    return float(np.asarray(scenario["object_mass"])), float(np.asarray(scenario["object_radius"]))


def test_the_robot_record_gives_the_robots_defaults(robot):
    """One typed record, one place for the defaults: the robot's object in both
    tasks, its raised gains, and which robot it is."""
    assert isinstance(robot.robot, jaxsync.RobotScene)
    assert (robot.robot.object_mass, robot.robot.object_radius) == (MASS, RADIUS)
    for s in (jaxsync.default_scenario(robot), jaxsync.short_task(robot)):
        assert float(s.object_mass) == MASS and float(s.object_radius) == RADIUS and float(s.mass_estimate) == MASS
    assert float(jaxsync.default_scenario(robot, object_mass=1.0).mass_estimate) == 1.0  # an override wins
    paper = jaxsync.default_gains()
    raised = jaxsync.default_gains(robot)
    assert np.all(np.asarray(raised.imp_mass)[:, 2] > np.asarray(paper.imp_mass)[:, 2])
    assert float(jaxsync.default_scenario().object_mass) == 0.5  # the paper model's task unchanged
    assert robot.fingerprint == robot.robot.fingerprint and len(robot.fingerprint) == 64
    assert jaxsync.load_model().fingerprint != robot.fingerprint


def test_gains_tuned_on_another_robot_are_refused_by_name(robot, robot_file, tmp_path, capsys):
    """A gains file records its model; export and compare refuse it on another
    one, naming both, unless --any-model says to go ahead."""
    doc = {"gains": _gains.to_dict(jaxsync.default_gains(robot)), "model": jaxsync.identity(robot)}
    path = tmp_path / "gains.json"
    path.write_text(json.dumps(doc))
    rc = main(["export", str(path), "--format", "ros2-admittance", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and "small_ball" in err and "dual_arm" in err and "--any-model" in err
    assert not (tmp_path / "x").exists()
    rc = main(["compare", "--gains", str(path), "--out", str(tmp_path / "c")])
    assert rc == 2 and "small_ball" in capsys.readouterr().err and not (tmp_path / "c").exists()
    out = tmp_path / "y"
    assert main(["export", str(path), "--format", "yaml", "--robot", robot_file, "--no-visual", "--out", str(out)]) == 0
    out2 = tmp_path / "z"
    argv = ["export", str(path), "--format", "yaml", "--model", jaxsync.default_model_path(), "--any-model"]
    assert main([*argv, "--out", str(out2)]) == 0


@pytest.mark.slow
def test_every_robot_command_runs_the_robots_gains_and_object(robot, robot_file, tmp_path):
    """compare, tune, sweep, sensitivity, study, export, bench and render on the
    robot, each as small as it goes: what each wrote says it ran the robot's
    default gains and its object (the study: what it handed its tuning runs
    and scored, its runs being tune's own pipeline)."""
    r = ["--robot", robot_file, "--no-visual"]
    ident = jaxsync.identity(robot)

    out = tmp_path / "compare"
    assert main(["compare", *r, "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert _same_gains(s["gains"], robot) and _object_of(s["scenario"]) == (MASS, RADIUS)
    assert s["model"] == ident

    out = tmp_path / "tune"
    # CMA-ES: forward rollouts only, no gradient to compile (what ran is the point here, not the method)
    small = ["--task", "short", "--iterations", "1", "--batch", "1", "--heldout-batch", "1", "--validation-batch", "1"]
    small += ["--method", "cmaes", "--popsize", "2"]
    assert main(["tune", *r, *small, "--validate-every", "0", "--no-mujoco-check", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert _same_gains(s["gains_start"], robot) and _object_of(s["scenario_base"]) == (MASS, RADIUS)
    assert s["model"] == ident and json.loads((out / "gains.json").read_text())["model"] == ident

    out = tmp_path / "sweep"
    assert main(["sweep", *r, "--param", "k_rk=0.5", "--duration", "3.5", "--out", str(out)]) == 0
    plan = json.loads((out / "plan.json").read_text())["spec"]
    assert _same_gains(plan["base_gains"], robot) and _object_of(plan["base_scenario"]) == (MASS, RADIUS)
    assert plan["model_identity"] == ident

    out = tmp_path / "sensitivity"
    assert main(["sensitivity", *r, "--task", "short", "--batch", "1", "--out", str(out)]) == 0
    s = json.loads((out / "sensitivity.json").read_text())
    assert _same_gains(s["gains"], robot) and _object_of(s["scenario_base"]) == (MASS, RADIUS)
    assert s["model"] == ident

    # the study's tuning runs are the pipeline tune ran above (what it records is checked
    # there); here, what the study hands it and scores: stand-ins record both
    with pytest.MonkeyPatch.context() as mp:
        _, seen = fake_study_parts(mp)
        argv = ["study", *r, "--controllers", "classical,synchronous", "--bounds", "1", "--seeds", "0"]
        assert main([*argv, "--out", str(tmp_path / "study")]) == 0
    assert [c for c, _, _ in seen["tuned"]] == ["classical", "synchronous"]
    for controller, base, scenario in seen["tuned"]:
        assert gains_file.same_gains(base, _gains.default_gains(robot, "torque", controller))
        assert (scenario["object_mass"], scenario["object_radius"]) == (MASS, RADIUS)
    assert {c for c, _, _ in seen["evaluated"]} == {"classical", "synchronous"}
    for controller, g, scenarios in seen["evaluated"]:
        assert gains_file.same_gains(g, _gains.default_gains(robot, "torque", controller))
        # the object's mass drawn about the robot's, which the controller assumes
        assert np.all(np.asarray(scenarios.mass_estimate) == MASS)
        assert np.all(np.asarray(scenarios.object_radius) == RADIUS)

    out = tmp_path / "export"
    assert main(["export", "--format", "yaml", *r, "--out", str(out)]) == 0
    assert gains_file.same_gains(gains_file.load(str(out / "gains.yaml")), jaxsync.default_gains(robot))

    # bench: its measurements compile for minutes in child processes; what it records of the
    # model it loaded is checked with stand-in measurements (tests/test_bench.py)

    try:
        select_gl_backend()
    except RenderUnavailableError:
        return  # no OpenGL here: the other commands are checked
    out = tmp_path / "render"
    assert main(["render", *r, "--width", "64", "--height", "48", "--out", str(out)]) == 0
    s = json.loads((out / "render.json").read_text())
    assert s["model"] == ident and (s["object"]["mass_kg"], s["object"]["radius_m"]) == pytest.approx((MASS, RADIUS))


def test_a_study_of_an_edited_robot_file_is_not_resumed(robot_file, tmp_path, capsys):
    """A study folder records its robot by fingerprint: after the robot file is
    edited in place (an arm base moved), --resume refuses by name before anything runs."""
    from jaxsync.optimize.studies import study as _study

    path, out = tmp_path / "robot.yaml", tmp_path / "study"
    doc = yaml.safe_load(open(robot_file))
    path.write_text(yaml.safe_dump(doc))
    before = jaxsync.load_model(str(path), visual=False)
    out.mkdir()
    _study._prepare(str(out), _study.StudyConfig(), _study.model_label(before), False, False)
    doc["arms"]["right"]["base"]["pos"] = [0, -0.42, 0]
    path.write_text(yaml.safe_dump(doc))
    after = jaxsync.load_model(str(path), visual=False)
    assert before.fingerprint != after.fingerprint
    rc = main(["study", "--robot", str(path), "--no-visual", "--resume", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and before.fingerprint[:12] in err and after.fingerprint[:12] in err
    assert sorted(p.name for p in out.iterdir()) == ["study.json"]
