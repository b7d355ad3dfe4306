"""Intrinsics (Paper I, step 7): Zhang's method for each lens (OpenCV's calibrateCamera,
Brown-Conrady k1, k2, p1, p2, k3), and the lens refit with the robot as the rig (which
also gives the camera's pose from pixels alone; the colour camera's offset from the
depth camera is the difference of the two rig poses)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from earcore.calibration.board import Detection, _cv2
from earcore.calibration.errors import DegeneratePoses, TooFewFrames
from earcore.transforms import pose_from_vector

__all__ = [
    "LensFit",
    "PoseUncertainty",
    "calibrate_lens",
    "calibrate_lens_on_robot",
    "lens_displacement",
    "pose_uncertainty",
    "reprojection_errors",
]


@dataclass
class LensFit:
    K: np.ndarray
    distortion: np.ndarray  # (5,): k1, k2, p1, p2, k3
    #: RMS reprojection error (pixels) over every corner of every frame.
    rms: float
    frames: int


#: The distortion coefficients (indices into k1, k2, p1, p2, k3) each lens model fits.
_FITTED_DISTORTION = {"full": [0, 1, 2, 3, 4], "radial": [0, 1, 4], "radial2": [0, 1]}


def _lens_flags(model: str) -> int:
    """OpenCV's calibration flags for a lens model."""
    cv2 = _cv2()
    flags = {
        "full": 0,  # k1, k2, p1, p2, k3
        "radial": cv2.CALIB_ZERO_TANGENT_DIST,  # k1, k2, k3
        "radial2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,  # k1, k2
    }
    if model not in flags:
        raise ValueError(f"lens_model must be one of {sorted(flags)}, got {model!r}")
    return flags[model]


def _object_points(board_points: np.ndarray, n: int) -> list[np.ndarray]:
    return [board_points.astype(np.float32)] * n


def calibrate_lens(
    detections: list[Detection],
    board_points: np.ndarray,
    K_guess: np.ndarray,
    *,
    camera: str = "camera",
    min_frames: int = 8,
    lens_model: str = "radial",
) -> LensFit:
    """K and distortion from board detections in one camera's images. `lens_model`:
    "radial" (k1, k2, k3; the default: these sensors' tangential terms are negligible
    and fitting them lets the principal point wander), "radial2" (k1, k2) or "full"
    (k1, k2, p1, p2, k3)."""
    cv2 = _cv2()
    if len(detections) < min_frames:
        raise TooFewFrames(camera, len(detections), min_frames, "for the lens (Zhang's method)")
    size = detections[0].image_size
    image_points = [d.corners.astype(np.float32).reshape(-1, 1, 2) for d in detections]
    # Field-of-view coverage: the corners must spread over the image, else the
    # distortion is extrapolated.
    allpx = np.concatenate([d.corners for d in detections])
    cover = (np.ptp(allpx[:, 0]) / size[0], np.ptp(allpx[:, 1]) / size[1])
    if min(cover) < 0.3:
        raise DegeneratePoses(camera, f"the board covered only {cover[0]:.0%} × {cover[1]:.0%} of the image")
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | _lens_flags(lens_model)
    with _solver_refusal(camera, "Zhang's method"):
        rms, K, dist, _, _ = cv2.calibrateCamera(
            _object_points(board_points, len(detections)), image_points, size, K_guess.astype(np.float64).copy(), None, flags=flags
        )
    return LensFit(K, np.asarray(dist, dtype=np.float64).reshape(-1)[:5], float(rms), len(detections))


def lens_displacement(K_a, dist_a, K_b, dist_b, size: tuple[int, int], step: int = 8, region=None, pixels=None) -> float:
    """Largest distance (pixels) between where two lens models put the same ray: how far
    apart two calibrations of one camera really are (the coefficients trade off against
    each other). Over a grid of the image, of `region` (u_min, v_min, u_max, v_max), or
    at `pixels` (N, 2), e.g. the corners the calibration saw: beyond them a fitted lens
    is extrapolation."""
    cv2 = _cv2()
    w, h = size
    if pixels is not None:
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    else:
        u0, v0, u1, v1 = region if region is not None else (0, 0, w - 1, h - 1)
        u, v = np.meshgrid(np.arange(u0, u1 + 1, step), np.arange(v0, v1 + 1, step))
        px = np.c_[u.ravel(), v.ravel()].astype(np.float64)
    rays = cv2.undistortPoints(px.reshape(-1, 1, 2), np.asarray(K_a, float), np.asarray(dist_a, float)).reshape(-1, 2)
    back, _ = cv2.projectPoints(np.c_[rays, np.ones(len(rays))], np.zeros(3), np.zeros(3), np.asarray(K_b, float), np.asarray(dist_b, float))
    return float(np.linalg.norm(back.reshape(-1, 2) - px, axis=1).max())


@contextmanager
def _solver_refusal(camera: str, what: str) -> Iterator[None]:
    """OpenCV refuses a lens that has wandered off (a principal point outside the
    image, too few points for the model) with its own error: name the camera instead."""
    cv2 = _cv2()
    try:
        yield
    except cv2.error as exc:
        reason = " ".join(str(getattr(exc, "err", None) or exc).split())
        raise DegeneratePoses(camera, f"{what} failed: {reason}") from exc


def calibrate_lens_on_robot(
    points_base: np.ndarray,
    pixels: np.ndarray,
    image_size: tuple[int, int],
    K_guess: np.ndarray,
    dist_guess=None,
    *,
    camera: str = "camera",
    lens_model: str = "radial",
) -> tuple[LensFit, np.ndarray]:
    """Lens and `base_from_camera` at once, with the robot as the calibration rig.

    Every frame's corners are placed in the base frame by forward kinematics and the
    board's mount, so all frames together are one non-planar 3D target seen from one
    camera pose. Zhang's method has to find each frame's board pose from the image,
    which trades focal length against distance when the board is small in the image;
    here the robot fixes the distances and the focal length follows. Starts from
    `K_guess` and `dist_guess` (e.g. Zhang's result; zero distortion when None);
    `lens_model` as in `calibrate_lens`."""
    cv2 = _cv2()
    points_base = np.asarray(points_base, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    if len(points_base) < 12:
        raise TooFewFrames(camera, len(points_base) // 24, 1, "too few corners for the lens")
    # OpenCV wants a non-planar rig's points near its own origin and the pose guessed
    # well: start from the pinhole pose (PnP with the guessed K).
    dist0 = np.zeros(5) if dist_guess is None else np.asarray(dist_guess, dtype=np.float64).reshape(-1)[:5].copy()
    ok, rvec, tvec = cv2.solvePnP(points_base, pixels, K_guess, dist0, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise DegeneratePoses(camera, "no camera pose explains the corners (PnP failed)")
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS | _lens_flags(lens_model)
    with _solver_refusal(camera, "the lens fit on the robot"):
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [points_base.astype(np.float32)], [pixels.astype(np.float32).reshape(-1, 1, 2)], image_size,
            K_guess.astype(np.float64).copy(), dist0, rvecs=(rvec,), tvecs=(tvec,), flags=flags,
        )
    r, _ = cv2.Rodrigues(np.asarray(rvecs[0]))
    camera_from_base = np.eye(4)
    camera_from_base[:3, :3] = r
    camera_from_base[:3, 3] = np.asarray(tvecs[0]).reshape(3)
    lens = LensFit(K, np.asarray(dist, dtype=np.float64).reshape(-1)[:5], float(rms), len(points_base) // 24)
    return lens, np.linalg.inv(camera_from_base)


def reprojection_errors(points_base, pixels, K, distortion, base_from_camera) -> np.ndarray:
    """Distance (pixels) between each corner's pixel (N, 2) and its base-frame point (N, 3)
    projected through the camera."""
    cv2 = _cv2()
    camera_from_base = np.linalg.inv(base_from_camera)
    rvec, _ = cv2.Rodrigues(camera_from_base[:3, :3])
    projected, _ = cv2.projectPoints(
        np.asarray(points_base, dtype=np.float64), rvec, camera_from_base[:3, 3], np.asarray(K, float), np.asarray(distortion, float)
    )
    return np.linalg.norm(projected.reshape(-1, 2) - np.asarray(pixels, dtype=np.float64), axis=1)


@dataclass
class PoseUncertainty:
    """How well the corners pin down a camera's pose: the covariance of the camera's
    centre in the base frame and of a small turn of the camera about the base's axes."""

    #: 6×6 covariance of (centre x, y, z in m; rotation x, y, z in rad).
    covariance: np.ndarray

    @property
    def translation_m(self) -> float:
        """One standard deviation of the centre's position (3D, m)."""
        return float(np.sqrt(np.trace(self.covariance[:3, :3])))

    @property
    def rotation_deg(self) -> float:
        """One standard deviation of the orientation (the turn's angle, degrees)."""
        return float(np.degrees(np.sqrt(np.trace(self.covariance[3:, 3:]))))


def pose_uncertainty(
    points_base: np.ndarray,
    pixels: np.ndarray,
    K: np.ndarray,
    distortion: np.ndarray,
    base_from_camera: np.ndarray,
    *,
    lens_model: str = "radial",
    mount: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    corners_per_frame: int | None = None,
) -> PoseUncertainty:
    """The covariance of the pose `calibrate_lens_on_robot` found, from its residuals:
    σ²(JᵀJ)⁻¹ over the pose and every lens parameter the fit estimated (so that the
    lens's own uncertainty widens the pose's), σ² the residuals' variance per pixel
    coordinate; carried to the camera's centre and orientation in the base frame.

    With `mount` = (base_from_flange per frame (F, 4, 4), the board's corners (C, 3),
    flange_from_board), `points_base` being those corners carried by each frame's flange
    and the mount, the mount's six parameters are estimated along (a pose error that the
    mount can absorb widens the pose's uncertainty). Without it, the corners' base-frame
    positions count as exact. Errors of the robot's kinematics are in neither.

    With `corners_per_frame` (the points come frame by frame, that many each), the
    covariance is the cluster-robust sandwich (JᵀJ)⁻¹(Σ_f J_fᵀr̃_f r̃_fᵀJ_f)(JᵀJ)⁻¹ over
    frames f, r̃_f the frame's residuals with its leverage taken out (the jackknife's
    "CR3" form): a frame's corners err together (blur, the board's pose in the image),
    which the per-pixel σ² would count as independent."""
    cv2 = _cv2()
    points_base = np.asarray(points_base, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    dist = np.asarray(distortion, dtype=np.float64).reshape(-1)[:5]
    K = np.asarray(K, float)
    camera_from_base = np.linalg.inv(base_from_camera)
    rvec, _ = cv2.Rodrigues(camera_from_base[:3, :3])
    tvec = camera_from_base[:3, 3]
    projected, jacobian = cv2.projectPoints(points_base, rvec, tvec, K, dist)
    # Columns: rvec (3), tvec (3), fx fy, cx cy, then the distortion coefficients.
    columns = list(range(10)) + [10 + i for i in _FITTED_DISTORTION[lens_model]]
    J = jacobian[:, columns]
    if mount is not None:
        J = np.hstack([J, _mount_jacobian(mount, rvec, tvec, K, dist, len(points_base))])
    residual = projected.reshape(-1) - pixels.reshape(-1)
    dof = max(len(residual) - J.shape[1], 1)
    sigma2 = float(residual @ residual) / dof
    try:
        bread = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return PoseUncertainty(np.full((6, 6), np.inf))
    cov = sigma2 * bread[:6, :6]
    if corners_per_frame is not None:
        per_frame = 2 * corners_per_frame
        if len(residual) % per_frame:
            raise ValueError(f"{len(residual) // 2} corners are not whole frames of {corners_per_frame}")
        n_frames = len(residual) // per_frame
        if n_frames < 2:
            # One frame has no spread to measure.
            return PoseUncertainty(np.full((6, 6), np.inf))
        J_f = J.reshape(n_frames, per_frame, -1)
        r_f = residual.reshape(n_frames, per_frame)
        # Each frame's residuals as if the fit had not seen that frame (the jackknife's
        # leverage correction, "CR3"): a fit pulls toward every frame, most toward the
        # few that alone fix a parameter, which would hide their error.
        leverage = np.einsum("fip,pq,fjq->fij", J_f, bread, J_f)
        try:
            r_f = np.linalg.solve(np.eye(per_frame) - leverage, r_f[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return PoseUncertainty(np.full((6, 6), np.inf))
        scores = np.einsum("fkp,fk->fp", J_f, r_f)
        meat = scores.T @ scores * (n_frames - 1) / n_frames
        cov = (bread @ meat @ bread)[:6, :6]
    if not (np.isfinite(cov).all() and (np.diag(cov) > 0).all()):
        # A nearly singular JᵀJ: some direction of the pose is not fixed at all.
        return PoseUncertainty(np.full((6, 6), np.inf))

    def centre_and_turn(v: np.ndarray) -> np.ndarray:
        r, _ = cv2.Rodrigues(v[:3])
        centre = -r.T @ v[3:]
        # The turn from the estimate to this orientation, about the base's axes (a
        # small one: the antisymmetric part is exact to third order, where an
        # arccos-based logarithm loses the difference).
        d = r.T @ camera_from_base[:3, :3]
        turn = 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
        return np.concatenate([centre, turn])

    # The map from (rvec, tvec) to (centre, turn), linearised by central differences.
    x0 = np.concatenate([rvec.reshape(3), tvec])
    G = np.zeros((6, 6))
    for k in range(6):
        h = np.zeros(6)
        h[k] = 1e-6
        G[:, k] = (centre_and_turn(x0 + h) - centre_and_turn(x0 - h)) / 2e-6
    return PoseUncertainty(G @ cov @ G.T)


def _mount_jacobian(mount, rvec, tvec, K, dist, n_points: int) -> np.ndarray:
    """d(pixels)/d(mount) by central differences, the mount moved by a small
    (translation, rotation vector) in the board's frame: (2N, 6)."""
    cv2 = _cv2()
    flanges, board, flange_from_board = (np.asarray(m, dtype=np.float64) for m in mount)
    if len(flanges) * len(board) != n_points:
        raise ValueError(f"mount: {len(flanges)} frames × {len(board)} corners, but {n_points} points")

    def pixels_with(m: np.ndarray) -> np.ndarray:
        poses = flanges @ m  # (F, 4, 4)
        points = (np.einsum("fij,cj->fci", poses[:, :3, :3], board) + poses[:, None, :3, 3]).reshape(-1, 3)
        return cv2.projectPoints(points, rvec, tvec, K, dist)[0].reshape(-1)

    h = 1e-6
    out = np.empty((2 * n_points, 6))
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        out[:, k] = (pixels_with(flange_from_board @ pose_from_vector(step)) - pixels_with(flange_from_board @ pose_from_vector(-step))) / (2 * h)
    return out
