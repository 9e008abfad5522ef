"""The ros2-admittance files against the admittance controller's parameter definition.

The facts below are ros2_controllers' ``admittance_controller/src/
admittance_controller_parameters.yaml`` as published (jazzy ed360c97 and
master 94e74de3 identical, last changed in a048212b; humble ad559d9c, which
adds ``robot_description``), written out here by hand: the test fails when
the export drops a parameter the controller has no default for, writes one of
the wrong type or length, or leaves a bound.
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import pytest
import yaml

import jaxsync
from jaxsync.cli import main
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io import ros2_target as ros2_target_mod

# name -> (type, fixed size or None); every one of these has no default
NO_DEFAULT = {
    "joints": ("string_array", None),
    "command_interfaces": ("string_array", None),
    "state_interfaces": ("string_array", None),
    "kinematics.plugin_name": ("string", None),
    "kinematics.plugin_package": ("string", None),
    "kinematics.base": ("string", None),
    "kinematics.tip": ("string", None),
    "ft_sensor.name": ("string", None),
    "ft_sensor.frame.id": ("string", None),
    "control.frame.id": ("string", None),
    "fixed_world_frame.frame.id": ("string", None),
    "gravity_compensation.frame.id": ("string", None),
    "gravity_compensation.CoG.pos": ("double_array", 3),
    "admittance.selected_axes": ("bool_array", 6),
    "admittance.mass": ("double_array", 6),
    "admittance.damping_ratio": ("double_array", 6),
    "admittance.stiffness": ("double_array", 6),
}
HUMBLE_NO_DEFAULT = {"robot_description": ("string", None)}
WITH_DEFAULT = {
    "command_joints": "string_array",
    "chainable_command_interfaces": "string_array",
    "kinematics.alpha": "double",
    "ft_sensor.filter_coefficient": "double",
    "gravity_compensation.CoG.force": "double",
    "admittance.joint_damping": "double",
    "enable_parameter_update_without_reactivation": "bool",
}
BOUNDS = {"admittance.mass": (0.0001, 1e6), "admittance.stiffness": (0.0, 1e8), "admittance.joint_damping": (0.0, None)}


def _get(params, dotted):
    for part in dotted.split("."):
        if not isinstance(params, dict) or part not in params:
            return KeyError
        params = params[part]
    return params


def _has_type(v, kind: str, size) -> bool:
    scalar = {"string": str, "double": float, "bool": bool}
    if kind.endswith("_array"):
        item = scalar[kind.removesuffix("_array")]
        ok = isinstance(v, list) and all(isinstance(x, item) and not (item is float and isinstance(x, bool)) for x in v)
        return ok and (size is None or len(v) == size) and len(v) > 0
    if kind == "double":
        return isinstance(v, float | int) and not isinstance(v, bool)
    return isinstance(v, scalar[kind])


def _check(path: str, distro: str, n_joints: int):
    doc = yaml.safe_load(open(path))
    (name,) = [k for k in doc if k != "controller_manager"]
    entry = doc["controller_manager"]["ros__parameters"][name]
    assert entry["type"] == "admittance_controller/AdmittanceController"
    params = doc[name]["ros__parameters"]
    required = {**NO_DEFAULT, **(HUMBLE_NO_DEFAULT if distro == "humble" else {})}
    for key, (kind, size) in required.items():
        v = _get(params, key)
        assert v is not KeyError, f"{path}: {key} (no default) missing"
        assert _has_type(v, kind, size), f"{path}: {key} = {v!r} is not a {kind} of size {size}"
    for key, kind in WITH_DEFAULT.items():
        v = _get(params, key)
        assert v is KeyError or _has_type(v, kind, None), f"{path}: {key} = {v!r} is not a {kind}"
    for key, (lo, hi) in BOUNDS.items():
        v = np.atleast_1d(np.asarray(_get(params, key), dtype=float))
        assert np.all(v >= lo) and (hi is None or np.all(v <= hi)), f"{path}: {key} out of bounds"
    assert len(params["joints"]) == n_joints
    assert params["ft_sensor"]["filter_coefficient"] == 1.0  # unfiltered, as simulated
    assert params["kinematics"]["plugin_package"] == "kinematics_interface"
    assert params["kinematics"]["alpha"] == 0.01  # the damped least squares' alpha the position stack runs
    if distro == "humble":
        assert params["alpha"] == 0.01  # what Humble's KDL plugin reads
    if distro == "humble":
        assert "wrench_reference" not in open(path).read().split("Humble")[0]
    return params


@pytest.mark.parametrize("robot,n", [("ur5e_twice.yaml", 6), ("iiwa14_pair.yaml", 7)])
@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_every_written_file_holds_against_the_parameter_definition(tmp_path, capsys, robot, n, distro):
    path = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots", robot)
    out = tmp_path / "ros2"
    argv = ["export", "--format", "ros2-admittance", "--robot", path, "--ros-distro", distro, "--out", str(out)]
    assert main([*argv, "--actuation", "position"]) == 0  # the defaults the admittance rule runs stably
    said = capsys.readouterr().out
    assert ("note: Humble's admittance controller has no wrench set-point" in said) is (distro == "humble")
    for arm in ("right", "left"):
        params = _check(str(out / f"admittance_{arm}.yaml"), distro, n)
    robot_doc = yaml.safe_load(open(path))
    # the robot's own names, not jaxsync's; one arm file used twice: each arm's prefixed (right_, left_)
    prefix = "left_" if "model" in robot_doc["arms"]["left"] else ""
    assert params["joints"] == [prefix + j for j in robot_doc["arms"]["left"]["joints"]]
    assert params["kinematics"]["tip"] != "l_ee" and params["control"]["frame"]["id"] == params["kinematics"]["tip"]


def test_the_pad_axes_travel_to_the_flange_links_axes_and_back(tmp_path):
    """The UR5e-like flange site is turned -90 deg about x on its link: the pad's
    normal (z) is the link's y, so the normal-axis values sit in column y."""
    path = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots", "ur5e_twice.yaml")
    model = jaxsync.load_model(path)
    g = jaxsync.default_gains()
    g = g._replace(imp_mass=g.imp_mass.at[:, 2].set(7.0), imp_stiffness=g.imp_stiffness.at[:, 5].set(33.0))
    target = _export.ros2_target(model.mj_model, model.robot, compliance_at="flange")
    assert target.arms[0].axes == (0, 2, 1, 3, 5, 4)
    _export.export(g, "ros2-admittance", str(tmp_path), target)
    adm = yaml.safe_load(open(tmp_path / "admittance_right.yaml"))["admittance_controller_right"]["ros__parameters"]
    assert adm["admittance"]["mass"][1] == 7.0 and adm["admittance"]["stiffness"][4] == 33.0
    back = gains_file.load(tmp_path)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(g), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14)
    # the mass per base axis (Jazzy: the pad's x lies along the base's z at the grasp), in the control
    # frame on Rolling (the pad's x is the flange link's x); both read back to the same gains
    g = g._replace(imp_mass=g.imp_mass.at[:, 0].set(5.0))
    for distro, at in (("jazzy", 2), ("rolling", 0)):
        out = tmp_path / distro
        _export.export(g, "ros2-admittance", str(out), dataclasses.replace(target, distro=distro))
        doc = yaml.safe_load(open(out / "admittance_right.yaml"))["admittance_controller_right"]["ros__parameters"]
        mass = doc["admittance"]["mass"]
        assert mass[at] == 5.0 and mass.count(5.0) == 1 and mass[1] == 7.0, (distro, mass)
        assert gains_file.same_gains(gains_file.load(out), g)


def test_the_paper_models_files_load_too_and_bad_options_are_named(tmp_path, capsys):
    params = None
    _export.export(jaxsync.default_gains(), "ros2-admittance", str(tmp_path))
    params = _check(str(tmp_path / "admittance_right.yaml"), "jazzy", 7)
    assert params["kinematics"]["base"] == "torso" and params["kinematics"]["tip"] == "right_jaxsync_pad"
    rc = main(["export", "--format", "ros2-admittance", "--out", str(tmp_path / "x"), "--command-interfaces", "effort"])
    err = capsys.readouterr().err
    assert (
        rc == 2 and "command_interfaces must name position and/or velocity" in err and "(--command-interfaces)" in err
    )
    rc = main(["export", "--format", "yaml", "--out", str(tmp_path / "y")])
    assert rc == 0 and "from the default gains of the paper model" in capsys.readouterr().out
    assert gains_file.same_gains(gains_file.load(str(tmp_path / "y" / "gains.yaml")), jaxsync.default_gains())


def test_the_compliance_can_be_centred_at_the_pad(tmp_path):
    """--compliance-at pad: the files name a pad link as tip, control, sensor and
    gravity frame, in jaxsync's pad axes; pad_links.urdf fixes it to the flange
    link where the model's pad is; the sensor's tool transform is the pad in
    the sensor frame; the gains read back bit for bit."""
    import xml.etree.ElementTree as ET  # noqa: PLC0415 -- this test alone reads URDF

    import mujoco  # noqa: PLC0415 -- the model's own pad and flange poses

    path = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots", "ur5e_twice.yaml")
    model = jaxsync.load_model(path, visual=False)
    g = jaxsync.default_gains(model, "position")
    out = tmp_path / "pad"
    argv = ["export", "--format", "ros2-admittance", "--robot", path, "--no-visual", "--actuation", "position"]
    assert main([*argv, "--compliance-at", "pad", "--out", str(out)]) == 0
    m, d = model.mj_model, mujoco.MjData(model.mj_model)
    mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "grasp"))
    mujoco.mj_kinematics(m, d)
    joints = {j.find("child").get("link"): j for j in ET.parse(out / "pad_links.urdf").getroot().iter("joint")}
    for arm, side in ((0, "r"), (1, "l")):
        name = ("right", "left")[arm]
        p = yaml.safe_load(open(out / f"admittance_{name}.yaml"))[f"admittance_controller_{name}"]["ros__parameters"]
        pad_link = p["kinematics"]["tip"]
        assert pad_link == f"{name}_jaxsync_pad" and pad_link in joints
        assert p["control"]["frame"]["id"] == p["ft_sensor"]["frame"]["id"] == pad_link
        assert p["gravity_compensation"]["frame"]["id"] == pad_link
        assert p["admittance"]["stiffness"] == np.asarray(g.imp_stiffness)[arm].tolist()  # the pad's axis order
        # the fixed joint puts the pad link where the model's pad is, in the flange link's frame
        ee = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"{side}_ee")
        tip = int(m.body_parentid[ee])
        pad = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{side}_pad")
        origin = joints[pad_link].find("origin")
        xyz = np.array(origin.get("xyz").split(), dtype=float)
        roll, pitch, yaw = np.array(origin.get("rpy").split(), dtype=float)
        R_tip = d.xmat[tip].reshape(3, 3)
        np.testing.assert_allclose(xyz, R_tip.T @ (d.site_xpos[pad] - d.xpos[tip]), atol=1e-9)
        np.testing.assert_allclose(_rpy_matrix(roll, pitch, yaw), R_tip.T @ d.site_xmat[pad].reshape(3, 3), atol=1e-9)
        assert abs(xyz[1]) == pytest.approx(0.1356, abs=1e-4)  # the UR5e-like pad sits 0.136 m out
    text = open(out / "admittance_right.yaml").read()
    assert "transform xyz [0, 0, 0.036] m, rpy [0, 0, 0] rad" in text  # the pad 36 mm out from the wrist sensor
    assert gains_file.same_gains(gains_file.load(out), g, rtol=0.0)
    with pytest.raises(SystemExit):
        main([*argv, "--compliance-at", "tcp", "--out", str(tmp_path / "x")])


def _rpy_matrix(roll, pitch, yaw):
    c, s = np.cos, np.sin
    rx = np.array([[1, 0, 0], [0, c(roll), -s(roll)], [0, s(roll), c(roll)]])
    ry = np.array([[c(pitch), 0, s(pitch)], [0, 1, 0], [-s(pitch), 0, c(pitch)]])
    rz = np.array([[c(yaw), -s(yaw), 0], [s(yaw), c(yaw), 0], [0, 0, 1]])
    return rz @ ry @ rx


def test_urdf_angles_rebuild_the_rotation():
    rng = np.random.default_rng(3)
    for angles in [rng.uniform(-3, 3, 3) for _ in range(20)] + [(0.3, np.pi / 2, 0.0), (0.2, -np.pi / 2, 0.0)]:
        R = _rpy_matrix(*angles)
        np.testing.assert_allclose(_rpy_matrix(*ros2_target_mod.rpy_of(R)), R, atol=1e-12)


def test_the_files_carry_the_ft_filter_the_gains_were_tuned_with(tmp_path, capsys):
    argv = ["export", "--format", "ros2-admittance", "--actuation", "position"]
    assert main([*argv, "--ft-filter", "0.2", "--out", str(tmp_path / "f")]) == 0
    doc = yaml.safe_load(open(tmp_path / "f" / "admittance_left.yaml"))["admittance_controller_left"]
    assert doc["ros__parameters"]["ft_sensor"]["filter_coefficient"] == 0.2
    assert main([*argv, "--ft-filter", "0.1:1", "--out", str(tmp_path / "r")]) == 2
    assert "one coefficient here" in capsys.readouterr().err and not (tmp_path / "r").exists()


def test_gains_not_tuned_through_the_rule_are_exported_with_a_warning(tmp_path, capsys):
    """A ros2-admittance export of gains tuned for jaxsync's own law says the rule may run them
    otherwise and how to check; gains tuned through the rule are exported without it."""
    argv = ["export", "--format", "json", "--actuation", "position", "--out", str(tmp_path / "j")]
    assert main(argv) == 0
    path = next((tmp_path / "j").glob("*.json"))
    capsys.readouterr()
    for controller, warned in (("classical", True), ("ros2_admittance", False)):
        doc = json.loads(path.read_text()) | {"controller": controller}
        tuned = tmp_path / f"{controller}.json"
        tuned.write_text(json.dumps(doc))
        assert main(["export", str(tuned), "--format", "ros2-admittance", "--out", str(tmp_path / controller)]) == 0
        said = capsys.readouterr().out
        assert ("tuned for jaxsync's classical law, not through the admittance rule" in said) is warned, said
        assert ("--controllers ros2_admittance --gains " + str(tuned) in said) is warned


def test_gains_tuned_through_the_rule_export_the_control_rate_they_were_tuned_at(tmp_path, capsys):
    """A gains file that records the rule's control period (jaxsync tune through the rule) exports
    that rate as update_rate and is checked at it (the position stack's defaults, within the margin
    at 2 ms, are not at 4 ms); a period of no whole Hz is refused by name."""
    from jaxsync.control import gains as _gains  # noqa: PLC0415
    from jaxsync.control import schedule as _schedule  # noqa: PLC0415

    defaults = jaxsync.default_gains(jaxsync.load_model(visual=False), "position")

    def tuned_at(period, gains, name):
        record = {"deployed_rule": {"control_period_s": period, "margin": 1.5}} if period else {}
        doc = {"gains": _schedule.to_file_dict(gains), "controller": "ros2_admittance", "tune": record}
        (tmp_path / name).write_text(json.dumps(doc))
        return str(tmp_path / name)

    def export(path, out):
        return main(["export", path, "--format", "ros2-admittance", "--out", str(tmp_path / out)])

    capsys.readouterr()
    assert export(tuned_at(0.004, defaults, "slow.json"), "slow") == 2
    assert "unstable" in (err := capsys.readouterr().err) and "at dt = 0.004 s" in err
    for period, rate in ((0.004, 250), (None, 500)):
        gains = _gains.deployable_gains(defaults, period) if period else defaults
        assert export(tuned_at(period, gains, f"tuned_{rate}.json"), f"r{rate}") == 0
        for side in ("left", "right"):
            manager = yaml.safe_load(open(tmp_path / f"r{rate}" / f"admittance_{side}.yaml"))["controller_manager"]
            assert manager["ros__parameters"]["update_rate"] == rate
    capsys.readouterr()
    assert export(tuned_at(0.003, defaults, "odd.json"), "odd") == 2
    assert "control period of 0.003 s, which is no whole number of Hz" in capsys.readouterr().err


def test_a_coupling_not_tuned_through_the_rule_is_exported_with_a_warning(tmp_path, capsys):
    """synchronisation.yaml couples the two rules: with nonzero factors not
    tuned through the coupled rule (ros2_synchronous), it and the notes say
    so and how to check; tuned through it, or with every factor zero, not."""
    argv = ["export", "--format", "json", "--actuation", "position", "--out", str(tmp_path / "j")]
    assert main(argv) == 0
    doc = json.loads(next((tmp_path / "j").glob("*.json")).read_text())
    capsys.readouterr()
    uncoupled = json.loads(json.dumps(doc))
    for k in ("k_rk", "k_lk", "k_rl", "k_ll"):
        uncoupled["jaxsync_gains"]["gains"][k]["value"] = 0.0
    for name, base, controller, warned in (
        ("synchronous", doc, "synchronous", True),
        ("ros2_admittance", doc, "ros2_admittance", True),
        ("ros2_synchronous", doc, "ros2_synchronous", False),
        ("uncoupled", uncoupled, "ros2_admittance", False),
    ):
        tuned = tmp_path / f"{name}.json"
        tuned.write_text(json.dumps(base | {"controller": controller}))
        assert main(["export", str(tuned), "--format", "ros2-admittance", "--out", str(tmp_path / name)]) == 0
        said = capsys.readouterr().out
        head = (tmp_path / name / "synchronisation.yaml").read_text().splitlines()[0]
        assert ("coupling (k_rk, k_lk, k_rl, k_ll) was not tuned" in said) is warned, said
        assert head.startswith("# WARNING: synchronisation.yaml's coupling") is warned, head
        assert ("--controllers ros2_synchronous --gains " + str(tuned) in said) is warned
        assert yaml.safe_load((tmp_path / name / "synchronisation.yaml").read_text())  # still YAML


ANGLE = np.deg2rad(25.0)


@pytest.fixture(scope="module")
def angled(tmp_path_factory):
    """The iiwa-like arm twice, each base turned 25 deg about x toward the middle (a torso's angled mounts)."""
    robots = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots")
    doc = yaml.safe_load(open(os.path.join(robots, "iiwa14_twice.yaml")))
    for side, sign in (("right", 1.0), ("left", -1.0)):
        arm = doc["arms"][side]
        arm["model"] = os.path.join(robots, arm["model"])
        arm["base"]["quat"] = [float(np.cos(ANGLE / 2)), float(sign * np.sin(ANGLE / 2)), 0.0, 0.0]
    path = tmp_path_factory.mktemp("angled") / "angled.yaml"
    path.write_text(yaml.safe_dump(doc))
    return jaxsync.load_model(str(path), visual=False)


def _grasp_frames(model, side: str):
    """(the arm's base link rotation, the pad rotation), world frame, at the grasp: from the model itself."""
    import mujoco  # noqa: PLC0415 -- the model's own poses

    m, d = model.mj_model, mujoco.MjData(model.mj_model)
    mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "grasp"))
    mujoco.mj_kinematics(m, d)
    joint = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{side}_joint1")
    base = int(m.body_parentid[m.jnt_bodyid[joint]])
    pad = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{side}_pad")
    return d.xmat[base].reshape(3, 3), d.site_xmat[pad].reshape(3, 3)


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling", "humble"])
def test_arms_mounted_at_an_angle_export_for_every_release(angled, tmp_path, distro):
    """The loop applies the rule's mass per world axis and gravity along the world's z: the files name a
    world-aligned link fixed to each turned base link as kinematics.base and fixed_world_frame (Humble,
    whose KDL plugin roots the chain at the URDF's root, names the root 'world' and says so); the mass
    written on each base axis is the tuned mass of the pad axis along it; the gains read back."""
    import xml.etree.ElementTree as ET  # noqa: PLC0415 -- this test alone reads URDF

    from jaxsync.io.export_gains import export_gains  # noqa: PLC0415 -- the job under test

    g = jaxsync.default_gains(angled, "position")
    g = g._replace(imp_mass=jax.numpy.asarray(g.imp_mass).at[:, 0].set(5.0))  # one mass per axis, told apart
    out = tmp_path / distro
    r = export_gains(g, "ros2-admittance", str(out), model=angled, distro=distro)
    assert r.same
    urdf = {j.find("child").get("link"): j for j in ET.parse(out / "pad_links.urdf").getroot().iter("joint")}
    for arm, (name, side) in enumerate((("right", "r"), ("left", "l"))):
        p = yaml.safe_load(open(out / f"admittance_{name}.yaml"))[f"admittance_controller_{name}"]["ros__parameters"]
        R_base, R_pad = _grasp_frames(angled, side)
        assert not np.allclose(R_base, np.eye(3), atol=1e-3)  # the arm is turned
        if distro == "humble":
            assert p["fixed_world_frame"]["frame"]["id"] == "world"
            assert any("Humble roots the chain at your URDF's root link" in n for n in r.notes), r.notes
        else:
            world = f"{name}_jaxsync_world"
            assert p["kinematics"]["base"] == p["fixed_world_frame"]["frame"]["id"] == world
            joint = urdf[world]
            assert joint.find("parent").get("link") == f"{name}_link0"
            origin = joint.find("origin")
            np.testing.assert_allclose(np.array(origin.get("xyz").split(), dtype=float), 0.0, atol=1e-12)
            rpy = np.array(origin.get("rpy").split(), dtype=float)
            np.testing.assert_allclose(R_base @ _rpy_matrix(*rpy), np.eye(3), atol=1e-9)  # the world's axes
        mass = np.asarray(p["admittance"]["mass"])
        if distro == "rolling":  # the control frame's order: the pad's own
            np.testing.assert_array_equal(mass, np.asarray(g.imp_mass)[arm])
        else:  # per world axis: each holds the mass of the pad axis lying along it at the grasp
            along = np.argmax(np.abs(R_pad), axis=1)  # world axis i lies along pad axis along[i]
            np.testing.assert_array_equal(mass[:3], np.asarray(g.imp_mass)[arm][along])
            assert mass.tolist().count(5.0) == 1


def test_the_default_export_centres_the_compliance_where_it_was_simulated(tmp_path, capsys):
    """Without --compliance-at the files name the pad link jaxsync simulated at; what the controller still
    does otherwise (the tool's inertia) is a note with its size; --compliance-at flange says how far off."""
    path = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots", "ur5e_twice.yaml")
    argv = ["export", "--format", "ros2-admittance", "--robot", path, "--no-visual", "--actuation", "position"]
    assert main([*argv, "--out", str(tmp_path / "d")]) == 0
    said = capsys.readouterr().out
    p = yaml.safe_load(open(tmp_path / "d" / "admittance_right.yaml"))["admittance_controller_right"]
    assert p["ros__parameters"]["kinematics"]["tip"] == "right_jaxsync_pad"
    # the end effector 0.3 kg; the carry a min-jerk of lift 0.112 m in 1.2 s: (10 / sqrt 3) 0.112 / 1.2^2 m/s^2
    assert "jaxsync's wrist sensing also its inertia: 0.3 kg, 0.134 N" in said, said
    assert "centred at the flange" not in said
    assert main([*argv, "--compliance-at", "flange", "--out", str(tmp_path / "f")]) == 0
    said = capsys.readouterr().out
    assert "the compliance is centred at the flange link, 136 mm and 136 mm (right, left) from the pad" in said
