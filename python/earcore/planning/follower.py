"""The trajectory follower: the control law that turns a timed motion into joint
velocity commands, and its roll-out from a moving start.

A new plan usually starts while the robot still moves along the old one. The new
path is timed from the robot's position with only the speed it has along the path's
first direction; the rest of its velocity the follower brakes away within the
acceleration limit, and meanwhile the robot is off the path that was checked (up to
7 cm at the tool in the experiments before the executive checked it). The control
law is deterministic, so the executive rolls it out (`Follower.rollout`) and checks
the states the robot will really pass through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    (√(2·a·|e|)): no overshoot when the reference changes abruptly. Commands stay
    within the speed limit and change by at most the acceleration limit per step."""

    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    #: Position feedback gain (1/s).
    gain: float = 8.0
    #: The roll-out follows a transition this long at most (s), and counts the robot
    #: back on its motion within `tolerance` (rad) of it.
    horizon: float = 3.0
    tolerance: float = 1e-3

    def command(self, q: np.ndarray, command: np.ndarray, now: np.ndarray | None, ahead: np.ndarray | None, dt: float) -> np.ndarray:
        """The next velocity command from position q and the last `command`, tracking
        the reference at `now` and one step `ahead`; None for both: stop (every joint
        brakes at its limit)."""
        desired = np.zeros_like(q)
        if now is not None:
            error = now - q
            bounded = np.minimum(self.gain * np.abs(error), np.sqrt(2 * self.max_acceleration * np.abs(error)))
            desired = (ahead - now) / dt + np.sign(error) * bounded
        step = self.max_acceleration * dt
        return np.clip(np.clip(desired, command - step, command + step), -self.max_velocity, self.max_velocity)

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
        q = np.asarray(q, dtype=np.float64).copy()
        command = np.asarray(command, dtype=np.float64).copy()
        steps = max(1, int(np.ceil(self.horizon / dt)))
        # The reference at every step at once (one call), then the loop: the feedback
        # depends on the state, so the steps cannot be batched.
        reference = motion.sample(start + np.arange(steps + 2) * dt)
        lo, hi = joint_limits[:, 0], joint_limits[:, 1]
        slack = self.max_acceleration * dt
        states = [q.copy()]
        largest = float(np.abs(reference[0] - q).max())
        for k in range(steps):
            command = self.command(q, command, reference[k], reference[k + 1], dt)
            q = np.clip(q + command * dt, lo, hi)
            states.append(q.copy())
            error = np.abs(reference[k + 1] - q)
            largest = max(largest, float(error.max()))
            velocity = (reference[k + 2] - reference[k + 1]) / dt
            if error.max() < self.tolerance and np.all(np.abs(command - velocity) <= slack):
                return Rollout(np.array(states), True, (k + 1) * dt, largest)
        return Rollout(np.array(states), False, steps * dt, largest)
