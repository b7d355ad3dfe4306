"""The "earcore-images" format (version 1): labelled images in shards that any tool can
read (a tar of PNGs and a CSV per shard, a JSON manifest).

    DATASET/
      manifest.json        format, version, kind, width, height, seed, mode, shards,
                           generator, and what the kind adds (below); optional `layers`
                           {name: pixel format} (absent: the robots' rgb + links)
      shard-00000.tar      <key>.<layer>.png per sample and layer
      shard-00000.csv      one row per sample

Kinds:

* ``robots``: manifest adds robots, keypoints, num_keypoints, links, max_dof (optional:
  keypoint_frames, dof); layers `rgb` (H×W×3) and `links` (H×W; 0 = not the robot,
  i >= 1 = link i-1 of manifest["links"][robot]); the CSV's columns are `columns`.
* ``parts``: manifest adds classes and max_instances; layers `rgb`, `depth` (H×W,
  16 bits, mm; 0 = no return) and `instances` (H×W; 0 = background, i >= 1 = the
  row's instance i-1); see `earcore.sim.part_images`.

Shards are written atomically (a temporary name, then a rename; the CSV last), so a
shard whose CSV exists is complete and an interrupted run resumes by skipping it.
"""

from __future__ import annotations

import csv
import io
import json
import os
import tarfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning import png
from earcore.learning.errors import DatasetError

__all__ = [
    "FORMAT",
    "VERSION",
    "Sample",
    "Shard",
    "manifest_layers",
    "columns",
    "complete_shards",
    "read_manifest",
    "read_shard",
    "shard_name",
    "write_manifest",
    "write_shard",
]

FORMAT = "earcore-images"
VERSION = 1
MANIFEST = "manifest.json"
#: Keys every manifest has, and those each kind adds.
COMMON_KEYS = ("format", "version", "kind", "width", "height", "seed", "mode", "shards", "generator")
KIND_KEYS = {
    "robots": ("robots", "keypoints", "num_keypoints", "links", "max_dof"),
    "parts": ("classes", "max_instances"),
}
#: Pixel formats of a layer: channels and dtype.
PIXELS: dict[str, tuple[int, Any]] = {"rgb8": (3, np.uint8), "gray8": (1, np.uint8), "gray16": (1, np.uint16)}
#: The layers of a dataset whose manifest names none (the robots').
ROBOT_LAYERS = {"rgb": "rgb8", "links": "gray8"}
BASE_COLUMNS = ("base_x", "base_y", "base_z", "base_qw", "base_qx", "base_qy", "base_qz")


def shard_name(index: int) -> str:
    return f"shard-{index:05d}"


def columns(max_dof: int, num_keypoints: int) -> list[str]:
    """The CSV's columns, in order."""
    names = ["key", "robot", "robot_class", "recording", "split", "width", "height", "fx", "fy", "cx", "cy"]
    names += [f"q{i}" for i in range(max_dof)]
    for i in range(num_keypoints):
        names += [f"kp{i}_{c}" for c in ("x", "y", "z", "u", "v", "in_image")]
    return names + list(BASE_COLUMNS) + ["coverage"]


def manifest_layers(manifest: dict[str, Any]) -> dict[str, str]:
    """The layers (name → pixel format) of a dataset's images."""
    return dict(manifest.get("layers", ROBOT_LAYERS))


@dataclass
class Sample:
    """One labelled image: its layers (name → (H, W, 3) or (H, W) array, e.g. `rgb`
    and `links`) and its CSV row (column → value; None or missing for an empty cell)."""

    key: str
    images: dict[str, np.ndarray]
    row: dict[str, Any]


@dataclass
class Shard:
    """A shard read into memory: each layer's images stacked ((N, H, W, 3) or
    (N, H, W)), and the CSV's columns as strings (`text`) in row order."""

    images: dict[str, np.ndarray]
    text: dict[str, list[str]]

    def numbers(self, column: str, path: Path | str = "") -> np.ndarray:
        """A column as float64 (NaN for empty cells)."""
        if column not in self.text:
            raise DatasetError(f"{path}: missing column {column!r}")
        try:
            return np.array([float(v) if v != "" else np.nan for v in self.text[column]], dtype=np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}: column {column!r} holds a value that is not a number ({exc})") from None


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _format_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        return "" if not np.isfinite(value) else repr(float(value))
    return str(value)


def write_shard(folder: str | Path, name: str, samples: Sequence[Sample], header: Sequence[str], level: int = 6) -> None:
    """Write `name`.tar and `name`.csv into `folder`, each atomically, the CSV last."""
    folder = Path(folder)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for s in samples:
            for suffix, image in s.images.items():
                data = png.encode(image, level)
                info = tarfile.TarInfo(f"{s.key}.{suffix}.png")
                info.size = len(data)
                info.mode = 0o644
                tar.addfile(info, io.BytesIO(data))
    _atomic_write(folder / f"{name}.tar", buffer.getvalue())
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(header)
    for s in samples:
        unknown = set(s.row) - set(header)
        if unknown:
            raise ValueError(f"sample {s.key}: columns {sorted(unknown)} are not in the header")
        writer.writerow([_format_cell(s.key if c == "key" else s.row.get(c)) for c in header])
    _atomic_write(folder / f"{name}.csv", text.getvalue().encode())


def complete_shards(folder: str | Path, manifest: dict[str, Any] | None = None) -> set[str]:
    """Names of the shards whose CSV and tar are both there (the CSV is written last);
    given the `manifest`, only those that are also whole: the CSV holds a row per
    sample and the tar every layer of each, all of its bytes present (a copy cut
    short, or a disk that filled, leaves files that exist but are not whole)."""
    folder = Path(folder)
    names = {p.stem for p in folder.glob("shard-*.csv") if (folder / f"{p.stem}.tar").is_file()}
    if manifest is None:
        return names
    layers = len(manifest_layers(manifest))
    samples = {s["name"]: s["samples"] for s in manifest["shards"]}
    return {n for n in names if n in samples and _whole(folder, n, samples[n], layers)}


def _whole(folder: Path, name: str, samples: int, layers: int) -> bool:
    """Whether shard `name` has `samples` CSV rows and `samples` × `layers` tar members
    whose bytes all lie within the file (headers are read, images are not)."""
    try:
        with open(folder / f"{name}.csv", newline="", encoding="utf-8") as f:
            rows = sum(1 for _ in csv.reader(f)) - 1
        tar_path = folder / f"{name}.tar"
        size = tar_path.stat().st_size
        with tarfile.open(tar_path) as tar:
            members = tar.getmembers()
    except (OSError, UnicodeDecodeError, csv.Error, tarfile.TarError):
        return False
    return rows == samples and len(members) == samples * layers and all(m.offset_data + m.size <= size for m in members)


def read_shard(
    folder: str | Path,
    name: str,
    width: int,
    height: int,
    required: Iterable[str] = (),
    samples: int | None = None,
    layers: dict[str, str] | None = None,
) -> Shard:
    """Read a shard: every CSV row's PNG of each layer (name → pixel format; default the
    robots' rgb + links) from the tar, checked against the image size and format;
    `required` columns must be present, and `samples` (the manifest's count, if given)
    rows. Raises `DatasetError` naming the file."""
    layers = dict(ROBOT_LAYERS if layers is None else layers)
    folder = Path(folder)
    csv_path, tar_path = folder / f"{name}.csv", folder / f"{name}.tar"
    try:
        with open(csv_path, newline="") as f:
            rows = list(csv.reader(f))
    except FileNotFoundError:
        raise DatasetError(f"{csv_path}: missing (the manifest lists shard {name})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{csv_path}: not a readable CSV ({exc})") from None
    if not rows:
        raise DatasetError(f"{csv_path}: empty (no header)")
    header, body = rows[0], rows[1:]
    missing = [c for c in ["key", *required] if c not in header]
    if missing:
        raise DatasetError(f"{csv_path}: missing column{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}")
    for i, r in enumerate(body):
        if len(r) != len(header):
            raise DatasetError(f"{csv_path}: row {i + 2} has {len(r)} cells, the header {len(header)}")
    if samples is not None and len(body) != samples:
        raise DatasetError(f"{csv_path}: {len(body)} rows, the manifest says {samples} samples (a damaged shard, or one of another dataset)")
    text = {c: [r[j] for r in body] for j, c in enumerate(header)}
    keys = text["key"]
    if len(set(keys)) != len(keys):
        twice = next(k for i, k in enumerate(keys) if k in keys[:i])
        raise DatasetError(f"{csv_path}: key {twice!r} appears in more than one row")
    files: dict[str, bytes] = {}
    try:
        with tarfile.open(tar_path, mode="r:") as tar:
            for entry in tar:
                if entry.isfile():
                    extracted = tar.extractfile(entry)
                    if extracted is not None:
                        files[entry.name] = extracted.read()
    except FileNotFoundError:
        raise DatasetError(f"{tar_path}: missing (the manifest lists shard {name})") from None
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise DatasetError(f"{tar_path}: corrupt or truncated tar ({exc})") from None
    n = len(body)
    images: dict[str, np.ndarray] = {}
    for layer, pixels in layers.items():
        channels, dtype = PIXELS[pixels]
        shape = (height, width, 3) if channels == 3 else (height, width)
        out = images[layer] = np.empty((n, *shape), dtype=dtype)
        for i, key in enumerate(text["key"]):
            member = f"{key}.{layer}.png"
            if member not in files:
                raise DatasetError(f"{tar_path}: no {member} for the CSV's row {i + 2}")
            image = png.decode(files[member], f"{tar_path}:{member}")
            if image.shape != shape or image.dtype != dtype:
                raise DatasetError(f"{tar_path}:{member}: {image.shape} {image.dtype} image, expected {shape} {np.dtype(dtype).name}")
            out[i] = image
    return Shard(images, text)


def _required_keys(manifest: dict[str, Any]) -> tuple[str, ...]:
    return COMMON_KEYS + KIND_KEYS.get(manifest.get("kind", "robots"), ())


def write_manifest(folder: str | Path, manifest: dict[str, Any]) -> None:
    missing = [k for k in _required_keys(manifest) if k not in manifest]
    if missing:
        raise ValueError(f"manifest lacks {missing}")
    _atomic_write(Path(folder) / MANIFEST, (json.dumps(manifest, indent=1, sort_keys=False) + "\n").encode())


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """The manifest of a dataset folder, checked for the format, version and keys."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such dataset folder")
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing (not an {FORMAT} dataset folder)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise DatasetError(f"{path}: format {found!r}, expected {FORMAT!r}")
    if manifest.get("version") != VERSION:
        raise DatasetError(f"{path}: format version {manifest.get('version')!r}; this earcore reads version {VERSION}")
    if manifest.get("kind") not in KIND_KEYS:
        raise DatasetError(f"{path}: kind {manifest.get('kind')!r}; this earcore reads {', '.join(KIND_KEYS)}")
    missing = [k for k in _required_keys(manifest) if k not in manifest]
    if missing:
        raise DatasetError(f"{path}: missing {', '.join(missing)}")
    numbers = {"robots": ("num_keypoints", "max_dof"), "parts": ("max_instances",)}[manifest["kind"]]
    for key in ("width", "height", *numbers):
        v = manifest[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < (1 if key in ("width", "height") else 0):
            raise DatasetError(f"{path}: {key} must be a whole number, got {v!r}")
    shards = manifest["shards"]
    if not isinstance(shards, list) or not all(isinstance(s, dict) and "name" in s and "samples" in s for s in shards):
        raise DatasetError(f"{path}: shards must be a list of {{name, samples}}")
    for s in shards:
        if not isinstance(s["name"], str) or isinstance(s["samples"], bool) or not isinstance(s["samples"], int) or s["samples"] < 0:
            raise DatasetError(f"{path}: shards must be a list of {{name (text), samples (a whole number >= 0)}}, got {s!r}")
    layers = manifest.get("layers", ROBOT_LAYERS)
    if not isinstance(layers, dict) or not layers or not all(isinstance(k, str) and v in PIXELS for k, v in layers.items()):
        raise DatasetError(f"{path}: layers must be a table {{name: pixel format}} with formats among {', '.join(PIXELS)}, got {layers!r}")
    if manifest["kind"] == "robots":
        _check_robots(manifest, path)
    else:
        classes = manifest["classes"]
        if not isinstance(classes, list) or not classes or not all(isinstance(c, str) for c in classes) or len(set(classes)) != len(classes):
            raise DatasetError(f"{path}: classes must be a list of distinct names, got {classes!r}")
    return manifest


def _check_robots(manifest: dict[str, Any], path: Path) -> None:
    """`robots` a list of distinct names; `keypoints` (and `links`, `keypoint_frames` and
    `dof` where present) a table with a list for every robot; no robot with more
    keypoints than `num_keypoints` or more joints than `max_dof`."""
    robots = manifest["robots"]
    if not isinstance(robots, list) or not all(isinstance(r, str) for r in robots) or len(set(robots)) != len(robots):
        raise DatasetError(f"{path}: robots must be a list of distinct names, got {robots!r}")
    for key in ("keypoints", "links", "keypoint_frames", "dof"):
        if key not in manifest:
            continue
        table = manifest[key]
        if not isinstance(table, dict):
            raise DatasetError(f"{path}: {key} must be a table {{robot: ...}}, got {type(table).__name__}")
        missing = [r for r in robots if r not in table]
        if missing:
            raise DatasetError(f"{path}: {key} has no entry for robot{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
        for r in robots:
            value = table[r]
            if key == "dof":
                if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= manifest["max_dof"]:
                    raise DatasetError(f"{path}: dof of {r} must be a whole number in [0, max_dof = {manifest['max_dof']}], got {value!r}")
            elif not isinstance(value, list):
                raise DatasetError(f"{path}: {key} of {r} must be a list, got {type(value).__name__}")
    for r in robots:
        names = manifest["keypoints"][r]
        if not all(isinstance(n, str) for n in names):
            raise DatasetError(f"{path}: keypoints of {r} must be names")
        if len(names) > manifest["num_keypoints"]:
            raise DatasetError(f"{path}: {r} has {len(names)} keypoints, more than num_keypoints = {manifest['num_keypoints']}")
        frames = manifest.get("keypoint_frames", {}).get(r)
        if frames is not None:
            if len(frames) != len(names):
                raise DatasetError(f"{path}: keypoint_frames of {r} has {len(frames)} entries, its keypoints {len(names)}")
            for f in frames:
                ok = isinstance(f, list) and len(f) == 2 and isinstance(f[0], str) and isinstance(f[1], list) and len(f[1]) == 3
                if not ok or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in f[1]):
                    raise DatasetError(f"{path}: keypoint_frames of {r} must be [link name, [x, y, z]] pairs, got {f!r}")
