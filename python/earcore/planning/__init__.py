"""Planning (Paper II): joint-space RRT-Connect (OMPL) validated by earcore's collision
core, the predictive planner that costs solutions on the danger map (Eq. 4), the
reflexive layer (obstacle tracking, risk Eq. 2, backtrack / move away), time
parameterisation within the speed and acceleration limits, and the executive that runs
A-B-A tasks in the cell. Needs ``pip install 'earcore[planning]'`` (OMPL)."""

from earcore.planning.config import PlanningConfig
from earcore.planning.errors import GoalInCollision, NoPathFound, PlanningError, StartInCollision
from earcore.planning.ik import IkResult, UnreachablePose, solve_ik
from earcore.planning.predictive import PlanChoice, PredictivePlanner, ReactivePlanner
from earcore.planning.reflex import ObstacleTracker, ReflexMove, RiskReport, plan_reflex
from earcore.planning.rrt import JointSpacePlanner, PlannedPath
from earcore.planning.separation import protective_separation, shortest_avoidable_distance, ssm_speed_limit
from earcore.planning.trajectory import Trajectory, path_length, time_parameterize

__all__ = [
    "GoalInCollision",
    "IkResult",
    "UnreachablePose",
    "solve_ik",
    "JointSpacePlanner",
    "NoPathFound",
    "ObstacleTracker",
    "PlanChoice",
    "PlannedPath",
    "PlanningConfig",
    "PlanningError",
    "PredictivePlanner",
    "ReactivePlanner",
    "ReflexMove",
    "RiskReport",
    "StartInCollision",
    "Trajectory",
    "path_length",
    "plan_reflex",
    "protective_separation",
    "shortest_avoidable_distance",
    "ssm_speed_limit",
    "time_parameterize",
]
