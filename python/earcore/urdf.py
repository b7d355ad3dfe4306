"""Reading URDF robot descriptions and the meshes they point to (STL, OBJ, COLLADA).

Only what the robot geometry needs: links, joints (revolute, continuous, prismatic,
fixed), each link's collision (or visual) geometry as vertices in the link frame.
Everything numeric downstream (fitting capsules, kinematics) happens in Rust.
"""

from __future__ import annotations

import copy
import functools
import math
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from earcore.errors import UrdfError
from earcore.transforms import axis_angle_matrix, rotation_xyz

__all__ = ["UrdfError", "UrdfJoint", "UrdfRobot", "collision_as_visual", "parse_urdf", "read_mesh", "read_mesh_vertices"]


@dataclass(frozen=True)
class UrdfJoint:
    name: str
    kind: str  # revolute | continuous | prismatic | fixed
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]
    lower: float
    upper: float
    mimic: str | None = None
    #: Velocity limit (rad/s or m/s; inf when the URDF gives none).
    velocity: float = math.inf


@dataclass
class UrdfRobot:
    name: str
    path: Path
    #: Link names, the root first.
    links: list[str]
    joints: list[UrdfJoint]
    #: Per link: geometry vertices (N, 3) in the link frame, or None without geometry.
    vertices: dict[str, np.ndarray | None] = field(default_factory=dict)


def _floats(text: str | None, n: int, default: tuple[float, ...], what: str) -> tuple[float, ...]:
    if text is None:
        return default
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        raise UrdfError(f"{what}: expected {n} numbers, got {text!r}") from None
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise UrdfError(f"{what}: expected {n} finite numbers, got {text!r}")
    return values


def _origin(element: ET.Element | None, what: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    if element is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    xyz = _floats(element.get("xyz"), 3, (0.0, 0.0, 0.0), f"{what} origin xyz")
    rpy = _floats(element.get("rpy"), 3, (0.0, 0.0, 0.0), f"{what} origin rpy")
    return xyz, rpy


def resolve_mesh_path(filename: str, urdf_path: Path) -> Path:
    """Find a mesh named in a URDF: plain paths are relative to the URDF's folder;
    ``package://pkg/rest`` is looked up in the URDF's folder and its ancestors (a
    folder named ``pkg`` holding ``rest``, or any ancestor holding ``pkg/rest``)."""
    base = urdf_path.parent
    if filename.startswith("file://"):
        filename = filename[len("file://") :]
    if not filename.startswith("package://"):
        p = Path(filename)
        p = p if p.is_absolute() else base / p
        if p.is_file():
            return p
        raise UrdfError(f"{urdf_path.name}: mesh {filename!r} not found (looked for {p})")
    rel = filename[len("package://") :]
    package, _, rest = rel.partition("/")
    for folder in [base, *base.parents]:
        if folder.name == package and (folder / rest).is_file():
            return folder / rest
        if (folder / rel).is_file():
            return folder / rel
    raise UrdfError(f"{urdf_path.name}: mesh {filename!r} not found in {base} or its parent folders")


#: Colour of links whose visual elements name no material (a UR arm's light grey).
DEFAULT_LINK_RGBA = "0.75 0.75 0.75 1"


def collision_as_visual(path: str | Path, out: str | Path) -> Path:
    """Write a copy of the URDF at `path` into the folder `out` whose links *look* like
    their collision geometry: each link with collision elements gets them as its visual
    elements (same origins and meshes; mesh and texture paths made absolute), keeping the
    first visual's material (or a light grey). Links without collision geometry keep their
    visuals; links without visuals (collision-only volumes) stay invisible. Returns the new
    file's path.

    For rendering speed: pybullet's tiny renderer spends most of a small image on
    triangles, and a UR5's visual meshes have ~20x the collision meshes' (its depth
    images agree to ~1 mm; `tests/test_sim.py` measures it)."""
    path = Path(path)
    try:
        tree = ET.parse(path)
    except (OSError, ET.ParseError) as exc:
        raise UrdfError(f"{path}: cannot read the URDF: {exc}") from exc
    root = tree.getroot()
    for link in root.findall("link"):
        collisions, visuals = link.findall("collision"), link.findall("visual")
        if not collisions or not visuals:  # collision-only volumes stay invisible
            continue
        material = next((v.find("material") for v in visuals if v.find("material") is not None), None)
        for v in visuals:
            link.remove(v)
        for c in collisions:
            visual = ET.SubElement(link, "visual")
            for child in c:
                if child.tag in ("origin", "geometry"):
                    visual.append(copy.deepcopy(child))
            if material is not None:
                visual.append(copy.deepcopy(material))
            else:
                ET.SubElement(ET.SubElement(visual, "material", name="earcore_link"), "color", rgba=DEFAULT_LINK_RGBA)
    # The copy lives elsewhere: every mesh and texture it names by absolute path.
    for element in (*root.iter("mesh"), *root.iter("texture")):
        if element.get("filename"):
            element.set("filename", str(resolve_mesh_path(element.get("filename", ""), path).resolve()))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    target = out / f"{path.stem}_collision_visuals.urdf"
    tree.write(target, encoding="unicode")
    return target


def read_mesh_vertices(path: Path) -> np.ndarray:
    """Vertices (N, 3) of an STL (binary or ASCII), OBJ or COLLADA (.dae) mesh, in
    metres for COLLADA (its <unit>) and in the file's units otherwise."""
    return read_mesh(path)[0]


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3), triangles (M, 3) indices) of an STL (binary or ASCII), OBJ or
    COLLADA (.dae) mesh, in metres for COLLADA (its <unit>) and in the file's units
    otherwise. Polygons are split into fans; STL's triangles keep their own corners."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UrdfError(f"cannot read mesh {path}: {exc}") from exc
    if suffix == ".stl":
        vertices = _stl_vertices(data, path)
        triangles = np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)
    elif suffix == ".obj":
        vertices, triangles = _obj_mesh(data, path)
    elif suffix == ".dae":
        vertices, triangles = _collada_mesh(data, path)
    else:
        raise UrdfError(f"mesh {path.name}: unsupported format {suffix!r} (STL, OBJ and COLLADA are read)")
    if len(vertices) == 0:
        raise UrdfError(f"mesh {path} has no vertices")
    if not np.isfinite(vertices).all():
        raise UrdfError(f"mesh {path} has non-finite vertices")
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise UrdfError(f"mesh {path}: a face names a vertex that does not exist")
    return vertices, triangles


def _fan(polygon: list[int]) -> list[tuple[int, int, int]]:
    return [(polygon[0], polygon[k], polygon[k + 1]) for k in range(1, len(polygon) - 1)]


def _stl_vertices(data: bytes, path: Path) -> np.ndarray:
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * count:
            record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            triangles = np.frombuffer(data, dtype=record, count=count, offset=84)
            return triangles["v"].reshape(-1, 3).astype(np.float64)
    text = data.decode("ascii", errors="replace")
    if not text.lstrip().startswith("solid"):
        raise UrdfError(f"mesh {path} is neither binary nor ASCII STL")
    rows = [line.split()[1:4] for line in text.splitlines() if line.strip().startswith("vertex")]
    try:
        return np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise UrdfError(f"mesh {path}: malformed ASCII STL vertex") from None


def _obj_mesh(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows: list[list[str]] = []
    faces: list[tuple[int, int, int]] = []
    for line in data.decode("utf-8", errors="replace").splitlines():
        if line.startswith("v "):
            parts = line.split()
            if len(parts) < 4:
                raise UrdfError(f"mesh {path}: malformed vertex line {line!r}")
            rows.append(parts[1:4])
        elif line.startswith("f "):
            try:
                # "f 1 2 3", "f 1/1 2/2 3/3", "f 1//1 ..."; negative: from the end so far.
                corners = [int(c.split("/")[0]) for c in line.split()[1:]]
            except ValueError:
                raise UrdfError(f"mesh {path}: malformed face line {line!r}") from None
            faces.extend(_fan([c - 1 if c > 0 else len(rows) + c for c in corners]))
    try:
        vertices = np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise UrdfError(f"mesh {path}: malformed OBJ vertex") from None
    return vertices, np.array(faces, dtype=np.int64).reshape(-1, 3)


def _collada_mesh(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions and faces of every geometry instanced in the visual scene, placed by
    the node transforms (matrix / translate / rotate / scale) and scaled to metres."""
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise UrdfError(f"mesh {path} is not valid COLLADA XML: {exc}") from exc
    for element in root.iter():  # drop the namespace: tags become plain names
        if "}" in element.tag:
            element.tag = element.tag.split("}", 1)[1]
    unit = root.find("asset/unit")
    meter = float(unit.get("meter", "1")) if unit is not None else 1.0
    by_id = {e.get("id"): e for e in root.iter() if e.get("id")}

    def floats(element: ET.Element | None, what: str) -> np.ndarray:
        if element is None or not (element.text or "").strip():
            raise UrdfError(f"mesh {path}: {what} is empty")
        return np.array(str(element.text).split(), dtype=np.float64)

    def geometry_mesh(geometry: ET.Element) -> tuple[np.ndarray, np.ndarray]:
        clouds, faces, count = [], [], 0
        for mesh in geometry.iter("mesh"):
            starts: dict[str, int] = {}
            for vertices in mesh.findall("vertices"):
                for inp in vertices.findall("input"):
                    if inp.get("semantic") != "POSITION":
                        continue
                    source = by_id.get((inp.get("source") or "").lstrip("#"))
                    array = source.find("float_array") if source is not None else None
                    cloud = floats(array, "a POSITION source").reshape(-1, 3)
                    starts[vertices.get("id") or ""] = count
                    clouds.append(cloud)
                    count += len(cloud)
            for primitive in (*mesh.findall("triangles"), *mesh.findall("polylist"), *mesh.findall("polygons")):
                inputs = primitive.findall("input")
                stride = 1 + max((int(i.get("offset", "0")) for i in inputs), default=0)
                vertex = next((i for i in inputs if i.get("semantic") == "VERTEX"), None)
                if vertex is None:
                    continue
                start = starts.get((vertex.get("source") or "").lstrip("#"), 0)
                offset = int(vertex.get("offset", "0"))
                lists = primitive.findall("p")
                if primitive.tag == "polylist":
                    sizes = floats(primitive.find("vcount"), "a polylist's vcount").astype(int).tolist()
                else:
                    sizes = None
                for p in lists:
                    index = floats(p, "a primitive's p").astype(np.int64)[offset::stride] + start
                    if primitive.tag == "triangles":
                        faces.append(index[: len(index) // 3 * 3].reshape(-1, 3))
                    elif sizes is not None:
                        at = 0
                        for n in sizes:
                            faces.append(np.array(_fan(index[at : at + n].tolist()), dtype=np.int64).reshape(-1, 3))
                            at += n
                    else:
                        faces.append(np.array(_fan(index.tolist()), dtype=np.int64).reshape(-1, 3))
        positions = np.concatenate(clouds) if clouds else np.empty((0, 3))
        return positions, np.concatenate(faces) if faces else np.empty((0, 3), np.int64)

    def local(node: ET.Element) -> np.ndarray:
        m = np.eye(4)
        for child in node:
            values = np.array((child.text or "").split(), dtype=np.float64)
            t = np.eye(4)
            if child.tag == "matrix" and values.size == 16:
                t = values.reshape(4, 4)
            elif child.tag == "translate" and values.size == 3:
                t[:3, 3] = values
            elif child.tag == "scale" and values.size == 3:
                t[:3, :3] = np.diag(values)
            elif child.tag == "rotate" and values.size == 4:
                axis, angle = values[:3] / np.linalg.norm(values[:3]), np.radians(values[3])
                t[:3, :3] = axis_angle_matrix(axis, angle)
            m = m @ t
        return m

    out: list[tuple[np.ndarray, np.ndarray]] = []

    def walk(node: ET.Element, parent: np.ndarray) -> None:
        m = parent @ local(node)
        for inst in node.findall("instance_geometry"):
            geometry = by_id.get((inst.get("url") or "").lstrip("#"))
            if geometry is not None:
                v, f = geometry_mesh(geometry)
                out.append((v @ m[:3, :3].T + m[:3, 3], f))
        for child in node.findall("node"):
            walk(child, m)

    try:
        scenes = list(root.iter("visual_scene"))
        for scene in scenes:
            for node in scene.findall("node"):
                walk(node, np.eye(4))
        if not scenes:  # no scene: take every geometry as is
            out = [geometry_mesh(g) for g in root.iter("geometry")]
    except ValueError:
        raise UrdfError(f"mesh {path}: malformed COLLADA positions or faces") from None
    vertices, faces, count = [], [], 0
    for v, f in out:
        vertices.append(v)
        faces.append(f + count)
        count += len(v)
    if not vertices:
        return np.empty((0, 3)), np.empty((0, 3), np.int64)
    return np.concatenate(vertices) * meter, np.concatenate(faces)


def _sizes(text: str | None, n: int, what: str) -> tuple[float, ...]:
    """`n` dimensions of a primitive: finite and not negative (a negative size would
    describe the same points as its absolute value and hide a typo)."""
    values = _floats(text, n, (0.0,) * n, what)
    if any(v < 0 for v in values):
        raise UrdfError(f"{what} must not be negative, got {text!r}")
    return values


def _mesh_scale(text: str | None, what: str) -> tuple[float, ...]:
    """A mesh's scale: finite and non-zero per axis. A negative factor mirrors the mesh
    (URDFs use it for left/right parts), which keeps its vertices meaningful; zero
    would flatten it."""
    scale = _floats(text, 3, (1.0, 1.0, 1.0), what)
    if any(v == 0 for v in scale):
        raise UrdfError(f"{what} must not be zero on any axis, got {text!r}")
    return scale


def _primitive_vertices(geometry: ET.Element, what: str) -> np.ndarray:
    """Points whose enclosing capsule encloses the primitive."""
    shape = next(iter(geometry), None)
    if shape is None:
        raise UrdfError(f"{what}: empty <geometry>")
    ring = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    if shape.tag == "box":
        sx, sy, sz = _sizes(shape.get("size"), 3, f"{what} box size")
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
        return corners * [sx / 2, sy / 2, sz / 2]
    if shape.tag in ("cylinder", "capsule"):
        (r,) = _sizes(shape.get("radius"), 1, f"{what} {shape.tag} radius")
        (length,) = _sizes(shape.get("length"), 1, f"{what} {shape.tag} length")
        # The polygon is circumscribed so the cylinder stays inside.
        r_out = r / math.cos(math.pi / len(ring))
        circle = np.stack([r_out * np.cos(ring), r_out * np.sin(ring)], axis=1)
        ends = [length / 2 + (r if shape.tag == "capsule" else 0.0)]
        return np.concatenate([np.column_stack([circle, np.full(len(ring), z)]) for z in (-ends[0], ends[0])])
    if shape.tag == "sphere":
        (r,) = _sizes(shape.get("radius"), 1, f"{what} sphere radius")
        return r * _unit_sphere_hull()
    raise UrdfError(f"{what}: unsupported geometry <{shape.tag}>")


@functools.cache
def _unit_sphere_hull(splits: int = 3) -> np.ndarray:
    """Vertices of a polyhedron that encloses the unit sphere: an icosahedron with each
    face split in four `splits` times, pushed out until its nearest face plane touches
    the sphere, so that any body enclosing the vertices encloses the sphere in any pose
    and beside other geometry (the six axis points do only alone)."""
    g = (1 + 5**0.5) / 2
    vertices = [np.array(v, float) for v in [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g),
                                             (0, -1, -g), (0, 1, -g), (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)]]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
             (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
             (8, 6, 7), (9, 8, 1)]
    vertices = [v / np.linalg.norm(v) for v in vertices]
    for _ in range(splits):
        middle: dict[tuple[int, int], int] = {}

        def between(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in middle:
                m = vertices[a] + vertices[b]
                vertices.append(m / np.linalg.norm(m))
                middle[key] = len(vertices) - 1
            return middle[key]

        split = []
        for a, b, c in faces:
            ab, bc, ca = between(a, b), between(b, c), between(c, a)
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    points = np.array(vertices)
    # The distance from the centre to each face's plane; the nearest sets the push.
    a, b, c = np.moveaxis(points[np.array(faces)], 1, 0)
    normals = np.cross(b - a, c - a)
    inradius = np.min(np.abs(np.sum(normals * a, axis=1)) / np.linalg.norm(normals, axis=1))
    return points / inradius


def parse_urdf(path: str | Path, *, geometry: str = "collision") -> UrdfRobot:
    """Parse a URDF file: links (root first), joints and each link's geometry vertices.

    ``geometry`` picks the ``collision`` elements (default) or the ``visual`` ones; a
    link without the chosen kind falls back to the other.
    """
    if geometry not in ("collision", "visual"):
        raise ValueError(f"geometry must be 'collision' or 'visual', got {geometry!r}")
    path = Path(path)
    if not path.is_file():
        raise UrdfError(f"URDF file {path} does not exist")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise UrdfError(f"{path} is not valid XML: {exc}") from exc
    if root.tag != "robot":
        raise UrdfError(f"{path}: the root element is <{root.tag}>, expected <robot>")

    link_elements = {}
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise UrdfError(f"{path}: a <link> has no name")
        if name in link_elements:
            raise UrdfError(f"{path}: link {name!r} is defined twice")
        link_elements[name] = link
    if not link_elements:
        raise UrdfError(f"{path}: no <link> elements")

    joints: list[UrdfJoint] = []
    for j in root.findall("joint"):
        name = j.get("name") or "?"
        kind = j.get("type")
        what = f"{path.name}: joint {name!r}"
        if any(other.name == name for other in joints):
            raise UrdfError(f"{what} is defined twice")
        if kind not in ("revolute", "continuous", "prismatic", "fixed"):
            raise UrdfError(f"{what} has unsupported type {kind!r}")
        parent_el, child_el = j.find("parent"), j.find("child")
        if parent_el is None or child_el is None:
            raise UrdfError(f"{what} needs <parent> and <child>")
        parent, child = parent_el.get("link"), child_el.get("link")
        for role, link_name in (("parent", parent), ("child", child)):
            if link_name not in link_elements:
                raise UrdfError(f"{what}: {role} link {link_name!r} is not defined")
        xyz, rpy = _origin(j.find("origin"), what)
        axis_el = j.find("axis")
        axis = _floats(axis_el.get("xyz") if axis_el is not None else None, 3, (1.0, 0.0, 0.0), f"{what} axis")
        lower, upper = -math.inf, math.inf
        limit_el = j.find("limit")
        velocity = math.inf
        if limit_el is not None and limit_el.get("velocity") is not None:
            (velocity,) = _floats(limit_el.get("velocity"), 1, (math.inf,), f"{what} velocity limit")
        if kind in ("revolute", "prismatic"):
            limit = j.find("limit")
            if limit is None or limit.get("lower") is None or limit.get("upper") is None:
                raise UrdfError(f"{what} ({kind}) needs <limit lower=... upper=...>")
            (lower,) = _floats(limit.get("lower"), 1, (0.0,), f"{what} lower limit")
            (upper,) = _floats(limit.get("upper"), 1, (0.0,), f"{what} upper limit")
            if lower > upper:
                raise UrdfError(f"{what}: lower limit {lower} > upper limit {upper}")
        mimic = j.find("mimic")
        joints.append(
            UrdfJoint(name, kind, parent, child, xyz, rpy, axis, lower, upper,  # type: ignore[arg-type]
                      mimic.get("joint") if mimic is not None else None, velocity)
        )

    children = {j.child for j in joints}
    roots = [name for name in link_elements if name not in children]
    if len(roots) != 1:
        raise UrdfError(f"{path}: expected one root link, found {roots or 'none (a cycle)'}")
    links = roots + [name for name in link_elements if name != roots[0]]

    robot = UrdfRobot(name=root.get("name") or path.stem, path=path, links=links, joints=joints)
    other = "visual" if geometry == "collision" else "collision"
    for name, element in link_elements.items():
        parts = element.findall(geometry) or element.findall(other)
        clouds = []
        for part in parts:
            what = f"{path.name}: link {name!r} {part.tag}"
            geom = part.find("geometry")
            if geom is None:
                raise UrdfError(f"{what} has no <geometry>")
            mesh = geom.find("mesh")
            if mesh is not None:
                filename = mesh.get("filename")
                if not filename:
                    raise UrdfError(f"{what}: <mesh> without filename")
                vertices = read_mesh_vertices(resolve_mesh_path(filename, path))
                vertices = vertices * np.array(_mesh_scale(mesh.get("scale"), f"{what} mesh scale"))
            else:
                vertices = _primitive_vertices(geom, what)
            xyz, rpy = _origin(part.find("origin"), what)
            clouds.append(vertices @ rotation_xyz(*rpy).T + np.array(xyz))
        robot.vertices[name] = np.concatenate(clouds) if clouds else None
    return robot
