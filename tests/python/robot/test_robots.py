"""Robot geometry: kinematics against Pinocchio and pybullet, bodies, self-filter,
collision and clearance against FCL and brute force, motion checks and Eq. 4 danger."""

from __future__ import annotations

import numpy as np
import pytest

import earcore
import earcore.robots as robots
import earcore.urdf as urdf_module
from earcore.synthetic import robot_cell_voxels
from reference import motion_danger_reference

# The peer references are test dependencies (`.[test]`); only the tests that compare
# with them skip where they are missing, not the whole module.

ARMS = ["ur3", "ur5", "ur10", "iiwa", "panda"]


@pytest.fixture(scope="module")
def ur5():
    return robots.load("ur5")


def cell_tree(resolution=0.05, seed=0):
    tree = earcore.OcTree(resolution)
    tree.update_nodes(robot_cell_voxels(resolution, seed))
    return tree


def above_table(model, count, seed):
    """UR configurations with the upper arm above the table (shoulder lift in [-π, 0]),
    the rest uniform in ±π: what a planner in the cell mostly samples."""
    qs = model.random_configurations(count, seed=seed)
    qs[:, 1] = np.random.default_rng(seed).uniform(-np.pi, 0, count)
    return qs


# --- kinematics -------------------------------------------------------------------


@pytest.mark.parametrize("name", ARMS)
def test_fk_equals_pinocchio(name):
    """Double-precision reference: Pinocchio's frame placements from the same URDF."""
    pin = pytest.importorskip("pinocchio")
    model = robots.load(name)
    ref = pin.buildModelFromUrdf(str(robots.urdf_path(name)))
    data = ref.createData()
    qs = model.random_configurations(200, seed=3)
    ours = model.fk(qs)
    assert ours.shape == (200, len(model.link_names), 4, 4)
    order = [model.joint_names.index(ref.names[j]) for j in range(1, ref.njoints)]
    link_index = {n: i for i, n in enumerate(model.link_names)}
    frames = [(f, link_index[fr.name]) for f, fr in enumerate(ref.frames) if fr.type == pin.FrameType.BODY and fr.name in link_index]
    assert len(frames) >= model.dof
    worst = 0.0
    for k, q in enumerate(qs):
        pin.framesForwardKinematics(ref, data, q[order])
        for f, link in frames:
            worst = max(worst, np.abs(data.oMf[f].homogeneous - ours[k, link]).max())
    assert worst < 1e-9


def pybullet_link_frames(name, qs):
    """world_from_link of every pybullet link, relative to the root link's URDF frame."""
    p = pytest.importorskip("pybullet")
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(robots.urdf_path(name)), useFixedBase=True, physicsClientId=cid)
        joints = [p.getJointInfo(body, j, physicsClientId=cid) for j in range(p.getNumJoints(body, physicsClientId=cid))]
        movable = [j[0] for j in joints if j[2] != p.JOINT_FIXED]
        names = [j[12].decode() for j in joints]
        out = []
        for q in qs:
            for j, v in zip(movable, q):
                p.resetJointState(body, j, v, physicsClientId=cid)
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            info = p.getDynamicsInfo(body, -1, physicsClientId=cid)
            root = p.multiplyTransforms(pos, orn, *p.invertTransform(info[3], info[4]))
            inverse = p.invertTransform(*root)
            frames = {}
            for j, link in enumerate(names):
                state = p.getLinkState(body, j, computeForwardKinematics=True, physicsClientId=cid)
                lp, lo = p.multiplyTransforms(*inverse, state[4], state[5])
                m = np.eye(4)
                m[:3, :3] = np.reshape(p.getMatrixFromQuaternion(lo), (3, 3))
                m[:3, 3] = lp
                frames[link] = m
            out.append(frames)
        return out
    finally:
        p.disconnect(cid)


@pytest.mark.parametrize("name", ["ur5", "ur10", "iiwa", "panda"])
def test_fk_equals_pybullet_to_its_single_precision(name):
    """pybullet stores the model in float32 (a 0.089159 m offset comes back 3e-9 off),
    so it agrees to ~1e-6; the 1e-9 check is against Pinocchio above."""
    model = robots.load(name)
    qs = model.random_configurations(30, seed=4)
    ours = model.fk(qs)
    reference = pybullet_link_frames(name, qs)
    worst = max(
        np.abs(ours[k, i] - reference[k][link]).max()
        for k in range(len(qs))
        for i, link in enumerate(model.link_names)
        if link in reference[k]
    )
    assert worst < 2e-6


def test_fk_single_and_batch_agree_and_base_moves_everything(ur5):
    q = ur5.random_configurations(1, seed=1)[0]
    single = ur5.fk(q)
    assert single.shape == (len(ur5.link_names), 4, 4)
    assert np.array_equal(single, ur5.fk(q[None])[0])
    moved = robots.load("ur5")
    base = np.eye(4)
    base[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    base[:3, 3] = [0.5, -0.2, 0.8]
    moved.base = base
    assert np.allclose(moved.fk(q), base @ single, atol=1e-14)


# --- bodies -----------------------------------------------------------------------


def inside_bodies(points, bodies):
    """Brute-force membership in capsules and flat-ended cylinders."""
    inside = np.zeros(len(points), dtype=bool)
    for a, b, r, shape in zip(bodies["a"], bodies["b"], bodies["radius"], bodies["shape"]):
        d = b - a
        t_raw = (points - a) @ d / (d @ d)
        t = np.clip(t_raw, 0, 1)
        dist = np.linalg.norm(points - (a + t[:, None] * d), axis=1)
        inside |= (dist <= r) & ((shape == "capsule") | ((t_raw >= 0) & (t_raw <= 1)))
    return inside


@pytest.mark.parametrize("name", ARMS)
def test_bodies_enclose_the_collision_meshes(name):
    """Every collision-mesh vertex lies inside its link's body, by at least the padding."""
    from earcore.urdf import parse_urdf

    model = robots.load(name)
    urdf = parse_urdf(robots.urdf_path(name))
    q = model.random_configurations(1, seed=5)[0]
    frames = model.fk(q)
    placed = model.bodies(q)
    for slot, link in enumerate(placed["link"]):
        vertices = urdf.vertices[model.link_names[link]]
        world = vertices @ frames[link][:3, :3].T + frames[link][:3, 3]
        one = {key: (np.asarray(v)[slot : slot + 1] if key != "shape" else [v[slot]]) for key, v in placed.items()}
        shrunk = dict(one, radius=one["radius"] - model.padding * 0.999)
        assert inside_bodies(world, one).all()
        if one["shape"][0] == "capsule":
            assert inside_bodies(world, shrunk).all()


def test_fit_body_shapes():
    rng = np.random.default_rng(0)
    can = np.column_stack([rng.normal(size=(2000, 2)), rng.uniform(-0.06, 0.06, 2000)])
    can[:, :2] *= 0.06 / np.linalg.norm(can[:, :2], axis=1, keepdims=True).max()
    def body(a, b, r, shape):
        # A hair of slack (radius and ends) for the points the fit puts exactly on the surface.
        e = 1e-9 * (b - a) / np.linalg.norm(b - a)
        return {"a": (a - e)[None], "b": (b + e)[None], "radius": np.array([r + 1e-9]), "shape": np.array([shape])}

    def fit(*args):
        a, b, r, shape = earcore.fit_body(can, *args)
        return np.asarray(a), np.asarray(b), r, shape

    a, b, r, shape = fit(0.0)
    assert shape == "cylinder"
    # The can's axis and length, every point inside, and a radius between the half
    # width of its widest pair of points (any enclosing circle's least) and 6 cm (the
    # circle about the origin encloses them all).
    xy = can[:, :2]
    half_width = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(axis=2).max()) / 2
    assert half_width - 1e-9 <= r <= 0.0601
    assert abs((b - a)[2]) == pytest.approx(0.12, abs=2e-3) and np.abs((b - a)[:2]).max() < 2e-3
    assert inside_bodies(can, body(a, b, r, shape)).all()
    a, b, r, shape = fit(0.01, "capsule")
    assert shape == "capsule"
    assert r >= half_width + 0.01 - 1e-9 and inside_bodies(can, body(a, b, r, shape)).all()
    with pytest.raises(ValueError, match="shape"):
        earcore.fit_body(can, 0.0, "sphere")
    with pytest.raises(ValueError):
        earcore.fit_body(np.empty((0, 3)))


# --- self-filter ------------------------------------------------------------------


def test_self_filter_equals_brute_force(ur5):
    rng = np.random.default_rng(1)
    for q in ur5.random_configurations(5, seed=2):
        placed = ur5.bodies(q)
        centre = placed["a"].mean(axis=0)
        points = centre + rng.uniform(-0.9, 0.9, size=(100_000, 3))
        keep = ur5.self_filter(points, q)
        assert keep.dtype == bool and keep.shape == (len(points),)
        assert np.array_equal(keep, ~inside_bodies(points, placed))
        assert (~keep).sum() > 100


def render_robot_frame(p, cid, body, eye, target, width=320, height=240, fov=60.0, near=0.05, far=4.0):
    """Points (N, 3) in the world frame and whether each belongs to `body`."""
    view = p.computeViewMatrix(eye, target, [0, 0, 1], physicsClientId=cid)
    projection = p.computeProjectionMatrixFOV(fov, width / height, near, far, physicsClientId=cid)
    _, _, _, depth, seg = p.getCameraImage(
        width, height, view, projection, renderer=p.ER_TINY_RENDERER, physicsClientId=cid
    )
    depth = np.reshape(depth, (height, width))
    seg = np.reshape(seg, (height, width))
    valid = depth < 1.0
    z = far * near / (far - (far - near) * depth)
    fy = 0.5 * height / np.tan(np.radians(fov) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x_cam = (u - width / 2) / fy * z
    y_cam = (v - height / 2) / fy * z
    # OpenGL camera: x right, y up, looking down -z.
    cam = np.stack([x_cam, -y_cam, -z], axis=-1)[valid]
    view_m = np.reshape(view, (4, 4)).T
    world_from_camera = np.linalg.inv(view_m)
    world = cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    return world, (seg[valid] & ((1 << 24) - 1)) == body


def farther_than(points, vertices, distance):
    """Whether each point is farther than `distance` from every vertex (grid buckets of
    that size: only the 27 around a point can hold a closer vertex)."""
    keys = np.floor(vertices / distance).astype(np.int64)
    order = np.lexsort(keys.T)
    keys, vertices = keys[order], vertices[order]
    cells, starts = np.unique(keys, axis=0, return_index=True)
    ends = np.append(starts[1:], len(keys))
    bucket = {tuple(c): (a, b) for c, a, b in zip(cells, starts, ends)}
    far = np.ones(len(points), dtype=bool)
    near_box = np.all((points >= vertices.min(0) - distance) & (points <= vertices.max(0) + distance), axis=1)
    point_keys = np.floor(points / distance).astype(np.int64)
    for i in np.flatnonzero(near_box):
        p, k = points[i], point_keys[i]
        for offset in np.ndindex(3, 3, 3):
            span = bucket.get((k[0] + offset[0] - 1, k[1] + offset[1] - 1, k[2] + offset[2] - 1))
            if span and (((vertices[span[0] : span[1]] - p) ** 2).sum(axis=1) <= distance**2).any():
                far[i] = False
                break
    return far


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_self_filter_on_rendered_frames(name):
    """Acceptance: ≥ 99% of the robot's own points removed, ≤ 0.5% of the other points
    farther than 2 cm from the robot (its mesh vertices) removed."""
    p = pytest.importorskip("pybullet")
    from earcore.urdf import parse_urdf

    model = robots.load(name)
    urdf = parse_urdf(robots.urdf_path(name), geometry="visual")
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(robots.urdf_path(name)), useFixedBase=True, physicsClientId=cid)
        movable = [j for j in range(p.getNumJoints(body, physicsClientId=cid)) if p.getJointInfo(body, j, physicsClientId=cid)[2] != p.JOINT_FIXED]
        # Clutter near the robot: boxes and a floor.
        p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[2, 2, 0.01], physicsClientId=cid),
                          p.createVisualShape(p.GEOM_BOX, halfExtents=[2, 2, 0.01], physicsClientId=cid), [0, 0, -0.011], physicsClientId=cid)
        rng = np.random.default_rng(7)
        for _ in range(6):
            half = rng.uniform(0.05, 0.15, 3)
            pos = [*rng.uniform(-0.8, 0.8, 2), half[2]]
            if np.linalg.norm(pos[:2]) < 0.35:
                continue
            p.createMultiBody(0, -1, p.createVisualShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid), pos, physicsClientId=cid)
        own_total = own_kept = other_total = other_removed = 0
        for q in model.random_configurations(6, seed=8):
            for j, v in zip(movable, q):
                p.resetJointState(body, j, v, physicsClientId=cid)
            angle = rng.uniform(0, 2 * np.pi)
            eye = [1.6 * np.cos(angle), 1.6 * np.sin(angle), rng.uniform(0.6, 1.4)]
            points, is_robot = render_robot_frame(p, cid, body, eye, [0, 0, 0.35])
            keep = model.self_filter(points, q)
            own_total += is_robot.sum()
            own_kept += (keep & is_robot).sum()
            # Distance of the other points to the robot's visual mesh vertices.
            frames = model.fk(q)
            vertices = np.concatenate([
                urdf.vertices[link] @ frames[i][:3, :3].T + frames[i][:3, 3]
                for i, link in enumerate(model.link_names) if urdf.vertices.get(link) is not None
            ])
            far = farther_than(points[~is_robot], vertices, 0.02)
            other_total += far.sum()
            other_removed += (~keep[~is_robot] & far).sum()
        assert own_total > 2000
        print(f"{name}: removed {1 - own_kept / own_total:.2%} of {own_total} own points, "
              f"{other_removed / other_total:.3%} of {other_total} points farther than 2 cm")
        assert 1 - own_kept / own_total >= 0.99, (own_kept, own_total)
        assert other_removed / other_total <= 0.005, (other_removed, other_total)
    finally:
        p.disconnect(cid)


# --- collision against FCL ---------------------------------------------------------


def fcl_body(a, b, r, shape):
    fcl = pytest.importorskip("fcl")
    d = b - a
    length = np.linalg.norm(d)
    z = d / length
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    rot = np.column_stack([x, np.cross(z, x), z])
    geom = fcl.Capsule(r, length) if shape == "capsule" else fcl.Cylinder(r, length)
    return fcl.CollisionObject(geom, fcl.Transform(rot, (a + b) / 2))


def fcl_boxes(tree):
    fcl = pytest.importorskip("fcl")
    centres, sizes = tree.occupied_voxels()
    objects = [fcl.CollisionObject(fcl.Box(s, s, s), fcl.Transform(np.eye(3), c)) for c, s in zip(centres, sizes)]
    manager = fcl.DynamicAABBTreeCollisionManager()
    manager.registerObjects(objects)
    manager.setup()
    return manager


def fcl_reference(model, manager, q):
    """(any moving body collides, min distance of the moving bodies) per FCL."""
    fcl = pytest.importorskip("fcl")
    placed = model.bodies(q)
    moving = [not model.fixed_to_root[link] for link in placed["link"]]
    hit, dist = False, np.inf
    for a, b, r, shape, m in zip(placed["a"], placed["b"], placed["radius"], placed["shape"], moving):
        if not m:
            continue
        obj = fcl_body(a, b, r, shape)
        cdata = fcl.CollisionData(request=fcl.CollisionRequest())
        manager.collide(obj, cdata, fcl.defaultCollisionCallback)
        hit |= cdata.result.is_collision
        ddata = fcl.DistanceData()
        manager.distance(obj, ddata, fcl.defaultDistanceCallback)
        dist = min(dist, ddata.result.min_distance)
    return hit, dist


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_collision_agrees_with_fcl(ur5, seed):
    """No false 'free' ever; a 'collision' FCL calls free only within 1e-6 m of touching."""
    rng = np.random.default_rng(seed)
    tree = earcore.OcTree(0.05)
    # The robot on a 0.3 m pedestal: a floor below it and scattered voxels around.
    cells = rng.uniform([-1.0, -1.0, -0.25], [1.0, 1.0, 1.2], size=(40, 3))
    floor = np.stack(np.meshgrid(np.arange(-1, 1, 0.05), np.arange(-1, 1, 0.05), [-0.325]), -1).reshape(-1, 3)
    tree.update_nodes(np.vstack([cells, floor]))
    manager = fcl_boxes(tree)
    qs = ur5.random_configurations(150, seed=seed)
    hit = ur5.check_configurations(tree, qs, self_collision=False)
    assert 0 < hit.sum() < len(qs)
    for q, ours in zip(qs, hit):
        reference, distance = fcl_reference(ur5, manager, q)
        if reference:
            assert ours, "reported free where FCL finds a collision"
        elif ours:
            # Both sides run GJK on cylinders (tolerances ~1e-6 m).
            assert distance < 1e-5, f"false collision {distance} m from touching"


@pytest.mark.parametrize("seed", [0, 1])
def test_touches_voxels_agrees_with_fcl_and_the_clearance(ur5, seed):
    """The yes/no box test the reflexes use: FCL's collision verdict (up to GJK's
    tolerance at touching) and the sign of `clearance_to_voxels`."""
    rng = np.random.default_rng(seed)
    tree = earcore.OcTree(0.05)
    tree.update_nodes(rng.uniform([-0.8, -0.8, 0.0], [0.8, 0.8, 1.0], size=(80, 3)))
    centres, sizes = tree.occupied_voxels()
    assert np.all(sizes == 0.05)
    manager = fcl_boxes(tree)
    qs = ur5.random_configurations(150, seed=seed)
    touches = ur5.touches_voxels(centres, 0.05, qs)
    distance = ur5.clearance_to_voxels(centres, 0.05, qs)["distance"]
    assert touches.dtype == bool and touches.shape == (len(qs),)
    assert 0 < touches.sum() < len(qs)
    for q, ours, d in zip(qs, touches, distance):
        reference, fcl_distance = fcl_reference(ur5, manager, q)
        if reference:
            assert ours, "reported free where FCL finds a collision"
        elif ours:
            assert fcl_distance < 1e-5, f"false touch {fcl_distance} m from touching"
        assert ours == (d <= 0) or abs(d) < 1e-6
    # A compact cluster (a hand): most bodies' bounds miss it and skip the box tests.
    for _ in range(10):
        centre = rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 0.8])
        cluster = centre + 0.05 * rng.integers(-2, 3, size=(25, 3))
        touches = ur5.touches_voxels(cluster, 0.05, qs)
        distance = ur5.clearance_to_voxels(cluster, 0.05, qs)["distance"]
        assert np.all((touches == (distance <= 0)) | (np.abs(distance) < 1e-6))
    assert not ur5.touches_voxels(np.zeros((0, 3)), 0.05, qs[:3]).any()
    with pytest.raises(ValueError, match="finite"):
        ur5.touches_voxels(np.array([[np.nan, 0, 0]]), 0.05, qs[0])
    with pytest.raises(ValueError, match=">= 0"):
        ur5.touches_voxels(centres, -0.05, qs[0])


def test_clearance_agrees_with_fcl(ur5):
    tree = cell_tree()
    manager = fcl_boxes(tree)
    qs = above_table(ur5, 400, seed=11)
    free = qs[~ur5.check_configurations(tree, qs, self_collision=False)][:40]
    assert len(free) >= 10
    result = ur5.clearance(tree, free)
    errors = []
    for q, d, on_robot, on_obstacle in zip(free, result["distance"], result["on_robot"], result["on_obstacle"]):
        _, reference = fcl_reference(ur5, manager, q)
        assert d >= reference - 1e-5  # GJK tolerances on cylinders, both sides
        errors.append(d - reference)
        assert np.linalg.norm(on_obstacle - on_robot) == pytest.approx(d, abs=1e-6)
    errors = np.array(errors)
    # Exact for most; never more than the documented bound.
    assert np.median(errors) < 1e-5
    assert errors.max() <= 0.05 * (0.25 + 1.5 * np.sqrt(3))


def test_clearance_of_an_empty_map(ur5):
    out = ur5.clearance(earcore.OcTree(0.05), np.zeros(6))
    assert out["distance"] == np.inf and out["link"] == -1 and np.isnan(out["on_robot"]).all()


def test_collision_follows_map_updates_and_base_moves():
    model = robots.load("ur5")
    tree = earcore.OcTree(0.05)
    q = np.array([0.0, -np.pi / 2, 0, -np.pi / 2, 0, 0])  # arm straight up
    assert not model.check_configurations(tree, q)
    top = model.fk(q)[model.link_names.index("wrist_2_link")][:3, 3]
    tree.update_nodes(top[None])
    hit, link = model.check_configurations(tree, q, return_links=True)
    assert hit and model.link_names[link] in {"wrist_1_link", "wrist_2_link", "wrist_3_link", "forearm_link"}
    shifted = np.eye(4)
    shifted[0, 3] = 0.6
    model.base = shifted
    assert not model.check_configurations(tree, q)


def test_current_obstacles_only():
    model = robots.load("ur5")
    tree = earcore.OcTree(0.05)
    q = np.array([0.0, -np.pi / 2, 0, -np.pi / 2, 0, 0])
    elbow = model.fk(q)[model.link_names.index("forearm_link")][:3, 3]
    tree.update_nodes(elbow[None])
    # Occupied, but not seen in the last frame.
    assert model.check_configurations(tree, q)
    assert not model.check_configurations(tree, q, obstacles="current")
    tree.insert_point_cloud(elbow[None], elbow + [1.0, 0, 0])
    tree.end_frame(1 / 15)
    assert model.check_configurations(tree, q, obstacles="current")


def test_self_collision(ur5):
    folded = np.array([0.0, -np.pi / 2, 3.0, 0, 0, 0])  # forearm folded onto the upper arm
    assert ur5.self_collisions(folded[None])[0]
    assert ur5.check_configurations(earcore.OcTree(0.05), folded)
    assert not ur5.check_configurations(earcore.OcTree(0.05), folded, self_collision=False)
    home = np.array([0.0, -np.pi / 2, 0, -np.pi / 2, 0, 0])
    assert not ur5.self_collisions(home[None])[0]
    pairs = ur5.self_collision_pairs
    links = ur5.link_names
    assert (links.index("upper_arm_link"), links.index("forearm_link")) not in pairs  # adjacent


@pytest.mark.parametrize("name", ["ur3", "ur10"])
def test_compact_wrists_are_not_self_collisions(name):
    """A UR's tool pointing down (wrist 2 at -90°) is its everyday pose: the capsules
    around the first and third wrist links overlap there, the links themselves never
    meet, so that pair is not tested. A forearm folded onto the upper arm still collides."""
    model = robots.load(name)
    links = model.link_names
    tool_down = np.array([0.0, -1.6, 1.2, -1.5, -np.pi / 2, 0.0])
    assert not model.self_collisions(tool_down[None])[0]
    assert (links.index("wrist_1_link"), links.index("wrist_3_link")) not in model.self_collision_pairs
    folded = np.array([0.0, -np.pi / 2, 3.0, 0, 0, 0])
    assert model.self_collisions(folded[None])[0]


# --- motions ----------------------------------------------------------------------


def test_check_motion_equals_interpolated_checks(ur5):
    tree = cell_tree()
    rng = np.random.default_rng(3)
    starts = above_table(ur5, 60, seed=12)
    ends = starts + rng.normal(scale=0.6, size=starts.shape)
    ends = np.clip(ends, ur5.joint_limits[:, 0], ur5.joint_limits[:, 1])
    batch = ur5.check_motions(tree, starts, ends, 0.05)
    for q0, q1, hit in zip(starts, ends, batch):
        steps = int(np.ceil(np.abs(q1 - q0).max() / 0.05))
        path = q0 + np.linspace(0, 1, max(steps, 1) + 1)[:, None] * (q1 - q0)
        assert hit == ur5.check_configurations(tree, path).any()
        assert hit == ur5.check_motion(tree, q0, q1, 0.05)
    assert 0 < batch.sum() < len(batch)


def test_motion_danger_equals_reference(ur5):
    tree = earcore.OcTree(0.05)
    q0 = np.array([0.0, -1.2, 1.0, -1.0, -1.5, 0.0])
    q1 = np.array([1.2, -1.0, 0.8, -1.2, -1.5, 0.3])
    base_cost = ur5.motion_danger(tree, q0, q1, 0.02)
    assert base_cost == pytest.approx(motion_danger_reference(ur5, tree, q0, q1, 0.02), rel=1e-9)
    # Make the region the arm sweeps through dangerous: danger 0.999 there.
    mid = ur5.fk((q0 + q1) / 2)[ur5.link_names.index("forearm_link")][:3, 3]
    blob = mid + np.stack(np.meshgrid(*[np.arange(-0.2, 0.21, 0.05)] * 3), -1).reshape(-1, 3)
    tree.insert_point_cloud(blob, mid + [0, 0, 1.5])
    tree.end_frame(1 / 15)
    risky = ur5.motion_danger(tree, q0, q1, 0.02)
    assert risky == pytest.approx(motion_danger_reference(ur5, tree, q0, q1, 0.02), rel=1e-9)
    assert base_cost < risky < 2 * base_cost


# --- bad input --------------------------------------------------------------------


def test_bad_configurations(ur5):
    tree = earcore.OcTree(0.05)
    with pytest.raises(ValueError, match=r"shape \(6,\) or \(K, 6\)"):
        ur5.fk(np.zeros(5))
    with pytest.raises(ValueError, match="shoulder_lift_joint.*NaN"):
        ur5.check_configurations(tree, [0, np.nan, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="elbow_joint.*outside its limits"):
        ur5.fk([0, 0, 4.0, 0, 0, 0])
    with pytest.raises(ValueError, match="configuration 1"):
        ur5.clearance(tree, [[0] * 6, [0, 0, 0, 0, 0, 99]])
    with pytest.raises(ValueError, match="obstacles"):
        ur5.check_configurations(tree, np.zeros(6), obstacles="everything")
    with pytest.raises(ValueError, match="resolution"):
        ur5.check_motion(tree, np.zeros(6), np.ones(6), 0.0)
    with pytest.raises(ValueError):
        ur5.self_filter(np.array([[0, 0, np.nan]]), np.zeros(6))
    with pytest.raises(TypeError):
        ur5.fk("up")
    with pytest.raises(ValueError, match="base"):
        ur5.base = np.ones((4, 4))


def test_bad_urdfs(tmp_path):
    def urdf(body: str) -> str:
        path = tmp_path / "robot.urdf"
        path.write_text(f'<?xml version="1.0"?><robot name="r">{body}</robot>')
        return path

    link = '<link name="{}"/>'
    joint = '<joint name="j" type="{}"><parent link="a"/><child link="b"/>{}</joint>'
    with pytest.raises(robots.UrdfError, match="not valid XML"):
        robots.RobotModel.from_urdf(urdf("<link name='a'>"))
    with pytest.raises(robots.UrdfError, match="does not exist"):
        robots.RobotModel.from_urdf(tmp_path / "missing.urdf")
    with pytest.raises(robots.UrdfError, match="needs <limit"):
        robots.RobotModel.from_urdf(urdf(link.format("a") + link.format("b") + joint.format("revolute", "")))
    with pytest.raises(robots.UrdfError, match="unsupported type 'floating'"):
        robots.RobotModel.from_urdf(urdf(link.format("a") + link.format("b") + joint.format("floating", "")))
    with pytest.raises(robots.UrdfError, match="child link 'b' is not defined"):
        robots.RobotModel.from_urdf(urdf(link.format("a") + joint.format("fixed", "")))
    # Joints that do not make a tree: the core's check, as a UrdfError naming the file.
    diamond = "".join(f'<joint name="{p}{c}" type="fixed"><parent link="{p}"/><child link="{c}"/></joint>'
                      for p, c in ("ab", "ac", "bd", "cd"))
    with pytest.raises(robots.UrdfError, match="robot.urdf: a tree of 4 links needs 3 joints"):
        robots.RobotModel.from_urdf(urdf("".join(link.format(n) for n in "abcd") + diamond))
    twice = '<joint name="j" type="fixed"><parent link="b"/><child link="c"/></joint>'
    with pytest.raises(robots.UrdfError, match="joint 'j' is defined twice"):
        robots.RobotModel.from_urdf(urdf("".join(link.format(n) for n in "abc") + joint.format("fixed", "") + twice))
    mesh = '<link name="a"><collision><geometry><mesh filename="meshes/gone.stl"/></geometry></collision></link>'
    with pytest.raises(robots.UrdfError, match="gone.stl.*not found"):
        robots.RobotModel.from_urdf(urdf(mesh))
    (tmp_path / "bad.stl").write_bytes(b"\x00" * 10)
    bad = '<link name="a"><collision><geometry><mesh filename="bad.stl"/></geometry></collision></link>'
    with pytest.raises(robots.UrdfError, match="STL"):
        robots.RobotModel.from_urdf(urdf(bad))
    with pytest.raises(ValueError, match="unknown robot 'ur7'"):
        robots.load("ur7")
    assert issubclass(robots.UrdfError, earcore.EarcoreError)


#: How far out the corners of the polyhedron standing in for a URDF sphere lie.
SPHERE_HULL = float(np.linalg.norm(urdf_module._unit_sphere_hull(), axis=1).max())


def test_a_sphere_is_inside_its_body_in_any_pose_and_beside_other_geometry(tmp_path):
    """Every point of a URDF sphere lies in its link's body: rotated by its origin's rpy,
    and sharing a link with a box (the six axis points a sphere once stood for were
    enclosed while the sphere was not: a cylinder of 0.091 m round a 0.1 m sphere)."""
    path = tmp_path / "spheres.urdf"
    path.write_text(
        """<robot name="s">
  <link name="base"><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link>
  <link name="tip">
    <collision><origin xyz="0 0 0.2" rpy="0.3 0.6 0.9"/><geometry><sphere radius="0.1"/></geometry></collision>
    <collision><origin xyz="0 0 0.05"/><geometry><box size="0.02 0.02 0.1"/></geometry></collision>
  </link>
  <joint name="j" type="revolute"><parent link="base"/><child link="tip"/><origin xyz="0 0 0.05"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1"/></joint>
</robot>"""
    )
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(4000, 3))
    surface = directions / np.linalg.norm(directions, axis=1, keepdims=True) * 0.1 * (1 - 1e-9)
    for shape in ("auto", "capsule", "cylinder"):
        arm = robots.RobotModel.from_urdf(path, padding=0.0, shape=shape)
        for q in (-0.7, 0.0, 0.4):
            tip = arm.fk([q])[1]
            points = (surface + [0, 0, 0.2]) @ tip[:3, :3].T + tip[:3, 3]
            assert not np.asarray(arm.self_filter(points, [q], 0.0)).any(), (shape, q)


def _two_link_arm(tmp_path):
    """A base box, a 0.5 m cylinder on a pitch joint, a 3 cm sphere at its tip (no padding)."""
    path = tmp_path / "arm.urdf"
    path.write_text(
        """<robot name="arm">
  <link name="base"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision></link>
  <link name="upper"><collision><origin xyz="0 0 0.25"/><geometry><cylinder radius="0.04" length="0.5"/></geometry></collision></link>
  <link name="tool"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.05"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="wrist" type="fixed"><parent link="upper"/><child link="tool"/><origin xyz="0 0 0.5"/></joint>
</robot>"""
    )
    return robots.RobotModel.from_urdf(path, padding=0.0)


def test_primitive_geometry_and_a_two_link_arm(tmp_path):
    """Primitives (box, cylinder, sphere) and a hand-checkable chain."""
    arm = _two_link_arm(tmp_path)
    assert arm.dof == 1 and arm.link_names == ["base", "upper", "tool"]
    tool = arm.fk([np.pi / 2])[2][:3, 3]
    assert np.allclose(tool, [0.5, 0, 0.05], atol=1e-12)
    a, b, r, shape = arm.link_bodies[2]
    # The sphere is enclosed by a polyhedron whose faces touch it (0.45 % out at the corners).
    assert shape in ("capsule", "cylinder") and r == pytest.approx(0.03 * SPHERE_HULL, abs=1e-9)
    assert 1.0 < SPHERE_HULL < 1.005
    a, b, r, shape = arm.link_bodies[1]
    assert r == pytest.approx(0.04 / np.cos(np.pi / 64), rel=1e-6)  # circumscribed 64-gon
    assert np.linalg.norm(np.subtract(b, a)) == pytest.approx(0.5, abs=1e-6)


def test_a_sphere_body_is_checked_against_the_map(tmp_path):
    """A URDF sphere becomes a zero-length body; checks of it once never returned (its
    free-space step was infinite and wrapped to zero). Verdicts against the analytic
    distance from the sphere's centre to the one voxel, which only the sphere can reach
    (its body: the sphere grown to the corners of the polyhedron enclosing it)."""
    import threading

    arm = _two_link_arm(tmp_path)
    tree = earcore.OcTree(0.02)
    tree.update_nodes(np.array([[0.525, 0.005, 0.05]]))  # cell [0.52, 0.54) × [0, 0.02) × [0.04, 0.06)
    lo, hi = np.array([0.52, 0.0, 0.04]), np.array([0.54, 0.02, 0.06])
    qs = np.linspace(-2.0, 2.0, 801)[:, None]
    centres = np.array([arm.fk(q)[2][:3, 3] for q in qs])
    gap = np.linalg.norm(centres - np.clip(centres, lo, hi), axis=1)
    radius = 0.03 * SPHERE_HULL
    assert np.any(gap <= radius - 1e-4) and np.any(gap > 0.05)
    decided = np.abs(gap - radius) > 1e-6
    result = {}

    def check():
        result["hits"] = np.asarray(arm.check_configurations(tree, qs)).astype(bool)
        result["motions"] = [bool(arm.check_motion(tree, [0.0], [q1])) for q1 in (1.3, 2.0)]

    worker = threading.Thread(target=check, daemon=True)
    worker.start()
    worker.join(timeout=60)
    assert not worker.is_alive(), "the check of a sphere body did not return"
    assert np.array_equal(result["hits"][decided], (gap <= radius)[decided])
    assert result["motions"] == [False, True]  # 0 → 1.3 rad stays clear; 0 → 2 passes the voxel
