"""A joint torque limit clips the torque the servo would apply, nothing else.

The recordings come from ``independent_servo`` (MuJoCo C, the servo written
from its definition, another step and integrator): on two robots with joint
torque limits and friction loss as published arms have them (the FR3's
figures and the UR5e's), the position stack's replay with the true
parameters reproduces a recording at speeds where a clipped feed-forward
would brake to a fraction of a milliradian.
"""

from __future__ import annotations

import independent_servo as ind
import numpy as np
import pytest

from jaxsync.calibrate import replay
from jaxsync.calibrate.fit import _spec
from jaxsync.physics.model import load_model
from jaxsync.physics.servo import STRUCTURES
from jaxsync.sim import actuation as _actuation

PERIOD, DELAY, DURATION = 0.002, 2, 4.0
# joint speeds (rad/s) above limit / damping on some joint of each robot, where a feed-forward
# clipped with the servo's torque would brake: the FR3's wrists 12 / 200 = 0.06 rad/s at the
# excitation's cap; the UR5e's shoulder and elbow 150 / 200 = 0.75 rad/s
SPEED = {"fr3": 0.5, "ur5e": 1.2}


@pytest.fixture(scope="module", params=sorted(ind.LIMITED))
def limited_robot(tmp_path_factory, request):
    path = ind.limited_robot(tmp_path_factory.mktemp("limited"), request.param)
    return request.param, load_model(str(path), visual=False)


@pytest.fixture(scope="module")
def limited(limited_robot):
    return limited_robot[1]


@pytest.fixture(scope="module", params=sorted(STRUCTURES))
def fast_recording(limited_robot, request):
    """Both arms moving faster than limit / damping on some joint, where a clipped feed-forward
    would brake; recorded in each servo structure and replayed in the same."""
    figures, limited = limited_robot
    structure = request.param
    r = replay.Replay(limited, structure=STRUCTURES[structure])
    qadr, _ = ind.arm_joints(limited.mj_model)
    assert np.array_equal(qadr, r.pc.qpos_adr)
    q0 = np.asarray(limited.keyframe_qpos("grasp"))
    ct, cmds = ind.commands(q0[qadr], PERIOD, DURATION, speed=SPEED[figures])
    truth = r.nominal()
    lim = np.tile(ind.LIMITED[figures].limits, 2)
    t, q, dq = ind.record(
        limited.mj_model, q0, truth.stiffness, truth.damping, lim, ct, cmds, DELAY, structure=structure
    )
    assert (np.abs(dq).max(axis=0) > lim / truth.damping).any()  # the speeds where a clipped feed-forward brakes
    return r, truth, ct, cmds, t, q, dq, structure


def test_the_limited_robot_is_what_it_says(limited_robot):
    figures, limited = limited_robot
    fig = ind.LIMITED[figures]
    m = limited.mj_model
    _, dofs = ind.arm_joints(m)
    jids = m.dof_jntid[dofs]
    assert m.jnt_actfrclimited[jids].all()
    assert np.allclose(np.abs(m.jnt_actfrcrange[jids]).max(axis=1), np.tile(fig.limits, 2))
    assert np.allclose(m.dof_frictionloss[dofs], np.tile(fig.frictionloss, 2))
    assert np.allclose(m.dof_armature[dofs], np.tile(fig.armature, 2))
    pc = _actuation.position_consts(limited)
    assert np.allclose(pc.stiffness, np.tile(fig.kp, 2)) and np.allclose(pc.damping, np.tile(fig.kv, 2))


def test_the_position_stack_opens_the_joints_force_range(limited):
    """The entries both engines apply: the joints' actuator force range opened with the motors'
    (the servo clips its own torque), for MuJoCo C and MJX alike."""
    pc = _actuation.position_consts(limited)
    updates = {(name, where[1]): (where[0], value) for name, where, value in _actuation.model_updates(pc, 1.0)[1:]}
    ids, low = updates[("jnt_actfrcrange", 0)]
    assert np.array_equal(ids, limited.mj_model.dof_jntid[pc.dof_adr]) and low <= -1e6
    assert updates[("jnt_actfrcrange", 1)][1] >= 1e6


def test_the_replay_reproduces_a_fast_recording_with_torque_limits(fast_recording):
    r, truth, ct, cmds, t, q, dq, _ = fast_recording
    state = r.state(cmds[0], np.zeros(q.shape[1]), 0.0)
    _, qr, _ = r.run(truth, state, int(round(DURATION / r.timestep)), ct, cmds, DELAY, PERIOD)
    every = int(round(PERIOD / r.timestep))
    err = np.sqrt(((qr[every - 1 :: every][: len(q)] - q) ** 2).mean(axis=0))
    # a false brake misses this recording by tens of milliradians; the step and integrator differ
    assert err.max() < 1e-3, f"RMS per joint, mrad: {np.round(1e3 * err, 3)}"
    tracking = np.sqrt(((q - cmds[1:]) ** 2).mean(axis=0))
    assert tracking.max() > 5 * err.max()  # the replay explains the tracking, not just the commands


def test_the_fits_native_replay_has_no_brake_either(limited, fast_recording):
    r, truth, ct, cmds, t, q, dq, structure = fast_recording
    native = replay.NativeReplay(limited, _spec(limited), structure=STRUCTURES[structure])
    state = native.exact.state(cmds[0], np.zeros(q.shape[1]), 0.0)
    n = int(round(DURATION / native.timestep))
    ((_, qn, _),) = native.run_many([(truth, state, ct, cmds)], n, DELAY, PERIOD)
    every = int(round(PERIOD / native.timestep))
    err = np.sqrt(((qn[every - 1 :: every][: len(q)] - q) ** 2).mean(axis=0))
    assert err.max() < 1e-3, f"RMS per joint, mrad: {np.round(1e3 * err, 3)}"


def test_a_replay_in_another_structure_misses_the_recording(limited, fast_recording):
    """The structures differ by far more than the replay's error: each recording told apart."""
    r, truth, ct, cmds, t, q, dq, structure = fast_recording
    every = int(round(PERIOD / r.timestep))
    for other in sorted(set(STRUCTURES) - {structure}):
        o = replay.Replay(limited, structure=STRUCTURES[other])
        state = o.state(cmds[0], np.zeros(q.shape[1]), 0.0)
        _, qo, _ = o.run(truth, state, int(round(DURATION / o.timestep)), ct, cmds, DELAY, PERIOD)
        err = np.sqrt(((qo[every - 1 :: every][: len(q)] - q) ** 2).mean(axis=0))
        assert err.max() > 3e-3, f"{other} replays a {structure} recording within {err.max():.2g} rad"


def test_the_limited_robot_runs_its_servo_as_written_unless_stated(limited, tmp_path):
    """Its robot file states gains and no structure: MuJoCo's <position> law, compensating nothing."""
    pc = _actuation.position_consts(limited)
    assert not pc.weight.any() and not pc.feedforward.any()
