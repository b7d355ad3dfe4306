"""Labelled images of parts on a platform, in the "earcore-images" format (kind
"parts", `earcore.learning.shards`): 2-12 parts of the RoboCup@Work set
(`earcore.parts.catalogue`) lying on a platform or in a tray, touching allowed, seen
from above by an SR300-like RGB-D camera (its depth noise), under random light, with
random platform, tray and floor colours and textures.

Labels per image: the instance mask (layer `instances`: 0 background, i >= 1 the row's
part i-1), the camera's depth (layer `depth`, mm, 0 = no return) and, per part, its
class, centre of gravity ("pickup point") in the camera frame and in pixels, its grasp
axis in the image (the direction of its longest extent; empty for round parts), its
yaw and position on the platform and its visible pixels. The camera's pose on the
platform (platform_from_camera) and intrinsics are in every row.

Every image is drawn from (seed, image number) alone, so a dataset is the same whatever
the number of workers; shards are written atomically and resumed like the robots'.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning.shards import Sample, shard_name
from earcore.parts.catalogue import Part, part, part_names
from earcore.sim.camera import opengl_projection, opengl_view
from earcore.sim.image_scene import Lighting, load_textures, random_colour
from earcore.sim.sensors import SENSORS
from earcore.sim.shard_worker import render_shard
from earcore.transforms import axis_angle_matrix, look_at, quaternion
from earcore.validate import ConfigError

__all__ = [
    "LAYERS",
    "PartImageOptions",
    "PartImageRenderer",
    "PartSpec",
    "RenderedParts",
    "generate_shard",
    "manifest_for",
    "part_columns",
    "plan_shards",
]

#: The image layers of a parts dataset.
LAYERS = {"rgb": "rgb8", "depth": "gray16", "instances": "gray8"}
#: Per-part CSV columns (prefix obj<i>_).
PART_FIELDS = ("class", "x", "y", "z", "u", "v", "axis_u", "axis_v", "yaw", "table_x", "table_y", "pixels")
CAMERA_COLUMNS = ("cam_x", "cam_y", "cam_z", "cam_qw", "cam_qx", "cam_qy", "cam_qz")
NEAR, FAR = 0.05, 5.0
#: Where unused bodies wait.
HIDDEN = (0.0, 0.0, -50.0)
#: Half sizes (m) of the region the parts are placed in (around the aim point).
REGION = (0.17, 0.12)
#: Camera height above the platform (m) and tilt from straight down (degrees).
HEIGHT = (0.3, 0.5)
TILT = (0.0, 20.0)


def part_columns(max_instances: int) -> list[str]:
    """The CSV's columns, in order."""
    names = ["key", "split", "width", "height", "fx", "fy", "cx", "cy", *CAMERA_COLUMNS, "count"]
    for i in range(max_instances):
        names += [f"obj{i}_{f}" for f in PART_FIELDS]
    return names


@dataclass(frozen=True)
class PartImageOptions:
    """What a parts dataset is made of; equal options give equal bytes."""

    classes: tuple[str, ...] = tuple(part_names())
    count: int = 2000
    width: int = 128
    height: int = 96
    seed: int = 0
    #: Parts per image (inclusive); (1, 1) gives single-part ("needle") images.
    objects: tuple[int, int] = (2, 12)
    #: Probability of a tray (rims around the parts) instead of a bare platform.
    tray: float = 0.3
    #: Probability that a part is pushed against one already placed (touching).
    touching: float = 0.3
    #: Probability of shadows.
    shadow: float = 0.3
    test_fraction: float = 0.2
    shard_size: int = 256
    textures: int = 8

    def validate(self) -> PartImageOptions:
        known = set(part_names())
        if not self.classes:
            raise ConfigError("classes: name at least one part type")
        unknown = [c for c in self.classes if c not in known]
        if unknown:
            raise ConfigError(f"classes: unknown part type(s) {', '.join(unknown)}; known: {', '.join(part_names())}")
        if len(set(self.classes)) != len(self.classes):
            raise ConfigError(f"classes: each part type once, got {list(self.classes)}")
        for name, value, lo, hi in (
            ("width", self.width, 16, 2048),
            ("height", self.height, 16, 2048),
            ("shard_size", self.shard_size, 1, 100000),
            ("count", self.count, 1, 10_000_000),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ConfigError(f"{name} must be a whole number in [{lo}, {hi}], got {value!r}")
        lo, hi = self.objects
        if not (isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi <= 255):
            raise ConfigError(f"objects must be (min, max) with 1 <= min <= max <= 255, got {self.objects!r}")
        for label, chance in (("tray", self.tray), ("touching", self.touching), ("shadow", self.shadow), ("test_fraction", self.test_fraction)):
            if not 0 <= chance <= 1:
                raise ConfigError(f"{label} must be in [0, 1], got {chance!r}")
        if not 0 <= self.seed < 2**32:
            raise ConfigError(f"seed must be in [0, 2^32), got {self.seed!r}")
        return self

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["classes"] = list(self.classes)
        d["objects"] = list(self.objects)
        return d


@dataclass(frozen=True)
class PartSpec:
    key: str
    index: int
    split: str


def plan_shards(options: PartImageOptions) -> list[list[PartSpec]]:
    """Every image of the dataset in shards, a random test fraction; only the options
    decide."""
    n = options.count
    rng = np.random.default_rng([options.seed, 7])
    test = np.zeros(n, dtype=bool)
    test[rng.permutation(n)[: round(options.test_fraction * n)]] = True
    specs = [PartSpec(f"parts-{i:07d}", i, "test" if test[i] else "train") for i in range(n)]
    return [specs[i : i + options.shard_size] for i in range(0, n, options.shard_size)]


def manifest_for(options: PartImageOptions, shards: list[list[PartSpec]]) -> dict[str, Any]:
    parts = [part(c) for c in options.classes]
    return {
        "format": "earcore-images",
        "version": 1,
        "kind": "parts",
        "width": options.width,
        "height": options.height,
        "seed": options.seed,
        "mode": "platform",
        "layers": dict(LAYERS),
        "classes": list(options.classes),
        "round": [p.round for p in parts],
        # Where each part's pickup point sits in its rest frame, and its size (m).
        "centre_of_gravity": [[float(v) for v in p.centre_of_gravity] for p in parts],
        "extent": [[float(v) for v in p.extent] for p in parts],
        "max_instances": options.objects[1],
        "shards": [{"name": shard_name(i), "samples": len(s)} for i, s in enumerate(shards)],
        "generator": options.as_dict(),
    }


# --- placement ------------------------------------------------------------------------


@dataclass
class Placement:
    """A part on the platform: its type, yaw (rad) and position (m) of its rest frame."""

    part: Part
    yaw: float
    x: float
    y: float
    colour: tuple[float, float, float]

    def footprint(self) -> np.ndarray:
        """(4, 2) corners of its rest-frame bounds on the platform."""
        v = self.part.mesh.vertices
        lo, hi = v[:, :2].min(0), v[:, :2].max(0)
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return corners @ np.array([[c, s], [-s, c]]) + [self.x, self.y]

    def world_from_part(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = axis_angle_matrix([0, 0, 1], self.yaw)
        m[:3, 3] = [self.x, self.y, 0.0]
        return m


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two convex quadrilaterals overlap by more than a touch (separating axes)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.c_[-edges[:, 1], edges[:, 0]]:
            n = np.array([nx, ny]) / np.hypot(nx, ny)
            pa, pb = a @ n, b @ n
            if pa.max() <= pb.min() + 1e-4 or pb.max() <= pa.min() + 1e-4:
                return False
    return True


def _at(p: Part, yaw: float, other: Placement, offset: np.ndarray, colour: tuple[float, float, float]) -> Placement:
    """`p` placed at `offset` from `other`'s position."""
    return Placement(p, yaw, float(other.x + offset[0]), float(other.y + offset[1]), colour)


def place_parts(rng: np.random.Generator, parts: list[Part], centre: np.ndarray, touching: float) -> list[Placement]:
    """Random non-overlapping placements in the region around `centre`; with
    probability `touching` a part is slid against one already placed until they touch.
    A part that finds no free spot in 60 draws is left out."""
    placed: list[Placement] = []
    for p in parts:
        colour = p.colour(rng)
        yaw = rng.uniform(-np.pi, np.pi)
        spot = None
        if placed and rng.random() < touching:
            other = placed[rng.integers(len(placed))]
            direction = rng.normal(size=2)
            direction /= np.linalg.norm(direction)
            near, far = 0.0, 0.3  # distance from the other's centre: overlapping at near, free at far
            candidate = _at(p, yaw, other, far * direction, colour)
            if not any(_overlap(candidate.footprint(), q.footprint()) for q in placed):
                for _ in range(20):
                    mid = (near + far) / 2
                    candidate = _at(p, yaw, other, mid * direction, colour)
                    if _overlap(candidate.footprint(), other.footprint()):
                        near = mid
                    else:
                        far = mid
                candidate = _at(p, yaw, other, far * direction, colour)
                inside = np.all(np.abs(candidate.footprint() - centre) <= np.array(REGION) + 0.03)
                if inside and not any(_overlap(candidate.footprint(), q.footprint()) for q in placed):
                    spot = candidate
        for _ in range(60):
            if spot is not None:
                break
            xy = centre + rng.uniform(-1, 1, 2) * np.array(REGION)
            candidate = Placement(p, yaw, float(xy[0]), float(xy[1]), colour)
            if not any(_overlap(candidate.footprint(), q.footprint()) for q in placed):
                spot = candidate
        if spot is not None:
            placed.append(spot)
    return placed


# --- rendering --------------------------------------------------------------------------


@dataclass
class RenderedParts:
    """A sample and what made it (for checks): camera pose (platform_from_camera) and
    intrinsics, the true depth, the placements, pybullet's segmentation and the bodies."""

    sample: Sample
    world_from_camera: np.ndarray
    K: np.ndarray
    true_depth: np.ndarray
    placements: list[Placement]
    segmentation: np.ndarray
    bodies: list[int] = field(default_factory=list)


class PartImageRenderer:
    """One pybullet world (DIRECT) rendering images of a parts dataset; one per worker."""

    def __init__(self, options: PartImageOptions) -> None:
        from earcore.sim.robot_images import _quiet_client

        self.options = options.validate()
        self.p = p = _quiet_client()
        self.parts = [part(c) for c in options.classes]
        self.class_of = {c: i for i, c in enumerate(options.classes)}
        self._shapes = [p.createVisualShape(p.GEOM_MESH, vertices=q.mesh.vertices.tolist(), indices=q.mesh.triangles.reshape(-1).tolist()) for q in self.parts]
        self._pool: dict[int, list[int]] = {i: [] for i in range(len(self.parts))}
        self.platform = self._box((0.45, 0.35, 0.02))
        self.rims = [self._box(h) for h in ((0.22, 0.006, 0.015), (0.22, 0.006, 0.015), (0.006, 0.16, 0.015), (0.006, 0.16, 0.015))]
        self.floor = self._box((3.0, 3.0, 0.01))
        self.sensor = SENSORS["sr300"].scaled(options.width / SENSORS["sr300"].width)
        self.header = part_columns(options.objects[1])
        self.textures = load_textures(p, options.seed, options.textures)

    def close(self) -> None:
        self.p.disconnect()

    def _box(self, half) -> int:
        shape = self.p.createVisualShape(self.p.GEOM_BOX, halfExtents=list(half))
        return self.p.createMultiBody(0, -1, shape, HIDDEN)

    def _bodies(self, placements: list[Placement]) -> list[int]:
        """A body per placement (a pool per part type, grown as needed), the rest hidden."""
        used: dict[int, int] = {}
        out = []
        for pl in placements:
            c = self.class_of[pl.part.name]
            k = used.get(c, 0)
            used[c] = k + 1
            while len(self._pool[c]) <= k:
                self._pool[c].append(self.p.createMultiBody(0, -1, self._shapes[c], HIDDEN))
            out.append(self._pool[c][k])
        for c, bodies in self._pool.items():
            for body in bodies[used.get(c, 0) :]:
                self.p.resetBasePositionAndOrientation(body, HIDDEN, [0, 0, 0, 1])
        return out

    def _intrinsics(self, rng: np.random.Generator) -> np.ndarray:
        w, h = self.options.width, self.options.height
        s = self.sensor
        f = rng.uniform(0.97, 1.03)
        fx = 0.5 * w / np.tan(np.radians(s.fov_h_deg) / 2) * f
        fy = 0.5 * h / np.tan(np.radians(s.fov_v_deg) / 2) * f
        cx = (w - 1) / 2 + rng.uniform(-0.015, 0.015) * w
        cy = (h - 1) / 2 + rng.uniform(-0.015, 0.015) * h
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    def _camera(self, rng: np.random.Generator, aim: np.ndarray) -> np.ndarray:
        """platform_from_camera (OpenCV axes): above `aim`, tilted from straight down by
        up to TILT, turned about the vertical at random."""
        height = rng.uniform(*HEIGHT)
        tilt = np.radians(rng.uniform(*TILT))
        azimuth = rng.uniform(0, 2 * np.pi)
        target = np.array([aim[0], aim[1], 0.0])
        eye = target + height * np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
        turn = rng.uniform(0, 2 * np.pi)  # the image's "up" on the platform
        return look_at(eye, target, up=(np.cos(turn), np.sin(turn), 0.0))

    def _surface(self, rng: np.random.Generator, white: float) -> tuple[tuple[float, float, float], int]:
        """A colour (light grey to white with probability `white`) and maybe a texture."""
        if rng.random() < white:
            v = rng.uniform(0.75, 1.0)
            tint = rng.uniform(-0.04, 0.04, 3)
            return tuple(float(np.clip(v + t, 0, 1)) for t in tint), -1  # type: ignore[return-value]
        return random_colour(rng), int(rng.integers(-1, len(self.textures)))

    def _look(self, body: int, colour, texture: int) -> None:
        self.p.changeVisualShape(body, -1, rgbaColor=[*colour, 1.0], textureUniqueId=self.textures[texture] if texture >= 0 else -1)

    def render(self, spec: PartSpec) -> RenderedParts:
        o = self.options
        p = self.p
        rng = np.random.default_rng([o.seed, 11, spec.index])
        centre = rng.uniform(-0.1, 0.1, 2)
        n = int(rng.integers(o.objects[0], o.objects[1] + 1))
        chosen = [self.parts[i] for i in rng.integers(0, len(self.parts), n)]
        placements = place_parts(rng, chosen, centre, o.touching)
        bodies = self._bodies(placements)
        for body, pl in zip(bodies, placements):
            p.resetBasePositionAndOrientation(body, [pl.x, pl.y, 0.0], p.getQuaternionFromEuler([0, 0, pl.yaw]))
            p.changeVisualShape(body, -1, rgbaColor=[*pl.colour, 1.0])
        # The platform's top is z = 0; a tray adds rims around the region.
        p.resetBasePositionAndOrientation(self.platform, [centre[0], centre[1], -0.02], [0, 0, 0, 1])
        self._look(self.platform, *self._surface(rng, 0.75))
        tray = rng.random() < o.tray
        rim_colour = self._surface(rng, 0.3)
        offsets = ((0, REGION[1] + 0.04), (0, -REGION[1] - 0.04), (REGION[0] + 0.05, 0), (-REGION[0] - 0.05, 0))
        for body, (dx, dy) in zip(self.rims, offsets):
            where = [centre[0] + dx, centre[1] + dy, 0.015] if tray else HIDDEN
            p.resetBasePositionAndOrientation(body, where, [0, 0, 0, 1])
            self._look(body, *rim_colour)
        p.resetBasePositionAndOrientation(self.floor, [0, 0, -rng.uniform(0.4, 0.9)], [0, 0, 0, 1])
        self._look(self.floor, *self._surface(rng, 0.2))
        K = self._intrinsics(rng)
        world_from_camera = self._camera(rng, centre + rng.normal(0, 0.03, 2))
        light = Lighting(
            direction=tuple(float(v) for v in (*rng.uniform(-1, 1, 2), rng.uniform(0.6, 1.5))),  # type: ignore[arg-type]
            colour=tuple(float(v) for v in rng.uniform(0.85, 1.0, 3)),  # type: ignore[arg-type]
            ambient=float(rng.uniform(0.35, 0.7)),
            diffuse=float(rng.uniform(0.3, 0.7)),
            specular=float(rng.uniform(0.0, 0.4)),
            shadow=bool(rng.random() < o.shadow),
        )
        w, h = o.width, o.height
        _, _, rgba, depth_buffer, seg = p.getCameraImage(
            w, h, opengl_view(world_from_camera), opengl_projection(K, w, h, NEAR, FAR), renderer=p.ER_TINY_RENDERER, **light.arguments()
        )
        rgb = np.ascontiguousarray(np.reshape(rgba, (h, w, 4))[..., :3], dtype=np.uint8)
        seg = np.reshape(seg, (h, w)).astype(np.int64)
        d = np.reshape(depth_buffer, (h, w)).astype(np.float64)
        true_depth = FAR * NEAR / (FAR - (FAR - NEAR) * d)
        true_depth[d >= 1.0] = 0.0
        measured = self.sensor.corrupt(true_depth, np.random.default_rng([o.seed, 12, spec.index]))
        depth_mm = np.clip(np.rint(measured * 1000.0), 0, 65535).astype(np.uint16)
        instances = np.zeros((h, w), dtype=np.uint8)
        for i, body in enumerate(bodies):
            instances[seg == body] = i + 1
        row = self._labels(spec, K, world_from_camera, placements, instances)
        sample = Sample(spec.key, {"rgb": rgb, "depth": depth_mm, "instances": instances}, row)
        return RenderedParts(sample, world_from_camera, K, true_depth, placements, seg, bodies)

    def _labels(self, spec: PartSpec, K, world_from_camera, placements: list[Placement], instances) -> dict[str, Any]:
        w, h = self.options.width, self.options.height
        camera_from_world = np.linalg.inv(world_from_camera)
        qx, qy, qz, qw = quaternion(world_from_camera[:3, :3])
        row: dict[str, Any] = {
            "split": spec.split,
            "width": w,
            "height": h,
            "fx": K[0, 0],
            "fy": K[1, 1],
            "cx": K[0, 2],
            "cy": K[1, 2],
            **dict(zip(CAMERA_COLUMNS, (*world_from_camera[:3, 3], qw, qx, qy, qz))),
            "count": len(placements),
        }

        def project(point_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            c = camera_from_world[:3, :3] @ point_world + camera_from_world[:3, 3]
            return np.array([K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]]), c

        for i, pl in enumerate(placements):
            pose = pl.world_from_part()
            cog_world = pose[:3, :3] @ pl.part.centre_of_gravity + pose[:3, 3]
            uv, cam = project(cog_world)
            fields: dict[str, Any] = {
                "class": self.class_of[pl.part.name],
                "x": cam[0],
                "y": cam[1],
                "z": cam[2],
                "u": uv[0],
                "v": uv[1],
                "yaw": pl.yaw,
                "table_x": cog_world[0],
                "table_y": cog_world[1],
                "pixels": int((instances == i + 1).sum()),
            }
            if not pl.part.round:
                ahead, _ = project(cog_world + 0.01 * pose[:3, 0])
                axis = (ahead - uv) / max(np.linalg.norm(ahead - uv), 1e-12)
                fields.update(axis_u=axis[0], axis_v=axis[1])
            row.update({f"obj{i}_{k}": v for k, v in fields.items()})
        return row


def generate_shard(options: PartImageOptions, index: int, folder: str | Path) -> int:
    """Render shard `index` of the dataset and write it into `folder` (atomically);
    returns its number of images. The worker's renderer is kept for its next shard."""
    return render_shard(options, PartImageRenderer, plan_shards(options)[index], index, folder)
