"""The paper's comparison: summary files, the claims on three scenarios, and CLI input errors."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxsync import _compare, _metrics
from jaxsync._gains import default_gains
from jaxsync._scenario import default_scenario


def _cli(*args, cwd):
    exe = os.path.join(os.path.dirname(sys.executable), "jaxsync")
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def test_compare_writes_a_well_formed_summary(tmp_path, rollouts):
    s = rollouts["scenario"]
    results = {name: (rollouts[name], _metrics.summarize(rollouts[name], s)) for name in ("classical", "synchronous")}
    summary = _compare.write_results(str(tmp_path), results, s, rollouts["gains"], {"test": True}, 1.0)
    for f in ("summary.json", "series.csv", "forces_classical.png", "forces_synchronous.png"):
        assert (tmp_path / f).stat().st_size > 0, f
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    for name in ("classical", "synchronous"):
        for key in _compare.SUMMARY_KEYS:
            assert key in on_disk[name]
        assert isinstance(on_disk[name]["dropped"], bool)
    ratio = on_disk["classical"]["settled_peak_resultant_N"] / on_disk["synchronous"]["settled_peak_resultant_N"]
    assert on_disk["resultant_ratio"] == pytest.approx(ratio)
    with open(tmp_path / "series.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(rollouts["classical"].time)
    assert {"time_s", "classical_resultant_force_N", "synchronous_right_normal_force_N"} <= set(rows[0])
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]  # atomic writes left nothing behind


@pytest.mark.slow
@pytest.mark.parametrize(
    "overrides",
    [{}, {"object_mass": 0.8, "mass_estimate": 0.8}, {"object_offset": [0.0, 0.008, 0.0]}],
    ids=["default", "mass-0.8kg", "offset-8mm"],
)
def test_paper_claims(model, overrides):
    """The paper's result on the default task and two others: the synchronous
    controller's settled peak resultant force is at least 4 times smaller,
    both hold the grip force within 2 % of f_d, and the object is not dropped."""
    s = default_scenario(**overrides)
    res = _compare.run(model, default_gains(), s, duration=4.0, log=lambda m: None)
    m = {k: jax.tree_util.tree_map(np.asarray, v[1]) for k, v in res.items()}
    for name in ("classical", "synchronous"):
        assert not m[name].dropped and not m[name].nonfinite, name
        assert m[name].grip_force_error_rel < 0.02, name
    # both show a real effect, not numerical noise
    assert m["synchronous"].settled_peak_resultant_N > 1e-3
    assert m["classical"].settled_peak_resultant_N >= 4 * m["synchronous"].settled_peak_resultant_N
    if not overrides:  # the README's numbers (jaxsync compare on the defaults)
        np.testing.assert_allclose(m["classical"].settled_peak_resultant_N, 0.0560, rtol=0.01)
        np.testing.assert_allclose(m["synchronous"].settled_peak_resultant_N, 0.00758, rtol=0.01)


def test_compare_rejects_bad_input(tmp_path, capsys):
    from jaxsync.cli import main

    blocker = tmp_path / "afile"
    blocker.write_text("x")
    bad_gains = tmp_path / "g.json"
    bad_gains.write_text('{"k_rk": 3}')
    cases = [
        (["--duration", "1.0"], "--duration must be at least"),
        (["--duration", "-2"], "must be positive"),
        (["--object-mass", "0"], "must be positive"),
        (["--object-offset", "0.5"], "object_offset"),
        (["--gains", str(bad_gains)], "k_rk"),
        (["--gains", str(tmp_path / "missing.json")], "no such file"),
        (["--out", str(blocker / "sub")], "cannot be written"),
    ]
    for args, message in cases:  # in this process (the console script itself: tests/test_model.py)
        try:
            rc = main(["compare", "--out", str(tmp_path / "o"), *args])
        except SystemExit as exit_:  # argparse's own errors
            rc = exit_.code
        err = capsys.readouterr().err
        assert rc == 2, args
        assert message in err, (args, err)
        assert "Traceback" not in err, args


def test_render_cli_and_compare_video(tmp_path, model, rollouts):
    """``jaxsync render`` writes a non-blank PNG; the comparison video has one
    frame per 1/25 s of slowed-down rollout (skipped without an OpenGL backend)."""
    from jaxsync import _render
    from jaxsync.cli.render import VIDEO_FPS, compare_video

    try:
        _render.select_gl_backend()
    except _render.RenderUnavailableError as err:
        pytest.skip(f"no OpenGL backend: {err}")
    out = _cli("render", "--out", str(tmp_path), "--width", "320", "--height", "240", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "grasp.png"))
    assert img.shape == (240, 320, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 50

    s = rollouts["scenario"]
    results = {n: (rollouts[n], _metrics.summarize(rollouts[n], s)) for n in ("classical", "synchronous")}
    path = compare_video(model, results, s, str(tmp_path), speed=2.0, width=96, height=72)
    n_states = len(rollouts["classical"].time)
    expected = len(_render.frame_indices(n_states, VIDEO_FPS, 0.002, 2.0))
    if path.endswith(".gif"):
        with Image.open(path) as gif:
            assert gif.n_frames <= expected and gif.n_frames > expected // 2  # Pillow merges identical frames
            assert gif.size == (2 * 96 + 4, 72)
    assert os.path.getsize(path) > 0


def test_infinite_duration_and_bad_cache_dir_are_clear_errors(tmp_path, capsys):
    from jaxsync.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["compare", "--duration", "inf", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2 and "finite" in capsys.readouterr().err
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["--cache-dir", str(blocker / "xla"), "info"]) == 2
    err = capsys.readouterr().err
    assert "compilation cache folder" in err and "Traceback" not in err
