"""jaxsync export: every format reads back to the same gains, constant and scheduled."""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io.export_gains import Exported, export_gains

ROBOTS = os.path.join(os.path.dirname(__file__), "..", "mjcf", "robots")


def _tuned_like():
    """Gains unlike the defaults in every field (per arm, per axis); the
    admittance rule runs them within its margin (the normal axis's stability
    index ramp / 2.5 <= 0.52)."""
    g = _gains.default_gains()
    ramp = np.linspace(0.7, 1.3, 12).reshape(2, 6)
    return g._replace(
        imp_mass=g.imp_mass * ramp * 2.5,
        imp_stiffness=g.imp_stiffness * ramp[::-1],
        imp_damping=g.imp_damping * ramp**2,
        k_rk=jnp.asarray(0.18),
        k_lk=jnp.asarray(0.97),
        k_rl=jnp.asarray(0.061),
        k_ll=jnp.asarray(-0.2),
        kp_pos=jnp.asarray(1234.5),
        kd_pos=jnp.asarray(70.25),
        kp_null=jnp.asarray(90.0),
        kd_null=jnp.asarray(19.0),
    )


def _schedule_like():
    sched = _schedule.constant(_tuned_like())
    return sched._replace(phases=sched.phases._replace(k_rk=jnp.array([0.5, 0.3, 0.2, 0.1])))


def _same(a, b, rtol):
    assert type(a) is type(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=0)


@pytest.mark.parametrize("fmt", _export.FORMATS)
@pytest.mark.parametrize("kind", ["constant", "schedule"])
def test_every_format_round_trips(tmp_path, fmt, kind):
    gains = _tuned_like() if kind == "constant" else _schedule_like()
    paths = _export.export(gains, fmt, str(tmp_path))
    back = gains_file.load(paths[0] if fmt != "ros2-admittance" else tmp_path)  # what compare --gains reads
    # every format carries the values exactly (ros2: the damping ratio's D kept in synchronisation.yaml)
    _same(back, gains, rtol=0)


def test_ros2_files_follow_the_admittance_controller_schema(tmp_path):
    g = _tuned_like()
    _export.export(
        g, "ros2-admittance", str(tmp_path), _export.ros2_target(jaxsync.load_model().mj_model, compliance_at="flange")
    )
    doc = yaml.safe_load((tmp_path / "admittance_left.yaml").read_text())
    params = doc["admittance_controller_left"]["ros__parameters"]
    adm = params["admittance"]
    assert params["control"]["frame"]["id"] == "l_ee" and params["ft_sensor"]["frame"]["id"] == "l_ee"
    assert adm["selected_axes"] == [True] * 6
    m, k, zeta = (np.array(adm[key]) for key in ("mass", "stiffness", "damping_ratio"))
    # the paper model's flange frame is its pad frame; the mass is per axis of the base (pad y, z, x)
    np.testing.assert_allclose(m, np.asarray(g.imp_mass)[1][[1, 2, 0, 4, 5, 3]], rtol=0)
    np.testing.assert_allclose(k, np.asarray(g.imp_stiffness)[1], rtol=0)
    np.testing.assert_allclose(2 * zeta * np.sqrt(m * k), np.asarray(g.imp_damping)[1], rtol=1e-14)
    text = (tmp_path / "admittance_left.yaml").read_text()
    assert "Not carried over" in text and "synchronisation.yaml" in text
    sync = yaml.safe_load((tmp_path / "synchronisation.yaml").read_text())["dual_arm_synchronisation"]
    assert sync["ros__parameters"]["k_lk"] == pytest.approx(0.97)


def test_synchronisation_yaml_has_a_versioned_schema_and_the_admittance_files_win(tmp_path):
    """synchronisation.yaml names its schema and every key docs/export.md lists;
    a damping_ratio edited in an admittance file is what is read back (the D
    kept beside it only while the ratio still gives it); a newer schema, or a
    file written before the schema had a version, is said."""
    g = _tuned_like()._replace(ff_vel=np.float64(0.0041234567891), ff_acc=np.float64(0.00123456789012))
    _export.export(g, "ros2-admittance", str(tmp_path))
    path = tmp_path / "synchronisation.yaml"
    sync = yaml.safe_load(path.read_text())["dual_arm_synchronisation"]["ros__parameters"]
    assert sync["schema_version"] == _export.SYNC_SCHEMA == 3
    documented = open(os.path.join(os.path.dirname(__file__), "..", "docs", "synchronisation.md")).read()
    for key in sync:
        assert f"`{key}`" in documented, f"synchronisation.yaml key {key} is not documented in docs/synchronisation.md"
    assert sync["controllers"] == ["admittance_controller_right", "admittance_controller_left"]
    assert sync["update_rate"] == 500 and sync["ros_distro"] == "jazzy" and sync["alpha"] == 0.01
    right = tmp_path / "admittance_right.yaml"
    doc = yaml.safe_load(right.read_text())
    adm = doc["admittance_controller_right"]["ros__parameters"]["admittance"]
    adm["damping_ratio"][0] = 0.5
    right.write_text(yaml.safe_dump(doc))
    back = gains_file.load(tmp_path)  # the paper model: control axes = pad axes; the mass per base axis
    expected = 2 * 0.5 * np.sqrt(adm["mass"][0] * adm["stiffness"][0])
    assert float(back.imp_damping[0, 0]) == pytest.approx(expected, rel=1e-12) != float(g.imp_damping[0, 0])
    np.testing.assert_array_equal(np.asarray(back.imp_damping)[1], np.asarray(g.imp_damping)[1])
    assert (float(back.ff_vel), float(back.ff_acc)) == (float(g.ff_vel), float(g.ff_acc))
    written = path.read_text()
    # schema 1 had no feed-forward: such a file reads it as none
    path.write_text(
        "\n".join(x for x in written.splitlines() if not x.lstrip().startswith(("ff_vel", "ff_acc"))).replace(
            "schema_version: 3", "schema_version: 1"
        )
    )
    assert float(gains_file.load(tmp_path).ff_acc) == 0.0 == float(gains_file.load(tmp_path).ff_vel)
    for version, message in ((4, "schema_version 4 is not one this jaxsync reads"), ("one", "'one'")):
        path.write_text(written.replace("schema_version: 3", f"schema_version: {version}"))
        with pytest.raises(ConfigError, match=message):
            gains_file.load(tmp_path)


def test_yaml_names_every_gain_with_its_unit(tmp_path):
    (path,) = _export.export(_gains.default_gains(), "yaml", str(tmp_path))
    doc = yaml.safe_load(open(path))["jaxsync_gains"]["gains"]
    assert set(doc) == set(_gains.Gains._fields)
    assert all(doc[k]["unit"] and doc[k]["paper"] for k in doc)


def test_export_cli_and_its_errors(tmp_path, capsys):
    src = tmp_path / "gains.json"
    _gains_file = {"gains": _schedule.to_file_dict(_schedule_like())}
    src.write_text(json.dumps(_gains_file))
    assert main(["export", str(src), "--format", "ros2-admittance", "--out", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "a gain schedule" in out and "the same gains" in out
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == sorted(_schedule.PHASES)
    # bad input: one line, exit 2, nothing written
    rc = main(["export", str(tmp_path / "missing.json"), "--format", "yaml", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "no such file" in err and "Traceback" not in err and not (tmp_path / "o").exists()
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "synchronisation.yaml").write_text("dual_arm_synchronisation: {}\n")
    with pytest.raises(ConfigError, match="admittance_right.yaml"):
        gains_file.load(tmp_path / "half")
    with pytest.raises(SystemExit):
        main(["export", str(src), "--format", "urdf"])


def test_ros2_refuses_what_the_admittance_controller_cannot_hold(tmp_path, capsys):
    """Out of its bounds, or a damping with zero stiffness (its D = 2 zeta sqrt(M K)
    is then 0 whatever the ratio, and jaxsync's damping is always > 0): a
    one-line error, and nothing written."""
    g = _gains.default_gains()
    k0 = g._replace(imp_stiffness=g.imp_stiffness.at[1, 2].set(0.0))
    with pytest.raises(ConfigError, match="left arm, axis z.*zero stiffness.*--format yaml or json"):
        _export.export(k0, "ros2-admittance", str(tmp_path / "a"))
    heavy = g._replace(imp_mass=g.imp_mass.at[0, 4].set(2e6))
    with pytest.raises(ConfigError, match=r"mass 2e\+06 of the right arm, axis ry is outside"):
        _export.export(heavy, "ros2-admittance", str(tmp_path / "a"))
    sched = _schedule.constant(g)
    sched = sched._replace(phases=sched.phases._replace(imp_stiffness=sched.phases.imp_stiffness.at[3, 0, 0].set(-1.0)))
    with pytest.raises(ConfigError, match=r"stiffness -1 of the right arm, axis x \(phase hold\)"):
        _export.export(sched, "ros2-admittance", str(tmp_path / "a"))
    assert not (tmp_path / "a").exists()  # not even the phases before the bad one
    src = tmp_path / "k0.json"
    src.write_text(json.dumps({"gains": _schedule.to_file_dict(k0)}))
    rc = main(["export", str(src), "--format", "ros2-admittance", "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert rc == 2 and "zero stiffness" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "b").exists()


def test_ros2_files_say_what_differs_from_jaxsync(tmp_path, capsys):
    """joint_damping 0 (jaxsync's law has none), the missing force set-point
    named; the mass written per axis of kinematics.base, where Jazzy and
    Humble apply it: on the paper model the pad's normal (z) lies along the
    base's y at the grasp, so the normal mass sits in column y of the mass
    while stiffness and damping stay in the flange link's axis order, and the
    controller's D = 2 zeta sqrt(M K), formed entry by entry, is the tuned D."""
    _export.export(_gains.default_gains(), "ros2-admittance", str(tmp_path / "d"))
    text = (tmp_path / "d" / "admittance_right.yaml").read_text()
    params = yaml.safe_load(text)["admittance_controller_right"]["ros__parameters"]
    assert params["admittance"]["joint_damping"] == 0.0 and "f_d" in text and "kinematics.base" in text
    tuned = _tuned_like()
    target = _export.ros2_target(jaxsync.load_model().mj_model, compliance_at="flange")
    right = target.arms[0]
    assert right.base_axes == (1, 2, 0, 4, 5, 3)  # base x, y, z carry the pad's y, z (normal), x
    paths = _export.export(tuned, "ros2-admittance", str(tmp_path / "e"), target)
    adm = yaml.safe_load(open(paths[0]).read())["admittance_controller_right"]["ros__parameters"]["admittance"]
    m_pad = np.asarray(tuned.imp_mass)[0]
    np.testing.assert_allclose(adm["mass"], m_pad[[1, 2, 0, 4, 5, 3]], rtol=1e-15)
    k = np.asarray(adm["stiffness"])
    d = 2 * np.asarray(adm["damping_ratio"]) * np.sqrt(np.asarray(adm["mass"]) * k)  # what the controller forms
    order = list(right.axes)
    np.testing.assert_allclose(d, np.asarray(tuned.imp_damping)[0][order], rtol=1e-12)
    _same(_export.load(str(tmp_path / "e")), tuned, rtol=1e-12)
    src = tmp_path / "g.json"
    src.write_text(json.dumps({"gains": _schedule.to_file_dict(tuned)}))
    assert main(["export", str(src), "--format", "ros2-admittance", "--out", str(tmp_path / "f")]) == 0
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("note: ")]
    # within the margin: no stability WARNING; the coupling's and the tool's inertia are said
    assert [n for n in notes if "synchronisation.yaml's coupling" not in n and "also its inertia" not in n] == []
    assert "the same gains, bit for bit" in out
    # a pad frame not aligned with the base: only a mass equal on a block's axes has a base-frame form
    tilted = dataclasses.replace(right, base_axes=None)
    with pytest.raises(ConfigError, match=r"right arm's pad frame is not aligned with kinematics.base .* x, y, z"):
        _export.mass_in_base(tuned, 0, tilted)
    iso = _gains.default_gains()
    np.testing.assert_array_equal(_export.mass_in_base(iso, 0, tilted), np.asarray(iso.imp_mass)[0])


def test_export_job_says_what_it_wrote_and_refuses_what_ros2_cannot_run(tmp_path, capsys):
    """export_gains: the files, whose gains, their kind, the read-back and the
    ros2 notes as a value; gains tuned for a controller that ros2_controllers'
    admittance controller cannot run are refused in the job's words (the
    command's: --gains), and nothing is written."""
    src = tmp_path / "g.json"
    src.write_text(json.dumps({"gains": _gains.to_dict(_gains.default_gains()), "controller": "task_space"}))
    with pytest.raises(ConfigError, match=r"^gains .* was tuned for the task_space controller.*yaml or json") as err:
        export_gains(str(src), "ros2-admittance", str(tmp_path / "r"))
    assert err.value.inputs == ("gains",)
    rc = main(["export", str(src), "--format", "ros2-admittance", "--out", str(tmp_path / "r")])
    assert rc == 2 and f"gains {src} was tuned for the task_space controller" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    r = export_gains(str(src), "yaml", str(tmp_path / "y"))  # yaml carries any controller's gains
    assert r == Exported([str(tmp_path / "y" / "gains.yaml")], "constant gains", str(src), True, [])
    r = export_gains(_tuned_like(), "ros2-admittance", str(tmp_path / "t"))
    assert r.same and r.origin == "the given gains" and len(r.paths) == 4  # pad_links.urdf, 2 arms, the coupling
    assert r.notes[0].startswith("WARNING: synchronisation.yaml's coupling")  # untuned k's
    assert len(r.notes) == 2 and "also its inertia" in r.notes[1]  # what the controller does otherwise
    r = export_gains(None, "json", str(tmp_path / "d"))
    assert r.origin == "the default gains of the paper model" and r.same
    with pytest.raises(ConfigError, match="^command_interfaces must name position") as err:
        export_gains(None, "ros2-admittance", str(tmp_path / "e"), command_interfaces=["effort"])
    with pytest.raises(ConfigError, match="^fmt must be one of") as err:
        export_gains(None, "urdf", str(tmp_path / "e"))
    assert err.value.inputs == ("fmt",) and not (tmp_path / "e").exists()


def test_export_writes_a_stacks_defaults(tmp_path, capsys):
    """export --actuation position without gains: the robot's defaults for
    position-controlled arms (on the iiwa-like pair, whose shoulder servo is
    slow, a lower kp_pos than the torque stack's), said in the origin."""
    robot = os.path.join(ROBOTS, "iiwa14_twice.yaml")
    r = export_gains(None, "json", str(tmp_path / "p"), model=robot, visual=False, actuation="position")
    assert r.same and r.origin.endswith("iiwa14_twice.yaml on position-controlled arms")
    written = gains_file.load(r.paths[0])
    iiwa = jaxsync.load_model(robot, visual=False)
    assert float(written.kp_pos) == pytest.approx(float(_gains.default_gains(iiwa, "position").kp_pos))
    assert float(written.kp_pos) < float(_gains.default_gains(iiwa).kp_pos)
    argv = ["export", "--format", "json", "--robot", robot, "--no-visual", "--actuation", "position"]
    assert main([*argv, "--out", str(tmp_path / "c")]) == 0
    assert "on position-controlled arms" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="actuation must be one of"):
        export_gains(None, "json", str(tmp_path / "e"), actuation="velocity")
    assert not (tmp_path / "e").exists()


def test_ros2_export_is_refused_where_the_admittance_rule_runs_near_its_bound(tmp_path, capsys):
    """The paper model's torque-stack defaults put the normal axis at dt D/M =
    2.00, the explicit rule's bound: refused with the numbers, no folder; with
    force written, each file opening with the WARNING and the notes saying it;
    the position stack's defaults (normal mass 3 kg) export as they are."""
    with pytest.raises(ConfigError, match=r"the right arm's pad axis z unstable: dt D/M = 2, .* = 1\.000") as err:
        export_gains(None, "ros2-admittance", str(tmp_path / "r"))
    assert err.value.inputs == ("gains", "force") and not (tmp_path / "r").exists()
    assert "(and" not in str(err.value)  # the two normal axes, no more
    r = export_gains(None, "ros2-admittance", str(tmp_path / "f"), force=True)
    assert r.notes[0].startswith("WARNING: the admittance rule runs the right arm's pad axis z unstable")
    for arm in ("right", "left"):
        first = (tmp_path / "f" / f"admittance_{arm}.yaml").read_text().splitlines()[0]
        assert first.startswith("# WARNING: the admittance rule runs the ") and "unstable" in first
    assert main(["export", "--format", "ros2-admittance", "--out", str(tmp_path / "c")]) == 2
    assert "(--gains, --force)" in capsys.readouterr().err
    assert main(["export", "--format", "ros2-admittance", "--out", str(tmp_path / "c"), "--force"]) == 0
    p = export_gains(None, "ros2-admittance", str(tmp_path / "p"), actuation="position")
    assert not any(n.startswith("WARNING: the admittance rule runs") for n in p.notes)  # the rule: within margin
    adm = yaml.safe_load((tmp_path / "p" / "admittance_right.yaml").read_text())
    mass = adm["admittance_controller_right"]["ros__parameters"]["admittance"]["mass"]
    assert max(mass) == pytest.approx(3.0, rel=1e-4)  # 1.5 (2 dt D + dt^2 K) / 4 on the normal axis
    iiwa = os.path.join(ROBOTS, "iiwa14_twice.yaml")
    with pytest.raises(ConfigError, match=r"pad axis z within its margin: dt D/M = 1\.63"):
        export_gains(None, "ros2-admittance", str(tmp_path / "i"), model=iiwa, visual=False)


def test_one_arm_file_used_twice_exports_each_arm_by_its_own_names(tmp_path):
    """ur5e_twice.yaml gives no ros_prefix: the files name the right arm's joints and links right_...,
    the left's left_..., and the pad links hang from two different flange links; a note says so."""
    ur5e = os.path.join(ROBOTS, "ur5e_twice.yaml")
    r = export_gains(None, "ros2-admittance", str(tmp_path / "u"), model=ur5e, visual=False, actuation="position",
                     compliance_at="pad")  # fmt: skip
    assert r.same and any("prefixed right_ and left_" in n for n in r.notes), r.notes
    names = {}
    for arm in ("right", "left"):
        doc = yaml.safe_load((tmp_path / "u" / f"admittance_{arm}.yaml").read_text())
        p = doc[f"admittance_controller_{arm}"]["ros__parameters"]
        names[arm] = {*p["joints"], p["kinematics"]["base"], p["kinematics"]["tip"]} - {"world"}
        assert all(n.startswith(f"{arm}_") for n in names[arm]), names[arm]
    assert not names["right"] & names["left"]
    urdf = (tmp_path / "u" / "pad_links.urdf").read_text()
    parents = [line.split('"')[1] for line in urdf.splitlines() if "<parent link=" in line]
    assert parents == ["right_wrist_3_link", "left_wrist_3_link"], parents


def test_prefixes_that_leave_the_arms_a_name_in_common_are_refused(tmp_path):
    doc = yaml.safe_load(open(os.path.join(ROBOTS, "ur5e_twice.yaml")).read())
    for arm in doc["arms"].values():
        arm["model"] = os.path.abspath(os.path.join(ROBOTS, arm["model"]))
        arm["ros_prefix"] = "arm_"
    (tmp_path / "same.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"ros_prefix 'arm_' .* give the arms different prefixes"):
        jaxsync.load_model(str(tmp_path / "same.yaml"), visual=False)
