"""The cell's configuration: one typed structure, loaded from and dumped to TOML.

Field names are the TOML keys. Every default is the paper's setup (Paper II, Table I):
a UR5 on a table, two Kinect V2-like cameras at ±45° in front, a Kinect V1-like camera
overhead, an F200-like camera on the end-effector, a person reaching in.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CameraConfig",
    "CellConfig",
    "PerceptionConfig",
    "PersonConfig",
    "PlanningConfig",
    "RunConfig",
    "calibration_cameras",
    "dump_toml",
    "load_config",
]


@dataclass
class CameraConfig:
    name: str
    #: A key of `earcore.sim.sensors.SENSORS`: kinect_v2, kinect_v1, f200, webcam (colour only).
    sensor: str
    #: Camera position and the point it looks at, in the robot base frame (m); for a
    #: camera on the end-effector, the offset along the tool's z axis instead.
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: "world" for a fixed camera, "end_effector" for one carried by the robot.
    mount: str = "world"
    #: Frames per second (the paper: 15 for the Kinects, 30 for the F200).
    rate_hz: float = 15.0


def default_cameras() -> list[CameraConfig]:
    return [
        CameraConfig("kinect_v2_left", "kinect_v2", (1.45, 1.45, 0.9), (0.25, 0.0, 0.15)),
        CameraConfig("kinect_v2_right", "kinect_v2", (1.45, -1.45, 0.9), (0.25, 0.0, 0.15)),
        CameraConfig("kinect_v1_overhead", "kinect_v1", (0.35, 0.0, 2.1), (0.3, 0.0, 0.0)),
        CameraConfig("f200_wrist", "f200", (0.0, 0.0, 0.05), mount="end_effector", rate_hz=30.0),
    ]


def calibration_cameras() -> list[CameraConfig]:
    """Paper I's calibration set-up: two Kinect V2-like cameras at ±45° to the robot's
    work area and a Kinect V1-like camera between them, facing it, each 1.05 m from the
    area's centre (0.45, 0, 0.3): close enough that the robot carries the 21 × 15 cm
    board over most of each image (the main cell's cameras, 2.2 m away, see it ~35 px
    wide, too small for a lens calibration)."""
    centre = np.array([0.45, 0.0, 0.3])

    def place(azimuth: float, elevation: float, distance: float = 1.05) -> tuple[float, float, float]:
        a, e = np.radians(azimuth), np.radians(elevation)
        return tuple(float(v) for v in centre + distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]))

    target = tuple(float(v) for v in centre)
    return [
        CameraConfig("kinect_v2_left", "kinect_v2", place(45, 25), target),
        CameraConfig("kinect_v2_right", "kinect_v2", place(-45, 25), target),
        CameraConfig("kinect_v1_front", "kinect_v1", place(0, 30), target),
    ]


@dataclass
class PersonConfig:
    enabled: bool = True
    #: Where the person's shoulder is, and the hand's rest position (base frame, m).
    shoulder: tuple[float, float, float] = (0.95, 0.45, 0.45)
    rest_hand: tuple[float, float, float] = (0.85, 0.5, 0.05)
    #: Peak hand speed (m/s); ISO/TS 15066 assumes up to 1.6.
    peak_speed: float = 1.2
    #: Reaches: start times (s) and hand targets; empty = random ones from the seed.
    reach_starts: list[float] = field(default_factory=lambda: [1.0])
    reach_targets: list[tuple[float, float, float]] = field(default_factory=lambda: [(0.45, 0.25, 0.2)])
    hold_s: float = 1.5
    #: Peak hand speed (m/s) and hold (s) per reach; empty = `peak_speed` / `hold_s`.
    reach_speeds: list[float] = field(default_factory=list)
    reach_holds: list[float] = field(default_factory=list)
    #: While held, the hand moves about its target by up to this much (m); 0 = still.
    wander: float = 0.0
    #: When the person steps up to the cell (s); before, the arm is out of the scene.
    #: The reflexes' obstacle tracker learns the static scene during the planner's
    #: warm-up (0.5 s) and assumes nobody is there then: a resting arm learned as static
    #: hid the first 15 cm of its reach.
    arrive_s: float = 0.75


@dataclass
class CellConfig:
    seed: int = 0
    #: A built-in robot (ur3, ur5, ur10, iiwa, panda).
    robot: str = "ur5"
    #: Link body padding (m), Paper II: 5 mm.
    padding: float = 0.005
    #: Table top at z = 0 (the robot's base), size (m) and height above the floor.
    table_size: tuple[float, float] = (1.6, 1.4)
    table_height: float = 0.75
    #: Static boxes on the table: (x_min, y_min, z_min, x_max, y_max, z_max) each.
    #: The default clutter (parts boxes, a tray) also gives the cameras' ICP alignment
    #: 3D structure to lock onto; a bare table is ambiguous along its plane.
    boxes: list[tuple[float, float, float, float, float, float]] = field(
        default_factory=lambda: [
            (-0.45, 0.35, 0.0, -0.25, 0.6, 0.25),
            (0.6, -0.6, 0.0, 0.8, -0.35, 0.4),
            (-0.3, -0.6, 0.0, -0.1, -0.45, 0.15),
            (0.9, -0.3, 0.0, 1.1, -0.1, 0.3),
        ]
    )
    cameras: list[CameraConfig] = field(default_factory=default_cameras)
    #: Resolution factor for every camera (1 = the sensor's own; 0.5 renders 4× fewer pixels).
    camera_scale: float = 1.0
    #: Further resolution factor of the separate colour cameras (a 1920×1080 frame takes
    #: ~2 s with the tiny renderer; only calibration renders them).
    colour_scale: float = 0.5
    #: Render s×s samples per pixel (anti-aliasing, s² the render time); calibration
    #: uses 2 for sharper checkerboard corners.
    supersample: int = 1
    #: What the cameras see of the robot: its URDF's "visual" meshes, or its "collision"
    #: meshes (`earcore.urdf.collision_as_visual`). A UR arm's visual meshes have many
    #: times the triangles, which dominate small renders: at camera_scale 0.25 a frame of
    #: the four cameras takes 33 ms instead of 112, with depth on the robot within ~1 mm
    #: (the experiments use them). The panda's collision meshes are convex hulls (2-4 cm
    #: off); the iiwa's are its visual meshes (no gain).
    robot_meshes: str = "visual"
    person: PersonConfig = field(default_factory=PersonConfig)
    #: Joint speed and acceleration limits as fractions of the maximum (Table I).
    speed_fraction: float = 0.5
    acceleration_fraction: float = 0.6
    #: Maximum joint acceleration (rad/s²) when the URDF gives none.
    max_acceleration: float = 3.0
    #: Simulation step (s); cameras capture at their own rates on this clock.
    time_step: float = 1.0 / 30.0


@dataclass
class PerceptionConfig:
    #: Map frames per second (Paper II: 15, the Kinects' rate); faster cameras
    #: contribute their newest frame to each map frame.
    rate_hz: float = 15.0
    resolution: float = 0.05
    crop_radius: float = 1.5
    #: Points lower than this (m, base frame) only clear the space in front of them (free
    #: rays, no hit): the robot's table (its top at z = 0) is known geometry, added to
    #: the map by `PerceptionPipeline.add_support`, and sensed table points would fill
    #: the 5 cm voxels above the top with obstacles that the robot's shoulder brushes.
    #: None inserts every point as a hit.
    min_height: float | None = 0.02
    #: Rays of the points beyond `crop_radius` still clear the space inside the crop
    #: sphere (free rays cut where they leave it, no hit). Paper II drops those points
    #: outright, so space that cameras see only against a far background never decays.
    clear_beyond_crop: bool = True
    outlier_k: int = 20
    outlier_std_ratio: float = 2.0
    #: Voxel-grid size before insertion (m); 0 disables it.
    voxel_size: float = 0.02
    max_range: float = 4.5
    danger_alpha: float = 0.3
    decay_mode: str = "observed"
    #: Growth (m) of the robot's bodies for the self-filter on top of their padding, for
    #: sensor noise: with the Kinect V1's 1.1-1.3 cm depth steps at 2 m, Paper II's 5 mm
    #: alone leaves ~0.9 % of the robot's points in the map.
    self_filter_margin: float = 0.01
    #: A calibration file (`earcore calibrate`): the cameras it names use its poses and
    #: depth lenses instead of the simulation's ground truth. Empty: ground truth.
    calibration: str = ""
    #: Refine the camera poses once with ICP against each other (Paper II).
    refine_poses: bool = False
    #: Perturb the ground-truth camera poses by this much (m, rad) before use, to
    #: exercise the refinement; 0 = ground truth.
    pose_error: tuple[float, float] = (0.0, 0.0)


@dataclass
class PlanningConfig:
    """Paper II's planning layers (Table I)."""

    #: "predictive" (danger-costed choice + reflexes, Paper II), "reactive" (the
    #: paper's baseline: shortest path, stop and re-plan when blocked) or "none" (the
    #: robot shuttles along the straight joint-space path, no planning).
    mode: str = "predictive"
    #: RRT-Connect: time limit per attempt (s) and attempts (solutions to choose from).
    time_limit: float = 1.0
    attempts: int = 3
    #: Largest joint step (rad) between checked configurations along a motion.
    motion_resolution: float = 0.02
    #: Re-plan the rest of the path every this many seconds when the danger map offers
    #: a path cheaper by `replan_gain` (0 = only when the path is blocked).
    replan_period: float = 1.0
    replan_gain: float = 0.15
    #: Reflexes (Eqs. 2-3): risk D = |v|² / (β d) against the threshold T.
    reflexes: bool = True
    risk_beta: float = 1.5
    risk_threshold: float = 1.0
    #: v in Eq. 2: the obstacle's velocity relative to the robot's closest point (true),
    #: or the obstacle's own velocity as in the paper (false).
    relative_velocity: bool = True
    #: Backtracking: this fraction of the executed path; else move the end-effector
    #: this far away from the closest obstacle point (m).
    backtrack_fraction: float = 0.1
    move_away_distance: float = 0.15
    #: Beyond the paper: an approaching obstacle closer than this (m) also fires the
    #: reflex, as a move away (a slow hand's risk D stays below T until it touches).
    min_separation: float = 0.06
    #: Beyond the paper: paths keep this much clearance (m) from the tracked moving
    #: obstacles (people) on top of not touching what the map holds of them: the cameras
    #: see one side of a hand, and a tight path brushed its other side. 0 = off.
    person_margin: float = 0.04
    #: Round planned paths' corners by arcs at most this far (rad) from each corner
    #: before they run, where the rounded path is still valid (else a quarter of it,
    #: else none); corners are otherwise taken at a crawl. 0 = off, the default: with
    #: 0.1 rad every experiment ran 25-35 % faster, Exp. 1 most (10.7 -> 7.0 s per
    #: return trip, Exp. 3 11.1 -> 7.9 s), and Exp. 3 touched the person once in five
    #: seeds (a faster robot meets more fast reaches while moving; NOTES.md, session 13).
    blend_deviation: float = 0.0
    #: The share of each joint's acceleration limit that planned paths and backtracks
    #: use along straight stretches away from corners (`time_parameterize`'s
    #: `straight_share`): 0.5, the default, splits it with the curvature everywhere; 1.0
    #: uses it all where no curvature competes, so straight moves run ~30 % faster (A to
    #: B: 2.63 -> 1.86 s). Left at 0.5 until the experiments (people reaching in) have
    #: been run with 1.0; reflexes' moves away are per-joint transfers either way.
    straight_acceleration_share: float = 0.5
    #: Goal tolerances for end-effector pose goals (m, rad).
    position_tolerance: float = 0.01
    orientation_tolerance: float = 0.1
    #: Seconds of the run before planning starts, used to learn the static scene (the
    #: reflex layer tracks what is not part of it).
    warmup: float = 0.5


@dataclass
class RunConfig:
    #: Simulated seconds: long enough for the danger the arm leaves (~3 s) to fade (~21 s).
    duration: float = 30.0
    #: Snapshot times (s) of the danger map (PNG).
    snapshots: list[float] = field(default_factory=lambda: [2.5, 10.0, 20.0, 29.9])
    #: Joint targets the robot shuttles between (A-B-A); empty = the robot's defaults.
    waypoints: list[list[float]] = field(default_factory=list)
    cell: CellConfig = field(default_factory=CellConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    planning: PlanningConfig = field(default_factory=PlanningConfig)


def _build(cls, data: dict[str, Any], where: str):
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)}; known: {sorted(known)}")
    kwargs = {}
    for name, value in data.items():
        kind = known[name].type
        if name == "cell":
            value = _build(CellConfig, value, f"{where}.cell")
        elif name == "perception":
            value = _build(PerceptionConfig, value, f"{where}.perception")
        elif name == "planning":
            value = _build(PlanningConfig, value, f"{where}.planning")
        elif name == "person":
            value = _build(PersonConfig, value, f"{where}.person")
        elif name == "cameras":
            value = [_build(CameraConfig, c, f"{where}.cameras[{i}]") for i, c in enumerate(value)]
        elif str(kind).startswith("tuple"):
            value = tuple(value)
        elif str(kind).startswith("list[tuple"):
            value = [tuple(v) for v in value]
        kwargs[name] = value
    return cls(**kwargs)


def load_config(path: str | Path) -> RunConfig:
    """Read a TOML file (missing keys keep their defaults; unknown keys are errors)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path} is not valid TOML: {exc}") from exc
    return _build(RunConfig, data, path.name)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(config: RunConfig) -> str:
    """The configuration as TOML (round-trips through `load_config`)."""
    lines: list[str] = []

    def table(obj, prefix: str) -> None:
        data = asdict(obj)
        nested = []
        for f in fields(obj):
            value = getattr(obj, f.name)
            if is_dataclass(value):
                nested.append((f.name, value))
            elif f.name == "cameras":
                nested.append((f.name, value))
            else:
                lines.append(f"{f.name} = {_toml_value(data[f.name])}")
        for name, value in nested:
            if name == "cameras":
                for cam in value:
                    lines.append(f"\n[[{prefix}{name}]]")
                    for cf in fields(cam):
                        lines.append(f"{cf.name} = {_toml_value(getattr(cam, cf.name))}")
            else:
                lines.append(f"\n[{prefix}{name}]")
                table(value, f"{prefix}{name}.")

    table(config, "")
    return "\n".join(lines) + "\n"
