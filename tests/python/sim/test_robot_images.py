"""The labelled-image generator: labels against the renderer's own segmentation and
against pybullet's link frames, the camera_from_base pose against the keypoints,
determinism, both sampling modes and the robot's image coverage."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pybullet")

from earcore.robots import load  # noqa: E402
from earcore.sim.robot_images import (  # noqa: E402
    RobotImageOptions,
    RobotImageRenderer,
    collision_free,
    plan_shards,
)

ROBOTS = ("ur3", "ur10", "iiwa", "panda")


@pytest.fixture(scope="module")
def clean():
    """Distractors and the person off: nothing can hide the robot but itself."""
    options = RobotImageOptions(robots=ROBOTS, mode="random", count=8, distractors=False, person=0.0, shard_size=8)
    renderer = RobotImageRenderer(options)
    samples = [renderer.render(spec) for shard in plan_shards(options) for spec in shard]
    yield renderer, samples
    renderer.close()


def test_keypoints_and_base_project_onto_the_robot(clean):
    """Each in-image keypoint and the base, projected through the stored intrinsics,
    lands on the renderer's robot pixels or within 2 px of them."""
    _, samples = clean
    checked = 0
    for s in samples:
        row, robot = s.sample.row, s.sample.images["links"] > 0
        vs, us = np.nonzero(robot)
        if len(us) == 0:
            continue
        points = [(row[f"kp{i}_x"], row[f"kp{i}_y"], row[f"kp{i}_z"]) for i in range(8) if row.get(f"kp{i}_in_image") == 1]
        points.append((row["base_x"], row["base_y"], row["base_z"]))
        for x, y, z in points:
            u, v = row["fx"] * x / z + row["cx"], row["fy"] * y / z + row["cy"]
            if not (0 <= u <= 127 and 0 <= v <= 105):
                continue
            assert np.hypot(us - u, vs - v).min() <= 2.0, (s.sample.key, u, v)
            checked += 1
    assert checked > 150


def test_stored_pixels_are_the_projection_of_the_stored_points(clean):
    _, samples = clean
    for s in samples:
        row = s.sample.row
        for i in range(8):
            if f"kp{i}_x" not in row:
                continue
            x, y, z = (row[f"kp{i}_{c}"] for c in "xyz")
            assert abs(row[f"kp{i}_u"] - (row["fx"] * x / z + row["cx"])) < 1e-9
            inside = z > 0 and -0.5 <= row[f"kp{i}_u"] < 127.5 and -0.5 <= row[f"kp{i}_v"] < 105.5
            assert row[f"kp{i}_in_image"] == int(inside)


def test_the_mask_is_the_renderers_segmentation_of_the_robot(clean):
    """Rendered once more with pybullet's plain object segmentation (no link bits)."""
    renderer, samples = clean
    from earcore.sim.camera import opengl_projection, opengl_view

    p = renderer.p
    for spec in plan_shards(renderer.options)[-1][:4]:
        s = renderer.render(spec)  # the scene as this sample left it
        K = s.K
        _, _, _, _, seg = p.getCameraImage(
            128,
            106,
            opengl_view(s.world_from_camera),
            opengl_projection(K, 128, 106, 0.05, 20.0),
            renderer=p.ER_TINY_RENDERER,
            **s.extra["layout"].lighting.arguments(),
        )
        assert np.array_equal(s.sample.images["links"] > 0, np.reshape(seg, (106, 128)) == s.robot_body)
        # Each link value names a link with geometry, decoded from pybullet's link index.
        names = renderer.robot.model.link_names
        for value in np.unique(s.sample.images["links"][s.sample.images["links"] > 0]):
            pixels = np.reshape(s.segmentation, (106, 128))[s.sample.images["links"] == value]
            link = (pixels >> 24) - 1
            assert len(np.unique(link)) == 1
            pb_name = p.getBodyInfo(s.robot_body)[0].decode() if link[0] < 0 else p.getJointInfo(s.robot_body, int(link[0]))[12].decode()
            assert names[value - 1] == pb_name


def test_pybullet_link_frames_agree_with_earcore_fk(clean):
    renderer, samples = clean
    p, robot = renderer.p, renderer.robot
    q = samples[-1].q
    for j, value in zip(robot.joint_ids, q):
        p.resetJointState(robot.body, j, float(value))
    fk = robot.model.fk(q)
    for j in range(p.getNumJoints(robot.body)):
        name = p.getJointInfo(robot.body, j)[12].decode()
        state = p.getLinkState(robot.body, j, computeForwardKinematics=True)
        pose = fk[robot.model.link_names.index(name)]
        assert np.allclose(state[4], pose[:3, 3], atol=1e-5), name
        assert np.allclose(np.reshape(p.getMatrixFromQuaternion(state[5]), (3, 3)), pose[:3, :3], atol=1e-5), name


def test_camera_from_base_carries_the_base_frame_keypoints_to_the_camera(clean):
    """FK in the robot's own base frame, moved by the stored base pose, gives the stored
    camera-frame keypoints."""
    _, samples = clean
    for s in samples:
        row = s.sample.row
        model = load(row["robot"])
        w, x, y, z = (row[f"base_q{c}"] for c in "wxyz")
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        t = np.array([row["base_x"], row["base_y"], row["base_z"]])
        fk = model.fk(s.q)
        flange = {"ur3": ("tool0", 0.0), "ur10": ("tool0", 0.0), "iiwa": ("lbr_iiwa_link_7", 0.045), "panda": ("panda_link8", 0.0)}
        link, offset = flange[row["robot"]]
        tip = fk[model.link_names.index(link)] @ [0, 0, offset, 1]
        n = 7 if row["robot"] in ("ur3", "ur10") else 8
        stored = np.array([row[f"kp{n - 1}_{c}"] for c in "xyz"])
        assert np.allclose(r @ tip[:3] + t, stored, atol=1e-9)
        # The first joint (shoulder pan / joint 1) sits on the base's z axis.
        first = np.array([row[f"kp0_{c}"] for c in "xyz"])
        assert np.allclose(np.cross(first - t, r[:, 2]), 0, atol=1e-9)


def test_joint_states_are_collision_free(clean):
    _, samples = clean
    for s in samples:
        model = load(s.sample.row["robot"])
        assert not model.self_collisions(s.q[None])[0]
        assert collision_free(model, s.q[None])[0]


def test_collision_check_rejects_self_collision_and_the_table():
    model = load("ur5")
    folded = np.array([[0.0, -1.57, 3.1, 0.0, 0.0, 0.0]])  # forearm folded into the upper arm
    assert model.self_collisions(folded)[0] and not collision_free(model, folded)[0]
    down = np.array([[0.0, 1.2, 0.0, 0.0, 0.0, 0.0]])  # the arm swung down through the table
    assert not model.self_collisions(down)[0] and not collision_free(model, down)[0]
    up = np.array([[0.0, -1.57, 0.0, -1.57, 0.0, 0.0]])
    assert collision_free(model, up)[0]


def test_the_same_seed_gives_the_same_bytes_another_seed_other_images():
    options = RobotImageOptions(robots=("ur5",), mode="recordings", scale=0.004, shard_size=4)
    spec = plan_shards(options)[0][1]
    a, b = RobotImageRenderer(options), RobotImageRenderer(options)
    first = a.render(spec).sample
    a.render(plan_shards(options)[0][0])  # another sample in between changes nothing
    again, fresh = a.render(spec).sample, b.render(spec).sample
    for other in (again, fresh):
        assert all(np.array_equal(first.images[k], other.images[k]) for k in ("rgb", "links")) and first.row == other.row
    c = RobotImageRenderer(RobotImageOptions(robots=("ur5",), mode="recordings", scale=0.004, shard_size=4, seed=1))
    assert not np.array_equal(c.render(spec).sample.images["rgb"], first.images["rgb"])
    for r in (a, b, c):
        r.close()


def test_recordings_keep_the_camera_while_the_joints_sweep():
    options = RobotImageOptions(robots=("ur3",), mode="recordings", scale=0.02, shard_size=100)
    assert options.recordings() == {"ur3": (4, 5, 9)}
    assert RobotImageOptions().recordings() == {"ur3": (211, 252, 463), "ur5": (252, 756, 1512), "ur10": (112, 278, 514)}
    specs = plan_shards(options)[0]
    assert sum(s.split == "test" for s in specs) == round(0.2 * 18)
    renderer = RobotImageRenderer(options)
    out = [renderer.render(s) for s in specs]
    renderer.close()
    by_recording: dict[int, list] = {}
    for spec, s in zip(specs, out):
        by_recording.setdefault(spec.recording, []).append(s)
    cameras = []
    for samples in by_recording.values():
        poses = np.stack([s.world_from_camera for s in samples])
        assert np.allclose(poses, poses[0])
        assert len({tuple(np.round(s.q, 6)) for s in samples}) == len(samples)
        cameras.append(poses[0])
    assert len({tuple(np.round(c[:3, 3], 6)) for c in cameras}) == 3


def test_random_mode_moves_the_camera_every_image_out_of_the_arms_reach_with_the_robot_in_view():
    options = RobotImageOptions(robots=("ur5",), mode="random", count=40, shard_size=40)
    renderer = RobotImageRenderer(options)
    out = [renderer.render(s) for s in plan_shards(options)[0]]
    renderer.close()
    assert len({tuple(np.round(s.world_from_camera[:3, 3], 6)) for s in out}) == 40
    coverage = np.array([s.sample.row["coverage"] for s in out])
    assert np.all(coverage == [float((s.sample.images["links"] > 0).mean()) for s in out])
    # No keypoint near the lens: the camera is out of the arm's reach (0.85 m for a UR5).
    eyes = np.stack([s.world_from_camera[:3, 3] for s in out])
    nearest = np.array([np.linalg.norm(s.keypoints_world - eye, axis=1).min() for s, eye in zip(out, eyes)])
    assert nearest.min() > 0.15
    # The whole arm in view in most images; the robot's share of the image as in the papers
    # (6-17 %, here 3-25 %) in most of them.
    inside = np.array([[s.sample.row[f"kp{i}_in_image"] for i in range(7)] for s in out])
    assert inside.all(1).mean() >= 0.8
    assert np.mean((coverage >= 0.03) & (coverage <= 0.25)) >= 0.7
    assert 0.04 <= np.median(coverage) <= 0.2


def test_a_renderer_prints_nothing(tmp_path):
    """A dataset worker's renderer prints neither pybullet's "pybullet build time" line
    (its C module, on import; stdout or stderr by build) nor "argv[0]=" (on connect):
    one line per worker over the progress bar otherwise."""
    import subprocess
    import sys
    from pathlib import Path

    import earcore

    code = "from earcore.sim.robot_images import _quiet_client\nc = _quiet_client()\nprint('done')\n"
    env = {"PYTHONPATH": str(Path(earcore.__file__).resolve().parent.parent), "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "done\n" and "pybullet" not in done.stderr and "argv" not in done.stderr, (done.stdout, done.stderr)


def test_cameras_stand_out_of_reach_and_above_the_table():
    """The placement rule over many draws (no rendering): 1.2 reaches or more from the
    base, 0.15-1.2 m above the table top (the base frame's z = 0)."""
    renderer = RobotImageRenderer(RobotImageOptions(robots=("ur3", "ur10")))
    try:
        for name in ("ur3", "ur10"):
            robot = renderer._use(name)
            rng = np.random.default_rng(5)
            aim = np.array([0.0, 0.0, 0.4 * robot.reach])
            eyes = np.array([(np.linalg.inv(robot.model.base) @ renderer._camera(rng, robot, aim))[:3, 3] for _ in range(300)])
            assert np.linalg.norm(eyes, axis=1).min() >= 1.2 * robot.reach - 1e-9
            assert eyes[:, 2].min() >= 0.15 - 1e-9 and eyes[:, 2].max() <= 1.2 + 1e-9
    finally:
        renderer.close()
