"""The charging station's eye-to-hand calibration without markers (Paper III's future
work): the robot turns its plug to face the stereo pair and moves it through poses it
picks itself; the plug's pins, found in both images, give the plug's pose in the left
camera; Tsai-Lenz gives the left camera in the robot's base and the plug's tip on the
flange, and a joint fit of both to all poses' pins refines them. Poses whose match is
poor (flagged by `charging.locate`) are discarded.

    result = calibrate_markerless(station, robot, flange_link, rough_camera, rough_tip)

`rough_camera` (the left camera's pose in the base, as installed: centimetres and
degrees off do) and `rough_tip` (the plug's tip on the flange, as designed) only aim
the plug at the cameras. The station is what `charging.plug_in` needs plus
`capture()` and `rig` (the stereo pair's own calibration).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import earcore
from earcore.calibration.eye_to_hand import apply_pose, fit_eye_to_hand, fit_eye_to_hand_from_poses
from earcore.charging.connectors import Connector
from earcore.charging.locate import locate
from earcore.charging.matching import ShapeModel
from earcore.errors import EarcoreError
from earcore.planning.ik import UnreachablePose, solve_ik
from earcore.transforms import axis_angle_matrix, look_at

__all__ = ["MarkerlessCalibration", "MarkerlessConfig", "calibrate_markerless", "workspace_error_mm"]


class CalibrationFailed(EarcoreError):
    """Too few poses showed the plug well enough to calibrate."""


@dataclass(frozen=True)
class MarkerlessConfig:
    #: Poses the robot picks (at most), and how many good ones it needs at least.
    poses: int = 30
    min_good: int = 8
    #: Where the plug goes: this far from the left camera (m), this far across the
    #: view (a fraction of the distance), facing the pair's midpoint within `tilt_deg`
    #: and turned about its axis within `roll_deg`.
    distance: tuple[float, float] = (1.2, 1.8)
    across: float = 0.12
    tilt_deg: float = 12.0
    roll_deg: float = 60.0
    seed: int = 0


@dataclass
class MarkerlessCalibration:
    base_from_camera: np.ndarray
    flange_from_tip: np.ndarray
    #: The Tsai-Lenz solution before the joint refinement.
    tsai: tuple[np.ndarray, np.ndarray]
    #: RMS distance (mm) between the pins as seen and as the robot put them.
    rmse_mm: float
    used: int
    tried: int
    discarded: list[str] = field(default_factory=list)


def _targets(config: MarkerlessConfig, rough_camera: np.ndarray, middle: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Tip poses facing the pair: the pins (the tip's −z) towards the pair's middle."""
    out = []
    for _ in range(config.poses * 3):
        depth = rng.uniform(*config.distance)
        local = np.array([rng.uniform(-1, 1) * config.across * depth, rng.uniform(-1, 1) * config.across * depth, depth])
        position = rough_camera[:3, :3] @ local + rough_camera[:3, 3]
        # look_at's z points from the eye to the target: away from the cameras, as the tip's z must
        rotation = look_at(middle, position)[:3, :3]
        across = rng.normal(size=3) * [1.0, 1.0, 0.0]
        tilt = axis_angle_matrix(across / np.linalg.norm(across), np.radians(rng.uniform(0, config.tilt_deg)))
        rotation = rotation @ tilt @ axis_angle_matrix([0.0, 0.0, 1.0], np.radians(rng.uniform(-config.roll_deg, config.roll_deg)))
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, position
        out.append(pose)
    return out


def calibrate_markerless(
    station,
    robot,
    flange_link: int,
    plug: Connector,
    rough_camera: np.ndarray,
    rough_tip: np.ndarray,
    config: MarkerlessConfig | None = None,
    *,
    progress=None,
) -> MarkerlessCalibration:
    """Calibrate the left camera and the plug's tip (see the module's docstring). The
    robot ends where it started. Raises CalibrationFailed."""
    c = config or MarkerlessConfig()
    rng = np.random.default_rng(c.seed)
    rig = station.rig
    model = ShapeModel.plug(plug)
    right_in_left = np.linalg.inv(rig.right_from_left)[:3, 3]
    middle = rough_camera[:3, :3] @ (right_in_left / 2) + rough_camera[:3, 3]
    start = station.joints
    pins = plug.reference_points - [0.0, 0.0, plug.pin_length]  # the pins' tips in the tip frame
    flanges, seen, discarded = [], [], []
    tried, q = 0, start
    tip_from_flange = np.linalg.inv(rough_tip)
    free_space = earcore.OcTree(0.05)  # nothing but the robot itself to avoid
    try:
        for target in _targets(c, rough_camera, middle, rng):
            if tried >= c.poses:
                break
            try:
                q = solve_ik(robot, target @ tip_from_flange, link=flange_link, seed_q=q, tree=free_space, position_tolerance=1e-3,
                             orientation_tolerance=5e-3, restarts=4, iterations=150, rng=rng).q  # fmt: skip
            except UnreachablePose:
                continue  # not a pose tried: the robot never went there
            if robot.check_motion(free_space, station.joints, q, 0.02):
                q = station.joints
                continue  # the arm would pass through itself on the way
            tried += 1
            station.set_joints(q)
            left, right = station.capture()
            estimate = locate(left, right, model, rig)
            if progress is not None:
                progress(tried)
            if estimate is None:
                discarded.append(f"pose {tried}: the plug not found in both images")
                continue
            if estimate.flagged:
                discarded.append(f"pose {tried}: " + "; ".join(estimate.reasons))
                continue
            flanges.append(robot.fk(q)[flange_link])
            seen.append(estimate.camera_from_port)
    finally:
        station.set_joints(start)
    if len(seen) < c.min_good:
        raise CalibrationFailed(f"only {len(seen)} of {tried} poses showed the plug well (need {c.min_good}): " + "; ".join(discarded[:5]))
    flanges_arr, seen_arr = np.array(flanges), np.array(seen)
    tsai = fit_eye_to_hand_from_poses(seen_arr, flanges_arr, pins, camera="left", method="tsai")
    # the joint refinement: both unknowns fitted to every pose's pins at once
    joint = fit_eye_to_hand([apply_pose(a, pins) for a in seen_arr], flanges_arr, pins, tsai.flange_from_board, camera="left", threshold=0.005)
    return MarkerlessCalibration(
        joint.base_from_camera, joint.flange_from_board, (tsai.base_from_camera, tsai.flange_from_board), joint.rmse * 1000, len(seen), tried, discarded
    )


def workspace_error_mm(estimate: np.ndarray, truth: np.ndarray, centre: np.ndarray, half: float = 0.25, steps: int = 5) -> float:
    """The mean distance (mm) between where `estimate` and `truth` (base_from_camera)
    put points of a cube of side 2·`half` around `centre` (base frame): a camera pose's
    error where the robot works, not at the camera."""
    g = np.linspace(-half, half, steps)
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + centre
    in_camera = apply_pose(np.linalg.inv(truth), cube)
    return float(np.linalg.norm(apply_pose(estimate, in_camera) - cube, axis=1).mean() * 1000)
