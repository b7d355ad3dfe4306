"""Joint-space RRT-Connect (OMPL) with earcore's collision core as the validity check.

OMPL explores; every state and every edge it proposes is checked in Rust against the
map (`RobotModel.check_configurations` / `check_motion`, including self-collision).
Solutions are shortcut and B-spline smoothed by OMPL's simplifier, which keeps only
changes that stay valid.

Needs the `ompl` package (PyPI, 2.x API): ``pip install 'earcore[planning]'``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from earcore.planning.errors import GoalInCollision, NoPathFound, StartInCollision
from earcore.planning.ik import solve_ik
from earcore.planning.trajectory import blend_corners, path_length

__all__ = ["JointSpacePlanner", "PlannedPath"]

_SEEDED = False
#: `JointSpacePlanner._keep_out` before its map is built.
_UNFILTERED = object()


def _ompl():
    try:
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("planning needs OMPL: pip install 'earcore[planning]' (PyPI package `ompl` >= 2)") from exc
    ou.setLogLevel(ou.LOG_ERROR)
    return ob, og, ou


@dataclass
class PlannedPath:
    """One solution: waypoints (M, dof) and how long finding and simplifying it took."""

    waypoints: np.ndarray
    planning_time: float
    simplify_time: float

    @property
    def length(self) -> float:
        return path_length(self.waypoints)


class JointSpacePlanner:
    """RRT-Connect in the robot's joint space against `tree` (the map; whatever is
    occupied in it, static structure and current obstacles alike, is forbidden).

    `resolution` (rad) is the largest joint step between checked configurations on an
    edge; `range` the RRT step (0 = OMPL's default, 20 % of the space's extent).
    Joint limits wider than `max_joint_span` (UR's ±2π) are narrowed to that span around
    the middle of start and goal, widened to hold both when they are farther apart: the
    search stays in the part of the space a task uses.
    """

    def __init__(
        self,
        robot,
        tree,
        *,
        resolution: float = 0.02,
        range: float = 0.0,
        obstacles: str = "occupied",
        max_joint_span: float = 2 * np.pi,
        seed: int | None = None,
        position_tolerance: float = 0.01,
        orientation_tolerance: float = 0.1,
    ) -> None:
        self.robot = robot
        self.tree = tree
        self.resolution = resolution
        self.range = range
        self.obstacles = obstacles
        self.max_joint_span = max_joint_span
        #: Tolerances for end-effector pose goals (Table I: 0.01 m, 0.1 rad).
        self.position_tolerance = position_tolerance
        self.orientation_tolerance = orientation_tolerance
        self.dof = robot.dof
        self._ob, self._og, ou = _ompl()
        global _SEEDED
        if seed is not None and not _SEEDED:
            # OMPL's generator is process-wide and can be seeded once, before first use.
            ou.RNG.setSeed(int(seed))
            _SEEDED = True
        #: Validity queries made by the last `plan` call (states, edges) and the time
        #: spent in them, for the planning benchmark's "validity share".
        self.checks = {"states": 0, "motions": 0, "seconds": 0.0}
        #: Keep-out (`set_keep_out`): the grown robot, the voxels and their size; and the
        #: (grown robot, map) in force, without the voxels the robot is already near.
        self._keep_out_source: tuple | None = None
        self._keep_out: tuple | object | None = None
        self._keep_out_cache: dict = {}

    # --- validity, as the planner sees it ---------------------------------------

    def set_keep_out(self, grown_robot, voxels, resolution: float) -> None:
        """Besides the map, keep `grown_robot` (this robot with its bodies grown by a
        margin; self-collision is not checked on it) clear of `voxels` (centres of
        `resolution` cubes, e.g. the people the reflex layer tracks). None or no voxels:
        off. Voxels already within the margin where a plan starts or ends (or where the
        robot is, for `path_is_valid`) are left out for that query: the reflexes deal
        with what is that close, and a robot next to one could not move at all."""
        if grown_robot is None or voxels is None or not len(voxels):
            self._keep_out_source = self._keep_out = None
            return
        voxels = np.asarray(voxels, dtype=np.float64).reshape(-1, 3)
        self._keep_out_source = (grown_robot, voxels, float(resolution))
        self._keep_out = _UNFILTERED  # built on first use: plans and paths pick their own

    def _keep_out_away_from(self, *qs) -> tuple | None:
        """The keep-out map without the voxels within the margin at any of `qs`."""
        if self._keep_out_source is None:
            return None
        robot, voxels, res = self._keep_out_source
        keep = np.ones(len(voxels), dtype=bool)
        for q in qs:
            # A voxel centre within half a diagonal of the grown bodies: within the margin.
            keep &= np.asarray(robot.self_filter(voxels, np.asarray(q, dtype=np.float64), 0.87 * res), dtype=bool)
        chosen = voxels[keep]
        if not len(chosen):
            return None
        key = chosen.tobytes()
        if key not in self._keep_out_cache:
            import earcore

            tree = earcore.OcTree(res)
            tree.update_nodes(chosen)
            self._keep_out_cache = {key: (robot, tree)}  # one map at a time; its index is built once
        return self._keep_out_cache[key]

    def _active_keep_out(self) -> tuple | None:
        if self._keep_out is _UNFILTERED:
            self._keep_out = self._keep_out_away_from()
        assert self._keep_out is None or isinstance(self._keep_out, tuple)
        return self._keep_out

    def _kept_out(self, q) -> bool:
        """True where `q` comes within the keep-out margin."""
        active = self._active_keep_out()
        if active is None:
            return False
        robot, tree = active
        return bool(robot.check_configurations(tree, q, self_collision=False))

    def _motion_kept_out(self, q0, q1) -> bool:
        active = self._active_keep_out()
        if active is None:
            return False
        robot, tree = active
        return bool(robot.check_motion(tree, q0, q1, self.resolution, self_collision=False))

    def is_valid(self, q) -> bool:
        return not bool(self.robot.check_configurations(self.tree, q, obstacles=self.obstacles)) and not self._kept_out(q)

    def path_is_valid(self, path) -> bool:
        """Every edge of a polyline free at the planner's resolution."""
        path = np.asarray(path, dtype=np.float64)
        self._keep_out = self._keep_out_away_from(path[0], path[-1])
        if len(path) == 1:
            return self.is_valid(path[0])
        hits = self.robot.check_motions(self.tree, path[:-1], path[1:], self.resolution, obstacles=self.obstacles)
        if np.any(hits):
            return False
        if self._keep_out is not None:
            robot, tree = self._keep_out
            near = robot.check_motions(tree, path[:-1], path[1:], self.resolution, self_collision=False)
            return not bool(np.any(near))
        return True

    def rounded(self, path, max_deviation: float) -> np.ndarray:
        """`path` with its corners rounded by arcs (`blend_corners`) as far as the
        rounded path stays valid (`path_is_valid`): `max_deviation` first, then a
        quarter of it, else the path as it is."""
        path = np.asarray(path, dtype=np.float64)
        if max_deviation <= 0 or len(path) < 3:
            return path
        for deviation in (max_deviation, 0.25 * max_deviation):
            candidate = blend_corners(path, deviation)
            if self.path_is_valid(candidate):
                return candidate
        return path

    def _describe(self, q) -> str | None:
        hit, link = self.robot.check_configurations(self.tree, q, obstacles=self.obstacles, return_links=True)
        if not hit:
            return "within the keep-out margin of a tracked obstacle" if self._kept_out(q) else None
        return self.robot.link_names[link] if link >= 0 else "self-collision"

    # --- planning ---------------------------------------------------------------

    def _setup(self, start: np.ndarray, goal: np.ndarray):
        ob, og = self._ob, self._og
        dof = self.dof
        space = ob.RealVectorStateSpace(dof)
        bounds = ob.RealVectorBounds(dof)
        limits = self.robot.joint_limits
        for j in range(dof):
            lo, hi = float(limits[j, 0]), float(limits[j, 1])
            if hi - lo > self.max_joint_span:
                # The window always holds both ends: OMPL cannot start outside its space.
                centre = 0.5 * (start[j] + goal[j])
                lo = max(lo, min(centre - 0.5 * self.max_joint_span, start[j], goal[j]))
                hi = min(hi, max(centre + 0.5 * self.max_joint_span, start[j], goal[j]))
            bounds.setLow(j, lo)
            bounds.setHigh(j, hi)
        space.setBounds(bounds)
        setup = og.SimpleSetup(space)
        si = setup.getSpaceInformation()
        robot, tree, obstacles, res, checks = self.robot, self.tree, self.obstacles, self.resolution, self.checks

        clock = time.perf_counter

        kept_out, motion_kept_out = self._kept_out, self._motion_kept_out

        def state_valid(s) -> bool:
            t0 = clock()
            q = s[0:dof]
            free = not robot.check_configurations(tree, q, obstacles=obstacles) and not kept_out(q)
            checks["states"] += 1
            checks["seconds"] += clock() - t0
            return free

        # OMPL's simplifier asks about some edges again (about one in six, ~11 % of the
        # edge-checking time in the planning benchmark); the map is fixed for the call.
        known_edges: dict[tuple, bool] = {}

        class EdgeValidator(ob.MotionValidator):  # type: ignore[name-defined]  # OMPL has no stubs
            def checkMotion(self, s1, s2) -> bool:  # noqa: N802 (OMPL's name)
                t0 = clock()
                q0, q1 = s1[0:dof], s2[0:dof]
                key = (*q0, *q1)
                free = known_edges.get(key)
                if free is None:
                    free = not robot.check_motion(tree, q0, q1, res, obstacles=obstacles) and not motion_kept_out(q0, q1)
                    known_edges[key] = free
                checks["motions"] += 1
                checks["seconds"] += clock() - t0
                return free

        setup.setStateValidityChecker(state_valid)
        si.setMotionValidator(EdgeValidator(si))
        planner = og.RRTConnect(si)
        if self.range > 0:
            planner.setRange(self.range)
        setup.setPlanner(planner)

        def state(q):
            st = si.allocState()
            st[0:dof] = [float(v) for v in q]
            return st

        setup.setStartAndGoalStates(state(start), state(goal))
        setup.setup()
        return setup, si

    def _first_free(self, paths) -> np.ndarray | None:
        """The waypoints of the first of `paths` (OMPL's, smoothed first) whose every edge
        is free at the planner's resolution. OMPL checks the edges it makes whole, and
        splitting a checked edge samples it elsewhere, where the pieces may touch what
        the whole was not sampled at (5 in 850 smoothed UR5 paths among pillars did)."""
        for path in paths:
            waypoints = np.array([s[0 : self.dof] for s in path.getStates()], dtype=np.float64)
            if self.path_is_valid(waypoints):
                return waypoints
        return None

    def check_ends(self, start, goal) -> tuple[np.ndarray, np.ndarray]:
        """Validate and convert the two ends (raises the planning errors). A 4×4 goal is
        an end-effector pose (world_from_tool of the last link), reached through inverse
        kinematics within the tolerances, starting from `start`."""
        start = np.asarray(start, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        if goal.shape == (4, 4) and start.shape == (self.dof,) and np.isfinite(start).all():
            goal = solve_ik(
                self.robot, goal, seed_q=start, tree=self.tree,
                position_tolerance=self.position_tolerance, orientation_tolerance=self.orientation_tolerance,
            ).q
        for name, q in (("start", start), ("goal", goal)):
            if q.shape != (self.dof,):
                raise ValueError(f"{name} must have {self.dof} joint values, got shape {q.shape}")
            if not np.isfinite(q).all():
                raise ValueError(f"{name} contains NaN or infinite values: {q}")
        self._keep_out = self._keep_out_away_from(start, goal)
        # Joints outside their limits raise ValueError (naming the joint) here.
        link = self._describe(start)
        if link is not None:
            raise StartInCollision(f"the start configuration is in collision ({link})", link)
        link = self._describe(goal)
        if link is not None:
            raise GoalInCollision(f"the goal configuration is in collision ({link})", link)
        return start, goal

    def plan(
        self, start, goal, *, time_limit: float = 1.0, attempts: int = 1, simplify: bool = True
    ) -> list[PlannedPath]:
        """Up to `attempts` independent RRT-Connect solutions start → goal (a joint state,
        or a 4×4 end-effector pose: see `check_ends`), each found
        within `time_limit` seconds (Paper II, Table I: 1 s, 3 attempts). Raises
        `StartInCollision`, `GoalInCollision`, or `NoPathFound` when no attempt
        succeeds; never runs longer than attempts × (time_limit + simplification)."""
        start, goal = self.check_ends(start, goal)
        if not (time_limit > 0 and attempts >= 1):
            raise ValueError("time_limit must be > 0 and attempts >= 1")
        self.checks.update(states=0, motions=0, seconds=0.0)
        straight_hits = self.robot.check_motion(self.tree, start, goal, self.resolution, obstacles=self.obstacles)
        if not straight_hits and not self._motion_kept_out(start, goal):
            # The straight motion is free: RRT-Connect would find it at once; skip OMPL.
            direct = PlannedPath(np.stack([start, goal]), 0.0, 0.0)
            return [direct]
        setup, si = self._setup(start, goal)
        ob, og = self._ob, self._og
        simplifier = og.PathSimplifier(si)
        found = []
        for _ in range(attempts):
            setup.clear()
            t0 = time.perf_counter()
            status = setup.solve(time_limit)
            t1 = time.perf_counter()
            if status.getStatus() != ob.PlannerStatus.EXACT_SOLUTION:
                continue
            path = og.PathGeometric(setup.getSolutionPath())
            candidates = [path]
            if simplify:
                raw = og.PathGeometric(path)
                simplifier.simplifyMax(path)
                shortcut = og.PathGeometric(path)
                simplifier.smoothBSpline(path, 3)
                candidates = [path, shortcut, raw]
            waypoints = self._first_free(candidates)
            if waypoints is not None:
                found.append(PlannedPath(waypoints, t1 - t0, time.perf_counter() - t1))
        if not found:
            raise NoPathFound(
                f"RRT-Connect found no collision-free path in {attempts} attempt(s) of {time_limit:g} s "
                "(the goal may be enclosed by obstacles)"
            )
        return found
