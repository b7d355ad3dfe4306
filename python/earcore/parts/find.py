"""Finding a wanted part in one camera image with a trained network: the belief map
(H, W) in [0, 1] that each pixel shows it, for `earcore.parts.locate` to turn into
pickup points in the robot's base frame.

    belief = detector_belief(detector, rgb, depth_mm, cls)                 # a trained type
    belief = oneshot_belief(segmenter, needle, rgb, depth_mm)              # a type from one image
    needle = Needle.from_image(rgb, depth_mm, mask)                        # the needle's crop

Images are the camera's: rgb (H, W, 3) uint8 and depth (H, W) uint16 mm, 0 = no return,
as the parts datasets store them; the networks' input is built as in training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from earcore.parts.dataset import depth_channel
from earcore.parts.detector import PartDetector
from earcore.parts.oneshot import OneShotSegmenter
from earcore.parts.oneshot_data import MIN_PIXELS, needle_crop, needle_size, part_mask

__all__ = ["Needle", "detector_belief", "detector_beliefs", "network_input", "oneshot_belief"]


def network_input(rgb: np.ndarray, depth_mm: np.ndarray | None, channels: int) -> torch.Tensor:
    """(1, channels, H, W): colour in [0, 1] and, for 4 channels, the depth channel."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    planes = [rgb.astype(np.float32).transpose(2, 0, 1) / 255.0]
    if channels == 4:
        if depth_mm is None or np.shape(depth_mm) != rgb.shape[:2]:
            raise ValueError(f"this network takes RGB-D: give a depth image of {rgb.shape[:2]}, got {None if depth_mm is None else np.shape(depth_mm)}")
        planes.append(depth_channel(np.asarray(depth_mm))[None])
    return torch.from_numpy(np.ascontiguousarray(np.concatenate(planes)))[None]


def _sized(image: torch.Tensor, width: int, height: int) -> None:
    if image.shape[2:] != (height, width):
        raise ValueError(f"the network was trained on {width}x{height} images, got {image.shape[3]}x{image.shape[2]}")


def detector_beliefs(detector: PartDetector, rgb: np.ndarray, depth_mm: np.ndarray | None) -> np.ndarray:
    """The parts detector's activations (classes, H, W)."""
    o = detector.options
    image = network_input(rgb, depth_mm, o.in_channels)
    _sized(image, o.width, o.height)
    with torch.no_grad():
        return detector.eval()(image)["activations"][0].numpy().astype(np.float64)


def detector_belief(detector: PartDetector, rgb: np.ndarray, depth_mm: np.ndarray | None, cls: int) -> np.ndarray:
    """The parts detector's activation (H, W) for class `cls`."""
    classes = detector.options.classes
    if not 0 <= cls < classes:
        raise ValueError(f"class {cls} is not one of the detector's {classes}")
    return detector_beliefs(detector, rgb, depth_mm)[cls]


@dataclass(frozen=True)
class Needle:
    """One image of the wanted part, cut to the one-shot segmenter's needle crop."""

    image: torch.Tensor  # (4, s, s): colour and depth channel
    mask: torch.Tensor  # (1, s, s)

    #: whether `image` has a real depth channel (an RGB-D segmenter needs one)
    has_depth: bool = True

    @classmethod
    def from_image(
        cls, rgb: np.ndarray, depth_mm: np.ndarray | None = None, mask: np.ndarray | None = None, *, camera_width: int | None = None, divisor: int = 8
    ) -> Needle:
        """The part's crop at the scale of a camera `camera_width` pixels wide (default:
        the needle image's own width); its pixels are `mask` or, without one, what
        stands above the platform in the depth image (`part_mask`)."""
        has_depth = depth_mm is not None
        if depth_mm is None:
            depth_mm = np.zeros(np.shape(rgb)[:2], dtype=np.uint16)
            if mask is None:
                raise ValueError("a needle needs its part's pixels: give a mask or a depth image")
        image = network_input(rgb, depth_mm, 4)[0]
        pixels = part_mask(image) if mask is None else np.asarray(mask, dtype=bool)
        if pixels.shape != image.shape[1:]:
            raise ValueError(f"the needle's mask must be {tuple(image.shape[1:])}, got {pixels.shape}")
        if int(pixels.sum()) < MIN_PIXELS:
            where = "in its mask" if mask is not None else "above the platform in its depth"
            raise ValueError(f"the needle image shows {int(pixels.sum())} part pixel(s) {where}; a needle needs at least {MIN_PIXELS}")
        size = needle_size(camera_width or image.shape[2], divisor)
        crop, crop_mask = needle_crop(image, pixels, size)
        return cls(crop, crop_mask, has_depth)


def oneshot_belief(segmenter: OneShotSegmenter, needle: Needle, rgb: np.ndarray, depth_mm: np.ndarray | None) -> np.ndarray:
    """The one-shot segmenter's belief (H, W) that a pixel shows the needle's type."""
    channels = segmenter.options.in_channels
    if channels == 4 and not needle.has_depth:
        raise ValueError("this segmenter takes RGB-D: the needle needs its depth image too")
    haystack = network_input(rgb, depth_mm, channels)
    divisor = segmenter.divisor
    if haystack.shape[2] % divisor or haystack.shape[3] % divisor:
        raise ValueError(f"the image's sides must be multiples of {divisor}, got {haystack.shape[3]}x{haystack.shape[2]}")
    with torch.no_grad():
        belief = segmenter.eval().segment(needle.image[None, :channels], haystack, needle.mask[None])
    return belief[0, 0].numpy().astype(np.float64)
