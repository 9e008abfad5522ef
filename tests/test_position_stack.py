"""Position-controlled arms: the joint servo, the command delay, the control
rate, where a robot's servo comes from, and a rollout on the paper model."""

from __future__ import annotations

import os

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import TEST_DURATION, fast_scenario

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.cli import _stack
from jaxsync.control import gains as _gains
from jaxsync.physics import servo as _servo
from jaxsync.physics.robot import load_robot
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import metrics as _metrics
from jaxsync.sim.scenario import MAX_DELAY

ROBOTS = os.path.join(os.path.dirname(__file__), "..", "mjcf", "robots")

ONE_JOINT = """
<mujoco>
  <option timestep="{dt}" integrator="Euler" gravity="0 0 0"/>
  <worldbody>
    <body>
      <joint name="j" type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="1" diaginertia="{inertia} {inertia} {inertia}"/>
    </body>
  </worldbody>
  <actuator><motor joint="j"/></actuator>
</mujoco>
"""


def _consts(stiffness, damping, weight=1.0, feedforward=1.0, lo=-np.inf, hi=np.inf):
    """PositionConsts of joints 0..n-1 in order, one structure for all."""
    k = np.atleast_1d(np.asarray(stiffness, float))
    idx, ones = np.arange(len(k)), np.ones(len(k))
    return _actuation.PositionConsts(
        stiffness=k,
        damping=np.atleast_1d(np.asarray(damping, float)),
        dof_adr=idx,
        qpos_adr=idx,
        joint_damping=np.zeros(len(k)),
        actuator_ids=idx,
        joint_ids=idx,
        weight=weight * ones,
        feedforward=feedforward * ones,
        command_lo=lo * ones,
        command_hi=hi * ones,
    )


def _one_joint_servo(stiffness, damping, limit, command, steps, dt=0.001, inertia=0.5):
    """MuJoCo C, one free hinge: the servo's two parts as a rollout applies them."""
    m = mujoco.MjModel.from_xml_string(ONE_JOINT.format(dt=dt, inertia=inertia))
    pc = _consts(stiffness, damping)
    for name, where, value in _actuation.model_updates(pc, 1.0):
        getattr(m, name)[where] = value
    d = mujoco.MjData(m)
    q, tau_out = [], []
    for _ in range(steps):
        mujoco.mj_step1(m, d)
        tau, motor = _actuation.servo_torque(
            pc, d.qpos, d.qvel, d.qfrc_bias, np.array([command]), np.zeros(1), 1.0, np.array([limit]), np
        )
        d.ctrl[:] = motor
        mujoco.mj_step2(m, d)
        q.append(d.qpos[0])
        tau_out.append(tau[0])
    return np.array(q), np.array(tau_out)


def test_the_servo_tracks_a_step_as_its_second_order_loop():
    """k = I w^2, b = 2 I w: the critically damped response 1 - (1 + w t) e^(-w t)."""
    inertia, w, dt = 0.5, 2 * np.pi * 10.0, 0.001
    q, _ = _one_joint_servo(inertia * w * w, 2 * inertia * w, 1e6, 0.1, 300, dt, inertia)
    t = dt * np.arange(1, 301)
    closed = 0.1 * (1 - (1 + w * t) * np.exp(-w * t))
    assert np.max(np.abs(q - closed)) < 0.1 * 0.03
    assert q.max() < 0.1 * 1.01  # critically damped: no overshoot beyond the integrator's rounding


def test_the_servo_clips_its_torque_and_stays_stable_at_any_damping():
    """The torque limit holds what the joint gets (a ramp at limit / I), and a
    damping far beyond the explicit bound (dt b / I = 40) still settles."""
    inertia, dt, limit = 0.5, 0.001, 2.0
    q, tau = _one_joint_servo(1e5, 0.0, limit, 1.0, 100, dt, inertia)
    assert np.all(np.abs(tau) <= limit + 1e-12)
    t = dt * np.arange(1, 101)
    # semi-implicit Euler of qdd = limit / I: q_k = (limit / I) dt^2 k (k + 1) / 2
    np.testing.assert_allclose(q, limit / inertia * dt * t * (t / dt + 1) / 2, rtol=1e-9)
    q, _ = _one_joint_servo(200.0, 2e4, 1e6, 0.1, 3000, dt, inertia)
    # overdamped: the slow pole k / b = 0.01 1/s, q ~ 0.1 (1 - e^(-k t / b)), rising without oscillation
    np.testing.assert_allclose(q[-1], 0.1 * (1 - np.exp(-200.0 / 2e4 * 3.0)), rtol=0.02)
    assert np.all(np.diff(q) >= -1e-12)


def test_motor_torque_is_the_servo_torque_plus_the_cancelled_damping():
    pc = _consts([100.0, 50.0], [10.0, 4.0])
    qpos, qvel, bias = np.array([0.1, -0.2]), np.array([0.5, 1.0]), np.array([1.0, -2.0])
    cmd, cmd_vel, limit = np.array([0.2, -0.1]), np.array([0.0, 2.0]), np.array([1e3, 3.0])
    tau, motor = _actuation.servo_torque(pc, qpos, qvel, bias, cmd, cmd_vel, 1.3, limit, np)
    want = 1.3 * (pc.stiffness * (cmd - qpos) + pc.damping * (cmd_vel - qvel)) + bias
    np.testing.assert_allclose(tau, np.clip(want, -limit, limit))
    assert tau[1] == 3.0  # clipped
    np.testing.assert_allclose(motor - tau, 1.3 * pc.damping * qvel)


def test_the_servo_structure_and_command_range():
    """As written (w = 0, f = 0): no bias compensation, the damping on the joint's velocity;
    a command outside the actuator's control range acts at its end."""
    qpos, qvel, bias = np.array([0.1, -0.2]), np.array([0.5, 1.0]), np.array([1.0, -2.0])
    cmd, cmd_vel, limit = np.array([0.2, -0.5]), np.array([0.3, 2.0]), np.array([1e3, 1e3])
    k, b = np.array([100.0, 50.0]), np.array([10.0, 4.0])
    for w, f in ((0, 0), (1, 0), (0, 1), (1, 1)):
        tau, _ = _actuation.servo_torque(_consts(k, b, w, f), qpos, qvel, bias, cmd, cmd_vel, 1.0, limit, np)
        np.testing.assert_allclose(tau, k * (cmd - qpos) + b * (f * cmd_vel - qvel) + w * bias, rtol=1e-15)
    pc = _consts(k, b, 0, 0, lo=-0.3, hi=0.15)
    tau, _ = _actuation.servo_torque(pc, qpos, qvel, bias, cmd, cmd_vel, 1.0, limit, np)
    np.testing.assert_allclose(tau, k * (np.array([0.15, -0.3]) - qpos) - b * qvel, rtol=1e-15)


PENDULUM = """
<mujoco>
  <option timestep="{dt}" integrator="{integrator}"/>
  <worldbody>
    <body>
      <joint name="j" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="2" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>{actuator}</actuator>
</mujoco>
"""


@pytest.mark.parametrize("forcerange", [None, 4.0])
def test_as_written_is_mujocos_own_position_actuator(forcerange):
    """A pendulum under MuJoCo's <position kp kv forcerange ctrlrange> (implicitfast, 0.25 ms)
    and under the position stack's servo as written (Euler, 1 ms: a motor plus the joint damping):
    the same sag under gravity, the same saturated swing, within the integrators' difference."""
    kp, kv = 60.0, 3.0
    # held, a step, one beyond the control range's 1.0, then a sine (a command with a velocity)
    steps = [(lambda t, c=c: c, lambda t: 0.0) for c in (0.0, 0.8, 1.5)]
    steps.append((lambda t: 0.5 * np.sin(2 * np.pi * t), lambda t: np.pi * np.cos(2 * np.pi * t)))
    limit = forcerange or 1e6
    fr = f' forcelimited="true" forcerange="-{forcerange} {forcerange}"' if forcerange else ""
    ref = mujoco.MjModel.from_xml_string(PENDULUM.format(
        dt=0.00025, integrator="implicitfast",
        actuator=f'<position joint="j" kp="{kp}" kv="{kv}" ctrlrange="-1 1"{fr}/>'))  # fmt: skip
    m = mujoco.MjModel.from_xml_string(PENDULUM.format(dt=0.001, integrator="Euler", actuator='<motor joint="j"/>'))
    pc = _consts(kp, kv, 0.0, 0.0, lo=-1.0, hi=1.0)._replace(joint_damping=np.array([0.05]))
    for name, where, value in _actuation.model_updates(pc, 1.0):
        getattr(m, name)[where] = value
    dr, d = mujoco.MjData(ref), mujoco.MjData(m)
    q_ref, q = [], []
    for command, velocity in steps:
        for i in range(1000):  # 1 s per command
            c, v = command(i * 0.001), velocity(i * 0.001)
            dr.ctrl[0] = c
            for _ in range(4):
                mujoco.mj_step(ref, dr)
            mujoco.mj_step1(m, d)
            _, motor = _actuation.servo_torque(
                pc, d.qpos, d.qvel, d.qfrc_bias, np.array([c]), np.array([v]), 1.0, np.array([limit]), np
            )
            d.ctrl[:] = motor
            mujoco.mj_step2(m, d)
            q_ref.append(dr.qpos[0])
            q.append(d.qpos[0])
    q_ref, q = np.array(q_ref), np.array(q)
    sag = 2 * 9.81 * 0.2 / kp  # the weight's torque over the stiffness, at the horizontal
    assert abs(q_ref[999]) > 0.5 * sag  # no compensation: it sags
    assert abs(q_ref[2999] - 1.0) < 0.2  # the command held at the control range's end
    assert np.max(np.abs(q - q_ref)) < 0.02 * np.ptp(q_ref), np.max(np.abs(q - q_ref))


def test_a_command_acts_delay_periods_later_with_its_velocity():
    dt = 0.002
    q0 = jnp.zeros(2)
    buffer = _actuation.initial_buffer(q0)
    assert buffer.shape == (MAX_DELAY + 2, 2)
    commands = [jnp.full(2, 0.01 * (k + 1) ** 2) for k in range(12)]
    for k, c in enumerate(commands):
        buffer = _actuation.push(buffer, c)
        for delay in (0, 1, 3, MAX_DELAY):
            acting, vel = _actuation.acting(buffer, delay, dt)
            j = k - delay
            want = commands[j] if j >= 0 else q0
            before = commands[j - 1] if j >= 1 else q0
            np.testing.assert_array_equal(acting, want)
            np.testing.assert_allclose(vel, (want - before) / dt)


def test_control_rate_sets_the_substeps_and_refuses_rates_that_do_not_divide(model):
    assert _actuation.substeps_for_rate(model, None) == 1
    assert _actuation.substeps_for_rate(model, 500) == 1
    assert _actuation.substeps_for_rate(model, 250.0) == 2
    for bad in (1000, 300, 0, -5):
        with pytest.raises(ConfigError, match="control_rate") as err:
            _actuation.substeps_for_rate(model, bad)
        assert err.value.inputs == ("control_rate",)
    with pytest.raises(ConfigError, match="divide the physics rate 500 Hz"):
        _actuation.substeps_for_rate(model, 1000)


@pytest.mark.parametrize(("text", "want"), [("0", (0, 0)), ("2", (2, 2)), ("0:3", (0, 3)), (f"{MAX_DELAY}", (8, 8))])
def test_delay_reads_a_number_or_a_range(text, want):
    assert _stack.parse_delay(text) == want
    assert _actuation.check_delay(want) == want and _actuation.check_delay(want[0]) == (want[0], want[0])


@pytest.mark.parametrize("bad", ["-1", "3:1", "a", "1:2:3", f"0:{MAX_DELAY + 1}", "1.5"])
def test_delay_refuses_what_is_not_whole_periods_in_range(bad):
    with pytest.raises(ConfigError, match=f"^delay must be .* lo:hi within 0..{MAX_DELAY}, got '{bad}'"):
        _stack.parse_delay(bad)


@pytest.mark.parametrize("bad", [-1, (3, 1), "2", 1.5, (0, MAX_DELAY + 1), True, (1, 2, 3)])
def test_the_library_takes_periods_not_text(bad):
    with pytest.raises(ConfigError, match=f"delay must be whole control periods .* within 0..{MAX_DELAY}"):
        _actuation.check_delay(bad)


@pytest.mark.parametrize(("text", "want"), [("1", (1.0, 1.0)), ("0.05:1", (0.05, 1.0))])
def test_ft_filter_reads_a_coefficient_or_a_range(text, want):
    assert _stack.parse_ft_filter(text) == want == _actuation.check_ft_filter(want)
    for bad in ("0:1", "a", "1:0.5", "2"):
        with pytest.raises(ConfigError, match=f"^ft_filter must be .* lo:hi within 0.001..1 .*, got '{bad}'"):
            _stack.parse_ft_filter(bad)
    with pytest.raises(ConfigError, match="one coefficient here"):
        _stack.parse_ft_filter("0.05:1", one=True)
    with pytest.raises(ConfigError, match="ft_filter must be"):
        _actuation.check_ft_filter("0.5")


def test_actuation_names_what_is_allowed():
    with pytest.raises(ConfigError, match=r"actuation must be one of \['torque', 'position'\]"):
        _actuation.check("velocity")
    with pytest.raises(ConfigError, match="delay"):
        jaxsync.short_task(delay=1.5)


def test_a_stack_reads_what_a_user_writes_and_refuses_what_does_not_run(model):
    stack = _actuation.Stack.of("position", 250.0, 2, "rolling")
    assert stack == _actuation.Stack("position", 250.0, (2, 2), "rolling") and stack.scenario_delay() == 2
    assert stack.rollout_options(model) == {"actuation": "position", "control_substeps": 2, "distro": "rolling"}
    written = stack.to_dict(model)
    assert written["control_period_s"] == pytest.approx(0.004) and written["delay"] == [2, 2]
    assert written["ros_distro"] == "rolling"
    with pytest.raises(ConfigError, match=r"distro must be one of \['jazzy', 'kilted', 'rolling', 'humble'\]"):
        _actuation.Stack("position", distro="iron")
    assert written["servo"]["source"] == _servo.servo_of(model).source
    assert "servo" not in _actuation.TORQUE.to_dict(model)  # a torque stack has no servo
    with pytest.raises(ConfigError, match="delay applies to position-controlled arms") as err:
        _actuation.Stack.of("torque", None, 1)
    assert err.value.inputs == ("delay", "actuation")
    with pytest.raises(ConfigError, match="one scenario runs one delay, got the range 0:3"):
        _actuation.Stack.of("position", None, (0, 3)).scenario_delay()


def test_position_defaults_hold_the_inner_loop_below_the_slowest_servo(model):
    """default_gains(model, "position"): on the iiwa-like pair (shoulder servo
    about 28 rad/s) lambda = 2 kp_pos / kd_pos falls to a third of the slowest
    joint's servo frequency; the paper model's 25 Hz servo and the UR5e-like
    pair's are fast enough for the torque defaults' 40 1/s. Normal-axis masses
    are raised to what ros2_controllers' admittance rule runs with a margin."""
    iiwa = jaxsync.load_model(os.path.join(ROBOTS, "iiwa14_twice.yaml"), visual=False)
    torque, position = _gains.default_gains(iiwa), _gains.default_gains(iiwa, "position")
    slowest = np.min(np.sqrt(_servo.servo_of(iiwa).stiffness / _servo.joint_inertia(iiwa)))
    lam = 2 * float(position.kp_pos) / float(position.kd_pos)
    assert lam == pytest.approx(slowest / _gains.SERVO_SEPARATION, rel=1e-6) and 5 < lam < 15
    assert float(position.kd_pos) == float(torque.kd_pos)
    assert 2 * float(torque.kp_pos) / float(torque.kd_pos) == pytest.approx(40.0)
    # the normal axis's mass raised to what the admittance rule runs within its margin (2.46 -> 3.0 kg)
    np.testing.assert_allclose(np.asarray(position.imp_mass)[:, 2], 3.0, rtol=1e-4)
    np.testing.assert_array_equal(np.asarray(position.imp_mass)[:, [0, 1, 3, 4, 5]],
                                  np.asarray(torque.imp_mass)[:, [0, 1, 3, 4, 5]])  # fmt: skip
    ur5e = jaxsync.load_model(os.path.join(ROBOTS, "ur5e_twice.yaml"), visual=False)
    for m in (model, ur5e):
        assert float(_gains.default_gains(m, "position").kp_pos) == float(_gains.default_gains(m).kp_pos)
    # the UR5e-like pair's 6.3 kg normal mass is far from the bound already; the paper model's 2 kg is on it
    np.testing.assert_array_equal(_gains.default_gains(ur5e, "position").imp_mass, _gains.default_gains(ur5e).imp_mass)
    np.testing.assert_allclose(np.asarray(_gains.default_gains(model, "position").imp_mass)[:, 2], 3.0, rtol=1e-4)


def test_a_servo_without_feed_forward_gets_its_lag_led_by_default(model, tmp_path):
    """ff_vel = b / k (median over the joints, at most FF_VEL_MAX) where the servo does not feed
    the command's velocity forward: the iiwa-like MJCF's kv / kp = 50 / 2000; none where it does."""
    iiwa = jaxsync.load_model(os.path.join(ROBOTS, "iiwa14_twice.yaml"), visual=False)
    assert float(_gains.default_gains(iiwa, "position").ff_vel) == pytest.approx(0.025)
    assert float(_gains.default_gains(iiwa).ff_vel) == 0.0  # torque-driven arms have no servo
    for m in (model, jaxsync.load_model(os.path.join(ROBOTS, "ur5e_twice.yaml"), visual=False)):
        assert float(_gains.default_gains(m, "position").ff_vel) == 0.0
    import shutil

    for f in ("iiwa14_twice.yaml", "iiwa14_like_arm.xml"):
        shutil.copy(os.path.join(ROBOTS, f), tmp_path / f)
    text = (tmp_path / "iiwa14_twice.yaml").read_text()
    (tmp_path / "ff.yaml").write_text(text + "\nservo: {weight_compensation: true, velocity_feedforward: true}\n")
    stated = jaxsync.load_model(str(tmp_path / "ff.yaml"), visual=False)
    assert float(_gains.default_gains(stated, "position").ff_vel) == 0.0
    slow = text + f"\nservo: {{stiffness: {[2000] * 7}, damping: {[400] * 7}}}\n"
    (tmp_path / "slow.yaml").write_text(slow)
    slow_model = jaxsync.load_model(str(tmp_path / "slow.yaml"), visual=False)
    assert float(_gains.default_gains(slow_model, "position").ff_vel) == _gains.FF_VEL_MAX  # 0.2 s, capped


def test_the_paper_model_servo_is_its_stated_bandwidth(model):
    s = _servo.servo_of(model)
    inertia = _servo.joint_inertia(model)
    w = 2 * np.pi * _servo.PAPER_SERVO["bandwidth"]
    np.testing.assert_allclose(s.stiffness, inertia * w * w)
    np.testing.assert_allclose(s.damping, 2 * _servo.PAPER_SERVO["damping_ratio"] * inertia * w)
    assert "paper" in s.source and s.stiffness.shape == (2, 7)


def test_a_robot_servo_comes_from_its_mjcf_or_its_file(tmp_path):
    iiwa = jaxsync.load_model(os.path.join(ROBOTS, "iiwa14_twice.yaml"))
    s = _servo.servo_of(iiwa)  # the MJCF's <position kp="2000" kv="50">
    np.testing.assert_array_equal(s.stiffness, np.full((2, 7), 2000.0))
    np.testing.assert_array_equal(s.damping, np.full((2, 7), 50.0))
    text = open(os.path.join(ROBOTS, "ur5e_twice.yaml")).read()
    assert s.structure == "as_written" and "as written" in s.source  # the MJCF's actuators compensate nothing
    assert SERVO_LINE in text
    (tmp_path / "ur5e_like_arm.xml").write_text(open(os.path.join(ROBOTS, "ur5e_like_arm.xml")).read())
    assert _servo.servo_of(jaxsync.load_model(os.path.join(ROBOTS, "ur5e_twice.yaml"))).structure == "feedforward"
    stated = text.replace(SERVO_LINE, "servo: {stiffness: [1, 2, 3, 4, 5, 6], damping: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]}")
    (tmp_path / "stated.yaml").write_text(stated)
    s = _servo.servo_of(jaxsync.load_model(str(tmp_path / "stated.yaml")))
    np.testing.assert_array_equal(s.stiffness, [[1, 2, 3, 4, 5, 6]] * 2)
    np.testing.assert_array_equal(s.damping, [[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]] * 2)
    assert s.structure == "as_written"  # unstated: false
    (tmp_path / "none.yaml").write_text(text.replace(SERVO_LINE, ""))
    with pytest.raises(ConfigError, match="no joint servo known .* servo: {stiffness"):
        _servo.servo_of(jaxsync.load_model(str(tmp_path / "none.yaml")))


SERVO_LINE = "servo: {bandwidth: 25, damping_ratio: 1.0, weight_compensation: true, velocity_feedforward: true}"


def test_a_robot_file_states_the_servo_structure_alone_or_with_gains(tmp_path):
    """servo: {weight_compensation: true} alone keeps the MJCF actuators' gains and command ranges."""
    import shutil

    for f in ("iiwa14_twice.yaml", "iiwa14_like_arm.xml"):
        shutil.copy(os.path.join(ROBOTS, f), tmp_path / f)
    text = (tmp_path / "iiwa14_twice.yaml").read_text()
    (tmp_path / "wc.yaml").write_text(text + "\nservo: {weight_compensation: true}\n")
    s = _servo.servo_of(jaxsync.load_model(str(tmp_path / "wc.yaml"), visual=False))
    assert s.structure == "weight_compensated" and "structure stated" in s.source
    np.testing.assert_array_equal(s.stiffness, np.full((2, 7), 2000.0))
    written = s.to_dict()
    assert written["weight_compensation"] is True and written["velocity_feedforward"] is False
    pc = _actuation.position_consts(jaxsync.load_model(str(tmp_path / "wc.yaml"), visual=False))
    assert pc.weight.all() and not pc.feedforward.any()


@pytest.mark.parametrize(
    ("servo", "match"),
    [
        ("{weight_compensation: 1}", "servo.weight_compensation must be true or false"),
        ("{}", "servo is empty"),
        ("{bandwidth: 20, velocity_feedforward: yes please}", "servo.velocity_feedforward must be true or false"),
        ("{stiffness: [1, 2, 3, 4, 5, 6]}", "missing 'damping'"),
        ("{stiffness: [1, 2, 3], damping: [1, 2, 3]}", "servo.stiffness must be 6 numbers"),
        ("{stiffness: [1, 2, 3, 4, 5, -6], damping: [1, 1, 1, 1, 1, 1]}", "stiffness must be > 0"),
        ("{bandwidth: 0}", r"servo.bandwidth must be a number in \[0.1, 500.0\] Hz"),
        ("{bandwidth: 20, stiffness: [1, 2, 3, 4, 5, 6]}", "servo must be"),
        ("{bandwidth: 20, gain: 3}", r"unknown key\(s\) \['gain'\]"),
        ("25", "servo must be"),
    ],
)
def test_a_robot_file_servo_is_checked(tmp_path, servo, match):
    text = open(os.path.join(ROBOTS, "ur5e_twice.yaml")).read()
    (tmp_path / "ur5e_like_arm.xml").write_text(open(os.path.join(ROBOTS, "ur5e_like_arm.xml")).read())
    (tmp_path / "r.yaml").write_text(text.replace(SERVO_LINE, "servo: " + servo))
    with pytest.raises(ConfigError, match=match):
        load_robot(str(tmp_path / "r.yaml"))


def compile_ahead():
    """The position stack's rollout (tests/conftest.py: compiled ahead in a second process)."""
    from conftest import paper_model

    m = paper_model()
    s = fast_scenario(delay=0.0)
    traj = jaxsync.rollout(m, jaxsync.default_gains(m), s, duration=TEST_DURATION, actuation="position")
    traj.time.block_until_ready()


@pytest.fixture(scope="module")
def position_rollouts(model, shared_rollout):
    """The synchronous controller on position-controlled arms: one program, delays 0 and 3."""
    g = jaxsync.default_gains(model)
    out = {}
    for delay in (0, 3):
        s = fast_scenario(delay=float(delay))
        out[delay] = (s, shared_rollout(model, g, s, duration=TEST_DURATION, actuation="position"))
    return out


@pytest.mark.parametrize("delay", [0, 3])
def test_position_controlled_arms_hold_the_ball_at_delays_0_and_3(position_rollouts, model, delay):
    s, traj = position_rollouts[delay]
    m = _metrics.summarize(traj, s)
    assert not bool(m.dropped) and not bool(m.chattering) and not bool(m.nonfinite)
    assert float(m.grip_force_error_rel) < 0.02
    assert float(m.settled_peak_resultant_N) < 0.1
    assert not np.asarray(traj.at_torque_limit).any()
    # the pads follow the plan: within 2 mm of it once the object is held
    hold = np.asarray(traj.phase) == 3
    assert np.abs(np.asarray(traj.pad_pos - traj.plan_pad_pos))[hold].max() < 2e-3


def test_the_delay_changes_the_rollout_and_the_torque_stack_differs(position_rollouts, rollouts):
    (_, t0), (_, t3) = position_rollouts[0], position_rollouts[3]
    assert float(jnp.abs(t0.pad_forces - t3.pad_forces).max()) > 0.1
    assert float(jnp.abs(t0.torque - rollouts["synchronous"].torque).max()) > 1.0


def test_mujoco_c_runs_the_same_position_stack(position_rollouts, model, shared_rollout):
    s, x = position_rollouts[3]
    c = shared_rollout(model, jaxsync.default_gains(model), s, duration=TEST_DURATION, actuation="position",
                       backend="mujoco")  # fmt: skip
    mx, mc = _metrics.summarize(x, s), _metrics.summarize(c, s)
    np.testing.assert_allclose(float(mc.settled_peak_resultant_N), float(mx.settled_peak_resultant_N), rtol=0.05)
    np.testing.assert_allclose(float(mc.grip_force_error_rel), float(mx.grip_force_error_rel), rtol=0.05, atol=1e-4)
    assert float(jnp.abs(x.obj_pos - c.obj_pos).max()) < 5e-4


def test_the_servo_gets_the_plan_fed_forward_and_mujoco_c_runs_it_too(position_rollouts, model, shared_rollout):
    """With the command's feed-forward (ff_vel, ff_acc) the servo gets the
    integrated command plus J# (ff_vel dx_plan + ff_acc ddx_plan): the
    joints move otherwise while the plan moves, the ball is held, and
    MuJoCo C runs the same."""
    s, plain = position_rollouts[3]
    g = jaxsync.default_gains(model)._replace(ff_vel=jnp.asarray(0.006), ff_acc=jnp.asarray(1e-4))
    x = shared_rollout(model, g, s, duration=TEST_DURATION, actuation="position")
    c = shared_rollout(model, g, s, duration=TEST_DURATION, actuation="position", backend="mujoco")
    assert float(jnp.abs(x.qpos - plain.qpos).max()) > 1e-4  # the plan's feed-forward moves the joints
    mx, mc = _metrics.summarize(x, s), _metrics.summarize(c, s)
    assert not bool(mx.dropped) and not bool(mx.chattering)
    np.testing.assert_allclose(float(mc.settled_peak_resultant_N), float(mx.settled_peak_resultant_N), rtol=0.05)
    assert float(jnp.abs(x.obj_pos - c.obj_pos).max()) < 5e-4
