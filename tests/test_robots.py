"""Robot files: validation, the composed scene, the solved poses."""

from __future__ import annotations

import os
import shutil

import mujoco
import numpy as np
import pytest

import jaxsync
from jaxsync.physics import ik
from jaxsync.physics.model import compose_robot, joints_per_arm

ROBOTS = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots")


def robot_path(name: str) -> str:
    return os.path.join(ROBOTS, name)


@pytest.fixture(scope="module")
def composed():
    return {n: compose_robot(robot_path(f"{n}.yaml")) for n in ("iiwa14_twice", "iiwa14_pair", "ur5e_twice")}


def _site(m, d, name):
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)
    return d.site_xpos[i].copy(), d.site_xmat[i].reshape(3, 3).copy()


def _at_key(m, key):
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key))
    mujoco.mj_forward(m, d)
    return d


@pytest.mark.parametrize("name,n", [("iiwa14_twice", 7), ("iiwa14_pair", 7), ("ur5e_twice", 6)])
def test_composed_scene_has_what_jaxsync_needs(composed, name, n):
    m, report = composed[name]
    assert joints_per_arm(m) == n
    assert m.nu == 2 * n and all(m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED for a in range(m.nu))
    assert all(m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE for a in range(m.nu))  # torque motors
    # only the explicit pairs collide
    assert int(((m.geom_contype != 0) | (m.geom_conaffinity != 0)).sum()) == 0 and m.npair == 3
    # jaxsync's physics
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER and m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert m.opt.timestep == 0.002
    # the object where the task frame puts it
    obj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
    np.testing.assert_allclose(m.body_pos[obj], [0.65, 0.0, 0.9])
    # the arms' own joint data kept: ranges and armature of the file
    j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "r_joint2")
    assert m.jnt_limited[j] and m.dof_armature[m.jnt_dofadr[j]] == pytest.approx(0.1)
    assert len(report.joint_names["right"]) == n


def test_torque_limits_come_from_the_file_or_the_robot_file(composed):
    _, iiwa = composed["iiwa14_twice"]
    assert iiwa.torque_limits["right"] == (320.0, 320.0, 176.0, 176.0, 110.0, 40.0, 40.0)  # position forcerange
    m, ur = composed["ur5e_twice"]
    assert ur.torque_limits["left"] == (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)  # the robot file's
    a = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, "l_motor4")
    np.testing.assert_allclose(m.actuator_ctrlrange[a], [-28.0, 28.0])
    assert any("integrator implicitfast" in note for note in iiwa.notes)


@pytest.mark.parametrize("name", ["iiwa14_twice", "ur5e_twice"])
def test_grasp_and_approach_put_both_pads_on_the_clamp_axis(composed, name):
    m, _ = composed[name]
    c = np.array([0.65, 0.0, 0.9])
    for key, gap in (("grasp", 0.0), ("approach", ik.APPROACH_GAP)):
        d = _at_key(m, key)
        (pr, Rr), (pl, Rl) = _site(m, d, "r_pad"), _site(m, d, "l_pad")
        np.testing.assert_allclose(pr, c - [0, 0.1 + gap, 0], atol=1e-5)
        np.testing.assert_allclose(pl, c + [0, 0.1 + gap, 0], atol=1e-5)
        np.testing.assert_allclose(Rr[:, 2], [0, 1, 0], atol=1e-4)  # normals into the ball
        np.testing.assert_allclose(Rl[:, 2], [0, -1, 0], atol=1e-4)
        np.testing.assert_allclose(Rr[:, 0], Rl[:, 0], atol=1e-4)  # no roll between the pads
        np.testing.assert_allclose(Rr[:, 0], [0, 0, -1], atol=1e-4)


def test_one_bimanual_file_and_one_arm_file_twice_give_the_same_scene(composed):
    (m1, r1), (m2, r2) = composed["iiwa14_twice"], composed["iiwa14_pair"]
    for key in ("grasp", "approach"):
        d1, d2 = _at_key(m1, key), _at_key(m2, key)
        for s in ("r_pad", "l_pad", "r_ft", "l_ft"):
            np.testing.assert_allclose(_site(m1, d1, s)[0], _site(m2, d2, s)[0], atol=1e-6)
    assert r1.joint_names["right"][0] == "joint1" and r2.joint_names["right"][0] == "right_joint1"
    assert np.isclose(m1.body_subtreemass[0], m2.body_subtreemass[0])  # the pair file adds two massless mounts


def _write(tmp_path, text: str, *models: str) -> str:
    for f in models:
        shutil.copy(robot_path(f), tmp_path / f)
    p = tmp_path / "robot.yaml"
    p.write_text(text)
    return str(p)


UR = """
version: 1
arms:
  right: {{model: ur5e_like_arm.xml, base: {{pos: [0, -0.4, 0]}}, joints: [shoulder_pan, shoulder_lift, elbow,
          wrist_1, wrist_2, wrist_3], flange: flange{right}}}
  left: {{model: ur5e_like_arm.xml, base: {{pos: [0, 0.4, 0]}}, joints: [shoulder_pan, shoulder_lift, elbow,
          wrist_1, wrist_2, wrist_3], flange: flange, torque_limits: [150, 150, 150, 28, 28, 28]}}
object: {{position: {position}}}
"""


def test_an_unreachable_object_is_refused_naming_the_arm_and_the_shortfall(tmp_path):
    limits = ", torque_limits: [150, 150, 150, 28, 28, 28]"
    path = _write(tmp_path, UR.format(right=limits, position="[1.8, 0, 0.35]"), "ur5e_like_arm.xml")
    with pytest.raises(jaxsync.ConfigError, match=r"arms\.right: the grasp pose is out of reach: the pad stays"):
        compose_robot(path)


def test_a_joint_without_a_torque_limit_is_named(tmp_path):
    path = _write(tmp_path, UR.format(right="", position="[0.45, 0, 0.35]"), "ur5e_like_arm.xml")
    with pytest.raises(jaxsync.ConfigError, match=r"arms\.right: joint 'shoulder_pan' has no torque limit"):
        compose_robot(path)


@pytest.mark.parametrize(
    "edit,message",
    [
        (("flange: flange,", "flange: nowhere,"), r"arms\.right\.flange: no site or body 'nowhere'"),
        (("wrist_2, wrist_3], flange: flange,", "wrist_3, wrist_2], flange: flange,"), r"one chain"),
        (("[shoulder_pan, shoulder_lift, elbow,", "[shoulder_pan, nope, elbow,"), r"no joint 'nope' in the model"),
    ],
)
def test_model_mistakes_are_named(tmp_path, edit, message):
    limits = ", torque_limits: [150, 150, 150, 28, 28, 28]"
    text = UR.format(right=limits, position="[0.45, 0, 0.35]").replace(*edit, 1)
    with pytest.raises(jaxsync.ConfigError, match=message):
        compose_robot(_write(tmp_path, text, "ur5e_like_arm.xml"))


_ARMS = ("arms: {right: {joints: [a,b,c,d,e,f], flange: f, model: arm.xml}, left: {joints: [a,b,c,d,e,f], "
         "flange: f, model: arm.xml}}\nobject: {position: [0, 0, 0]}\n")  # fmt: skip


@pytest.mark.parametrize(
    "text,message",
    [
        ("arms: {right: {}, left: {}}\nobject: {position: [0, 0, 0]}", r"arms\.right: missing 'joints'"),
        ("arms: {right: 1}\nobject: {position: [0, 0, 0]}", r"arms must have exactly the keys right and left"),
        ("arms: {right: {joints: [a, b, c], flange: f, model: arm.xml}, left: {joints: [a], flange: f, "
         "model: arm.xml}}\nobject: {position: [0, 0, 0]}", r"arms\.right\.joints must name 6 or 7 hinge joints"),
        ("arms: {right: {joints: [a,b,c,d,e,f], flange: f}, left: {joints: [a,b,c,d,e,f], flange: f}}\n"
         "object: {position: [0, 0, 0]}", r"arms\.right: missing 'model'"),
        ("colour: red\narms: {}\nobject: {}", r"unknown key\(s\) \['colour'\]"),
        ("version: 2\narms: {}\nobject: {}", r"version: this jaxsync reads robot files of version 1"),
        ("model: robot.xml\narms: {}\nobject: {}", r"model: no such MJCF file"),
        ("arms: {right: {joints: [a,b,c,d,e,f], flange: f, model: arm.xml, torque_limits: [1, 2]}, left: "
         "{joints: [a,b,c,d,e,f], flange: f, model: arm.xml}}\nobject: {position: [0, 0, 0]}",
         r"torque_limits must be 6 numbers"),
        ("arms: {right: {joints: [a,b,c,d,e,f], flange: f, model: arm.xml}, left: {joints: [a,b,c,d,e,f], "
         "flange: f, model: arm.xml}}\nobject: {position: [0, 0, 0], radius: 2}", r"object\.radius must be a number"),
        ("clamp_axis: [0, 0, 1]\narms: {right: {joints: [a,b,c,d,e,f], flange: f, model: arm.xml}, left: "
         "{joints: [a,b,c,d,e,f], flange: f, model: arm.xml}}\nobject: {position: [0, 0, 0]}",
         r"clamp_axis must be horizontal"),
        (_ARMS + "end_effector: {mass: 0}", r"end_effector\.mass must be a number in \[0\.01, 20\.0\] kg"),
        (_ARMS + "end_effector: {weight: 1}", r"end_effector: unknown key\(s\) \['weight'\]"),
        (_ARMS + "end_effector: {inertia: [1, 1, 3]}", r"end_effector\.inertia must be three positive"),
        (_ARMS + "end_effector: {com: [0, 0, 1]}", r"end_effector\.com must lie within 0\.5 m"),
        (_ARMS + "end_effector: {pad_offset: 0.001}", r"end_effector\.pad_offset must be a number in"),
        (_ARMS + "end_effector: 0.3", r"end_effector must be \{mass: kg"),
    ],
)  # fmt: skip
def test_robot_file_mistakes_name_the_key(tmp_path, text, message):
    (tmp_path / "arm.xml").write_text("<mujoco/>")
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(jaxsync.ConfigError, match=message):
        jaxsync.load_robot(str(p))


def test_missing_meshes_load_with_no_visual(tmp_path):
    arm = open(robot_path("ur5e_like_arm.xml")).read()
    arm = arm.replace("<worldbody>", '<asset><mesh name="shell" file="missing_shell.stl"/></asset>\n  <worldbody>')
    arm = arm.replace('<geom fromto="0 0 0 0 0 0.425"/>', '<geom fromto="0 0 0 0 0 0.425"/><geom type="mesh" '
                      'mesh="shell" contype="0" conaffinity="0"/>')  # fmt: skip
    (tmp_path / "ur5e_like_arm.xml").write_text(arm)
    limits = ", torque_limits: [150, 150, 150, 28, 28, 28]"
    p = tmp_path / "robot.yaml"
    p.write_text(UR.format(right=limits, position="[0.45, 0, 0.35]"))
    with pytest.raises(jaxsync.ModelFileError, match="--no-visual"):
        compose_robot(str(p))
    m, _ = compose_robot(str(p), visual=False)
    assert joints_per_arm(m) == 6 and m.nmesh == 0


# ------------------------------------------------------------- rollouts on a robot


UR5E_DURATION = 2.0


def _ur5e():
    return jaxsync.load_model(robot_path("ur5e_twice.yaml"))


def compile_ahead():
    """The UR5e-like pair's rollout (tests/conftest.py: compiled ahead in a second process)."""
    from jaxsync.control import gains as G

    ur5e = _ur5e()
    jaxsync.rollout(ur5e, G.default_gains(ur5e), jaxsync.short_task(), duration=UR5E_DURATION).time.block_until_ready()


@pytest.fixture(scope="module")
def ur5e():
    return _ur5e()


def test_a_6_dof_robot_holds_the_ball_and_the_chatter_metric_tells_its_gains_apart(ur5e):
    """The UR5e-like pair at the paper model's defaults (stability ratio 0.87)
    chatters; at its own defaults (ratio 1.5) it holds the ball without."""
    from jaxsync.control import gains as G
    from jaxsync.physics.inertia import pad_apparent_inertia

    lam = pad_apparent_inertia(ur5e.mj_model)
    dt = float(ur5e.mj_model.opt.timestep)
    own = G.default_gains(ur5e)
    np.testing.assert_allclose(G.stability_ratio(own, lam, dt), G.STABILITY_MARGIN)
    assert np.all(G.stability_ratio(G.default_gains(), lam, dt) < 1)
    s = jaxsync.short_task()
    # rollout()'s program, the one the MuJoCo C comparison below runs too (one compile for both tests)
    m_own = jaxsync.summarize(jaxsync.rollout(ur5e, own, s, duration=UR5E_DURATION), s)
    m_paper = jaxsync.summarize(jaxsync.rollout(ur5e, G.default_gains(), s, duration=UR5E_DURATION), s)
    assert not bool(m_own.dropped) and not bool(m_own.chattering), float(m_own.force_chatter_N)
    assert float(m_own.force_chatter_N) < 0.5
    assert bool(m_paper.chattering) and float(m_paper.force_chatter_N) > 5.0
    assert abs(float(m_own.mean_grip_force_N) - float(s.grip_force)) < 0.5


def test_a_robots_composed_scene_runs_the_same_on_mujoco_c(ur5e):
    from jaxsync.control import gains as G

    s = jaxsync.short_task()
    g = G.default_gains(ur5e)
    x = jaxsync.rollout(ur5e, g, s, duration=UR5E_DURATION)
    c = jaxsync.rollout_mujoco(ur5e, g, s, duration=UR5E_DURATION)
    assert float(np.abs(np.asarray(c.obj_pos) - np.asarray(x.obj_pos)).max()) < 1e-3
    mx, mc = jaxsync.summarize(x, s), jaxsync.summarize(c, s)
    assert abs(float(mx.mean_grip_force_N) - float(mc.mean_grip_force_N)) < 0.05
    assert not bool(mc.dropped) and not bool(mc.chattering)


@pytest.mark.parametrize("name", ["iiwa14_twice", "ur5e_twice"])
def test_the_grasp_leaves_every_joint_room_to_move(composed, name):
    """A grasp with a joint at its range's margin could not squeeze or lift
    (found: an iiwa-like grasp with joint 2 at 1.994 of 2.094 rad dropped the ball)."""
    m, report = composed[name]
    for arm, side in (("right", "r"), ("left", "l")):
        q = np.asarray(report.poses[arm]["grasp_q"])
        for k, qk in enumerate(q, start=1):
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{side}_joint{k}")
            if m.jnt_limited[j]:
                lo, hi = m.jnt_range[j]
                margin = min(ik.MARGIN, 0.05 * (hi - lo))
                assert lo + margin + 1e-4 < qk < hi - margin - 1e-4, (arm, k, qk)


def test_the_end_effector_is_the_robot_files_and_unstated_is_the_documented_default(tmp_path):
    """The end effector jaxsync adds is what the robot file states (mass, centre of
    mass, inertia, pad face): the composed scene carries it and the summary says it;
    stating the documented default changes nothing in the scene."""
    src = open(robot_path("ur5e_twice.yaml")).read()
    for name, extra in (
        ("stated_default", "end_effector: {mass: 0.3, com: [0, 0, 0.02], inertia: [0.0003, 0.0003, 0.0004], "
                           "pad_offset: 0.036}\n"),
        ("heavy", "end_effector: {mass: 1.2, com: [0, 0.01, 0.05], pad_offset: 0.08}\n"),
    ):  # fmt: skip
        text = src.replace("ur5e_like_arm.xml", os.path.join(ROBOTS, "ur5e_like_arm.xml"))
        (tmp_path / f"{name}.yaml").write_text(text + extra)
    plain = compose_robot(robot_path("ur5e_twice.yaml"), visual=False)
    stated = compose_robot(str(tmp_path / "stated_default.yaml"), visual=False)
    heavy = compose_robot(str(tmp_path / "heavy.yaml"), visual=False)
    assert stated[1].fingerprint == plain[1].fingerprint
    assert plain[1].summary()["end_effector"] == {
        "mass_kg": 0.3, "com_m": [0.0, 0.0, 0.02], "inertia_kg_m2": [0.0003, 0.0003, 0.0004], "pad_offset_m": 0.036
    }  # fmt: skip
    m, scene = heavy
    assert scene.fingerprint != plain[1].fingerprint
    assert scene.summary()["end_effector"]["mass_kg"] == 1.2
    for p in ("r", "l"):
        ee = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"{p}_ee")
        assert m.body_mass[ee] == pytest.approx(1.2)
        np.testing.assert_allclose(m.body_ipos[ee], [0, 0.01, 0.05])
        np.testing.assert_allclose(m.body_inertia[ee], [0.0003, 0.0003, 0.0004])
        d = _at_key(m, "grasp")
        flange, R = _site(m, d, f"{p}_flange")
        pad, _ = _site(m, d, f"{p}_pad")
        assert (pad - flange) @ R[:, 2] == pytest.approx(0.08) and np.linalg.norm(pad - flange) == pytest.approx(0.08)
    # the grasp is solved for the longer end effector: the pads still touch the ball
    d = _at_key(m, "grasp")
    centre = d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")]
    for p in ("r", "l"):
        assert np.linalg.norm(_site(m, d, f"{p}_pad")[0] - centre) == pytest.approx(scene.object_radius, abs=2e-3)
