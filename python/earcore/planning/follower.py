"""The trajectory follower: the control law that turns a timed motion into joint
velocity commands, and its roll-out from a moving start.

A new plan usually starts while the robot still moves along the old one. The new
path is timed from the robot's position with only the speed it has along the path's
first direction; the rest of its velocity the follower brakes away within the
acceleration limit, and meanwhile the robot is off the path that was checked (up to
7 cm at the tool in the experiments). The control
law is deterministic, so the executive rolls it out (`Follower.rollout`) and checks
the states the robot will really pass through.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from earcore import _earcore

__all__ = ["Follower", "Rollout"]


@dataclass
class Rollout:
    """The states (n, dof) a follower passes through, the start first, one per control
    step, until it has rejoined its motion (`rejoined`) or the horizon ran out."""

    states: np.ndarray
    rejoined: bool
    #: Seconds from the start to the rejoining (or to the horizon).
    duration: float
    #: Largest joint distance (rad) between a state and the motion's reference then.
    largest_error: float


@dataclass(frozen=True)
class Follower:
    """Feed-forward of the reference's velocity plus a feedback on the position error
    that never asks for more speed than can be braked away before the error closes
    (√(2·a·|e|)): no overshoot when the reference changes abruptly (beyond what the
    discrete steps add). Commands stay within the speed limit and change by at most
    the acceleration limit per step. The law and the roll-out's loop run in the core
    (a reflex rolls out ~50 steps within its few milliseconds)."""

    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    #: Position feedback gain (1/s).
    gain: float = 8.0
    #: The roll-out follows a transition this long at most (s), and counts the robot
    #: back on its motion within `tolerance` (rad) of it.
    horizon: float = 3.0
    tolerance: float = 1e-3

    @cached_property
    def _core(self):
        return _earcore.Follower(self.max_velocity, self.max_acceleration, float(self.gain))

    def command(self, q: np.ndarray, command: np.ndarray, now: np.ndarray | None, ahead: np.ndarray | None, dt: float) -> np.ndarray:
        """The next velocity command from position q and the last `command`, tracking
        the reference at `now` and one step `ahead`; None for both: stop (every joint
        brakes at its limit)."""
        return self._core.command(q, command, now, ahead, dt)

    def rollout(
        self,
        motion,
        q: np.ndarray,
        command: np.ndarray,
        dt: float,
        joint_limits: np.ndarray,
        *,
        start: float = 0.0,
    ) -> Rollout:
        """Follow `motion` (anything with `sample(times)`) from its time `start`, with
        the robot at q moving at `command`, as the cell does: q ← clip(q + command·dt,
        limits). Rejoined: every joint within `tolerance` of the reference and its
        command within one step's acceleration of the reference's velocity (without the
        velocity condition an arm crossing the reference at speed counts as back on it);
        from there on the robot stays within a few milliradians of the motion."""
        steps = max(1, int(np.ceil(self.horizon / dt)))
        reference = motion.sample(start + np.arange(steps + 2) * dt)
        limits = np.asarray(joint_limits, dtype=np.float64)
        states, rejoined, taken, largest = self._core.rollout(
            reference, q, command, dt, limits[:, 0].copy(), limits[:, 1].copy(), float(self.tolerance),
        )
        return Rollout(states, rejoined, taken * dt, largest)
