"""A small synthetic dataset with the Dataset contract's dicts of tensors, whose labels
are geometrically consistent: a "robot" is a chain of 3D keypoints in front of a pinhole
camera, drawn as bright segments; its mask is what was drawn, its pixels the
keypoints' projections. Two robot types differ in colour and keypoint count."""

from __future__ import annotations

import numpy as np
import torch


class FakeDataset(torch.utils.data.Dataset):
    def __init__(self, count: int = 32, width: int = 32, height: int = 32, keypoints: int = 4, seed: int = 0, noise: bool = False):
        self.width, self.height, self.K = width, height, keypoints
        self.robots = ["red", "green"]
        self.num_keypoints = keypoints
        self.image_size = (width, height)
        self.manifest = {
            "robots": self.robots,
            "keypoints": {"red": [f"r{i}" for i in range(keypoints - 1)], "green": [f"g{i}" for i in range(keypoints)]},
            "keypoint_frames": {"red": [[f"r{i}", [0.0, 0.0, 0.0]] for i in range(keypoints - 1)], "green": [[f"g{i}", [0.0, 0.0, 0.1]] for i in range(keypoints)]},
        }
        self.noise, self.seed, self.epoch = noise, seed, 0
        f = 0.9 * width
        self.intrinsics = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
        rng = np.random.default_rng(seed)
        self.samples = [self._make(rng, i) for i in range(count)]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def project(self, p: np.ndarray) -> np.ndarray:
        k = self.intrinsics
        return np.stack([k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2], k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]], 1)

    def _make(self, rng: np.random.Generator, index: int) -> dict[str, np.ndarray]:
        robot = index % 2
        count = self.K - 1 if robot == 0 else self.K
        base = np.array([rng.uniform(-0.3, 0.3), rng.uniform(0.0, 0.3), rng.uniform(1.6, 2.4)])
        points = [base]
        for _ in range(count):
            d = rng.normal(size=3)
            d[1] = -abs(d[1]) - 0.5  # upwards in the image
            points.append(points[-1] + 0.25 * d / np.linalg.norm(d))
        chain = np.array(points)
        uv = self.project(chain)
        image = np.full((self.height, self.width, 3), 0.15)
        links = np.zeros((self.height, self.width), np.int64)
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        colour = np.array([0.95, 0.2, 0.2]) if robot == 0 else np.array([0.2, 0.95, 0.3])
        for s in range(count):
            a, b = uv[s], uv[s + 1]
            ab = b - a
            t = np.clip(((xs - a[0]) * ab[0] + (ys - a[1]) * ab[1]) / max(ab @ ab, 1e-9), 0, 1)
            d = np.hypot(xs - (a[0] + t * ab[0]), ys - (a[1] + t * ab[1]))
            on = d <= 1.2
            image[on] = colour
            links[on] = s + 1
        kp = np.zeros((self.K, 3))
        kp[:count] = chain[1:]
        px = np.zeros((self.K, 2))
        px[:count] = uv[1:]
        valid = np.zeros(self.K, bool)
        valid[:count] = True
        return {
            "image": image.transpose(2, 0, 1).astype(np.float32),
            "mask": (links > 0)[None].astype(np.float32),
            "links": links,
            "keypoints": kp.astype(np.float32),
            "keypoint_valid": valid,
            "pixels": px.astype(np.float32),
            "base": base.astype(np.float32),
            "base_rotation": np.eye(3, dtype=np.float32),
            "robot": np.int64(robot),
            "intrinsics": self.intrinsics.astype(np.float32),
            "joints": np.zeros(6, np.float32),
        }

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        s = self.samples[i]
        item = {k: torch.as_tensor(v) for k, v in s.items()}
        if self.noise:
            g = torch.Generator().manual_seed(self.seed * 7919 + self.epoch * 104729 + i)
            item["image"] = (item["image"] + 0.02 * torch.randn(item["image"].shape, generator=g)).clamp(0, 1)
        item["index"] = torch.tensor(i, dtype=torch.int64)
        return item
