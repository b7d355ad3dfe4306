"""Needles and haystacks for one-shot segmentation (AAMAS 2019): a needle is one image
of a single part, a haystack an image of several; the network is to find the needle's
part type in the haystack.

    from earcore.parts.oneshot_data import HeldOutTrials, OneShotPairs, split_classes
    seen, unseen = split_classes(classes, ("Axis", "Motor"))
    train = OneShotPairs(PartImages("data/haystacks"), PartImages("data/needles"), seen)
    trials = HeldOutTrials(PartImages("data/haystacks", "test"), PartImages("data/needles", None), unseen)

A needle is cut from its image as a square around the part (`needle_crop`) at the
camera's own scale: the convolutions' filters respond to structure of a given size in
pixels, so a needle magnified to fill its crop would excite other filters than the same
part in a haystack. Only a part too big for the crop is shrunk into it. Training pairs use only the seen types: their
haystacks hold no part of a held-out type and their needles are seen types. Trials are
the paper's protocol: haystacks holding both held-out types (and known parts as
distractors), needles of the held-out types only.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from earcore.learning.dataset import colour_noise
from earcore.learning.errors import DatasetError
from earcore.parts.dataset import DEPTH_SCALE, PartImages, depth_channel

__all__ = ["NEEDLE_SIZE", "HeldOutTrials", "OneShotPairs", "needle_crop", "needle_size", "needles_by_class", "part_mask", "split_classes", "visible_pixels"]

#: Needle crops are this many pixels square for images 128 pixels wide (`needle_size`).
NEEDLE_SIZE = 32
#: A part counts as visible (as a needle, or as a haystack's target) with this many pixels.
MIN_PIXELS = 12
#: A pixel this high above the platform (m) is part of an object (`part_mask`).
PART_HEIGHT = 0.004


def split_classes(classes: Sequence[str], held_out: Sequence[str]) -> tuple[list[int], list[int]]:
    """(seen, held-out) class indices of the held-out type names."""
    names = list(classes)
    unknown = [h for h in held_out if h not in names]
    if unknown:
        raise ValueError(f"unknown part type(s) {', '.join(unknown)}; the dataset has {', '.join(names)}")
    out = sorted(names.index(h) for h in held_out)
    if len(set(out)) != len(out) or len(out) >= len(names):
        raise ValueError(f"hold out distinct types, fewer than all {len(names)}; got {list(held_out)}")
    return [i for i in range(len(names)) if i not in out], out


def needle_size(width: int, divisor: int = 8) -> int:
    """The side of the needle crops for images `width` pixels wide: NEEDLE_SIZE at 128,
    in proportion otherwise, a multiple of `divisor` (the segmenter's) and at least 16."""
    step = max(int(divisor), 1)
    return max(-(-16 // step) * step, step * round(NEEDLE_SIZE * width / 128 / step))


def part_mask(image: np.ndarray | torch.Tensor) -> np.ndarray:
    """(H, W) bool: the pixels of an earcore image (4, H, W) standing PART_HEIGHT above
    the platform (its depth channel), for a needle image without labels."""
    depth = np.asarray(image[3])
    return depth > PART_HEIGHT / DEPTH_SCALE


def needle_crop(image: torch.Tensor, mask: torch.Tensor | np.ndarray, size: int = NEEDLE_SIZE, margin: float = 0.25) -> tuple[torch.Tensor, torch.Tensor]:
    """(image (C, size, size), mask (1, size, size)): the square around `mask`'s
    pixels, `size` pixels at the image's scale, or bigger to hold the part with `margin`
    of its side on each side and then shrunk to `size`; moved inside the image."""
    m = torch.as_tensor(np.asarray(mask, dtype=bool))
    rows, cols = torch.nonzero(m.any(1)).flatten(), torch.nonzero(m.any(0)).flatten()
    if not len(rows):
        raise DatasetError("the needle image shows no part (its mask is empty)")
    _, h, w = image.shape
    top, bottom, left, right = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    side = min(max(int(round(max(bottom - top, right - left) * (1 + 2 * margin))), size), h, w)
    cy, cx = (top + bottom) // 2, (left + right) // 2
    y0, x0 = min(max(cy - side // 2, 0), h - side), min(max(cx - side // 2, 0), w - side)
    patch = image[:, y0 : y0 + side, x0 : x0 + side][None].float()
    patch_mask = m[y0 : y0 + side, x0 : x0 + side][None, None].float()
    if side == size:
        return patch[0].clone(), patch_mask[0].clone()  # not views: a cached crop must not hold its whole image
    crop = F.interpolate(patch, size=(size, size), mode="bilinear", align_corners=False, antialias=side > size)[0]
    crop_mask = F.interpolate(patch_mask, size=(size, size), mode="nearest")[0]
    return crop, crop_mask


def _check_same_classes(haystacks: PartImages, needles: PartImages) -> None:
    if haystacks.classes != needles.classes:
        raise DatasetError(f"the haystacks ({haystacks.folder}) and needles ({needles.folder}) name different part types")


def visible_pixels(images: PartImages) -> np.ndarray:
    """(N, C) pixels of each part type in each image."""
    a = images._load()
    n, m, c = len(a["instances"]), images.max_instances, len(images.classes)
    per_slot = np.stack([np.bincount(inst.ravel(), minlength=m + 1)[1 : m + 1] for inst in a["instances"]]) if n else np.zeros((0, m), np.int64)
    out = np.zeros((n, c), dtype=np.int64)
    rows = np.repeat(np.arange(n), m)
    cls = a["classes"].ravel()
    keep = cls >= 0
    np.add.at(out, (rows[keep], cls[keep]), per_slot.ravel()[keep])
    return out


def needles_by_class(needles: PartImages, classes: Sequence[int], every: bool = True) -> dict[int, np.ndarray]:
    """Single-part images per type; a type without one is an error with `every`, else left out."""
    a = needles._load()
    single = (a["count"] == 1) & (visible_pixels(needles).sum(1) >= MIN_PIXELS)
    out = {c: np.flatnonzero(single & (a["classes"][:, 0] == c)) for c in classes}
    empty = [needles.classes[c] for c, idx in out.items() if not len(idx)]
    if not every:
        out = {c: idx for c, idx in out.items() if len(idx)}
    if (empty and every) or not out:
        raise DatasetError(f"{needles.folder}: no single-part image of {', '.join(empty)} (generate needles with --objects 1-1)")
    return out


class NeedleCrops:
    """The needle crops of a needles dataset (noise-free, cut once, kept); `get` adds
    the camera's colour noise to the crop when given a generator."""

    def __init__(self, needles: PartImages, channels: int, divisor: int = 8) -> None:
        self.needles, self.channels = needles, channels
        self.size = needle_size(needles._load()["rgb"].shape[2], divisor)
        self._crops: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def get(self, index: int, rng: np.random.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        if index not in self._crops:
            a = self.needles._load()
            rgb = torch.from_numpy(a["rgb"][index].astype(np.float32).transpose(2, 0, 1) / 255.0)
            image = torch.cat([rgb, torch.from_numpy(depth_channel(a["depth"][index]))[None]])
            self._crops[index] = needle_crop(image[: self.channels], a["instances"][index] == 1, self.size)
        crop, mask = self._crops[index]
        if rng is not None:
            noisy = colour_noise(np.ascontiguousarray(crop[:3].numpy().transpose(1, 2, 0)), rng)
            crop = torch.cat([torch.from_numpy(noisy.transpose(2, 0, 1)), crop[3:]])
        return crop, mask


class OneShotPairs(torch.utils.data.Dataset):
    """Training pairs over the haystacks that hold only `seen` types: item k is haystack
    k with a target type drawn among its visible parts that have needles and two needles of that type (the second
    for the vector spread), redrawn each epoch (`set_epoch`). Random flips; colour
    noise on the needles with `noise` (on the haystacks: their dataset's `noise`)."""

    def __init__(
        self, haystacks: PartImages, needles: PartImages, seen: Sequence[int], *, depth: bool = True, seed: int = 0, noise: bool = True, divisor: int = 8
    ) -> None:
        _check_same_classes(haystacks, needles)
        self.haystacks, self.needles, self.seen, self.noise = haystacks, needles, sorted(int(c) for c in seen), noise
        self.channels, self.seed, self.epoch = 4 if depth else 3, int(seed), 0
        a = haystacks._load()
        self.by_class = needles_by_class(needles, self.seen, every=False)
        self.targets = visible_pixels(haystacks) >= MIN_PIXELS
        self.targets[:, [c for c in range(len(haystacks.classes)) if c not in self.by_class]] = False
        allowed = np.isin(a["classes"], [*self.seen, -1]).all(1) & self.targets.any(1)
        self.images = np.flatnonzero(allowed)
        if not len(self.images):
            raise DatasetError(f"{haystacks.folder}: no haystack holds only the seen part types")
        self.crops = NeedleCrops(needles, self.channels, divisor)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        self.haystacks.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        image_index = int(self.images[index])
        hay = self.haystacks[image_index]
        cls = int(rng.choice(np.flatnonzero(self.targets[image_index])))
        first, second = rng.choice(self.by_class[cls], size=2, replace=len(self.by_class[cls]) < 2)
        needle, needle_mask = self.crops.get(int(first), rng if self.noise else None)
        other, other_mask = self.crops.get(int(second), rng if self.noise else None)
        image, target = hay["image"][: self.channels], hay["target"]
        flips = [d for d, flip in ((-1, rng.random() < 0.5), (-2, rng.random() < 0.5)) if flip]
        if flips:
            image, target = image.flip(flips), target.flip(flips)
        nflips = [d for d, flip in ((-1, rng.random() < 0.5), (-2, rng.random() < 0.5)) if flip]
        if nflips:
            needle, needle_mask = needle.flip(nflips), needle_mask.flip(nflips)
        return {
            "needle": needle.contiguous(),
            "needle_mask": needle_mask.contiguous(),
            "second": other,
            "second_mask": other_mask,
            "haystack": image.contiguous(),
            "target": target[cls : cls + 1].contiguous(),
            "all": target.amax(0, keepdim=True).contiguous(),
            "cls": torch.tensor(cls),
        }


class HeldOutTrials(torch.utils.data.Dataset):
    """The evaluation trials: every haystack holding all `held_out` types, once per
    held-out type, with a needle of that type drawn (by `seed`) from `needles`. Items
    carry every type's mask (`masks`, for the classification metric) and the target's
    pickup points (`points`, `valid`), depth and intrinsics for the pickup rate."""

    def __init__(self, haystacks: PartImages, needles: PartImages, held_out: Sequence[int], *, depth: bool = True, seed: int = 0, divisor: int = 8) -> None:
        _check_same_classes(haystacks, needles)
        self.haystacks, self.needles, self.held_out = haystacks, needles, sorted(int(c) for c in held_out)
        self.channels = 4 if depth else 3
        visible = visible_pixels(haystacks) >= MIN_PIXELS
        holds_all = visible[:, self.held_out].all(1)
        images = np.flatnonzero(holds_all)
        if not len(images):
            raise DatasetError(f"{haystacks.folder}: no haystack holds all of {', '.join(haystacks.classes[c] for c in self.held_out)}")
        by_class = needles_by_class(needles, self.held_out)
        self.crops = NeedleCrops(needles, self.channels, divisor)
        rng = np.random.default_rng(seed)
        self.trials = [(int(i), c, int(rng.choice(by_class[c]))) for i in images for c in self.held_out]

    def __len__(self) -> int:
        return len(self.trials)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        image_index, cls, needle_index = self.trials[index]
        hay = self.haystacks[image_index]
        needle, needle_mask = self.crops.get(needle_index)
        return {
            "needle": needle,
            "needle_mask": needle_mask,
            "haystack": hay["image"][: self.channels],
            "target": hay["target"][cls : cls + 1],
            "masks": hay["target"],
            "cls": torch.tensor(cls),
            "points": hay["points"],
            "valid": hay["valid"] & (hay["classes"] == cls),
            "depth": hay["depth"],
            "intrinsics": hay["intrinsics"],
        }
