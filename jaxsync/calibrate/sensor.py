"""The wrist force/torque sensors' noise, from the still parts of a recording.

The tuner draws each scenario's white sensor noise around the task's
(``Scenario.force_noise``, ``torque_noise``; 0.1 N and 0.005 N m unless the
robot file's ``sensor:`` says otherwise). A recording of the excitation with
the sensors' ``geometry_msgs/WrenchStamped`` holds what that number is on
the robot: wherever the commands have not moved for ``SETTLE_S`` (the servo
settled), the arm is still and its wrench is a constant (the tool's weight,
the sensor's bias) plus the noise. Each still interval's samples, less a
straight line fitted to them per axis (what is left of settling or drift),
give the noise's standard deviation per axis, pooled over the intervals.
What is not estimated: the bias itself (reported, not used: the task's
wrench has none), noise that is not white, and anything the sensor does in
contact.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxsync._errors import ConfigError

SETTLE_S = 0.05  # s after a command last moved before the arm counts as still (a critically damped 25 Hz
# servo: 8 time constants, after a delay of up to 4 periods at 500 Hz; what is left, the line fit takes)
MIN_STILL_S = 0.01  # s: shorter still intervals are skipped (a line through 5 samples at 500 Hz leaves 3)
MIN_SAMPLES = 50  # pooled still samples per sensor below which no noise is estimated


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Each sensor's (arm's) noise and bias while still: (2, 6) [fx, fy, fz, tx, ty, tz], N and N m."""

    std: np.ndarray
    bias: np.ndarray
    samples: tuple[int, int]  # still samples used per sensor
    still_s: float  # still time found in the commands

    @property
    def force_noise(self) -> float:
        """N: the RMS over both sensors' force axes (the scenario's one number)."""
        return float(np.sqrt(np.mean(self.std[:, :3] ** 2)))

    @property
    def torque_noise(self) -> float:
        """N m: the RMS over both sensors' torque axes."""
        return float(np.sqrt(np.mean(self.std[:, 3:] ** 2)))

    def to_dict(self) -> dict:
        axes = ("fx", "fy", "fz", "tx", "ty", "tz")
        arms = ("right", "left")
        return {
            "force_noise_N": self.force_noise,
            "torque_noise_Nm": self.torque_noise,
            "std": {a: dict(zip(axes, map(float, s), strict=True)) for a, s in zip(arms, self.std, strict=True)},
            "bias": {a: dict(zip(axes, map(float, b), strict=True)) for a, b in zip(arms, self.bias, strict=True)},
            "still_samples": list(self.samples),
            "still_s": self.still_s,
        }


def still_intervals(command_times: np.ndarray, commands: np.ndarray, settle: float = SETTLE_S) -> list[tuple]:
    """(start, end) s of the stretches where no command has moved for ``settle`` seconds."""
    moved = np.any(np.diff(commands, axis=0) != 0.0, axis=1)  # command k+1 differs from command k
    changes = command_times[1:][moved]
    edges = np.concatenate([[command_times[0] - settle], changes, [command_times[-1]]])
    return [(a + settle, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b - (a + settle) >= MIN_STILL_S]


def estimate(rec, wrenches) -> SensorNoise:
    """Both sensors' noise from ``wrenches`` ((times (W,), values (W, 6)) per arm, right first; times on
    the recording's clock) over the still parts of ``rec``'s commands."""
    if len(wrenches) != 2:
        raise ConfigError(f"wrench: one sensor per arm (2), got {len(wrenches)}", inputs=("wrench_topics",))
    spans = still_intervals(rec.command_times, rec.commands)
    still = float(sum(b - a for a, b in spans))
    std, bias, counts = np.zeros((2, 6)), np.zeros((2, 6)), []
    for k, (t, w) in enumerate(wrenches):
        sq, dof, total, n = np.zeros(6), 0, np.zeros(6), 0
        for a, b in spans:
            inside = (t >= a) & (t < b)
            m = int(inside.sum())
            if m < 5:
                continue
            x = t[inside] - t[inside].mean()
            y = w[inside]
            design = np.column_stack([np.ones(m), x])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            sq += ((y - design @ coef) ** 2).sum(axis=0)
            dof += m - 2
            total += y.sum(axis=0)
            n += m
        if n < MIN_SAMPLES:
            raise ConfigError(
                f"wrench: {n} samples of sensor {k + 1} while the arms are still ({still:.2f} s of still commands), "
                f"the noise needs at least {MIN_SAMPLES}",
                inputs=("wrench_topics",),
            )
        std[k], bias[k] = np.sqrt(sq / dof), total / n
        counts.append(n)
    return SensorNoise(std, bias, tuple(counts), still)
