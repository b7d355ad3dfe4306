"""Calibration's estimation (Paper I, steps 6-7 and the fits along the way): pure
functions of the observations, the board and the camera's datasheet. No robot, no
simulator: what the frames say about each camera's lenses, colour-depth offset, depth
error and pose, and the board's mount on the flange."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from earcore.calibration.board import Detection, _cv2, corner_points
from earcore.calibration.config import CalibrationConfig
from earcore.calibration.errors import DegeneratePoses, TooFewFrames
from earcore.calibration.eye_to_hand import (
    EyeToHand,
    apply_pose,
    fit_eye_to_hand,
    fit_eye_to_hand_from_poses,
    refine_by_reprojection,
)
from earcore.calibration.intrinsics import calibrate_lens, calibrate_lens_on_robot, pose_uncertainty, reprojection_errors
from earcore.calibration.store import CameraCalibration
from earcore.depth_error import DepthBias, radius2_grid, radius2_of
from earcore.transforms import mean_pose, rotation_angle, rotation_from_vector

__all__ = ["Estimator", "Observation", "SensorSpec"]


@dataclass
class Observation:
    """One accepted frame of one camera."""

    camera: str
    q: np.ndarray
    base_from_flange: np.ndarray
    ir: Detection
    colour: Detection | None
    #: Depth frames (F, h, w) of the image region around the board, from pixel `origin`.
    depth: np.ndarray
    origin: tuple[int, int]
    tilted: bool
    #: Where in Algorithm 1: "start", "tilt" (a tilt limit) or "stage" (the trajectory).
    phase: str = "stage"
    #: For stage frames: the distance factor and the stage's radius (fraction of the
    #: usable half-field of view).
    distance_factor: float | None = None
    radius: float | None = None
    #: For stage frames: the position's index on its stage's ring.
    slot: int | None = None


@dataclass(frozen=True)
class SensorSpec:
    """What estimation knows of a camera before calibrating it: whether it measures
    depth, its (depth/IR, or only) camera's datasheet pinhole and that of a separate
    colour camera (None when there is none)."""

    has_depth: bool
    intrinsics: np.ndarray
    colour_intrinsics: np.ndarray | None = None

    @classmethod
    def of(cls, sensor) -> SensorSpec:
        """From a sensor model (`earcore.sim.sensors.SensorModel` or a driver's own)."""
        colour = getattr(sensor, "colour", None)
        return cls(bool(sensor.has_depth), np.asarray(sensor.intrinsics, dtype=np.float64), None if colour is None else colour.intrinsics)


def _region(detections: list[Detection]) -> tuple[int, int, int, int]:
    """(u_min, v_min, u_max, v_max) of the corners of all detections."""
    px = np.concatenate([d.corners for d in detections])
    lo, hi = np.floor(px.min(axis=0)).astype(int), np.ceil(px.max(axis=0)).astype(int)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


class Estimator:
    """The fits of Paper I from observed frames, for one board (`board_points`: its
    inner corners in the board frame) and one configuration. `solver_time` adds up the
    seconds spent in the solvers."""

    def __init__(self, board_points: np.ndarray, config: CalibrationConfig, progress: Callable[[str], None] | None = None) -> None:
        self.board_points = np.asarray(board_points, dtype=np.float64)
        self.config = config
        self.progress = progress or (lambda message: None)
        self.solver_time = 0.0

    def corners_3d(self, obs: Observation, K: np.ndarray, distortion, depth_error: DepthBias | None = None) -> np.ndarray:
        """The frame's corners in the camera frame from its depth, through the lens (K,
        distortion), with `depth_error` taken out of the depth first."""
        depth = obs.depth
        if depth_error is not None and not depth_error.is_zero:
            depth = depth_error.correct(depth, radius2_grid(K, depth.shape[2], depth.shape[1], obs.origin))
        return corner_points(obs.ir, depth, K, distortion, method=self.config.corner_method, origin=obs.origin)

    def depth_error(self, obs: list[Observation], K, distortion, base_from_camera: np.ndarray, mount: np.ndarray) -> DepthBias:
        """Step 7's depth distortion: every corner's measured depth against its depth
        where forward kinematics, the mount and the pose from the pixels put it."""
        measured, predicted, rho2 = [], [], []
        camera_from_base = np.linalg.inv(base_from_camera)
        for o in obs:
            measured.append(self.corners_3d(o, K, distortion)[:, 2])
            predicted.append(apply_pose(camera_from_base @ o.base_from_flange @ mount, self.board_points)[:, 2])
            rho2.append(radius2_of(o.ir.corners, K))
        return DepthBias.fit(
            np.concatenate(measured), np.concatenate(predicted), np.concatenate(rho2), terms=self.config.depth_error_terms
        )

    def fit(
        self, obs: list[Observation], sensor: SensorSpec, K, distortion, mount: np.ndarray, estimate_mount: bool,
        threshold: float | None = None, depth_error: DepthBias | None = None,
    ) -> EyeToHand:
        """Eye-to-hand (base_from_camera and, if `estimate_mount`, flange_from_board) from
        the frames: Paper I's 3D-3D fit of the depth corners through the lens, or for a
        colour-only camera from the board's pose in each image."""
        name = obs[0].camera
        if not sensor.has_depth:
            return self.fit_from_pixels(obs, K, distortion, mount, estimate_mount)
        t = time.perf_counter()
        try:
            return fit_eye_to_hand(
                [self.corners_3d(o, K, distortion, depth_error) for o in obs],
                np.array([o.base_from_flange for o in obs]),
                self.board_points,
                mount,
                estimate_mount=estimate_mount,
                threshold=self.config.ransac_threshold if threshold is None else threshold,
                camera=name,
            )
        finally:
            self.solver_time += time.perf_counter() - t

    def board_poses(self, obs: list[Observation], K, distortion) -> np.ndarray:
        """camera_from_board (F, 4, 4) of every frame from its corners' pixels (PnP for a
        planar target, through the lens K, distortion)."""
        cv2 = _cv2()
        out = np.empty((len(obs), 4, 4))
        for i, o in enumerate(obs):
            ok, rvec, tvec = cv2.solvePnP(
                self.board_points, o.ir.corners.astype(np.float64), np.asarray(K, float), np.asarray(distortion, float),
                flags=cv2.SOLVEPNP_IPPE,
            )
            if not ok:
                raise DegeneratePoses(o.camera, "PnP found no board pose for a frame")
            out[i] = np.eye(4)
            out[i, :3, :3] = rotation_from_vector(np.ravel(rvec))
            out[i, :3, 3] = np.ravel(tvec)
        return out

    def fit_from_pixels(self, obs: list[Observation], K, distortion, mount: np.ndarray, estimate_mount: bool) -> EyeToHand:
        """Eye-to-hand of a colour-only camera from the board's pose in each frame: AX = ZB
        (OpenCV's robot-world/hand-eye) when the mount is wanted, else the camera pose
        that carries the designed mount's board onto each frame's, averaged."""
        t = time.perf_counter()
        try:
            poses = self.board_poses(obs, K, distortion)
            flanges = np.array([o.base_from_flange for o in obs])
            if estimate_mount:
                return fit_eye_to_hand_from_poses(poses, flanges, self.board_points, camera=obs[0].camera)
            x = mean_pose(np.array([f @ mount @ np.linalg.inv(a) for f, a in zip(flanges, poses)]))
            seen = np.concatenate([apply_pose(x @ a, self.board_points) for a in poses])
            robot = np.concatenate([apply_pose(f @ mount, self.board_points) for f in flanges])
            rmse = float(np.sqrt(np.mean(np.sum((seen - robot) ** 2, axis=1))))
            return EyeToHand(x, np.asarray(mount, dtype=np.float64), rmse, len(obs), len(seen))
        finally:
            self.solver_time += time.perf_counter() - t

    def finish(
        self, name: str, obs: list[Observation], sensor: SensorSpec, *, start_q: np.ndarray | None = None, screened: bool = False
    ) -> CameraCalibration:
        """Steps 6-7 from the frames (the camera's accepted ones, or `observations`):
        Zhang's method for each lens (Paper I), refined with the robot as the rig
        (`calibrate_lens_on_robot`), the colour-depth offset, and eye-to-hand again
        through the corrected lens."""
        if len(obs) < 3:
            raise TooFewFrames(name, len(obs), 3)
        if not sensor.has_depth:
            return self._finish_colour_only(name, obs, sensor, start_q, screened)
        t = time.perf_counter()
        zhang = calibrate_lens(
            [o.ir for o in obs], self.board_points, sensor.intrinsics, camera=name, lens_model=self.config.lens_model
        )
        self.solver_time += time.perf_counter() - t
        # The mount from the depth corners through Zhang's lens, then the rig; the lens
        # and the mount are refined in turn (each pass: the rig's lens and pose from the
        # pixels, the mount from the depth corners through that lens).
        fit = self.fit(
            obs, sensor, zhang.K, zhang.distortion, self.config.mount, estimate_mount=True,
            threshold=self.config.ransac_threshold_uncorrected,
        )
        depth_lens = zhang
        depth_error = DepthBias()
        for _ in range(self.config.refinement_passes):
            t = time.perf_counter()
            rig_mount = fit.flange_from_board
            depth_lens, base_from_ir = self._lens_on_robot(name, obs, [o.ir for o in obs], rig_mount, depth_lens.K, depth_lens.distortion)
            self.solver_time += time.perf_counter() - t
            if not screened:
                # A frame the lens and pose cannot explain (a corner found in the wrong
                # place) is dropped once, and everything is solved again without it.
                good = self._explained(obs, [o.ir for o in obs], fit.flange_from_board, depth_lens, base_from_ir)
                if not good.all():
                    self.progress(f"{name}: {int((~good).sum())} frame(s) the lens and pose cannot explain dropped")
                    return self.finish(name, [o for o, g in zip(obs, good) if g], sensor, start_q=start_q, screened=True)
                screened = True
            previous = fit.flange_from_board
            if self.config.depth_error_terms:
                t = time.perf_counter()
                depth_error = self.depth_error(obs, depth_lens.K, depth_lens.distortion, base_from_ir, previous)
                self.solver_time += time.perf_counter() - t
            fit = self.fit(obs, sensor, depth_lens.K, depth_lens.distortion, previous, estimate_mount=True, depth_error=depth_error)
            if np.abs(fit.flange_from_board - previous).max() < 1e-5:
                break
        self.refuse_poor_lens(name, depth_lens)
        pixel_pose = self._pixel_pose_uncertainty(obs, depth_lens, base_from_ir, rig_mount)
        t = time.perf_counter()
        colour_lens, offset = None, None
        both = [o for o in obs if o.colour is not None]
        colour_detections = [o.colour for o in both if o.colour is not None]
        if sensor.colour_intrinsics is not None and len(both) >= 8:
            colour_zhang = calibrate_lens(
                colour_detections, self.board_points, sensor.colour_intrinsics, camera=name,
                lens_model=self.config.lens_model,
            )
            colour_lens, base_from_colour = self._lens_on_robot(
                name, both, colour_detections, fit.flange_from_board, colour_zhang.K, colour_zhang.distortion
            )
            good = self._explained(both, colour_detections, fit.flange_from_board, colour_lens, base_from_colour)
            if not good.all() and good.sum() >= 8:
                both = [o for o, g in zip(both, good) if g]
                colour_detections = [d for d, g in zip(colour_detections, good) if g]
                colour_lens, base_from_colour = self._lens_on_robot(
                    name, both, colour_detections, fit.flange_from_board, colour_lens.K, colour_lens.distortion
                )
            offset = np.linalg.inv(base_from_ir) @ base_from_colour
        self.solver_time += time.perf_counter() - t
        pose = base_from_ir if self.config.pose_from == "pixels" else fit.base_from_camera
        agreement_m = float(np.linalg.norm(base_from_ir[:3, 3] - fit.base_from_camera[:3, 3]))
        agreement_deg = float(np.degrees(rotation_angle(base_from_ir, fit.base_from_camera)))
        return CameraCalibration(
            name=name,
            base_from_camera=pose,
            depth_K=depth_lens.K,
            depth_distortion=depth_lens.distortion,
            depth_size=obs[0].ir.image_size,
            colour_K=None if colour_lens is None else colour_lens.K,
            colour_distortion=None if colour_lens is None else colour_lens.distortion,
            colour_size=None if colour_lens is None else colour_detections[0].image_size,
            depth_from_colour=offset,
            depth_error=None if depth_error.is_zero else depth_error.as_list(),
            flange_from_board=fit.flange_from_board,
            eye_to_hand_rmse=fit.rmse,
            depth_reprojection_rms=depth_lens.rms,
            colour_reprojection_rms=float("nan") if colour_lens is None else colour_lens.rms,
            zhang_reprojection_rms=zhang.rms,
            pose_agreement_m=agreement_m,
            pose_agreement_deg=agreement_deg,
            pixel_pose_sigma_m=pixel_pose.translation_m,
            pixel_pose_sigma_deg=pixel_pose.rotation_deg,
            pose_sigma_m=float(np.hypot(pixel_pose.translation_m, agreement_m)),
            pose_sigma_deg=float(np.hypot(pixel_pose.rotation_deg, agreement_deg)),
            frames=len(obs),
            corners=fit.corners,
            depth_region=_region([o.ir for o in obs]),
            colour_region=_region(colour_detections) if colour_lens is not None else None,
            start_q=None if start_q is None else [float(v) for v in start_q],
        )

    def _finish_colour_only(
        self, name: str, obs: list[Observation], sensor: SensorSpec, start_q: np.ndarray | None, screened: bool
    ) -> CameraCalibration:
        """Steps 6-7 for a camera without depth: Zhang's method, AX = ZB for the pose and
        the mount, then the lens and pose refined with the robot as the rig, the mount
        from every frame's board pose in turn (the pose of the camera's own image)."""
        s = self.config
        t = time.perf_counter()
        zhang = calibrate_lens([o.ir for o in obs], self.board_points, sensor.intrinsics, camera=name, lens_model=s.lens_model)
        self.solver_time += time.perf_counter() - t
        fit = self.fit_from_pixels(obs, zhang.K, zhang.distortion, s.mount, True)
        lens, mount = zhang, fit.flange_from_board
        flanges = np.array([o.base_from_flange for o in obs])
        base_from_camera = fit.base_from_camera
        for _ in range(s.refinement_passes):
            t = time.perf_counter()
            lens, base_from_camera = self._lens_on_robot(name, obs, [o.ir for o in obs], mount, lens.K, lens.distortion)
            if not screened:
                good = self._explained(obs, [o.ir for o in obs], mount, lens, base_from_camera)
                if not good.all():
                    self.progress(f"{name}: {int((~good).sum())} frame(s) the lens and pose cannot explain dropped")
                    return self._finish_colour_only(name, [o for o, g in zip(obs, good) if g], sensor, start_q, True)
                screened = True
            # The pose and the mount that best explain every corner's pixel through the
            # refined lens (no depth to fix the mount with).
            previous = mount
            base_from_camera, mount, _ = refine_by_reprojection(
                [o.ir.corners for o in obs], flanges, self.board_points, lens.K, lens.distortion, base_from_camera, mount
            )
            self.solver_time += time.perf_counter() - t
            if np.abs(mount - previous).max() < 1e-5:
                break
        self.refuse_poor_lens(name, lens)
        pixel_pose = self._pixel_pose_uncertainty(obs, lens, base_from_camera, mount)
        return CameraCalibration(
            name=name,
            base_from_camera=base_from_camera,
            pixel_pose_sigma_m=pixel_pose.translation_m,
            pixel_pose_sigma_deg=pixel_pose.rotation_deg,
            pose_sigma_m=pixel_pose.translation_m,
            pose_sigma_deg=pixel_pose.rotation_deg,
            colour_K=lens.K,
            colour_distortion=lens.distortion,
            colour_size=obs[0].ir.image_size,
            flange_from_board=mount,
            eye_to_hand_rmse=fit.rmse,
            colour_reprojection_rms=lens.rms,
            zhang_reprojection_rms=zhang.rms,
            frames=len(obs),
            corners=len(obs) * len(self.board_points),
            colour_region=_region([o.ir for o in obs]),
            start_q=None if start_q is None else [float(v) for v in start_q],
        )

    def refuse_poor_lens(self, name: str, lens) -> None:
        """A calibration whose lens and pose leave the corners too far off is refused."""
        limit = self.config.max_reprojection_px
        if lens.rms > limit:
            raise DegeneratePoses(
                name, f"the lens and pose explain the corners only to {lens.rms:.1f} px rms (> {limit} px): too few or too similar frames"
            )

    def _pixel_pose_uncertainty(self, obs: list[Observation], lens, base_from_camera: np.ndarray, mount: np.ndarray):
        """The rig fit's pose covariance (`pose_uncertainty`): the mount estimated along,
        residuals counted per frame."""
        return pose_uncertainty(
            self._corners_in_base(obs, mount), np.concatenate([o.ir.corners for o in obs]), lens.K, lens.distortion,
            base_from_camera, lens_model=self.config.lens_model,
            mount=(np.array([o.base_from_flange for o in obs]), self.board_points, mount), corners_per_frame=len(self.board_points),
        )

    def _corners_in_base(self, obs: list[Observation], mount: np.ndarray) -> np.ndarray:
        """Every frame's board corners placed in the base frame by forward kinematics."""
        return np.concatenate([apply_pose(o.base_from_flange @ mount, self.board_points) for o in obs])

    def _explained(self, obs, detections, mount, lens, base_from_camera) -> np.ndarray:
        """Per frame: do the lens and pose reproject its corners within max(1 px, 4× the
        median frame's rms)?"""
        errors = reprojection_errors(
            self._corners_in_base(obs, mount),
            np.concatenate([d.corners for d in detections]), lens.K, lens.distortion, base_from_camera,
        ).reshape(len(obs), -1)
        per_frame = np.sqrt((errors**2).mean(axis=1))
        return per_frame <= max(1.0, 4 * float(np.median(per_frame)))

    def _lens_on_robot(self, name, obs, detections, mount, K_guess, dist_guess):
        pixels = np.concatenate([d.corners for d in detections])
        return calibrate_lens_on_robot(
            self._corners_in_base(obs, mount), pixels, detections[0].image_size, K_guess, dist_guess, camera=name, lens_model=self.config.lens_model
        )
