"""Planners that choose among RRT-Connect solutions.

`PredictivePlanner` (Paper II §C.7-8): several RRT-Connect solutions (Table I: 3
attempts of at most 1 s), each simplified and smoothed, costed with Eq. 4 against the
danger map, the cheapest executed: a longer path through safe space beats a short one
through space where obstacles keep appearing. A free straight motion is taken without a
search; with `detour_danger` the planner also plans detours around the voxels that
dangerous, so that Eq. 4 weighs the straight motion against them.

`ReactivePlanner` (the paper's baseline): the shortest of the solutions, the danger
map ignored; current obstacles are simply static obstacles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from earcore.planning.errors import PlanningError
from earcore.planning.rrt import JointSpacePlanner, PlannedPath

__all__ = ["PlanChoice", "PredictivePlanner", "ReactivePlanner"]


@dataclass
class PlanChoice:
    """The executed path and what it was chosen from."""

    path: np.ndarray
    cost: float
    #: (path, cost) of every solution found.
    candidates: list[tuple[PlannedPath, float]] = field(default_factory=list)
    #: Seconds spent finding solutions (RRT-Connect) and making them better
    #: (simplification, smoothing and costing), as Table II reports them.
    planning_time: float = 0.0
    optimisation_time: float = 0.0
    #: Share of planning spent in validity checks (states and edges).
    validity_checks: dict = field(default_factory=dict)


class PredictivePlanner:
    """Cheapest of `attempts` solutions by Eq. 4 (`RobotModel.path_danger`)."""

    use_danger = True

    def __init__(
        self,
        robot,
        tree,
        *,
        time_limit: float = 1.0,
        attempts: int = 3,
        resolution: float = 0.02,
        seed: int | None = None,
        detour_danger: float = 0.0,
    ) -> None:
        self.robot = robot
        self.tree = tree
        self.time_limit = time_limit
        self.attempts = attempts
        self.resolution = resolution
        #: With a free straight motion, also plan detours around voxels this dangerous (0: off).
        self.detour_danger = detour_danger
        self.rrt = JointSpacePlanner(robot, tree, resolution=resolution, seed=seed)

    def detours(self, start, goal) -> list[PlannedPath]:
        """Solutions that keep out of the voxels where obstacles have been (danger at
        least `detour_danger`, not occupied now), when the straight motion is free: it is
        found without a search, and a search's paths through free space simplify back
        to it, so without these Eq. 4 would have nothing to weigh it against. None when
        the straight motion stays clear of those voxels or no detour is found."""
        centres, _, danger = self.tree.danger_voxels()
        risky = centres[danger >= self.detour_danger]
        if len(risky):
            risky = risky[np.asarray(self.tree.is_occupied(risky)) != 1]
        if not len(risky):
            return []
        try:
            found = self.rrt.plan(start, goal, time_limit=self.time_limit, attempts=self.attempts, avoid=risky)
        except PlanningError:
            return []
        return [] if len(found) == 1 and len(found[0].waypoints) == 2 else found

    def cost(self, path: np.ndarray) -> float:
        """Eq. 4 of a path (the danger-free part is the bodies' mean path length)."""
        return float(self.robot.path_danger(self.tree, path, 0.05))

    def plan(self, start, goal) -> PlanChoice:
        solutions = self.rrt.plan(start, goal, time_limit=self.time_limit, attempts=self.attempts)
        if self.use_danger and self.detour_danger > 0 and len(solutions) == 1 and len(solutions[0].waypoints) == 2:
            solutions += self.detours(start, goal)
        t0 = time.perf_counter()
        scored = [(s, self.cost(s.waypoints) if self.use_danger else s.length) for s in solutions]
        costing = time.perf_counter() - t0
        best, cost = min(scored, key=lambda sc: sc[1])
        return PlanChoice(
            path=best.waypoints,
            cost=cost,
            candidates=scored,
            planning_time=sum(s.planning_time for s in solutions),
            optimisation_time=sum(s.simplify_time for s in solutions) + costing,
            validity_checks=dict(self.rrt.checks),
        )


class ReactivePlanner(PredictivePlanner):
    """The baseline: the shortest solution (joint-space length), no danger."""

    use_danger = False
