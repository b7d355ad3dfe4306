"""Joint control: the robot interface a real driver could implement too, and a
velocity-based trajectory follower with speed and acceleration limits (Paper II,
Table I: 50 % of the maximum joint speed, 60 % of the maximum acceleration).
"""

from __future__ import annotations

import numpy as np

from earcore.interfaces import RobotInterface

__all__ = ["JointTrajectoryController", "RobotInterface"]


class JointTrajectoryController:
    """Follows a joint-space path (waypoints) by commanding velocities.

    Each step moves along the straight segment to the next waypoint at the largest
    speed the limits allow: every joint within `max_velocity`, speed changes within
    `max_acceleration`, braking in time to stop at each waypoint (a corner taken at
    speed would need an infinite acceleration; smoothing paths into curves is the
    planner's job). Deterministic: no clock, `step(dt)` only.
    """

    def __init__(self, max_velocity: np.ndarray, max_acceleration: np.ndarray, *, tolerance: float = 1e-4) -> None:
        self.max_velocity = np.asarray(max_velocity, dtype=np.float64)
        self.max_acceleration = np.asarray(max_acceleration, dtype=np.float64)
        if np.any(self.max_velocity <= 0) or np.any(self.max_acceleration <= 0):
            raise ValueError("velocity and acceleration limits must be > 0")
        self.tolerance = tolerance
        self.waypoints: list[np.ndarray] = []
        self.speed = 0.0  # along the path, in "path units" = largest joint displacement

    @property
    def done(self) -> bool:
        return not self.waypoints

    def follow(self, waypoints) -> None:
        """Replace the path (the robot keeps its current velocity; the next steps
        re-plan the speed)."""
        self.waypoints = [np.asarray(w, dtype=np.float64) for w in waypoints]

    def stop(self) -> None:
        self.waypoints = []

    def brake(self, q: np.ndarray) -> None:
        """Stop as soon as the acceleration limit allows: the path is cut at the point
        where braking from the current speed along the current segment ends."""
        q = np.asarray(q, dtype=np.float64)
        if not self.waypoints or self.speed <= 0:
            self.waypoints = []
            return
        delta = self.waypoints[0] - q
        span = np.abs(delta).max()
        if span <= self.tolerance:
            self.waypoints = [self.waypoints[0]]
            return
        direction = delta / span
        distance = min(span, self.speed**2 / (2 * self._path_accel(direction)))
        self.waypoints = [q + direction * distance]

    def step(self, q: np.ndarray, dt: float) -> np.ndarray:
        """Joint velocities for the next `dt` seconds, from the current positions."""
        q = np.asarray(q, dtype=np.float64)
        if self.waypoints and np.abs(self.waypoints[0] - q).max() <= self.tolerance:
            # Arrived (at a speed of at most one step's braking): rest for this step so
            # the turn onto the next segment starts from zero velocity.
            self.waypoints.pop(0)
            self.speed = 0.0
            return np.zeros_like(q)
        if not self.waypoints:
            self.speed = 0.0
            return np.zeros_like(q)
        delta = self.waypoints[0] - q
        span = np.abs(delta).max()
        direction = delta / span  # largest component ±1
        v_cap = np.min(self.max_velocity / np.maximum(np.abs(direction), 1e-12))
        a_cap = self._path_accel(direction)
        # Largest speed from which braking at a_cap per step stops on the waypoint
        # (discrete: v²/2a + v·dt/2 = span).
        half = 0.5 * a_cap * dt
        v_stop = -half + np.sqrt(half * half + 2 * a_cap * span)
        target = min(v_cap, v_stop)
        if target > self.speed:
            self.speed = min(target, self.speed + a_cap * dt)
        else:
            self.speed = max(target, self.speed - a_cap * dt)
        # Land on the waypoint rather than step past it.
        self.speed = min(self.speed, span / dt)
        return direction * self.speed

    def _path_accel(self, direction: np.ndarray) -> float:
        return float(np.min(self.max_acceleration / np.maximum(np.abs(direction), 1e-12)))
