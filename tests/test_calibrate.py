"""jaxsync excite / calibrate: bags written and read, bad recordings refused, the servo and delay found."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from jaxsync._errors import ConfigError
from jaxsync.calibrate import efforts, excite, fit, replay, sensor, uncertainty
from jaxsync.calibrate.replay import Joints
from jaxsync.cli import main
from jaxsync.io import bags
from jaxsync.physics.compose import robot_delay
from jaxsync.physics.model import load_model
from jaxsync.physics.robot import load_robot
from jaxsync.physics.servo import servo_of
from jaxsync.sim.scenario import default_scenario

ROBOTS = Path(__file__).resolve().parents[1] / "mjcf" / "robots"
UR5E = str(ROBOTS / "ur5e_twice.yaml")
TRUE_DELAY = 2
WRENCH_TOPICS = ("/right_ft_sensor/wrench", "/left_ft_sensor/wrench")
FORCE_NOISE, TORQUE_NOISE = 0.08, 0.004  # N, N m: the recording's wrist sensors' white noise


@pytest.fixture(scope="module")
def ur5e():
    return load_model(UR5E, visual=False)


@pytest.fixture(scope="module")
def truth(ur5e):
    """A known servo (each joint's stiffness and damping off the robot file's by up to 25 %)."""
    nom = replay.Replay(ur5e).nominal()
    rng = np.random.default_rng(7)
    n = len(nom.stiffness)
    return nom.replace(stiffness=nom.stiffness * rng.uniform(0.75, 1.25, n),
                       damping=nom.damping * rng.uniform(0.75, 1.25, n))  # fmt: skip


@pytest.fixture(scope="module")
def recording(ur5e, truth):
    """6 s of the excitation played on MuJoCo C at another step and integrator than the fit's
    (0.25 ms, implicitfast; the fit replays at 0.5 ms, Euler), with sensor noise."""
    ex = excite.excitation(ur5e, duration=6.0, amplitude=0.02)
    t, q, dq = replay.record(ur5e, truth, ex.times, ex.commands, TRUE_DELAY, timestep=0.00025,
                             integrator="implicitfast", noise_q=1e-5, noise_dq=5e-4)  # fmt: skip
    return bags.Recording(ex.joints, t, q, dq, ex.times, ex.commands, wrenches=_wrenches(t, q, dq))


def _wrenches(t, q, dq, seed=3):
    """Each wrist sensor's reading while the arm moves free: a bias, a load that follows the arm's pose
    (its weight turning) and its speed (what settling leaves), and white noise of known size."""
    rng = np.random.default_rng(seed)
    n = q.shape[1] // 2
    out = []
    for arm in range(2):
        sl = slice(arm * n, (arm + 1) * n)
        load = 40.0 * (q[:, sl] - q[0, sl]).sum(axis=1) + 5.0 * dq[:, sl].sum(axis=1)
        w = np.outer(load, [1.0, -0.5, 0.8, 0.05, 0.02, -0.03]) + [2.0, -1.0, 9.5, 0.1, 0.3, 0.0]
        w[:, :3] += rng.normal(0.0, FORCE_NOISE, (len(t), 3))
        w[:, 3:] += rng.normal(0.0, TORQUE_NOISE, (len(t), 3))
        out.append((t.copy(), w))
    return tuple(out)


@pytest.fixture(scope="module")
def bag(recording, tmp_path_factory):
    return bags.write_recording(tmp_path_factory.mktemp("bags") / "run", recording, wrench_topics=WRENCH_TOPICS)


def test_the_excitation_keeps_to_its_limits(ur5e):
    ex = excite.excitation(ur5e, duration=12.0, amplitude=0.05, speed=0.4)
    n = len(ex.joints) // 2
    off = ex.commands - ex.pose
    assert np.abs(off).max() == pytest.approx(0.05, rel=1e-6)
    assert np.abs(np.diff(ex.commands, axis=0)).max() * ex.rate <= 0.4 * (1 + 1e-9)
    for j, t0, t1 in ex.segments:  # one joint moves at a time, the same in both arms
        rows = (ex.times >= t0) & (ex.times < t1)
        moving = np.flatnonzero(np.abs(off[rows]).max(axis=0) > 0)
        assert set(moving) == {j, n + j}
    assert ex.clearance > excite.CLEARANCE_M
    assert np.allclose(ex.commands[-1], ex.pose)


def test_the_excitation_refuses_what_it_cannot_keep(ur5e, monkeypatch):
    m = ur5e.mj_model
    jid = int(m.dof_jntid[ur5e.index.arms[1].dof_adr[2]])
    pose = excite.pose_of(ur5e)[len(ur5e.index.arms[0].dof_adr) + 2]
    saved = m.jnt_range[jid].copy()
    try:
        m.jnt_range[jid] = [pose - 0.05, pose + 0.05]
        with pytest.raises(ConfigError, match=r"amplitude 0.05 rad takes joint left_elbow .* out of its range"):
            excite.excitation(ur5e)
    finally:
        m.jnt_range[jid] = saved
    monkeypatch.setattr(excite, "CLEARANCE_M", 10.0)
    with pytest.raises(ConfigError, match="the arms come .* close .* lower the amplitude"):
        excite.excitation(ur5e)
    monkeypatch.undo()
    with pytest.raises(ConfigError, match="too short"):
        excite.excitation(ur5e, duration=2.0)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_recording_reads_back_in_any_joint_order(recording, tmp_path, storage):
    shuffled = list(reversed(recording.joints))
    path = bags.write_recording(tmp_path / "b", recording, state_order=shuffled, storage=storage)
    back = bags.read_recording(path, recording.joints)
    assert np.allclose(back.q, recording.q, atol=0) and np.allclose(back.dq, recording.dq, atol=0)
    assert np.allclose(back.commands, recording.commands, atol=0)
    assert np.allclose(back.state_times, recording.state_times, rtol=0, atol=1e-6)  # ns stamps at 1e9 s
    # a Float64MultiArray in another order than the joints asked for
    perm = [recording.joints[i] for i in np.random.default_rng(0).permutation(len(recording.joints))]
    again = bags.read_recording(path, perm, command_joints=recording.joints)
    assert np.allclose(again.commands, recording.commands[:, [recording.joints.index(j) for j in perm]], atol=0)


def test_trajectory_commands_read_like_arrays(recording, tmp_path):
    path = bags.write_recording(tmp_path / "t", recording, command_type=bags.TRAJECTORY)
    back = bags.read_recording(path, recording.joints)
    assert np.allclose(back.commands, recording.commands, atol=0)


@pytest.mark.parametrize("kind", ["multi_array", "trajectory"])
def test_per_arm_command_topics_read_as_one(recording, tmp_path, kind, capsys):
    """One position controller per arm (the usual dual-arm layout): each topic in its own arm's joint order,
    the left's messages 40 us after the right's, read back as the one-topic recording; two topics at other
    rates or a cycle apart are refused naming both."""
    topics = ("/right_position_controller/commands", "/left_position_controller/commands")
    command_type = bags.MULTI_ARRAY if kind == "multi_array" else bags.TRAJECTORY
    path = bags.write_recording(tmp_path / "b", recording, command_topic=topics, command_type=command_type,
                                left_lag=40e-6)  # fmt: skip
    back = bags.read_recording(path, recording.joints, command_topic=topics)
    assert np.array_equal(back.commands, recording.commands)
    assert np.allclose(back.command_times, recording.command_times, rtol=0, atol=1e-6)
    with pytest.raises(bags.RecordingError, match="no topic /forward_position_controller/commands"):
        bags.read_recording(path, recording.joints)  # the one-topic default is not there
    late = bags.write_recording(tmp_path / "late", recording, command_topic=topics, left_lag=0.0009)
    with pytest.raises(bags.RecordingError, match=r"within a quarter period .*same control cycle"):
        bags.read_recording(late, recording.joints, command_topic=topics)
    slow = dataclasses.replace(recording, command_times=recording.command_times[::2], commands=recording.commands[::2])
    store = bags._typestore()
    half = len(recording.joints) // 2
    msgs = [(bags.STATE_TOPIC, bags.JOINT_STATE, 1e9 + t,
             bags.joint_state(1e9 + t, list(recording.joints), recording.q[i], recording.dq[i], store))
            for i, t in enumerate(recording.state_times)]  # fmt: skip
    msgs += [(topics[0], bags.MULTI_ARRAY, 1e9 + t, bags.multi_array(recording.commands[i, :half], store))
             for i, t in enumerate(recording.command_times)]  # fmt: skip
    msgs += [(topics[1], bags.MULTI_ARRAY, 1e9 + t, bags.multi_array(slow.commands[i, half:], store))
             for i, t in enumerate(slow.command_times)]  # fmt: skip
    msgs.sort(key=lambda m: m[2])
    two_rates = bags.write_bag(tmp_path / "two", msgs, "mcap")
    with pytest.raises(bags.RecordingError, match=r"run at 500 Hz and 250 Hz"):
        bags.read_recording(two_rates, recording.joints, command_topic=topics)
    out = tmp_path / "cli"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(path), "--out", str(out),
               "--command-topic", "/a,/b,/c", "--no-report"])  # fmt: skip
    assert rc == 2 and "command_topic must be one topic or two, R,L" in capsys.readouterr().err
    assert not out.exists()


def _broken(recording, tmp_path, how):
    store = bags._typestore()
    J = list(recording.joints)
    msgs = []
    for i, t in enumerate(recording.state_times):
        if how == "gap" and 400 <= i < 460:
            continue
        stamp = 1e9 + (t if not (how == "unordered" and i == 300) else t - 0.1)
        names = J if how != "joint missing" else J[:-1]
        msgs.append((bags.STATE_TOPIC, bags.JOINT_STATE, 1e9 + t,
                     bags.joint_state(stamp, names, recording.q[i, : len(names)], recording.dq[i, : len(names)],
                                      store)))  # fmt: skip
    topic = "/wrong/commands" if how == "wrong topic" else bags.COMMAND_TOPIC
    for i, t in enumerate(recording.command_times):
        if how == "wrong type":
            msgs.append((topic, bags.JOINT_STATE, 1e9 + t, bags.joint_state(1e9 + t, J, recording.commands[i])))
        else:
            msgs.append((topic, bags.MULTI_ARRAY, 1e9 + t, bags.multi_array(recording.commands[i], store)))
    msgs.sort(key=lambda m: m[2])
    return bags.write_bag(tmp_path / how.replace(" ", "_"), msgs)


@pytest.mark.parametrize(
    "how, says",
    [
        ("wrong topic", "no topic /forward_position_controller/commands; its topics:"),
        ("wrong type", "is sensor_msgs/msg/JointState, expected std_msgs/msg/Float64MultiArray"),
        ("joint missing", "not in its messages"),
        ("unordered", "time stamps out of order at message 300"),
        ("gap", "messages were dropped"),
    ],
)
def test_a_bad_recording_is_one_line_and_leaves_nothing(ur5e, recording, tmp_path, capsys, how, says):
    path = _broken(recording, tmp_path, how)
    with pytest.raises(bags.RecordingError, match=says.split(";")[0].replace("(", r"\(")):
        bags.read_recording(path, recording.joints)
    out = tmp_path / "out"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(path), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and says in err and len(err.splitlines()) == 1 and err.startswith("jaxsync calibrate: error:")
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


@pytest.mark.parametrize(
    "topics, says",
    [
        ("/joint_states,/left_ft_sensor/wrench", "topic /joint_states is sensor_msgs/msg/JointState, expected"),
        ("/right_ft_sensor/wrench,/left/wrench", "no topic /left/wrench; its topics:"),
        ("/right_ft_sensor/wrench", "wrench_topics: one per arm"),
    ],
)
def test_bad_wrench_topics_are_one_line(bag, tmp_path, capsys, topics, says):
    out = tmp_path / "out"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(bag), "--out", str(out),
               "--wrench-topics", topics])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert rc == 2 and says in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_sensor_noise_needs_the_arms_still(recording):
    """No still stretch long enough (every command moving): the estimate refuses, naming how little it had."""
    moving = recording.commands + 1e-6 * np.arange(len(recording.commands))[:, None]
    rec = bags.Recording(recording.joints, recording.state_times, recording.q, recording.dq,
                         recording.command_times, moving, wrenches=recording.wrenches)  # fmt: skip
    with pytest.raises(ConfigError, match=r"wrench: 0 samples of sensor 1 while the arms are still \(0.00 s"):
        sensor.estimate(rec, rec.wrenches)


def test_too_few_samples_and_a_missing_bag(recording, tmp_path):
    short = bags.Recording(recording.joints, recording.state_times[:100], recording.q[:100], recording.dq[:100],
                           recording.command_times[:100], recording.commands[:100])  # fmt: skip
    path = bags.write_recording(tmp_path / "s", short)
    with pytest.raises(bags.RecordingError, match="100 messages, calibration needs at least 500"):
        bags.read_recording(path, recording.joints)
    with pytest.raises(bags.RecordingError, match="no such bag"):
        bags.read_recording(tmp_path / "nothing", recording.joints)


def test_calibrate_finds_the_delay_and_the_servo(ur5e, truth, bag, tmp_path, capsys):
    """The delay exactly, each stiffness within 5 % (the robot file's are up to 25 % off), the
    tracking error down to the noise, and the fragment read back by --robot."""
    out = tmp_path / "cal"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(bag), "--out", str(out),
               "--delays", "1:3", "--no-report", "--wrench-topics", ",".join(WRENCH_TOPICS)])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    res = json.loads((out / "calibration.json").read_text())
    assert res["delay_periods"] == TRUE_DELAY
    # the recording's servo structure (the robot file's: weight-compensated, velocity fed forward) chosen
    # on held-out windows, the others far behind
    assert res["structure"] == "feedforward" and res["structure_margin"] > 1.0, res["structure_held_out_costs"]
    assert set(res["structure_held_out_costs"]) == {"as_written", "weight_compensated", "feedforward"}
    # the wrist sensors' noise from the still parts, through a load that moves with the arm
    sensed = res["sensor"]
    assert sensed["force_noise_N"] == pytest.approx(FORCE_NOISE, rel=0.1), sensed
    assert sensed["torque_noise_Nm"] == pytest.approx(TORQUE_NOISE, rel=0.1), sensed
    assert sensed["bias"]["left"]["fz"] == pytest.approx(9.5, abs=0.5)
    nom = replay.Replay(ur5e).nominal()
    fitted = np.array([v["stiffness_N m/rad"] for v in res["joints"].values()])
    err_fit = np.abs(fitted / truth.stiffness - 1)
    err_nom = np.abs(nom.stiffness / truth.stiffness - 1)
    assert err_fit.max() < 0.05 and err_nom.max() > 0.15, (err_fit, err_nom)
    # each stated half-width is the largest of its parts, and it holds the truth
    for v, k_true in zip(res["joints"].values(), truth.stiffness, strict=True):
        parts = [v[f"stiffness_interval95_{p}"] for p in ("jacobian", "windows", "halves", "open_step", "step")]
        assert v["stiffness_interval95"] == pytest.approx(max(parts)) and v["stiffness_interval95_windows_se"] > 0
        assert abs(v["stiffness_N m/rad"] - k_true) <= v["stiffness_interval95"], v
    before = np.array([v["rms_before_rad"] for v in res["joints"].values()])
    after = np.array([v["rms_after_rad"] for v in res["joints"].values()])
    assert after.max() < 2e-5 and after.mean() < 0.8 * before.mean(), (before, after)  # the noise: 1e-5 rad
    assert (out / "calibration.png").stat().st_size > 10_000
    # the fragment goes into the robot file and the position stack runs it
    robot = yaml.safe_load(Path(UR5E).read_text())
    robot.update(yaml.safe_load((out / "calibration.yaml").read_text()))
    arm = robot["arms"]["right"]["model"]
    shutil.copy(ROBOTS / arm, tmp_path / arm)
    (tmp_path / "cal.yaml").write_text(yaml.safe_dump(robot))
    loaded = load_robot(tmp_path / "cal.yaml")
    assert loaded.delay == (TRUE_DELAY, 500.0)
    calibrated = load_model(str(tmp_path / "cal.yaml"), visual=False)
    servo = servo_of(calibrated)
    assert np.allclose(servo.stiffness.reshape(-1), fitted, rtol=1e-5)
    assert servo.weight_compensation and servo.velocity_feedforward
    task = default_scenario(calibrated)  # the task (and every scenario drawn around it) takes the sensors' noise
    assert float(task.force_noise) == pytest.approx(sensed["force_noise_N"], rel=1e-5)
    assert float(task.torque_noise) == pytest.approx(sensed["torque_noise_Nm"], rel=1e-5)


def test_excite_writes_a_bag_that_calibrate_reads(tmp_path, capsys):
    out = tmp_path / "ex"
    assert main(["excite", "--robot", UR5E, "--no-visual", "--out", str(out), "--duration", "8",
                 "--amplitude", "0.03"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "8.0 s at 500 Hz" in printed and "speed at most 0.500 rad/s" in printed
    about = yaml.safe_load((out / "excitation.yaml").read_text())
    table = np.loadtxt(out / "excitation.csv", delimiter=",", skiprows=1)
    assert table.shape == (about["samples"], 1 + len(about["joints"]))
    ex = bags.read_recording
    with pytest.raises(bags.RecordingError, match="no topic /joint_states"):  # commands only: nothing recorded yet
        ex(out / "excitation", about["joints"])
    assert main(["excite", "--robot", UR5E, "--no-visual", "--out", str(out)]) == 2  # not over a folder in use


def test_robot_file_delay_and_per_arm_servo(tmp_path):
    doc = yaml.safe_load(Path(UR5E).read_text())
    shutil.copy(ROBOTS / doc["arms"]["right"]["model"], tmp_path)
    doc["delay"] = {"periods": 2, "control_rate": 1000}
    doc["servo"] = {"right": {"stiffness": [1] * 6, "damping": [0] * 6}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="missing 'left'"):
        load_robot(tmp_path / "r.yaml")
    doc["servo"]["left"] = {"bandwidth": 20}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="per arm, stiffness and damping"):
        load_robot(tmp_path / "r.yaml")
    doc["servo"]["left"] = {"stiffness": [2] * 6, "damping": [1] * 6}
    doc["delay"] = {"periods": 2.5, "control_rate": 1000}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="delay.periods must be a whole number"):
        load_robot(tmp_path / "r.yaml")
    doc["delay"] = {"periods": 2, "control_rate": 1000}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    assert robot_delay(str(tmp_path / "r.yaml")) == 1  # 2 periods at 1 kHz: 1 of the scene's 500 Hz
    assert robot_delay(str(tmp_path / "r.yaml"), 1000.0) == 2
    assert robot_delay(UR5E) == 0


def test_fitted_joint_dynamics_reach_the_model(ur5e, tmp_path):
    """What ``--fit`` adds is written as ``joint_dynamics:``, which --robot applies to the MJCF's joints
    (both simulators read them from the compiled model); bad values are one line naming the key."""
    from types import SimpleNamespace

    from jaxsync.calibrate.jobs import fragment

    nom = replay.Replay(ur5e).nominal()
    n = len(nom.stiffness)
    fitted = nom.replace(joint_damping=np.linspace(0.5, 1.6, n), frictionloss=np.linspace(0.1, 1.2, n),
                         armature=np.linspace(0.01, 0.12, n))  # fmt: skip
    cal = SimpleNamespace(joints=tuple(f"j{k}" for k in range(n)), fitted=fitted, delay=1, period=0.002,
                          fields=("stiffness", "damping", "joint_damping", "frictionloss", "armature"),
                          structure="weight_compensated", structure_margin=0.5)  # fmt: skip
    doc = yaml.safe_load(Path(UR5E).read_text())
    doc.update(yaml.safe_load(fragment(cal, "test", "ur5e")))
    shutil.copy(ROBOTS / doc["arms"]["right"]["model"], tmp_path)
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    model = load_model(str(tmp_path / "r.yaml"), visual=False)
    dofs = replay.Replay(model).pc.dof_adr
    m = model.mj_model
    assert np.allclose(m.dof_damping[dofs], fitted.joint_damping)
    # the structure the fit chose reaches the model's servo
    assert replay.Replay(model).servo.structure == "weight_compensated"
    assert np.allclose(m.dof_frictionloss[dofs], fitted.frictionloss)
    assert np.allclose(m.dof_armature[dofs], fitted.armature)
    assert np.allclose(np.asarray(model.mjx_model.dof_armature)[dofs], fitted.armature)
    assert model.fingerprint != ur5e.fingerprint
    assert not np.allclose(ur5e.mj_model.dof_armature[dofs], fitted.armature)  # the MJCF's were other values
    doc["joint_dynamics"]["left"]["armature"] = [-1.0] * (n // 2)
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="joint_dynamics.left.armature must be >= 0"):
        load_robot(tmp_path / "r.yaml")
    doc["joint_dynamics"]["left"] = {"stiction": [0.0] * (n // 2)}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="stiction"):
        load_robot(tmp_path / "r.yaml")


def test_robot_file_sensor_noise_sets_the_task_and_its_draws(tmp_path):
    import jax

    from jaxsync.optimize.tuning import scenarios as S

    doc = yaml.safe_load(Path(UR5E).read_text())
    shutil.copy(ROBOTS / doc["arms"]["right"]["model"], tmp_path)
    doc["sensor"] = {"force_noise": 0.3}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    model = load_model(str(tmp_path / "r.yaml"), visual=False)
    base, plain = default_scenario(model), default_scenario()
    assert float(base.force_noise) == 0.3 and float(base.torque_noise) == float(plain.torque_noise)
    assert dict(S.model_overrides(model))["force_noise"] == 0.3  # what tune, study and compare start from
    drawn = S.sample_scenarios(jax.random.key(1), 8, base).force_noise
    nominal = S.sample_scenarios(jax.random.key(1), 8, plain).force_noise
    assert np.allclose(drawn, 3.0 * nominal) and 0.05 <= nominal.min() and nominal.max() <= 0.15
    for bad, says in (({"force_noise": -1}, "sensor.force_noise must be a standard deviation in"),
                      ({"noise": 1.0}, "noise")):  # fmt: skip
        doc["sensor"] = bad
        (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
        with pytest.raises(ConfigError, match=says):
            load_robot(tmp_path / "r.yaml")


def test_the_fits_threaded_replay_is_the_position_stacks_servo(ur5e, recording):
    """The fit rolls out MuJoCo's own actuators (threaded C); the position stack's servo code agrees
    with it along the excitation to micro-radians (it adds Coriolis compensation and a torque clip)."""
    from jaxsync.calibrate.fit import _spec

    native = replay.NativeReplay(ur5e, _spec(ur5e), timestep=0.0005)
    joints = native.exact.nominal()
    state = native.exact.state(recording.commands[0], np.zeros(len(recording.joints)), 0.0)
    exact = native.exact.run(joints, state, 8000, recording.command_times, recording.commands, 1, 0.002)
    ((t, q, dq),) = native.run_many([(joints, state, recording.command_times, recording.commands)], 8000, 1, 0.002)
    assert np.allclose(t, exact[0])
    assert np.abs(q - exact[1]).max() < 3e-5 and np.abs(q - recording.commands[0]).max() > 1e-2


def test_a_fit_that_explains_nothing_says_so(recording, bag, tmp_path, capsys):
    """Commands read in the wrong joint order (a wrong --command-joints): no servo explains the
    motion, and the command says so, naming the joints and the figure."""
    wrong = ",".join(reversed(recording.joints))
    out = tmp_path / "poor"
    argv = ["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(bag), "--out", str(out), "--delays", "2",
            "--timestep", "0.002", "--no-report", "--command-joints", wrong, "--force"]  # fmt: skip
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 0 and "WARNING: the fitted model does not explain the motion of" in err and "calibration.png" in err
    assert "times the recording's noise" in err and "(written as asked, --force)" in err
    written = json.loads((out / "calibration.json").read_text())
    assert len(written["poor_fit"]) >= len(recording.joints) // 2, written["poor_fit"]
    assert written["problems"] and (out / "calibration.yaml").read_text().startswith("# WARNING: ")


def test_arms_on_one_torso_keep_their_clearance():
    """The paper model's arms hang from one torso: each arm's clearance counts its moving bodies only."""
    ex = excite.excitation(load_model(None, visual=False), duration=10.0, amplitude=0.02)
    assert 0.05 < ex.clearance < 1.0
    assert len(ex.joints) == 14 and ex.joints[0] == "r_joint1" and ex.joints[7] == "l_joint1"


def test_a_calibration_with_problems_is_refused_and_nothing_written(bag, tmp_path, capsys, monkeypatch):
    """The job refuses what ``problems`` names: exit 2, the reasons and --force in one line, no folder."""
    from jaxsync.calibrate import jobs  # noqa: PLC0415 -- the job whose fit is stood in for

    def fitted(model, rec, **kw):
        cal = _calibration(joints=tuple(rec.joints), fitted=replay.Replay(model).nominal())
        cal.problems = ("the fitted servo leaves 3 joint(s) over 2 times the recording's noise",)
        return cal, None, None, None, None

    monkeypatch.setattr(jobs, "calibrate", fitted)
    out = tmp_path / "refused"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(bag), "--out", str(out), "--no-report"])
    err = capsys.readouterr().err
    assert rc == 2 and "no calibration written, the recording does not support one" in err, err
    assert "times the recording's noise" in err and "--force writes it with these as WARNINGs" in err
    assert not out.exists() and not list(tmp_path.glob(".refused*"))


def test_the_noise_floor_is_the_samples_own_noise():
    """Third differences see the white noise, not the motion: a step-and-chirp-like motion sampled at 500 Hz."""
    t = np.arange(0.0, 20.0, 0.002)
    motion = 0.05 * np.sin(2 * np.pi * 0.7 * t)[:, None] + 0.02 * np.tanh(20 * np.sin(0.5 * t))[:, None]
    rng = np.random.default_rng(3)
    for sigma in (1e-5, 1e-4):
        q = np.repeat(motion, 3, axis=1) + sigma * rng.standard_normal((len(t), 3))
        np.testing.assert_allclose(uncertainty.noise_floor(q), sigma, rtol=0.1)


def _clustered_fit(rng, shared: float, delta=(0.0, 0.0)):
    """A linear least-squares fit over 40 windows of 50 samples, its residual (at the optimum moved by
    ``delta``) and Jacobian: parameter 0 moves every window, parameter 1 five of them, each mostly by one
    level per window (a smooth motion); each window's samples share an error of standard deviation
    ``shared`` on top of white noise of 0.1."""
    x = rng.standard_normal((40, 1, 2)) + 0.3 * rng.standard_normal((40, 50, 2))
    x[5:, :, 1] = 0.0
    y = x @ np.array([1.0, -2.0]) + shared * rng.standard_normal((40, 1)) + 0.1 * rng.standard_normal((40, 50))
    jac = x.reshape(-1, 2)
    theta = np.linalg.lstsq(jac, y.ravel(), rcond=None)[0]
    residuals = list((x @ (theta + np.asarray(delta)) - y).reshape(40, 50))
    return theta - np.array([1.0, -2.0]), residuals, jac


def test_the_windows_intervals_hold_where_a_window_shares_its_error():
    """Where each window's samples share an error, the white-noise (Jacobian) interval covers the truth in
    about a third of the draws; the windows' sandwich covers it near its 95 %, also for a parameter that
    only five windows move; with white noise alone it is no wider than it must be (under twice the
    Jacobian's)."""
    rng = np.random.default_rng(4)
    hits, white = np.zeros(2), np.zeros(2)
    for _ in range(300):
        err, residuals, jac = _clustered_fit(rng, shared=1.0)
        half, se, step = uncertainty.clustered_intervals(residuals, jac)
        r = np.concatenate(residuals)
        s2 = r @ r / (r.size - 2)
        jac_half = 1.96 * np.sqrt(s2 * np.diag(np.linalg.inv(jac.T @ jac)))
        hits += np.abs(err) <= half
        white += np.abs(err) <= jac_half
        np.testing.assert_allclose(step, 0.0, atol=1e-9)  # at the optimum nothing is left open
    assert np.all(hits / 300 >= 0.90) and np.all(hits / 300 <= 0.995), hits / 300
    assert np.all(white / 300 < 0.6), white / 300
    _, residuals, jac = _clustered_fit(rng, shared=0.0)
    r = np.concatenate(residuals)
    jac_half = 1.96 * np.sqrt(r @ r / (r.size - 2) * np.diag(np.linalg.inv(jac.T @ jac)))
    assert np.all(uncertainty.clustered_intervals(residuals, jac)[0] < 2.0 * jac_half * np.array([1.0, 2.5]))


def test_the_open_step_is_what_the_fit_left():
    """Away from the optimum by delta, the Gauss-Newton step still open is |delta|."""
    _, residuals, jac = _clustered_fit(np.random.default_rng(5), shared=0.3, delta=(0.01, -0.2))
    np.testing.assert_allclose(uncertainty.clustered_intervals(residuals, jac)[2], [0.01, 0.2], rtol=1e-9)


def _calibration(**kw):
    n = 2
    ones = np.ones(n)
    joints = Joints(ones * 100, ones * 10, ones * 0, ones * 0, ones * 0.1)
    base = dict(joints=("a", "b"), delay=2, period=0.002, fitted=joints, nominal=joints,
                intervals={"stiffness": ones * 1.0, "damping": ones * 0.5}, rms_before=ones * 1e-3,
                rms_after=ones * 1e-4, motion=ones * 1e-2, delay_costs={0: 300.0, 1: 200.0, 2: 100.0, 3: 150.0},
                fields=("stiffness", "damping"), seconds=1.0, windows=4, noise=ones * 1e-4)  # fmt: skip
    return fit.Calibration(**(base | kw))


class _Param:
    def __init__(self, v):
        self.value = np.array([v])


def test_calibrate_names_every_reason_it_cannot_stand_behind_a_result():
    pd = {"a stiffness": _Param(1.1), "a damping": _Param(0.9), "b stiffness": _Param(1.0), "b damping": _Param(1.2)}
    assert fit.problems(_calibration(), [0, 1, 2, 3, 4], pd) == []
    edge = fit.problems(_calibration(delay=4, delay_costs={2: 300.0, 3: 200.0, 4: 100.0}), [0, 1, 2, 3, 4], pd)
    assert edge and "the last one scanned" in edge[0] and "--delays 0:8" in edge[0]
    near = fit.problems(_calibration(delay_costs={1: 101.0, 2: 100.0, 3: 150.0}), [0, 1, 2, 3, 4], pd)
    assert near == ["delays [1] explain the recording within 2% of delay 2's cost"]
    bound = fit.problems(_calibration(), [0, 1, 2, 3, 4], pd | {"b damping": _Param(10.0)})
    assert bound == ["1 gain(s) sit on their bounds: b's damping (10 times the robot file's)"]
    noisy = fit.problems(_calibration(rms_after=np.array([1e-4, 5e-4])), [0, 1, 2, 3, 4], pd)
    assert len(noisy) == 1 and "worst b: 0.5 mrad RMS against 0.1 mrad of noise" in noisy[0]
    loose = _calibration(intervals={"stiffness": np.array([1.0, 12.0]), "damping": np.array([0.5, np.nan])})
    said = fit.problems(loose, [0, 1, 2, 3, 4], pd)
    assert said == [
        "the recording does not determine the stiffness of 1 joint(s) to 10% (worst b: +-12%)",
        "the recording does not determine the damping of 1 joint(s) to 20% (worst b: no interval)",
        "the delay found (2 periods) was fitted with those gains: not stood behind either",
    ]
    # where the joint efforts fix the delay, it is theirs, not the gains'
    ef = efforts.EffortFit("feedforward", 2, np.ones(2), np.ones(2), np.ones(2), np.zeros(2),
                           {("feedforward", d): c for d, c in ((1, 3.0), (2, 1.0), (3, 2.0))},
                           {"stiffness": np.full(2, 0.01), "damping": np.full(2, 0.01)})  # fmt: skip
    with_efforts = dataclasses.replace(loose, efforts=ef)
    assert not any("delay found" in p for p in fit.problems(with_efforts, [0, 1, 2, 3, 4], pd))
    costs = {"as_written": 104.0, "weight_compensated": 300.0, "feedforward": 100.0}
    close = fit.problems(_calibration(structure="feedforward", structure_costs=costs), [0, 1, 2, 3, 4], pd)
    assert close == [
        "the as_written servo explains the held-out windows within 4.0% of the feedforward one's cost: "
        "the recording does not tell the structures apart"
    ]
    apart = _calibration(structure="feedforward", structure_costs=costs | {"as_written": 110.0})
    assert fit.problems(apart, [0, 1, 2, 3, 4], pd) == [] and apart.structure_margin == pytest.approx(0.1)


def test_the_fits_residual_is_the_toolboxs_number_for_number(ur5e, recording):
    """The fit's own road to the residual (each column's model once, every window in one rollout) gives
    the toolbox's ``build_residual_fn`` with the same hooks exactly, for one point and for the columns of
    a finite-difference Jacobian, in every structure; a changed gain changes it."""
    from jaxsync.physics.servo import STRUCTURES

    for name in STRUCTURES:
        prob = fit.Problem(ur5e, recording, 0.5, structure=STRUCTURES[name])
        pd = prob.parameters(prob.replay.nominal(), fit.FACTORS)
        prob.delay = TRUE_DELAY
        m = prob.replay.m
        toolbox = prob.sysid.build_residual_fn(models_sequences=[prob.sequences], build_model=lambda p, s, m=m: m,
                                               custom_rollout=prob._rollout, modify_residual=prob._residual,
                                               resample_true=False, n_threads=1)  # fmt: skip
        x = pd.as_vector() * np.random.default_rng(1).uniform(0.9, 1.1, pd.size)
        cols = np.column_stack([x, x + 1e-3 * np.eye(pd.size)[:, 0], x - 1e-3 * np.eye(pd.size)[:, -1]])
        for point in (x, cols):
            want, got = toolbox(point, pd.copy())[0], prob.residual_fn(point, pd.copy())[0]
            assert len(got) == len(want) == len(prob.sequences.measured_rollout)
            for a, b in zip(want, got, strict=True):
                assert a.shape == b.shape and np.array_equal(a, b), name
        moved = prob.residual_fn(cols, pd.copy())[0]
        assert not np.array_equal(moved[0][:, 0], moved[0][:, 1])


def test_a_structure_far_behind_stops_its_delay_scan(ur5e, recording):
    """The recording's own structure scanned first; as written, 50 times its cost at the first delay,
    is scanned no further, and the result is the same."""
    said = []
    cal = fit.calibrate(ur5e, recording, delays=range(1, 4), structures=["feedforward", "as_written"],
                        progress=said.append)[0]  # fmt: skip
    scanned = [line.split(",")[0] for line in said if "joint-by-joint fit, cost" in line]
    assert scanned == ["feedforward"] * 3 + ["as_written"], said
    assert cal.structure == "feedforward" and cal.delay == TRUE_DELAY and cal.structure_margin > 10


def test_unknown_servo_structures_are_one_line(bag, tmp_path, capsys):
    out = tmp_path / "cal"
    rc = main(["calibrate", "--robot", UR5E, "--no-visual", "--bag", str(bag), "--out", str(out),
               "--structures", "as_written,geared", "--no-report"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and "structures must be one or more of ['as_written', 'weight_compensated', 'feedforward']" in err
    assert "Traceback" not in err and not out.exists()


def test_a_joint_whose_fastest_mode_the_samples_cannot_resolve_is_not_stood_behind_on_its_motion():
    """An overdamped joint's fast pole (an FR3-like wrist: I 0.1, k 2000, b 200: 0.50 ms) quicker than the
    2 ms samples: its motion sets k / b, not each, and without efforts that fix it calibrate refuses; an
    underdamped joint (k 3000, b 15: 1 / w = 5.8 ms) is resolved and its motion stands."""
    joints = Joints(np.array([2000.0, 3000.0]), np.array([150.0, 15.0]), np.array([50.0, 0.0]), np.zeros(2),
                    np.zeros(2))  # fmt: skip
    tau = fit.fastest_mode([0.1, 0.1], joints)  # the servo's damping and the joint's own add
    np.testing.assert_allclose(tau, [0.2 / (200.0 + np.sqrt(200.0**2 - 4 * 0.1 * 2000.0)), np.sqrt(0.1 / 3000.0)])
    pd = {"a stiffness": _Param(1.0), "a damping": _Param(1.0), "b stiffness": _Param(1.0), "b damping": _Param(1.0)}
    intervals = {"stiffness": np.array([20.0, 30.0]), "damping": np.array([2.0, 0.3])}  # both claim to fix
    cal = _calibration(fitted=joints, nominal=joints, intervals=intervals, inertia=np.array([0.1, 0.1]),
                       sample_period=0.002)  # fmt: skip
    assert cal.unresolved.tolist() == [True, False]
    (said,) = fit.problems(cal, [0, 1, 2, 3, 4], pd)
    assert "fastest mode of 1 joint(s) (a; 0.5 ms) is quicker than the recording's samples (2 ms)" in said
    assert fit.problems(dataclasses.replace(cal, sample_period=0.0004), [0, 1, 2, 3, 4], pd) == []
    # with efforts: those that fix the quick joint's gains stand in for its motion, those that do not refuse it
    costs = {("feedforward", d): c for d, c in ((1, 3.0), (2, 1.0), (3, 2.0))}
    fixing = efforts.EffortFit("feedforward", 2, joints.stiffness, joints.damping, np.ones(2), np.zeros(2), costs,
                               {"stiffness": np.array([20.0, 3000.0]), "damping": np.array([2.0, 15.0])})  # fmt: skip
    assert fit.problems(dataclasses.replace(cal, efforts=fixing), [0, 1, 2, 3, 4], pd) == []
    loose = dataclasses.replace(
        fixing, intervals={"stiffness": np.array([2000.0, 3.0]), "damping": np.array([200.0, 0.1])}
    )
    (said,) = fit.problems(dataclasses.replace(cal, efforts=loose), [0, 1, 2, 3, 4], pd)
    assert "do not fix the gains of 1 joint(s) (a) whose fastest mode is quicker" in said
    # and the efforts' gains are taken for a quick joint even where its motion claims to fix them
    nominal = Joints(np.array([1000.0, 3000.0]), np.array([100.0, 15.0]), np.zeros(2), np.zeros(2), np.zeros(2))
    mine = {k: _Param(v.value[0]) for k, v in pd.items()}
    taken = efforts.take_open_gains(fixing, mine, ("a", "b"), nominal, {k: v.copy() for k, v in intervals.items()},
                                    fit.DETERMINED, fit.FACTOR_BOUNDS, unresolved=cal.unresolved)  # fmt: skip
    assert taken == ("a",) and mine["a stiffness"].value[0] == pytest.approx(2.0)
    assert efforts.take_open_gains(fixing, dict(pd), ("a", "b"), nominal, intervals, fit.DETERMINED,
                                   fit.FACTOR_BOUNDS) == ()  # fmt: skip
