"""The parts of the RoboCup@Work set, built as triangle meshes from their dimensions.

Thirteen types after the set the IROS 2018 and AAMAS 2019 papers detect: aluminium
profiles 20×20 and 40×40 mm in black and grey, an M20×100 bolt, M20 and M30 nuts, a
ring (R20), an axis, a bearing, a bearing box, a distance tube and a motor. The papers
name the parts but give no drawings; the dimensions here are those of the standard
items the names denote (DIN 934 nuts, ISO 4017 bolt, 6202-size bearing), the rest
chosen to look like the competition's pieces (docs/parts.md lists them).

Each part is a union of pieces that touch but do not overlap (so volumes add): prisms
of a round, hexagonal or square cross-section, optionally with a round bore, and boxes.
A part is built in its rest frame: lying on the table (z = 0 its lowest point), its
longest horizontal extent along x. The centre of gravity (uniform density) comes from
the closed mesh by the divergence theorem.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

from earcore.mesh import Mesh

__all__ = ["PARTS", "Mesh", "Part", "Piece", "part", "part_names"]

#: Points around a prism's cross-section (every 5°: the corners of hexagons and squares
#: fall on them, so those outlines are exact).
SEGMENTS = 72


@dataclass(frozen=True)
class Piece:
    """A prism along its local z from 0 to `length` (`shape` "round" of radius
    `size`, "hex" of across-flats `2·size`, "square" of side `2·size`, each with an
    optional round `bore` radius, the outline turned by `turn` rad about the prism's
    axis), or a "box" of half extents `half`; placed in the part by `origin` (m) and
    `axis` ("x", "y" or "z": where the prism's z points)."""

    shape: str
    size: float = 0.0
    length: float = 0.0
    bore: float = 0.0
    half: tuple[float, float, float] = (0.0, 0.0, 0.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: str = "z"
    turn: float = 0.0


@dataclass(frozen=True)
class Part:
    """A part type: its pieces (rest frame), colour range (HSV: hue, saturation and
    value bounds) and whether its outline is round about the vertical (then it has no
    grasp axis of its own)."""

    name: str
    description: str
    pieces: tuple[Piece, ...]
    hsv: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
    round: bool = False
    mesh: Mesh = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "mesh", _union([_piece_mesh(p) for p in self.pieces]))

    def colour(self, rng: np.random.Generator) -> tuple[float, float, float]:
        """A random RGB colour in [0, 1] within the type's range."""
        hue, saturation, value = self.hsv
        r, g, b = colorsys.hsv_to_rgb(rng.uniform(*hue) % 1.0, rng.uniform(*saturation), rng.uniform(*value))
        return float(r), float(g), float(b)

    @property
    def centre_of_gravity(self) -> np.ndarray:
        """(3,) in the rest frame (m)."""
        return self.mesh.volume_and_centroid()[1]

    @property
    def extent(self) -> np.ndarray:
        """(3,) size of the axis-aligned bounds in the rest frame (m)."""
        return np.ptp(self.mesh.vertices, axis=0)


def _outline(shape: str, size: float, turn: float = 0.0) -> np.ndarray:
    """(SEGMENTS, 2) points of the cross-section's outline, counter-clockwise."""
    theta = np.arange(SEGMENTS) * 2 * np.pi / SEGMENTS
    if shape == "round":
        r = np.full(SEGMENTS, size)
    elif shape in ("hex", "square"):
        n, phase = (6, turn) if shape == "hex" else (4, np.pi / 4 + turn)
        sector = 2 * np.pi / n
        r = size / np.cos(np.mod(theta - phase, sector) - sector / 2)  # `size` is the apothem
    else:
        raise ValueError(f"unknown cross-section {shape!r}")
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1)


def _prism(shape: str, size: float, length: float, bore: float, turn: float = 0.0) -> Mesh:
    outer = _outline(shape, size, turn)
    n = len(outer)
    ring = np.arange(n)
    nxt = (ring + 1) % n
    if bore > 0:
        inner = _outline("round", bore)
        # vertices: outer bottom, outer top, inner bottom, inner top
        v = np.concatenate([np.c_[outer, np.zeros(n)], np.c_[outer, np.full(n, length)], np.c_[inner, np.zeros(n)], np.c_[inner, np.full(n, length)]])
        ob, ot, ib, it = ring, ring + n, ring + 2 * n, ring + 3 * n
        tris = [
            np.c_[ob, ob[nxt], ot[nxt]], np.c_[ob, ot[nxt], ot],  # outer wall, facing out
            np.c_[ib, it[nxt], ib[nxt]], np.c_[ib, it, it[nxt]],  # bore wall, facing the axis
            np.c_[ot, ot[nxt], it[nxt]], np.c_[ot, it[nxt], it],  # top annulus, up
            np.c_[ob, ib[nxt], ob[nxt]], np.c_[ob, ib, ib[nxt]],  # bottom annulus, down
        ]  # fmt: skip
    else:
        v = np.concatenate([np.c_[outer, np.zeros(n)], np.c_[outer, np.full(n, length)], [[0, 0, 0], [0, 0, length]]])
        ob, ot, cb, ct = ring, ring + n, 2 * n, 2 * n + 1
        tris = [
            np.c_[ob, ob[nxt], ot[nxt]], np.c_[ob, ot[nxt], ot],
            np.c_[np.full(n, ct), ot, ot[nxt]],
            np.c_[np.full(n, cb), ob[nxt], ob],
        ]  # fmt: skip
    return Mesh(v.astype(np.float64), np.concatenate(tris).astype(np.int64))


def _box(half: tuple[float, float, float]) -> Mesh:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * np.asarray(half)
    # corner index = 4·(x>0) + 2·(y>0) + (z>0); two outward triangles per face
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]
    return Mesh(corners, np.array(tris, dtype=np.int64))


#: Rotations taking a prism's z to the named axis (right-handed).
_AXES = {
    "z": np.eye(3),
    "x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


def _piece_mesh(piece: Piece) -> Mesh:
    mesh = _box(piece.half) if piece.shape == "box" else _prism(piece.shape, piece.size, piece.length, piece.bore, piece.turn)
    return Mesh(mesh.vertices @ _AXES[piece.axis].T + np.asarray(piece.origin), mesh.triangles)


def _union(meshes: list[Mesh]) -> Mesh:
    """The pieces in one mesh, moved so the part rests on z = 0 centred over x = y = 0."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    v = np.concatenate([m.vertices for m in meshes])
    t = np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)])
    lo, hi = v.min(0), v.max(0)
    v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return Mesh(v, t)


def _lying(shape: str, size: float, length: float, bore: float = 0.0) -> Piece:
    """A prism lying along x on a face (hex and square) or its side (round)."""
    return Piece(shape, size, length, bore, axis="x")


_BLACK = ((0.0, 1.0), (0.0, 0.15), (0.06, 0.2))
_GREY = ((0.55, 0.65), (0.0, 0.08), (0.55, 0.8))
_STEEL = ((0.55, 0.62), (0.02, 0.12), (0.45, 0.7))

PARTS: tuple[Part, ...] = (
    Part("F20_20_B", "small black aluminium profile, 20×20×100 mm", (_lying("square", 0.010, 0.100, 0.0021),), _BLACK),
    Part("F20_20_G", "small grey aluminium profile, 20×20×100 mm", (_lying("square", 0.010, 0.100, 0.0021),), _GREY),
    Part("S40_40_B", "large black aluminium profile, 40×40×100 mm", (_lying("square", 0.020, 0.100, 0.0042),), _BLACK),
    Part("S40_40_G", "large grey aluminium profile, 40×40×100 mm", (_lying("square", 0.020, 0.100, 0.0042),), _GREY),
    Part(
        "M20_100",
        "M20×100 hexagon bolt (ISO 4017: 30 mm across flats, 12.5 mm head)",
        (Piece("hex", 0.015, 0.0125, axis="x", turn=np.pi / 6), Piece("round", 0.010, 0.100, origin=(0.0125, 0.0, 0.0), axis="x")),
        _STEEL,
    ),
    Part("M20", "M20 hexagon nut (DIN 934: 30 mm across flats, 16 mm)", (Piece("hex", 0.015, 0.016, 0.010),), _STEEL, round=True),
    Part("M30", "M30 hexagon nut (DIN 934: 46 mm across flats, 24 mm)", (Piece("hex", 0.023, 0.024, 0.015),), _STEEL, round=True),
    Part(
        "R20",
        "plastic ring, 40 mm outside, 20 mm bore, 10 mm",
        (Piece("round", 0.020, 0.010, 0.010),),
        ((0.0, 1.0), (0.0, 0.1), (0.1, 0.3)),
        round=True,
    ),
    Part(
        "Axis",
        "stepped steel axis, Ø 16 mm with Ø 12 mm journals, 100 mm",
        (
            Piece("round", 0.006, 0.020, axis="x"),
            Piece("round", 0.008, 0.060, origin=(0.020, 0.0, 0.0), axis="x"),
            Piece("round", 0.006, 0.020, origin=(0.080, 0.0, 0.0), axis="x"),
        ),
        _STEEL,
    ),
    Part("Bearing", "ball bearing, 6202 size: 35 mm outside, 15 mm bore, 11 mm", (Piece("round", 0.0175, 0.011, 0.0075),), _STEEL, round=True),
    Part(
        "Bearing_Box",
        "bearing box: a 64×32×10 mm foot under a Ø 32 mm housing with a 17 mm bore",
        (
            Piece("box", half=(0.032, 0.016, 0.005), origin=(0.0, 0.0, 0.005)),
            Piece("round", 0.016, 0.032, 0.0085, origin=(0.0, -0.016, 0.026), axis="y"),
        ),
        ((0.55, 0.7), (0.0, 0.5), (0.3, 0.75)),
    ),
    Part("Distance_Tube", "small grey aluminium ring (distance tube), 20 mm outside, 16 mm bore, 12 mm", (Piece("round", 0.010, 0.012, 0.008),), _GREY, round=True),
    Part(
        "Motor",
        "DC motor: Ø 40×55 mm body, Ø 6×15 mm shaft",
        (Piece("round", 0.020, 0.055, axis="x"), Piece("round", 0.003, 0.015, origin=(0.055, 0.0, 0.0), axis="x")),
        ((0.0, 1.0), (0.0, 0.2), (0.08, 0.35)),
    ),
)

_BY_NAME = {p.name: p for p in PARTS}


def part_names() -> list[str]:
    return [p.name for p in PARTS]


def part(name: str) -> Part:
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown part {name!r}; known: {', '.join(_BY_NAME)}") from None
