"""The simulated cell: cameras against analytic planes and their documented noise, the controller's limits, the person's speed, tools on the flange, other robots."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pybullet = pytest.importorskip("pybullet")

import earcore  # noqa: E402
from earcore.sim.camera import SimulatedCamera  # noqa: E402
from earcore.sim.controller import JointTrajectoryController  # noqa: E402
from earcore.sim.person import MINIMUM_JERK_PEAK, HumanArm, Reach  # noqa: E402
from earcore.sim.sensors import SENSORS, DepthBias, radius2_grid  # noqa: E402
from earcore.synthetic import look_at  # noqa: E402


@pytest.fixture
def client():
    from pybullet_utils.bullet_client import BulletClient

    p = BulletClient(pybullet.DIRECT)
    yield p
    p.disconnect()


def plane_scene(client, normal_angles=(0.35, 0.2)):
    """A large thin box whose top face is a plane through (0, 0, 0.3)."""
    q = pybullet.getQuaternionFromEuler([*normal_angles, 0])
    visual = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=[4, 4, 0.001])
    client.createMultiBody(0, -1, visual, [0, 0, 0.3], q)
    normal = np.reshape(pybullet.getMatrixFromQuaternion(q), (3, 3))[:, 2]
    return normal, np.array([0, 0, 0.3]) + 0.001 * normal


@pytest.mark.parametrize("name", sorted(n for n, s in SENSORS.items() if s.has_depth))
def test_depth_of_a_plane_back_projects_onto_it(client, name):
    sensor = SENSORS[name]
    normal, point = plane_scene(client)
    distance = 0.8 if sensor.far < 2.0 else 2.0  # short-range coded-light sensors (F200, SR300) stay in range
    pose = look_at(point + distance * normal + [0.25, -0.1, 0.0], point)
    camera = SimulatedCamera(client, name, sensor, pose, rng=np.random.default_rng(1))
    _, true_depth, _ = camera.render_true()
    K, lens = sensor.intrinsics, sensor.distortion
    exact = earcore.depth_to_points(true_depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], distortion=lens, base_from_camera=pose)
    assert len(exact) > 0.9 * sensor.width * sensor.height
    assert np.abs((exact - point) @ normal).max() < 1e-4  # the projection is K through the lens
    if np.any(lens):  # and the lens matters: the pinhole alone misplaces the points
        pinhole = earcore.depth_to_points(true_depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], base_from_camera=pose)
        assert np.linalg.norm(pinhole - exact, axis=1).max() > 1e-2
    frame = camera.capture(0.0)
    assert np.array_equal(frame.distortion, lens)
    noisy = earcore.depth_to_points(frame.depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], distortion=lens, base_from_camera=pose)
    offsets = (noisy - point) @ normal
    # Within the noise model: 4 σ at the farthest valid depth plus the quantisation step.
    z = frame.depth[frame.depth > 0]
    step = z.max() ** 2 / (8 * 580.0 * 0.075) if sensor.baseline else sensor.depth_step
    rho2 = radius2_grid(K, sensor.width, sensor.height)
    bias = np.abs(sensor.depth_bias.error(frame.depth, rho2))[frame.depth > 0].max()
    bound = 4 * sensor.sigma(z.max(), np.radians(sensor.max_incidence_deg)) + step + bias
    assert np.abs(offsets).max() < bound


@pytest.mark.parametrize("name", ["kinect_v2", "f200"])
def test_noise_statistics_match_the_documented_model(client, name):
    """Fronto-parallel plane at several distances: the mean error is the documented
    systematic error (`DepthBias`) and the spread around it √(σ(z)² + step²/12) (noise
    plus rounding to whole millimetres) within 10 %."""
    sensor = SENSORS[name].scaled(0.5)
    visual = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=[5, 5, 0.001])
    client.createMultiBody(0, -1, visual, [0, 0, -0.001])
    distances = [0.4, 0.8, 1.1] if name == "f200" else [0.8, 1.5, 2.5, 3.5]
    for z in distances:
        camera = SimulatedCamera(client, name, sensor, look_at([0, 0, z], [0, 0, 0], up=(0, 1, 0)), rng=np.random.default_rng(2))
        _, true_depth, _ = camera.render_true()
        measured = sensor.corrupt(true_depth, np.random.default_rng(3))
        valid = (measured > 0) & (true_depth > 0)
        rho2 = radius2_grid(sensor.intrinsics, sensor.width, sensor.height)
        err = (measured - true_depth - sensor.depth_bias.error(true_depth, rho2))[valid]
        expected = np.sqrt(sensor.sigma(z) ** 2 + sensor.depth_step**2 / 12)
        assert abs(err.mean()) < 0.1 * expected + 1e-4
        assert err.std() == pytest.approx(expected, rel=0.1)


def test_a_colour_only_camera_has_an_image_and_no_depth(client):
    sensor = SENSORS["webcam"]
    normal, point = plane_scene(client)
    camera = SimulatedCamera(client, "webcam", sensor, look_at(point + 0.8 * normal, point), rng=np.random.default_rng(1))
    frame = camera.capture(0.0)
    assert not sensor.has_depth and frame.colour.shape == (480, 640, 3)
    assert (frame.segmentation >= 0).mean() > 0.9  # it sees the plane
    assert not frame.depth.any()


def test_depth_bias_is_the_documented_systematic_error(client):
    """The mean depth error over a fronto-parallel plane, per image region, is the
    documented offset + scale·z + radial·ρ²·z² (Kinect V2: +3 mm, +6 mm radial)."""
    sensor = SENSORS["kinect_v2"].scaled(0.5)
    assert sensor.depth_bias == DepthBias(offset=0.003, radial=0.006)
    visual = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=[5, 5, 0.001])
    client.createMultiBody(0, -1, visual, [0, 0, -0.001])
    camera = SimulatedCamera(client, "v2", sensor, look_at([0, 0, 1.2], [0, 0, 0], up=(0, 1, 0)), rng=np.random.default_rng(2))
    _, true_depth, _ = camera.render_true()
    measured = np.mean([sensor.corrupt(true_depth, np.random.default_rng(i)) - true_depth for i in range(20)], axis=0)
    rho2 = radius2_grid(sensor.intrinsics, sensor.width, sensor.height)
    centre, corner = rho2 < 0.02, rho2 > 0.6
    assert measured[centre].mean() == pytest.approx(0.003 + 0.006 * rho2[centre].mean() * 1.2**2, abs=2e-4)
    assert measured[corner].mean() == pytest.approx(0.003 + 0.006 * rho2[corner].mean() * 1.2**2, abs=2e-4)
    assert measured[corner].mean() - measured[centre].mean() > 0.004  # the corners read deeper


def test_structured_light_quantisation_grows_with_distance():
    sensor = SENSORS["kinect_v1"]
    z = np.linspace(0.8, 3.5, 2000)
    steps = np.diff(np.unique(sensor.quantise(z)))
    assert steps.max() == pytest.approx(3.5**2 / (8 * 580 * 0.075), rel=0.05)
    assert steps.min() == pytest.approx(0.8**2 / (8 * 580 * 0.075), abs=1.5e-3)


def test_incidence_angles_of_a_tilted_plane_are_exact():
    """Differences between back-projected neighbours of a plane lie in the plane, so
    the estimated normal is the plane's and the angle to each pixel's ray is analytic
    (border pixels included); a hole makes its neighbours NaN."""
    from earcore.cloud import incidence_angles

    w, h, f = 64, 48, 50.0
    normal = np.array([0.3, -0.5, -1.0])
    normal /= np.linalg.norm(normal)
    d = -1.2  # plane: normal · X = d, 1.2 m in front of the camera
    u = (np.arange(w) - (w - 1) / 2) / f
    v = (np.arange(h) - (h - 1) / 2) / f
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1)
    depth = d / (rays @ normal)  # z of each pixel's ray hitting the plane
    expected = np.arccos(np.abs(rays @ normal) / np.linalg.norm(rays, axis=-1))
    assert np.allclose(incidence_angles(depth, f, f), expected, atol=1e-9)
    depth[20, 30] = 0.0
    holed = incidence_angles(depth, f, f)
    assert np.isnan(holed[20, 29:32]).all() and np.isnan(holed[19:22, 30]).all()
    assert np.isfinite(holed[20, 33]) and np.isfinite(holed[23, 30])


def test_sigma_follows_the_published_models():
    v2, v1 = SENSORS["kinect_v2"], SENSORS["kinect_v1"]
    assert v2.sigma(1.0) == pytest.approx(1.3e-3)  # 1.5 - 0.5 + 0.3 mm
    assert v1.sigma(2.0) == pytest.approx((1.2 + 1.9 * 1.6**2) * 1e-3)
    assert v2.sigma(2.0, np.radians(70)) > 3 * v2.sigma(2.0)
    # F200 (coded light): 0.5 + 2.5·z² mm.
    assert SENSORS["f200"].sigma(1.0) == pytest.approx(3.0e-3)
    assert SENSORS["f200"].sigma(0.4) == pytest.approx((0.5 + 2.5 * 0.16) * 1e-3)


def test_controller_respects_limits_and_arrives():
    vmax = np.array([1.0, 0.5, 2.0])
    amax = np.array([2.0, 1.0, 4.0])
    ctrl = JointTrajectoryController(vmax, amax)
    q = np.zeros(3)
    goal = np.array([1.0, -0.8, 0.3])
    ctrl.follow([np.array([0.5, 0.2, 0.0]), goal])
    dt, qd_prev, speeds = 0.01, np.zeros(3), []
    for _ in range(2000):
        qd = ctrl.step(q, dt)
        assert np.all(np.abs(qd) <= vmax + 1e-9)
        assert np.all(np.abs(qd - qd_prev) <= amax * dt * 1.0001 + 1e-9) or ctrl.done
        speeds.append(np.abs(qd).max())
        q = q + qd * dt
        qd_prev = qd
        if ctrl.done:
            break
    assert ctrl.done and np.abs(q - goal).max() < 1e-3


def test_person_hand_speed_stays_within_the_limit(client):
    arm = HumanArm(client, (0.9, 0.4, 0.45), (0.8, 0.5, 0.05), [Reach(0.5, (0.4, 0.2, 0.2), 1.0)], peak_speed=1.6)
    go = arm.duration((0.4, 0.2, 0.2))
    times = np.arange(0, 0.5 + 2 * go + 1.5, 0.005)
    speeds = np.array([arm.speed(t) for t in times])
    assert speeds.max() == pytest.approx(1.6, rel=0.02)
    assert np.allclose(arm.hand_position(0.5 + go + 0.5), (0.4, 0.2, 0.2))
    # The arm's segments keep their lengths whatever the hand does.
    for t in times[::20]:
        lengths = [np.linalg.norm(b - a) for a, b, _ in arm.segments(t)]
        assert lengths == pytest.approx([0.30, 0.27, 0.15], abs=1e-6)
    assert MINIMUM_JERK_PEAK == pytest.approx(1.875)


def test_person_phase_follows_the_reach_schedule(client):
    """A reach starting at 0.5 s to a target 0.5 m from rest at 1.0 m/s peak: on its way
    in for 1.875 * 0.5 / 1.0 s, held 1.0 s, back as long, then at rest; the hand is at
    the target while held and at rest outside the reach."""
    rest, target = np.array([0.8, 0.5, 0.05]), np.array([0.8, 0.0, 0.05])
    arm = HumanArm(client, (0.9, 0.4, 0.45), tuple(rest), [Reach(0.5, tuple(target), 1.0, speed=1.0)])
    go = 1.875 * 0.5 / 1.0
    expected = [(0.49, "rest"), (0.51, "in"), (0.5 + go - 0.01, "in"), (0.5 + go + 0.01, "held"),
                (0.5 + go + 0.99, "held"), (0.5 + go + 1.01, "back"), (0.5 + 2 * go + 0.99, "back"),
                (0.5 + 2 * go + 1.01, "rest")]
    for t, phase in expected:
        assert arm.phase(t) == phase, t
    # Each stage begins at its boundary (as the schedule computes them) and ends just before the next.
    start, go_s = 0.5, arm.duration(tuple(target), 1.0)
    for t, phase in ((start, "in"), (start + go_s, "held"), (start + go_s + 1.0, "back"), (start + 2 * go_s + 1.0, "rest")):
        assert arm.phase(t) == phase, t
        assert arm.phase(np.nextafter(t, -np.inf)) != phase, t
    np.testing.assert_allclose(arm.hand_position(0.5 + go + 0.5), target)
    np.testing.assert_allclose(arm.hand_position(0.49), rest)
    assert arm.speed(0.5 + go / 2) == pytest.approx(1.0, rel=1e-3)  # the peak half-way in


def test_a_held_hand_wanders_by_its_documented_offset(client):
    """While held, the hand sits at the target plus the reach's wander: the amplitude times
    sin²(π τ / hold) times (1, 1, 0.5) times sin(2π τ / period + phase) per axis, τ the
    seconds into the hold; zero offset where the hold begins and ends."""
    rest, target = np.array([0.8, 0.5, 0.05]), np.array([0.5, 0.2, 0.4])
    reach = Reach(0.5, tuple(target), 2.0, speed=1.0, wander=0.08)
    arm = HumanArm(client, (0.9, 0.4, 0.45), tuple(rest), [reach])
    go = arm.duration(tuple(target), 1.0)
    periods, phases = arm._wander_terms[0]
    for tau in (0.0, 0.3, 0.7, 1.0, 1.6, 1.999):
        want = 0.08 * np.sin(np.pi * tau / 2.0) ** 2 * np.array([1.0, 1.0, 0.5]) * np.sin(2 * np.pi * tau / periods + phases)
        np.testing.assert_allclose(arm.hand_position(0.5 + go + tau), target + want, atol=1e-12)
    assert np.linalg.norm(arm.hand_position(0.5 + go + 1.0) - target) > 0.01  # it does wander


def test_person_arrives_after_the_warm_up(client):
    """Before `arrive` the arm is out of the scene (below the floor, no contact possible);
    a reach planned before it is refused."""
    arm = HumanArm(client, (0.9, 0.4, 0.45), (0.8, 0.5, 0.05), [Reach(1.0, (0.4, 0.2, 0.2), 1.0)], arrive=0.75)
    arm.set_time(0.5)
    assert not arm.present(0.5)
    assert all(client.getBasePositionAndOrientation(b)[0][2] < -5 for b in arm.bodies)
    arm.set_time(0.75)
    assert arm.present(0.75)
    centres = [np.array(client.getBasePositionAndOrientation(b)[0]) for b in arm.bodies]
    expected = [(a + b) / 2 for a, b, _ in arm.segments(0.75)]
    np.testing.assert_allclose(centres, expected, atol=1e-9)
    with pytest.raises(ValueError, match="before the person arrives"):
        HumanArm(client, (0.9, 0.4, 0.45), (0.8, 0.5, 0.05), [Reach(0.5, (0.4, 0.2, 0.2))], arrive=0.75)


def test_checkerboard_renders_its_pattern(client):
    """Each square's centre, projected through the camera, has the square's colour;
    the hollow corner square is light at its centre and dark at its outline."""
    from earcore.sim.tools import Checkerboard, visual_shape

    board = Checkerboard()
    shape, texture = visual_shape(board, client)
    world_from_board = look_at([0.1, -0.05, 0.6], [0.0, 0.0, 0.0])  # printed face (+z) toward the camera
    from earcore.transforms import quaternion

    x, y, z, w = quaternion(world_from_board[:3, :3])
    body = client.createMultiBody(0, -1, shape, world_from_board[:3, 3].tolist(), [x, y, z, w])
    client.changeVisualShape(body, -1, textureUniqueId=texture)
    sensor = SENSORS["f200"]
    camera_pose = look_at([0.0, 0.0, 0.0], [0.1, -0.05, 0.6], up=(0, -1, 0))
    camera = SimulatedCamera(client, "cam", sensor, camera_pose, rng=np.random.default_rng(0))
    colour, depth, _ = camera.render_true()
    grey = colour.mean(axis=2)
    camera_from_board = np.linalg.inv(camera_pose) @ world_from_board
    K = sensor.intrinsics

    def pixel(p):
        c = camera_from_board[:3, :3] @ p + camera_from_board[:3, 3]
        u, v = (K @ (c / c[2]))[:2]
        return grey[int(round(v)), int(round(u))]

    for col, row, centre in board.square_centres():
        value = pixel(centre)
        dark = board.is_dark(col, row) and (col, row) != (0, 0)
        assert (value < 60) if dark else (value > 120), (col, row, value)  # lit white renders ~160
    outline = board.square_centres()[0][2] + np.array([0.45 * board.square, 0.0, 0.0])
    assert pixel(outline) < 60
    assert len(board.inner_corners()) == 24


def test_tools_follow_the_flange():
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig
    from earcore.sim.tools import Checkerboard, ObstaclePlate

    config = CellConfig(cameras=[])
    config.person.enabled = False
    cell = SimulatedCell(config)
    offset = np.eye(4)
    offset[2, 3] = 0.12
    board = cell.attach_tool(Checkerboard(), offset)
    plate = cell.attach_tool(ObstaclePlate(), np.eye(4))
    cell.controller.follow([cell.q + 0.3])
    for _ in range(20):
        cell.step()
    tool0 = cell.model.fk(cell.q)[cell.model.link_names.index("tool0")]
    for body, expected in ((board, tool0 @ offset), (plate, tool0)):
        pos, orn = cell.p.getBasePositionAndOrientation(body)
        assert np.allclose(pos, expected[:3, 3], atol=1e-5)
        assert np.allclose(np.reshape(cell.p.getMatrixFromQuaternion(orn), (3, 3)), expected[:3, :3], atol=1e-5)
    cell.close()


@pytest.mark.parametrize("robot", ["ur10", "iiwa", "panda"])
def test_other_robots_run_in_the_cell(robot):
    from earcore.sim.cell import SimulatedCell, default_waypoints
    from earcore.sim.config import CellConfig

    config = CellConfig(robot=robot, camera_scale=0.25)
    config.person.enabled = False
    cell = SimulatedCell(config)
    cell.controller.follow(default_waypoints(robot)[1:])
    frames = []
    for _ in range(15):
        cell.step()
        frames += cell.capture()
    assert {f.camera for f in frames} == {c.name for c in config.cameras}
    # pybullet's links sit where earcore's kinematics put them.
    fk = cell.model.fk(cell.q)
    for name, link in cell.link_ids.items():
        state = cell.p.getLinkState(cell.robot_id, link, computeForwardKinematics=True)
        assert np.allclose(state[4], fk[cell.model.link_names.index(name)][:3, 3], atol=2e-5)
    cell.close()


@pytest.mark.parametrize("robot", ["ur5", "ur10"])
def test_collision_meshes_render_the_same_robot(robot, tmp_path):
    """`robot_meshes="collision"` (the experiments' fast renders) shows the cameras the
    same UR arm as its visual meshes: the same pixels, depth within a few millimetres,
    the same kinematics; the rewritten URDF keeps every link and joint. (Not so for
    the panda, whose collision meshes are convex hulls: ~8 % more pixels, 2-4 cm off.)"""
    import xml.etree.ElementTree as ET

    from earcore.robots import urdf_path
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig
    from earcore.urdf import collision_as_visual, parse_urdf

    original = urdf_path(robot)
    copy = collision_as_visual(original, tmp_path)
    a, b = parse_urdf(original), parse_urdf(copy, geometry="visual")
    assert a.links == b.links and a.joints == b.joints
    for link in a.links:  # visual geometry of the copy == collision geometry of the original
        if a.vertices[link] is not None:
            assert np.array_equal(a.vertices[link], b.vertices[link])
    assert all(Path(m.get("filename")).is_absolute() for m in ET.parse(copy).getroot().iter("mesh"))
    # Collision-only volumes (the UR's ee_link box) stay invisible.
    invisible = lambda p: {l.get("name") for l in ET.parse(p).getroot().iter("link") if l.find("visual") is None}  # noqa: E731
    assert invisible(copy) == invisible(original)

    views = {}
    for meshes in ("visual", "collision"):
        config = CellConfig(robot=robot, camera_scale=0.5, robot_meshes=meshes)
        config.person.enabled = False
        cell = SimulatedCell(config)
        views[meshes] = [cam.render_true()[1:] + (cell.robot_id,) for cam in cell.cameras]
        links = {name: cell.p.getLinkState(cell.robot_id, i)[4] for name, i in cell.link_ids.items()}
        views[meshes + "_links"] = links
        cell.close()
    assert views["visual_links"] == views["collision_links"]
    robot_pixels = 0
    for (zv, bv, rid), (zc, bc, _) in zip(views["visual"], views["collision"]):
        on_v, on_c = bv == rid, bc == rid
        both = on_v & on_c
        robot_pixels += on_v.sum()
        # Silhouettes: at most a few per cent of the robot's pixels differ (edges).
        assert (on_v ^ on_c).sum() <= 0.05 * max(on_v.sum(), 1) + 5
        if both.sum() > 20:
            d = np.abs(zv - zc)[both]
            assert np.median(d) < 0.002 and np.percentile(d, 90) < 0.01
    assert robot_pixels > 500  # the cameras do see the robot


def test_robot_meshes_must_be_visual_or_collision():
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig

    with pytest.raises(ValueError, match="robot_meshes"):
        SimulatedCell(CellConfig(robot_meshes="mesh"))


def test_random_reaches_from_the_seed():
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig

    config = CellConfig(cameras=[])
    config.person.reach_starts = []
    config.person.reach_targets = []
    config.person.peak_speed = 1.6
    cells = [SimulatedCell(config) for _ in range(2)]
    a, b = (c.person.reaches for c in cells)
    assert a == b and len(a) >= 5  # same seed, same reaches
    times = np.arange(0.0, a[2].start, 0.01)
    speeds = [cells[0].person.speed(t) for t in times]
    assert max(speeds) <= 1.6 * 1.01 and max(speeds) > 1.0
    for reach in a:
        assert 0.25 <= reach.target[0] <= 0.65 and reach.target[2] >= 0.1
    for c in cells:
        c.close()
