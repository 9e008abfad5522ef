"""``calibrate`` on recordings MuJoCo C made with a robot's own actuators: right, or refused.

The recordings come from ``independent_servo.record_actuators``: MuJoCo's own
``<position>`` actuators (plus a feed-forward motor and gravity compensation
where the structure has them) on the robot's scene, implicitfast at 0.25 ms
(the fit replays at 0.5 ms, Euler), nothing of jaxsync's servo, replay or
calibrate code; the servo gains moved by up to +-25 %, a delay of whole
command periods, noise on the positions, velocities and efforts. Two robots
with joint torque limits and friction loss as published arms have them.
A result calibrate stands behind must be the truth; anything else must be a
refusal (``Calibration.problems``), never a wrong answer without a word.
Slow: each fit replays a 20 s recording for a few minutes.
"""

from __future__ import annotations

import independent_servo as ind
import numpy as np
import pytest

from jaxsync.calibrate import excite
from jaxsync.calibrate.fit import calibrate
from jaxsync.calibrate.replay import Replay
from jaxsync.io.bags import Recording
from jaxsync.physics.model import load_model

NOISE_Q, NOISE_DQ, NOISE_TAU = 1e-4, 5e-3, 0.05
TOLERANCE = {"stiffness": 0.10, "damping": 0.20}  # what "the truth" means for a gain stood behind

# (figures, structure, delay, what the structure and delay must come out as where the fit is
# certain enough to say: the UR5e's motion fixes both, the FR3's as written does not)
CASES = [("ur5e", "feedforward", 2, True), ("fr3", "as_written", 2, False)]


@pytest.mark.slow
@pytest.mark.parametrize("figures,structure,delay,identified", CASES)
def test_calibrate_is_right_or_refuses(tmp_path, figures, structure, delay, identified):
    model = load_model(str(ind.limited_robot(tmp_path, figures)), visual=False)
    nominal = Replay(model).nominal()
    rng = np.random.default_rng(0)
    n = len(nominal.stiffness)
    kp = nominal.stiffness * rng.uniform(0.75, 1.25, n)
    kv = nominal.damping * rng.uniform(0.75, 1.25, n)
    ex = excite.excitation(model, duration=20.0)
    q0 = np.asarray(model.keyframe_qpos("grasp"))
    t, q, dq, tau = ind.record_actuators(model.robot.spec, q0, kp, kv, ex.times, ex.commands, delay,
                                         structure=structure, efforts=True)  # fmt: skip
    q, dq = ind.noisy(q, dq, NOISE_Q, NOISE_DQ, seed=1)
    tau = tau + NOISE_TAU * np.random.default_rng(2).standard_normal(tau.shape)
    rec = Recording(tuple(ex.joints), t, q, dq, ex.times, ex.commands, effort=tau)
    cal = calibrate(model, rec)[0]
    err = {"stiffness": np.abs(cal.fitted.stiffness / kp - 1), "damping": np.abs(cal.fitted.damping / kv - 1)}
    wrong = {k: np.round(v, 3) for k, v in err.items() if v.max() > TOLERANCE[k]}
    answered_right = not wrong and (cal.structure, cal.delay) == (structure, delay)
    assert cal.problems or answered_right, (
        f"a wrong calibration stood behind: {cal.structure}, delay {cal.delay}, {wrong}"
    )
    if identified:
        assert (cal.structure, cal.delay) == (structure, delay)
