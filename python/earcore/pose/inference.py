"""Robot pose from one colour image with a trained network, through onnxruntime and
numpy only (no torch):

    >>> from earcore.pose import estimate
    >>> result = estimate(frame.colour, frame.K)       # doctest: +SKIP
    >>> result.robot, result.keypoints, result.base    # doctest: +SKIP

The network is an .onnx file with a sidecar .json beside it (`earcore export pose`
writes both); by default the one shipped in `earcore/pose/weights/pose.onnx`.

**Other image sizes and cameras.** The image is resized to the network's input size
(box-averaged when shrinking, bilinear when growing), which scales the intrinsics by
the same factors (pixel centres at integers). The network answers as if the image came
from the camera it was trained with, K_t; a point it puts at pixel (u, v) and depth z
is re-placed for the actual (resized) camera K': the pixel is kept, the depth is
multiplied by f'/f_t (apparent size scales with focal length over depth; f is the
geometric mean of fx and fy), and the point is back-projected through K'. Pixels are
reported in the given image's coordinates, the mask at its resolution.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning.crops import Box, crop, crop_intrinsics, uncrop_pixels
from earcore.pose.errors import PoseWeightsError
from earcore.pose.zoom import first_look_points, second_look_box

__all__ = ["DEFAULT_WEIGHTS", "PoseEstimate", "estimate", "load_model", "resize"]

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "pose.onnx"
SIDECAR_FORMAT = "earcore-pose-onnx"


@dataclass
class PoseEstimate:
    """One image's estimate. `keypoints` (K, 3) and `base` (3,) in the camera frame
    (metres, OpenCV axes), `pixels` (K, 2) and `base_pixel` (2,) in the image's pixels,
    `mask` (H, W) bool at the image's resolution, `robot` the most probable type (None
    if the network has no type head and knows several robots), `probabilities` per type;
    `keypoint_names` and `keypoint_frames` ([link name, [x, y, z]]: where each keypoint
    sits on the robot, from the sidecar) say what the keypoints are, so that

        refine(robots.load(est.robot), est.keypoints, frames=est.keypoint_frames,
               pixels=est.pixels, intrinsics=K, base=est.base, base_pixel=est.base_pixel)

    fits the robot's kinematics to them (`earcore.pose.refine`)."""

    mask: np.ndarray
    keypoints: np.ndarray
    pixels: np.ndarray
    base: np.ndarray
    base_pixel: np.ndarray
    robot: str | None
    probabilities: dict[str, float] = field(default_factory=dict)
    keypoint_names: list[str] = field(default_factory=list)
    keypoint_frames: list[list[Any]] = field(default_factory=list)


@dataclass
class _Model:
    session: Any
    sidecar: dict[str, Any]
    input_size: tuple[int, int]
    intrinsics: np.ndarray


def _read_sidecar(onnx_path: Path) -> dict[str, Any]:
    path = onnx_path.with_suffix(".json")
    if not path.is_file():
        raise PoseWeightsError(f"{onnx_path} has no sidecar {path.name} (written by `earcore export pose`)")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PoseWeightsError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != SIDECAR_FORMAT:
        raise PoseWeightsError(f"{path} is not an {SIDECAR_FORMAT} sidecar")
    for key in ("input_size", "intrinsics", "robots", "num_keypoints"):
        if key not in data:
            raise PoseWeightsError(f"{path} lacks {key!r}")
    return data


@functools.lru_cache(maxsize=4)
def _load(path: str, mtime: float, threads: int | None) -> _Model:
    import onnxruntime as ort

    onnx_path = Path(path)
    sidecar = _read_sidecar(onnx_path)
    options = ort.SessionOptions()
    # Threads that spin after a run steal the cores from the numpy work around it
    # (resizing the mask took 4 ms instead of 0.5 ms right after a spinning run).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads is not None:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    try:
        session = ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for unreadable models
        raise PoseWeightsError(f"{onnx_path} could not be loaded by onnxruntime: {exc}") from None
    w, h = (int(v) for v in sidecar["input_size"])
    return _Model(session, sidecar, (w, h), np.asarray(sidecar["intrinsics"], dtype=np.float64))


def load_model(weights: str | Path | None = None, threads: int | None = None) -> _Model:
    """The network at `weights` (.onnx with its sidecar), or the shipped one; cached."""
    path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
    if not path.is_file():
        if weights is None:
            raise PoseWeightsError(
                f"no pose network is shipped yet ({path} is missing): train and export one with "
                "`earcore train pose --data DATA --out RUN` and `earcore export pose --checkpoint RUN --out "
                f"{path}`, or pass weights=PATH"
            )
        raise PoseWeightsError(f"no network at {path}")
    return _load(str(path.resolve()), path.stat().st_mtime, threads)


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) or (H, W, C) float image → (height, width[, C]), in the image's precision."""
    h, w = image.shape[:2]
    if h % height == 0 and w % width == 0:  # whole-number shrink (a Kinect's 512×424 to 128×106): block means
        fy, fx = h // height, w // width
        rest = image.shape[2:]
        # Strided slices added one by one: 3-4× faster than numpy's sum over axes (1, 3).
        columns = image.reshape(h, width, fx, *rest)
        acc = columns[:, :, 0].astype(np.float32)
        for i in range(1, fx):
            acc += columns[:, :, i]
        rows = acc.reshape(height, fy, width, *rest)
        out = rows[:, 0].copy()
        for i in range(1, fy):
            out += rows[:, i]
        return out * np.float32(1.0 / (fy * fx))
    return crop(image, Box.whole(w, h), (width, height)).astype(image.dtype, copy=False)


def _image(image: Any) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise TypeError(f"image must be a numpy array (H, W, 3), got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) RGB, got shape {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"image is too small: {image.shape[1]}×{image.shape[0]}")
    if image.dtype == np.uint8:
        return image.astype(np.float32) * np.float32(1 / 255.0)
    if image.dtype not in (np.float32, np.float64):
        raise TypeError(f"image must be uint8 (0-255) or float32/float64 (0-1), got {image.dtype}")
    if not np.isfinite(image).all():
        raise ValueError("image has non-finite values (NaN or inf)")
    if image.min() < -1e-6 or image.max() > 1 + 1e-6:
        raise ValueError(f"a float image must be in [0, 1], got values in [{image.min():.3g}, {image.max():.3g}]")
    return image.astype(np.float32)


def _camera(camera: Any, model: _Model, width: int, height: int) -> np.ndarray:
    if camera is None:
        w, h = model.input_size
        return crop_intrinsics(model.intrinsics, Box.whole(w, h), (width, height))
    k = getattr(camera, "K", camera)
    k = np.asarray(k, dtype=np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"camera must be intrinsics (3, 3) with positive focal lengths (or have them as .K), got {k.tolist()}")
    return k


def _run(model: _Model, image: np.ndarray) -> dict[str, np.ndarray]:
    """The network's outputs by name for one (h, w, 3) float image at its input size."""
    inputs = np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)
    names = [o.name for o in model.session.get_outputs()]
    return dict(zip(names, model.session.run(names, {"image": inputs})))


def estimate(image: np.ndarray, camera: Any = None, weights: str | Path | None = None, *, threads: int | None = None) -> PoseEstimate:
    """The robot's mask, keypoints, base and type in `image` ((H, W, 3) RGB, uint8 or
    float in [0, 1]) seen by `camera` (intrinsics (3, 3), or anything with `.K`, e.g. a
    `Frame`; None: the training camera scaled to the image)."""
    rgb = _image(image)
    model = load_model(weights, threads)
    height, width = rgb.shape[:2]
    k_image = _camera(camera, model, width, height)
    size = model.input_size
    box = Box.whole(width, height)
    first = _run(model, resize(rgb, *size) if size != (width, height) else rgb)
    out = first
    zoom = int(model.sidecar.get("options", {}).get("zoom", 1))
    if zoom > 1 and "pixels" in first:
        # The second look: a box around what the first found, at up to `zoom` times its resolution.
        found = uncrop_pixels(first["pixels"][0].astype(np.float64), box, size)
        counts = [len(model.sidecar.get("keypoints", {}).get(r, [])) or int(model.sidecar["num_keypoints"]) for r in model.sidecar["robots"]]
        types = first["type_logits"][0] if "type_logits" in first and len(counts) == first["type_logits"].shape[1] else None
        box = second_look_box(first_look_points(found, types, counts), (width, height), size, zoom)
        out = _run(model, crop(rgb, box, size))
    k_net = crop_intrinsics(k_image, box, size)

    k_t = model.intrinsics
    points = np.concatenate([out["keypoints"][0], out["base"][0][None]]).astype(np.float64)
    z = np.maximum(points[:, 2], 1e-6)
    if "pixels" in out:
        uv = out["pixels"][0].astype(np.float64)
    else:
        uv = np.stack([k_t[0, 0] * points[:, 0] / z + k_t[0, 2], k_t[1, 1] * points[:, 1] / z + k_t[1, 2]], 1)
    z_true = points[:, 2] * np.sqrt(k_net[0, 0] * k_net[1, 1] / (k_t[0, 0] * k_t[1, 1]))
    xyz = np.stack([(uv[:, 0] - k_net[0, 2]) * z_true / k_net[0, 0], (uv[:, 1] - k_net[1, 2]) * z_true / k_net[1, 1], z_true], 1)
    pixels = uncrop_pixels(uv, box, size)

    logits = first["mask_logits"][0, 0].astype(np.float32)
    mask = (resize(logits, width, height) if size != (width, height) else logits) > 0

    robots = list(model.sidecar["robots"])
    probabilities: dict[str, float] = {}
    robot: str | None = robots[0] if len(robots) == 1 else None
    if "type_logits" in out and robots:
        t = out["type_logits"][0].astype(np.float64)
        p = np.exp(t - t.max())
        p /= p.sum()
        probabilities = {name: float(v) for name, v in zip(robots, p)}
        robot = robots[int(np.argmax(p))]
    names = list(model.sidecar.get("keypoints", {}).get(robot, [])) if robot is not None else []
    count = len(names) if names else int(model.sidecar["num_keypoints"])
    return PoseEstimate(
        mask=mask,
        keypoints=xyz[:count],
        pixels=pixels[:count],
        base=xyz[-1],
        base_pixel=pixels[-1],
        robot=robot,
        probabilities=probabilities,
        keypoint_names=names,
        keypoint_frames=list(model.sidecar.get("keypoint_frames", {}).get(robot, [])) if robot is not None else [],
    )
