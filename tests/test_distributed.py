"""Multi-process runs on JAX's distributed runtime, with real processes.

Two local processes (CPU, one device each, JAX's gloo collectives, a
coordinator on 127.0.0.1 and a free port) run a sweep and two tuning
iterations; their results are compared with one process's. Every launched
process has a timeout and is killed when a test ends.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from test_sweep import FAST, run_cli

from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.optimize.tuning.tune import tune
from jaxsync.runtime import distributed as _distributed

TIMEOUT_S = 600  # each launched process
# heartbeat timeouts (s): where a killed process must be noticed, and elsewhere (JAX's default);
# the CI runs this file beside another slow test on two cores, so a heartbeat can stall
HEARTBEAT_KILL_S = 20
HEARTBEAT_S = 100
# 8 points in chunks of 2: four chunks, two per process
GRID8 = ["--param", "k_rk=-0.5:0.5:4", "--param", "object_mass=0.5,0.6", "--chunk", "2", "--no-progress"]


# ----------------------------------------------------------------- no processes


def test_settings_come_from_flags_or_environment():
    assert _distributed.settings(environ={}) is None  # one process: nothing to join
    kw = _distributed.settings("10.0.0.1:1234", "4", "3", environ={})
    assert kw == {"coordinator_address": "10.0.0.1:1234", "num_processes": 4, "process_id": 3}
    env = {"JAXSYNC_COORDINATOR": "h:9", "JAXSYNC_NUM_PROCESSES": "2", "JAXSYNC_PROCESS_ID": "1"}
    assert _distributed.settings(environ=env) == {"coordinator_address": "h:9", "num_processes": 2, "process_id": 1}
    assert _distributed.settings(process_id=0, environ=env)["process_id"] == 0  # a flag wins
    assert _distributed.settings(auto=True, environ={}) == {}  # JAX's cluster detection decides
    env["JAXSYNC_HEARTBEAT_TIMEOUT_S"] = "7"
    assert _distributed.settings(environ=env)["heartbeat_timeout_seconds"] == 7


@pytest.mark.parametrize(
    "args, message",
    [
        (("h:1", None, None), "missing --num-processes (or JAXSYNC_NUM_PROCESSES), --process-id"),
        (("nohost", "2", "0"), "--coordinator must be HOST:PORT"),
        (("h:port", "2", "0"), "port must be an integer"),
        (("h:1", "2", "2"), "--process-id must be below --num-processes (2), got 2"),
        (("h:1", "0", "0"), "--num-processes must be at least 1"),
        (("h:1", "two", "0"), "--num-processes must be an integer, got 'two'"),
    ],
)
def test_bad_settings_are_named(args, message):
    with pytest.raises(ConfigError) as err:
        _distributed.settings(*args, environ={})
    assert message in str(err.value)


def test_cli_rejects_a_partial_multi_process_setting(tmp_path, capsys):
    for cmd in (["sweep", "--param", "k_rk=0,1"], ["tune"]):
        rc = main([*cmd, "--out", str(tmp_path / "o"), "--coordinator", "127.0.0.1:1"])
        err = capsys.readouterr().err
        assert rc == 2 and "missing --num-processes" in err and "Traceback" not in err, err
        assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------- two processes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _processes(argv: list[str], tmp_path, heartbeat_s: int, n: int = 2):
    """``jaxsync ARGV`` as ``n`` processes of one run; yields the Popen objects
    (output in tmp_path/pK.log); kills what is still running on the way out.
    ``heartbeat_s``: the coordination service's heartbeat timeout; short only
    where a test waits for a killed process to be noticed, as a heartbeat RPC
    can stall for seconds while the other process compiles on a shared core."""
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
    env["JAXSYNC_HEARTBEAT_TIMEOUT_S"] = str(heartbeat_s)
    env.pop("XLA_FLAGS", None)  # one CPU device per process
    code = "import sys; from jaxsync.cli import main; sys.exit(main(sys.argv[1:]))"
    procs = []
    try:
        for k in range(n):
            dist = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n), "--process-id", str(k)]
            log = open(tmp_path / f"p{k}.log", "w")  # noqa: SIM115 - closed with the process
            p = subprocess.Popen(
                [sys.executable, "-c", code, *argv, *dist],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=tmp_path,  # not the source checkout: python -c puts the cwd first on sys.path
                start_new_session=True,
            )
            p.log = log
            procs.append(p)
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
            p.log.close()


def _wait(procs, tmp_path, timeout: float = TIMEOUT_S) -> list[int]:
    t_end = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(timeout=max(1.0, t_end - time.monotonic()))
        except subprocess.TimeoutExpired:
            pytest.fail(f"a launched process ran past {timeout:g} s; logs: {_logs(tmp_path)}")
    return [p.returncode for p in procs]


def _logs(tmp_path) -> str:
    out = []
    for f in sorted(tmp_path.glob("p*.log")):
        lines = [ln for ln in f.read_text().splitlines() if not ln.startswith(("W0000", "I0000", "    @"))]
        out.append(f"--- {f.name}\n" + "\n".join(lines[-25:]))
    return "\n".join(out)


def _computed(out, partial: bool = False) -> list[dict]:
    """The chunks' computed records (chunks/computed_pK.jsonl); ``partial``: a
    line still being written is skipped, not an error."""
    rows = []
    for f in sorted((out / "chunks").glob("computed_p*.jsonl")):
        for line in f.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                if not partial:
                    raise
    return rows


def _chunks(out) -> set[int]:
    return {int(f.name[6:11]) for f in (out / "chunks").glob("chunk_*.npz")}


@pytest.fixture(scope="module")
def killed_then_resumed(tmp_path_factory):
    """One process's 8-point sweep; then two processes on it, process 1 killed
    (SIGKILL) as soon as it has written its first chunk; then the same command
    with --resume, in one process (a re-run on the machines that are left)."""
    root = tmp_path_factory.mktemp("distributed_sweep")
    ref = root / "one"
    assert run_cli(["sweep", *FAST, *GRID8, "--out", str(ref)]) == 0
    out = root / "two"
    argv = ["sweep", *FAST, *GRID8, "--out", str(out)]
    run1 = root / "run1"
    run1.mkdir()
    with _processes(argv, run1, heartbeat_s=HEARTBEAT_KILL_S) as (p0, p1):
        t_end = time.monotonic() + TIMEOUT_S
        while not any(r["process"] == 1 for r in (_computed(out, True) if (out / "chunks").exists() else [])):
            if p1.poll() is not None or time.monotonic() > t_end:
                pytest.fail(f"process 1 wrote no chunk (exit {p1.poll()}): {_logs(run1)}")
            time.sleep(0.02)
        os.killpg(p1.pid, signal.SIGKILL)
        # process 0 finishes its own chunks, then the coordination service stops it (heartbeat timeout)
        rc0 = _wait([p0], run1)[0]
    after_kill = {"chunks": _chunks(out), "computed": _computed(out), "rc0": rc0}
    # re-run on what is left (here one process, this one: its chunk function is compiled already)
    assert run_cli([*argv, "--resume"]) == 0
    return {"ref": ref, "out": out, "after_kill": after_kill}


@pytest.mark.slow
def test_killed_sweep_resumes_with_every_point_computed_once(killed_then_resumed):
    r = killed_then_resumed
    out, first = r["out"], r["after_kill"]
    assert first["rc0"] != 0  # process 0 did not finish the run alone
    assert {c["chunk"] for c in first["computed"] if c["process"] == 1} == {1}  # then it was killed
    assert 0 < len(first["chunks"]) < 4 and 3 not in first["chunks"]  # its second chunk was lost
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["n_points"] == 8
    assert summary["timing"]["chunks_loaded"] == len(first["chunks"])
    assert summary["timing"]["chunks_computed"] == 4 - len(first["chunks"])
    # every chunk computed and written exactly once over both runs, by the process it was given to
    computed = _computed(out)
    assert sorted(c["chunk"] for c in computed) == [0, 1, 2, 3], computed
    assert _chunks(out) == {0, 1, 2, 3}


@pytest.mark.slow
def test_two_processes_give_the_rows_of_one(killed_then_resumed):
    """Rows of the killed two-process run, completed, byte for byte those of one process."""
    r = killed_then_resumed
    with open(r["out"] / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 and all(row["ok"] == "1" for row in rows)
    assert (r["out"] / "results.csv").read_bytes() == (r["ref"] / "results.csv").read_bytes()


@pytest.mark.slow
def test_two_process_tuning_equals_one_process_with_both_batches(model, tuning_program, tmp_path):
    """Two processes with --batch 1 each take the same two L-BFGS iterations as one
    process with batch 2 (the scenarios of both), to float64 rounding: the
    data-parallel cost and gradient (optimize.parallel) average what one
    process's batch averages. Process 0 alone writes the results."""
    cfg = tuning_program["cfg"].replace(iterations=2, validate_every=0, method="lbfgs")
    assert cfg.training.batch == 2 and cfg.training.task == "full"
    one = tune(model, tuning_program["base"], cfg, progress=False)
    out = tmp_path / "two"
    argv = ["tune", "--out", str(out), "--iterations", "2", "--batch", "1", "--method", "lbfgs"]
    argv += ["--validate-every", "0", "--heldout-batch", "1", "--no-mujoco-check"]
    with _processes(argv, tmp_path, heartbeat_s=HEARTBEAT_S) as procs:
        rcs = _wait(procs, tmp_path)
    assert rcs == [0, 0], _logs(tmp_path)
    got = json.loads((out / "gains.json").read_text())["gains"]
    want = _gains.to_dict(one.last_gains)
    assert got.keys() == want.keys()
    for k in want:
        np.testing.assert_allclose(np.asarray(got[k]), np.asarray(want[k]), rtol=1e-9, atol=1e-12, err_msg=k)
    assert _gains.to_dict(one.last_gains) != _gains.to_dict(tuning_program["base"])  # it did move
    with open(out / "history.csv") as f:
        hist = list(csv.DictReader(f))
    # the same cost from programs partitioned apart, to rounding: the stratified batches hold the
    # softest contact, which amplifies that rounding through the rollout, hence rtol 1e-8
    for row, ref in zip(hist, one.history, strict=True):
        np.testing.assert_allclose(float(row["cost"]), ref["cost"], rtol=1e-8)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["options"]["num_processes"] == "2" and summary["options"]["batch"] == 1
    logs = {k: (tmp_path / f"p{k}.log").read_text() for k in (0, 1)}
    assert "results in" in logs[0] and "results in" not in logs[1]  # process 0 reports, process 1 is quiet
    assert jax.process_count() == 1  # the test process itself never joined
