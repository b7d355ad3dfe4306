"""The simulated cell's configuration (robot, table, boxes, cameras, person).

Field names are the TOML keys of `[cell]` in `earcore run`'s configuration. Every default is the paper's setup (Paper II, Table I):
a UR5 on a table, two Kinect V2-like cameras at ±45° in front, a Kinect V1-like camera
overhead, an F200-like camera on the end-effector, a person reaching in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from earcore.validate import ConfigError, count, fraction, non_negative, one_of, positive, vector

__all__ = ["CameraConfig", "CellConfig", "PersonConfig", "calibration_cameras", "default_cameras"]


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

    def validate(self, where: str) -> CameraConfig:
        from earcore.sim.sensors import SENSORS

        one_of(self.sensor, sorted(SENSORS), f"{where}.sensor")
        one_of(self.mount, ("world", "end_effector"), f"{where}.mount")
        position = vector(self.position, f"{where}.position", 3)
        target = vector(self.target, f"{where}.target", 3)
        if self.mount == "world" and position == target:
            raise ConfigError(f"{where}: position and target must differ (the camera looks from one at the other)")
        positive(self.rate_hz, f"{where}.rate_hz", at_most=1000.0)
        return self


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
    target = (0.45, 0.0, 0.3)
    centre = np.array(target)

    def place(azimuth: float, elevation: float, distance: float = 1.05) -> tuple[float, float, float]:
        a, e = np.radians(azimuth), np.radians(elevation)
        x, y, z = (float(v) for v in centre + distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]))
        return x, y, z

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

    def validate(self, where: str) -> PersonConfig:
        vector(self.shoulder, f"{where}.shoulder", 3)
        vector(self.rest_hand, f"{where}.rest_hand", 3)
        positive(self.peak_speed, f"{where}.peak_speed", at_most=10.0)
        starts = vector(self.reach_starts, f"{where}.reach_starts")
        if any(s < 0 for s in starts):
            raise ConfigError(f"{where}.reach_starts must be >= 0 s, got {self.reach_starts!r}")
        if len(self.reach_targets) != len(starts):
            raise ConfigError(f"{where}.reach_targets must have one target per reach start ({len(starts)}), got {len(self.reach_targets)}")
        for i, target in enumerate(self.reach_targets):
            vector(target, f"{where}.reach_targets[{i}]", 3)
        non_negative(self.hold_s, f"{where}.hold_s")
        for name, values in (("reach_speeds", self.reach_speeds), ("reach_holds", self.reach_holds)):
            checked = vector(values, f"{where}.{name}")
            if checked and len(checked) != len(starts):
                raise ConfigError(f"{where}.{name} must be empty or have one entry per reach start ({len(starts)}), got {len(checked)}")
            if any(v < 0 or (name == "reach_speeds" and v == 0) for v in checked):
                raise ConfigError(f"{where}.{name} must be {'> 0' if name == 'reach_speeds' else '>= 0'}, got {values!r}")
        non_negative(self.wander, f"{where}.wander")
        non_negative(self.arrive_s, f"{where}.arrive_s")
        return self


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
    #: What draws the cameras' images: "raster", the core's rasterizer (exact geometry,
    #: Lambert-shaded colours, no textures; a 512×424 frame of the cell in under 10 ms),
    #: or "pybullet", its tiny renderer (textures, e.g. the calibration board; 5-10×
    #: slower). Labels agree on 99.4 %+ of the pixels (the rest on silhouettes, and on the
    #: person's capsules, which pybullet draws as coarser, slightly smaller polygons).
    renderer: str = "raster"
    person: PersonConfig = field(default_factory=PersonConfig)
    #: Joint speed and acceleration limits as fractions of the maximum (Table I).
    speed_fraction: float = 0.5
    acceleration_fraction: float = 0.6
    #: Maximum joint acceleration (rad/s²) when the URDF gives none.
    max_acceleration: float = 3.0
    #: Simulation step (s); cameras capture at their own rates on this clock.
    time_step: float = 1.0 / 30.0

    def validate(self, where: str = "cell") -> CellConfig:
        """Raise `ConfigError` naming the first setting out of its range; returns self."""
        from earcore.robots import BUILTIN_MODELS

        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**31:
            raise ConfigError(f"{where}.seed must be a whole number in [0, 2^31), got {self.seed!r}")
        one_of(self.robot, sorted(BUILTIN_MODELS), f"{where}.robot")
        non_negative(self.padding, f"{where}.padding")
        if self.padding > 0.5:
            raise ConfigError(f"{where}.padding must be at most 0.5 m, got {self.padding!r}")
        for i, v in enumerate(vector(self.table_size, f"{where}.table_size", 2)):
            positive(v, f"{where}.table_size[{i}]", at_most=100.0)
        positive(self.table_height, f"{where}.table_height", at_most=10.0)
        for i, box in enumerate(self.boxes):
            b = vector(box, f"{where}.boxes[{i}]", 6)
            if not all(b[k] < b[k + 3] for k in range(3)):
                raise ConfigError(f"{where}.boxes[{i}] must be (x_min, y_min, z_min, x_max, y_max, z_max) with each min < max, got {box!r}")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ConfigError(f"{where}.cameras: names must be unique, got {names}")
        for i, camera in enumerate(self.cameras):
            camera.validate(f"{where}.cameras[{i}]")
        positive(self.camera_scale, f"{where}.camera_scale", at_most=4.0)
        if self.camera_scale < 0.05:
            raise ConfigError(f"{where}.camera_scale must be at least 0.05, got {self.camera_scale!r}")
        positive(self.colour_scale, f"{where}.colour_scale", at_most=4.0)
        count(self.supersample, f"{where}.supersample")
        if self.supersample > 8:
            raise ConfigError(f"{where}.supersample must be at most 8 (8×8 samples per pixel), got {self.supersample!r}")
        one_of(self.robot_meshes, ("visual", "collision"), f"{where}.robot_meshes")
        one_of(self.renderer, ("raster", "pybullet"), f"{where}.renderer")
        self.person.validate(f"{where}.person")
        fraction(self.speed_fraction, f"{where}.speed_fraction", zero=False)
        fraction(self.acceleration_fraction, f"{where}.acceleration_fraction", zero=False)
        positive(self.max_acceleration, f"{where}.max_acceleration")
        positive(self.time_step, f"{where}.time_step", at_most=0.1)
        if self.time_step < 1e-4:
            raise ConfigError(f"{where}.time_step must be at least 0.0001 s, got {self.time_step!r}")
        return self
