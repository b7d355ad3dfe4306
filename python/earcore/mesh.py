"""Closed triangle meshes built from outlines: the solid's volume and centre of gravity,
planar faces with holes, and prisms (an outline extruded, with blind holes).

    face = triangulate(outline, holes)          # (m, 3) indices into outline + holes
    plate = extrude(outline, depth, holes=[(polygon, hole_depth), ...])

Outlines and holes are simple polygons (N, 2), counter-clockwise. The face's
triangulation is OpenCV's Delaunay over the polygons' corners and a fill of interior
points kept away from every edge, with the triangles outside the outline or inside a
hole dropped; the polygons' edges are then edges of the triangulation as long as a
polygon's corners are closer together than `spacing` (the fill's pitch).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Mesh", "circle", "densify", "extrude", "inside_polygon", "offset_polygon", "polygon_area", "triangulate"]


@dataclass(frozen=True)
class Mesh:
    """A closed triangle mesh: vertices (n, 3) m, triangles (m, 3) indices, outward."""

    vertices: np.ndarray
    triangles: np.ndarray

    def volume_and_centroid(self) -> tuple[float, np.ndarray]:
        """Volume (m³) and centre of gravity (uniform density) of the enclosed solid:
        sums over the signed tetrahedra from the origin to each triangle."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        signed = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
        volume = float(signed.sum())
        centroid = (signed[:, None] * (a + b + c) / 4.0).sum(0) / volume
        return volume, centroid

    def moved(self, pose: np.ndarray) -> Mesh:
        """The mesh with its vertices through the 4x4 `pose`."""
        return Mesh(self.vertices @ pose[:3, :3].T + pose[:3, 3], self.triangles)

    def unshared(self) -> Mesh:
        """The same surface with three vertices of its own per triangle: a renderer
        that averages normals over shared vertices then shades every face flat."""
        return Mesh(self.vertices[self.triangles.ravel()], np.arange(self.triangles.size, dtype=np.int64).reshape(-1, 3))

    def face_normals(self) -> np.ndarray:
        """(m, 3) each triangle's outward unit normal."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    @staticmethod
    def union(meshes: Sequence[Mesh]) -> Mesh:
        """The meshes as one (their solids must not overlap for the volume to add)."""
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(np.concatenate([m.vertices for m in meshes]), np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]))


def polygon_area(polygon: np.ndarray) -> float:
    """Signed area of a polygon (N, 2): positive counter-clockwise (the shoelace)."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def circle(radius: float, segments: int = 96, centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(segments, 2) points on a circle, counter-clockwise from +x."""
    angles = np.arange(segments) * 2 * np.pi / segments
    return np.stack([centre[0] + radius * np.cos(angles), centre[1] + radius * np.sin(angles)], 1)


def densify(polygon: np.ndarray, max_edge: float) -> np.ndarray:
    """The polygon with points added along its edges so none is longer than `max_edge`."""
    p = np.asarray(polygon, dtype=np.float64)
    out = []
    for a, b in zip(p, np.roll(p, -1, axis=0)):
        k = max(int(np.ceil(np.linalg.norm(b - a) / max_edge)), 1)
        out.append(a + (b - a) * (np.arange(k) / k)[:, None])
    return np.concatenate(out)


def offset_polygon(polygon: np.ndarray, distance: float) -> np.ndarray:
    """A counter-clockwise polygon moved outwards by `distance` (inwards when negative):
    each corner along its bisector, so every edge moves by `distance` (mitred corners;
    for distances small against the edges)."""
    p = np.asarray(polygon, dtype=np.float64)
    before, after = p - np.roll(p, 1, axis=0), np.roll(p, -1, axis=0) - p
    n1 = np.stack([before[:, 1], -before[:, 0]], 1) / np.linalg.norm(before, axis=1, keepdims=True)
    n2 = np.stack([after[:, 1], -after[:, 0]], 1) / np.linalg.norm(after, axis=1, keepdims=True)
    bisector = n1 + n2
    scale = 2.0 / np.maximum((bisector * bisector).sum(1), 1e-12)  # |b|² = 2(1 + cos): length d/cos(half angle)
    return p + distance * bisector * scale[:, None]


def inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Whether points (P, 2) lie inside a simple polygon (N, 2): the even-odd rule."""
    x, y = points[:, 0:1], points[:, 1:2]
    ax, ay = polygon[:, 0], polygon[:, 1]
    bx, by = np.roll(ax, -1), np.roll(ay, -1)
    crosses = (ay > y) != (by > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = ax + (y - ay) * (bx - ax) / (by - ay)
    return (crosses & (x < at)).sum(1) % 2 == 1


def _edge_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    a, b = polygon, np.roll(polygon, -1, axis=0)
    d = b - a
    t = np.clip(((points[:, None] - a) * d).sum(2) / (d * d).sum(1), 0.0, 1.0)
    closest = a + t[..., None] * d
    return np.linalg.norm(points[:, None] - closest, axis=2).min(1)


def _check_polygon(polygon: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(polygon, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise ValueError(f"{name}: expected a polygon (N >= 3, 2), got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: the polygon has non-finite coordinates")
    if (np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1) <= 0).any():
        raise ValueError(f"{name}: the polygon repeats a vertex (give each corner once; the ring closes by itself)")
    if polygon_area(p) <= 0:
        raise ValueError(f"{name}: the polygon must be counter-clockwise with a positive area")
    return p


def triangulate(outline: np.ndarray, holes: Sequence[np.ndarray] = (), spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 2), triangles (m, 3) counter-clockwise) covering the outline minus
    the holes. The points start with the outline's corners, then each hole's in order;
    interior fill points (pitch `spacing`, by default the longest polygon edge) follow."""
    import cv2

    outline = _check_polygon(outline, "outline")
    polygons = [outline] + [_check_polygon(h, f"hole {k}") for k, h in enumerate(holes)]
    corners = np.concatenate(polygons)
    longest = max(float(np.linalg.norm(p - np.roll(p, -1, 0), axis=1).max()) for p in polygons)
    pitch = float(spacing) if spacing is not None else longest
    if pitch < longest:
        raise ValueError(f"triangulate: spacing {pitch} is below the longest polygon edge {longest}; the edges would not survive")
    lo, hi = outline.min(0), outline.max(0)
    gx, gy = np.meshgrid(np.arange(lo[0] + pitch / 2, hi[0], pitch), np.arange(lo[1] + pitch / 2, hi[1], pitch))
    fill = np.stack([gx.ravel(), gy.ravel()], 1)
    if len(fill):
        keep = inside_polygon(fill, outline) & (_edge_distance(fill, outline) > pitch)
        for h in polygons[1:]:
            keep &= ~inside_polygon(fill, h) & (_edge_distance(fill, h) > pitch)
        fill = fill[keep]
    points = np.concatenate([corners, fill])
    # Delaunay in a frame scaled to about 1000 units across: float32 inside OpenCV
    scale = 1000.0 / max(float(np.ptp(points, 0).max()), 1e-12)
    local = (points - lo) * scale
    subdiv = cv2.Subdiv2D((-10, -10, int(np.ceil(local.max())) + 20, int(np.ceil(local.max())) + 20))
    index: dict[tuple[float, float], int] = {}
    for k, (x, y) in enumerate(local.astype(np.float32)):
        subdiv.insert((float(x), float(y)))
        index[(float(x), float(y))] = k
    tris = []
    for t in subdiv.getTriangleList():
        ids = [index.get((float(t[2 * i]), float(t[2 * i + 1]))) for i in range(3)]
        if None not in ids:
            tris.append(ids)
    triangles = np.array(tris, dtype=np.int64).reshape(-1, 3)
    centres = points[triangles].mean(1)
    keep = inside_polygon(centres, outline)
    for h in polygons[1:]:
        keep &= ~inside_polygon(centres, h)
    triangles = triangles[keep]
    edges = {frozenset(e) for t in triangles.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    start = 0
    for k, poly in enumerate(polygons):
        ring = range(start, start + len(poly))
        if any(frozenset((i, j)) not in edges for i, j in zip(ring, [*ring[1:], ring[0]])):
            what = "the outline" if k == 0 else f"hole {k - 1}"
            raise ValueError(f"triangulate: an edge of {what} was lost; a hole is too close to another or to the outline for its edges' length (densify them)")
        start += len(poly)
    a, b, c = (points[triangles[:, i]] for i in range(3))
    turn = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    triangles[turn < 0] = triangles[turn < 0][:, ::-1]
    return points, triangles


def _wall(ring_top: np.ndarray, ring_bottom: np.ndarray, outward: bool) -> np.ndarray:
    """Quads between two rings of vertex indices (top at higher z); counter-clockwise
    rings give outward-facing walls with `outward`, walls facing the axis without."""
    nxt = np.roll(np.arange(len(ring_top)), -1)
    t, b = ring_top, ring_bottom
    if outward:
        return np.concatenate([np.c_[b, b[nxt], t[nxt]], np.c_[b, t[nxt], t]])
    return np.concatenate([np.c_[b, t[nxt], b[nxt]], np.c_[b, t, t[nxt]]])


def extrude(outline: np.ndarray, depth: float, holes: Sequence[tuple[np.ndarray, float]] = (), spacing: float | None = None) -> Mesh:
    """The closed solid of `outline` from z = −depth to z = 0, with holes (polygon, hole
    depth) going into it from the face at z = 0: blind below `depth`, through at it."""
    if depth <= 0:
        raise ValueError(f"extrude: depth must be positive, got {depth}")
    for k, (_, d) in enumerate(holes):
        if not 0 < d <= depth:
            raise ValueError(f"extrude: hole {k}'s depth {d} must be in (0, {depth}]")
    polygons = [_check_polygon(h, f"hole {k}") for k, (h, _) in enumerate(holes)]
    outline = _check_polygon(outline, "outline")
    for k, h in enumerate(polygons):
        if not inside_polygon(h, outline).all() or inside_polygon(outline, h).any():
            raise ValueError(f"extrude: hole {k} is not inside the outline")
        for j, other in enumerate(polygons[:k]):
            if inside_polygon(h, other).any() or inside_polygon(other, h).any():
                raise ValueError(f"extrude: holes {j} and {k} overlap")
    depths = [float(d) for _, d in holes]
    through = [p for p, d in zip(polygons, depths) if d == depth]
    face, face_tris = triangulate(outline, polygons, spacing)
    back, back_tris = triangulate(outline, through, spacing)
    n_face = len(face)
    vertices = [np.c_[face, np.zeros(n_face)], np.c_[back, np.full(len(back), -depth)]]
    triangles = [face_tris, back_tris[:, ::-1] + n_face]
    n = n_face + len(back)
    outline_ring = np.arange(len(outline))
    triangles.append(_wall(outline_ring, outline_ring + n_face, outward=True))  # the back's first points are the outline's
    start, back_start = len(outline), n_face + len(outline)
    for polygon, d in zip(polygons, depths):
        m = len(polygon)
        ring = np.arange(start, start + m)
        start += m
        if d == depth:  # through: the wall meets the back's copy of the hole
            triangles.append(_wall(ring, np.arange(back_start, back_start + m), outward=False))
            back_start += m
            continue
        floor, floor_tris = triangulate(polygon, (), spacing)  # its first points are the polygon's
        vertices.append(np.c_[floor, np.full(len(floor), -d)])
        triangles.append(_wall(ring, np.arange(n, n + m), outward=False))
        triangles.append(floor_tris + n)  # the hole's floor faces up
        n += len(floor)
    return Mesh(np.concatenate(vertices).astype(np.float64), np.concatenate(triangles).astype(np.int64))


def frustum(top_radius: float, bottom_radius: float, depth: float, segments: int = 96) -> Mesh:
    """The closed solid of a truncated cone from z = −depth (`bottom_radius`) to z = 0
    (`top_radius`), its circles `circle`'s polygons: `extrude` of a circle with a slope."""
    if depth <= 0 or min(top_radius, bottom_radius) <= 0:
        raise ValueError(f"frustum: depth and radii must be positive, got {depth}, {top_radius}, {bottom_radius}")
    top, bottom = circle(top_radius, segments), circle(bottom_radius, segments)
    vertices = np.concatenate([np.c_[top, np.zeros(segments)], np.c_[bottom, np.full(segments, -depth)], [[0.0, 0.0, 0.0], [0.0, 0.0, -depth]]])
    ring = np.arange(segments)
    nxt = np.roll(ring, -1)
    centre_top, centre_bottom = 2 * segments, 2 * segments + 1
    caps = [np.c_[np.full(segments, centre_top), ring, nxt], np.c_[np.full(segments, centre_bottom), nxt + segments, ring + segments]]
    triangles = np.concatenate([*caps, _wall(ring, ring + segments, outward=True)])
    return Mesh(vertices.astype(np.float64), triangles.astype(np.int64))


def box(half_extents: Sequence[float] | np.ndarray) -> Mesh:
    """The closed box of `half_extents` (3,) centred at the origin, twelve triangles."""
    h = np.asarray(half_extents, dtype=np.float64)
    if h.shape != (3,) or not (h > 0).all():
        raise ValueError(f"box: half_extents must be three positive numbers, got {half_extents}")
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * h
    # Corner index = 4 x + 2 y + z over {0, 1}; each face as two outward triangles.
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    return Mesh(corners, triangles)


def capsule(radius: float, length: float, segments: int = 24) -> Mesh:
    """The closed capsule along z: a cylinder of `length` between two hemispheres of
    `radius`, centred at the origin (`length` 0: a sphere). `segments` around."""
    if radius <= 0 or length < 0 or segments < 3:
        raise ValueError(f"capsule: radius must be positive, length >= 0 and segments >= 3, got {radius}, {length}, {segments}")
    rings = max(2, segments // 4)
    # Latitude rings from the top pole to the bottom one, the upper hemisphere lifted.
    angles = np.linspace(0.0, np.pi / 2, rings + 1)
    top = [(radius * np.sin(a), radius * np.cos(a) + length / 2) for a in angles[1:]]
    bottom = [(r, -z) for r, z in reversed(top)]
    profile = top + bottom if length > 0 else top + bottom[1:]
    around = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_points = [np.c_[r * np.cos(around), r * np.sin(around), np.full(segments, z)] for r, z in profile]
    vertices = np.concatenate([[[0.0, 0.0, radius + length / 2]], *ring_points, [[0.0, 0.0, -radius - length / 2]]])
    ring = np.arange(segments)
    nxt = np.roll(ring, -1)
    last = len(vertices) - 1
    triangles = [np.c_[np.zeros(segments, np.int64), 1 + ring, 1 + nxt]]
    for k in range(len(profile) - 1):
        upper, lower = 1 + k * segments, 1 + (k + 1) * segments
        triangles.append(_wall(upper + ring, lower + ring, outward=True))
    base = 1 + (len(profile) - 1) * segments
    triangles.append(np.c_[np.full(segments, last), base + nxt, base + ring])
    return Mesh(vertices, np.concatenate(triangles).astype(np.int64))
