"""Calibration's robot side: moving the board where Algorithm 1 wants it, along free
motions (the cell's known geometry as an occupancy map), counting the simulated time
the robot spends moving. Works on anything with the cell's robot interface:
`joint_positions`, `controller` (`follow`, `done`, `brake`), `step()`, `config.time_step`,
`table_box()`, `config.boxes` and `model`."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

import earcore
from earcore.calibration.config import CalibrationConfig
from earcore.cloud import box_voxel_centres
from earcore.planning.errors import PlanningError
from earcore.planning.ik import UnreachablePose, solve_ik
from earcore.planning.rrt import JointSpacePlanner

__all__ = ["BoardMotion", "flange_link_name", "known_geometry"]


def flange_link_name(model) -> str:
    """The link the board is mounted on: the tool flange of the built-in arms."""
    for name in ("tool0", "panda_grasptarget", "panda_hand", "lbr_iiwa_link_7"):
        if name in model.link_names:
            return name
    return model.link_names[-1]


def known_geometry(model, table_box: tuple[np.ndarray, np.ndarray], boxes) -> earcore.OcTree:
    """The cell's table and boxes as an occupancy map for motion checks (5 cm cells; the
    robot's mount, within 25 cm of its base, left out)."""
    tree = earcore.OcTree(0.05)
    base = model.base[:3, 3]
    for lo, hi in [table_box] + [(b[:3], b[3:]) for b in boxes]:
        centres = box_voxel_centres(lo, hi, tree.resolution)
        centres = centres[np.linalg.norm(centres[:, :2] - base[:2], axis=1) > 0.25]  # the robot's mount
        if len(centres):
            tree.update_nodes(centres, occupied=True)
    return tree


class BoardMotion:
    """The robot carrying the board: joint-space motions checked against the cell's
    known geometry (straight when free, else RRT-Connect), IK for board poses."""

    def __init__(self, cell, config: CalibrationConfig, rng: np.random.Generator) -> None:
        self.cell = cell
        self.config = config
        self.rng = rng
        self.model = cell.model
        self.flange_link = self.model.link_names.index(flange_link_name(self.model))
        self.tree = known_geometry(self.model, cell.table_box(), cell.config.boxes)
        #: Simulated seconds the robot spent moving.
        self.motion_time = 0.0
        #: The sweep's "L" pose: open space to pass through between cameras.
        self.home: np.ndarray | None = None
        self._planner: JointSpacePlanner | None = None

    def base_from_flange(self, q: np.ndarray) -> np.ndarray:
        return self.model.fk(q)[self.flange_link]

    def go_to(self, q: np.ndarray) -> bool:
        """`move_to` with more planning time, or by way of the sweep's open "L" pose when
        no path is found from here (e.g. from deep in the previous camera's trajectory)."""
        if self.move_to(q, plan_time=3.0):
            return True
        return self.home is not None and self.move_to(self.home, plan_time=3.0) and self.move_to(q, plan_time=3.0)

    def nearest_equivalent(self, q: np.ndarray) -> np.ndarray:
        """`q` with each revolute joint turned by whole turns (where its limits allow) to
        lie closest to the current state: the same pose, reached with the least motion
        (a UR's joints span ±2π, and IK or a 360° sweep may land a turn away)."""
        q = np.asarray(q, dtype=np.float64).copy()
        now = self.cell.joint_positions
        lo, hi = self.model.joint_limits[:, 0], self.model.joint_limits[:, 1]
        for j in range(len(q)):
            if hi[j] - lo[j] <= 2 * math.pi:
                continue
            turns = np.round((now[j] - q[j]) / (2 * math.pi))
            for k in (turns, turns - 1, turns + 1):
                c = q[j] + 2 * math.pi * k
                if lo[j] <= c <= hi[j] and abs(c - now[j]) < abs(q[j] - now[j]):
                    q[j] = c
        return q

    def _path_to(self, q: np.ndarray, plan_time: float | None = None) -> list[np.ndarray] | None:
        """Waypoints from the current state to `q`: the straight motion when it is free,
        else an RRT-Connect path (OMPL, against the cell's known geometry) cut short
        wherever a straight motion skips waypoints; None when there is none."""
        now = self.cell.joint_positions
        if not self.model.check_motion(self.tree, now, q, 0.02):
            return [q]
        if self._planner is None:
            self._planner = JointSpacePlanner(self.model, self.tree, seed=self.config.seed)
        try:
            limit = self.config.plan_time if plan_time is None else plan_time
            path = self._planner.plan(now, q, time_limit=limit, simplify=False)[0].waypoints
        except PlanningError:
            return None
        out, i = [], 0
        while i < len(path) - 1:
            j = len(path) - 1
            while j > i + 1 and self.model.check_motion(self.tree, path[i], path[j], 0.02):
                j -= 1
            out.append(path[j])
            i = j
        return out

    def move_to(self, q: np.ndarray, plan_time: float | None = None) -> bool:
        """Drive the robot to `q` (or the same pose a whole turn nearer, per joint), by
        a planned path when the straight motion is blocked; False (and no motion) when
        no path is found."""
        cell = self.cell
        path = None
        # The nearest turn of each joint first; the pose as given when that one has no path.
        for candidate in (self.nearest_equivalent(q), np.asarray(q, dtype=np.float64)):
            path = self._path_to(candidate, plan_time)
            if path is not None:
                break
        if path is None:
            return False
        cell.controller.follow(path)
        steps = 0
        while not cell.controller.done and steps < 3000:
            cell.step()
            steps += 1
        self.motion_time += steps * cell.config.time_step
        return True

    def move_through(self, q: np.ndarray, watch: Callable[[np.ndarray], bool], every: float, *, shortest: bool = True) -> bool:
        """Drive to `q` (when the straight motion is free) calling `watch(q_now)` every
        `every` seconds on the way (cameras capture while the robot moves, their frames
        stamped with the joint state); when it returns False the robot brakes and stops.
        `shortest`: go to the nearest equivalent of `q` (not for a deliberate full turn)."""
        if shortest:
            q = self.nearest_equivalent(q)
        cell = self.cell
        if self.model.check_motion(self.tree, cell.joint_positions, q, 0.02):
            return False
        cell.controller.follow([q])
        steps, next_watch, watching = 0, 0.0, True
        while not cell.controller.done and steps < 6000:
            cell.step()
            steps += 1
            if watching and steps * cell.config.time_step >= next_watch:
                next_watch += every
                if not watch(cell.joint_positions):
                    cell.controller.brake(cell.joint_positions)
                    watching = False
        self.motion_time += steps * cell.config.time_step
        return True

    def flange_targets(self, base_from_board: np.ndarray, mount: np.ndarray, near: np.ndarray | None = None) -> Iterator[np.ndarray]:
        """Collision-free joint states putting the board (as the mount is believed) at
        `base_from_board`: first ones near `near` (default: the current state; short
        motions), then one from anywhere."""
        target = base_from_board @ np.linalg.inv(mount)
        now = self.cell.joint_positions if near is None else np.asarray(near, dtype=np.float64)
        seeds = [now] + [now + self.rng.normal(scale=0.3, size=now.shape) for _ in range(3)] + [None]
        for seed in seeds:
            try:
                yield solve_ik(
                    self.model, target, link=self.flange_link, seed_q=seed, tree=self.tree,
                    position_tolerance=0.02, orientation_tolerance=0.08, restarts=1 if seed is not None else 6,
                    iterations=150, rng=self.rng,
                ).q
            except UnreachablePose:
                continue

    def flange_target(self, base_from_board: np.ndarray, mount: np.ndarray, near: np.ndarray | None = None) -> np.ndarray | None:
        """The first of `flange_targets`, or None when the pose cannot be reached."""
        return next(self.flange_targets(base_from_board, mount, near), None)

    def reach_board_pose(self, base_from_board: np.ndarray, mount: np.ndarray) -> bool:
        """Move so the board (as the mount is believed) sits at `base_from_board`, by the
        first joint state whose straight motion from here is free."""
        for i, q in enumerate(self.flange_targets(base_from_board, mount)):
            if i >= 3:
                break
            if self.move_to(q):
                return True
        return False
