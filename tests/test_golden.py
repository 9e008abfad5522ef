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
from jaxsync.control import coupling as _coupling
from jaxsync.control import schedule as _schedule
from jaxsync.io import golden
from jaxsync.sim.actuation import Stack

STEPS = 300  # the pads touch the ball at about row 250 of the comparison scenario
CONTROLLERS = ("synchronous", "ros2_admittance", "ros2_coupled", "ros2_coupled_direct")


def _coupled(g):
    """``g`` with the coupling family's every part on: a gain of 0.05-0.3 either sign on every channel, arm
    and axis, filters 0.3-0.8, and each channel's off-diagonal 6x6 blocks within +-0.05; the left arm's
    stiffness 20 % higher, so that the force channel's scale shows whose it is."""
    rng = np.random.default_rng(7)
    shape = (2, 6)
    gains = {f: rng.choice([-1.0, 1.0], shape) * rng.uniform(0.05, 0.3, shape) for f in _coupling.GAIN_FIELDS}
    filters = {f: rng.uniform(0.3, 0.8, shape) for f in _coupling.FILTER_FIELDS}
    block = rng.uniform(-0.05, 0.05, (len(_coupling.CHANNELS), 2, 6, 6)) * (1.0 - np.eye(6))
    left = np.array([[1.0], [1.2]])
    return g._replace(
        **gains,
        **filters,
        **{_coupling.BLOCK_FIELD: block},
        imp_stiffness=np.asarray(g.imp_stiffness) * left,
    )


@pytest.fixture(scope="module")
def recorded(model, tmp_path_factory):
    out = {}
    for controller in CONTROLLERS:
        folder = str(tmp_path_factory.mktemp(controller))
        # the command's feed-forward on: `sent` differs from `command` while the plan moves
        g = jaxsync.default_gains(model, "position")._replace(ff_vel=np.float64(0.004), ff_acc=np.float64(0.0013))
        if controller.startswith("ros2_coupled"):
            g = _coupled(g)
        golden.export_golden(
            model, g, folder, controller=controller, steps=STEPS, stack=Stack("position", delay=(1, 1))
        )
        out[controller] = folder
    return out


@pytest.mark.parametrize("controller", CONTROLLERS)
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
    assert set(meta["output_fields"]) == {c.split("[")[0] for c in outputs if c != "t" and not c.startswith("state.")}


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


def test_the_replay_checks_the_coupling_offset(recorded, tmp_path):
    """A coupling offset changed in ros2_coupled's outputs is seen by the replay."""
    folder = recorded["ros2_coupled"]
    for name in golden.FILES:
        (tmp_path / name).write_bytes(open(os.path.join(folder, name), "rb").read())
    lines = (tmp_path / "outputs.csv").read_text().splitlines()
    col = lines[0].split(",").index("coupling_offset[1][2]")
    row = lines[STEPS].split(",")
    row[col] = repr(float(row[col]) + 1e-6)
    lines[STEPS] = ",".join(row)
    (tmp_path / "outputs.csv").write_text("\n".join(lines) + "\n")
    assert 1e-7 < golden.replay(str(tmp_path)) < 1e-5


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
    assert main(["export", "--format", "ros2-admittance", "--steps", "2", "--out", str(tmp_path / "y")]) == 2
    assert "--steps: not for --format ros2-admittance" in capsys.readouterr().err
    assert main(["export", "--format", "yaml", "--delay", "2", "--out", str(tmp_path / "y")]) == 2
    assert "--delay: not for --format yaml" in capsys.readouterr().err
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


@pytest.mark.parametrize("controller", ["ros2_coupled", "ros2_coupled_direct"])
def test_the_coupling_documents_equations_give_the_recorded_rows(recorded, controller):
    """tests/golden_numpy_coupling.py, written from docs/coupling.md's "One period, in order" alone (NumPy,
    no jaxsync import), recomputes every row's coupling filters, offset and rate, reference joints and the
    joints the rule runs on (its command less its new offset) from the row's inputs, with every part of the
    family on, in either placement."""
    import golden_numpy  # noqa: PLC0415 -- the tests' own reimplementation
    import golden_numpy_coupling  # noqa: PLC0415 -- the same, of the coupling

    inputs, outputs, meta = golden_numpy.read(recorded[controller])
    n = len(meta["joints"]["right"])
    assert {"coupling.value", "coupling.rate"} <= set(meta["state_fields"])
    assert {"coupling_offset", "coupling_offset_rate"} <= set(meta["output_fields"])
    worst = 0.0
    for k in range(len(inputs["t"])):
        row, q_rule = golden_numpy_coupling.step(inputs, k, meta)
        assert set(row) == {c for c in outputs if c.startswith(("state.coupling", "coupling_", "state.ros2.q_ref"))}
        command = np.array([outputs[f"command[{j}]"][k] for j in range(2 * n)]).reshape(2, n)
        rule = np.array([[outputs[f"state.ros2.rule.joint_pos[{i}][{j}]"][k] for j in range(n)] for i in range(2)])
        worst = max(worst, *(abs(v - outputs[c][k]) for c, v in row.items()), np.abs(command - rule - q_rule).max())
    print(f"{controller}: NumPy from docs/coupling.md against the files, largest difference {worst:.3g}")
    assert worst <= 1e-12, worst
    # every channel's filter moved, the own and other channels' rates too, and the offset entered
    for c in range(4):
        assert max(np.abs(outputs[f"state.coupling.value[{c}][0][{a}]"]).max() for a in range(6)) > 1e-6
    for c in (1, 2):
        assert max(np.abs(outputs[f"state.coupling.rate[{c}][1][{a}]"]).max() for a in range(6)) > 1e-6
    assert max(np.abs(outputs[f"coupling_offset[0][{a}]"]).max() for a in range(6)) > 1e-5
