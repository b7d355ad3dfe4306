"""The torch dataset over an "earcore-images" folder (`earcore.learning.shards`).

    from earcore.learning.dataset import ImageDataset
    train = ImageDataset("data/robots", split="train", noise=True, seed=0)
    sample = train[0]          # dict of tensors: image (3, H, W) in [0, 1], mask, links, keypoints, ...

The shards are read into uint8 arrays once, on first use. Images are stored clean;
with `noise=True` each item gets a camera's colour noise (per-pixel Gaussian noise,
white-balance gains, brightness and contrast jitter), the same for the same
(seed, epoch, index): `set_epoch` draws new noise for a new epoch.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from earcore.learning.crops import Box, box_around, crop, crop_intrinsics, crop_labels, crop_pixels
from earcore.learning.errors import DatasetError
from earcore.learning.shards import BASE_COLUMNS, columns, read_manifest, read_shard
from earcore.transforms import rotation_from_quaternion

__all__ = ["ImageDataset", "ImageDatasets", "ZoomedImages", "colour_noise"]

SPLITS = ("train", "test")


def colour_noise(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A float32 (H, W, 3) image in [0, 1] as a colour camera might deliver it: contrast
    ×0.85-1.15 about the image mean, brightness ±0.06, per-channel gains ±4 % (white
    balance), then Gaussian noise of σ 0.004-0.02 per pixel and channel."""
    contrast = rng.uniform(0.85, 1.15)
    brightness = rng.uniform(-0.06, 0.06)
    gains = rng.uniform(0.96, 1.04, 3).astype(np.float32)
    sigma = rng.uniform(0.004, 0.02)
    mean = float(image.mean())
    out = ((image - mean) * contrast + mean + brightness) * gains
    out += rng.standard_normal(image.shape, dtype=np.float32) * np.float32(sigma)
    return np.clip(out, 0.0, 1.0, out=out)


class ImageDataset(torch.utils.data.Dataset):
    """Samples of an "earcore-images" folder (see the module doc); `split` is "train",
    "test" or None (both), `robots` a subset of the manifest's robots (None: all)."""

    def __init__(self, folder: str | Path, split: str | None = "train", robots: list[str] | None = None, noise: bool = True, seed: int = 0) -> None:
        if split is not None and split not in SPLITS:
            raise ValueError(f"split must be 'train', 'test' or None, got {split!r}")
        self.folder = Path(folder)
        self.manifest: dict[str, Any] = read_manifest(self.folder)
        self.robots: list[str] = list(self.manifest["robots"])
        if robots is not None:
            unknown = sorted(set(robots) - set(self.robots))
            if unknown:
                raise ValueError(f"robots {unknown} are not in {self.folder / 'manifest.json'} (it has {self.robots})")
        self.split = split
        self.selected = list(robots) if robots is not None else list(self.robots)
        self.noise = noise
        self.seed = int(seed)
        self.epoch = 0
        self.num_keypoints: int = self.manifest["num_keypoints"]
        self.max_dof: int = self.manifest["max_dof"]
        self.image_size: tuple[int, int] = (self.manifest["width"], self.manifest["height"])
        self._arrays: dict[str, np.ndarray] | None = None

    def set_epoch(self, epoch: int) -> None:
        """Draw the noise of this epoch (the same epoch gives the same noise)."""
        self.epoch = int(epoch)

    # --- loading --------------------------------------------------------------

    def _load(self) -> dict[str, np.ndarray]:
        if self._arrays is not None:
            return self._arrays
        w, h = self.image_size
        k, d = self.num_keypoints, self.max_dof
        required = [c for c in columns(d, k) if c != "key"]
        parts: dict[str, list[np.ndarray]] = {}
        for entry in self.manifest["shards"]:
            name = str(entry["name"])
            shard = read_shard(self.folder, name, w, h, required, samples=int(entry["samples"]))
            path = self.folder / f"{name}.csv"
            robot_names = np.array(shard.text["robot"])
            unknown = sorted(set(robot_names.tolist()) - set(self.robots))
            if unknown:
                raise DatasetError(f"{path}: robots {unknown} are not in the manifest's {self.robots}")
            keep = np.isin(robot_names, self.selected)
            if self.split is not None:
                splits = np.array(shard.text["split"])
                bad = sorted(set(splits.tolist()) - set(SPLITS))
                if bad:
                    raise DatasetError(f"{path}: split values {bad}; expected 'train' or 'test'")
                keep &= splits == self.split
            if not keep.any():
                continue
            num = {c: shard.numbers(c, path)[keep] for c in required if c not in ("robot", "split")}
            robot = np.array([self.robots.index(r) for r in robot_names[keep]], dtype=np.int64)
            xyz = np.stack([np.stack([num[f"kp{i}_{c}"] for c in "xyz"], -1) for i in range(k)], 1) if k else np.zeros((len(robot), 0, 3))
            uv = np.stack([np.stack([num[f"kp{i}_{c}"] for c in "uv"], -1) for i in range(k)], 1) if k else np.zeros((len(robot), 0, 2))
            inside = np.stack([num[f"kp{i}_in_image"] for i in range(k)], 1) if k else np.zeros((len(robot), 0))
            counts = np.array([len(self.manifest["keypoints"][self.robots[r]]) for r in robot])
            valid = np.arange(k)[None, :] < counts[:, None]
            rows = np.flatnonzero(keep)
            base = np.stack([num[c] for c in BASE_COLUMNS], -1)
            scalars = np.stack([num[c] for c in ("fx", "fy", "cx", "cy")], -1)
            q = np.stack([num[f"q{i}"] for i in range(d)], -1) if d else np.zeros((len(robot), 0))
            own = np.arange(d)[None, :] < self._dof(robot_names, q, keep)[robot][:, None]
            for what, columns_, cells in (
                ("a keypoint", [f"kp{i}_{c}" for i in range(k) for c in ("x", "y", "z", "u", "v", "in_image")], _kp_cells(xyz, uv, inside, valid)),
                ("the base pose", list(BASE_COLUMNS), ~np.isfinite(base)),
                ("the intrinsics", ["fx", "fy", "cx", "cy"], ~np.isfinite(scalars)),
                ("a joint angle", [f"q{i}" for i in range(d)], np.isinf(q) | (own & np.isnan(q))),
            ):
                _refuse(path, rows, columns_, cells, f"lacks {what}: {{column}} is empty or not finite")
            _refuse(path, rows, ["fx", "fy"], ~(scalars[:, :2] > 0), "has a focal length {column} <= 0")
            norm = np.linalg.norm(base[:, 3:], axis=1, keepdims=True)
            _refuse(path, rows, ["base_qw"], ~(norm > 1e-6), "has a base quaternion (base_qw, base_qx, base_qy, base_qz) of length zero")
            quat = base[:, 3:] / norm
            intrinsics = np.zeros((len(robot), 3, 3))
            intrinsics[:, 0, 0], intrinsics[:, 1, 1], intrinsics[:, 0, 2], intrinsics[:, 1, 2] = scalars.T
            intrinsics[:, 2, 2] = 1.0
            for key, value in (
                ("rgb", shard.images["rgb"][keep]),
                ("links", shard.images["links"][keep]),
                ("keypoints", np.where(valid[..., None], xyz, 0.0).astype(np.float32)),
                ("pixels", np.where(valid[..., None], uv, 0.0).astype(np.float32)),
                ("keypoint_valid", valid),
                ("keypoint_in_image", valid & (np.nan_to_num(inside) > 0.5)),
                ("base", base[:, :3].astype(np.float32)),
                ("base_rotation", rotation_from_quaternion(quat).astype(np.float32)),
                ("robot", robot),
                ("intrinsics", intrinsics.astype(np.float32)),
                ("joints", np.where(own, q, 0.0).astype(np.float32)),
                ("coverage", num["coverage"].astype(np.float32)),
            ):
                parts.setdefault(key, []).append(value)
        if not parts:
            self._arrays = {"rgb": np.zeros((0, h, w, 3), np.uint8)}
        else:
            self._arrays = {key: np.concatenate(v) for key, v in parts.items()}
        return self._arrays

    def _dof(self, robot_names: np.ndarray, q: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Joints per robot (in the manifest's order): the manifest's `dof`, or, for a
        manifest without it, the most joint angles any row of this shard gives a robot."""
        table = self.manifest.get("dof")
        if isinstance(table, dict):
            return np.array([int(table[r]) for r in self.robots])
        given = ~np.isnan(q)
        last = np.where(given.any(1), given.shape[1] - np.argmax(given[:, ::-1], axis=1), 0)
        names = robot_names[keep]
        return np.array([int(last[names == r].max()) if (names == r).any() else 0 for r in self.robots])

    # --- access ---------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._load()["rgb"])

    def robot_labels(self) -> np.ndarray:
        """Each image's robot index (among `robots`)."""
        a = self._load()
        return a["robot"] if "robot" in a else np.zeros(0, np.int64)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        a = self._load()
        n = len(a["rgb"])
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} samples")
        i = index % n
        image = a["rgb"][i].astype(np.float32) / np.float32(255.0)
        if self.noise:
            image = colour_noise(image, np.random.default_rng([self.seed, self.epoch, i]))
        links = a["links"][i]
        return {
            "image": torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))),
            "mask": torch.from_numpy((links > 0).astype(np.float32)[None]),
            "links": torch.from_numpy(links.astype(np.int64)),
            "keypoints": torch.from_numpy(a["keypoints"][i]),
            "keypoint_valid": torch.from_numpy(a["keypoint_valid"][i]),
            "keypoint_in_image": torch.from_numpy(a["keypoint_in_image"][i]),
            "pixels": torch.from_numpy(a["pixels"][i]),
            "base": torch.from_numpy(a["base"][i]),
            "base_rotation": torch.from_numpy(a["base_rotation"][i]),
            "robot": torch.tensor(a["robot"][i], dtype=torch.int64),
            "intrinsics": torch.from_numpy(a["intrinsics"][i]),
            "joints": torch.from_numpy(a["joints"][i]),
            "coverage": torch.tensor(a["coverage"][i]),
            "index": torch.tensor(i, dtype=torch.int64),
        }


class ImageDatasets(torch.utils.data.Dataset):
    """Several `ImageDataset`s as one (a recordings set and a random-camera set; the old
    robots' images and a new robot's). Images must be of one size; the robots are
    united by name in order of first appearance (an image's `robot` is its robot's
    index among them), the keypoints and joint angles padded to the most any robot
    has (padding marked invalid)."""

    def __init__(self, parts: list[Any]) -> None:
        if not parts:
            raise ValueError("ImageDatasets needs at least one dataset")
        first = parts[0]
        for other in parts[1:]:
            if tuple(other.image_size) != tuple(first.image_size):
                raise DatasetError(f"{other.folder} cannot join {first.folder}: image size {tuple(other.image_size)} there, {tuple(first.image_size)} here")
        self.parts = list(parts)
        self.folder = first.folder
        self.robots: list[str] = []
        for part in parts:
            self.robots += [r for r in part.robots if r not in self.robots]
        self.num_keypoints = max(int(p.num_keypoints) for p in parts)
        self.max_dof = max(int(p.max_dof) for p in parts)
        self.image_size = first.image_size
        self.split = first.split
        self.manifest = dict(first.manifest)
        for key in ("keypoints", "keypoint_frames", "dof"):
            merged: dict[str, Any] = {}
            for part in parts:
                merged.update({k: v for k, v in part.manifest.get(key, {}).items() if k not in merged})
            if merged:
                self.manifest[key] = merged
        self.manifest["robots"] = list(self.robots)
        self._maps = [np.array([self.robots.index(r) for r in part.robots], dtype=np.int64) for part in parts]

    def set_epoch(self, epoch: int) -> None:
        for part in self.parts:
            part.set_epoch(epoch)

    def __len__(self) -> int:
        return sum(len(part) for part in self.parts)

    def robot_labels(self) -> np.ndarray:
        """Each image's robot index (among `robots`), without loading the images again."""
        return np.concatenate([m[part.robot_labels()] for m, part in zip(self._maps, self.parts)]) if len(self) else np.zeros(0, np.int64)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} samples")
        i = index % n
        for m, part in zip(self._maps, self.parts):
            if i < len(part):
                return self._united(part[i], m)
            i -= len(part)
        raise AssertionError("unreachable: the index was checked against the total length")

    def _united(self, item: dict[str, torch.Tensor], robot_map: np.ndarray) -> dict[str, torch.Tensor]:
        out = dict(item)
        out["robot"] = torch.tensor(int(robot_map[int(item["robot"])]), dtype=torch.int64)
        k, d = self.num_keypoints, self.max_dof
        for key, size in (("keypoints", k), ("pixels", k), ("keypoint_valid", k), ("keypoint_in_image", k), ("joints", d)):
            value = item.get(key)
            if value is not None and value.shape[0] < size:
                pad = torch.zeros((size - value.shape[0], *value.shape[1:]), dtype=value.dtype)
                out[key] = torch.cat([value, pad])
        return out


class SampledImages(torch.utils.data.Dataset):
    """`count` images drawn at random (without replacement, the same for the same seed)
    from a dataset, which describes them (robots, keypoints, image size): the small
    training sets of transfer learning. With `per_robot`, `count` images of each robot
    (the dataset's `robot_labels()`; a robot with fewer gives all it has)."""

    def __init__(self, dataset: Any, count: int, seed: int = 0, *, per_robot: bool = False) -> None:
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ValueError(f"count must be a whole number >= 1, got {count!r}")
        rng = np.random.default_rng(seed)
        if per_robot:
            labels = np.asarray(dataset.robot_labels())
            picks = []
            for r in np.unique(labels):
                rows = np.flatnonzero(labels == r)
                picks.append(rng.choice(rows, size=min(count, len(rows)), replace=False))
            self.indices = np.sort(np.concatenate(picks)) if picks else np.zeros(0, np.int64)
        else:
            if count > len(dataset):
                raise ValueError(f"{count} images asked for, the set has {len(dataset)}")
            self.indices = np.sort(rng.choice(len(dataset), size=count, replace=False))
        self.dataset = dataset
        for name in ("folder", "manifest", "robots", "num_keypoints", "max_dof", "image_size", "split"):
            if hasattr(dataset, name):
                setattr(self, name, getattr(dataset, name))

    def set_epoch(self, epoch: int) -> None:
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return self.dataset[int(self.indices[index])]


class ZoomedImages(torch.utils.data.Dataset):
    """The items of `dataset` (images `zoom` times the network's input size) at the input
    size: with probability `whole` the whole image shrunk, otherwise a box around the
    robot's keypoints and base (from the labels, a `margin` drawn in its range on every
    side, its size and place jittered by up to `jitter` of it, as a first look at the
    whole image would place it), never zoomed past the source's resolution. The image,
    mask, links, pixels and intrinsics follow the box; the 3D labels stay. The same for
    the same (seed, epoch, index)."""

    def __init__(self, dataset: Any, zoom: int, *, whole: float = 0.3, margin: tuple[float, float] = (0.15, 0.45), jitter: float = 0.15, seed: int = 0) -> None:
        w, h = dataset.image_size
        if isinstance(zoom, bool) or not isinstance(zoom, int) or zoom < 2 or w % zoom or h % zoom:
            raise ValueError(f"zoom must be a whole number >= 2 dividing the images' size {w}×{h}, got {zoom!r}")
        if not 0.0 <= whole <= 1.0 or not 0.0 <= margin[0] <= margin[1] or not 0.0 <= jitter < 1.0:
            raise ValueError(f"whole must be in [0, 1], margin a range of fractions >= 0, jitter in [0, 1); got {whole}, {margin}, {jitter}")
        self.dataset, self.zoom = dataset, zoom
        self.whole, self.margin, self.jitter, self.seed = whole, margin, jitter, int(seed)
        self.source_size: tuple[int, int] = (w, h)
        self.image_size: tuple[int, int] = (w // zoom, h // zoom)
        self.robots, self.num_keypoints = dataset.robots, dataset.num_keypoints
        self.folder, self.manifest = getattr(dataset, "folder", None), getattr(dataset, "manifest", {})
        self.max_dof, self.split = getattr(dataset, "max_dof", None), getattr(dataset, "split", None)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.dataset)

    def box(self, item: dict[str, torch.Tensor], rng: np.random.Generator) -> Box:
        """Where `item` is zoomed into (source pixels)."""
        w, h = self.source_size
        if rng.random() < self.whole:
            return Box.whole(w, h)
        k = item["intrinsics"].numpy().astype(np.float64)
        base = item["base"].numpy().astype(np.float64)
        # Keypoints behind the camera have no pixel worth framing.
        ahead = item["keypoint_valid"].numpy() & (item["keypoints"].numpy()[:, 2] > 1e-3)
        points = item["pixels"].numpy()[ahead].astype(np.float64)
        if base[2] > 1e-3:
            points = np.vstack([points, (k @ base)[:2] / base[2]])
        out_w, out_h = self.image_size
        found = box_around(points, (w, h), (out_w, out_h), margin=rng.uniform(*self.margin), min_width=out_w)
        # Between the source's resolution and the whole image: what a second look can be.
        width = min(max(found.width * float(np.exp(rng.uniform(-self.jitter, self.jitter))), float(out_w)), float(w))
        height = width * out_h / out_w
        cx = found.left + found.width / 2 + rng.uniform(-self.jitter, self.jitter) * width
        cy = found.top + found.height / 2 + rng.uniform(-self.jitter, self.jitter) * height
        return Box(cx - width / 2, cy - height / 2, width, height)

    def zoomed(self, item: dict[str, torch.Tensor], box: Box) -> dict[str, torch.Tensor]:
        """`item` seen through `box`."""
        out = self.image_size
        valid = item["keypoint_valid"].numpy()
        links = crop_labels(item["links"].numpy(), box, out)
        pixels = np.where(valid[:, None], crop_pixels(item["pixels"].numpy(), box, out), 0.0).astype(np.float32)
        seen = (pixels[:, 0] >= -0.5) & (pixels[:, 0] < out[0] - 0.5) & (pixels[:, 1] >= -0.5) & (pixels[:, 1] < out[1] - 0.5)
        inside = valid & seen & (item["keypoints"].numpy()[:, 2] > 0)
        image = crop(item["image"].numpy().transpose(1, 2, 0), box, out)
        zoomed = dict(item)
        zoomed.update(
            {
                "image": torch.from_numpy(np.ascontiguousarray(np.clip(image, 0.0, 1.0).transpose(2, 0, 1))),
                "mask": torch.from_numpy((links > 0).astype(np.float32)[None]),
                "links": torch.from_numpy(links.astype(np.int64)),
                "pixels": torch.from_numpy(pixels),
                "keypoint_in_image": torch.from_numpy(inside),
                "intrinsics": torch.from_numpy(crop_intrinsics(item["intrinsics"].numpy(), box, out).astype(np.float32)),
                "coverage": torch.tensor(float((links > 0).mean())),
            }
        )
        return zoomed

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = self.dataset[index]
        rng = np.random.default_rng([self.seed, self.epoch, index % len(self), 7])
        return self.zoomed(item, self.box(item, rng))

    def first_look(self, index: int) -> dict[str, torch.Tensor]:
        """Item `index` with the whole image shrunk (a first look): its intrinsics are
        the network's camera."""
        return self.zoomed(self.dataset[index], Box.whole(*self.source_size))


def _kp_cells(xyz: np.ndarray, uv: np.ndarray, inside: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, 6K) non-finite cells of the robots' own keypoints, in the CSV's column order."""
    cells = np.concatenate([xyz, uv, inside[..., None]], -1)  # (N, K, 6): x y z u v in_image
    return (~np.isfinite(cells) & valid[..., None]).reshape(len(cells), -1)


def _refuse(path: Path, rows: np.ndarray, names: list[str], bad: np.ndarray, what: str) -> None:
    """A `DatasetError` naming the first bad cell's row (the header is row 1) and, for
    `{column}` in `what`, its column."""
    if bad.size and bad.any():
        i, j = np.argwhere(bad.reshape(len(bad), -1))[0]
        raise DatasetError(f"{path}: row {rows[i] + 2} " + what.format(column=names[j]))
