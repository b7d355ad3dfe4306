"""The torch dataset over a parts folder ("earcore-images", kind "parts";
`earcore.sim.part_images`).

    from earcore.parts.dataset import PartImages
    train = PartImages("data/parts", split="train")
    item = train[0]   # image (4, H, W): RGB in [0, 1] + relative depth; target (C, H, W); parts ...

Items: `image` (RGB with a camera's colour noise when `noise`, and the depth channel of
`depth_channel`), `target` (one 0/1 mask per class), and per part slot (M = the
manifest's max_instances): `points` (u, v) px, `classes`, `valid`, `depth` (the pickup
point's z, m), plus `intrinsics` (fx, fy, cx, cy) and `counts` (parts per class).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from earcore.learning.dataset import colour_noise
from earcore.learning.errors import DatasetError
from earcore.learning.shards import manifest_layers, read_manifest, read_shard

__all__ = ["DEPTH_SCALE", "PartImages", "depth_channel"]

#: The depth channel's unit: metres above the image's dominant surface per unit.
DEPTH_SCALE = 0.05


def depth_channel(depth_mm: np.ndarray) -> np.ndarray:
    """(H, W) float32: height above the image's dominant surface (the median valid
    depth: the platform) in units of DEPTH_SCALE, clipped to ±3; 0 where the camera had
    no return. Independent of the camera's height, so one network serves any."""
    d = np.asarray(depth_mm, dtype=np.float32) / 1000.0
    valid = d > 0
    if not valid.any():
        return np.zeros(d.shape, dtype=np.float32)
    surface = np.median(d[valid])
    return np.where(valid, np.clip((surface - d) / DEPTH_SCALE, -3.0, 3.0), 0.0).astype(np.float32)


class PartImages(torch.utils.data.Dataset):
    """Images of a parts folder; `split` "train", "test" or None (both)."""

    def __init__(self, folder: str | Path, split: str | None = "train", noise: bool = True, seed: int = 0) -> None:
        if split not in ("train", "test", None):
            raise ValueError(f"split must be 'train', 'test' or None, got {split!r}")
        self.folder = Path(folder)
        self.manifest: dict[str, Any] = read_manifest(self.folder)
        if self.manifest["kind"] != "parts":
            raise DatasetError(f"{self.folder}: a {self.manifest['kind']!r} dataset, not parts images")
        self.classes: list[str] = list(self.manifest["classes"])
        self.max_instances: int = self.manifest["max_instances"]
        self.image_size: tuple[int, int] = (self.manifest["width"], self.manifest["height"])
        self.split, self.noise, self.seed, self.epoch = split, noise, int(seed), 0
        self._arrays: dict[str, np.ndarray] | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _load(self) -> dict[str, np.ndarray]:
        if self._arrays is not None:
            return self._arrays
        w, h = self.image_size
        m = self.max_instances
        layers = manifest_layers(self.manifest)
        missing = [k for k in ("rgb", "depth", "instances") if k not in layers]
        if missing:
            raise DatasetError(f"{self.folder / 'manifest.json'}: layers lack {', '.join(missing)}")
        fields = ("class", "u", "v", "z")
        required = ["split", "fx", "fy", "cx", "cy", "count", *(f"obj{i}_{f}" for i in range(m) for f in fields)]
        parts: dict[str, list[np.ndarray]] = {k: [] for k in ("rgb", "depth", "instances", "intrinsics", "classes", "points", "z", "count")}
        for entry in self.manifest["shards"]:
            shard = read_shard(self.folder, entry["name"], w, h, required, samples=int(entry["samples"]), layers=layers)
            path = self.folder / f"{entry['name']}.csv"
            split = np.array(shard.text["split"])
            keep = np.ones(len(split), dtype=bool) if self.split is None else split == self.split
            count = shard.numbers("count", path)
            classes = np.stack([shard.numbers(f"obj{i}_class", path) for i in range(m)], axis=1)
            points = np.stack([np.stack([shard.numbers(f"obj{i}_u", path), shard.numbers(f"obj{i}_v", path)], axis=1) for i in range(m)], axis=1)
            z = np.stack([shard.numbers(f"obj{i}_z", path) for i in range(m)], axis=1)
            slots = np.arange(m)[None, :] < count[:, None]
            bad = (slots & ~(np.isfinite(classes) & np.isfinite(points).all(-1) & np.isfinite(z))) | (slots & ((classes < 0) | (classes >= len(self.classes))))
            if bad.any() or not np.all((count >= 0) & (count <= m)):
                row = int(np.flatnonzero(bad.any(1) | (count < 0) | (count > m))[0])
                raise DatasetError(f"{path}: row {row + 2}: a part's class, point or depth is missing or out of range, or the count is not in [0, {m}]")
            parts["rgb"].append(shard.images["rgb"][keep])
            parts["depth"].append(shard.images["depth"][keep])
            parts["instances"].append(shard.images["instances"][keep])
            parts["intrinsics"].append(np.stack([shard.numbers(c, path) for c in ("fx", "fy", "cx", "cy")], axis=1)[keep])
            parts["classes"].append(np.where(slots, classes, -1)[keep].astype(np.int64))
            parts["points"].append(np.where(slots[..., None], points, 0.0)[keep])
            parts["z"].append(np.where(slots, z, 0.0)[keep])
            parts["count"].append(count[keep].astype(np.int64))
        self._arrays = {k: np.concatenate(v) for k, v in parts.items()}
        return self._arrays

    def __len__(self) -> int:
        return len(self._load()["rgb"])

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        a = self._load()
        if not 0 <= index < len(a["rgb"]):
            raise IndexError(index)
        rgb = a["rgb"][index].astype(np.float32) / 255.0
        if self.noise:
            rgb = colour_noise(rgb, np.random.default_rng([self.seed, self.epoch, index]))
        image = np.concatenate([rgb.transpose(2, 0, 1), depth_channel(a["depth"][index])[None]])
        classes = a["classes"][index]
        valid = classes >= 0
        c = len(self.classes)
        instances = a["instances"][index].astype(np.int64)
        pixel_class = np.where(instances > 0, np.concatenate([[-1], classes])[np.clip(instances, 0, len(classes))], -1)
        target = (pixel_class[None] == np.arange(c)[:, None, None]).astype(np.float32)
        return {
            "image": torch.from_numpy(np.ascontiguousarray(image)),
            "target": torch.from_numpy(target),
            "points": torch.from_numpy(a["points"][index].astype(np.float32)),
            "classes": torch.from_numpy(np.where(valid, classes, 0)),
            "valid": torch.from_numpy(valid),
            "depth": torch.from_numpy(a["z"][index].astype(np.float32)),
            "intrinsics": torch.from_numpy(a["intrinsics"][index].astype(np.float32)),
            "counts": torch.from_numpy(np.bincount(classes[valid], minlength=c).astype(np.int64)),
        }
