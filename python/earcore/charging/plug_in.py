"""Paper III's plug-in in three steps, and the unplugging.

    plan = plan_plug_in(model, flange, flange_from_tip, base_from_port, q_now, car)
    result = plug_in(station, plan)        # approach, align, insert (force-watched)
    unplug(station, result)                # the executed waypoints in reverse, then stand-by

1. Approach: a free joint-space motion (straight when free, else RRT-Connect) to the plug
   `approach_distance` in front of the port, on its axis, at full speed.
2. Align: a straight line at `align_fraction` of the speed until the pins' tips are
   `standoff` from the face, the plug's axis on the port's.
3. Insert: along the port's axis at `insert_fraction` of the speed, watching the wrist's
   force along the axis and stopping when it passes `force_threshold`: either the
   plug's shell met the port's collar (fully in) or a pin met the face (blocked).

Everything is planned before the robot moves: a port the robot cannot reach, or whose
straight-line moves pass a singularity, is refused before any motion toward the car.
The station is anything with `joints`, `set_joints(q)` (a move in free space),
`servo(q) -> force` (one control tick; the wrist's force on the plug in the tip
frame) and `config.time_step`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from earcore.errors import ConfigError
from earcore.planning.errors import PlanningError
from earcore.planning.ik import UnreachablePose, solve_ik

__all__ = ["PlugInConfig", "PlugInPlan", "PlugInResult", "PlugStuck", "PortOutOfReach", "car_keep_out", "plan_plug_in", "plug_in", "unplug"]


class PortOutOfReach(PlanningError):
    """The robot cannot carry the plug into the port along the three steps."""


@dataclass(frozen=True)
class PlugInConfig:
    #: Where the fast approach ends (m in front of the face) and the align step stops
    #: (the pins' tips this far from the face).
    approach_distance: float = 0.10
    standoff: float = 0.005
    #: How far past full insertion the insert step is commanded (the force stops it).
    overtravel: float = 0.004
    #: The tool's full speed (m/s, the approach) and the fractions for align and insert.
    tool_speed: float = 0.25
    joint_speed: float = 1.0
    #: The tool's acceleration on the straight moves (m/s²).
    acceleration: float = 0.1
    align_fraction: float = 0.10
    insert_fraction: float = 0.02
    #: Insertion stops when the force along the axis passes this (N); `force_limit`
    #: is what the pins stand without damage (N), reported per run.
    force_threshold: float = 25.0
    force_limit: float = 60.0
    #: Full insertion: the plug stopped within this of the mating depth (m).
    depth_tolerance: float = 0.0015
    pause: float = 1.0
    #: Spacing of the IK waypoints on straight-line moves (m), and how many arm
    #: configurations (IK branches) are tried before a port counts as out of reach.
    step: float = 0.0005
    branches: int = 6

    def __post_init__(self) -> None:
        if not 0 < self.insert_fraction <= self.align_fraction <= 1:
            raise ConfigError(f"plug-in: need 0 < insert_fraction <= align_fraction <= 1, got {self.insert_fraction}, {self.align_fraction}")
        if not 0 < self.force_threshold < self.force_limit:
            raise ConfigError(f"plug-in: need 0 < force_threshold < force_limit, got {self.force_threshold}, {self.force_limit}")
        if min(self.approach_distance, self.standoff, self.tool_speed, self.joint_speed, self.step, self.acceleration) <= 0:
            raise ConfigError("plug-in: distances, speeds and the step must be positive")
        if self.branches < 1:
            raise ConfigError(f"plug-in: branches must be at least 1, got {self.branches}")


@dataclass
class PlugInPlan:
    """Joint waypoints of each step, planned from the estimated port pose."""

    base_from_port: np.ndarray
    approach: np.ndarray
    align: np.ndarray
    insert: np.ndarray
    #: The pins' travel from touching the face to fully in (m).
    insertion_depth: float
    config: PlugInConfig
    #: Each insert waypoint's tip offset out of the face (m).
    insert_offsets: np.ndarray


@dataclass
class PlugInResult:
    """`inserted`: the plug stopped at the mating depth (the procedure's own judgement).
    `depth`: how far past the pins touching the face the flange went (m); `trace`:
    (T, 2) time (s) and the force along the axis (N) during align and insert."""

    inserted: bool
    stopped_by_force: bool
    depth: float
    peak_force: float
    trace: np.ndarray
    executed: list[np.ndarray] = field(default_factory=list)
    seconds: float = 0.0


def car_keep_out(base_from_port: np.ndarray, resolution: float = 0.05, extent: float = 1.0):
    """The car as the station knows it, an occupancy map: the half-space behind the
    port's face (a slab `extent` around the port, from 2 cm to 30 cm behind it)."""
    import earcore

    tree = earcore.OcTree(resolution)
    g = np.arange(-extent, extent + 1e-9, resolution / 2)
    depth = np.arange(-0.30, -0.02 + 1e-9, resolution / 2)
    u, v, w = np.meshgrid(g, g, depth, indexing="ij")
    local = np.stack([u.ravel(), v.ravel(), w.ravel()], 1)
    tree.update_nodes(local @ base_from_port[:3, :3].T + base_from_port[:3, 3], occupied=True)
    return tree


def _tip_pose(base_from_port: np.ndarray, offset: float) -> np.ndarray:
    """The plug's tip on the port's axis, `offset` out of the face, axes as when mated."""
    pose = base_from_port.copy()
    pose[:3, 3] = base_from_port[:3, 3] + base_from_port[:3, 2] * offset
    return pose


def _line(model, link: int, flange_from_tip: np.ndarray, base_from_port: np.ndarray, offsets: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Joint states putting the tip at each offset along the port's axis, each solved
    from the previous (one continuous branch); raises PortOutOfReach."""
    tip_from_flange = np.linalg.inv(flange_from_tip)
    out: list[np.ndarray] = []
    q = seed
    for offset in offsets:
        target = _tip_pose(base_from_port, offset) @ tip_from_flange
        try:
            q_next = solve_ik(model, target, link=link, seed_q=q, position_tolerance=2e-5, orientation_tolerance=2e-4, restarts=1, iterations=100).q
        except UnreachablePose as exc:
            raise PortOutOfReach(f"the plug cannot follow the port's axis {offset * 1000:.0f} mm from the face: {exc}") from None
        if out and np.abs(q_next - q).max() > 0.05:
            raise PortOutOfReach(f"the straight move along the port's axis passes near a singularity ({offset * 1000:.0f} mm from the face)")
        out.append(q_next)
        q = q_next
    return np.array(out)


def plan_plug_in(
    model,
    link: int,
    flange_from_tip: np.ndarray,
    base_from_port: np.ndarray,
    q_now: np.ndarray,
    insertion_depth: float,
    config: PlugInConfig | None = None,
    tree=None,
    rng: np.random.Generator | None = None,
) -> PlugInPlan:
    """Plan the three steps for the port at `base_from_port` (estimated), from `q_now`.
    `tree`: the known obstacles (default: `car_keep_out` of the port). Raises
    PortOutOfReach before anything moves."""
    c = config or PlugInConfig()
    base_from_port = np.asarray(base_from_port, dtype=np.float64)
    if base_from_port.shape != (4, 4) or not np.isfinite(base_from_port).all():
        raise ValueError(f"base_from_port must be a finite 4x4 pose, got shape {base_from_port.shape}")
    if c.approach_distance <= insertion_depth + c.standoff:
        raise ConfigError(
            f"plug-in: the approach ends {c.approach_distance * 1000:.0f} mm from the face, inside the align step's "
            f"{(insertion_depth + c.standoff) * 1000:.0f} mm (the pins' length and the standoff)"
        )
    tree = car_keep_out(base_from_port) if tree is None else tree
    rng = rng or np.random.default_rng(0)
    start = c.approach_distance
    target = _tip_pose(base_from_port, start) @ np.linalg.inv(flange_from_tip)
    touch = insertion_depth
    align_offsets = np.linspace(start, touch + c.standoff, max(2, int(np.ceil((start - touch - c.standoff) / c.step)) + 1))
    end = -c.overtravel
    insert_offsets = np.linspace(touch + c.standoff, end, max(2, int(np.ceil((touch + c.standoff - end) / c.step)) + 1))
    # one arm configuration (IK branch) after another, from the one nearest the current
    # state, until one carries the plug all the way clear of the car and of itself
    problems: list[str] = []
    for branch in range(c.branches):
        try:
            q_approach = solve_ik(
                model, target, link=link, seed_q=q_now if branch == 0 else None, tree=tree, position_tolerance=2e-5, orientation_tolerance=2e-4,
                restarts=30 if branch == 0 else 10, iterations=150, rng=rng,
            ).q  # fmt: skip
        except UnreachablePose as exc:
            if branch == 0:
                distance = np.linalg.norm(base_from_port[:3, 3] - model.base[:3, 3])
                raise PortOutOfReach(f"the port ({distance:.2f} m from the robot's base) is out of reach: {exc}") from None
            problems.append(str(exc))
            continue
        try:
            align = _line(model, link, flange_from_tip, base_from_port, align_offsets, q_approach)
            insert = _line(model, link, flange_from_tip, base_from_port, insert_offsets, align[-1])
            if model.check_configurations(tree, np.vstack([align, insert])).any():
                raise PortOutOfReach("the arm would touch the car (or itself) on the straight moves to the port")
            path = _free_path(model, tree, np.asarray(q_now, dtype=np.float64), q_approach)
        except PortOutOfReach as exc:
            problems.append(str(exc))
            continue
        return PlugInPlan(base_from_port, path, align, insert, insertion_depth, c, insert_offsets)
    raise PortOutOfReach(f"no arm configuration of {c.branches} carries the plug in: " + "; ".join(dict.fromkeys(problems)))


def _free_path(model, tree, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Waypoints after `q0` to `q1` clear of `tree`: straight when free, else RRT-Connect."""
    if not model.check_motion(tree, q0, q1, 0.02):
        return q1[None]
    from earcore.planning.rrt import JointSpacePlanner

    try:
        path = JointSpacePlanner(model, tree, seed=0).plan(q0, q1, time_limit=3.0)[0].waypoints
    except PlanningError as exc:
        raise PortOutOfReach(f"no collision-free motion to the port's approach pose: {exc}") from None
    return path[1:]


def _follow(station, path: np.ndarray, speed: float, step: float, *, watch: float | None, trace: list, executed: list, acceleration: float) -> tuple[bool, float]:
    """Servo along `path` (waypoints `step` apart) at up to `speed` (m/s), speeding up
    and slowing down at `acceleration` (a jump in speed would be a force spike through
    the holder's damping), interpolating the joints. With `watch`, stop when the force
    along the axis passes it. Returns (stopped by force, peak force)."""
    dt = station.config.time_step
    s, last, peak, v = 0.0, len(path) - 1, 0.0, 0.0
    while True:
        remaining = (last - s) * step
        v = min(speed, v + acceleration * dt, max(np.sqrt(2 * acceleration * remaining), acceleration * dt))
        s = min(s + v * dt / step, last)
        i = min(int(s), last - 1)
        q = path[i] + (s - i) * (path[i + 1] - path[i])
        force = -float(station.servo(q)[2])
        peak = max(peak, force)
        trace.append((station.time, force))
        executed.append(q)
        if watch is not None and force > watch:
            return True, peak
        if s >= last:
            return False, peak


def plug_in(station, plan: PlugInPlan) -> PlugInResult:
    """Run the plan: approach (free space), align, insert until the force threshold."""
    c = plan.config
    start = station.time
    q0 = station.joints
    for q in plan.approach:
        station.set_joints(q)
    station.time += _joint_seconds(np.vstack([q0, plan.approach]), c.joint_speed)
    trace: list = []
    executed: list = [plan.approach[-1]]
    stopped, peak = _follow(
        station, plan.align, c.tool_speed * c.align_fraction, c.step, watch=c.force_threshold, trace=trace, executed=executed, acceleration=c.acceleration
    )
    if stopped:  # something met the plug before the pins should reach the face: go no further
        return PlugInResult(False, True, -c.standoff, peak, np.array(trace).reshape(-1, 2), executed, station.time - start)
    stopped, peak = _follow(
        station, plan.insert, c.tool_speed * c.insert_fraction, c.step, watch=c.force_threshold, trace=trace, executed=executed, acceleration=c.acceleration
    )
    # judged by where the commanded pose stopped: the shell on the collar at the mating
    # depth, or a pin on the face short of it
    traveled = _travelled(plan, executed[-1])
    inserted = stopped and traveled >= plan.insertion_depth - c.depth_tolerance
    peak = max(peak, max((f for _, f in trace), default=0.0))
    return PlugInResult(inserted, stopped, traveled, peak, np.array(trace).reshape(-1, 2), executed, station.time - start)


def _travelled(plan: PlugInPlan, q: np.ndarray) -> float:
    """How far past the pins touching the face the waypoint nearest `q` is (m)."""
    nearest = int(np.argmin(np.abs(plan.insert - q).max(axis=1)))
    return float(plan.insertion_depth - plan.insert_offsets[nearest])


def _joint_seconds(path: np.ndarray, speed: float) -> float:
    return float(np.abs(np.diff(path, axis=0)).max(axis=1).sum() / speed) if len(path) > 1 else 0.0


class PlugStuck(PlanningError):
    """Pulling the plug out met more force than the pins stand: the robot stopped."""


def unplug(station, result: PlugInResult, standby: np.ndarray, config: PlugInConfig | None = None) -> np.ndarray:
    """Wait `pause`, pull out by replaying the executed states in reverse (at the pace
    they went in), then go back to `standby`. Returns the force trace while pulling
    (T, 2): time (s) and force along the axis (N; negative pulls). Raises PlugStuck,
    with the robot stopped where it was, when the force passes `force_limit`."""
    c = config or PlugInConfig()
    trace = []
    holding = [result.executed[-1]] * int(round(c.pause / station.config.time_step))
    for q in holding + result.executed[::-1]:
        force = -float(station.servo(q)[2])
        trace.append((station.time, force))
        if abs(force) > c.force_limit:
            raise PlugStuck(f"unplugging met {force:.0f} N (limit {c.force_limit:.0f} N): stopped with the plug in the port")
    q0 = station.joints
    station.set_joints(standby)
    station.time += _joint_seconds(np.vstack([q0, standby]), c.joint_speed)
    return np.array(trace).reshape(-1, 2)

