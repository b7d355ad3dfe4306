"""Inverse kinematics for end-effector pose goals (Paper II, Table I: 0.01 m and
0.1 rad tolerances): damped least squares on the 6-D pose error with the link's
analytic Jacobian (one core call per iteration), restarted from random
configurations until a collision-free solution within the tolerances is found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.planning.errors import PlanningError
from earcore.transforms import rotation_vector

__all__ = ["IkResult", "UnreachablePose", "solve_ik"]


class UnreachablePose(PlanningError):
    """No collision-free configuration reaches the pose within the tolerances."""


@dataclass
class IkResult:
    q: np.ndarray
    position_error: float
    orientation_error: float
    iterations: int


def _pose_error(current: np.ndarray, target: np.ndarray) -> np.ndarray:
    return np.r_[target[:3, 3] - current[:3, 3], rotation_vector(target[:3, :3] @ current[:3, :3].T)]


def solve_ik(
    robot,
    target: np.ndarray,
    *,
    link: int | None = None,
    seed_q: np.ndarray | None = None,
    tree=None,
    position_tolerance: float = 0.01,
    orientation_tolerance: float = 0.1,
    restarts: int = 20,
    iterations: int = 60,
    rng: np.random.Generator | None = None,
) -> IkResult:
    """A configuration placing `link` (default: the last) at `target` (4×4,
    world_from_link) within the tolerances, collision-free on `tree` when given. The
    first attempt starts from `seed_q` (e.g. the current state), so the answer tends
    to stay close to it. Raises `UnreachablePose`."""
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (4, 4) or not np.isfinite(target).all():
        raise ValueError(f"target must be a finite 4×4 pose, got shape {target.shape}")
    r = target[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError("target's rotation part is not a rotation matrix")
    link = len(robot.link_names) - 1 if link is None else link
    if not 0 <= link < len(robot.link_names):
        raise ValueError(f"link must be 0 to {len(robot.link_names) - 1} (the robot's links), got {link}")
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    # Sample restarts within ±π of the middle of wide (±2π) joints; where a limit is
    # missing (a continuous joint) around 0, or the nearest point of the range to it.
    bounded = np.isfinite(lo) & np.isfinite(hi)
    mid = np.clip(0.0, lo, hi)
    mid[bounded] = 0.5 * (lo[bounded] + hi[bounded])
    s_lo, s_hi = np.maximum(lo, mid - np.pi), np.minimum(hi, mid + np.pi)
    rng = rng or np.random.default_rng(0)
    best = None
    for attempt in range(restarts):
        start = np.asarray(seed_q, dtype=np.float64) if (attempt == 0 and seed_q is not None) else rng.uniform(s_lo, s_hi)
        q = np.clip(start, lo, hi)  # a seed may lie beyond the limits (a perturbed state)
        for it in range(iterations):
            error = _pose_error(robot.fk(q)[link], target)
            p_err, o_err = np.linalg.norm(error[:3]), np.linalg.norm(error[3:])
            if p_err <= position_tolerance and o_err <= orientation_tolerance:
                if tree is None or not robot.check_configurations(tree, q):
                    return IkResult(q, float(p_err), float(o_err), it)
                break  # a solution in collision: restart elsewhere
            # The link's velocity per joint (linear, angular; world axes): the pose error
            # (target - current) shrinks along it. Damped least squares.
            jac = robot.frame_jacobian(q, link)
            damping = 1e-2
            dq = jac.T @ np.linalg.solve(jac @ jac.T + damping**2 * np.eye(6), error)
            # Small steps keep the linearisation honest far from the goal.
            dq *= min(1.0, 0.5 / max(np.abs(dq).max(), 1e-12))
            q = np.clip(q + dq, lo, hi)
            if it == 20 and p_err > 0.1:
                break  # stuck far away: a fresh start is cheaper
            if best is None or p_err + o_err < best[0]:
                best = (p_err + o_err, p_err, o_err)
    detail = f" (closest: {best[1]:.3f} m, {best[2]:.3f} rad)" if best else ""
    raise UnreachablePose(f"no collision-free configuration reaches the pose within {position_tolerance} m / "
                          f"{orientation_tolerance} rad after {restarts} restarts{detail}")
