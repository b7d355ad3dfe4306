"""Paper II's experiments in the simulated cell: the whole-system test (Table II) and
the danger-map construction test (Fig. 7).

A-B-A return trips of the UR5, four experiments with one seed:
  Exp. 1  reactive planner, a static pillar blocking the direct path;
  Exp. 2  reactive planner, a person's arm entering the direct path at random;
  Exp. 3  predictive planner + reflexes, the same arm (same reaches);
  Direct  no obstacle.
Two scenarios of the person's reaches (`SCENARIOS`):
  stress  one reach after another, 0.5-3 s apart, held 2-5 s, peak hand speed
          0.25-1.6 m/s (`HELD_HAND_WANDER` lets the held hand move about);
  paper   Paper II's protocol: the hand brought into the direct path at operator pace
          (0.2-0.5 m/s) at random times (1-8 s apart), held 2-8 s.
Prints mean ± std per return trip of planning, optimisation and execution time, path
length, and the totals of collisions (true contacts), reflexes (by the rule that fired,
and by what the person's arm was doing then: on its way in, held, on its way back) and
stops, and the minimum true robot-person distance; with the stress scenario also
the physical limit: the reaches that started closer than the shortest distance from
which the arm can still avoid them (`separation.shortest_avoidable_distance`). Writes
table2.json and paths.png (the tool's paths over the trips on the danger the map held,
top view, in the manner of Paper II's Fig. 8).

    earcore experiment table2 [--scenario stress|paper] [--trips 15] [--seed 0] [--camera-scale 0.25] [--out out/table2]

Fig. 7: the obstacle plate (10 × 20 cm) on the end-effector runs horizontal circles of
radius 20, 32 and 46 cm around the robot's base (9.1, 14.69, 21.06 s each), the whole
sequence repeated, the overhead camera straight above the base; the danger of every voxel
is averaged over the run and reported per band of radius (over the plate's sweep, the
voxels hit in at least half of the repetitions, and over every voxel that held danger),
with how often the band's fading voxels were seen free (the occlusion), and a picture.

    earcore experiment fig7 [--repetitions 20] [--camera-scale 0.25] [--out out/fig7]
"""

from __future__ import annotations

import argparse
import sys
import time
from copy import deepcopy
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from earcore import DANGER_ON_HIT, jsonfile
from earcore.app.arguments import Parser, count, positive_int, scale
from earcore.app.config import RunConfig
from earcore.planning.executive import REACTION_TIME, Executive
from earcore.sim.cell import default_waypoints

__all__ = [
    "SCENARIOS", "CirclesDriver", "WatchedExecutive", "draw_paths", "experiment_configs", "fig7", "limit_analysis", "main",
    "reflex_truth", "reflexes_by_phase", "table2",
]

#: How far the held hand moves about its target (m) in Exp. 2 and 3. Still (0) by
#: default: with 8 cm of wander (up to 0.28 m/s) both planners touched the person
#: (3 contacts each in 15 trips, seed 0) and Exp. 3 ran 12.0 s per trip against
#: Exp. 2's 7.1 s (docs/design/reflexes.md).
HELD_HAND_WANDER = 0.0

#: A 10 × 10 cm pillar between the tool's A and B positions (Exp. 1).
PILLAR = (0.28, 0.33, 0.0, 0.38, 0.43, 0.8)


#: The person's reaches per scenario: peak hand speed (m/s), how long the hand is held
#: in the path (s) and the pause between reaches (s), each drawn uniformly.
SCENARIOS = {
    "stress": {"speeds": (0.25, 1.6), "holds": (2.0, 5.0), "gaps": (0.5, 3.0)},
    "paper": {"speeds": (0.2, 0.5), "holds": (2.0, 8.0), "gaps": (1.0, 8.0)},
}


def _reaches(seed: int, duration: float, rest=(0.85, 0.5, 0.05), scenario: str = "stress"):
    """Random reaches into the direct path, one after another: the hand aimed at the
    middle of the tool's A-B sweep and held there (Paper II's obstacle was held into the
    path by hand), at the speeds, holds and pauses of the `scenario` (`SCENARIOS`)."""
    from earcore.sim.person import reach_duration

    ranges = SCENARIOS[scenario]
    rng = np.random.default_rng([seed, 7])
    starts, targets, speeds, holds = [], [], [], []
    t = rng.uniform(1.0, 3.0)
    while t < duration:
        target = rng.uniform([0.22, 0.25, 0.4], [0.36, 0.48, 0.56])
        speed, hold = rng.uniform(*ranges["speeds"]), rng.uniform(*ranges["holds"])
        starts.append(float(t))
        targets.append(tuple(float(v) for v in target))
        speeds.append(float(speed))
        holds.append(float(hold))
        go = reach_duration(rest, target, speed)
        t += 2 * go + hold + rng.uniform(*ranges["gaps"])
    return starts, targets, speeds, holds


def experiment_configs(
    seed: int = 0, camera_scale: float = 0.25, duration: float = 600.0, scenario: str = "stress"
) -> dict[str, RunConfig]:
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {sorted(SCENARIOS)}, got {scenario!r}")
    base = RunConfig(duration=duration, snapshots=[])
    base.cell.seed = seed
    base.cell.camera_scale = camera_scale
    base.cell.robot_meshes = "collision"  # 3× faster renders, the same depth to ~1 mm
    base.cell.person.enabled = False
    configs = {}
    exp1 = deepcopy(base)
    exp1.cell.boxes = list(exp1.cell.boxes) + [PILLAR]
    exp1.planning.mode = "reactive"
    configs["Exp. 1"] = exp1
    person = deepcopy(base)
    person.cell.person.enabled = True
    starts, targets, speeds, holds = _reaches(seed, duration, person.cell.person.rest_hand, scenario)
    person.cell.person.reach_starts = starts
    person.cell.person.reach_targets = targets
    person.cell.person.reach_speeds = speeds
    person.cell.person.reach_holds = holds
    person.cell.person.wander = HELD_HAND_WANDER
    exp2 = deepcopy(person)
    exp2.planning.mode = "reactive"
    configs["Exp. 2"] = exp2
    exp3 = deepcopy(person)
    exp3.planning.mode = "predictive"
    configs["Exp. 3"] = exp3
    configs["Direct"] = deepcopy(base)
    return configs


class WatchedExecutive(Executive):
    """The planning executive with what Table II's pictures and the limit analysis
    need: per map frame of a trip the time, joint state, command and true robot-person
    distance; the times contacts began; per reflex of the reflex layer what the person
    truly did then (`reflex_truth`); and the danger of each map column (the largest of
    its voxels', top view) averaged over frames sampled every `DANGER_EVERY`."""

    DANGER_EVERY = 5
    #: The top view's grid: lower corner (m), cell (m) and cells.
    GRID_LO = np.array([-0.6, -0.6])
    GRID_CELL = 0.05
    GRID_SHAPE = (28, 28)

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.frames: list[tuple[float, np.ndarray, np.ndarray, float]] = []
        self.contact_times: list[float] = []
        #: Per reflex fired by the reflex layer: its time, the person's phase (`HumanArm.phase`:
        #: on the way in, held, on the way back, at rest), true hand speed (m/s) and true
        #: robot-person distance (m).
        self.reflex_truth: list[dict] = []
        self._danger_sum = np.zeros(self.GRID_SHAPE)
        self._danger_samples = 0
        self._frame_index = 0

    @property
    def danger_top(self) -> np.ndarray:
        """Each map column's danger averaged over the sampled frames (top view)."""
        return self._danger_sum / max(self._danger_samples, 1)

    def on_frame(self):
        fired = len(self.log.reflexes)
        report = super().on_frame()
        new = self.log.reflexes[fired:]
        distance = float("inf")
        if self.person_distance is not None and (new or self.trip is not None):
            distance = self.person_distance()
        if new:
            self.reflex_truth += reflex_truth(new, getattr(self.cell, "person", None), self.cell.time, distance)
        if self.trip is not None:
            if distance <= 0 and (not self.frames or self.frames[-1][3] > 0):
                self.contact_times.append(self.cell.time)
            self.frames.append((self.cell.time, self.cell.q.copy(), self.command.copy(), distance))
        self._frame_index += 1
        if self._frame_index % self.DANGER_EVERY == 0:
            centres, _, values = self.tree.danger_voxels()
            cells = np.floor((centres[:, :2] - self.GRID_LO) / self.GRID_CELL).astype(int)
            inside = np.all((cells >= 0) & (cells < self.GRID_SHAPE), axis=1)
            column = np.zeros(self.GRID_SHAPE)
            np.maximum.at(column, tuple(cells[inside].T), values[inside])
            self._danger_sum += column
            self._danger_samples += 1
        return report


def limit_analysis(executive: WatchedExecutive, person) -> dict:
    """Item 4 of the stress scenario: for every reach that started during the trips, the
    shortest distance from which the arm could still avoid it
    (`separation.shortest_avoidable_distance`: the reach's peak hand speed over its
    length, the reflex layer's reaction time, and the tool's top speed and acceleration
    straight away from the reach's target at the joint limits, with the tool's speed
    towards it then), against the true robot-person distance when it started; and the
    contacts made while a reach was on its way (from its start to its target), each
    counted with that reach. Conservative: the hand is taken at its peak speed all the
    way and straight at the robot (the minimum-jerk reach averages 1/1.875 of its peak,
    and aims at the middle of the sweep), and the arm's top speed and acceleration away
    come from the minimum-norm joint motion, so the limit overstates what is unavoidable."""
    from earcore.planning.separation import shortest_avoidable_distance
    from earcore.sim.person import reach_duration

    if not executive.frames:
        return {"reaches": 0, "inside_limit": 0, "contacts": 0, "contacts_inside_limit": 0, "limits_m": []}
    robot = executive.robot
    times = np.array([f[0] for f in executive.frames])
    rest = np.asarray(person.rest_hand, dtype=np.float64)
    rows = []
    for start, target, speed in zip(person.reach_starts, person.reach_targets, person.reach_speeds):
        if not times[0] <= start <= times[-1]:
            continue
        _, q, qd, gap = executive.frames[int(np.searchsorted(times, start))]
        tool = robot.fk(q)[-1, :3, 3]
        away = tool - np.asarray(target)
        away /= max(float(np.linalg.norm(away)), 1e-9)
        jacobian = robot.jacobian(q, len(robot.link_names) - 1, tool)
        joints = np.abs(np.linalg.pinv(jacobian) @ away)  # joint speeds per m/s of the tool away
        top = float(np.min(executive.v_max / np.maximum(joints, 1e-9)))
        acceleration = float(np.min(executive.a_max / np.maximum(joints, 1e-9)))
        towards = max(0.0, -float(away @ (jacobian @ qd)))
        limit = shortest_avoidable_distance(
            speed, reach=float(np.linalg.norm(np.asarray(target) - rest)), latency=REACTION_TIME,
            max_speed=top, acceleration=acceleration, robot_speed=towards,
        )
        rows.append((start, limit, gap, start + reach_duration(rest, target, speed)))
    inside = {i for i, (_, limit, gap, _) in enumerate(rows) if gap < limit}
    owners = [next((i for i, r in enumerate(rows) if r[0] <= t <= r[3]), -1) for t in executive.contact_times]
    return {
        "reaches": len(rows),
        "inside_limit": len(inside),
        "contacts": len(owners),
        "contacts_inside_limit": sum(o in inside for o in owners),
        "limits_m": [round(float(r[1]), 3) for r in rows],
    }


def reflex_truth(entries: list[dict], person, t: float, distance: float) -> list[dict]:
    """For the reflex layer's reflexes among a frame's new log `entries` (those with a
    rule; recoveries have none): the time `t`, the person's phase then (`HumanArm.phase`),
    the true hand speed (m/s) and the true robot-person `distance` (m). None without a
    person."""
    if person is None:
        return []
    return [
        {"time": t, "phase": person.phase(t), "hand_speed": person.speed(t), "distance": distance}
        for entry in entries
        if "rule" in entry
    ]


def reflexes_by_phase(truth: list[dict], moves: list[dict]) -> dict[str, int]:
    """How many of the reflexes in `truth` (`WatchedExecutive.reflex_truth`) fired in each
    phase of the person's arm, counting those up to the end of the last completed move
    (Table II counts the completed trips' reflexes)."""
    end = max((m["start_time"] + m["execution_time"] for m in moves), default=-np.inf)
    counts: dict[str, int] = {}
    for reflex in truth:
        if reflex["time"] <= end:
            counts[reflex["phase"]] = counts.get(reflex["phase"], 0) + 1
    return counts


def table2(
    trips: int = 15,
    seed: int = 0,
    camera_scale: float = 0.25,
    out: Path = Path("out/table2"),
    only=None,
    reflex_rule: str = "prediction",
    scenario: str = "stress",
) -> dict:
    """Run the experiments; returns {experiment: figures per return trip}; draws the
    tool's paths over the danger map (paths.png in `out`)."""
    from earcore.app.run import run

    results, watched = {}, {}
    for name, config in experiment_configs(seed, camera_scale, scenario=scenario).items():
        if only and name not in only:
            continue
        config.planning.reflex_rule = reflex_rule

        def make(cell, pipeline, config=config, name=name):
            watched[name] = WatchedExecutive(
                cell, pipeline, config.planning, default_waypoints(config.cell.robot), seed=config.cell.seed,
                person_distance=cell.robot_person_distance,
            )
            return watched[name]

        t0 = time.perf_counter()
        print(f"  {name} ...", file=sys.stderr)
        summary = run(config, out / name.replace(". ", "").lower(), progress=True, record=False, trips=2 * trips, driver=make)
        moves = summary.get("trips", [])
        # A return trip is two moves (A→B, B→A).
        pairs = [moves[i : i + 2] for i in range(0, len(moves) - 1, 2)]
        per_trip = {
            key: [sum(m[key] for m in pair) for pair in pairs]
            for key in ("planning_time", "optimisation_time", "execution_time", "path_length")
        }
        planning = summary.get("planning", {})
        results[name] = {
            "return_trips": len(pairs),
            **{k: (float(np.mean(v)), float(np.std(v))) if v else (float("nan"), float("nan")) for k, v in per_trip.items()},
            "execution_times": per_trip["execution_time"],
            "collisions": sum(m["collisions"] for m in moves),
            "reflexes": sum(m["reflexes"] for m in moves),
            "reflex_rules": planning.get("reflex_rules", {}),
            "protective_stops": sum(m.get("protective_stops", 0) for m in moves),
            "stops": sum(m["stops"] for m in moves),
            "min_clearance_m": min((m["min_clearance"] for m in moves), default=float("inf")),
            "reflex_compute_ms": planning.get("reflex_compute_ms"),
            "reflex_cpu_ms": planning.get("reflex_cpu_ms"),
            "ssm_cpu_ms": planning.get("ssm_cpu_ms"),
            "ssm_slowed_frames": planning.get("ssm_slowed_frames", 0),
            "refused_plans": planning.get("refused_plans", 0),
            "reflexes_by_phase": reflexes_by_phase(watched[name].reflex_truth, moves),
            "reflex_truth": watched[name].reflex_truth,
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        if config.cell.person.enabled and scenario == "stress":
            results[name]["limit"] = limit_analysis(watched[name], config.cell.person)
        print(f"  {name}: {len(pairs)} return trips in {results[name]['wall_s']} s", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table2.json").write_text(jsonfile.dumps(results, indent=2))
    if watched:
        draw_paths(out / "paths.png", watched, results, scenario, seed)
    return results


def draw_paths(png: Path, watched: dict[str, WatchedExecutive], results: dict, scenario: str, seed: int) -> None:
    """Paper II's Fig. 8 in simulation: per experiment, the tool's paths over the trips
    (top view, one colour per return trip) on the map's danger averaged over the run
    (static scenery stays at 1; the person's reaches fade)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(watched)
    fig, axes = plt.subplots(1, len(names), figsize=(max(6.0, 4.2 * len(names)), 5.0), squeeze=False)
    for ax, name in zip(axes[0], names):
        executive = watched[name]
        lo, cell = executive.GRID_LO, executive.GRID_CELL
        extent = (lo[0], lo[0] + cell * executive.GRID_SHAPE[0], lo[1], lo[1] + cell * executive.GRID_SHAPE[1])
        ax.imshow(executive.danger_top.T, origin="lower", extent=extent, cmap="Reds", vmin=0, vmax=1, alpha=0.8)
        if executive.frames:
            times = np.array([f[0] for f in executive.frames])
            tools = executive.robot.fk(np.array([f[1] for f in executive.frames]))[:, -1, :3, 3]
            starts = [t.start_time for t in executive.trips[::2]] + [np.inf]
            colours = plt.cm.viridis(np.linspace(0, 1, max(1, len(starts) - 1)))
            for k in range(len(starts) - 1):
                sel = (times >= starts[k]) & (times < starts[k + 1])
                ax.plot(tools[sel, 0], tools[sel, 1], color=colours[k], lw=0.9)
            for t in executive.contact_times:
                i = int(np.searchsorted(times, t))
                ax.plot(*tools[min(i, len(tools) - 1), :2], "kx", ms=8)
        ax.plot(0, 0, "ks", ms=6)
        r = results[name]
        ax.set_title(f"{name}: {r['execution_time'][0]:.1f} s/trip, {r['reflexes']} reflexes,\n"
                     f"{r.get('protective_stops', 0)} protective stops, {r['stops']} stops, {r['collisions']} contacts", fontsize=9)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    axes[0][0].set_ylabel("y (m)")
    fig.suptitle(f"Table II, {scenario} scenario, seed {seed}\ntool paths per return trip (colour) on the average danger "
                 "(x: contact)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)


def format_table(results: dict) -> str:
    names = list(results)
    rows = [
        ("planning time (s)", "planning_time", "{:.4f} ± {:.4f}"),
        ("optimisation time (s)", "optimisation_time", "{:.4f} ± {:.4f}"),
        ("execution time (s)", "execution_time", "{:.2f} ± {:.2f}"),
        ("path length (rad)", "path_length", "{:.2f} ± {:.2f}"),
    ]
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, key, fmt in rows:
        lines.append(f"| {label} | " + " | ".join(fmt.format(*results[n][key]) for n in names) + " |")
    counts = (("return trips", "return_trips"), ("collisions", "collisions"), ("reflexes", "reflexes"), ("protective stops", "protective_stops"), ("stops", "stops"),
              ("plans refused for their way on", "refused_plans"))
    for label, key in counts:
        lines.append(f"| {label} | " + " | ".join(str(results[n].get(key, 0)) for n in names) + " |")
    lines.append("| reflexes by rule | " + " | ".join(
        ", ".join(f"{k} {v}" for k, v in sorted(results[n].get("reflex_rules", {}).items())) or "–" for n in names) + " |")
    if any(results[n].get("reflexes_by_phase") for n in names):
        lines.append("| reflexes by the arm's phase (in / held / back / rest) | " + " | ".join(
            " / ".join(str(results[n].get("reflexes_by_phase", {}).get(k, 0)) for k in ("in", "held", "back", "rest"))
            if results[n].get("reflexes_by_phase") else "–" for n in names) + " |")
    lines.append("| min. robot-person distance (m) | " + " | ".join(
        f"{results[n]['min_clearance_m']:.3f}" if np.isfinite(results[n]["min_clearance_m"]) else "–" for n in names) + " |")
    if any("limit" in results[n] for n in names):
        lines.append("| reaches started inside the avoidable limit | " + " | ".join(
            f"{results[n]['limit']['inside_limit']} of {results[n]['limit']['reaches']} "
            f"({results[n]['limit']['contacts_inside_limit']} of {results[n]['limit']['contacts']} contacts)"
            if "limit" in results[n] else "–" for n in names) + " |")
    return "\n".join(lines)


#: The danger of a voxel hit in the frame.
HIT_DANGER = DANGER_ON_HIT


class CirclesDriver:
    """Drives the Fig. 7 test: circles of the tool around the base at `height`, the pan
    joint sweeping a full turn per circle (alternating direction so the joint stays
    within its range), moves between circles time-parameterised; averages the danger
    map over the run on a grid around the robot."""

    def __init__(self, cell, pipeline, *, radii=(0.20, 0.32, 0.46), durations=(9.1, 14.69, 21.06),
                 repetitions: int = 20, height: float = 0.35) -> None:
        from earcore.planning.ik import solve_ik
        from earcore.planning.trajectory import time_parameterize
        from earcore.sim.tools import ObstaclePlate

        self.cell, self.pipeline = cell, pipeline
        self.radii, self.height = radii, height
        robot = cell.model
        # The plate hangs 10 cm below the flange, its plane vertical (seen by the side cameras).
        flange_from_plate = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0.1], [0, 0, 0, 1]], dtype=float)
        cell.attach_tool(ObstaclePlate(), flange_from_plate)
        down = np.diag([1.0, -1.0, -1.0, 1.0])  # tool z pointing down
        postures = []
        q = cell.q
        for r in radii:
            target = down.copy()
            target[:3, 3] = [r, 0.0, height + 0.1]
            q = solve_ik(robot, target, seed_q=q, position_tolerance=0.005).q
            postures.append(q)
        # The schedule: (start time, kind, data) segments, one after another.
        self.segments: list[tuple[float, str, Any]] = []
        t, q, direction = 0.0, cell.q.copy(), 1.0
        for _ in range(repetitions):
            for posture, duration in zip(postures, durations):
                start = posture.copy()
                start[0] = q[0]  # keep the pan angle where it is
                move = time_parameterize(np.stack([q, start]), cell.controller.max_velocity,
                                         cell.controller.max_acceleration, control_period=cell.config.time_step)
                self.segments.append((t, "move", move))
                t += move.duration
                self.segments.append((t, "circle", (start, direction, duration)))
                t += duration
                q = start.copy()
                q[0] += direction * 2 * np.pi
                direction = -direction
        self.end_time = t
        self.command = np.zeros(robot.dof)
        res = pipeline.tree.resolution
        self.res = res
        # Danger accumulated on a grid: 1.2 m around the base, ±0.25 m around the height.
        self.lo = np.array([-1.2, -1.2, height - 0.25])
        self.shape = np.ceil(np.array([2.4, 2.4, 0.5]) / res).astype(int)
        self.sum = np.zeros(self.shape)
        self.frames = 0
        # The occlusion effect, measured: per cell, frames in which it was fading (danger
        # before, not hit now) and, of those, frames in which it decayed (a ray saw it
        # free: the `observed` decay mode).
        self.previous = np.zeros(self.shape)
        self.fading = np.zeros(self.shape)
        self.seen_free = np.zeros(self.shape)
        # In how many repetitions each cell was hit: the plate's sweep is the cells hit in
        # at least half of them (a cell hit once, by noise or a robot point that slipped
        # through the self-filter, is not where the obstacle keeps appearing).
        self.repetitions = repetitions
        self.reps_hit = np.zeros(self.shape, dtype=int)
        self._last_rep_hit = np.full(self.shape, -1)
        self.repetition_starts = [t for t, kind, _ in self.segments[:: 2 * len(radii)] if kind == "move"]
        self.trips: list = []

    @property
    def finished(self) -> bool:
        return self.cell.time >= self.end_time

    def reference(self, t: float) -> np.ndarray:
        for start, kind, data in reversed(self.segments):  # noqa: B007  (the segment at t, used below)
            if t >= start:
                break
        if kind == "move":
            return data.sample(t - start)
        posture, direction, duration = data
        q = posture.copy()
        q[0] += direction * 2 * np.pi * min((t - start) / duration, 1.0)
        return q

    def control(self, dt: float) -> None:
        desired = (self.reference(self.cell.time + dt) - self.cell.q) / dt
        step = self.cell.controller.max_acceleration * dt
        self.command = np.clip(np.clip(desired, self.command - step, self.command + step),
                               -self.cell.controller.max_velocity, self.cell.controller.max_velocity)
        self.cell.command_velocities(self.command)

    def after_step(self) -> None:
        pass

    def on_frame(self) -> None:
        centres, _, values = self.pipeline.tree.danger_voxels()
        index = np.floor((centres - self.lo) / self.res).astype(int)
        inside = np.all((index >= 0) & (index < self.shape), axis=1)
        current = np.zeros(self.shape)
        current[tuple(index[inside].T)] = values[inside]
        self.sum += current
        fading = (self.previous > 0) & (current < HIT_DANGER)
        self.fading += fading
        self.seen_free += fading & (current < self.previous)
        self.previous = current
        rep = int(np.searchsorted(self.repetition_starts, self.cell.time, side="right")) - 1
        hit = (current >= HIT_DANGER) & (self._last_rep_hit != rep)
        self.reps_hit += hit
        self._last_rep_hit[hit] = rep
        self.frames += 1

    def average(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxel centres that ever held danger and their danger averaged over the run."""
        mean = self.sum / max(self.frames, 1)
        cells = np.argwhere(mean > 0)
        return (cells + 0.5) * self.res + self.lo, mean[tuple(cells.T)]

    def bands(self) -> list[dict]:
        """Mean of the time-averaged danger per band of horizontal radius (each band
        centred on a circle, half-way to its neighbours)."""
        centres, mean = self.average()
        radius = np.linalg.norm(centres[:, :2] - self.cell.model.base[:2, 3], axis=1)
        edges = np.r_[self.radii[0] - 0.1, [(a + b) / 2 for a, b in zip(self.radii[:-1], self.radii[1:])], self.radii[-1] + 0.12]
        cells = np.floor((centres - self.lo) / self.res).astype(int)
        fading, seen = self.fading[tuple(cells.T)], self.seen_free[tuple(cells.T)]
        swept = self.reps_hit[tuple(cells.T)] >= max(1, int(np.ceil(self.repetitions / 2)))
        out = []
        for r, lo, hi in zip(self.radii, edges[:-1], edges[1:]):
            sel = (radius >= lo) & (radius < hi)
            band = sel & swept
            out.append({"radius_m": r, "from_m": float(lo), "to_m": float(hi), "voxels": int(sel.sum()),
                        "mean_danger": float(mean[sel].mean()) if sel.any() else 0.0,
                        # The plate's sweep only: voxels hit in at least half of the repetitions.
                        "swept_voxels": int(band.sum()),
                        "mean_danger_swept": float(mean[band].mean()) if band.any() else 0.0,
                        # Occlusion: how often a fading voxel of the band was seen free.
                        "seen_free_while_fading": float(seen[sel].sum() / fading[sel].sum()) if fading[sel].sum() else 0.0})
        return out

    def summary(self) -> dict:
        return {"frames": self.frames, "bands": self.bands()}


def fig7(repetitions: int = 20, camera_scale: float = 0.25, out: Path = Path("out/fig7"), seed: int = 0) -> dict:
    """Run the danger-map construction test; writes fig7.png and fig7.json to `out`."""
    from earcore.app.run import run

    config = RunConfig(duration=1e9, snapshots=[])
    config.cell.seed = seed
    config.cell.camera_scale = camera_scale
    config.cell.robot_meshes = "collision"
    config.cell.person.enabled = False
    config.cell.boxes = []
    # The overhead camera straight above the base, so that the whole circles are in its
    # view: the main cell's, above a point 35 cm in front, does not see the back of the
    # outer circle, where the side cameras look through the robot.
    config.cell.cameras = [
        replace(c, position=(0.0, 0.0, c.position[2]), target=(0.0, 0.0, 0.0)) if c.name == "kinect_v1_overhead" else c
        for c in config.cell.cameras
    ]
    holder = {}

    def make(cell, pipeline):
        holder["driver"] = CirclesDriver(cell, pipeline, repetitions=repetitions)
        return holder["driver"]

    print(f"  fig7: {repetitions} repetitions of the three circles (~{44.85 * repetitions:.0f} s simulated)", file=sys.stderr)
    summary = run(config, out, progress=False, record=False, driver=make)
    driver = holder["driver"]
    result = {"repetitions": repetitions, "simulated_s": summary["simulated_s"], "bands": driver.bands()}
    out.mkdir(parents=True, exist_ok=True)
    (out / "fig7.json").write_text(jsonfile.dumps(result, indent=2))
    _draw_fig7(out / "fig7.png", driver, result)
    return result


def _draw_fig7(png: Path, driver: CirclesDriver, result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres, mean = driver.average()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5.2), gridspec_kw={"width_ratios": [1.3, 1]})
    # Top view: the highest time-averaged danger over the heights of each column.
    order = np.argsort(mean)
    sc = ax.scatter(centres[order, 0], centres[order, 1], c=mean[order], s=30, marker="s", cmap="YlOrRd", vmin=0, vmax=1)
    for r in driver.radii:
        ax.add_patch(plt.Circle((0, 0), r, fill=False, ls="--", color="tab:blue", lw=1))
    ax.set_aspect("equal")
    ax.set_xlim(-0.8, 0.8)
    ax.set_ylim(-0.8, 0.8)
    ax.set_title("average danger per voxel (top view), circles of the plate (dashed)")
    fig.colorbar(sc, ax=ax, shrink=0.8, label="danger averaged over the run")
    bands = result["bands"]
    bars = bx.bar([f"{b['radius_m']*100:.0f} cm" for b in bands], [b["mean_danger_swept"] for b in bands], color=["#b2182b", "#ef8a62", "#fddbc7"])
    for bar, b in zip(bars, bands):
        bx.annotate(f"{b['mean_danger_swept']:.2f} (all: {b['mean_danger']:.2f})\nseen free {100 * b['seen_free_while_fading']:.0f} %\nof fading frames",
                    (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom", fontsize=8)
    bx.set_ylim(0, 1)
    bx.set_ylabel("mean average danger of the plate's sweep")
    bx.set_title(f"per band, {result['repetitions']} repetitions\n(Paper II: inner 0.5-1, middle 0.2-0.5, outer 0-0.2)")
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog="earcore experiment", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=["table2", "fig7", "calibration"], help="which experiment (calibration: Paper I's Tables II-III)")
    parser.add_argument("--repetitions", type=positive_int, default=20, help="fig7: repetitions of the three circles (default 20)")
    parser.add_argument("--trips", type=positive_int, default=15, help="A-B-A return trips per experiment (default 15)")
    parser.add_argument("--seed", type=count, default=0)
    parser.add_argument("--camera-scale", type=scale, default=0.25, help="camera resolution factor (rendering dominates the run time)")
    parser.add_argument("--only", nargs="*", help="run only these experiments, e.g. 'Exp. 3' Direct")
    parser.add_argument("--out", type=Path, default=Path("out/table2"), help="output folder (fig7: out/fig7)")
    parser.add_argument(
        "--reflex-rule", choices=("eq2", "prediction"), default="prediction",
        help="table2: when Exp. 3's reflexes fire: the hand's predicted course meeting the robot's motion (default) or Eq. 2 (the paper)",
    )  # fmt: skip
    parser.add_argument("--scenario", choices=sorted(SCENARIOS), default="stress",
                        help="table2: the person's reaches: fast ones one after another (stress) or Paper II's protocol (paper)")
    if argv and argv[0] == "calibration":
        from earcore.app.experiments.calibration import main as calibration_main

        return calibration_main(argv[1:])
    args = parser.parse_args(argv)
    names = list(experiment_configs(args.seed, args.camera_scale))
    if args.only is not None and (not args.only or set(args.only) - set(names)):
        unknown = sorted(set(args.only) - set(names))
        parser.error(f"argument --only: {'unknown experiments ' + repr(unknown) if unknown else 'names no experiment'}; "
                     f"choose from {', '.join(repr(n) for n in names)}")
    if args.name == "fig7":
        out = args.out if args.out != Path("out/table2") else Path("out/fig7")
        result = fig7(args.repetitions, args.camera_scale, out, args.seed)
        for b in result["bands"]:
            print(f"  circle {100 * b['radius_m']:.0f} cm (band {100 * b['from_m']:.0f}-{100 * b['to_m']:.0f} cm): "
                  f"mean danger {b['mean_danger_swept']:.3f} over the {b['swept_voxels']} voxels of the plate's sweep "
                  f"({b['mean_danger']:.3f} over all {b['voxels']} that held danger), "
                  f"seen free in {100 * b['seen_free_while_fading']:.0f} % of the frames they were fading")
        print(f"picture: {out / 'fig7.png'}")
        return 0
    results = table2(args.trips, args.seed, args.camera_scale, args.out, args.only, args.reflex_rule, args.scenario)
    print(format_table(results))
    print(f"picture: {args.out / 'paths.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
