"""Runs a task in the cell: A-B-A trips planned predictively (danger map + reflexes,
Paper II) or reactively (the paper's baseline), executed as time-parameterised
trajectories, with the per-trip figures of Table II.

The loop calls `control(dt)` before every simulation step (it sends the joint
velocities) and `on_frame(time)` after every map frame (reflexes, re-planning).
"""

from __future__ import annotations

import gc
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import numpy as np

import earcore
from earcore.planning.errors import PlanningError, StartInCollision
from earcore.planning.follower import Follower
from earcore.planning.predictive import PlanChoice, PredictivePlanner, ReactivePlanner
from earcore.planning.reflex import (
    ObstacleTracker,
    RiskReport,
    path_is_clear,
    plan_recovery,
    plan_reflex,
    predicted_contact,
    predicted_course,
)
from earcore.planning.separation import ssm_speed_limit
from earcore.planning.trajectory import StopThenMove, Trajectory, Transfer, braking, path_length, time_parameterize, transfer

__all__ = ["REACTION_TIME", "Executive", "TripReport"]

#: The reflex layer's reaction time (s): a map frame (15 Hz) plus its compute (5 ms).
REACTION_TIME = 1.0 / 15.0 + 0.005


@contextmanager
def _collector_paused():
    """Python's cyclic garbage collector paused for a latency-critical step: a full
    collection walks the whole heap (milliseconds in a long run), and the reflex should
    not wait for it; it runs after the command instead."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@dataclass
class TripReport:
    """One move to a goal (Table II's row entries)."""

    goal: int
    start_time: float
    planning_time: float = 0.0
    optimisation_time: float = 0.0
    execution_time: float = 0.0
    #: Executed path: joint space (rad) and the end-effector's (m).
    path_length: float = 0.0
    tool_path_length: float = 0.0
    plans: int = 0
    stops: int = 0
    reflexes: int = 0
    #: Plans halted by separation monitoring because the prediction rule saw an obstacle's
    #: course meet them, while braking still kept clear of it (instead of a reflex).
    protective_stops: int = 0
    collisions: int = 0
    #: Smallest true robot-person distance during the trip (m; inf without a person).
    min_clearance: float = float("inf")
    completed: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class _Motion:
    trajectory: Trajectory | StopThenMove | Transfer
    start: float
    kind: str  # "plan" | "reflex" (move away) | "backtrack"
    #: The motion's own clock (s): how far along its timing the reference is. It runs
    #: at the speed scale of separation monitoring, real time when nobody is near.
    elapsed: float = 0.0


@dataclass
class ExecutiveLog:
    """Everything the recording shows: planned paths, reflexes, risk per frame."""

    plans: list[tuple[float, np.ndarray]] = field(default_factory=list)
    reflexes: list[dict] = field(default_factory=list)
    #: Every frame's risk report, without the obstacle's voxels and the Jacobian (kept
    #: per frame for a whole run they grew the heap that garbage collections walk).
    risk: list[RiskReport] = field(default_factory=list)
    #: (time, message) of every planning call that produced no path.
    failures: list[tuple[float, str]] = field(default_factory=list)
    #: Every plan not started because the way the arm would take onto it from its
    #: velocity then was not free ("rejoined": False where the arm would not have got
    #: back onto the path within the follower's horizon).
    refused_plans: list[dict] = field(default_factory=list)
    #: Times of the protective stops (`Executive._fires`).
    protective_stops: list[float] = field(default_factory=list)


class Executive:
    def __init__(
        self, cell, pipeline, config, goals: list[np.ndarray], *, seed: int = 0, person_distance: Callable[[], float] | None = None
    ) -> None:
        if config.mode not in ("predictive", "reactive"):
            raise ValueError(f"planning mode must be 'predictive' or 'reactive', got {config.mode!r}")
        self.cell = cell
        self.pipeline = pipeline
        self.config = config
        self.robot = cell.model
        self.tree = pipeline.tree
        self.goals = [np.asarray(g, dtype=np.float64) for g in goals]
        #: Ground truth for the trips' contact figures (simulation): the true distance
        #: between the robot and the person now; None leaves them unscored.
        self.person_distance = person_distance
        kind = PredictivePlanner if config.mode == "predictive" else ReactivePlanner
        self.planner = kind(
            self.robot,
            self.tree,
            time_limit=config.time_limit,
            attempts=config.attempts,
            resolution=config.resolution,
            seed=seed,
        )
        self.reflexes_on = config.mode == "predictive" and config.reflexes
        self.tracker = ObstacleTracker(self.robot, self.tree.resolution, beta=config.beta)
        #: The robot grown by `person_margin`, kept that far from the tracked obstacles.
        self.grown_robot = None
        margin = config.person_margin
        if self.reflexes_on and margin > 0:
            from earcore.robots import load

            self.grown_robot = load(cell.config.robot, padding=cell.config.padding + margin)
            self.grown_robot.base = self.robot.base
        person = getattr(cell, "person", None)
        if self.reflexes_on and person is not None and person.arrive < config.warmup:
            # The tracker learns the static scene in the warm-up: a person there becomes scenery.
            warnings.warn(
                f"the person arrives at {person.arrive} s, before the planner's warm-up ends ({config.warmup} s): "
                "the reflexes will take their resting arm for static scene",
                stacklevel=2,
            )
        self.v_max = cell.controller.max_velocity
        self.a_max = cell.controller.max_acceleration
        self.motion: _Motion | None = None
        self.command = np.zeros(self.robot.dof)
        self.follower = Follower(self.v_max, self.a_max)
        self.goal_index = 0
        self.trip: TripReport | None = None
        self.trips: list[TripReport] = []
        self.executed: list[np.ndarray] = []
        #: The states that brought the robot here on this trip, minus what a backtrack
        #: took back (a second backtrack goes further back, never forward again).
        self.progress: list[np.ndarray] = []
        self.log = ExecutiveLog()
        #: Seconds from a frame's arrival to the reflex command (tracking + planning).
        self.reflex_latencies: list[float] = []
        #: The same frames' CPU time on the reflex's thread: what the reflex computes,
        #: without the time the machine gave to others (a shared VM stalls a thread now
        #: and then, which wall-clock latency includes).
        self.reflex_cpu: list[float] = []
        #: Separation monitoring: the path speed's scale wanted by the last frame
        #: (`ssm_scale`), the one the reference runs at now (it follows the wanted one
        #: within the acceleration limits), and each frame's CPU time for it.
        self.ssm_target = 1.0
        self.speed_scale = 1.0
        self.ssm_cpu: list[float] = []
        self.ssm_slowed_frames = 0
        #: Whether this frame's reflex layer made a protective stop, and the predicted
        #: courses (voxel centres) that made it.
        self._halted = False
        self._courses = np.zeros((0, 3))
        self._halting_tracks: list = []
        #: Whether the last frame made a protective stop (stops are counted per episode).
        self._stopping = False
        self._last_replan = 0.0
        self._in_contact = False
        #: The map as it was at the end of the warm-up (the static scene), for reflexes.
        self.static_tree = None

    # --- helpers -----------------------------------------------------------------

    def timed(self, path: np.ndarray, *, plan: bool) -> Trajectory:
        """`path` timed from here, keeping the speed the robot already has along its
        first direction. A plan's corners are rounded where the rounded path is still
        valid; reflex moves run as they are (no time to check a rounding)."""
        if plan:
            path = self.planner.rrt.rounded(path, self.config.blend_deviation)
        first = path[1] - path[0] if len(path) > 1 else np.zeros(len(path[0]))
        norm = float(np.linalg.norm(first))
        along = float(self.command @ first) / norm if norm > 0 else 0.0
        return time_parameterize(
            path, self.v_max, self.a_max, control_period=self.cell.config.time_step, initial_speed=along,
            straight_share=self.config.straight_share,
        )

    def way_onto(self, trajectory, t: float = 0.0) -> tuple[np.ndarray, bool]:
        """The way the robot goes on `trajectory` from its time t, starting where it is
        at the velocity it has: the follower's states until it is back on the reference
        (one step when it is on it already; `Follower.rollout`), then the reference's
        knots after that; and whether it got back on within the roll-out's horizon.
        While the arm moves across a new path, the follower brakes that velocity first
        and the arm leaves the path it was planned on (up to 0.6 rad for a fast swing):
        what is checked and costed has to be this way, not the path."""
        rollout = self.follower.rollout(
            trajectory, self.cell.q, self.command, self.cell.config.time_step, self.robot.joint_limits, start=t,
        )
        return np.vstack([rollout.states, trajectory.remaining_path(t + rollout.duration)[1:]]), rollout.rejoined

    def start_plan(self, path: np.ndarray, *, cheaper_than: float | None = None) -> bool:
        """Run the planned `path` from here if the way the arm will take (`way_onto`) is free
        on the map and the keep-out, as the planner checks paths, and, given
        `cheaper_than`, costs less than that on the danger map. A plan refused for its
        way is logged. Returns whether the plan started."""
        trajectory = self.timed(path, plan=True)
        way, rejoined = self.way_onto(trajectory)
        if cheaper_than is not None and self.planner.cost(way) >= cheaper_than:
            return False
        if not (rejoined and self.planner.rrt.path_is_valid(way)):
            self.log.refused_plans.append({"time": self.cell.time, "rejoined": rejoined})
            return False
        previous, scale = self.motion, self.speed_scale
        self.motion = _Motion(trajectory, self.cell.time, "plan")
        # Its timing starts from the arm's real speed: it runs at full scale, slowed from
        # there by what separation monitoring asks for it.
        self.speed_scale = 1.0
        if self._halted:
            # Out of a protective stop only onto a motion the predicted courses do not meet
            # (the keep-out leaves out what is near the arm's start and goal).
            free = self.ssm_scale(self.cell.q)
            if self._meets(self._halting_tracks, *self._committed(self.cell.q, free, REACTION_TIME + self.config.stop_lookahead)):
                self.motion, self.speed_scale = previous, scale
                return False
            self._halted = False
        if self.reflexes_on:
            self.ssm_target = self.ssm_scale(self.cell.q)
        return True

    def remaining_way(self) -> np.ndarray | None:
        """The way the robot will go on its motion from here (`way_onto`): checked every
        frame, so a map that changes during a transition is seen where the arm goes."""
        if self.motion is None:
            return None
        return self.way_onto(self.motion.trajectory, self.motion.elapsed)[0]

    def _plan(self, q: np.ndarray) -> PlanChoice | None:
        goal = self.goals[self.goal_index]
        try:
            choice = self.planner.plan(q, goal)
        except StartInCollision as exc:
            self.log.failures.append((self.cell.time, str(exc)))
            self._recover(q)
            return None
        except PlanningError as exc:
            self.log.failures.append((self.cell.time, str(exc)))
            return None
        finally:
            if self.trip is not None:
                self.trip.plans += 1
        if self.trip is not None:
            self.trip.planning_time += choice.planning_time
            self.trip.optimisation_time += choice.optimisation_time
        self.log.plans.append((self.cell.time, choice.path))
        return choice

    def _recover(self, q: np.ndarray) -> None:
        """The robot touches an occupied voxel (no plan can start there): move away from
        it, steadily increasing the clearance to the occupied cells around the contact,
        into nothing else of the map (`plan_recovery`)."""
        move = plan_recovery(
            self.robot, self.tree, q,
            move_away_distance=self.config.move_away_distance, resolution=self.config.resolution,
        )
        if move is not None:
            # Its way is not checked: the arm touches the map where it starts, so every
            # way out begins in collision (the move itself only gains clearance).
            self.motion = _Motion(self.timed(move.path, plan=False), self.cell.time, "reflex")
            self.log.reflexes.append({"time": self.cell.time, "kind": "recover_" + move.kind})

    def _new_trip(self) -> None:
        self.goal_index = (self.goal_index + 1) % len(self.goals)
        self.trip = TripReport(goal=self.goal_index, start_time=self.cell.time)
        self.executed = [self.cell.q.copy()]
        self.progress = [self.cell.q.copy()]
        self._last_replan = self.cell.time
        choice = self._plan(self.cell.q)
        if choice is not None:
            self.start_plan(choice.path)

    def _finish_trip(self) -> None:
        trip = self.trip
        assert trip is not None, "a trip is finished only while one runs"
        trip.execution_time = self.cell.time - trip.start_time
        path = np.asarray(self.executed)
        trip.path_length = path_length(path)
        tool = self.robot.fk(path)[:, -1, :3, 3]
        trip.tool_path_length = float(np.linalg.norm(np.diff(tool, axis=0), axis=1).sum())
        trip.completed = True
        self.trips.append(trip)
        self.trip = None
        self.motion = None

    # --- the loop's two calls ------------------------------------------------------

    def control(self, dt: float) -> None:
        """Joint velocities for the next step: track the motion's reference, within the
        speed and acceleration limits (a stop brakes at the acceleration limit)."""
        q = self.cell.q
        if self.trip is None and self.cell.time >= self.config.warmup:
            self._new_trip()
        now = ahead = None
        if self.motion is not None:
            scale = self._advance_scale(dt)
            t = self.motion.elapsed
            now, ahead = self.motion.trajectory.sample(np.array([t, t + scale * dt]))
            self.motion.elapsed += scale * dt
        self.command = self.follower.command(q, self.command, now, ahead, dt)
        self.cell.command_velocities(self.command)

    def after_step(self) -> None:
        q = self.cell.q
        if self.trip is None:
            return
        self.executed.append(q.copy())
        if self.motion is None or self.motion.kind != "backtrack":
            self.progress.append(q.copy())
        if self.motion is None:
            return
        done = self.motion.elapsed >= self.motion.trajectory.duration
        settled = np.abs(self.motion.trajectory.positions[-1] - q).max() < 1e-3
        if done and settled:
            if self.motion.kind == "plan" and np.abs(self.goals[self.goal_index] - q).max() < 1e-3:
                self._finish_trip()
            else:
                self.motion = None  # a reflex ended: on_frame plans on from here

    def on_frame(self) -> RiskReport | None:
        """After a map frame: contacts (ground truth), reflexes, re-planning."""
        cell, q = self.cell, self.cell.q
        if self.trip is None:
            if cell.time < self.config.warmup:
                self.tracker.learn_static(self.tree.current_obstacles()[0])
            return None
        if self.static_tree is None:
            self.static_tree = self.tree.copy()
            self.robot.check_configurations(self.static_tree, q)  # builds its index now, not in a reflex
        self._score_contact()
        report = None
        if self.reflexes_on:
            # The core runs the reflex's small batches (a few dozen configurations) on this
            # thread: waking workers costs more, milliseconds when another process holds the cores.
            with _collector_paused(), earcore.threads(1):
                report, fired = self._reflex_layer(cell, q)
            self.log.risk.append(replace(report, voxels=None, jacobian=None))
            if fired:
                return report
        if self.motion is not None and self.motion.kind in ("reflex", "backtrack"):
            return report
        remaining = self.remaining_way()
        blocked = remaining is not None and len(remaining) > 1 and not self.planner.rrt.path_is_valid(remaining)
        # A protective stop re-plans at once, around the courses that halted it; without a
        # plan clear of them it holds on its path (`start_plan`).
        halted = self._halted and self.motion is not None and self.motion.kind == "plan"
        if self.config.mode == "reactive":
            if blocked:
                self.motion = None  # stop; re-plan once stopped
                self.trip.stops += 1
            elif self.motion is None and np.abs(self.command).max() < 1e-3:
                choice = self._plan(q)
                if choice is not None:
                    self.start_plan(choice.path)
            return report
        # Predictive: re-plan when blocked, when idle, or periodically when the danger
        # map offers a clearly cheaper path.
        if self.replan_due(blocked or halted):
            self._last_replan = cell.time
            if blocked:
                self.trip.stops += 1
            choice = self._plan(q)
            if choice is None:
                if blocked and self.motion is not None and self.motion.kind == "plan":
                    self.motion = None  # (a recovery `_plan` may have started stays)
                return report
            if blocked or halted or self.motion is None:
                if not self.start_plan(choice.path) and not (halted and not blocked):
                    self.motion = None  # stop: the arm brakes, and the next frame plans from where it is
            else:
                # Both costed along the way the arm would take; a refused switch keeps
                # the current motion.
                current = self.planner.cost(remaining) if remaining is not None and len(remaining) > 1 else 0.0
                self.start_plan(choice.path, cheaper_than=(1 - self.config.replan_gain) * current)
        return report

    def _score_contact(self) -> None:
        """Table II's contacts and closest distance, from the ground truth if given."""
        if self.person_distance is None or self.trip is None:
            return
        distance = self.person_distance()
        self.trip.min_clearance = min(self.trip.min_clearance, distance)
        contact = distance <= 0.0
        if contact and not self._in_contact:
            self.trip.collisions += 1
        self._in_contact = contact

    def replan_due(self, blocked: bool) -> bool:
        """The predictive planner's re-plan gate: when the path is blocked, when the robot
        has no motion, or every `replan_period` seconds (to look for a cheaper path)."""
        due = self.config.replan_period > 0 and self.cell.time - self._last_replan >= self.config.replan_period
        return blocked or self.motion is None or due

    def _reflex_layer(self, cell, q: np.ndarray) -> tuple[RiskReport, bool]:
        """Track the obstacles, rate the risk (Eq. 2), set the speed scale of separation
        monitoring, and make a protective stop or fire a reflex if one is due (`_fires`);
        returns the frame's report and whether a reflex fired."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        tcp_speed = self._tool_speed()
        qd = self.command if self.config.relative_velocity else None
        centres = self.tree.current_obstacles()[0]
        report = self.tracker.update(cell.time, centres, q, tcp_speed, qd, points=self.pipeline.inserted_points)
        self.planner.rrt.set_keep_out(self.grown_robot, self.tracker.last_dynamic, self.tree.resolution)
        in_reflex = self.motion is not None and self.motion.kind in ("reflex", "backtrack")
        close = report.approaching and report.clearance < self.config.min_separation
        # A running reflex is not restarted, except a backtrack the obstacle still
        # closes in on: then it becomes a move away.
        backtracking = self.motion is not None and self.motion.kind == "backtrack"
        self._halted = False
        cpu = time.thread_time()
        free = self.ssm_scale(q)
        self.ssm_cpu.append(time.thread_time() - cpu)
        rule = self._fires(report, q, close, free)
        stopping = rule == "stop"
        if stopping and not self._stopping and self.trip is not None:
            self.trip.protective_stops += 1
            self.log.protective_stops.append(cell.time)
        self._stopping = stopping
        if stopping:
            self._set_ssm_target(0.0)
            # This frame's re-plan keeps clear of the courses too (grown by a voxel: the
            # keep-out's margin is on the robot, the prediction's on the obstacle).
            self.planner.rrt.set_keep_out(
                self.grown_robot, np.vstack([self.tracker.last_dynamic, self._courses]), self.tree.resolution
            )
            self._halted = True
            return report, False
        if rule is not None and (not in_reflex or (close and backtracking)):
            # The static scene (index cached) plus this frame's moving voxels
            # (exact): no rebuild of the live map's index before the reflex.
            move = plan_reflex(
                self.robot, self.static_tree, q, np.asarray(self.progress), report,
                backtrack_fraction=self.config.backtrack_fraction,
                move_away_distance=self.config.move_away_distance,
                resolution=self.config.resolution,
                dynamic=self.tracker.last_dynamic, voxel_size=self.tree.resolution,
                prefer_move_away=close, escape=report.clearance <= 0, check_move_away=False,
            )
            if self.trip is not None:
                self.trip.reflexes += 1
            if move is not None:
                kind = "backtrack" if move.kind == "backtrack" else "reflex"
                # The robot is moving and cannot turn on the spot: run the motion it
                # will really make from here, checked as such; where that is not clear,
                # the planned move timed from here, if the way the follower takes onto
                # it is clear.
                motion = self._reflex_motion(q, move, escape=report.clearance <= 0)
                if motion is None:
                    motion = self.timed_reflex(move.path, escape=report.clearance <= 0)
                if motion is not None:
                    self.motion = _Motion(motion, cell.time, kind)
                else:
                    move, self.motion = None, None  # nothing free: stop where we are
            else:
                self.motion = None  # nothing free: stop where we are
            if move is not None and move.kind == "backtrack":
                # Take the undone stretch off the progress stack.
                del self.progress[max(1, len(self.progress) - (len(move.path) - 1)):]
            self.reflex_latencies.append(time.perf_counter() - t0)
            self.reflex_cpu.append(time.thread_time() - cpu0)
            self.log.reflexes.append({"time": cell.time, "kind": move.kind if move else "stop", "risk": report.risk, "rule": rule})
            return report, True
        self._set_ssm_target(free)
        return report, False

    def _set_ssm_target(self, target: float) -> None:
        """This frame's speed scale from separation monitoring (frames below 1 counted)."""
        self.ssm_target = target
        self.ssm_slowed_frames += target < 1.0

    def _fires(self, report: RiskReport, q: np.ndarray, close: bool, free: float = 1.0) -> str | None:
        """The reflex rule (`PlanningConfig.reflex_rule`): Eq. 2-3 ("eq2"), or a moving
        obstacle's predicted course meeting the robot's committed motion, were it to
        react one frame later (at the speed scale `free` that separation monitoring
        allows; `_committed`). Under the prediction rule with separation monitoring, a
        plan whose motion would meet a course if it reacted one frame and
        `stop_lookahead` later, but that brakes clear of every course when it brakes
        now, stops instead ("stop", a protective stop); otherwise the reflex fires
        ("predicted").
        An approaching obstacle within `min_separation` fires under either ("close").
        None: neither."""
        if close:
            return "close"
        if self.config.reflex_rule == "eq2":
            return "eq2" if report.fires(self.config.threshold) else None
        tracks = [t for t in self.tracker.tracks if t.moving and t.approaching and len(t.voxels)]
        if not tracks:
            return None
        committed, horizon = self._committed(q, free, REACTION_TIME)
        late = self._meets(tracks, committed, horizon)
        if self.config.ssm and self.motion is not None and self.motion.kind == "plan":
            # A stop is cheap: it is taken `stop_lookahead` earlier than a reflex would be.
            ahead, horizon = self._committed(q, free, REACTION_TIME + self.config.stop_lookahead)
            early = late or self._meets(tracks, ahead, horizon)
            if early and not self._meets(tracks, *self._committed(q, self.speed_scale, 0.0)):
                # what the re-plan from the stop keeps clear of (`on_frame`)
                self._courses = np.vstack([
                    predicted_course(t.voxels, t.own_velocity, horizon, self.tree.resolution, grow=True) for t in tracks
                ])
                self._halting_tracks = tracks
                return "stop"
        return "predicted" if late else None

    def _meets(self, tracks, committed: np.ndarray, horizon: float) -> bool:
        """Whether any track's predicted course meets the `committed` joint states."""
        return any(
            predicted_contact(
                self.robot, track.voxels, track.own_velocity, committed, horizon, self.tree.resolution,
                margin=self.config.prediction_margin,
            )
            for track in tracks
        )

    def _committed(self, q: np.ndarray, scale: float, reaction: float) -> tuple[np.ndarray, float]:
        """The robot's joint states (every 1/30 s) if it reacts after `reaction` seconds:
        its motion goes on at the speed `scale` until then (a plan's; reflexes run at
        full speed), then brakes to rest along its path at the acceleration limits. The
        horizon (s) is the reaction time plus the longer of that braking and
        `escape_time`, the time a reflex needs to get clear of a hand that arrives while
        the robot stands. Returns the states and the horizon."""
        if self.motion is None:  # stopped, or braking at every joint's limit
            stop = braking(q, self.command, self.a_max)
            horizon = reaction + max(stop.duration, self.config.escape_time)
            return stop.sample(np.arange(0.0, horizon + 1e-9, 1.0 / 30.0)), horizon
        if self.motion.kind != "plan":
            scale = 1.0
        # braking from the faster of the speed now and the one it is scaled to
        speed = np.maximum(np.abs(self.command), scale * np.abs(self._nominal_velocity()))
        stopping = float(np.max(speed / self.a_max))
        horizon = reaction + max(stopping, self.config.escape_time)
        ahead = np.arange(0.0, horizon + 1e-9, 1.0 / 30.0)
        slowing = np.clip(ahead - reaction, 0.0, stopping)
        # the motion's clock: on at `scale`, then slowing linearly to rest over `stopping`
        clock = scale * (np.minimum(ahead, reaction) + slowing - (0.5 * slowing**2 / stopping if stopping > 0 else 0.0))
        return self.motion.trajectory.sample(self.motion.elapsed + clock), horizon

    # --- speed and separation monitoring (ISO/TS 15066) -----------------------------

    def _nominal_velocity(self, h: float = 1e-3) -> np.ndarray:
        """The running motion's joint velocity, unscaled (rad/s): the fastest of its clock
        now and over the next reaction time (a motion starting from rest, or at a
        corner, speeds up before the next frame)."""
        assert self.motion is not None
        t = self.motion.elapsed + np.array([0.0, 0.5, 1.0]) * REACTION_TIME
        a, b = self.motion.trajectory.sample(t), self.motion.trajectory.sample(t + h)
        velocities = (b - a) / h
        return velocities[int(np.argmax(np.abs(velocities).max(axis=1)))]

    def ssm_scale(self, q: np.ndarray) -> float:
        """The path speed's scale (0-1) that keeps every tracked obstacle at least its
        protective separation from the robot (`separation.ssm_speed_limit`): per track,
        the robot's speed at its closest point towards the obstacle (running the plan
        at full speed) against the largest that separation allows, with the obstacle's
        speed towards the robot (tracked, at least `ssm_human_speed`), the reaction time
        of a map frame plus the layer's compute, and the stopping time the scaled speed
        needs at the acceleration limits. 1 for reflexes, without a plan, or moving away."""
        if not self.config.ssm or self.motion is None or self.motion.kind != "plan":
            return 1.0
        nominal = self._nominal_velocity()
        stopping = float(np.max(np.abs(nominal) / self.a_max))  # at full speed
        scale = 1.0
        for track in self.tracker.tracks:
            d = track.clearance
            if not np.isfinite(d) or d <= 0 or track.on_robot is None or track.link < 0:
                continue  # touching is the reflex's matter
            toward = (track.on_obstacle - track.on_robot) / d
            robot_speed = float(toward @ (self.robot.jacobian(q, track.link, track.on_robot) @ nominal))
            if robot_speed <= 1e-6 or stopping <= 0:
                continue  # slowing a robot that moves away or stands does not help
            human_speed = max(self.config.ssm_human_speed, -float(track.own_velocity @ toward))
            allowed = ssm_speed_limit(
                d, human_speed, reaction_time=REACTION_TIME, deceleration=robot_speed / stopping,
                sensor_uncertainty=self.config.ssm_uncertainty, robot_uncertainty=0.0,
            )
            scale = min(scale, allowed / robot_speed)
        return scale

    def _advance_scale(self, dt: float) -> float:
        """The speed scale for this control step: the wanted one (`ssm_target`), reached
        as fast as the acceleration limits let the reference slow down (the follower
        brakes at them), and regained at half that rate."""
        assert self.motion is not None
        if self.motion.kind != "plan":
            return 1.0
        target, scale = self.ssm_target, self.speed_scale
        if target != scale:
            speed = np.abs(self._nominal_velocity())
            rate = float(np.min(self.a_max / np.maximum(speed, 1e-6)))  # 1/s: the reference's scale change at the limit
            step = rate * dt if target < scale else 0.5 * rate * dt
            scale = max(target, scale - step) if target < scale else min(target, scale + step)
            self.speed_scale = scale
        return scale

    def _reflex_motion(self, q: np.ndarray, move, *, escape: bool):
        """What the robot does for a reflex `move` planned from q while it moves at its
        commanded velocity: a move away runs as every joint's quickest transfer to the
        target (the joints leave their current course as soon as each can; a curve,
        checked as such); a backtrack first stops (every joint braking at its limit)
        and then retraces the path from q. None when that motion is not clear."""
        lo, hi = self.robot.joint_limits.T
        if move.kind == "move_away":
            curve = transfer(q, self.command, move.path[-1], self.v_max, self.a_max)
            samples = curve.path(self.config.resolution)
            inside = bool(np.all((lo <= samples) & (samples <= hi)))
            return curve if inside and self._clear(samples, escape=escape, sampled=True) else None
        stop = braking(q, self.command, self.a_max)
        if not np.all((lo <= stop.end) & (stop.end <= hi)):
            return None
        path = np.vstack([stop.end[None], move.path])
        if stop.duration > 0 and not self._clear(path[:2], escape=escape):
            return None
        traj = time_parameterize(
            path, self.v_max, self.a_max, control_period=self.cell.config.time_step,
            straight_share=self.config.straight_share,
        )
        return stop.then(traj)

    def timed_reflex(self, path: np.ndarray, *, escape: bool) -> Trajectory | None:
        """A reflex `path` timed from here, if the way the follower takes onto it and
        along it (`way_onto`) is clear (`_clear`); else None."""
        timed = self.timed(path, plan=False)
        way, rejoined = self.way_onto(timed)
        return timed if rejoined and self._clear(way, escape=escape) else None

    def _clear(self, path: np.ndarray, *, escape: bool, sampled: bool = False) -> bool:
        """A reflex path clear of the static scene and this frame's moving voxels."""
        return path_is_clear(
            self.robot, self.static_tree, path, self.config.resolution,
            self.tracker.last_dynamic, self.tree.resolution, escape, sampled=sampled,
        )

    def _tool_speed(self) -> float:
        """End-effector speed (m/s) from the commanded joint velocities."""
        q = self.cell.q
        dt = 1e-3
        p = self.robot.fk(np.stack([q, np.clip(q + self.command * dt, *self.robot.joint_limits.T)]))[:, -1, :3, 3]
        return float(np.linalg.norm(p[1] - p[0]) / dt)

    def summary(self) -> dict:
        """Mean ± std of the Table II figures over completed trips."""
        trips = [t for t in self.trips if t.completed]
        out: dict = {"trips": len(trips)}
        for key in ("planning_time", "optimisation_time", "execution_time", "path_length", "tool_path_length"):
            values = np.array([getattr(t, key) for t in trips])
            out[key] = (float(values.mean()), float(values.std())) if len(values) else (float("nan"), float("nan"))
        for key in ("collisions", "reflexes", "protective_stops", "stops", "plans"):
            out[key] = int(sum(getattr(t, key) for t in trips))
        out["refused_plans"] = len(self.log.refused_plans)
        clear = [t.min_clearance for t in trips]
        out["min_clearance"] = float(min(clear)) if clear else float("inf")
        lat = np.array(self.reflex_latencies)
        out["reflex_compute_ms"] = (float(1e3 * lat.mean()), float(1e3 * lat.max())) if len(lat) else None
        cpu = np.array(self.reflex_cpu)
        out["reflex_cpu_ms"] = (float(1e3 * cpu.mean()), float(1e3 * cpu.max())) if len(cpu) else None
        rules: dict[str, int] = {}
        for reflex in self.log.reflexes:
            if "rule" in reflex:
                rules[reflex["rule"]] = rules.get(reflex["rule"], 0) + 1
        out["reflex_rules"] = rules
        ssm = np.array(self.ssm_cpu)
        out["ssm_cpu_ms"] = (float(1e3 * ssm.mean()), float(1e3 * ssm.max())) if len(ssm) else None
        out["ssm_slowed_frames"] = self.ssm_slowed_frames
        return out
