"""Composing robot files in the robot's own names: actuators, exported names,
the flange's direction, MuJoCo's messages, the joints named in errors."""

from __future__ import annotations

import os
import warnings

import pytest
import yaml

import jaxsync
from jaxsync.io import export as _export
from jaxsync.physics.compose import compose
from jaxsync.physics.model import compose_robot

ROBOTS = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots")
IIWA = os.path.join(ROBOTS, "iiwa14_like_arm.xml")
UR = os.path.join(ROBOTS, "ur5e_like_arm.xml")
UR_JOINTS = "[shoulder_pan, shoulder_lift, elbow, wrist_1, wrist_2, wrist_3]"
UR_LIMITS = "[150, 150, 150, 28, 28, 28]"


def _twice(tmp_path, model: str, joints: str, flange: str, position="[0.6, 0, 0.45]", right="", left="") -> str:
    p = tmp_path / "robot.yaml"
    p.write_text(
        f"version: 1\narms:\n"
        f"  right: {{model: {model}, base: {{pos: [0, -0.45, 0]}}, joints: {joints}, flange: {flange}{right}}}\n"
        f"  left: {{model: {model}, base: {{pos: [0, 0.45, 0]}}, joints: {joints}, flange: {flange}{left}}}\n"
        f"object: {{position: {position}}}\n"
    )
    return str(p)


def _iiwa_twice(tmp_path, right="", left="", flange="attachment_site", model=IIWA) -> str:
    joints = "[" + ", ".join(f"joint{k}" for k in range(1, 8)) + "]"
    return _twice(tmp_path, model, joints, flange, right=right, left=left)


# ------------------------------------------------------------------ actuators


def test_actuators_are_the_names_of_the_arm_file(tmp_path):
    acts = "[" + ", ".join(f"a{k}" for k in range(1, 8)) + "]"
    c = compose(jaxsync.load_robot(_iiwa_twice(tmp_path, right=f", actuators: {acts}", left=f", actuators: {acts}")))
    assert c.torque_limits["right"] == (320.0, 320.0, 176.0, 176.0, 110.0, 40.0, 40.0)
    swapped = acts.replace("a1, a2", "a2, a1")
    with pytest.raises(jaxsync.ConfigError, match=r"arms\.right\.actuators: 'a2' does not drive joint 'joint1'"):
        compose(jaxsync.load_robot(_iiwa_twice(tmp_path, right=f", actuators: {swapped}")))
    with pytest.raises(jaxsync.ConfigError, match=r"no actuator 'b1' in the model; the arm's actuators: \['a1', "):
        compose(jaxsync.load_robot(_iiwa_twice(tmp_path, left=f", actuators: {acts.replace('a1', 'b1')}")))


def test_actuators_of_a_bimanual_file_are_its_own_names(tmp_path):
    arm = "{{joints: [{j}], flange: {s}_attachment_site, actuators: [{a}]}}"
    text = "version: 1\nmodel: {f}\narms:\n  right: {r}\n  left: {l}\nobject: {{position: [0.6, 0, 0.45]}}\n"
    side = {
        s: arm.format(j=", ".join(f"{s}_joint{k}" for k in range(1, 8)), s=s,
                      a=", ".join(f"{s}_a{k}" for k in range(1, 8)))
        for s in ("right", "left")
    }  # fmt: skip
    p = tmp_path / "pair.yaml"
    p.write_text(text.format(f=os.path.join(ROBOTS, "iiwa14_pair.xml"), r=side["right"], l=side["left"]))
    c = compose(jaxsync.load_robot(str(p)))
    assert c.torque_limits["left"] == (320.0, 320.0, 176.0, 176.0, 110.0, 40.0, 40.0)


# ------------------------------------------------------------------ ROS names


def test_a_ros_prefix_per_arm_names_every_exported_joint_and_link(tmp_path):
    path = _twice(tmp_path, UR, UR_JOINTS, "flange", "[0.45, 0, 0.35]",
                  right=f", torque_limits: {UR_LIMITS}, ros_prefix: right_",
                  left=f", torque_limits: {UR_LIMITS}, ros_prefix: left_")  # fmt: skip
    m, report = compose_robot(path)
    _export.export(
        jaxsync.default_gains(),
        "ros2-admittance",
        str(tmp_path / "out"),
        _export.ros2_target(m, report, compliance_at="flange"),
    )
    for arm in ("right", "left"):
        doc = yaml.safe_load(open(tmp_path / "out" / f"admittance_{arm}.yaml"))
        params = doc[f"admittance_controller_{arm}"]["ros__parameters"]
        assert params["joints"] == [f"{arm}_{j}" for j in UR_JOINTS[1:-1].split(", ")]
        assert params["kinematics"]["base"] == f"{arm}_base" and params["kinematics"]["tip"] == f"{arm}_wrist_3_link"
        for frame in ("ft_sensor", "control", "gravity_compensation"):
            assert params[frame]["frame"]["id"] == f"{arm}_wrist_3_link"
        assert params["fixed_world_frame"]["frame"]["id"] == f"{arm}_base"


@pytest.mark.parametrize(
    "prefix,message",
    [("3arm_", r"arms\.right\.ros_prefix must be a ROS name prefix"), ("[a]", r"ros_prefix must be a ROS name")],
)
def test_a_bad_ros_prefix_is_named(tmp_path, prefix, message):
    with pytest.raises(jaxsync.ConfigError, match=message):
        jaxsync.load_robot(_iiwa_twice(tmp_path, right=f", ros_prefix: {prefix}"))


# ------------------------------------------------------------------ the flange's direction


def _arm_with_site(tmp_path, site: str) -> str:
    text = open(IIWA).read().replace('<site name="attachment_site"', site + '\n<site name="attachment_site"')
    (tmp_path / "arm.xml").write_text(text)
    return str(tmp_path / "arm.xml")


def test_a_flange_facing_back_into_the_arm_is_refused(tmp_path):
    model = _arm_with_site(tmp_path, '<site name="backwards" pos="0 0 0.045" quat="0 1 0 0"/>')
    with pytest.raises(jaxsync.ConfigError, match=r"arms\.right\.flange 'backwards': its \+z points back into the arm"):
        compose(jaxsync.load_robot(_iiwa_twice(tmp_path, flange="backwards", model=model)))


def test_a_pad_that_would_put_the_arm_into_the_object_is_refused(tmp_path):
    """A flange turned sideways passes the arm's check; at the grasp its wrist is in the ball."""
    model = _arm_with_site(tmp_path, '<site name="sideways" quat="0.7071068 0 0.7071068 0"/>')
    with pytest.raises(jaxsync.ConfigError, match=r"arms\.right: at the grasp the arm's body 'link\d' is inside"):
        compose_robot(_iiwa_twice(tmp_path, flange="sideways", model=model))


def test_an_unknown_flange_lists_what_could_be_meant(tmp_path):
    with pytest.raises(jaxsync.ConfigError) as err:
        compose(jaxsync.load_robot(_iiwa_twice(tmp_path, flange="attachment")))
    text = str(err.value)
    assert "arms.right.flange: no site or body 'attachment'" in text and "did you mean 'attachment_site'" in text
    assert "the arm's last bodies: ['link5', 'link6', 'link7']" in text and "sites on them: ['attachment_site']" in text


# ------------------------------------------------------------------ MuJoCo's messages


def test_a_file_with_size_attributes_composes_quietly_with_one_note(tmp_path, monkeypatch, capfd):
    text = open(UR).read().replace("<worldbody>", '<size nkey="1" memory="20M" nuserdata="3"/>\n  <worldbody>', 1)
    (tmp_path / "arm.xml").write_text(text)
    path = _twice(tmp_path, "arm.xml", UR_JOINTS, "flange", "[0.45, 0, 0.35]", right=f", torque_limits: {UR_LIMITS}",
                  left=f", torque_limits: {UR_LIMITS}")  # fmt: skip
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, report = compose_robot(path)
    assert os.listdir(work) == []  # no MUJOCO_LOG.TXT
    assert "Attach conflict" not in capfd.readouterr().err
    sizes = [n for n in report.notes if "<size>" in n]
    assert sizes == ["the robot's file sets <size> memory, nkey, nuserdata; the task scene sizes its own"]


# ------------------------------------------------------------------ the robot's joint names in messages


def test_joint_limits_are_named_as_in_the_robot_file(tmp_path):
    text = open(UR).read().replace('name="elbow" axis="0 1 0" range="-3.1416 3.1416"',
                                   'name="elbow" axis="0 1 0" range="-0.3 0.3"')  # fmt: skip
    (tmp_path / "arm.xml").write_text(text)
    path = _twice(tmp_path, "arm.xml", UR_JOINTS, "flange", "[0.45, 0, 0.35]", right=f", torque_limits: {UR_LIMITS}",
                  left=f", torque_limits: {UR_LIMITS}")  # fmt: skip
    with pytest.raises(jaxsync.ConfigError, match=r"joint limits binding: .*elbow \(upper\)") as err:
        compose_robot(path)
    assert "r_joint" not in str(err.value)


def test_a_weak_joint_is_named_as_in_the_robot_file(tmp_path):
    weak = ", torque_limits: [150, 5, 150, 28, 28, 28]"
    path = _twice(tmp_path, UR, UR_JOINTS, "flange", "[0.45, 0, 0.35]", right=weak, left=weak)
    with pytest.raises(jaxsync.ConfigError, match=r"% of the torque limit of joint 'shoulder_lift' statically"):
        compose_robot(path)
