"""Shape-based matching of a connector (the car's port or the robot's plug) on image
edges, in the manner of Halcon's shape-based matching that Paper III used.

    model = ShapeModel.port(connector("type2"))
    found = find(image, model, K, distortion)          # best match, or None
    found.score, found.reference_pixels, found.camera_from_object

The model is the connector's outline edges as 3D points on its planar faces, each
with its edge direction (the collar's outer circle, the rim of the recessed face and
the contacts' holes for the port; the body's outline and the pins' tips for the plug).
Matching is a search in the object's pose, which fixes the 2D transformation
(`homography`, the paper's "2D affine transformation", exact for the plane):

1. Narrowing (`narrow=True`): the connector is black plastic, so the search starts in
   regions darker than their surroundings of the right size; each region's outline is
   the collar's circle seen as an ellipse, which gives the distance (its major axis)
   and the axis' tilt (its minor/major ratio, up to the sign of the tilt).
   Without narrowing every contour of a Canny edge map of the size is a candidate.
2. The turn about the axis: every 3° for both signs of the tilt, scored on the image's
   edge field.
3. Refinement (`refine`): moving edges. Each model point looks along its projected
   normal for the strongest gradient of the right orientation; the pose minimises the
   points' distances to those edges along the normals (Gauss-Newton, a few rounds).

The score is the mean over model points of the edge strength (saturated) times the
agreement of the image gradient's orientation with the model's edge normal (|cos|, so
either contrast polarity counts): 1 for a perfect, strong match, about 0.5·strength
for clutter. `min_score` flags doubtful matches (the paper's reflections case).
`score` and `refine_pose` work in the model's frame (`camera_from_model`, the port's
own frame; for the plug its tip frame turned about x); `Match` gives the object's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from earcore.charging.connectors import COLLAR, GAP, PLUG_CLEARANCE, RECESS, Connector
from earcore.charging.stereo import project_points
from earcore.mesh import circle, densify, inside_polygon, offset_polygon
from earcore.transforms import axis_angle_matrix, rotation_from_vector

__all__ = ["EdgeField", "Match", "ShapeModel", "edge_field", "find", "find_all", "project_points", "refine_pose", "score"]


@dataclass(frozen=True)
class ShapeModel:
    """Edge points (M, 3) with their tangents (M, 3), the reference points (K, 3), the
    radius of the outermost circle (for the distance) and whether a point belongs to the
    outermost outline (`outer`, M bool), all in the model's frame, whose z points at the
    viewer; `object_from_model` takes them to the object's own frame."""

    name: str
    points: np.ndarray
    tangents: np.ndarray
    reference: np.ndarray
    outer_radius: float
    outer: np.ndarray
    object_from_model: np.ndarray
    #: Each point's outward normal in its face (M, 3) and the side expected brighter:
    #: +1 outside, −1 inside, 0 either (a point's edge may take any contrast).
    normals: np.ndarray
    polarity: np.ndarray
    #: Points whose edges are sharp outlines (refinement uses them; the holes' edges are
    #: blurred by their walls seen at an angle: they help find the turn, not refine it).
    precise: np.ndarray
    #: An opening (polygon in the model's x, y at height z) the points below it are seen
    #: through: a point whose line of sight crosses z outside the polygon is hidden.
    rim: tuple[np.ndarray, float] | None = None

    def subset(self, keep: np.ndarray) -> ShapeModel:
        """The model with only the points where `keep` (M bool) holds."""
        return replace(
            self, points=self.points[keep], tangents=self.tangents[keep], outer=self.outer[keep], normals=self.normals[keep],
            polarity=self.polarity[keep], precise=self.precise[keep],
        )  # fmt: skip

    @staticmethod
    def _ring(polygon: np.ndarray, z: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        dense = densify(polygon, spacing)
        nxt = np.roll(dense, -1, axis=0)
        prev = np.roll(dense, 1, axis=0)
        tangent = nxt - prev
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        return np.c_[dense, np.full(len(dense), z)], np.c_[tangent, np.zeros(len(dense))]

    @classmethod
    def _build(
        cls,
        name: str,
        rings: list[tuple[np.ndarray, float, bool, bool, int]],
        reference: np.ndarray,
        outer_radius: float,
        spacing: float,
        object_from_model: np.ndarray,
        rim: tuple[np.ndarray, float] | None = None,
    ) -> ShapeModel:
        points, tangents, outer, precise, polarity = [], [], [], [], []
        for polygon, z, is_outer, is_precise, brighter in rings:
            p, t = cls._ring(polygon, z, spacing)
            points.append(p)
            tangents.append(t)
            outer.append(np.full(len(p), is_outer))
            precise.append(np.full(len(p), is_precise))
            polarity.append(np.full(len(p), brighter))
        t = np.concatenate(tangents)
        normals = np.stack([t[:, 1], -t[:, 0], np.zeros(len(t))], 1)  # outward of counter-clockwise rings
        model_from_object = np.linalg.inv(object_from_model)[:3, :3]
        return cls(
            name, np.concatenate(points) @ model_from_object.T, t @ model_from_object.T,
            np.asarray(reference) @ model_from_object.T, outer_radius, np.concatenate(outer), object_from_model,
            normals @ model_from_object.T, np.concatenate(polarity).astype(np.int8), np.concatenate(precise), rim,
        )  # fmt: skip

    @classmethod
    def port(cls, k: Connector, spacing: float = 0.0015) -> ShapeModel:
        """The car's port as installed: the outer edge of the gap around the collar (the
        outermost outline; the collar's own edge, a gap's width inside it, would blur into
        it), the recess' rim (the face's outline at the collar's front) and each
        contact's hole on the face (`rim`: what hides the holes at an angle)."""
        radius = k.radius + COLLAR + GAP
        # the car's paint outside the dark gap, the collar outside the recess, the face around the holes
        rings = [(circle(radius), RECESS, True, True, 1), (k.outline, RECESS, False, True, 1)]
        for c in k.contacts:
            rings.append((circle(k.hole_radius(c), 16, (c.x, c.y)), 0.0, False, False, 1))
        return cls._build(f"{k.name} port", rings, k.reference_points, radius, spacing, np.eye(4), (k.outline, RECESS))

    @classmethod
    def plug(cls, k: Connector, spacing: float = 0.0015) -> ShapeModel:
        """The robot's plug seen from the front (`Connector.plug_body_mesh`): the round
        shell's front (the outermost outline, at z = RECESS), the nose's outline at the
        front face (z = 0) and the pins' tips (z = −pin_length), in the tip frame, whose z
        points away from a viewer the pins point at (the model's frame is the tip's
        turned about x)."""
        # anything behind the shell, the same plastic around the nose, the metal pins brighter than it
        rings = [(circle(k.radius + COLLAR), RECESS, True, True, 0), (offset_polygon(k.outline, -PLUG_CLEARANCE), 0.0, False, True, 0)]
        for c in k.contacts:
            rings.append((circle(c.radius, 12, (c.x, c.y)), -k.pin_length, False, True, -1))
        reference = k.reference_points - [0.0, 0.0, k.pin_length]
        turned = np.eye(4)
        turned[:3, :3] = axis_angle_matrix([1.0, 0.0, 0.0], np.pi)
        return cls._build(f"{k.name} plug", rings, reference, k.radius + COLLAR, spacing, turned)


@dataclass(frozen=True)
class EdgeField:
    """An image's edges: gradient (gx, gy) after a light blur and the saturated
    strength in [0, 1]; for the coarse search the same spread over a few pixels (the
    structure tensor's txx, txy, tyy normalised by its trace, and the strength, blurred);
    `offset` (x, y) of the window in the full image."""

    gx: np.ndarray
    gy: np.ndarray
    strength: np.ndarray
    txx: np.ndarray
    txy: np.ndarray
    tyy: np.ndarray
    spread: np.ndarray
    offset: tuple[int, int] = (0, 0)


def edge_field(gray: np.ndarray, saturation: float = 40.0, offset: tuple[int, int] = (0, 0), spread_px: float = 2.0, blur: float = 1.0) -> EdgeField:
    import cv2

    raw = np.asarray(gray, dtype=np.float32)
    g = cv2.GaussianBlur(raw, (0, 0), blur) if blur > 0 else raw
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    strength = np.minimum(np.sqrt(gx * gx + gy * gy) / saturation, 1.0)
    wide = lambda a: cv2.GaussianBlur(a, (0, 0), spread_px)  # noqa: E731
    txx, txy, tyy = wide(gx * gx), wide(gx * gy), wide(gy * gy)
    trace = np.maximum(txx + tyy, 1e-6)
    spread = np.minimum(wide(strength) * 2.0, 1.0)  # an edge blurred over ~2σ keeps about half its peak
    return EdgeField(gx, gy, strength, txx / trace, txy / trace, tyy / trace, spread, offset)


@dataclass(frozen=True)
class Match:
    """A found connector: its pose in the camera (the object's frame: the port's, or the
    plug's tip frame), the plane's homography (object x, y in m on z = 0 → pixels,
    undistorted), the score, the reference points' pixels
    (distorted, as in the image), the searched window and the time taken."""

    camera_from_object: np.ndarray
    homography: np.ndarray
    score: float
    reference_pixels: np.ndarray
    window: tuple[int, int, int, int]
    seconds: float
    #: The score of the points inside the outermost outline (`score(inner=True)`).
    inner_score: float = float("nan")
    #: Whether the score is below the `min_score` the match was found with: a doubtful
    #: match (a reflection, a partial view) that must not be acted on.
    flagged: bool = False


def _project(points: np.ndarray, pose: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    return project_points(points @ pose[:3, :3].T + pose[:3, 3], K, dist)


def _sample(field: EdgeField, pixels: np.ndarray, layers: tuple[str, ...] = ("gx", "gy", "strength")) -> list[np.ndarray]:
    """The named layers at pixels (full-image coordinates), nearest pixel; zero outside."""
    x = np.rint(pixels[:, 0] - field.offset[0]).astype(np.int64)
    y = np.rint(pixels[:, 1] - field.offset[1]).astype(np.int64)
    h, w = field.gx.shape
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    x, y = np.where(ok, x, 0), np.where(ok, y, 0)
    return [getattr(field, name)[y, x] * ok for name in layers]


def _image_tangents(model: ShapeModel, pose: np.ndarray, K: np.ndarray, dist: np.ndarray, occlusion: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected model points (M, 2), their unit image normals (M, 2, pointing out of
    their rings) and a visibility
    mask (M; points on faces turned towards the camera) for one pose (4, 4), or for a
    stack of poses (P, 4, 4) with a leading P on every output. Without `occlusion`
    points hidden by the model's rim count as visible (the coarse search's shortcut)."""
    poses = np.asarray(pose, dtype=np.float64)
    single = poses.ndim == 2
    poses = poses[None] if single else poses
    eps = 0.0005
    both = np.concatenate([model.points - eps * model.tangents, model.points + eps * model.tangents, model.points + eps * model.normals])  # (3M, 3)
    cam = np.matmul(poses[:, :3, :3], both.T).transpose(0, 2, 1) + poses[:, None, :3, 3]
    ends = project_points(cam, K, dist).reshape(len(poses), 3, -1, 2)
    a, b, out = ends[:, 0], ends[:, 1], ends[:, 2]
    centre = (a + b) / 2
    t = b - a
    t /= np.maximum(np.linalg.norm(t, axis=2, keepdims=True), 1e-12)
    normal = np.stack([-t[..., 1], t[..., 0]], 2)
    normal *= np.where(((out - centre) * normal).sum(2, keepdims=True) < 0, -1.0, 1.0)  # pointing out of the ring
    points = cam[:, : len(model.points)]  # the first ends are near enough for the test
    facing = np.einsum("pi,pni->pn", poses[:, :3, 2], -points) > 0
    if occlusion and model.rim is not None:
        polygon, height = model.rim
        below = model.points[:, 2] < height - 1e-9
        if below.any():
            # each point's line of sight in the model's frame, crossing the rim's plane
            eye = np.einsum("pji,pj->pi", poses[:, :3, :3], -poses[:, :3, 3])  # the camera in the model's frame
            p = model.points[below][None]
            t = (height - p[..., 2]) / np.where(np.abs(eye[:, None, 2] - p[..., 2]) > 1e-12, eye[:, None, 2] - p[..., 2], 1e-12)
            cross = p[..., :2] + t[..., None] * (eye[:, None, :2] - p[..., :2])
            seen = inside_polygon(cross.reshape(-1, 2), polygon).reshape(len(poses), -1)
            facing[:, below] &= seen
    if single:
        return centre[0], normal[0], facing[0]
    return centre, normal, facing


def _agreement(along: np.ndarray, polarity: np.ndarray) -> np.ndarray:
    """The gradient along the outward normal, counted with the expected polarity: |.|
    where either contrast will do, only the expected sign otherwise."""
    return np.where(polarity == 0, np.abs(along), np.maximum(polarity * along, 0.0))


def score(
    field: EdgeField, model: ShapeModel, pose: np.ndarray, K: np.ndarray, dist: np.ndarray, *, coarse: bool = False, inner: bool = False
) -> float | np.ndarray:
    """The match's score at `pose` (`camera_from_model`; or (P,) scores for (P, 4, 4)
    poses): edge strength times the orientation's agreement, averaged over the model's
    points that can be seen; `coarse` on the spread field (tolerates a few pixels, for
    the search); `inner` over the points inside the outermost outline only (what tells
    connector types apart: their outer circles are alike)."""
    pixels, normal, visible = _image_tangents(model, pose, K, dist, occlusion=not coarse)
    if inner:
        visible = visible & ~model.outer
    shape = pixels.shape[:-1]
    pixels, normal = pixels.reshape(-1, 2), normal.reshape(-1, 2)
    nx, ny = normal[:, 0], normal[:, 1]
    if coarse:
        txx, txy, tyy, spread = _sample(field, pixels, ("txx", "txy", "tyy", "spread"))
        each = spread * (nx * nx * txx + 2 * nx * ny * txy + ny * ny * tyy)
    else:
        gx, gy, strength = _sample(field, pixels)
        polarity = np.broadcast_to(model.polarity, shape).reshape(-1)
        each = strength * _agreement(gx * nx + gy * ny, polarity) / np.maximum(np.hypot(gx, gy), 1e-9)
    visible = visible.reshape(shape)
    means = (each.reshape(shape) * visible).sum(-1) / np.maximum(visible.sum(-1), 1)
    return float(means) if np.ndim(means) == 0 else means


def _poses(normal_cam: np.ndarray, rolls: np.ndarray, centre_cam: np.ndarray) -> np.ndarray:
    """(R, 4, 4) poses with z along `normal_cam` (towards the camera), turned by each of
    `rolls` (rad) about it, at `centre_cam`."""
    z = normal_cam / np.linalg.norm(normal_cam)
    helper = np.array([0.0, -1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    y = helper - z * (helper @ z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = np.cos(rolls), np.sin(rolls)
    poses = np.zeros((len(rolls), 4, 4))
    poses[:, :3, 0] = c[:, None] * x + s[:, None] * y  # the frame turned about its z
    poses[:, :3, 1] = -s[:, None] * x + c[:, None] * y
    poses[:, :3, 2] = z
    poses[:, :3, 3] = centre_cam
    poses[:, 3, 3] = 1.0
    return poses


def _ellipses(
    gray: np.ndarray, lo_px: float, hi_px: float, offset: tuple[int, int] = (0, 0), source: str = "edges"
) -> list[tuple[np.ndarray, float, float, np.ndarray]]:
    """(centre, major and minor semi-axes, the minor axis' direction) of the contours of
    `gray` that are ellipses with a major semi-axis in [lo_px, hi_px]: its edges'
    contours (`source` "edges") or the outlines of its darkest blobs ("blobs": an edge
    contour of a dark outline that touches a neighbour's edges, a plug before the
    robot's flange, runs on along them)."""
    import cv2

    blurred = cv2.GaussianBlur(gray, (5, 5), 1.0)
    if source == "edges":
        contours, _ = cv2.findContours(cv2.Canny(blurred, 10, 30), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    else:
        darkest, middle = np.percentile(blurred, [2, 50])
        dark = (blurred < darkest + 0.35 * (middle - darkest)).astype(np.uint8)
        contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out: list[tuple[np.ndarray, float, float, np.ndarray]] = []
    for c in contours:
        if len(c) < max(12, lo_px):  # at least a good part of the outline
            continue
        (cx, cy), (w, h), angle = cv2.fitEllipse(c)
        major, minor = max(w, h) / 2, min(w, h) / 2
        if not lo_px <= major <= hi_px or minor < 0.5 * major:
            continue
        # the contour must lie on its ellipse (a circle seen at an angle), not just fill it
        a = np.radians(angle)
        u = c.reshape(-1, 2) - [cx, cy]
        x = u[:, 0] * np.cos(a) + u[:, 1] * np.sin(a)
        y = -u[:, 0] * np.sin(a) + u[:, 1] * np.cos(a)
        radial = np.sqrt((x / max(w / 2, 1e-9)) ** 2 + (y / max(h / 2, 1e-9)) ** 2)
        if np.median(np.abs(radial - 1.0)) > 0.06:
            continue
        minor_dir = np.array([np.cos(a), np.sin(a)]) if w < h else np.array([-np.sin(a), np.cos(a)])
        centre = np.array([cx + offset[0], cy + offset[1]])
        out.append((centre, major, minor, minor_dir))
    return out


def _distinct(ellipses: list) -> list:
    """`ellipses` without repeats (the same outline found as an edge and as a blob)."""
    out: list = []
    for e in ellipses:
        if not any(np.abs(e[0] - o[0]).max() < 2 and abs(e[1] - o[1]) < 0.03 * e[1] and abs(e[2] - o[2]) < 0.03 * e[2] for o in out):
            out.append(e)
    return out


def _dark_regions(darkness: np.ndarray, threshold: float, max_half: float, depth: int = 3) -> list[np.ndarray]:
    """Connected regions (x, y, w, h, area; quarter-resolution pixels) darker than their
    surroundings by more than `threshold`. A region wider than 2·`max_half` (full-
    resolution pixels) is split at a higher threshold, half its darkest: a black
    connector beside faintly shaded surfaces (a white robot's side) merges with them at
    a low threshold that a dark car's paint needs."""
    import cv2

    count, labels, stats, _ = cv2.connectedComponentsWithStats((darkness > threshold).astype(np.uint8))
    out = []
    for i in range(1, count):
        x, y, w, h, _ = stats[i]
        if 4 * max(w, h) / 2 <= max_half or depth == 0:
            out.append(stats[i])
            continue
        inside = np.where(labels[y : y + h, x : x + w] == i, darkness[y : y + h, x : x + w], 0)
        higher = max(threshold * 2, 0.5 * float(inside.max()))
        for sub in _dark_regions(inside, higher, max_half, depth - 1):
            out.append(sub + np.array([x, y, 0, 0, 0]))
    return out


def _candidates(
    gray: np.ndarray, model: ShapeModel, K: np.ndarray, narrow: bool, distances: tuple[float, float]
) -> list[tuple[np.ndarray, float, float, np.ndarray]]:
    """Ellipses that could be the connector's outermost outline: in the windows of dark
    regions of the right size (`narrow`), or anywhere in the image."""
    import cv2

    f = float(K[0, 0])
    lo_px, hi_px = 0.8 * f * model.outer_radius / distances[1], 1.2 * f * model.outer_radius / distances[0]
    if not narrow:
        return _distinct(_ellipses(gray, lo_px, hi_px) + _ellipses(gray, lo_px, hi_px, source="blobs"))
    # dark regions no bigger than the connector: a black-hat (closing minus image) with
    # a square a little wider than the connector at its nearest keeps those and drops
    # larger dark areas (a dark car's whole side)
    small = cv2.resize(gray, (gray.shape[1] // 4, gray.shape[0] // 4), interpolation=cv2.INTER_AREA)
    size = int(1.3 * 2 * hi_px / 4) | 1
    square = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))  # separable: fast at any size
    darkness = cv2.morphologyEx(cv2.GaussianBlur(small, (0, 0), 1.0), cv2.MORPH_BLACKHAT, square)
    out = []
    for x, y, w, h, area in _dark_regions(darkness, 8, 1.3 * hi_px / 2):
        side = 4 * max(w, h) / 2
        if not 0.5 * lo_px <= side <= 1.3 * hi_px or area < 0.2 * w * h:
            continue
        half = int(4 * max(w, h) * 0.75) + 8
        cx, cy = 4 * (x + w / 2), 4 * (y + h / 2)
        x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
        x1, y1 = min(int(cx) + half, gray.shape[1]), min(int(cy) + half, gray.shape[0])
        window = gray[y0:y1, x0:x1]
        edges = sorted(_ellipses(window, lo_px, hi_px, (x0, y0)), key=lambda e: -e[1])[:2]  # the outermost outline first
        blobs = sorted(_ellipses(window, lo_px, hi_px, (x0, y0), source="blobs"), key=lambda e: -e[1])[:1]
        out += _distinct(edges + blobs)
    return out


def find(image: np.ndarray, model: ShapeModel, K: np.ndarray, distortion=None, **options) -> Match | None:
    """The best match of `model` in the image, or None (`find_all`'s options)."""
    found = find_all(image, model, K, distortion, **options)
    return found[0] if found else None


def find_all(
    image: np.ndarray,
    model: ShapeModel,
    K: np.ndarray,
    distortion=None,
    *,
    narrow: bool = True,
    refine: bool = True,
    distances: tuple[float, float] = (1.0, 3.0),
    roll_step_deg: float = 6.0,
    refine_best: int = 4,
    min_score: float = 0.55,
    where: Callable[[np.ndarray, float], bool] | None = None,
) -> list[Match]:
    """The refined hypotheses of `model` in a colour or grey image, best first (empty
    when no candidate region is found). A single image cannot tell a planar pattern
    tilted one way from the same tilted the other way (they look alike up to
    perspective); `charging.locate` settles that with the second camera. Distances (m)
    bound the search's scale. The turn about the axis is searched every `roll_step_deg`
    on the points inside the outermost outline (a circle: alike at every turn), then
    at a third of the step around the best. The `refine_best` best hypotheses of the
    search (those within 60 % of the best's coarse score) are refined and the best of
    them kept; a match scoring
    under `min_score` comes back `flagged`. `where(centre_px, major_px)` keeps only the
    candidate ellipses it accepts (`locate`: those on the other image's epipolar lines).
    The image is 8-bit: (H, W) grey, (H, W, 3)
    RGB or (H, W, 4) RGBA."""
    import cv2

    start = time.perf_counter()
    image = np.asarray(image)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))):
        raise ValueError(f"find: expected an 8-bit grey, RGB or RGBA image, got {image.dtype} of shape {image.shape}")
    if image.ndim == 2:
        gray = image
    else:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY if image.shape[2] == 3 else cv2.COLOR_RGBA2GRAY)
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    found: list[tuple[float, np.ndarray, EdgeField, tuple[int, int, int, int]]] = []
    rolls = np.radians(np.arange(0.0, 360.0, roll_step_deg))
    fine = np.radians(roll_step_deg) * np.array([-2.0, -1.0, 1.0, 2.0]) / 3
    inner_points = model.subset(~model.outer)
    sparse = inner_points.subset(np.arange(len(inner_points.points)) % 2 == 0)  # the first, coarsest pass
    fields: list[tuple[tuple[int, int, int, int], EdgeField]] = []
    outer_z = float(model.points[model.outer, 2].mean())  # the outer outline's plane in the model
    # the largest first: a smaller candidate's window inside a larger one's shares its edges
    candidates = [e for e in _candidates(gray, model, K, narrow, distances) if where is None or where(e[0], e[1])]
    for centre, major, minor, minor_dir in sorted(candidates, key=lambda e: -e[1]):
        # a window around the region, edges only there
        half = int(major * 1.6) + 8
        x0, y0 = max(int(centre[0]) - half, 0), max(int(centre[1]) - half, 0)
        x1, y1 = min(int(centre[0]) + half, gray.shape[1]), min(int(centre[1]) + half, gray.shape[0])
        inside = [(w, f) for w, f in fields if w[0] <= x0 and w[1] <= y0 and w[2] >= x1 and w[3] >= y1]
        if inside:
            (x0, y0, x1, y1), field = inside[0]
        else:
            field = edge_field(gray[y0:y1, x0:x1], offset=(x0, y0))
            fields.append(((x0, y0, x1, y1), field))
        ray = cv2.undistortPoints(centre.reshape(1, 1, 2), K, dist).reshape(2)
        direction = np.array([ray[0], ray[1], 1.0])
        direction /= np.linalg.norm(direction)
        depth = float(K[0, 0]) * model.outer_radius / major
        tilt = np.arccos(np.clip(minor / major, 0.0, 1.0))
        # the tilt turns the axis away from the line of sight across the minor axis
        across = np.array([minor_dir[0], minor_dir[1], 0.0])
        hinge = np.cross(direction, across)
        hinge /= np.linalg.norm(hinge)
        for sign in (1.0, -1.0):
            normal = axis_angle_matrix(hinge, sign * tilt) @ (-direction)
            centre_cam = direction * depth - normal * outer_z  # the outline's centre on the ray
            scores = np.asarray(score(field, sparse, _poses(normal, rolls, centre_cam), K, dist, coarse=True))
            best = rolls[int(np.argmax(scores))]
            around = np.r_[best, best + fine]
            poses = _poses(normal, around, centre_cam)
            scores = np.asarray(score(field, inner_points, poses, K, dist, coarse=True))
            k = int(np.argmax(scores))
            found.append((float(scores[k]), poses[k], field, (x0, y0, x1, y1)))
    if not found:
        return []
    # the few best hypotheses refined
    out = []
    ranked = sorted(found, key=lambda f: -f[0])
    # a hypothesis far behind the best in the coarse search is not worth refining
    ranked = [h for h in ranked if h[0] >= 0.6 * ranked[0][0]]
    for _, pose, field, window in ranked[: refine_best if refine else 1]:
        if refine:
            pose = refine_pose([field], model, pose, [(K, dist, np.eye(4))])
        s = float(score(field, model, pose, K, dist))
        camera_from_object = pose @ np.linalg.inv(model.object_from_model)
        H = K @ np.c_[camera_from_object[:3, :2], camera_from_object[:3, 3]]
        reference = _project(model.reference, pose, K, dist)
        inner_score = float(score(field, model, pose, K, dist, inner=True))
        out.append(Match(camera_from_object, H / H[2, 2], s, reference, window, time.perf_counter() - start, inner_score, s < min_score))
    return sorted(out, key=lambda m: -m.score)


def _bilinear(field: EdgeField, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(gx, gy) at sub-pixel positions (full-image coordinates); zero outside."""
    x = pixels[:, 0] - field.offset[0]
    y = pixels[:, 1] - field.offset[1]
    h, w = field.gx.shape
    ok = (x >= 0) & (x < w - 1) & (y >= 0) & (y < h - 1)
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = x - x0, y - y0
    out = []
    for layer in (field.gx, field.gy):
        top = layer[y0, x0] * (1 - fx) + layer[y0, x0 + 1] * fx
        bottom = layer[y0 + 1, x0] * (1 - fx) + layer[y0 + 1, x0 + 1] * fx
        out.append((top * (1 - fy) + bottom * fy) * ok)
    return out[0], out[1]


def _edge_targets(
    field: EdgeField, pixels: np.ndarray, normals: np.ndarray, reach: float, polarity: np.ndarray, min_gradient: float = 12.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the signed distance (px) along its normal to the nearest local maximum
    of the gradient along the normal within ±reach (sub-pixel, a parabola through three
    samples half a pixel apart), and whether there is one of at least `min_gradient`
    (Sobel units: about a quarter of it in grey levels per pixel, above the noise)."""
    step = 0.5
    steps = np.arange(-reach, reach + step / 2, step)
    probes = pixels[:, None, :] + steps[None, :, None] * normals[:, None, :]
    gx, gy = _bilinear(field, probes.reshape(-1, 2))
    n = len(pixels)
    along = _agreement(gx * np.repeat(normals[:, 0], len(steps)) + gy * np.repeat(normals[:, 1], len(steps)), np.repeat(polarity, len(steps))).reshape(n, len(steps))
    inner = along[:, 1:-1]
    peaks = (inner >= along[:, :-2]) & (inner > along[:, 2:]) & (inner > 0.3 * along.max(1, keepdims=True)) & (inner > min_gradient)
    distance = np.where(peaks, np.abs(steps[1:-1])[None, :], np.inf)
    k = distance.argmin(1) + 1
    found = np.isfinite(distance.min(1))
    rows = np.arange(n)
    left, peak, right = along[rows, k - 1], along[rows, k], along[rows, np.minimum(k + 1, len(steps) - 1)]
    denom = left - 2 * peak + right
    sub = np.where(denom < 0, 0.5 * (left - right) / np.where(denom < 0, denom, -1.0), 0.0) * step
    strong = peak > min_gradient
    return steps[k] + sub, found & strong


def refine_pose(
    fields: list[EdgeField],
    model: ShapeModel,
    pose: np.ndarray,
    cameras: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    *,
    rounds: int = 6,
    reach: float = 4.0,
    sharp_only: bool = True,
) -> np.ndarray:
    """Moving edges: the model's pose in the first camera (`camera_from_model`) that
    puts the model's edges on the image edges of every camera. `cameras` holds (K, distortion,
    camera_from_first) per field. `sharp_only`: only the model's `precise` points (one
    image: the holes' edges, blurred by their walls, would pull a fit from a rough start
    astray); without it the holes count too (both images from a close start: their plane
    behind the rim steadies the tilt)."""
    pose = np.asarray(pose, dtype=np.float64).copy()
    if sharp_only and not model.precise.all():
        model = model.subset(model.precise)
    for r in range(rounds):
        rows, targets = [], []
        for field, (K, dist, cam_from_first) in zip(fields, cameras):
            here = cam_from_first @ pose
            pixels, normals, visible = _image_tangents(model, here, K, dist)
            offset, found = _edge_targets(field, pixels, normals, reach if r < rounds - 2 else 2.0, model.polarity)
            use = visible & found
            if use.sum() < 6:
                continue
            # each point's move along its normal for a turn ω (about the model's origin, in
            # the first camera's axes) and a shift v: δp = C_R (ω × R·p + v), through the
            # pinhole's derivative (the lens' own is small and only slows convergence)
            turned = model.points[use] @ pose[:3, :3].T  # R·p
            cam = (turned + pose[:3, 3]) @ cam_from_first[:3, :3].T + cam_from_first[:3, 3]
            x, y, z = cam.T
            n = normals[use]
            row = np.stack([n[:, 0] * K[0, 0] / z, n[:, 1] * K[1, 1] / z, -(n[:, 0] * K[0, 0] * x + n[:, 1] * K[1, 1] * y) / (z * z)], 1)
            row = row @ cam_from_first[:3, :3]  # d(offset)/d(point in the first camera)
            jac = np.concatenate([np.cross(turned, row), row], 1)  # row·(ω × a) = ω·(a × row)
            rows.append(jac)
            targets.append(offset[use])
        if not rows:
            break
        jac, residual = np.concatenate(rows), np.concatenate(targets)
        # robust: Huber weights at 1.5 px
        weight = np.minimum(1.0, 1.5 / np.maximum(np.abs(residual), 1e-9))
        normal_matrix = jac.T @ (jac * weight[:, None])
        step = np.linalg.solve(normal_matrix + 1e-9 * np.eye(6) * np.trace(normal_matrix), jac.T @ (weight * residual))
        pose[:3, :3] = rotation_from_vector(step[:3]) @ pose[:3, :3]
        pose[:3, 3] = pose[:3, 3] + step[3:]
        if np.abs(step[3:]).max() < 1e-6 and np.abs(step[:3]).max() < 1e-6:
            break
    return pose
