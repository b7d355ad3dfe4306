"""The reflexive layer (Paper II §C.6): obstacles tracked across frames, the risk of
Eq. 2, and the reflex moves, with ISO/TS 15066 speed-and-separation figures alongside.

Per map frame:
1. the voxels hit in the frame (`OcTree.current_obstacles`) minus the static scene
   (voxels seen during a warm-up, grown by one voxel for noise) are clustered
   (`earcore.cluster_points`, 26-connected voxels) into obstacles;
2. clusters are matched to the previous frame's tracks by nearest centroid; a track's
   velocity is the least-squares slope of its centroid over the last few frames, the
   centroid of where in each voxel the frame's points fell (`cloud.voxel_means`), which
   moves by less than a voxel;
3. per track, d = exact clearance between the robot's bodies and the cluster's voxel
   boxes (`RobotModel.clearance_to_voxels`) and the risk D = |v|² / (β d) (Eq. 2), v the
   obstacle's velocity (the paper) or, by default in the executive, for an obstacle
   moving towards the robot, its velocity relative to the robot's closest point (a
   robot moving towards an approaching hand closes the gap as surely as the hand does);
   the reflex fires when D ≥ T (Eq. 3) for an obstacle that approaches the robot
   (moving away from it is no danger, however fast).

The reflex itself (`plan_reflex`): back off along the last `backtrack_fraction` (10 %)
of the executed path if that path is free, else move the end-effector
`move_away_distance` along the inverted vector from it to the closest obstacle point.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

import earcore
from earcore.cloud import voxel_codes, voxel_means
from earcore.planning.separation import protective_separation
from earcore.planning.trajectory import cumsum0, densify, without_repeats

__all__ = [
    "ObstacleTrack", "ObstacleTracker", "ReflexMove", "RiskReport", "plan_recovery", "plan_reflex", "predicted_contact",
    "predicted_course",
]


@dataclass
class ObstacleTrack:
    id: int
    #: (time, centroid) of the last few frames.
    history: list[tuple[float, np.ndarray]] = field(default_factory=list)
    voxels: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: Per voxel, where in it the obstacle was seen (the mean of the frame's points in
    #: it, `cloud.voxel_means`; the centres when the tracker got no points): the centroid
    #: and the lead come from these, which move by less than a voxel.
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: The centroid's velocity for Eq. 2 (`_velocities`: the faster of the slope and
    #: a constant-acceleration fit at the newest frame; the slope lags a reach that speeds
    #: up by 1-1.5 frames). `velocity`, the slope, decides whether the track moves at all
    #: (`still_speed`): the fit's extra noise would make flickering still obstacles move.
    velocity_now: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: The centroid when first seen, and (time, lead point) of the last few frames: the
    #: lead is the obstacle's part farthest from where it started (a reaching hand).
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lead_history: list[tuple[float, np.ndarray]] = field(default_factory=list)
    lead_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: The lead's least-squares slope alone (no acceleration fit): steadier, for the
    #: prediction rule and separation monitoring (`course_velocity`).
    lead_slope: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: The last frame's rating (`ObstacleTracker.update`): exact clearance to the robot
    #: (m) and its closest points and robot link, whether the track moves by itself
    #: (`still_speed`) and towards the robot (by `approach_velocity`), and its course's
    #: velocity (`course_velocity`; zero when still).
    clearance: float = float("inf")
    on_robot: np.ndarray | None = None
    on_obstacle: np.ndarray | None = None
    link: int = -1
    moving: bool = False
    approaching: bool = False
    own_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def centroid(self) -> np.ndarray:
        return self.history[-1][1]

    def observe_lead(self, time_s: float, window: int, radius: float, jump: float) -> None:
        """Track the lead: the mean of the voxels within `radius` of the one farthest
        from the anchor. An arm reaching from a still shoulder moves its centroid at
        about half the hand's speed; the lead moves with the hand. A lead that jumps
        farther than `jump` in one frame is another part of the obstacle (the far end
        switched, or the robot hid it): its history starts again."""
        seen = self.positions if len(self.positions) == len(self.voxels) else self.voxels
        far = seen[np.argmax(_squared_norms(seen - self.anchor))]
        lead = seen[_squared_norms(seen - far) <= radius * radius].mean(axis=0)
        if self.lead_history and math.dist(lead, self.lead_history[-1][1]) > jump:
            self.lead_history = []
        self.lead_history = (self.lead_history + [(time_s, lead)])[-window:]
        self.lead_slope, self.lead_velocity = _velocities(self.lead_history)

    def course_velocity(self) -> np.ndarray:
        """The velocity the obstacle's course is predicted with: the direction of the
        least-squares slopes (of the lead where it runs ahead, as `approach_velocity`
        chooses), at the speed of `approach_velocity`, the faster of the slope and the
        newest-frame fit. The fit's direction is noisy (a hand passing at 0.6 m/s read
        anywhere up to 60° off its course, 5 cm voxels at 15 Hz); the slopes' speed lags
        a hand that speeds up by 1-1.5 frames (a 1.5 m/s reach read 0.5 m/s with
        0.5 m to go, and touched the arm)."""
        v, lead = self.velocity, self.lead_slope
        speed, lead_speed = math.hypot(*v), math.hypot(*lead)
        if lead_speed > speed > 0 and float(v @ lead) >= 0.7 * speed * lead_speed:
            v, speed = lead, lead_speed
        if speed <= 0:
            return v
        return v * (max(speed, math.hypot(*self.approach_velocity())) / speed)

    def approach_velocity(self) -> np.ndarray:
        """The velocity Eq. 2 uses: the centroid's, or the lead's where the lead runs
        ahead in about the same direction (only for an obstacle already moving as a
        whole, so a still one whose visible part flickers stays still), at most
        `LEAD_SPEED_CAP` times the centroid's speed (a hand at the end of a straight arm
        from a still shoulder moves at twice the centroid's). Both from `_velocities`."""
        v, lead = self.velocity_now, self.lead_velocity
        speed, lead_speed = math.hypot(*v), math.hypot(*lead)
        if lead_speed > speed > 0 and float(v @ lead) >= 0.7 * speed * lead_speed:
            return lead * min(1.0, LEAD_SPEED_CAP * speed / lead_speed)
        return v


def _squared_norms(rows: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", rows, rows)


#: The lead's speed counts up to this multiple of its obstacle's centroid speed.
LEAD_SPEED_CAP = 3.0


@dataclass
class RiskReport:
    """What the reflex layer saw in one frame."""

    time: float
    tracks: int
    #: Highest risk D over approaching obstacles (0 when none), its obstacle's speed
    #: and clearance, and the closest points (robot, obstacle) for a move-away.
    risk: float
    speed: float
    clearance: float
    on_robot: np.ndarray | None
    on_obstacle: np.ndarray | None
    #: ISO/TS 15066 protective separation distance for that obstacle and the robot's
    #: current speed (information only), and whether the separation is below it.
    protective_separation: float
    ssm_violated: bool
    compute_s: float
    #: Whether that obstacle moves towards the robot.
    approaching: bool = False
    #: The robot link holding `on_robot` (-1: unknown).
    link: int = -1
    #: That obstacle's own velocity (m/s, world frame; its lead's where that runs ahead, see
    #: `ObstacleTrack.approach_velocity`) and its voxels.
    velocity: np.ndarray | None = None
    voxels: np.ndarray | None = None
    #: (3, dof) Jacobian of `on_robot` on `link` at `q`, when the closing speed needed
    #: it (a move-away from the same `q` reuses it), and the joint state of the report.
    jacobian: np.ndarray | None = None
    q: np.ndarray | None = None

    def fires(self, threshold: float, min_separation: float = 0.0) -> bool:
        """Eq. 3 (risk ≥ T), or an approaching obstacle closer than `min_separation`
        (a slow hand's risk stays below T until it touches)."""
        return self.risk >= threshold or (self.approaching and self.clearance < min_separation)


#: A voxel's offset to itself and its 26 neighbours, in voxels.
_NEIGHBOURS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)], dtype=np.float64)


class ObstacleTracker:
    """Tracks clusters of current-obstacle voxels and rates their risk (Eq. 2)."""

    def __init__(
        self,
        robot,
        resolution: float,
        *,
        beta: float = 1.5,
        min_voxels: int = 3,
        gate: float = 0.35,
        window: int = 5,
        still_speed: float = 0.1,
        lead_window: int = 5,
        lead_radius: float = 0.08,
    ) -> None:
        if not (lead_window >= 2 and window >= 2 and lead_radius >= 0):
            raise ValueError(
                f"need window >= 2, lead_window >= 2 and lead_radius >= 0, got {window}, {lead_window}, {lead_radius}"
            )
        self.robot = robot
        #: Frames and radius (m) of the lead point's velocity (`ObstacleTrack.observe_lead`).
        self.lead_window = lead_window
        self.lead_radius = lead_radius
        #: Obstacles slower than this (m/s) are still: the planner keeps clear of them.
        self.still_speed = still_speed
        self.resolution = resolution
        self.beta = beta
        self.min_voxels = min_voxels
        #: Largest centroid jump (m) between frames that still counts as the same
        #: obstacle (1.6 m/s at 15 Hz moves 0.11 m; a cluster's visible part shifts more).
        self.gate = gate
        #: Frames of the centroid's velocity fits. Longer windows read slow hands less
        #: noisily and fast reaches later: 5 frames (0.27 s at 15 Hz) had fewer reflexes
        #: than 4 and no more contacts over ten seeds of either scenario; 6 touched the
        #: person twice (docs/design/reflexes.md).
        self.window = window
        self.tracks: list[ObstacleTrack] = []
        self._static: np.ndarray = np.zeros(0, dtype=np.int64)
        self._dynamic: np.ndarray = np.zeros((0, 3))
        self._next_id = 0

    def _keys(self, centres: np.ndarray) -> np.ndarray:
        return voxel_codes(centres, self.resolution)

    def learn_static(self, centres: np.ndarray) -> None:
        """Add voxels (e.g. the current obstacles during a warm-up without people) to
        the static scene, grown by one voxel in every direction for sensor noise."""
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        grown = (centres[:, None, :] + _NEIGHBOURS[None] * self.resolution).reshape(-1, 3)
        self._static = np.union1d(self._static, self._keys(grown))

    def dynamic_voxels(self, centres: np.ndarray) -> np.ndarray:
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        if not len(self._static) or not len(centres):
            return centres
        # `_static` is sorted and unique (union1d): membership by binary search, ~1000x
        # faster than np.isin, which sorts both sides every frame.
        keys = self._keys(centres)
        at = np.minimum(np.searchsorted(self._static, keys), len(self._static) - 1)
        return centres[self._static[at] != keys]

    @property
    def last_dynamic(self) -> np.ndarray:
        """The voxels of the last frame that are not static scene (every cluster)."""
        return self._dynamic

    def update(
        self,
        time_s: float,
        centres: np.ndarray,
        q: np.ndarray,
        robot_speed: float = 0.0,
        qd: np.ndarray | None = None,
        points: np.ndarray | None = None,
    ) -> RiskReport:
        """One frame: the current obstacles' voxel centres, the robot's joint state and
        its speed (m/s, for the ISO figure). Returns the frame's risk report.

        With the frame's `points` (those the map was updated with), obstacles are
        followed by where in their voxels they were seen (`cloud.voxel_means`) rather than
        by voxel centres, which jump a whole voxel at a time.

        With the joint velocities `qd`, v in Eq. 2 is the obstacle's velocity relative to
        the robot's closest point (the closing speed that braking distances are about;
        the paper uses the obstacle's own velocity, which is what `qd=None` gives)."""
        t0 = time.perf_counter()
        voxels = self._dynamic = self.dynamic_voxels(centres)
        clusters: list[tuple[np.ndarray, np.ndarray]] = []
        if len(voxels):
            positions = voxels if points is None else voxel_means(voxels, points, self.resolution)
            labels = earcore.cluster_points(voxels, self.resolution)
            counts = np.bincount(labels)
            clusters = [(voxels[labels == i], positions[labels == i]) for i in np.flatnonzero(counts >= self.min_voxels)]
        self._associate(time_s, clusters)
        best = None
        for track in self.tracks:
            c = self.robot.clearance_to_voxels(track.voxels, self.resolution, q)
            d = float(c["distance"])
            towards = c["on_robot"] - c["on_obstacle"]
            # Only an obstacle that itself moves towards the robot is a reflex matter (the
            # planner keeps the robot's own path clear of still ones); its speed is then
            # taken relative to the robot's closest point.
            # A still obstacle's voxel centroid jitters (noise, and the robot hiding parts
            # of it): below `still_speed` it does not count as coming by itself.
            moving = math.hypot(*track.velocity) >= self.still_speed
            own = v = track.approach_velocity() if moving else track.velocity
            approaching = (moving and float(v @ towards) > 0) if d > 0 else True
            track.clearance, track.on_robot, track.on_obstacle, track.link = d, c["on_robot"], c["on_obstacle"], int(c["link"])
            track.moving, track.approaching = moving, approaching
            track.own_velocity = track.course_velocity() if moving else np.zeros(3)
            jacobian = None
            if approaching and qd is not None and c["link"] >= 0:
                jacobian = self.robot.jacobian(q, int(c["link"]), c["on_robot"])
                v = v - jacobian @ qd
            speed = math.hypot(*v)
            risk = speed**2 / (self.beta * max(d, 1e-3)) if approaching else 0.0
            if best is None or risk > best[0] or (risk == best[0] and d < best[2]):
                best = (
                    risk, speed, d, c["on_robot"], c["on_obstacle"], approaching and speed > 0.05, int(c["link"]),
                    own, track.voxels, jacobian,
                )
        frame_period = 1.0 / 15.0
        if best is None:
            sp = protective_separation(0.0, robot_speed, reaction_time=frame_period, stopping_time=0.0)
            return RiskReport(time_s, 0, 0.0, 0.0, float("inf"), None, None, sp, False, time.perf_counter() - t0)
        risk, speed, d, on_robot, on_obstacle, approaching, link, velocity, track_voxels, jacobian = best
        sp = protective_separation(speed, robot_speed, reaction_time=frame_period, stopping_time=0.2)
        return RiskReport(
            time_s, len(self.tracks), risk, speed, d, on_robot, on_obstacle, sp, d < sp,
            time.perf_counter() - t0, approaching, link, velocity, track_voxels, jacobian, np.array(q, dtype=np.float64),
        )

    def _associate(self, time_s: float, clusters: list[tuple[np.ndarray, np.ndarray]]) -> None:
        centroids = [seen.mean(axis=0) for _, seen in clusters]
        unmatched = list(range(len(clusters)))
        kept = []
        for track in self.tracks:
            if not unmatched:
                break
            dists = [math.dist(centroids[i], track.centroid) for i in unmatched]
            j = int(np.argmin(dists))
            if dists[j] <= self.gate:
                i = unmatched.pop(j)
                track.history = (track.history + [(time_s, centroids[i])])[-self.window :]
                track.voxels, track.positions = clusters[i]
                track.velocity, track.velocity_now = _velocities(track.history)
                kept.append(track)
        for i in unmatched:
            voxels, positions = clusters[i]
            kept.append(ObstacleTrack(self._next_id, [(time_s, centroids[i])], voxels, positions, anchor=centroids[i]))
            self._next_id += 1
        for track in kept:
            track.observe_lead(time_s, self.lead_window, self.lead_radius, self.gate)
        self.tracks = kept


def _velocities(history: list[tuple[float, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Velocities of positions over time: the least-squares slope (zero with one
    sample), and one for Eq. 2 that does not lag a reach that speeds up: of the slope
    and the velocity at the newest sample from a least-squares constant-acceleration
    fit (four samples or more), the faster. The fit alone follows a hand's
    acceleration but amplifies voxel quantisation (~3.5x the slope's noise); for safety
    an underestimate is what must not happen, so the larger one counts, at the price of
    an upward bias (a steady 1.2 m/s blob of 5 cm voxels reads up to ~1.5x, more
    reflexes)."""
    slope_weights, fit_weights = _velocity_weights([h[0] for h in history])
    if slope_weights is None:  # one sample, or every sample at one time
        return np.zeros(3), np.zeros(3)
    p = np.array([h[1] for h in history])
    slope = np.array(slope_weights) @ p
    if fit_weights is None:
        return slope, slope.copy()
    fit = np.array(fit_weights) @ p
    return slope, (fit if float(fit @ fit) > float(slope @ slope) else slope.copy())


def _velocity_weights(times: list[float]) -> tuple[list[float] | None, list[float] | None]:
    """Both velocities of `_velocities` are linear in the positions: the weights of
    the least-squares slope and of the constant-acceleration fit's velocity at the
    newest sample (None where there are too few samples or distinct times). In plain
    floats: for a handful of samples numpy's per-call cost would be most of the reflex
    layer's tracking time."""
    n = len(times)
    if n < 2 or max(times) == min(times):  # (t - mean need not round to 0 then)
        return None, None
    mean = sum(times) / n
    tc = [t - mean for t in times]
    denom = sum(c * c for c in tc)
    if denom <= 0:  # (times apart by less than the square root of the smallest double)
        return None, None
    slope = [c / denom for c in tc]
    if n < 4:
        return slope, None
    # Fit p(t) = a + b t + c t² (t from the newest sample) by the normal equations;
    # b's weights are the middle row of (DᵀD)⁻¹ Dᵀ, from the 3×3 inverse by cofactors.
    t = [x - times[-1] for x in times]
    s1, s2 = sum(t), sum(x * x for x in t)
    s3, s4 = sum(x**3 for x in t), sum(x**4 for x in t)
    s0 = float(n)
    det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    if not abs(det) > 1e-12 * max(s0 * s2 * s4, 1e-300):  # fewer than three distinct times
        return slope, None
    # Middle row of the inverse (symmetric matrix): cofactors of the second column.
    r0 = -(s1 * s4 - s2 * s3) / det
    r1 = (s0 * s4 - s2 * s2) / det
    r2 = -(s0 * s3 - s1 * s2) / det
    return slope, [r0 + r1 * x + r2 * x * x for x in t]


def predicted_course(
    voxels: np.ndarray, velocity: np.ndarray, horizon: float, voxel_size: float, *, step: float = 1 / 30, grow: bool = False
) -> np.ndarray:
    """The voxels an obstacle sweeps when its `voxels` (centres) are carried on at
    `velocity` (m/s) for `horizon` seconds, every `step`: centres on the grid of
    `voxel_size` (consecutive steps overlap), (M, 3); with `grow`, with every voxel's 26
    neighbours added."""
    voxels = np.asarray(voxels, dtype=np.float64).reshape(-1, 3)
    if not len(voxels):
        return voxels
    times = np.arange(0.0, horizon + step / 2, step)
    swept = (voxels[None, :, :] + times[:, None, None] * np.asarray(velocity, dtype=np.float64)[None, None, :]).reshape(-1, 3)
    cells = np.unique(np.floor(swept / voxel_size), axis=0)
    if grow:
        cells = np.unique((cells[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3), axis=0)
    return (cells + 0.5) * voxel_size



def predicted_contact(
    robot,
    voxels: np.ndarray,
    velocity: np.ndarray,
    committed: np.ndarray,
    horizon: float,
    voxel_size: float,
    *,
    margin: float = 0.05,
    step: float = 1 / 30,
) -> bool:
    """Whether an obstacle's course (`predicted_course` of its `voxels` at `velocity`
    over `horizon` seconds) meets the robot anywhere along its `committed` joint states
    over the same horizon (M, dof), with `margin` (m) around the obstacle for what the
    cameras miss of it. The prediction rule: a hand that passes beside the robot's
    way, or moves away, does not fire; one whose course crosses it does."""
    swept = predicted_course(voxels, velocity, horizon, voxel_size, step=step)
    if not len(swept):
        return False
    qs = np.asarray(committed, dtype=np.float64).reshape(-1, robot.dof)
    return bool(robot.touches_voxels(swept, voxel_size + 2 * margin, qs).any())


@dataclass
class ReflexMove:
    """A reflex: the kind ("backtrack" or "move_away") and the joint path to run."""

    kind: str
    path: np.ndarray


def path_is_clear(
    robot, tree, path: np.ndarray, resolution: float, dynamic, voxel_size: float, escape: bool, *, sampled: bool = False
) -> bool:
    """Every edge of `path` free on `tree` and, when given, clear of the `dynamic` voxel
    boxes (checked exactly at configurations ≤ `resolution` apart). With `escape` (the
    robot already touches a dynamic obstacle) the path must instead take the robot
    steadily away from them: clearance never shrinking, larger at the end. `sampled`:
    the path is a curve already sampled at most `resolution` apart; its samples are
    checked as they are."""
    if sampled:
        if np.any(robot.check_configurations(tree, path)):
            return False
    elif np.any(robot.check_motions(tree, path[:-1], path[1:], resolution)):
        return False
    if dynamic is None or not len(dynamic):
        return True
    qs = path if sampled else densify(path, resolution, per_joint=True)
    if escape:
        d = robot.clearance_to_voxels(dynamic, voxel_size, qs)["distance"]
        return bool(np.all(np.diff(d) >= -1e-3) and d[-1] > d[0])
    # A yes/no needs no distances (cylinders near a box would need iterative ones).
    return not robot.touches_voxels(dynamic, voxel_size, qs).any()


def _leads_away(robot, q_end: np.ndarray, report: RiskReport, voxel_size: float, horizon: float) -> bool:
    """Whether the robot at `q_end` is farther from the reported obstacle than it is now,
    both from the obstacle's voxels now and from them moved on by its velocity over
    `horizon` seconds (True when the report carries no obstacle)."""
    if report.voxels is None or not len(report.voxels) or not np.isfinite(report.clearance):
        return True
    voxels = np.asarray(report.voxels, dtype=np.float64)
    shifted = voxels + (np.zeros(3) if report.velocity is None else np.asarray(report.velocity) * horizon)
    ends = robot.clearance_to_voxels(np.vstack([voxels, shifted]), voxel_size, q_end)
    return bool(float(ends["distance"]) > report.clearance)


def plan_reflex(
    robot,
    tree,
    q: np.ndarray,
    executed: np.ndarray,
    report: RiskReport,
    *,
    backtrack_fraction: float = 0.1,
    move_away_distance: float = 0.15,
    resolution: float = 0.02,
    end_effector_link: int | None = None,
    dynamic: np.ndarray | None = None,
    voxel_size: float = 0.05,
    escape: bool = False,
    prefer_move_away: bool = False,
    horizon: float = 0.3,
    check_move_away: bool = True,
) -> ReflexMove | None:
    """Paper II's reflex for the current state: backtrack along the last
    `backtrack_fraction` of `executed` (the joint states passed, oldest first) if that
    path is free, else move the robot's point closest to the obstacle (`report.on_robot`
    on `report.link`; the end-effector when unknown) `move_away_distance` straight away
    from the closest obstacle point.
    None when neither move is free (the caller stops the robot).

    Moves are checked against `tree`; for a fast reflex pass the static scene as `tree`
    (its collision index is built once and cached) and the frame's moving obstacles as
    `dynamic` voxel centres (edge `voxel_size`), checked exactly without an index, so a
    reflex never waits for the live map's index to be rebuilt. `escape`: the robot
    touches a dynamic obstacle already; accept moves that steadily increase the
    clearance to it (see `path_is_clear`). `prefer_move_away`: skip the backtrack (an
    obstacle this close is escaped fastest straight away from it). A backtrack is taken
    only if it ends farther from the obstacle than the robot is now, with the obstacle
    where it is and where its velocity takes it in `horizon` seconds: the executed path
    can lead back towards the obstacle (a hand coming from behind). `check_move_away`:
    False returns the move away unchecked, for a caller that checks the motion the
    robot will really make towards its end (see `Executive._reflex_motion`)."""
    q = np.asarray(q, dtype=np.float64)
    executed = np.asarray(executed, dtype=np.float64).reshape(-1, len(q))
    if len(executed) >= 2 and not prefer_move_away:
        seg = np.linalg.norm(np.diff(executed, axis=0), axis=1)
        total = seg.sum()
        if total > 1e-6:
            # Walk back from the end until the fraction of the executed length is covered.
            back = cumsum0(seg[::-1])
            n = int(np.searchsorted(back, backtrack_fraction * total))
            tail = np.vstack([q[None], executed[::-1][: n + 1]])
            tail = without_repeats(tail, 1e-9)
            # The cheap test first: in Exp. 3 runs the backtrack was clear but led back
            # towards the hand in 25 of 26 reflexes (0.06 ms to tell, against 0.2 ms for
            # the path check).
            if (
                len(tail) >= 2
                and _leads_away(robot, tail[-1], report, voxel_size, horizon)
                and path_is_clear(robot, tree, tail, resolution, dynamic, voxel_size, escape)
            ):
                return ReflexMove("backtrack", tail)
    if report.on_obstacle is None:
        return None
    # Move the robot's point closest to the obstacle straight away from it (the paper
    # moves the end-effector; when a forearm is the part in danger, moving the tool
    # away can bring the forearm closer).
    jac = None
    if report.on_robot is not None and report.link >= 0 and end_effector_link is None:
        link, position = report.link, np.asarray(report.on_robot, dtype=np.float64)
        if report.jacobian is not None and report.q is not None and np.array_equal(report.q, q):
            jac = report.jacobian
    else:
        link = end_effector_link if end_effector_link is not None else len(robot.link_names) - 1
        position = robot.fk(q)[link, :3, 3]
    if jac is None:
        jac = robot.jacobian(q, link, position)
    away = position - report.on_obstacle
    if report.clearance <= 0 and dynamic is not None and len(dynamic):
        # Touching: the closest points lie inside each other and their difference can
        # point into the obstacle; leave from the centre of its nearby voxels instead.
        near = dynamic[np.linalg.norm(dynamic - position, axis=1) < 0.2]
        if len(near):
            away = position - near.mean(axis=0)
    norm = np.linalg.norm(away)
    if norm < 1e-9:
        return None
    step = away / norm * move_away_distance
    # Damped least squares: the joint step that moves the end-effector by `step`.
    damping = 0.05
    dq = jac.T @ np.linalg.solve(jac @ jac.T + damping**2 * np.eye(3), step)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    target = np.clip(q + dq, lo, hi)
    path = np.stack([q, target])
    if check_move_away and not path_is_clear(robot, tree, path, resolution, dynamic, voxel_size, escape):
        return None
    return ReflexMove("move_away", path)


def occupied_cells_near(tree, point: np.ndarray, radius: float) -> np.ndarray:
    """Centres of the occupied finest-resolution cells of `tree` within `radius` of
    `point` (pruned nodes split into their cells by the core)."""
    point = np.asarray(point, dtype=np.float64)
    centres, _ = tree.leaves_at_full_depth(point - radius, point + radius, occupied_only=True)
    return centres[np.linalg.norm(centres - point, axis=1) <= radius]


def plan_recovery(
    robot,
    tree,
    q: np.ndarray,
    *,
    radius: float = 0.3,
    move_away_distance: float = 0.15,
    resolution: float = 0.02,
) -> ReflexMove | None:
    """The robot at `q` touches occupied voxels of `tree` (a start in collision, which no
    planner can leave): a move away from where it touches along which the clearance to
    every occupied cell within `radius` of that point never shrinks and grows by the end
    (`plan_reflex`'s escape), and which runs into nothing else of the map (checked against
    a copy without those cells). None when nothing is touched or no such move exists."""
    q = np.asarray(q, dtype=np.float64)
    c = robot.clearance(tree, q)
    if not np.isfinite(c["distance"]):
        return None
    near = occupied_cells_near(tree, c["on_robot"], radius)
    if not len(near):
        return None
    rest = tree.copy()
    rest.set_log_odds(near, -math.inf)  # those cells free, at the lower clamp
    report = RiskReport(
        0.0, 0, 0.0, 0.0, float(c["distance"]), c["on_robot"], c["on_obstacle"], 0.0, False, 0.0, link=int(c["link"])
    )
    return plan_reflex(
        robot, rest, q, np.zeros((0, len(q))), report, move_away_distance=move_away_distance,
        resolution=resolution, dynamic=near, voxel_size=tree.resolution, escape=True,
    )
