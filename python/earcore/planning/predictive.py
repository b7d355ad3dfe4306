"""Planners that choose among RRT-Connect solutions.

`PredictivePlanner` (Paper II §C.7-8): several RRT-Connect solutions (Table I: 3
attempts of at most 1 s), each simplified and smoothed, costed with Eq. 4 against the
danger map, the cheapest executed: a longer path through safe space beats a short one
through space where obstacles keep appearing.

`ReactivePlanner` (the paper's baseline): the shortest of the solutions, the danger
map ignored; current obstacles are simply static obstacles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

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
    ) -> None:
        self.robot = robot
        self.tree = tree
        self.time_limit = time_limit
        self.attempts = attempts
        self.resolution = resolution
        self.rrt = JointSpacePlanner(robot, tree, resolution=resolution, seed=seed)

    def cost(self, path: np.ndarray) -> float:
        """Eq. 4 of a path (the danger-free part is the bodies' mean path length)."""
        return float(self.robot.path_danger(self.tree, path, 0.05))

    def plan(self, start, goal) -> PlanChoice:
        solutions = self.rrt.plan(start, goal, time_limit=self.time_limit, attempts=self.attempts)
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
