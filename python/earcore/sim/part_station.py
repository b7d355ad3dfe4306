"""A parts station in the robot's cell: parts on a platform on the table in front of the
robot, seen from above by an SR300-like RGB-D camera, with the truth in the robot's
base frame.

    station = PartStation(seed=3)
    view = station.view(0)       # the camera's images, intrinsics, pose and the parts' truth
    view.centres                 # (n, 3) m: each part's centre of gravity in the base frame
    station.close()

The scene is the parts dataset's (`earcore.sim.part_images`: the same parts, colours,
light, trays and camera placements, drawn from (seed, view number)), its platform put on
the cell's table (whose top is the base frame's z = 0, `SimulatedCell.table_box`) at
`base_from_platform`. A view's `base_from_camera` is the camera's true pose: a
calibration (`earcore calibrate`) estimates it for a real camera, and
`calibrated_pose` gives it a calibration's error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.sim.part_images import PartImageOptions, PartImageRenderer, PartSpec

__all__ = ["BASE_FROM_PLATFORM", "PartStation", "StationView", "calibrated_pose"]

#: The station's views are the generator's images from this number on (datasets hold at most 10^7).
STATION_IMAGES = 2**40

#: The platform's centre 45 cm in front of the robot's base, on the table (z = 0).
BASE_FROM_PLATFORM = np.array([[1.0, 0, 0, 0.45], [0, 1.0, 0, 0.0], [0, 0, 1.0, 0.0], [0, 0, 0, 1.0]])


def calibrated_pose(pose: np.ndarray, millimetres: float, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """`pose` (4x4) as a calibration with this error would give it: moved by
    `millimetres` in a random direction, turned by `degrees` about a random axis."""
    from earcore.transforms import axis_angle_matrix

    out = np.array(pose, dtype=np.float64)
    move, axis = rng.normal(size=3), rng.normal(size=3)
    out[:3, 3] += 1e-3 * millimetres * move / np.linalg.norm(move)
    out[:3, :3] = axis_angle_matrix(axis / np.linalg.norm(axis), np.radians(degrees)) @ out[:3, :3]
    return out


@dataclass(frozen=True)
class StationView:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth_mm: np.ndarray  # (H, W) uint16, 0 = no return
    instances: np.ndarray  # (H, W) uint8: 0 background, i >= 1 part i - 1
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy
    base_from_camera: np.ndarray  # (4, 4), the truth
    classes: np.ndarray  # (n,) class index of each part
    centres: np.ndarray  # (n, 3) m, each part's centre of gravity in the base frame
    class_names: tuple[str, ...]

    @property
    def depth_m(self) -> np.ndarray:
        return self.depth_mm.astype(np.float64) / 1000.0


class PartStation:
    """Views of parts on the station's platform; one pybullet world (close it)."""

    def __init__(
        self,
        *,
        width: int = 128,
        height: int = 96,
        seed: int = 0,
        objects: tuple[int, int] = (2, 12),
        classes: tuple[str, ...] | None = None,
        base_from_platform: np.ndarray = BASE_FROM_PLATFORM,
    ) -> None:
        settings = {} if classes is None else {"classes": tuple(classes)}
        self.options = PartImageOptions(width=width, height=height, seed=seed, objects=objects, count=1, **settings).validate()  # type: ignore[arg-type]
        pose = np.asarray(base_from_platform, dtype=np.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"base_from_platform must be 4x4, got {pose.shape}")
        self.base_from_platform = pose
        self.renderer = PartImageRenderer(self.options)

    def view(self, index: int) -> StationView:
        # an image number no dataset of this seed uses: the station's views are not its images
        r = self.renderer.render(PartSpec(f"station-{index}", STATION_IMAGES + int(index), "test"))
        row = r.sample.row
        n = int(row["count"])
        base_from_camera = self.base_from_platform @ r.world_from_camera
        camera = np.array([[row[f"obj{i}_{a}"] for a in "xyz"] for i in range(n)]).reshape(n, 3)
        centres = camera @ base_from_camera[:3, :3].T + base_from_camera[:3, 3]
        return StationView(
            rgb=r.sample.images["rgb"],
            depth_mm=r.sample.images["depth"],
            instances=r.sample.images["instances"],
            intrinsics=(float(row["fx"]), float(row["fy"]), float(row["cx"]), float(row["cy"])),
            base_from_camera=base_from_camera,
            classes=np.array([int(row[f"obj{i}_class"]) for i in range(n)], dtype=np.int64),
            centres=centres,
            class_names=tuple(self.options.classes),
        )

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> PartStation:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
