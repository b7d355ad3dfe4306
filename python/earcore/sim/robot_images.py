"""Labelled robot images from the simulator, in the "earcore-images" format
(`earcore.learning.shards`): a robot at collision-free joint states over its full
ranges, seen by a Kinect V2-like colour camera from where a person holding it would
stand, in randomised surroundings (`earcore.sim.image_scene`).

Labels per image: the robot's per-link segmentation (from the renderer), each joint
frame's origin and the flange in the camera frame and in pixels, the base pose
(camera_from_base), the joint angles, the intrinsics and the robot's image coverage.
Positions come from earcore's forward kinematics (`RobotModel.fk`), the image from
pybullet's tiny renderer at the network's resolution.

Two sampling modes:

* ``recordings``: the papers' protocol. Each recording has one camera placement, one
  scene and one light while the joints sweep their ranges together (a shifted Halton
  sequence of collision-free states); a person's arm may pass in front in some frames.
  Sizes: the papers' recordings (UR3 211/252/463, UR5 252/756/1512, UR10 112/278/514;
  iiwa and Panda 14 recordings, 1,837 images, as Paper VI's iiwa set) times `scale`.
* ``random``: a new camera, scene, light and joint state per image.

Every image is drawn from seeds derived from the master seed, its robot, recording and
frame number, so a dataset is the same whatever the number of workers.
"""

from __future__ import annotations

import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning.shards import Sample, columns, shard_name
from earcore.robots import BUILTIN_MODELS, FLANGES, RobotModel, load, urdf_path
from earcore.sim.camera import opengl_projection, opengl_view
from earcore.sim.image_scene import ImageScene, draw_layout, draw_person
from earcore.sim.sensors import SENSORS
from earcore.sim.shard_worker import render_shard
from earcore.transforms import axis_angle_matrix, look_at, quaternion
from earcore.urdf import parse_urdf
from earcore.validate import ConfigError

__all__ = [
    "FLANGES",
    "PAPER_RECORDINGS",
    "RenderedSample",
    "keypoint_frames",
    "keypoint_positions",
    "RobotImageOptions",
    "RobotImageRenderer",
    "SampleSpec",
    "collision_free",
    "generate_shard",
    "manifest_for",
    "plan_shards",
]

#: The papers' recordings (Paper IV/V Table I) and, for the iiwa and the Panda, Paper
#: VI's iiwa set (1,837 images in 14 recordings) split evenly.
PAPER_RECORDINGS: dict[str, tuple[int, ...]] = {
    "ur3": (211, 252, 463),
    "ur5": (252, 756, 1512),
    "ur10": (112, 278, 514),
    "iiwa": (131,) * 13 + (134,),
    "panda": (131,) * 13 + (134,),
}
MODES = ("recordings", "random")
#: The camera's near and far clipping planes (m).
NEAR, FAR = 0.05, 20.0
#: Camera distance to the aim point, in multiples of the robot's reach, before the
#: clearance below pushes it out: the robot then covers roughly 3-10 % of the image at the
#: median 5 % (measured: docs/robot-images.md), with the whole arm in view in 9 of 10.
DISTANCE = (0.7, 1.2)
#: The camera stays this many reaches from the robot's base.
CLEARANCE = 1.2


@dataclass(frozen=True)
class RobotImageOptions:
    """What a dataset is made of; equal options give equal bytes."""

    robots: tuple[str, ...] = ("ur3", "ur5", "ur10")
    mode: str = "recordings"
    width: int = 128
    height: int = 106
    seed: int = 0
    #: Recordings mode: the papers' recording sizes times this factor (each at least 1).
    scale: float = 1.0
    #: Images per robot instead of `scale` (recordings mode: shared among the robot's
    #: recordings in the papers' proportions). Random mode: required unless `scale` is
    #: used, which then means the papers' totals times `scale`.
    count: int | None = None
    #: The robots' URDF meshes the camera sees: "visual" or "collision" (coarser, faster).
    meshes: str = "visual"
    distractors: bool = True
    #: Probability of a person's arm in an image, and of shadows.
    person: float = 0.25
    shadow: float = 0.3
    test_fraction: float = 0.2
    shard_size: int = 256
    #: Procedural textures per world (tables, floor, walls draw from them).
    textures: int = 8

    def validate(self) -> RobotImageOptions:
        if not self.robots:
            raise ConfigError("robots: name at least one robot")
        for r in self.robots:
            if r not in BUILTIN_MODELS:
                raise ConfigError(f"robots: unknown robot {r!r}; built-in: {', '.join(sorted(BUILTIN_MODELS))}")
        if len(set(self.robots)) != len(self.robots):
            raise ConfigError(f"robots: each robot once, got {list(self.robots)}")
        if self.mode not in MODES:
            raise ConfigError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for name, value, lo, hi in (("width", self.width, 16, 2048), ("height", self.height, 16, 2048), ("shard_size", self.shard_size, 1, 100000)):
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ConfigError(f"{name} must be a whole number in [{lo}, {hi}], got {value!r}")
        if not (0 < self.scale <= 100):
            raise ConfigError(f"scale must be in (0, 100], got {self.scale!r}")
        if self.count is not None and not (isinstance(self.count, int) and 1 <= self.count <= 10_000_000):
            raise ConfigError(f"count must be a whole number >= 1, got {self.count!r}")
        if self.meshes not in ("visual", "collision"):
            raise ConfigError(f"meshes must be 'visual' or 'collision', got {self.meshes!r}")
        for label, chance in (("person", self.person), ("shadow", self.shadow), ("test_fraction", self.test_fraction)):
            if not 0 <= chance <= 1:
                raise ConfigError(f"{label} must be in [0, 1], got {chance!r}")
        if not 0 <= self.seed < 2**32:
            raise ConfigError(f"seed must be in [0, 2^32), got {self.seed!r}")
        return self

    def recordings(self) -> dict[str, tuple[int, ...]]:
        """Images per recording per robot (random mode: one entry, the robot's total)."""
        out: dict[str, tuple[int, ...]] = {}
        for r in self.robots:
            paper = PAPER_RECORDINGS[r]
            if self.count is not None:
                if self.mode == "random":
                    out[r] = (self.count,)
                    continue
                shares = np.array(paper, dtype=float) / sum(paper) * self.count
                floor = np.floor(shares).astype(int)
                floor[np.argsort(-(shares - floor))[: self.count - floor.sum()]] += 1
                out[r] = tuple(int(s) for s in floor if s > 0)
            else:
                sizes = [max(1, round(n * self.scale)) for n in paper]
                out[r] = (sum(sizes),) if self.mode == "random" else tuple(sizes)
        return out

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["robots"] = list(self.robots)
        d["recordings"] = {r: list(v) for r, v in self.recordings().items()}
        return d


@dataclass(frozen=True)
class SampleSpec:
    key: str
    robot: str
    #: Recording number (random mode: every image is its own recording: its number).
    recording: int
    frame: int
    split: str


def _code(name: str) -> int:
    return zlib.crc32(name.encode())


#: How `plan_shards` orders the shards (in the manifest's generator table: a dataset
#: begun with another order is not resumed with this one).
SHARD_ORDER = "robots interleaved"


def plan_shards(options: RobotImageOptions) -> list[list[SampleSpec]]:
    """Every sample of the dataset, in shards of one robot each (a worker loads one
    robot per shard): a random test fraction per robot, each robot's samples in a random
    order, and the robots' shards interleaved (the first shard of each robot in the
    options' robot order, then the second of each, ...) so that the first images of a
    dataset show every robot. Only the options decide: equal options, equal shards."""
    per_robot: list[list[list[SampleSpec]]] = []
    for robot, sizes in options.recordings().items():
        rng = np.random.default_rng([options.seed, _code(robot), 7])
        if options.mode == "recordings":
            items = [(r, f) for r, n in enumerate(sizes) for f in range(n)]
        else:
            items = [(f, 0) for f in range(sizes[0])]
        n = len(items)
        test = np.zeros(n, dtype=bool)
        test[rng.permutation(n)[: round(options.test_fraction * n)]] = True
        order = rng.permutation(n)
        specs = []
        for i in order:
            r, f = items[i]
            key = f"{robot}-r{r:02d}-{f:05d}" if options.mode == "recordings" else f"{robot}-{r:07d}"
            specs.append(SampleSpec(key, robot, r, f, "test" if test[i] else "train"))
        per_robot.append([specs[i : i + options.shard_size] for i in range(0, n, options.shard_size)])
    rounds = max(len(shards) for shards in per_robot)
    return [shards[i] for i in range(rounds) for shards in per_robot if i < len(shards)]


def keypoint_names(model: RobotModel, robot: str) -> list[str]:
    """The robot's keypoints: its revolute joints in chain order, then the flange."""
    return [*revolute_joints(model, robot)[0], "flange"]


def revolute_joints(model: RobotModel, robot: str) -> tuple[list[str], list[int]]:
    """Names of the revolute (and continuous) joints and the index of each one's child
    link (the joint frame is its child link's frame)."""
    joints = {j.name: j for j in parse_urdf(urdf_path(robot)).joints}
    names = [n for n in model.joint_names if joints[n].kind in ("revolute", "continuous")]
    return names, [model.link_names.index(joints[n].child) for n in names]


def keypoint_frames(model: RobotModel, robot: str) -> tuple[list[int], np.ndarray]:
    """Each keypoint's link (index into `model.link_names`) and its homogeneous offset
    (n, 4) in that link's frame: the revolute joints' origins, then the flange."""
    links = revolute_joints(model, robot)[1]
    flange, offset = FLANGES[robot]
    offsets = np.zeros((len(links) + 1, 4))
    offsets[:, 3] = 1.0
    offsets[-1, :3] = offset
    return [*links, model.link_names.index(flange)], offsets


def keypoint_positions(model: RobotModel, frames: tuple[list[int], np.ndarray], q: np.ndarray) -> np.ndarray:
    """Keypoints at configuration `q` ((dof,) → (n, 3); (K, dof) → (K, n, 3)) in the
    model's world frame (its `base` applied), `frames` from `keypoint_frames`: the
    labels the images carry, for any camera."""
    links, offsets = frames
    poses = model.fk(np.asarray(q, dtype=np.float64))[..., links, :, :]
    return np.einsum("...nij,nj->...ni", poses, offsets)[..., :3]


def _frames_by_name(model: RobotModel, robot: str) -> list[list[Any]]:
    links, offsets = keypoint_frames(model, robot)
    return [[model.link_names[link], [float(v) for v in offset[:3]]] for link, offset in zip(links, offsets)]


def manifest_for(options: RobotImageOptions, shards: list[list[SampleSpec]]) -> dict[str, Any]:
    """The dataset's manifest (`earcore.learning.shards`)."""
    models = {r: load(r) for r in options.robots}
    keypoints = {r: keypoint_names(m, r) for r, m in models.items()}
    return {
        "format": "earcore-images",
        "version": 1,
        "kind": "robots",
        "width": options.width,
        "height": options.height,
        "seed": options.seed,
        "mode": options.mode,
        "robots": list(options.robots),
        "keypoints": keypoints,
        # Where each keypoint sits on the robot: (link name, offset in its frame, m).
        "keypoint_frames": {r: _frames_by_name(m, r) for r, m in models.items()},
        "num_keypoints": max(len(k) for k in keypoints.values()),
        "links": {r: list(m.link_names) for r, m in models.items()},
        "dof": {r: m.dof for r, m in models.items()},
        "max_dof": max(m.dof for m in models.values()),
        "shards": [{"name": shard_name(i), "samples": len(s)} for i, s in enumerate(shards)],
        "generator": {**options.as_dict(), "shard_order": SHARD_ORDER},
    }


# --- joint states ------------------------------------------------------------------

_PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)


def _halton(start: int, count: int, dims: int) -> np.ndarray:
    """Points start … start+count-1 of the Halton sequence in [0, 1)^dims."""
    index = np.arange(start + 1, start + count + 1)
    out = np.zeros((count, dims))
    for d in range(dims):
        base, f, i = _PRIMES[d], 1.0, index.copy()
        while i.any():
            f /= base
            out[:, d] += f * (i % base)
            i //= base
    return out


def joint_ranges(model: RobotModel) -> np.ndarray:
    """(dof, 2) ranges sampled: the limits, continuous ±2π joints cut to ±π (beyond,
    the same pictures repeat with other labels)."""
    return np.clip(model.joint_limits, -np.pi, np.pi)


def collision_free(model: RobotModel, qs: np.ndarray, clearance: float = 0.005) -> np.ndarray:
    """(K,) True where a configuration has no self-collision (the core's check on padded
    link bodies, adjacent links excluded) and the arm stays above the table top (z = 0
    of the base frame): every link body that moves up or down keeps `clearance` above
    it, except the first such link (a UR's upper arm, the iiwa's and Panda's link 2),
    which turns about a pivot above the table and whose fitted body, fatter than the
    link, would touch it when upright: its axis must stay above the table. Links that
    only turn about the vertical stand on the table as mounted."""
    qs = np.atleast_2d(qs)
    ok = ~np.asarray(model.self_collisions(qs), dtype=bool).reshape(len(qs))
    root = np.linalg.inv(model.base)
    probe = model.random_configurations(16, seed=0)
    first = True
    for _, radius, z in _body_heights(model, root, np.concatenate([probe, qs])):
        z_probe, z_qs = z[:, : len(probe)], z[:, len(probe) :]
        if np.ptp(z_probe, axis=1).max() < 1e-9:
            continue  # this body never moves vertically
        ok &= (z_qs.min(axis=0) - (0.0 if first else radius)) > clearance
        first = False
    return ok


def _body_heights(model: RobotModel, root: np.ndarray, qs: np.ndarray):
    """(link, radius, z of both ends of its axis (2, K)) of each link body, in chain
    order, at configurations qs."""
    poses = root[None, None] @ model.fk(qs).reshape(len(qs), -1, 4, 4)
    for link, body in enumerate(model.link_bodies):
        if body is None:
            continue
        a, b, radius, _ = body
        z = np.stack([poses[:, link, 2, :3] @ np.asarray(end) + poses[:, link, 2, 3] for end in (a, b)])
        yield link, radius, z


def sweep(model: RobotModel, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` collision-free configurations spread over the joint ranges together: a
    Halton sequence shifted by a random vector (mod 1), filtered."""
    ranges = joint_ranges(model)
    shift = rng.random(model.dof)
    found: list[np.ndarray] = []
    start, have = int(rng.integers(0, 1000)), 0
    while have < count:
        u = (_halton(start, 4096, model.dof) + shift) % 1.0
        qs = ranges[:, 0] + u * (ranges[:, 1] - ranges[:, 0])
        good = qs[collision_free(model, qs)]
        found.append(good)
        have += len(good)
        start += 4096
        if start > 4_000_000:
            raise RuntimeError(f"{model.name}: found only {have} collision-free configurations of {count}")
    return np.concatenate(found)[:count]


def random_state(model: RobotModel, rng: np.random.Generator) -> np.ndarray:
    """One collision-free configuration uniform over the joint ranges."""
    ranges = joint_ranges(model)
    for _ in range(1000):
        qs = rng.uniform(ranges[:, 0], ranges[:, 1], (64, model.dof))
        good = np.flatnonzero(collision_free(model, qs))
        if len(good):
            return qs[good[0]]
    raise RuntimeError(f"{model.name}: no collision-free configuration in 64,000 draws")


# --- rendering ---------------------------------------------------------------------


@dataclass
class RenderedSample:
    """A sample and what made it (for checks): the camera pose and intrinsics, the
    joint state, the keypoints in the world, pybullet's raw segmentation and the robot's
    body id."""

    sample: Sample
    world_from_camera: np.ndarray
    K: np.ndarray
    q: np.ndarray
    keypoints_world: np.ndarray
    segmentation: np.ndarray
    robot_body: int
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Robot:
    name: str
    body: int
    model: RobotModel
    joint_ids: list[int]
    keypoint_links: list[int]
    keypoint_offsets: np.ndarray
    #: pybullet link index + 1 → earcore link index + 1 (0: not a robot link)
    lut: np.ndarray
    #: pybullet link indices to colour (root -1 first)
    links: list[int]
    reach: float


def _quiet_client():
    """A DIRECT pybullet client, without pybullet's lines on import and connect (dataset
    workers would print them once each)."""
    from earcore.sim.cell import _pybullet, _quiet_stdout

    pybullet, BulletClient = _pybullet()
    with _quiet_stdout():
        return BulletClient(pybullet.DIRECT)


class RobotImageRenderer:
    """One pybullet world (DIRECT) rendering samples of a dataset; one per worker."""

    def __init__(self, options: RobotImageOptions) -> None:
        self.options = options.validate()
        self.p = self._client = _quiet_client()
        self.scene = ImageScene(self.p, options.seed, options.textures)
        self.robot: _Robot | None = None
        self.classes = {r: i for i, r in enumerate(options.robots)}
        self.header: list[str] = []
        self._sweeps: dict[tuple[str, int], np.ndarray] = {}
        self._sensor = SENSORS["kinect_v2"]
        models = {r: load(r) for r in options.robots}
        self.max_dof = max(m.dof for m in models.values())
        self.num_keypoints = max(len(keypoint_names(m, r)) for r, m in models.items())
        self.header = columns(self.max_dof, self.num_keypoints)

    def close(self) -> None:
        self.p.disconnect()

    def _use(self, robot: str) -> _Robot:
        if self.robot is not None and self.robot.name == robot:
            return self.robot
        p = self.p
        if self.robot is not None:
            p.removeBody(self.robot.body)  # a hidden robot still costs render time
        if self.options.meshes == "collision":
            import tempfile

            from earcore.urdf import collision_as_visual

            with tempfile.TemporaryDirectory(prefix="earcore-robot-") as folder:
                body = p.loadURDF(str(collision_as_visual(urdf_path(robot), folder)), useFixedBase=True)
        else:
            body = p.loadURDF(str(urdf_path(robot)), useFixedBase=True)
        model = load(robot)
        model.base = self._root_frame(body)
        infos = [p.getJointInfo(body, j) for j in range(p.getNumJoints(body))]
        by_joint = {i[1].decode(): i[0] for i in infos}
        by_link = {i[12].decode(): i[0] for i in infos}
        by_link[p.getBodyInfo(body)[0].decode()] = -1
        lut = np.zeros(len(infos) + 1, dtype=np.uint8)
        for name, index in by_link.items():
            lut[index + 1] = model.link_names.index(name) + 1
        keypoint_links, offsets = keypoint_frames(model, robot)
        poses = model.fk(model.random_configurations(256, seed=0))
        tip = poses[:, keypoint_links[-1]] @ offsets[-1]
        reach = float(np.linalg.norm(tip[:, :3] - model.base[:3, 3], axis=1).max())
        self.robot = _Robot(
            robot,
            body,
            model,
            [by_joint[n] for n in model.joint_names],
            keypoint_links,
            offsets,
            lut,
            [-1, *range(len(infos))],
            reach,
        )
        return self.robot

    def _root_frame(self, body: int) -> np.ndarray:
        """world_from_root of the loaded robot (pybullet reports the inertial frame)."""
        p = self.p
        pos, orn = p.getBasePositionAndOrientation(body)
        info = p.getDynamicsInfo(body, -1)
        pos, orn = p.multiplyTransforms(pos, orn, *p.invertTransform(info[3], info[4]))
        m = np.eye(4)
        m[:3, :3] = np.reshape(p.getMatrixFromQuaternion(orn), (3, 3))
        m[:3, 3] = pos
        return m

    # --- the random draws ----------------------------------------------------------

    def _intrinsics(self, rng: np.random.Generator) -> np.ndarray:
        """The Kinect V2's field of view (registered colour, as the papers' 512×424
        images) at this resolution; focal lengths ±3 %, principal point ±1.5 %."""
        w, h = self.options.width, self.options.height
        s = self._sensor
        f = rng.uniform(0.97, 1.03)
        fx = 0.5 * w / np.tan(np.radians(s.fov_h_deg) / 2) * f * rng.uniform(0.995, 1.005)
        fy = 0.5 * h / np.tan(np.radians(s.fov_v_deg) / 2) * f * rng.uniform(0.995, 1.005)
        cx = (w - 1) / 2 + rng.uniform(-0.015, 0.015) * w
        cy = (h - 1) / 2 + rng.uniform(-0.015, 0.015) * h
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    def _camera(self, rng: np.random.Generator, robot: _Robot, aim: np.ndarray) -> np.ndarray:
        """world_from_camera (OpenCV axes) of a hand-held camera: 0.7-1.2 reaches from
        the aim point (near `aim`, off by ~10 % of the reach), held 0.15-1.2 m above the
        table top, any side of the robot, rolled by up to ±8°, and moved back horizontally
        until it is 1.2 reaches from the base (out of the arm's way)."""
        reach = robot.reach
        target = aim + rng.normal(0.0, 0.1 * reach, 3)
        distance = reach * rng.uniform(*DISTANCE)
        height = rng.uniform(0.15, 1.2)
        dz = height - target[2]
        horizontal = np.sqrt(max(distance**2 - dz**2, (0.3 * distance) ** 2))
        azimuth = rng.uniform(0, 2 * np.pi)
        eye = target + np.array([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), dz])
        # Out of the arm's reach (a robot sweeping its joints would strike a camera inside
        # it), moved back horizontally: the held height stays above the table.
        while np.linalg.norm(eye) < CLEARANCE * reach:
            eye[:2] = target[:2] + 1.05 * (eye[:2] - target[:2])
        pose = robot.model.base @ look_at(eye, target)
        roll = np.eye(4)
        roll[:3, :3] = axis_angle_matrix([0, 0, 1], rng.uniform(-np.radians(8), np.radians(8)))
        return pose @ roll

    def _aim(self, robot: _Robot, qs: np.ndarray) -> np.ndarray:
        """Where the camera looks (base frame): the mean of the keypoints over `qs`."""
        pts = self._keypoints(robot, qs)
        return np.linalg.inv(robot.model.base)[:3] @ np.append(pts.reshape(-1, 3).mean(0), 1.0)

    def _keypoints(self, robot: _Robot, qs: np.ndarray) -> np.ndarray:
        """(K, n, 3) keypoints in the world for configurations (K, dof)."""
        return keypoint_positions(robot.model, (robot.keypoint_links, robot.keypoint_offsets), np.atleast_2d(qs))

    def _recording_sweep(self, robot: _Robot, recording: int) -> np.ndarray:
        key = (robot.name, recording)
        if key not in self._sweeps:
            size = self.options.recordings()[robot.name][recording]
            rng = np.random.default_rng([self.options.seed, _code(robot.name), 3, recording])
            self._sweeps[key] = sweep(robot.model, size, rng)
        return self._sweeps[key]

    # --- one sample ----------------------------------------------------------------

    def render(self, spec: SampleSpec) -> RenderedSample:
        o = self.options
        robot = self._use(spec.robot)
        code = _code(spec.robot)
        if o.mode == "recordings":
            q = self._recording_sweep(robot, spec.recording)[spec.frame]
            scene_rng = np.random.default_rng([o.seed, code, 1, spec.recording])
            frame_rng = np.random.default_rng([o.seed, code, 2, spec.recording, spec.frame])
            poses_seen = self._recording_sweep(robot, spec.recording)[:64]
        else:
            scene_rng = frame_rng = np.random.default_rng([o.seed, code, 4, spec.recording])
            q = random_state(robot.model, scene_rng)
            poses_seen = q[None]
        K = self._intrinsics(scene_rng)
        world_from_camera = self._camera(scene_rng, robot, self._aim(robot, poses_seen))
        camera_xy = (np.linalg.inv(robot.model.base) @ world_from_camera)[:2, 3]
        layout = draw_layout(scene_rng, robot.reach, camera_xy, len(robot.links), len(self.scene.textures), distractors=o.distractors, person=0.0, shadow=o.shadow)
        if frame_rng.random() < o.person:
            layout.person = draw_person(frame_rng, robot.reach, camera_xy)
        p = self.p
        for j, value in zip(robot.joint_ids, q):
            p.resetJointState(robot.body, j, float(value))
        self.scene.apply(layout, robot.body, robot.links)
        w, h = o.width, o.height
        _, _, rgba, _, seg = p.getCameraImage(
            w,
            h,
            opengl_view(world_from_camera),
            opengl_projection(K, w, h, NEAR, FAR),
            renderer=p.ER_TINY_RENDERER,
            flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
            **layout.lighting.arguments(),
        )
        rgb = np.ascontiguousarray(np.reshape(rgba, (h, w, 4))[..., :3], dtype=np.uint8)
        seg = np.reshape(seg, (h, w)).astype(np.int64)
        mine = (seg >= 0) & ((seg & 0xFFFFFF) == robot.body)
        links = np.where(mine, robot.lut[np.clip(seg >> 24, 0, len(robot.lut) - 1)], 0).astype(np.uint8)
        world = self._keypoints(robot, q)[0]
        row = self._labels(spec, robot, q, K, world_from_camera, world, links)
        return RenderedSample(Sample(spec.key, {"rgb": rgb, "links": links}, row), world_from_camera, K, q, world, seg, robot.body, {"layout": layout})

    def _labels(self, spec, robot: _Robot, q, K, world_from_camera, world, links) -> dict[str, Any]:
        w, h = self.options.width, self.options.height
        camera_from_world = np.linalg.inv(world_from_camera)
        cam = world @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        z = cam[:, 2]
        safe = np.where(np.abs(z) < 1e-6, 1e-6, z)  # behind the camera: in_image says so
        u = K[0, 0] * cam[:, 0] / safe + K[0, 2]
        v = K[1, 1] * cam[:, 1] / safe + K[1, 2]
        inside = (z > NEAR) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        base = camera_from_world @ robot.model.base
        qx, qy, qz, qw = quaternion(base[:3, :3])
        row: dict[str, Any] = {
            "robot": spec.robot,
            "robot_class": self.classes[spec.robot],
            "recording": spec.recording,
            "split": spec.split,
            "width": w,
            "height": h,
            "fx": K[0, 0],
            "fy": K[1, 1],
            "cx": K[0, 2],
            "cy": K[1, 2],
            "base_x": base[0, 3],
            "base_y": base[1, 3],
            "base_z": base[2, 3],
            "base_qw": qw,
            "base_qx": qx,
            "base_qy": qy,
            "base_qz": qz,
            "coverage": float((links > 0).mean()),
        }
        for i, value in enumerate(q):
            row[f"q{i}"] = float(value)
        for i in range(len(world)):
            row.update({f"kp{i}_x": cam[i, 0], f"kp{i}_y": cam[i, 1], f"kp{i}_z": cam[i, 2], f"kp{i}_u": u[i], f"kp{i}_v": v[i], f"kp{i}_in_image": int(inside[i])})
        return row


# --- workers -------------------------------------------------------------------------


def generate_shard(options: RobotImageOptions, index: int, folder: str | Path) -> int:
    """Render shard `index` of the dataset and write it into `folder` (atomically);
    returns its number of images. The worker's renderer is kept for its next shard."""
    return render_shard(options, RobotImageRenderer, plan_shards(options)[index], index, folder)
