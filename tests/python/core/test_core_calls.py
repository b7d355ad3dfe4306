"""The core's map, kinematics and voxel calls against independent references: OctoMap
(pyoctomap), the Python loops they replace, brute force, finite differences and
Pinocchio."""

from __future__ import annotations

import copy
import math
import struct
import threading

import numpy as np
import pytest

from earcore import _earcore as ec

RES = 0.05


# --- helpers -----------------------------------------------------------------------


def cell_centres(rng: np.random.Generator, n: int, span: int = 24, res: float = RES) -> np.ndarray:
    """Centres of `n` random finest cells within ±span/2 cells of the origin."""
    return (rng.integers(-span // 2, span // 2, size=(n, 3)) + 0.5) * res


def block_centres(corner, side: int, res: float = RES) -> np.ndarray:
    """Centres of a side³ block of cells starting at cell `corner` (aligned blocks prune)."""
    idx = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return (np.asarray(corner) + idx + 0.5) * res


def scan():
    """A small real scan (every 40th point of the benchmark frame) and its origin."""
    points, origin = ec.benchmark_frame()
    return np.ascontiguousarray(points[::40]), origin


def build_ours(seed: int, res: float = RES):
    """A map with scanned free space (pruned), clamped blocks (pruned), and random
    cells hit or missed a few times, plus the same operations as a replay list."""
    rng = np.random.default_rng(seed)
    tree = ec.OcTree(res)
    ops = []
    points, origin = scan()
    tree.insert_point_cloud(points, origin)
    ops.append(("scan", points, origin))
    for corner, side, hit in [((0, 0, 0), 4, True), ((-4, -4, 0), 4, False), ((2, -2, -2), 2, True)]:
        centres = block_centres(corner, side, res)
        for _ in range(12):
            tree.update_nodes(centres, occupied=hit)
            ops.append(("cells", centres, hit))
    for _ in range(6):
        centres = cell_centres(rng, 80, res=res)
        hit = bool(rng.random() < 0.5)
        tree.update_nodes(centres, occupied=hit)
        ops.append(("cells", centres, hit))
    return tree, ops


def build_octomap(octomap, ops, res: float = RES):
    ref = octomap.OcTree(res)
    for op in ops:
        if op[0] == "scan":
            ref.insertPointCloud(op[1], op[2])
        else:
            for p in op[1]:
                ref.updateNode(p, bool(op[2]))
    return ref


def ot_bytes(tree, tmp_path) -> bytes:
    path = tmp_path / "tree.ot"
    tree.write(path)
    return path.read_bytes()


def f32(x) -> float:
    return float(np.float32(x))


def logodds(p: float) -> float:
    return math.log(p / (1 - p))


@pytest.fixture
def octomap():
    return pytest.importorskip("pyoctomap")


# --- 1. OcTree.copy ------------------------------------------------------------------


def danger_state(tree):
    c, s, v = tree.danger_voxels()
    o, _ = tree.current_obstacles()
    return c.tobytes(), s.tobytes(), v.tobytes(), o.tobytes()


def params(tree):
    return (tree.resolution, tree.prob_hit, tree.prob_miss, tree.clamping_min, tree.clamping_max,
            tree.occupancy_threshold, tree.danger_alpha, tree.decay_mode)


@pytest.mark.parametrize("how", ["copy", "copy.copy", "copy.deepcopy"])
def test_copy_is_full_and_independent(tmp_path, how):
    tree = ec.OcTree(0.04, prob_hit=0.8, prob_miss=0.35, clamping_min=0.15, clamping_max=0.95,
                     occupancy_threshold=0.6, danger_alpha=0.5, decay_mode="always")
    points, origin = scan()
    tree.insert_point_cloud(points[: len(points) // 2], origin)
    tree.end_frame(0.1)
    tree.insert_point_cloud(points[len(points) // 2 :], origin)
    tree.end_frame(0.1)
    # A frame left open: its hits and free sightings must be copied too.
    tree.insert_point_cloud(points[::3], origin)
    take = {"copy": lambda t: t.copy(), "copy.copy": copy.copy, "copy.deepcopy": copy.deepcopy}[how]
    twin = take(tree)
    assert type(twin) is ec.OcTree and twin is not tree
    assert params(twin) == params(tree)
    assert ot_bytes(twin, tmp_path) == ot_bytes(tree, tmp_path)
    assert danger_state(twin) == danger_state(tree) and len(tree.danger_voxels()[0]) > 100
    assert twin.size() == tree.size() and twin.num_leaf_nodes() == tree.num_leaf_nodes()
    # Closing the open frame gives the same report and state on both.
    assert repr(twin.end_frame(0.2)) == repr(tree.end_frame(0.2))
    assert danger_state(twin) == danger_state(tree)
    # Changing the copy leaves the original alone, and the other way round.
    before, danger = ot_bytes(tree, tmp_path), danger_state(tree)
    twin.update_nodes(cell_centres(np.random.default_rng(1), 50), occupied=True)
    twin.end_frame(30.0)
    twin.danger_alpha, twin.decay_mode = 0.1, "observed"
    assert ot_bytes(tree, tmp_path) == before and danger_state(tree) == danger
    assert (tree.danger_alpha, tree.decay_mode) == (0.5, "always")
    twin.clear()
    assert ot_bytes(tree, tmp_path) == before and tree.size() > 0
    other = tree.copy()
    tree.clear()
    assert other.size() > 0


def test_a_copy_is_a_new_map_for_the_collision_index_cache():
    """A copy starts a new identity: the robot's cached index of the original (same
    contents, same write count) is not reused for it after either changes."""
    link_names = ["base", "arm"]
    joints = [("j", "revolute", 0, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -3.0, 3.0)]
    bodies = [None, ((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.05, "capsule")]
    robot = ec.RobotModel(link_names, joints, bodies)
    tree = ec.OcTree(RES)
    obstacle = np.array([[0.425, 0.025, 0.025]])
    tree.update_nodes(obstacle, occupied=True)
    q = np.array([0.0])
    assert robot.check_configurations(tree, q)
    twin = tree.copy()
    assert robot.check_configurations(twin, q)
    twin.set_log_odds(obstacle, -math.inf)
    assert not robot.check_configurations(twin, q)
    assert robot.check_configurations(tree, q)
    # Same number of writes on a fresh copy of the original: still its own map.
    third = tree.copy()
    tree.set_log_odds(obstacle, -math.inf)
    assert not robot.check_configurations(tree, q)
    assert robot.check_configurations(third, q)


# --- 2. set_log_odds / update_log_odds -----------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_set_log_odds_equals_octomap(octomap, tmp_path, seed):
    """OctoMap's setNodeValue per cell, which pyoctomap does not wrap, done through
    updateNode: a bound by one huge update, any other value v by the lower clamp
    and then v − clamp_min (values chosen so that this float sum is exact)."""
    ours, ops = build_ours(seed)
    ref = build_octomap(octomap, ops)
    assert ot_bytes(ours, tmp_path) == ref.write()
    lo, hi = ref.getClampingThresMinLog(), ref.getClampingThresMaxLog()
    rng = np.random.default_rng(100 + seed)
    for value in [math.inf, -math.inf, f32(lo + 0.75), f32(lo + 2.0), f32(lo) + 1.5, hi, lo]:
        step = np.float32(value) - np.float32(lo)
        if lo < value < hi:
            assert np.float32(lo) + step == np.float32(value), "the reference's sum must be exact"
        cells = np.vstack([cell_centres(rng, 150), block_centres((0, 0, 0), 4)[:30]])
        cells = np.vstack([cells, cells[:40]])  # duplicates
        ours.set_log_odds(cells, value)
        for p in cells:
            if value == math.inf or value >= hi:
                ref.updateNode(p, 1e6)
            else:
                ref.updateNode(p, -1e6)
                if value > lo:
                    ref.updateNode(p, float(step))
        assert ot_bytes(ours, tmp_path) == ref.write(), f"value {value}"
        want = np.float32(min(max(value, lo), hi))
        assert (ours.log_odds(cells) == want).all()


@pytest.mark.parametrize("seed", range(6))
def test_update_log_odds_equals_octomap_update_node(octomap, tmp_path, seed):
    ours, ops = build_ours(seed)
    ref = build_octomap(octomap, ops)
    rng = np.random.default_rng(200 + seed)
    for delta, repeat in [(0.85, 1), (-0.4, 3), (1.7, 2), (-2.5, 12), (0.3, 0)]:
        cells = cell_centres(rng, 200)
        cells = np.vstack([cells, cells[:60]])
        ours.update_log_odds(cells, delta, repeat=repeat)
        for _ in range(repeat):
            for p in cells:
                ref.updateNode(p, float(delta))
        assert ot_bytes(ours, tmp_path) == ref.write(), f"delta {delta}, repeat {repeat}"


@pytest.mark.parametrize("seed", range(4))
def test_the_old_hit_and_miss_loops_are_one_call(tmp_path, seed):
    """Perception's support (8 hits: reaching the upper clamp) is set_log_odds(inf);
    its stale-voxel freeing (10 misses) is update_log_odds(log-odds of a miss,
    repeat=10); one round of hits is update_log_odds(log-odds of a hit). Same trees,
    byte for byte, danger untouched as with update_nodes."""
    rng = np.random.default_rng(300 + seed)
    base, _ = build_ours(seed)
    base.end_frame(0.1)
    danger = danger_state(base)
    support = np.vstack([block_centres((-6, -6, -3), 6), cell_centres(rng, 100)])
    stale = np.vstack([cell_centres(rng, 150), block_centres((0, 0, 0), 4)])
    for cells, occupied, rounds in [(support, True, 8), (stale, False, 10), (support, True, 1), (stale, False, 3)]:
        looped, called = base.copy(), base.copy()
        for _ in range(rounds):
            looped.update_nodes(cells, occupied=occupied)
        if occupied and rounds == 8:
            called.set_log_odds(cells, math.inf)
        else:
            p = base.prob_hit if occupied else base.prob_miss
            called.update_log_odds(cells, logodds(p), repeat=rounds)
        assert ot_bytes(called, tmp_path) == ot_bytes(looped, tmp_path), (occupied, rounds)
        assert danger_state(called) == danger_state(looped) == danger


def test_freeing_near_cells_by_setting_the_lower_clamp(tmp_path):
    """plan_recovery's loop (misses until every cell is free, at most 32 rounds) and
    set_log_odds(cells, -inf) leave the same cells occupied; the trees differ only in
    how free the freed cells are (just below the threshold against the clamp)."""
    base, _ = build_ours(7)
    rng = np.random.default_rng(7)
    near = np.vstack([block_centres((0, 0, 0), 4)[::3], cell_centres(rng, 100)])
    near = near[base.is_occupied(near) == 1]
    assert len(near) > 20
    looped, called = base.copy(), base.copy()
    for _ in range(32):
        still = looped.is_occupied(near) == 1
        if not still.any():
            break
        looped.update_nodes(near[still], occupied=False)
    called.set_log_odds(near, -math.inf)
    (ca, sa), (cb, sb) = looped.occupied_voxels(), called.occupied_voxels()
    order = lambda c, s: np.lexsort((s, c[:, 2], c[:, 1], c[:, 0]))  # noqa: E731
    assert np.array_equal(ca[order(ca, sa)], cb[order(cb, sb)]) and np.array_equal(np.sort(sa), np.sort(sb))
    probe = np.vstack([near, cell_centres(rng, 2000, span=64)])
    assert np.array_equal(looped.is_occupied(probe), called.is_occupied(probe))
    assert (called.log_odds(near) == np.float32(logodds(base.clamping_min))).all()


def test_set_and_update_reject_bad_input_and_change_nothing(tmp_path):
    tree, _ = build_ours(0)
    before = ot_bytes(tree, tmp_path)
    good = cell_centres(np.random.default_rng(0), 5)
    with pytest.raises(ValueError, match="NaN"):
        tree.set_log_odds(good, math.nan)
    with pytest.raises(ValueError, match="finite"):
        tree.update_log_odds(good, math.inf)
    with pytest.raises(ValueError, match="finite"):
        tree.update_log_odds(good, 1e300)  # not a float32 number
    with pytest.raises(ValueError, match="repeat"):
        tree.update_log_odds(good, 0.5, repeat=-1)
    with pytest.raises(ValueError, match="not finite"):
        tree.set_log_odds(np.vstack([good, [np.nan, 0, 0]]), 1.0)
    with pytest.raises(ec.OutOfMapError):
        tree.update_log_odds(np.vstack([good, [1e6, 0, 0]]), 1.0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        tree.set_log_odds(np.zeros((4, 2)), 1.0)
    with pytest.raises(TypeError):
        tree.set_log_odds(good, "high")  # type: ignore[arg-type]
    assert ot_bytes(tree, tmp_path) == before
    tree.set_log_odds(np.zeros((0, 3)), 1.0)
    tree.update_log_odds(np.zeros((0, 3)), 1.0, repeat=5)
    tree.update_log_odds(good, 1.0, repeat=0)
    assert ot_bytes(tree, tmp_path) == before


# --- 3. leaves_at_full_depth ---------------------------------------------------------


def old_box_cells(tree, lo, hi):
    """The box part of planning.reflex.occupied_cells_near as it was: occupied leaves
    meeting the box, pruned ones split into the cells whose index range covers it."""
    centres, sizes, _ = tree.leaves(lo, hi)
    res = tree.resolution
    if len(centres):
        occupied = tree.is_occupied(centres) == 1
        centres, sizes = centres[occupied], sizes[occupied]
    cells = [centres[sizes <= res * 1.5]]
    for centre, size in zip(centres[sizes > res * 1.5], sizes[sizes > res * 1.5]):
        corner = centre - size / 2
        n = int(round(size / res))
        first = np.clip(np.floor((lo - corner) / res - 0.5), 0, n - 1).astype(int)
        last = np.clip(np.ceil((hi - corner) / res - 0.5), 0, n - 1).astype(int)
        axes = [corner[a] + (np.arange(first[a], last[a] + 1) + 0.5) * res for a in range(3)]
        cells.append(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3))
    return np.vstack(cells)


def cell_keys(centres, res):
    return {tuple(k) for k in np.floor(np.asarray(centres) / res).astype(np.int64)}


def random_pruned_tree(seed):
    tree, _ = build_ours(seed)
    tree.prune()
    return tree


@pytest.mark.parametrize("seed", range(8))
def test_leaves_at_full_depth_equals_the_old_box_loop(seed):
    tree = random_pruned_tree(seed)
    rng = np.random.default_rng(400 + seed)
    res = tree.resolution
    for _ in range(15):
        a, b = rng.uniform(-0.7, 0.7, 3), rng.uniform(-0.7, 0.7, 3)
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        centres, log_odds = tree.leaves_at_full_depth(lo, hi, occupied_only=True)
        assert centres.shape == (len(log_odds), 3) and centres.dtype == np.float64 and log_odds.dtype == np.float32
        assert ((centres >= lo) & (centres <= hi)).all()
        old = old_box_cells(tree, lo, hi)
        # The replaced loop also took cells up to half a cell outside the box (its
        # ball filter dropped them); within the box the two agree exactly.
        old = old[((old >= lo) & (old <= hi)).all(axis=1)]
        assert cell_keys(centres, res) == cell_keys(old, res)
        assert len(centres) == len(cell_keys(centres, res)), "each cell once"
        np.testing.assert_array_equal(log_odds, tree.log_odds(centres))
        assert (tree.is_occupied(centres) == 1).all()
        # occupied_cells_near, old and new, exactly.
        point, radius = rng.uniform(-0.5, 0.5, 3), rng.uniform(0.05, 0.4)
        near_old = old_box_cells(tree, point - radius, point + radius)
        near_old = near_old[np.linalg.norm(near_old - point, axis=1) <= radius]
        near_new, _ = tree.leaves_at_full_depth(point - radius, point + radius, occupied_only=True)
        near_new = near_new[np.linalg.norm(near_new - point, axis=1) <= radius]
        assert cell_keys(near_new, res) == cell_keys(near_old, res)


@pytest.mark.parametrize("seed", range(4))
def test_leaves_at_full_depth_equals_brute_force(seed):
    """Every known finest cell with its centre in the box, free ones included."""
    tree = random_pruned_tree(seed)
    rng = np.random.default_rng(500 + seed)
    res = tree.resolution
    a, b = rng.uniform(-0.6, 0.6, 3), rng.uniform(-0.6, 0.6, 3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    first, last = np.ceil(lo / res - 0.5).astype(int), np.floor(hi / res - 0.5).astype(int)
    grid = np.stack(np.meshgrid(*[np.arange(first[i], last[i] + 1) for i in range(3)], indexing="ij"), -1)
    grid = (grid.reshape(-1, 3) + 0.5) * res
    grid = grid[((grid >= lo) & (grid <= hi)).all(axis=1)]
    known = grid[~np.isnan(tree.log_odds(grid))]
    centres, log_odds = tree.leaves_at_full_depth(lo, hi)
    assert cell_keys(centres, res) == cell_keys(known, res) and len(centres) == len(known)
    np.testing.assert_array_equal(log_odds, tree.log_odds(centres))


def test_leaves_at_full_depth_edges():
    tree = ec.OcTree(0.1)
    assert tree.leaves_at_full_depth([0, 0, 0], [1, 1, 1])[0].shape == (0, 3)
    tree.set_log_odds(block_centres((0, 0, 0), 8, 0.1), math.inf)
    assert tree.num_leaf_nodes() == 1
    # Bounds on cell centres (as the map computes them) are included.
    c, lo = tree.leaves_at_full_depth(np.array([0.5, 0.5, 0.5]) * 0.1, np.array([1.5, 0.5, 3.5]) * 0.1)
    assert len(c) == 2 * 1 * 4 and (lo == np.float32(logodds(0.971))).all()
    assert len(tree.leaves_at_full_depth([0.5, 0, 0], [0.4, 1, 1])[0]) == 0
    assert len(tree.leaves_at_full_depth([-1e9] * 3, [1e9] * 3)[0]) == 512
    with pytest.raises(ValueError, match="NaN"):
        tree.leaves_at_full_depth([np.nan, 0, 0], [1, 1, 1])
    with pytest.raises(ValueError, match="3 numbers"):
        tree.leaves_at_full_depth([0, 0], [1, 1, 1])



def test_leaves_at_full_depth_of_a_map_that_is_one_pruned_root(tmp_path):
    """A root leaf (the whole map at one value, written by hand as .ot) splits into
    exactly the cells of the box; a box of more than 2^26 cells is refused."""
    path = tmp_path / "root.ot"
    ec.OcTree(0.01).write(path)
    text = path.read_bytes()
    assert b"size 0\n" in text
    path.write_bytes(text.replace(b"size 0\n", b"size 1\n") + struct.pack("<fB", 1.25, 0))
    tree = ec.OcTree.read(path)
    assert tree.num_leaf_nodes() == 1
    centres, log_odds = tree.leaves_at_full_depth([0.001, 0.0, -0.05], [0.1, 0.0499, 0.05])
    assert len(centres) == 10 * 5 * 10 and (log_odds == 1.25).all()
    assert cell_keys(centres, 0.01) == {(x, y, z) for x in range(10) for y in range(5) for z in range(-5, 5)}
    with pytest.raises(ValueError, match="more than"):
        tree.leaves_at_full_depth([-5, -5, -5], [5, 5, 5])


# --- 4. Jacobians --------------------------------------------------------------------


def numeric_jacobians(robot, q, link, point, eps=1e-6):
    """Central differences of fk: the point carried by `link`, its origin and its
    rotation (angular velocity from R(q+h)·R(q−h)ᵀ)."""
    dof = len(q)
    frames = robot.fk(np.vstack([q + eps * np.eye(dof), q - eps * np.eye(dof)]))[:, link]
    local = np.linalg.solve(robot.fk(q)[link], np.append(point, 1.0))
    p = frames @ local
    jp = ((p[:dof] - p[dof:]) / (2 * eps))[:, :3].T
    jo = ((frames[:dof, :3, 3] - frames[dof:, :3, 3]) / (2 * eps)).T
    r = frames[:dof, :3, :3] @ np.transpose(frames[dof:, :3, :3], (0, 2, 1))
    w = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=0) / (4 * eps)
    return jp, np.vstack([jo, w])


def moved_base():
    c, s = math.cos(0.7), math.sin(0.7)
    base = np.eye(4)
    base[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]] @ np.array([[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]])
    base[:3, 3] = [0.4, -0.2, 0.8]
    return base


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_jacobians_equal_central_differences(name):
    robots = pytest.importorskip("earcore.robots")
    try:
        robot = robots.load(name)
    except (FileNotFoundError, ImportError) as e:
        pytest.skip(f"{name} model unavailable: {e}")
    robot.base = moved_base()
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(30):
        q = rng.uniform(np.maximum(lo, -3) + 0.01, np.minimum(hi, 3) - 0.01)
        frames = robot.fk(q)
        for link in range(len(robot.link_names)):
            point = frames[link, :3, :3] @ rng.uniform(-0.2, 0.2, 3) + frames[link, :3, 3]
            jp_num, jf_num = numeric_jacobians(robot, q, link, point)
            jp, jf = robot.jacobian(q, link, point), robot.frame_jacobian(q, link)
            assert jp.shape == (3, robot.dof) and jf.shape == (6, robot.dof) and jp.dtype == np.float64
            worst = max(worst, np.abs(jp - jp_num).max(), np.abs(jf - jf_num).max())
            np.testing.assert_allclose(jf[:3], robot.jacobian(q, link, frames[link, :3, 3]), atol=1e-15)
    assert worst < 1e-7


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_frame_jacobian_equals_pinocchio(name):
    pin = pytest.importorskip("pinocchio")
    robots = pytest.importorskip("earcore.robots")
    try:
        robot = robots.load(name)
        ref = pin.buildModelFromUrdf(str(robots.urdf_path(name)))
    except (FileNotFoundError, ImportError) as e:
        pytest.skip(f"{name} model unavailable: {e}")
    base = moved_base()
    robot.base = base
    data = ref.createData()
    order = [robot.joint_names.index(ref.names[j]) for j in range(1, ref.njoints)]
    link_index = {n: i for i, n in enumerate(robot.link_names)}
    frames = [(f, link_index[fr.name]) for f, fr in enumerate(ref.frames) if fr.type == pin.FrameType.BODY and fr.name in link_index]
    rotate = np.kron(np.eye(2), base[:3, :3])
    worst = 0.0
    for q in robot.random_configurations(20, seed=5):
        qp = q[order]
        pin.computeJointJacobians(ref, data, qp)
        pin.updateFramePlacements(ref, data)
        for f, link in frames:
            want = rotate @ pin.getFrameJacobian(ref, data, f, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            ours = robot.frame_jacobian(q, link)[:, order]
            worst = max(worst, np.abs(ours - want).max())
    assert worst < 1e-9


def test_planar_two_link_jacobian_by_hand():
    joints = [
        ("a", "revolute", 0, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -3.0, 3.0),
        ("b", "revolute", 1, 2, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -3.0, 3.0),
        ("tip", "fixed", 2, 3, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.0, 0.0),
        ("slide", "prismatic", 0, 4, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), -1.0, 1.0),
    ]
    robot = ec.RobotModel(["base", "upper", "fore", "tip", "carriage"], joints, [None] * 5)
    a, b = 0.4, -1.2
    q = np.array([a, b, 0.3])
    want = np.array([
        [-math.sin(a) - math.sin(a + b), -math.sin(a + b), 0.0],
        [math.cos(a) + math.cos(a + b), math.cos(a + b), 0.0],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
    ])
    np.testing.assert_allclose(robot.frame_jacobian(q, 3), want, atol=1e-15)
    np.testing.assert_allclose(robot.jacobian(q, 3, robot.fk(q)[3, :3, 3]), want[:3], atol=1e-15)
    np.testing.assert_allclose(robot.frame_jacobian(q, 4)[:, 2], [0, 1, 0, 0, 0, 0])
    np.testing.assert_allclose(robot.frame_jacobian(q, 4)[:, :2], 0)
    with pytest.raises(ValueError, match="link must be 0 to 4"):
        robot.jacobian(q, 5, [0, 0, 0])
    with pytest.raises(ValueError, match="link must be 0 to 4"):
        robot.frame_jacobian(q, -1)
    with pytest.raises(ValueError, match="outside its limits"):
        robot.frame_jacobian(np.array([a, 3.5, 0.0]), 3)
    with pytest.raises(ValueError, match="one configuration"):
        robot.jacobian(np.zeros((2, 3)), 3, [0, 0, 0])
    with pytest.raises(ValueError, match="not finite"):
        robot.jacobian(q, 3, [np.inf, 0, 0])
    with pytest.raises(ValueError):
        robot.jacobian(q, 3, [0, 0])


# --- 5. voxel_codes ------------------------------------------------------------------


def old_voxel_codes(points, resolution):
    """earcore.cloud.voxel_codes as it was (numpy)."""
    if not (np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be finite and > 0, got {resolution}")
    cells = np.floor(np.asarray(points, dtype=np.float64).reshape(-1, 3) / resolution)
    if not (np.abs(cells) < (1 << 20)).all():
        raise ValueError(f"points must be finite and within 2^20 cells of size {resolution} of the origin")
    k = cells.astype(np.int64) + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


@pytest.mark.parametrize("resolution", [0.05, 0.013, 1.0, 1e-4])
def test_voxel_codes_equal_the_numpy_formula(resolution):
    rng = np.random.default_rng(6)
    reach = ((1 << 20) - 1) * resolution
    points = np.vstack([
        rng.uniform(-reach, reach, (5000, 3)),
        rng.normal(0, 3 * resolution, (5000, 3)),
        np.round(rng.uniform(-50, 50, (2000, 3))) * resolution,  # on cell borders
        [[-reach, reach, 0.0]],
    ])
    codes = ec.voxel_codes(points, resolution)
    assert codes.dtype == np.int64 and codes.shape == (len(points),)
    np.testing.assert_array_equal(codes, old_voxel_codes(points, resolution))
    assert ec.voxel_codes(np.zeros((0, 3)), resolution).shape == (0,)


def test_voxel_codes_errors_match():
    for bad in ([np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [0, 0, (1 << 20) * 0.05], [-(1 << 20) * 0.05 - 1e-9, 0, 0]):
        points = np.array([[0.1, 0.2, 0.3], bad])
        with pytest.raises(ValueError) as old:
            old_voxel_codes(points, 0.05)
        with pytest.raises(ValueError) as new:
            ec.voxel_codes(points, 0.05)
        assert str(old.value) in str(new.value)
    for resolution in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="resolution must be finite and > 0"):
            ec.voxel_codes(np.zeros((1, 3)), resolution)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        ec.voxel_codes(np.zeros((2, 2)), 0.1)


# --- 6. thread-local thread count ----------------------------------------------------


def test_local_num_threads_stays_on_its_thread():
    global_before = ec.get_num_threads()
    seen: dict[str, object] = {}
    ready, release = threading.Event(), threading.Event()

    def worker():
        seen["previous"] = ec.set_local_num_threads(1)
        seen["inside"] = ec.get_num_threads()
        # Real work under the override, while the main thread runs with its own.
        tree = ec.OcTree(0.05)
        points, origin = scan()
        tree.insert_point_cloud(points, origin)
        seen["cells"] = tree.size()
        ready.set()
        release.wait(10)
        seen["restored"] = ec.set_local_num_threads(None)
        seen["after"] = ec.get_num_threads()

    thread = threading.Thread(target=worker)
    thread.start()
    assert ready.wait(30)
    # The worker's override is not the main thread's, nor the global setting.
    assert ec.get_num_threads() == global_before
    assert ec.set_local_num_threads(3) is None
    assert ec.get_num_threads() == 3
    release.set()
    thread.join()
    assert seen["previous"] is None and seen["inside"] == 1 and seen["restored"] == 1
    assert seen["after"] == global_before and seen["cells"] > 0
    assert ec.set_local_num_threads(None) == 3
    assert ec.get_num_threads() == global_before
    # 0 means one thread per core, like the global setting.
    ec.set_local_num_threads(0)
    try:
        ec.set_num_threads(1)
        assert ec.get_num_threads() >= 1
    finally:
        ec.set_num_threads(0)
        ec.set_local_num_threads(None)
    for bad in (-1, 10**6):
        with pytest.raises(ValueError, match="num_threads"):
            ec.set_local_num_threads(bad)
    assert ec.set_local_num_threads(None) is None


def test_local_override_wins_over_the_global_setting():
    try:
        ec.set_num_threads(1)
        ec.set_local_num_threads(2)
        assert ec.get_num_threads() == 2
        other = {}
        t = threading.Thread(target=lambda: other.setdefault("n", ec.get_num_threads()))
        t.start()
        t.join()
        assert other["n"] == 1
    finally:
        ec.set_local_num_threads(None)
        ec.set_num_threads(0)


# --- 7. typed results in the stubs ---------------------------------------------------


def stub_typeddict_keys(name: str) -> dict[str, str]:
    """Field names and annotations of a TypedDict in the extension's stub file."""
    import ast
    from pathlib import Path

    stub = Path(ec.__file__).with_name("_earcore.pyi")
    tree = ast.parse(stub.read_text())
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return {
                item.target.id: ast.unparse(item.annotation)
                for item in node.body
                if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
            }
    raise AssertionError(f"{name} is not in the stub")


def small_arm():
    joints = [
        ("j1", "revolute", 0, 1, (0.0, 0.0, 0.1), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -3.0, 3.0),
        ("j2", "revolute", 1, 2, (0.0, 0.0, 0.3), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), -3.0, 3.0),
    ]
    bodies = [None, ((0.0, 0.0, 0.0), (0.0, 0.0, 0.3), 0.05, "capsule"), ((0.0, 0.0, 0.0), (0.3, 0.0, 0.0), 0.04, "cylinder")]
    return ec.RobotModel(["base", "upper", "fore"], joints, bodies)


def test_typed_dict_stubs_name_the_runtime_keys_and_types():
    robot = small_arm()
    q = np.array([0.2, -0.4])
    bodies = robot.bodies(q)
    assert set(bodies) == set(stub_typeddict_keys("_Bodies"))
    assert bodies["link"].dtype == np.int64 and bodies["a"].dtype == bodies["b"].dtype == bodies["radius"].dtype == np.float64
    assert bodies["shape"] == ["capsule", "cylinder"]
    tree = ec.OcTree(RES)
    tree.update_nodes(np.array([[0.3, 0.0, 0.4]]))
    fields = stub_typeddict_keys("_Clearance")
    for qs in (q, np.vstack([q, q])):
        for found in (robot.clearance(tree, qs), robot.clearance_to_voxels(np.zeros((1, 3)), 0.05, qs)):
            assert set(found) == set(fields)
            assert found["on_robot"].dtype == found["on_obstacle"].dtype == np.float64
            if qs.ndim == 1:
                assert isinstance(found["distance"], float) and isinstance(found["link"], int)
            else:
                assert found["distance"].dtype == np.float64 and found["link"].dtype == np.int64
    single, links = robot.check_configurations(tree, np.vstack([q, q]), return_links=True)
    assert single.dtype == np.bool_ and links.dtype == np.int32
    hit, link = robot.check_configurations(tree, q, return_links=True)
    assert isinstance(hit, bool) and isinstance(link, int)


def test_stub_types_are_checked_by_mypy(tmp_path):
    api = pytest.importorskip("mypy.api")
    snippet = tmp_path / "use.py"
    snippet.write_text(
        "import numpy as np\n"
        "from earcore import _earcore as ec\n"
        "def use(robot: ec.RobotModel, tree: ec.OcTree) -> None:\n"
        "    q = np.zeros(robot.dof)\n"
        "    b = robot.bodies(q)\n"
        "    reveal_type(b['radius'])\n"
        "    c = robot.clearance(tree, q, obstacles='current')\n"
        "    reveal_type(c['distance'])\n"
        "    b['colour']\n"
        "    robot.clearance(tree, q, obstacles='everything')\n"
        "    tree.decay_mode = 'sometimes'\n"
        "    reveal_type(robot.check_configurations(tree, q, return_links=True))\n"
        "    reveal_type(ec.OcTree(0.1).copy())\n"
    )
    out, _, _ = api.run([str(snippet), "--no-incremental", "--follow-imports=silent", "--ignore-missing-imports"])
    lines = out.splitlines()
    reveal = [line for line in lines if "Revealed type" in line]
    assert "numpy.ndarray" in reveal[0] and "float64" in reveal[0]
    plain = [r.replace("builtins.", "") for r in reveal]
    assert "float |" in plain[1] and "numpy.ndarray" in plain[1]
    assert "tuple[bool, int]" in plain[2]
    assert "earcore._earcore.OcTree" in reveal[3]
    errors = [line for line in lines if ": error:" in line]
    assert any('"colour"' in e for e in errors), out
    assert any("everything" in e or "obstacles" in e for e in errors), out
    assert any("sometimes" in e or "decay_mode" in e for e in errors), out
    assert len(errors) == 3, out
