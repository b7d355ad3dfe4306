"""Time parameterisation: a joint-space path (waypoints) becomes a trajectory q(t)
that respects per-joint speed and acceleration limits (Paper II, Table I: 50 % / 60 %
of the maximum).

The path is resampled densely by arc length s; along it the speed ṡ is limited by

    |q'_j(s)| ṡ ≤ v_j                      (joint speed)
    |q''_j(s)| ṡ² ≤ a_j / 2                (the curvature's share of the acceleration)
    |q'_j(s)| |s̈| ≤ a_j / 2                (the tangential share)

so every joint's acceleration |q'_j s̈ + q''_j ṡ²| stays within a_j. A forward pass
(accelerate from rest) and a backward pass (brake to rest) give the fastest profile
under these bounds; times follow from ṡ. Corners of a polyline have infinite
curvature; they are passed slowly enough that the velocity jump there fits in one
control period, so hand it smoothed paths (the planner does).

The paths are polylines, so their curvature sits at the corners alone: on a straight
stretch away from every corner nothing competes with the tangent for a joint's
acceleration, and `straight_share=1.0` lets it use all of it there (a straight move
accelerates √2 faster; near corners the split stays, for their velocity jumps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = [
    "StopThenMove",
    "Trajectory",
    "Transfer",
    "blend_corners",
    "braking",
    "densify",
    "path_length",
    "time_parameterize",
    "transfer",
]


def path_length(path: np.ndarray) -> float:
    """Euclidean joint-space length of a polyline (rad)."""
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2:
        raise ValueError(f"path must be an (M, dof) array, got shape {path.shape}")
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) if len(path) > 1 else 0.0


@dataclass
class Trajectory:
    """Knots of a timed path: times (T,), positions (T, dof), velocities (T, dof), and
    the arc length `s` and path speed `speed` (ṡ) at each knot. Between knots the path
    speed changes at a constant rate, so `sample` reproduces the planned motion."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    s: np.ndarray
    speed: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def sample(self, t: float | np.ndarray) -> np.ndarray:
        """Positions at time(s) t (clamped to [0, duration])."""
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        scalar = t.ndim == 0
        t = np.atleast_1d(t)
        if len(self.times) == 1:
            out = np.repeat(self.positions[:1], len(t), axis=0)
            return out[0] if scalar else out
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        tau = t - self.times[i]
        ds = self.s[i + 1] - self.s[i]
        accel = (self.speed[i + 1] ** 2 - self.speed[i] ** 2) / (2 * ds)
        s = np.minimum(self.s[i] + self.speed[i] * tau + 0.5 * accel * tau**2, self.s[i + 1])
        out = np.stack([np.interp(s, self.s, self.positions[:, j]) for j in range(self.positions.shape[1])], axis=1)
        return out[0] if scalar else out

    def remaining_path(self, t: float) -> np.ndarray:
        """Knot positions from time t to the end (the current position first)."""
        later = self.positions[self.times > t]
        return np.vstack([self.sample(t)[None], later])


def _joint_phases(x0: float, v0: float, x1: float, vmax: float, amax: float) -> list[tuple[float, float]]:
    """(duration, acceleration) phases of one joint's quickest move from (x0, v0) to
    rest at x1: brake first if it moves away from x1 or too fast to stop there, then
    accelerate, cruise at `vmax` if it gets there, and decelerate onto x1. (Plain
    floats and `math`: numpy's scalar calls would cost the reflex more than the rest.)"""
    phases = []
    d = x1 - x0
    stop = v0 * abs(v0) / (2 * amax)
    if v0 != 0.0 and (v0 * d <= 0.0 or abs(stop) > abs(d)):
        phases.append((abs(v0) / amax, -math.copysign(amax, v0)))
        x0, v0 = x0 + stop, 0.0
        d = x1 - x0
    if d == 0.0:
        return phases
    u, distance = abs(v0), abs(d)
    accel = math.copysign(amax, d)
    peak = math.sqrt(amax * distance + 0.5 * u * u)  # speed where accelerating meets braking
    if peak <= vmax:
        return phases + [(max(peak - u, 0.0) / amax, accel), (peak / amax, -accel)]
    to_cruise = abs(vmax * vmax - u * u) / (2 * amax)
    braking_distance = vmax * vmax / (2 * amax)
    return phases + [
        (abs(vmax - u) / amax, accel if vmax >= u else -accel),
        ((distance - to_cruise - braking_distance) / vmax, 0.0),
        (vmax / amax, -accel),
    ]


@dataclass
class Transfer:
    """Every joint's quickest move from its current position and velocity to rest at
    a target, each on its own clock within its limits (bang-bang with a cruise: what
    a velocity-controlled robot does when asked to go somewhere now). The joints do not
    arrive together, so the robot's path is a curve; `path` samples it densely enough
    to be checked."""

    start: np.ndarray
    velocity: np.ndarray
    #: Per joint (rows), its phases in order (columns, zero-padded): duration and
    #: constant acceleration.
    durations: np.ndarray
    accelerations: np.ndarray

    def __post_init__(self) -> None:
        # Each phase's start time and start velocity, per joint.
        self._phase_start = np.cumsum(self.durations, axis=1) - self.durations
        gained = np.cumsum(self.durations * self.accelerations, axis=1) - self.durations * self.accelerations
        self._phase_velocity = self.velocity[:, None] + gained

    @property
    def joint_durations(self) -> np.ndarray:
        return self.durations.sum(axis=1)

    @property
    def duration(self) -> float:
        return float(self.joint_durations.max()) if len(self.start) else 0.0

    def sample(self, t: float | np.ndarray) -> np.ndarray:
        """Positions at time(s) t (clamped to [0, duration])."""
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        # Time spent in each phase so far: (times, joints, phases).
        dt = np.clip(np.atleast_1d(t)[:, None, None] - self._phase_start, 0.0, self.durations)
        out = self.start + (self._phase_velocity * dt + 0.5 * self.accelerations * dt * dt).sum(axis=2)
        return out[0] if t.ndim == 0 else out

    def path(self, step: float = 0.01) -> np.ndarray:
        """The curve sampled in time so that no joint moves more than `step` between
        samples (speeds are piecewise linear in time: the fastest is at a phase end)."""
        ends = self._phase_velocity + self.durations * self.accelerations
        top = max(float(np.abs(self.velocity).max(initial=0.0)), float(np.abs(ends).max(initial=0.0)))
        n = int(np.clip(np.ceil(self.duration * top / step), 1, 100_000))
        return self.sample(np.linspace(0.0, self.duration, n + 1))

    @cached_property
    def positions(self) -> np.ndarray:
        return self.path()

    @property
    def end(self) -> np.ndarray:
        return self.sample(self.duration)

    def remaining_path(self, t: float) -> np.ndarray:
        return self.sample(np.linspace(min(t, self.duration), self.duration, 17))

    def then(self, move: Trajectory) -> StopThenMove:
        """This motion followed by `move`, which must start from rest where it ends."""
        if not np.allclose(move.positions[0], self.end, atol=1e-9):
            raise ValueError("the move must start where the first motion ends")
        return StopThenMove(self, move)


def transfer(q, velocity, target, max_velocity, max_acceleration) -> Transfer:
    """The quickest move from `q` moving at `velocity` to rest at `target`, every joint
    on its own (`Transfer`)."""
    q, v, target = (np.asarray(x, dtype=np.float64) for x in (q, velocity, target))
    vmax = np.broadcast_to(np.asarray(max_velocity, dtype=np.float64), q.shape)
    amax = np.broadcast_to(np.asarray(max_acceleration, dtype=np.float64), q.shape)
    if not all(np.isfinite(x).all() and x.shape == q.shape for x in (q, v, target)):
        raise ValueError("q, velocity and target must be finite and of one shape")
    if not (np.all(vmax > 0) and np.all(amax > 0)):
        raise ValueError("velocity and acceleration limits must be > 0")
    v = np.clip(v, -vmax, vmax)
    phases = [_joint_phases(*map(float, (q[j], v[j], target[j], vmax[j], amax[j]))) for j in range(len(q))]
    durations = np.zeros((len(q), 4))
    accelerations = np.zeros((len(q), 4))
    for j, joint in enumerate(phases):
        for k, (duration, accel) in enumerate(joint):
            durations[j, k], accelerations[j, k] = duration, accel
    return Transfer(q.copy(), v, durations, accelerations)


def braking(q, velocity, max_acceleration) -> Transfer:
    """The quickest stop from `velocity` at `q`: every joint decelerates at its limit
    until it rests (joints with little speed stop first, so the robot leaves its
    current joint-space line, but no joint travels farther than it must). A motion
    planned from its end starts where the robot can actually be at rest, so what is
    checked is what the robot does."""
    v = np.asarray(velocity, dtype=np.float64)
    a = np.broadcast_to(np.asarray(max_acceleration, dtype=np.float64), v.shape)
    if not np.all(a > 0):
        raise ValueError("acceleration limits must be > 0")
    with np.errstate(invalid="ignore"):
        rest = np.asarray(q, dtype=np.float64) + v * np.abs(v) / (2 * a)
    return transfer(q, v, rest, np.inf, a)


@dataclass
class StopThenMove:
    """A stop (`braking`) followed by a `Trajectory` from rest at its end, sampled as
    one motion (what the executive runs for a backtrack)."""

    stop: Transfer
    move: Trajectory

    @property
    def duration(self) -> float:
        return self.stop.duration + self.move.duration

    @cached_property
    def positions(self) -> np.ndarray:
        # Cached: the follower reads the last one every control step.
        return np.vstack([self.stop.positions, self.move.positions[1:]])

    def sample(self, t: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        d = self.stop.duration
        stopping = self.stop.sample(np.minimum(t, d))
        moving = self.move.sample(np.maximum(t - d, 0.0))
        return np.where((t < d)[..., None] if t.ndim else t < d, stopping, moving)

    def remaining_path(self, t: float) -> np.ndarray:
        d = self.stop.duration
        if t >= d:
            return self.move.remaining_path(t - d)
        later = np.linspace(t, d, 9)
        return np.vstack([self.stop.sample(later), self.move.positions[1:]])


def without_repeats(path: np.ndarray, tolerance: float = 1e-12) -> np.ndarray:
    """The polyline without points within `tolerance` of the one before (zero-length
    segments have no direction)."""
    return path[np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > tolerance])]


def cumsum0(values: np.ndarray) -> np.ndarray:
    """The running sum with a leading 0 (np.r_[0, cumsum] at a fraction of np.r_'s
    overhead, which the reflex's latency pays)."""
    out = np.zeros(len(values) + 1)
    np.cumsum(values, out=out[1:])
    return out


def densify(path: np.ndarray, step: float, *, per_joint: bool = False) -> np.ndarray:
    """The polyline with points at most `step` apart, the waypoints included: in
    Euclidean joint-space length, or with `per_joint` in the largest joint change (the
    collision checks' resolution)."""
    path = np.asarray(path, dtype=np.float64)
    if len(path) < 2:
        return path[:1].copy()
    # Whole-array form (no loop per segment: the reflex pays this on every move):
    # segment i gets n_i points a + (b - a)·k/n_i, k = 1..n_i.
    delta = np.diff(path, axis=0)
    span = np.abs(delta).max(axis=1) if per_joint else np.linalg.norm(delta, axis=1)
    if not step > 0:
        raise ValueError(f"densify needs a step > 0, got {step}")
    parts = span / step
    if not np.isfinite(parts).all():
        raise ValueError(f"densify needs a finite path and step, got step {step}")
    n = np.maximum(1, np.ceil(parts)).astype(np.int64)
    seg = np.repeat(np.arange(len(delta)), n)
    k = np.arange(1, len(seg) + 1) - np.repeat(np.cumsum(n) - n, n)
    return np.vstack([path[:1], path[seg] + delta[seg] * (k / n[seg])[:, None]])


def blend_corners(path, max_deviation: float, *, step: float = 0.01) -> np.ndarray:
    """The polyline with every corner replaced by a circular arc tangent to both of its
    segments (Kunz & Stilman's blends): at most `max_deviation` (rad) from the corner
    and using at most half of either segment, sampled with chords of at most `step`.

    A corner is a velocity jump, which a time parameterisation must take at a crawl
    (smoothed plans have a corner every ~0.1 rad); an arc of radius r only limits the
    speed to about sqrt(a·r). The arcs leave the checked polyline, so a caller must
    check the result again. Corners that turn back by more than ~170° stay corners."""
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2 or not np.isfinite(path).all():
        raise ValueError(f"path must be a finite (M, dof) array, got shape {path.shape}")
    if not (np.isfinite(max_deviation) and max_deviation >= 0 and step > 0):
        raise ValueError(f"need max_deviation >= 0 and step > 0, got {max_deviation}, {step}")
    path = without_repeats(path)
    if len(path) < 3 or max_deviation == 0:
        return path.copy()
    seg = np.diff(path, axis=0)
    length = np.linalg.norm(seg, axis=1)
    unit = seg / length[:, None]
    u_in, u_out = unit[:-1], unit[1:]
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", u_in, u_out), -1.0, 1.0))  # θ per corner
    half = 0.5 * turn
    with np.errstate(divide="ignore", invalid="ignore"):
        # Tangent length: half of either segment, or what keeps the arc within the
        # deviation from the corner: δ·sin(θ/2) / (1 - cos(θ/2)).
        reach = max_deviation * np.sin(half) / (1.0 - np.cos(half))
        tangent = np.minimum(np.minimum(0.5 * length[:-1], 0.5 * length[1:]), reach)
        radius = tangent / np.tan(half)
    blend = (turn > 1e-6) & (turn < np.radians(170.0)) & np.isfinite(radius) & (radius > 0)
    corners = path[1:-1]
    starts = corners - tangent[:, None] * u_in
    inward = u_out - u_in
    inward /= np.maximum(np.linalg.norm(inward, axis=1), 1e-300)[:, None]
    centres = corners + (radius / np.cos(half))[:, None] * inward
    # Arc samples: p(φ) = c + cos φ (a - c) + sin φ · r · u_in, φ from 0 to θ, k/n of
    # the way for k = 1..n (the arc's start point first).
    n = np.where(blend, np.maximum(1, np.ceil(np.where(blend, radius * turn, 0.0) / step)), 0).astype(np.int64)
    which = np.repeat(np.arange(len(corners)), n)
    k = np.arange(1, len(which) + 1) - np.repeat(np.cumsum(n) - n, n)
    phi = turn[which] * (k / n[which])
    arcs = (
        centres[which]
        + np.cos(phi)[:, None] * (starts - centres)[which]
        + (np.sin(phi) * radius[which])[:, None] * u_in[which]
    )
    # Assemble: the start, then per corner its block (the corner itself, or the arc's
    # start followed by its samples), then the goal.
    size = 1 + n
    block = 1 + np.concatenate([[0], np.cumsum(size)[:-1]])
    out = np.empty((2 + size.sum(), path.shape[1]))
    out[0], out[-1] = path[0], path[-1]
    out[block] = np.where(blend[:, None], starts, corners)
    out[block[which] + k] = arcs
    # Arcs that use half of a segment each meet at its middle: drop the repeated point.
    return without_repeats(out)


#: Segments on either side of a corner that keep half of each joint's acceleration
#: for the tangent whatever `time_parameterize`'s `straight_share`.
CORNER_REACH = 3


def time_parameterize(
    path,
    max_velocity,
    max_acceleration,
    *,
    step: float = 0.01,
    control_period: float = 1.0 / 30.0,
    initial_speed: float = 0.0,
    straight_share: float = 0.5,
) -> Trajectory:
    """The fastest trajectory along `path` (M, dof) from rest to rest within the limits
    (per joint, rad/s and rad/s²), sampled every `step` rad of arc length, for a
    controller that updates its command every `control_period` seconds.
    `initial_speed` (ṡ at the start, rad/s) lets a robot already moving along the
    path's first direction continue instead of being asked to be at rest (re-planning
    on the fly); it is capped by the limits there. `straight_share`: the share of each
    joint's acceleration the tangent may use on straight stretches more than
    `CORNER_REACH` segments from a corner (0.5, the split, everywhere by default; up to 1)."""
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2 or len(path) < 1:
        raise ValueError(f"path must be an (M, dof) array with M >= 1, got shape {path.shape}")
    if not np.isfinite(path).all():
        raise ValueError("path contains NaN or infinite values")
    v_max = np.broadcast_to(np.asarray(max_velocity, dtype=np.float64), path.shape[1:])
    a_max = np.broadcast_to(np.asarray(max_acceleration, dtype=np.float64), path.shape[1:])
    if not (np.all(v_max > 0) and np.all(a_max > 0) and np.isfinite(v_max).all() and np.isfinite(a_max).all()):
        raise ValueError("velocity and acceleration limits must be finite and > 0")
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step must be finite and > 0, got {step}")
    if not (np.isfinite(control_period) and control_period > 0):
        raise ValueError(f"control_period must be finite and > 0, got {control_period}")
    if not np.isfinite(initial_speed):  # negative (moving away from the path) counts as 0
        raise ValueError(f"initial_speed must be finite, got {initial_speed}")
    if not 0.5 <= straight_share <= 1.0:
        raise ValueError(f"straight_share must be in [0.5, 1], got {straight_share}")
    path = without_repeats(path)
    if len(path) == 1:
        return Trajectory(np.zeros(1), path.copy(), np.zeros_like(path), np.zeros(1), np.zeros(1))
    # At least two samples per path: from rest to rest over a single one the profile
    # would have zero speed at both knots and take forever (a tiny reflex move hung).
    q = densify(path, min(step, 0.5 * path_length(path)))
    ds = np.linalg.norm(np.diff(q, axis=0), axis=1)
    s = cumsum0(ds)
    # Path derivatives: one-sided on the segments, central at the knots.
    dq_seg = np.diff(q, axis=0) / ds[:, None]  # (n-1, dof), unit length
    d1 = np.empty_like(q)
    d1[0], d1[-1] = dq_seg[0], dq_seg[-1]
    d1[1:-1] = 0.5 * (dq_seg[:-1] + dq_seg[1:])
    d2 = np.zeros_like(q)
    d2[1:-1] = (dq_seg[1:] - dq_seg[:-1]) / (0.5 * (ds[:-1] + ds[1:]))[:, None]
    with np.errstate(divide="ignore"):
        # A knot's speed bounds the speed over both segments it ends (ṡ runs between
        # its ends' values), so each segment's own direction caps both its knots.
        v_lim = np.min(v_max / np.abs(d1), axis=1)
        on_segment = np.min(v_max / np.abs(dq_seg), axis=1)
        v_lim[:-1] = np.minimum(v_lim[:-1], on_segment)
        v_lim[1:] = np.minimum(v_lim[1:], on_segment)
        curv_lim = np.sqrt(np.min(0.5 * a_max / np.abs(d2), axis=1))
        # At a knot the direction turns by Δ (a corner of the polyline): the velocity
        # jumps by ṡ·|Δ_j|, which a controller running every `control_period` must
        # absorb within half its acceleration.
        turn = np.zeros_like(q)
        turn[1:-1] = np.abs(dq_seg[1:] - dq_seg[:-1])
        jump_lim = np.min(0.5 * a_max * control_period / turn, axis=1)
        # Tangential acceleration allowed on each segment (both ends' directions): half
        # of each joint's limit, or `straight_share` of it on stretches away from every
        # corner (no curvature there; near one, a controller's velocity differences
        # span a few stretches around its jump).
        share = np.full(len(ds), 0.5)
        if straight_share > 0.5:
            corner = (np.max(turn, axis=1) > 1e-6).astype(float)  # (rounding: ~ulp / step)
            # Segment i touches knots i and i + 1; it is near a corner at knots
            # i - CORNER_REACH + 1 .. i + CORNER_REACH.
            near = np.convolve(corner, np.ones(2 * CORNER_REACH))[CORNER_REACH : CORNER_REACH + len(ds)] > 0
            share[~near] = straight_share
        a_seg = share * np.minimum(
            np.min(a_max / np.abs(dq_seg), axis=1),
            np.minimum(np.min(a_max / np.abs(d1[:-1]), axis=1), np.min(a_max / np.abs(d1[1:]), axis=1)),
        )
    cap = np.minimum(np.minimum(v_lim, curv_lim), jump_lim)
    cap[0] = min(max(float(initial_speed), 0.0), cap[0])
    cap[-1] = 0.0
    # Forward (accelerate) and backward (brake) passes on ṡ²: v²[i] = min(cap²[i],
    # v²[i-1] + 2 a ds) unrolls to a running minimum of cap² - C plus C, with C the
    # cumulative 2 a ds (and the same backwards), so no loop is needed.
    c = cumsum0(2 * a_seg * ds)
    v2 = np.minimum(cap, 1e6) ** 2
    v2 = np.minimum.accumulate(v2 - c) + c
    v2 = np.minimum.accumulate((v2 + c)[::-1])[::-1] - c
    sd = np.sqrt(np.maximum(v2, 0.0))
    dt = 2 * ds / np.maximum(sd[:-1] + sd[1:], 1e-12)
    times = cumsum0(dt)
    return Trajectory(times, q, d1 * sd[:, None], s, sd)
