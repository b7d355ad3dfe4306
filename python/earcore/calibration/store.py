"""The calibration file (YAML): every camera's lenses, colour-depth offset, depth error
and `base_from_camera`, with residuals and frame counts. A colour-only camera has no
depth entries; its `base_from_camera` is its colour camera's pose. Written atomically, and a camera
that failed never replaces a good entry (a partial calibration merges into the file)."""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from earcore._earcore import checked_rigid_transform
from earcore.calibration.errors import CalibrationFileError

__all__ = ["Calibration", "CameraCalibration", "CalibrationFileError"]


def _yaml():
    try:
        import yaml  # type: ignore[import-untyped]
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("calibration files need PyYAML: pip install 'earcore[calibration]'") from exc
    return yaml


_MATRICES = {"base_from_camera": (4, 4), "depth_K": (3, 3), "colour_K": (3, 3), "depth_from_colour": (4, 4), "flange_from_board": (4, 4)}
_VECTORS = {"depth_distortion": 5, "colour_distortion": 5}


@dataclass
class CameraCalibration:
    name: str
    #: The depth camera's pose (the colour camera's for a colour-only camera).
    base_from_camera: np.ndarray
    depth_K: np.ndarray | None = None
    depth_distortion: np.ndarray | None = None
    depth_size: tuple[int, int] | None = None
    colour_K: np.ndarray | None = None
    colour_distortion: np.ndarray | None = None
    colour_size: tuple[int, int] | None = None
    depth_from_colour: np.ndarray | None = None
    #: The depth error (offset m, scale, radial m) that `earcore.depth_error.DepthBias`
    #: takes out of the depth images; None: not calibrated.
    depth_error: list[float] | None = None
    flange_from_board: np.ndarray | None = None
    #: RMS 3D distance (m) between the camera's and the robot's corners.
    eye_to_hand_rmse: float = math.nan
    #: RMS reprojection errors (pixels) of the final lens fits.
    depth_reprojection_rms: float = math.nan
    colour_reprojection_rms: float = math.nan
    #: Zhang's method alone (Paper I), before the robot-rig refinement.
    zhang_reprojection_rms: float = math.nan
    #: Distance (m) and angle (degrees) between the pose from pixels and the pose from
    #: depth (a check).
    pose_agreement_m: float = math.nan
    pose_agreement_deg: float = math.nan
    #: One standard deviation of the pose from pixels (the robot-rig fit, the board's
    #: mount estimated along), from the corners' pixel noise
    #: (`earcore.calibration.intrinsics.pose_uncertainty`): the centre's position (m)
    #: and the orientation (degrees).
    pixel_pose_sigma_m: float = math.nan
    pixel_pose_sigma_deg: float = math.nan
    #: The uncertainty of `base_from_camera` (m, degrees; about one standard
    #: deviation): for a depth camera the pose from pixels' σ and the two poses'
    #: disagreement added in quadrature (the disagreement carries what the pixel noise
    #: does not: the depth error left, the lens's bias); for a colour-only camera its σ.
    pose_sigma_m: float = math.nan
    pose_sigma_deg: float = math.nan
    frames: int = 0
    corners: int = 0
    #: Where the board was seen in the depth image (u_min, v_min, u_max, v_max): the
    #: lens is measured there and extrapolated beyond.
    depth_region: tuple[int, int, int, int] | None = None
    colour_region: tuple[int, int, int, int] | None = None
    #: The joint state where this camera saw the board best (re-checks start there).
    start_q: list[float] | None = None

    @property
    def depth_bias(self):
        """The calibrated depth error as an `earcore.depth_error.DepthBias` (zero if none)."""
        from earcore.depth_error import DepthBias

        return DepthBias() if self.depth_error is None else DepthBias(*self.depth_error)

    @property
    def has_depth(self) -> bool:
        return self.depth_K is not None

    def check_image_size(self, width: int, height: int, *, colour: bool = False) -> None:
        """Raise `CalibrationFileError` when this camera's depth (or `colour`) images are
        not `width` × `height` while the calibration's lens was fitted at another size:
        its intrinsics would be read at the wrong pixels."""
        size = self.colour_size if colour else self.depth_size
        if size is not None and (int(size[0]), int(size[1])) != (int(width), int(height)):
            kind = "colour" if colour else "depth"
            raise CalibrationFileError(
                f"camera {self.name!r} was calibrated on {kind} images of {size[0]}×{size[1]} pixels, "
                f"but its images are {width}×{height}: calibrate it at this size (the same --camera-scale)"
            )

    def to_dict(self) -> dict:
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = np.round(v.astype(float), 12).tolist()
            elif isinstance(v, tuple):
                v = [int(x) for x in v]
            elif isinstance(v, list):
                v = [float(x) for x in v]
            elif isinstance(v, float) and math.isnan(v):
                v = None
            out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, data: dict, where: str) -> CameraCalibration:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise CalibrationFileError(f"{where}: unknown keys {sorted(unknown)}")
        for key in ("name", "base_from_camera"):
            if data.get(key) is None:
                raise CalibrationFileError(f"{where}: missing {key!r}")
        for lens in ("depth", "colour"):
            given = [data.get(f"{lens}_{k}") is not None for k in ("K", "distortion", "size")]
            if any(given) and not all(given):
                raise CalibrationFileError(f"{where}: the {lens} lens needs {lens}_K, {lens}_distortion and {lens}_size")
        if data.get("depth_K") is None and data.get("colour_K") is None:
            raise CalibrationFileError(f"{where}: missing 'depth_K' (or 'colour_K' for a colour-only camera)")
        kwargs = {}
        for key, value in data.items():
            if value is None:
                continue
            if key in _MATRICES or key in _VECTORS:
                shape = _MATRICES.get(key) or (_VECTORS[key],)
                try:
                    arr = np.asarray(value, dtype=np.float64)
                except (TypeError, ValueError):
                    raise CalibrationFileError(f"{where}: {key} must be numbers of shape {shape}") from None
                if arr.shape != shape or not np.isfinite(arr).all():
                    raise CalibrationFileError(f"{where}: {key} must be finite numbers of shape {shape}, got {arr.shape}")
                if shape == (4, 4):
                    try:
                        arr = checked_rigid_transform(arr, key)
                    except ValueError as exc:
                        raise CalibrationFileError(f"{where}: {exc}") from None
                if shape == (3, 3) and not (arr[0, 0] > 0 and arr[1, 1] > 0 and np.array_equal(arr[2], [0.0, 0.0, 1.0])):
                    raise CalibrationFileError(f"{where}: {key} is not a camera matrix (fx, fy > 0, last row 0 0 1)")
                value = arr
            elif key in ("depth_size", "colour_size", "depth_region", "colour_region"):
                try:
                    value = tuple(int(v) for v in value)
                except (TypeError, ValueError):
                    raise CalibrationFileError(f"{where}: {key} must be whole numbers") from None
            elif key == "depth_error":
                try:
                    arr = np.asarray(value, dtype=np.float64)
                except (TypeError, ValueError):
                    arr = np.full(1, np.nan)
                if arr.shape != (3,) or not np.isfinite(arr).all():
                    raise CalibrationFileError(f"{where}: depth_error must be 3 finite numbers (offset, scale, radial)")
                value = [float(v) for v in arr]
            kwargs[key] = value
        return cls(**kwargs)


@dataclass
class Calibration:
    cameras: dict[str, CameraCalibration] = field(default_factory=dict)

    def save(self, path: str | Path) -> None:
        """Write atomically (a crash mid-write leaves the old file)."""
        yaml = _yaml()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        text = "# earcore calibration (Paper I): lenses, colour-depth offsets, base_from_camera\n"
        text += yaml.safe_dump({"version": 1, "cameras": [c.to_dict() for c in self.cameras.values()]}, sort_keys=False)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        yaml = _yaml()
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except FileNotFoundError as exc:
            raise CalibrationFileError(f"{path}: no such calibration file") from exc
        except yaml.YAMLError as exc:
            raise CalibrationFileError(f"{path} is not valid YAML: {exc}") from exc
        if not isinstance(data, dict) or data.get("version") != 1 or not isinstance(data.get("cameras"), list):
            raise CalibrationFileError(f"{path}: not an earcore calibration file (version 1 with a list of cameras)")
        cams = {}
        for i, entry in enumerate(data["cameras"]):
            if not isinstance(entry, dict):
                raise CalibrationFileError(f"{path}: cameras[{i}] is not a mapping")
            named = f" ({entry['name']!r})" if isinstance(entry.get("name"), str) else ""
            cam = CameraCalibration.from_dict(entry, f"{path}: cameras[{i}]{named}")
            cams[cam.name] = cam
        return cls(cams)

    def merged(self, new: dict[str, CameraCalibration]) -> Calibration:
        """This calibration with the given cameras replaced or added."""
        return Calibration({**self.cameras, **new})
