"""The randomised surroundings of a labelled robot image: a table or a stand under the
robot, a floor and back walls with random colours and procedural textures, distractor
objects, a person's arm, the light, and the robot's link colours.

Every body is made once per world (`ImageScene`); a sample only moves and recolours
them (`SceneLayout`, drawn from a seed), so rendering thousands of images creates no
bodies. Every sample sets every property, so an image depends on its own layout only.
"""

from __future__ import annotations

import colorsys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from earcore.sim.person import HumanArm

__all__ = ["ImageScene", "Lighting", "SceneLayout", "draw_layout", "draw_person", "load_textures", "procedural_texture", "random_colour"]

#: Where unused bodies wait (far below the floor, never in view).
HIDDEN = (0.0, 0.0, -60.0)
#: Table tops (x, y half sizes in m); index len(TABLES) is the stand.
TABLES = ((0.8, 0.6), (0.6, 0.45), (1.0, 0.7))
STAND = (0.2, 0.2)
#: Distractor shapes: (kind, size) with size = half extents of a box, (radius, length)
#: of a cylinder, radius of a sphere.
DISTRACTORS: tuple[tuple[str, Any], ...] = (
    ("box", (0.08, 0.06, 0.05)),
    ("box", (0.15, 0.1, 0.12)),
    ("box", (0.04, 0.2, 0.03)),
    ("cylinder", (0.05, 0.2)),
    ("cylinder", (0.1, 0.12)),
    ("sphere", 0.06),
    ("sphere", 0.12),
)
SKIN = ((0.87, 0.68, 0.55), (0.75, 0.55, 0.42), (0.55, 0.38, 0.27), (0.36, 0.24, 0.17), (0.95, 0.8, 0.7))


@dataclass
class Lighting:
    """getCameraImage's light: direction (towards the light), colour and coefficients."""

    direction: tuple[float, float, float] = (0.5, 0.3, 1.0)
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.5
    diffuse: float = 0.6
    specular: float = 0.1
    shadow: bool = False

    def arguments(self) -> dict:
        return {
            "lightDirection": list(self.direction),
            "lightColor": list(self.colour),
            "lightAmbientCoeff": self.ambient,
            "lightDiffuseCoeff": self.diffuse,
            "lightSpecularCoeff": self.specular,
            "shadow": int(self.shadow),
        }


@dataclass
class SceneLayout:
    """Everything random about one image's surroundings (positions in the robot's base
    frame, colours RGB in [0, 1]; a texture is an index into the scene's pool, -1 none)."""

    table: int = 0
    table_offset: tuple[float, float] = (0.0, 0.0)
    table_colour: tuple[float, float, float] = (0.55, 0.45, 0.35)
    table_texture: int = -1
    floor_depth: float = 0.75
    floor_colour: tuple[float, float, float] = (0.7, 0.7, 0.7)
    floor_texture: int = -1
    #: (x, y, yaw, colour, texture) per back wall; empty: none.
    walls: list[tuple[float, float, float, tuple[float, float, float], int]] = field(default_factory=list)
    #: (pool index, position, colour) of the distractors in view.
    distractors: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]] = field(default_factory=list)
    #: The person's shoulder and hand positions and skin / sleeve colours; None: no person.
    person: tuple[tuple[float, ...], tuple[float, ...], tuple[float, float, float], tuple[float, float, float]] | None = None
    #: One colour per robot link (pybullet link index order, root first).
    link_colours: list[tuple[float, float, float]] = field(default_factory=list)
    lighting: Lighting = field(default_factory=Lighting)


def random_colour(rng: np.random.Generator, saturation=(0.0, 0.8), value=(0.15, 0.95)) -> tuple[float, float, float]:
    r, g, b = colorsys.hsv_to_rgb(rng.random(), rng.uniform(*saturation), rng.uniform(*value))
    return float(r), float(g), float(b)


def load_textures(client, seed: int, count: int) -> list[int]:
    """`count` procedural textures loaded into a pybullet world (their ids); the same
    seed gives the same pool in every worker."""
    from earcore.learning import png

    rng = np.random.default_rng([seed, 51])
    with tempfile.TemporaryDirectory(prefix="earcore-textures-") as folder:
        out = []
        for i in range(count):
            path = Path(folder) / f"texture-{i}.png"
            png.write(path, procedural_texture(rng))
            out.append(client.loadTexture(str(path)))
    return out


def procedural_texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    """A (size, size, 3) uint8 texture: checkers, stripes, wood-like grain, speckle or
    blotches, in two random colours."""
    a, b = (np.array(random_colour(rng)) for _ in range(2))
    y, x = np.mgrid[0:size, 0:size] / size
    kind = rng.integers(5)
    if kind == 0:
        n = rng.integers(2, 9)
        t = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(float)
    elif kind == 1:
        angle, n = rng.uniform(0, np.pi), rng.integers(2, 12)
        t = (np.sin(2 * np.pi * n * (x * np.cos(angle) + y * np.sin(angle))) > 0).astype(float)
    elif kind == 2:
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.integers(3, 10) * x + 0.6 * np.sin(2 * np.pi * rng.integers(1, 4) * y)))
    elif kind == 3:
        t = rng.random((size, size))
    else:
        coarse = rng.random((8, 8))
        t = np.kron(coarse, np.ones((size // 8, size // 8)))
    image = a[None, None] * (1 - t[..., None]) + b[None, None] * t[..., None]
    return np.clip(np.rint(255 * image), 0, 255).astype(np.uint8)


def draw_layout(
    rng: np.random.Generator, reach: float, camera_xy: np.ndarray, links: int, textures: int, *, distractors: bool = True, person: float = 0.3, shadow: float = 0.3
) -> SceneLayout:
    """A random layout around a robot of this reach (m) seen from `camera_xy` (base
    frame): `person` and `shadow` are the probabilities of an arm in view and of shadows."""
    layout = SceneLayout()
    layout.table = int(rng.integers(len(TABLES) + 1)) if rng.random() < 0.85 else len(TABLES)
    half = STAND if layout.table == len(TABLES) else TABLES[layout.table]
    # The robot stands somewhere on the top, at least 15 cm from its edges.
    layout.table_offset = tuple(float(rng.uniform(-max(h - 0.15, 0.0), max(h - 0.15, 0.0))) for h in half)  # type: ignore[assignment]
    layout.table_colour = random_colour(rng)
    layout.table_texture = int(rng.integers(textures)) if rng.random() < 0.5 else -1
    layout.floor_depth = float(rng.uniform(0.7, 0.95))
    layout.floor_colour = random_colour(rng, value=(0.25, 0.9))
    layout.floor_texture = int(rng.integers(textures)) if rng.random() < 0.6 else -1
    # Walls behind the robot as the camera sees it.
    away = -camera_xy / max(float(np.linalg.norm(camera_xy)), 1e-9)
    for _ in range(int(rng.integers(1, 3))):
        turn = rng.uniform(-1.0, 1.0)
        c, s = np.cos(turn), np.sin(turn)
        d = np.array([c * away[0] - s * away[1], s * away[0] + c * away[1]])
        centre = d * rng.uniform(1.2, 3.0) * max(reach, 0.6)
        layout.walls.append(
            (float(centre[0]), float(centre[1]), float(np.arctan2(d[1], d[0])), random_colour(rng), int(rng.integers(textures)) if rng.random() < 0.5 else -1)
        )
    if distractors:
        count = int(rng.integers(0, 6))
        for index in rng.permutation(len(DISTRACTORS))[:count]:
            radius, angle = rng.uniform(0.3, 1.3) * reach, rng.uniform(0, 2 * np.pi)
            on_table = rng.random() < 0.6
            z = 0.0 if on_table else -layout.floor_depth
            layout.distractors.append((int(index), (float(radius * np.cos(angle)), float(radius * np.sin(angle)), z), random_colour(rng)))
    if rng.random() < person:
        layout.person = draw_person(rng, reach, camera_xy)
    # Robot links: a main colour and an accent (joint covers, the wrist), each link jittered.
    main, accent = random_colour(rng, (0.0, 0.6), (0.3, 1.0)), random_colour(rng)
    for _ in range(links):
        base = accent if rng.random() < 0.3 else main
        r, g, b = (float(v) for v in np.clip(np.array(base) + rng.normal(0, 0.04, 3), 0, 1))
        layout.link_colours.append((r, g, b))
    elevation, azimuth = rng.uniform(0.3, 1.4), rng.uniform(0, 2 * np.pi)
    layout.lighting = Lighting(
        direction=(float(np.cos(elevation) * np.cos(azimuth)), float(np.cos(elevation) * np.sin(azimuth)), float(np.sin(elevation))),
        colour=tuple(float(v) for v in rng.uniform(0.8, 1.0, 3)),  # type: ignore[arg-type]
        ambient=float(rng.uniform(0.3, 0.7)),
        diffuse=float(rng.uniform(0.3, 0.8)),
        specular=float(rng.uniform(0.0, 0.3)),
        shadow=bool(rng.random() < shadow),
    )
    return layout


def draw_person(rng: np.random.Generator, reach: float, camera_xy: np.ndarray):
    """A person between the camera and the robot, reaching towards the robot from one
    side: (shoulder, hand, skin colour, sleeve colour), base frame."""
    towards = np.asarray(camera_xy, dtype=np.float64) / max(float(np.linalg.norm(camera_xy)), 1e-9)
    side = np.array([-towards[1], towards[0]]) * rng.choice([-1.0, 1.0])
    along = rng.uniform(0.25, 0.6) * reach
    shoulder = np.array([*(towards * along + side * rng.uniform(0.35, 0.6)), rng.uniform(0.2, 0.6)])
    hand = np.array([*(towards * rng.uniform(0.05, 0.3) * reach + side * rng.uniform(-0.1, 0.2)), rng.uniform(0.05, 0.5)])
    skin = SKIN[int(rng.integers(len(SKIN)))]
    sleeve = random_colour(rng) if rng.random() < 0.7 else skin
    return tuple(shoulder.tolist()), tuple(hand.tolist()), skin, sleeve


class ImageScene:
    """The bodies around the robot in one pybullet world, made once (`texture_seed`
    fixes the texture pool, so every worker's pool is the same)."""

    def __init__(self, client, texture_seed: int, textures: int = 8) -> None:
        self.p = p = client
        self.tables = [self._box((hx, hy, 0.6)) for hx, hy in (*TABLES, STAND)]
        self.floor = self._box((8.0, 8.0, 0.01))
        self.walls = [self._box((0.02, 3.0, 1.5)) for _ in range(2)]
        self.distractors = []
        for kind, size in DISTRACTORS:
            if kind == "box":
                shape = p.createVisualShape(p.GEOM_BOX, halfExtents=list(size))
            elif kind == "cylinder":
                shape = p.createVisualShape(p.GEOM_CYLINDER, radius=size[0], length=size[1])
            else:
                shape = p.createVisualShape(p.GEOM_SPHERE, radius=size)
            self.distractors.append(p.createMultiBody(0, -1, shape, HIDDEN))
        self.arm = HumanArm(p, (0.0, 0.0, -60.0), (0.0, 0.3, -60.0), [], arrive=0.0)
        self.textures = load_textures(p, texture_seed, textures)

    def _box(self, half) -> int:
        shape = self.p.createVisualShape(self.p.GEOM_BOX, halfExtents=list(half))
        return self.p.createMultiBody(0, -1, shape, HIDDEN)

    def _look(self, body: int, colour, texture: int) -> None:
        self.p.changeVisualShape(body, -1, rgbaColor=[*colour, 1.0], textureUniqueId=self.textures[texture] if texture >= 0 else -1)

    def apply(self, layout: SceneLayout, robot: int, robot_links: list[int]) -> None:
        """Move and colour every body as `layout` says."""
        p = self.p
        for i, body in enumerate(self.tables):
            if i == layout.table:
                ox, oy = layout.table_offset
                p.resetBasePositionAndOrientation(body, [-ox, -oy, -0.6], [0, 0, 0, 1])
                self._look(body, layout.table_colour, layout.table_texture)
            else:
                p.resetBasePositionAndOrientation(body, HIDDEN, [0, 0, 0, 1])
        p.resetBasePositionAndOrientation(self.floor, [0, 0, -layout.floor_depth - 0.01], [0, 0, 0, 1])
        self._look(self.floor, layout.floor_colour, layout.floor_texture)
        for i, body in enumerate(self.walls):
            if i < len(layout.walls):
                x, y, yaw, colour, texture = layout.walls[i]
                quat = p.getQuaternionFromEuler([0, 0, yaw])
                p.resetBasePositionAndOrientation(body, [x, y, 1.5 - layout.floor_depth], quat)
                self._look(body, colour, texture)
            else:
                p.resetBasePositionAndOrientation(body, HIDDEN, [0, 0, 0, 1])
        placed = {index: (position, colour) for index, position, colour in layout.distractors}
        for i, body in enumerate(self.distractors):
            if i in placed:
                (x, y, z), colour = placed[i]
                kind, size = DISTRACTORS[i]
                lift = size[2] if kind == "box" else (size[1] / 2 if kind == "cylinder" else size)
                p.resetBasePositionAndOrientation(body, [x, y, z + lift], [0, 0, 0, 1])
                p.changeVisualShape(body, -1, rgbaColor=[*colour, 1.0])
            else:
                p.resetBasePositionAndOrientation(body, HIDDEN, [0, 0, 0, 1])
        if layout.person is None:
            self.arm.shoulder = np.array([0.0, 0.0, -60.0])
            self.arm.rest = np.array([0.0, 0.3, -60.0])
        else:
            shoulder, hand, skin, sleeve = layout.person
            self.arm.shoulder, self.arm.rest = np.array(shoulder), np.array(hand)
            for body, colour in zip(self.arm.bodies, (sleeve, sleeve, skin)):
                p.changeVisualShape(body, -1, rgbaColor=[*colour, 1.0])
        self.arm.set_time(0.0)
        for link, colour in zip(robot_links, layout.link_colours):
            p.changeVisualShape(robot, link, rgbaColor=[*colour, 1.0])
