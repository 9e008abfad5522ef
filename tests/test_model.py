"""The MJCF model: structure, geometry of the SRS arms, and bad-model errors."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from types import ModuleType

import jax
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import solver as mjx_solver

import jaxsync
import jaxsync.optimize  # noqa: F401  (a subpackage is an attribute once imported)
from jaxsync.physics.model import JOINTS_PER_ARM
from jaxsync.runtime.patches import sqrt_zero_safe


def _axes_and_anchors(m, d, prefix):
    ids = [m.joint(f"{prefix}_joint{k}").id for k in range(1, JOINTS_PER_ARM + 1)]
    return d.xanchor[ids].copy(), d.xaxis[ids].copy()


def _closest_distance(p1, a1, p2, a2):
    """Distance between two lines (point, unit direction)."""
    n = np.cross(a1, a2)
    if np.linalg.norm(n) < 1e-12:
        return np.linalg.norm(np.cross(p2 - p1, a1))
    return abs(np.dot(p2 - p1, n)) / np.linalg.norm(n)


def test_fourteen_hinges_and_actuators(model):
    m = model.mj_model
    for arm in model.index.arms:
        assert len(arm.dof_adr) == 7
        for k in range(1, 8):
            j = m.joint(f"{arm.prefix}_joint{k}")
            assert j.type[0] == mujoco.mjtJoint.mjJNT_HINGE
            act = m.actuator(f"{arm.prefix}_motor{k}")
            assert act.trntype[0] == mujoco.mjtTrn.mjTRN_JOINT and act.trnid[0] == j.id
            assert act.gainprm[0] == 1.0 and act.biastype[0] == mujoco.mjtBias.mjBIAS_NONE  # torque motor
    assert m.nu == 14


@pytest.mark.parametrize("key", ["approach", "grasp", None])
def test_spherical_shoulder_and_wrist(model, key):
    """Joints 1-3 meet at one point, joints 5-7 meet at one point, in any pose."""
    m = model.mj_model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    d.qpos[:] = model.keyframe_qpos(key) if key else m.qpos0
    if key is None:
        d.qpos[:14] = rng.uniform(-2, 2, 14)
    mujoco.mj_kinematics(m, d)
    for prefix in ("r", "l"):
        anchors, axes = _axes_and_anchors(m, d, prefix)
        for group in ((0, 1, 2), (4, 5, 6)):
            for i in group:
                for j in group:
                    if i < j:
                        assert _closest_distance(anchors[i], axes[i], anchors[j], axes[j]) < 1e-9
            # and they meet at the same point: all anchors coincide
            assert np.ptp(anchors[list(group)], axis=0).max() < 1e-9


def test_stretched_reach_is_1375_mm(model):
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0  # zero pose: the arm hangs stretched
    mujoco.mj_kinematics(m, d)
    for prefix in ("r", "l"):
        shoulder = d.xanchor[m.joint(f"{prefix}_joint1").id]
        flange = d.site_xpos[m.site(f"{prefix}_flange").id]
        assert abs(np.linalg.norm(flange - shoulder) - 1.375) < 1e-3
        # and the elbow is not where the reach comes from alone: 0.6 + 0.6 + 0.175
        elbow = d.xanchor[m.joint(f"{prefix}_joint4").id]
        assert abs(np.linalg.norm(elbow - shoulder) - 0.6) < 1e-9


def test_grasp_keyframe_is_a_clamp_pose(model):
    """Pads face each other across the object, away from limits and singularities."""
    m = model.mj_model
    d = mujoco.MjData(m)
    for key, gap in (("approach", 0.03), ("grasp", 0.0)):
        d.qpos[:] = model.keyframe_qpos(key)
        mujoco.mj_forward(m, d)
        obj = d.xpos[model.index.object_body]
        radius = m.geom_size[model.index.object_geom][0]
        for arm, side in zip(model.index.arms, (-1, 1), strict=True):
            p = d.site_xpos[arm.pad_site]
            normal = d.site_xmat[arm.pad_site].reshape(3, 3)[:, 2]
            np.testing.assert_allclose(normal, [0, -side, 0], atol=1e-6)  # pointing at the object
            np.testing.assert_allclose(p, obj + side * np.array([0, radius + gap, 0]), atol=1e-6)
            q = d.qpos[list(arm.qpos_adr)]
            jids = [m.dof_jntid[a] for a in arm.dof_adr]
            lo, hi = m.jnt_range[jids].T
            assert np.all(q > lo + 0.3) and np.all(q < hi - 0.3), "keyframe within 0.3 rad of a joint range"
            jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
            mujoco.mj_jacSite(m, d, jp, jr, arm.pad_site)
            sv = np.linalg.svd(np.vstack([jp, jr])[:, list(arm.dof_adr)], compute_uv=False)
            assert sv.min() > 0.1, f"{key}: pad Jacobian near-singular (sigma_min={sv.min():.3f})"


def test_only_explicit_pairs_collide(model):
    m = model.mj_model
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    names = {frozenset((m.geom(int(m.pair_geom1[i])).name, m.geom(int(m.pair_geom2[i])).name)) for i in range(m.npair)}
    assert names == {frozenset(p) for p in (("r_pad", "object"), ("l_pad", "object"), ("stand", "object"))}
    types = {int(m.geom(n).type[0]) for n in ("r_pad", "l_pad", "object", "stand")}
    assert types <= {
        int(mujoco.mjtGeom.mjGEOM_SPHERE),
        int(mujoco.mjtGeom.mjGEOM_CYLINDER),
        int(mujoco.mjtGeom.mjGEOM_PLANE),
    }  # analytic in MJX


def test_solver_settings(model, unrolled_model):
    assert unrolled_model.mj_model.opt.iterations == 1
    # the same cone: elliptic (its unrolled MJX gradient made finite by jaxsync.runtime.patches.mjx_elliptic_gradient)
    assert unrolled_model.mj_model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert model.mj_model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert model.mj_model.opt.iterations > 1
    assert model.solver == "accurate" and jaxsync.load_model().solver == "accurate"  # the default
    for mdl in (model, unrolled_model):
        assert mdl.mj_model.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON
    for name in ("pgs", "differentiable"):
        with pytest.raises(jaxsync.ConfigError, match="solver must be one of"):
            jaxsync.load_model(solver=name)


def test_model_ships_in_the_installed_package():
    path = jaxsync.default_model_path()
    assert os.path.isfile(path) and path.endswith("dual_arm.xml")


# ----------------------------------------------------------------- bad models


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(jaxsync.ModelFileError, match="no such MJCF file") as err:
        jaxsync.load_model(tmp_path / "nope.xml")
    assert "nope.xml" in str(err.value)


def test_unparsable_file(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(jaxsync.ModelFileError, match="cannot compile"):
        jaxsync.load_model(bad)


@pytest.mark.skipif(os.geteuid() == 0, reason="root can read any file")
def test_unreadable_file(tmp_path):
    f = tmp_path / "locked.xml"
    shutil.copy(jaxsync.default_model_path(), f)
    f.chmod(0)
    with pytest.raises(jaxsync.ModelFileError, match="not readable"):
        jaxsync.load_model(f)


def _stripped_model(tmp_path):
    """The paper model with the left wrist sensors and the right pad site renamed away."""
    text = open(jaxsync.default_model_path()).read()
    text = text.replace('name="l_ft_force"', 'name="x1"').replace('name="l_ft_torque"', 'name="x2"')
    text = text.replace('<site name="r_pad"', '<site name="r_padx"')
    f = tmp_path / "stripped.xml"
    f.write_text(text)
    return f


def test_missing_names_are_all_listed(tmp_path):
    f = _stripped_model(tmp_path)
    with pytest.raises(jaxsync.ModelStructureError) as err:
        jaxsync.load_model(f)
    msg = str(err.value)
    assert str(f) in msg
    for name in ("sensor 'l_ft_force'", "sensor 'l_ft_torque'", "site 'r_pad'"):
        assert name in msg


def _cli(*args, tmp_path, **env):
    """Run the installed ``jaxsync`` console script, away from the source tree."""
    exe = os.path.join(os.path.dirname(sys.executable), "jaxsync")
    return subprocess.run(
        [exe, *args], capture_output=True, text=True, cwd=tmp_path, env=dict(os.environ, **env), timeout=300
    )


def test_cli_info_on_bad_model_exits_nonzero_without_traceback(tmp_path):
    f = _stripped_model(tmp_path)
    out = _cli("info", "--model", str(f), tmp_path=tmp_path, JAXSYNC_CACHE_DIR="off")
    assert out.returncode == 2
    assert "Traceback" not in out.stderr + out.stdout
    assert "l_ft_force" in out.stderr and str(f) in out.stderr


def test_cli_info_prints_versions_and_model(tmp_path):
    out = _cli("info", tmp_path=tmp_path, XLA_FLAGS="")  # the command sets jaxsync's XLA flags itself
    assert out.returncode == 0, out.stderr
    for word in ("jax", "mujoco-mjx", "devices", "joints_per_arm", "r: 7, l: 7", "contact_pairs", "timestep_s"):
        assert word in out.stdout
    assert "warp" not in out.stdout
    # set before JAX's backend started (else set_xla_flags warns and leaves $XLA_FLAGS empty)
    assert "XLA_FLAGS    --xla_cpu_use_fusion_emitters=false" in out.stdout, out.stdout
    assert "Warning" not in out.stderr, out.stderr


def test_mjx_solver_sqrt_has_a_finite_derivative_at_zero():
    """The elliptic-cone fix (jaxsync.runtime.patches.mjx_elliptic_gradient) is installed by load_model."""
    jaxsync.load_model(solver="unrolled")

    assert mjx_solver.jp.sqrt is sqrt_zero_safe
    assert mjx_solver.jp.zeros is jax.numpy.zeros  # everything else is jax.numpy's
    assert float(jax.grad(sqrt_zero_safe)(0.0)) == 0.0
    assert abs(float(jax.grad(sqrt_zero_safe)(4.0)) - 0.25) < 1e-15
    assert float(sqrt_zero_safe(9.0)) == 3.0


def test_public_names_are_the_documented_ones():
    """dir(jaxsync) lists the public API (``__all__``) and its subpackages, no
    plumbing, and every name in ``__all__`` resolves (the lazily imported
    tuning and sweep API included)."""
    public = {n for n in dir(jaxsync) if not n.startswith("_") and not isinstance(getattr(jaxsync, n), ModuleType)}
    assert public == set(jaxsync.__all__), public ^ set(jaxsync.__all__)
    for name in jaxsync.__all__:
        assert getattr(jaxsync, name) is not None, name
