"""Two looks at an image for a network trained on zoomed boxes (`NetworkOptions.zoom`):
the whole image shrunk to the network's input finds the robot; a box around what it
found (its keypoints and base, with a margin), cut from the image at up to `zoom` times
the first look's resolution, gives the answer. The mask and nothing else comes from the
first look. numpy here; torch only inside `two_looks` (the training path's evaluation);
`earcore.pose.estimate` does the same with onnxruntime."""

from __future__ import annotations

from typing import Any

import numpy as np

from earcore.learning.crops import Box, box_around

__all__ = ["LOOK_MARGIN", "first_look_points", "second_look_box", "two_looks"]

#: The margin around the first look's keypoints and base, a fraction of their extent on
#: each side (the training boxes draw theirs from 0.15-0.45).
LOOK_MARGIN = 0.3


def second_look_box(pixels: np.ndarray, image_size: tuple[int, int], input_size: tuple[int, int], zoom: int) -> Box:
    """The box (image pixels) of the second look around the first look's keypoint and base
    pixels (N, 2) in the image: at least 1/`zoom` of the image's width and never narrower
    than the input (the training's boxes were never sharper than either)."""
    width = image_size[0]
    return box_around(pixels, image_size, input_size, margin=LOOK_MARGIN, min_width=max(width / zoom, float(input_size[0])))


def first_look_points(pixels: np.ndarray, type_logits: np.ndarray | None, counts: list[int] | None) -> np.ndarray:
    """Of the first look's pixels (K + 1, 2; the base last), the predicted robot's own
    keypoints (`counts`: keypoints per type; a robot with fewer than K has untrained
    padding outputs) and the base."""
    if counts is None or type_logits is None:
        return pixels
    count = counts[int(np.argmax(type_logits))]
    return np.vstack([pixels[:count], pixels[-1:]])


def two_looks(model: Any, images: Any, intrinsics: Any, counts: list[int] | None = None) -> dict[str, Any]:
    """A zoom network's outputs for images (N, 3, H, W) at `zoom` times its input size
    with their intrinsics (N, 3, 3): keypoints, base, type from the second look (pixels in
    the images' coordinates), the mask logits from the first, at the images' size.
    `counts`: keypoints per robot type, so the box frames the predicted robot's own."""
    import torch
    import torch.nn.functional as F

    from earcore.learning.crops import crop, crop_intrinsics, uncrop_pixels

    zoom = model.options.zoom
    w, h = model.options.input_size
    n, _, height, width = images.shape
    if (width, height) != (w * zoom, h * zoom):
        raise ValueError(f"this network reads boxes of {w * zoom}×{h * zoom} images (zoom {zoom}), got {width}×{height}")
    whole = Box.whole(width, height)
    k_source = intrinsics.detach().cpu().numpy().astype(np.float64)
    k_first = np.stack([crop_intrinsics(k, whole, (w, h)) for k in k_source])
    first = model(F.avg_pool2d(images, zoom), None, torch.as_tensor(k_first, dtype=images.dtype, device=images.device))
    found = uncrop_pixels(first["pixels"].detach().cpu().numpy(), whole, (w, h))
    types = first["type_logits"].detach().cpu().numpy() if "type_logits" in first else None
    boxes = [second_look_box(first_look_points(found[i], None if types is None else types[i], counts), (width, height), (w, h), zoom) for i in range(n)]
    source = images.detach().cpu().numpy().transpose(0, 2, 3, 1)
    crops = np.stack([crop(source[i], boxes[i], (w, h)) for i in range(n)]).transpose(0, 3, 1, 2)
    k_second = np.stack([crop_intrinsics(k_source[i], boxes[i], (w, h)) for i in range(n)])
    second = model(
        torch.as_tensor(np.ascontiguousarray(crops), dtype=images.dtype, device=images.device),
        None,
        torch.as_tensor(k_second, dtype=images.dtype, device=images.device),
    )
    pixels = np.stack([uncrop_pixels(second["pixels"][i].detach().cpu().numpy(), boxes[i], (w, h)) for i in range(n)])
    out = dict(second)
    out["pixels"] = torch.as_tensor(pixels, dtype=images.dtype, device=images.device)
    out["mask_logits"] = F.interpolate(first["mask_logits"], size=(height, width), mode="bilinear", align_corners=False)
    out["boxes"] = boxes
    return out
