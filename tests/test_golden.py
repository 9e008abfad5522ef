"""jaxsync export --format golden: a rollout's control periods on
position-controlled arms as files a port's unit test replays; jaxsync's own
step replays them exactly, and the replay sees a changed input."""

from __future__ import annotations

import os

import numpy as np
import pytest

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import schedule as _schedule
from jaxsync.io import golden
from jaxsync.sim.actuation import Stack

STEPS = 300  # the pads touch the ball at about row 250 of the comparison scenario


@pytest.fixture(scope="module")
def recorded(model, tmp_path_factory):
    out = {}
    for controller in ("synchronous", "ros2_admittance"):
        folder = str(tmp_path_factory.mktemp(controller))
        # the command's feed-forward on: `sent` differs from `command` while the plan moves
        g = jaxsync.default_gains(model, "position")._replace(ff_vel=np.float64(0.004), ff_acc=np.float64(0.0013))
        golden.export_golden(
            model, g, folder, controller=controller, steps=STEPS, stack=Stack("position", delay=(1, 1))
        )
        out[controller] = folder
    return out


@pytest.mark.parametrize("controller", ["synchronous", "ros2_admittance"])
def test_the_files_replay_exactly_and_name_every_column(recorded, controller):
    folder = recorded[controller]
    inputs, outputs, meta = golden.read(folder)
    assert meta["steps"] == STEPS and len(inputs["t"]) == len(outputs["t"]) == STEPS
    assert meta["controller"] == controller and meta["stack"]["delay"] == [1, 1] and meta["dt_s"] == 0.002
    assert list(inputs) == meta["columns"]["inputs"] and list(outputs) == meta["columns"]["outputs"]
    assert len(meta["joints"]["right"]) == 7 and meta["jaxsync_gains"]["gains"]["imp_mass"]["unit"]
    force = np.linalg.norm([inputs[f"right.wrench[{i}]"] for i in range(3)], axis=0)
    assert force[:200].max() < 1.0 < force.max()  # free motion, then contact: both are in the files
    assert golden.replay(folder) <= 1e-12
    # each row carries the state before and after: row k's state out is row k + 1's state in
    state = [c for c in outputs if c.startswith("state.")]
    assert state and all(np.array_equal(outputs[c][:-1], inputs["state_in." + c[6:]][1:]) for c in state)
    assert np.array_equal(outputs["command[0]"][:-1], inputs["command_in[0]"][1:])
    lead = np.abs(np.asarray(outputs["sent[0]"]) - np.asarray(outputs["command[0]"])).max()
    assert lead > 1e-6 if controller == "synchronous" else lead == 0.0  # the rule has no feed-forward


def test_the_replay_sees_a_changed_input(recorded, tmp_path):
    """The pad wrench of a contact row, changed in the file, changes the step's
    output: the replay reads what the files hold."""
    folder = recorded["synchronous"]
    for name in golden.FILES:
        (tmp_path / name).write_bytes(open(os.path.join(folder, name), "rb").read())
    lines = (tmp_path / "inputs.csv").read_text().splitlines()
    col = lines[0].split(",").index("right.wrench[2]")
    row = lines[STEPS].split(",")  # the last row: in contact
    row[col] = repr(float(row[col]) + 1.0)
    lines[STEPS] = ",".join(row)
    (tmp_path / "inputs.csv").write_text("\n".join(lines) + "\n")
    assert golden.replay(str(tmp_path)) > 1e-9
    (tmp_path / "outputs.csv").write_text("t,command[0]\n0.0\n")  # a row cut short
    with pytest.raises(ConfigError, match="outputs.csv: not a golden table"):
        golden.read(str(tmp_path))


def test_bad_requests_are_refused_before_anything_is_written(model, tmp_path, capsys):
    g = jaxsync.default_gains(model, "position")
    with pytest.raises(ConfigError, match="position-controlled arms") as err:
        golden.export_golden(model, g, str(tmp_path / "a"), stack=Stack("torque"))
    assert err.value.inputs == ("actuation",)
    with pytest.raises(ConfigError, match=r"steps must be a whole number in 1\.\.100000"):
        golden.export_golden(model, g, str(tmp_path / "a"), steps=0, stack=Stack("position"))
    with pytest.raises(ConfigError, match="constant gains"):
        golden.export_golden(model, _schedule.constant(g), str(tmp_path / "a"), stack=Stack("position"))
    for argv, message in [
        (["--actuation", "torque"], "need position-controlled arms"),
        (["--delay", "0:3"], "one scenario runs one delay"),
    ]:
        assert main(["export", "--format", "golden", "--out", str(tmp_path / "a"), *argv]) == 2
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", "--format", "golden", "--controller", "bang_bang", "--out", str(tmp_path / "a")])
    assert "invalid choice: 'bang_bang'" in capsys.readouterr().err
    assert main(["export", "--format", "yaml", "--steps", "5", "--out", str(tmp_path / "y")]) == 2
    assert "--steps: not for --format yaml" in capsys.readouterr().err
    assert main(["export", "--format", "ros2-admittance", "--delay", "2", "--out", str(tmp_path / "y")]) == 2
    assert "--delay: not for --format ros2-admittance" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "y").exists()
    assert main(["export", "--format", "golden", "--steps", "3", "--out", str(tmp_path / "g")]) == 0
    said = capsys.readouterr().out
    assert "wrote synchronous's golden files (0 periods of delay)" in said and "gives the recorded outputs" in said


def test_the_documents_equations_give_the_recorded_rows(recorded, tmp_path):
    """tests/golden_numpy.py, written from docs/deploy.md's update and docs/golden.md's layout alone (NumPy,
    no jaxsync import), recomputes every row's outputs from its inputs: the documents say what the files
    hold. A wrong number in golden.json (its alpha) is seen."""
    import json  # noqa: PLC0415 -- this test alone edits golden.json

    import golden_numpy  # noqa: PLC0415 -- the tests' own reimplementation

    folder = recorded["synchronous"]
    inputs, outputs, meta = golden_numpy.read(folder)
    assert set(meta["state_fields"]) == {"impedance.offset", "impedance.rate", "wrench_filter"}
    worst = 0.0
    for k in range(len(inputs["t"])):
        row = golden_numpy.step(inputs, k, meta)
        assert set(row) == {c for c in outputs if c != "t"}
        worst = max(worst, max(abs(v - outputs[c][k]) for c, v in row.items()))
    assert worst <= 1e-9, worst
    meta["alpha"] *= 2.0
    for name in ("inputs.csv", "outputs.csv"):
        (tmp_path / name).write_bytes(open(os.path.join(folder, name), "rb").read())
    (tmp_path / "golden.json").write_text(json.dumps(meta))
    inputs, outputs, meta = golden_numpy.read(str(tmp_path))
    k = len(inputs["t"]) - 1
    assert max(abs(v - outputs[c][k]) for c, v in golden_numpy.step(inputs, k, meta).items()) > 1e-9
