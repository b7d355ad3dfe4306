"""The core's rasterizer and lens resampling (`earcore.render`), the meshes it draws
(`earcore.mesh`, `earcore.urdf.read_mesh`) and the cell drawn with it: against ray
casting, scipy's interpolation, analytic volumes and pybullet's own renderer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from earcore.mesh import box, capsule
from earcore.render import PixelMap, Rasterizer
from earcore.urdf import read_mesh

K = np.array([[80.0, 0.0, 39.5], [0.0, 90.0, 29.5], [0.0, 0.0, 1.0]])
W, H = 80, 60


def rays(K, width, height):
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)


def ray_box_depth(directions, camera_from_box, half):
    """Slab test per pixel: the z (depth) of the first hit of each ray (z = 1
    directions) on the box, 0 where it misses."""
    box_from_camera = np.linalg.inv(camera_from_box)
    origin = box_from_camera[:3, 3]
    d = directions.reshape(-1, 3) @ box_from_camera[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - origin) / d, (half - origin) / d
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (near <= far) & (far > 0)
    return np.where(hit, near, 0.0).reshape(directions.shape[:2])


@pytest.mark.parametrize("seed", range(4))
def test_a_box_in_any_pose_has_the_ray_cast_depth(seed):
    rng = np.random.default_rng(seed)
    half = rng.uniform(0.1, 0.4, 3)
    m = box(half)
    from earcore.transforms import axis_angle_matrix

    pose = np.eye(4)
    axis = rng.normal(0, 1.0, 3)
    pose[:3, :3] = axis_angle_matrix(axis / np.linalg.norm(axis), rng.uniform(0.3, 3.0))
    pose[:3, 3] = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(1.5, 2.5)]
    raster = Rasterizer([(m.vertices, m.triangles, (0.9, 0.6, 0.3), 5)])
    rgb, depth, label = raster.render(pose[None], K, W, H)
    truth = ray_box_depth(rays(K, W, H), pose, half)
    inside = truth > 0
    # Pixels whose ray grazes an edge may fall either side; everything else agrees.
    edge = np.zeros_like(inside)
    edge[1:-1, 1:-1] = (
        (inside[1:-1, 1:-1] != inside[:-2, 1:-1])
        | (inside[1:-1, 1:-1] != inside[2:, 1:-1])
        | (inside[1:-1, 1:-1] != inside[1:-1, :-2])
        | (inside[1:-1, 1:-1] != inside[1:-1, 2:])
    )
    firm = ~edge
    assert inside.sum() > 100
    assert np.array_equal(label[firm] == 5, inside[firm]) and (label[~inside & firm] == -1).all()
    both = (depth > 0) & inside
    assert np.abs(depth[both] - truth[both]).max() < 1e-9
    assert (rgb[label == -1] == 0).all() and (rgb[label == 5].max(axis=1) > 0).all()


def test_hidden_meshes_near_far_and_bad_input():
    near_box, far_box = box((0.2, 0.2, 0.2)), box((1.0, 1.0, 0.1))
    raster = Rasterizer([(near_box.vertices, near_box.triangles, (1, 0, 0), 1), (far_box.vertices, far_box.triangles, (0, 0, 1), 2)])
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, 2, 3], poses[1, 2, 3] = 1.0, 3.0
    _, depth, label = raster.render(poses, K, W, H)
    assert label[30, 40] == 1 and abs(depth[30, 40] - 0.8) < 1e-12
    _, depth, label = raster.render(poses, K, W, H, hidden=[True, False])
    assert label[30, 40] == 2 and abs(depth[30, 40] - 2.9) < 1e-12
    _, depth, label = raster.render(poses, K, W, H, far=2.5, hidden=[True, False])
    assert (label == -1).all() and (depth == 0).all()
    with pytest.raises(ValueError, match="one pose per mesh"):
        raster.render(poses[:1], K, W, H)
    with pytest.raises(ValueError, match="near"):
        raster.render(poses, K, W, H, near=0.0)
    with pytest.raises(ValueError, match="beyond the mesh"):
        Rasterizer([(near_box.vertices, near_box.triangles + 8, (1, 0, 0), 1)])
    with pytest.raises(ValueError, match="colour"):
        Rasterizer([(near_box.vertices, near_box.triangles, (2, 0, 0), 1)])


def test_pixel_map_agrees_with_scipy_and_keeps_planes_exact():
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (30, 40, 3)).astype(np.uint8)
    u = rng.uniform(0, 38.9, (20, 25))
    v = rng.uniform(0, 28.9, (20, 25))
    lens = PixelMap(40, 30, u, v)
    reference = np.stack([ndimage.map_coordinates(image[..., c].astype(float), [v, u], order=1) for c in range(3)], -1)
    assert np.abs(lens.bilinear(image).astype(int) - np.rint(reference)).max() <= 1
    labels = rng.integers(-1, 5, (30, 40))
    assert np.array_equal(lens.nearest(labels), labels[np.rint(v).astype(int), np.rint(u).astype(int)])
    # Inverse depth affine in the image (a plane): interpolated exactly.
    uu, vv = np.meshgrid(np.arange(40), np.arange(30))
    inverse = 0.4 + 0.003 * uu - 0.002 * vv
    assert np.allclose(lens.depth(1.0 / inverse, edge=1.0), 1.0 / (0.4 + 0.003 * u - 0.002 * v), rtol=1e-12)
    with pytest.raises(TypeError, match="uint8"):
        lens.bilinear(image.astype(np.float32))
    with pytest.raises(ValueError):
        lens.depth(np.ones((29, 40)))


def test_box_and_capsule_volumes():
    v, _ = box((0.1, 0.2, 0.3)).volume_and_centroid()
    assert v == pytest.approx(8 * 0.1 * 0.2 * 0.3, rel=1e-12)
    r, length = 0.05, 0.3
    v, c = capsule(r, length, segments=96).volume_and_centroid()
    assert v == pytest.approx(np.pi * r**2 * length + 4 / 3 * np.pi * r**3, rel=2e-3)
    assert np.allclose(c, 0.0, atol=1e-12)
    v, _ = capsule(r, 0.0, segments=96).volume_and_centroid()
    assert v == pytest.approx(4 / 3 * np.pi * r**3, rel=3e-3)


def test_mesh_files_give_their_faces(tmp_path: Path):
    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\nf -4 -2 -1\n")
    vertices, triangles = read_mesh(tmp_path / "quad.obj")
    assert vertices.shape == (4, 3) and triangles.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3]]
    dae = """<?xml version="1.0"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit meter="0.001"/></asset>
  <library_geometries><geometry id="g"><mesh>
    <source id="p"><float_array id="pa" count="12">0 0 0 1000 0 0 1000 1000 0 0 1000 0</float_array></source>
    <source id="n"><float_array id="na" count="3">0 0 1</float_array></source>
    <vertices id="v"><input semantic="POSITION" source="#p"/></vertices>
    <polylist count="1"><input semantic="VERTEX" source="#v" offset="0"/><input semantic="NORMAL" source="#n" offset="1"/>
      <vcount>4</vcount><p>0 0 1 0 2 0 3 0</p></polylist>
    <triangles count="1"><input semantic="VERTEX" source="#v" offset="0"/><p>3 2 0</p></triangles>
  </mesh></geometry></library_geometries>
  <library_visual_scenes><visual_scene id="s"><node><translate>0 0 500</translate><instance_geometry url="#g"/></node></visual_scene></library_visual_scenes>
</COLLADA>"""
    (tmp_path / "quad.dae").write_text(dae)
    vertices, triangles = read_mesh(tmp_path / "quad.dae")
    assert np.allclose(vertices, [[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]])
    assert sorted(triangles.tolist()) == [[0, 1, 2], [0, 2, 3], [3, 2, 0]]


pybullet = pytest.importorskip("pybullet")


@pytest.mark.parametrize("robot", ["ur5", "panda"])
def test_the_rasterized_cell_matches_pybullets_renderer(robot):
    """Every camera of the cell, the robot mid-motion and the person reaching: the
    rasterizer's labels agree with pybullet's tiny renderer on all but edge pixels and
    its depth within a millimetre wherever both see the same body."""
    from earcore.sim.camera import opengl_view
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CameraConfig, CellConfig, default_cameras

    close = CameraConfig("close", "f200", (0.6, 0.35, 0.35), (0.0, 0.0, 0.15))  # the base and lower links, up close
    cell = SimulatedCell(CellConfig(robot=robot, camera_scale=0.5, seed=2, cameras=[*default_cameras(), close]))
    try:
        cell.controller.follow([cell.q + 0.4])
        for _ in range(150):
            cell.step()
        p = cell.p
        for cam in cell.cameras:
            s = cam.sensor
            world_from_camera = cam.world_from_base @ cam.base_from_camera
            _, depth, label = cell.scene.render(world_from_camera, cam._render_K, s.width, s.height, cam._near, cam._far)
            _, _, _, buffer, seg = p.getCameraImage(s.width, s.height, opengl_view(world_from_camera), cam._projection, renderer=p.ER_TINY_RENDERER)
            buffer = np.reshape(buffer, (s.height, s.width))
            n, f = cam._near, cam._far
            tiny_depth = np.where(buffer < 1.0, f * n / (f - (f - n) * buffer), 0.0)
            seg = np.reshape(seg, (s.height, s.width))
            tiny_label = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)
            assert (label == tiny_label).mean() > 0.995, cam.name
            ours, theirs = label == cell.robot_id, tiny_label == cell.robot_id
            # The robot's pixels (every link, the base's too) differ at most along its silhouette.
            inner = theirs.copy()
            inner[1:-1, 1:-1] &= theirs[:-2, 1:-1] & theirs[2:, 1:-1] & theirs[1:-1, :-2] & theirs[1:-1, 2:]
            assert (ours ^ theirs).sum() <= (theirs & ~inner).sum(), cam.name
            same = (label == tiny_label) & (depth > 0)
            assert np.median(np.abs(depth - tiny_depth)[same]) < 1e-4, cam.name
            assert np.percentile(np.abs(depth - tiny_depth)[same], 99) < 3e-3, cam.name
        assert any((cam.render_true()[2] == cell.robot_id).sum() > 50 for cam in cell.cameras)
    finally:
        cell.close()


def test_textured_tools_need_pybullets_renderer():
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig
    from earcore.sim.tools import Checkerboard, ObstaclePlate

    cell = SimulatedCell(CellConfig(camera_scale=0.25))
    try:
        plate = cell.attach_tool(ObstaclePlate(), np.eye(4))  # untextured: drawn
        assert sum((cam.render_true()[2] == plate).sum() for cam in cell.cameras) > 0
        with pytest.raises(ValueError, match="renderer='pybullet'"):
            cell.attach_tool(Checkerboard(), np.eye(4))
    finally:
        cell.close()


def test_a_camera_is_not_rendered_when_its_frame_would_be_replaced_unread():
    """A 30 Hz camera feeding a 15 Hz consumer: only every other frame is rendered,
    the one still newest when the consumer reads."""
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CameraConfig, CellConfig

    config = CellConfig(
        cameras=[
            CameraConfig("fast", "f200", (1.0, 0.5, 0.8), (0.3, 0.0, 0.2), rate_hz=30.0),
            CameraConfig("slow", "kinect_v1", (1.2, -0.5, 1.0), (0.3, 0.0, 0.2), rate_hz=15.0),
        ],
        camera_scale=0.25,
        time_step=1 / 30,
    )
    cell = SimulatedCell(config)
    try:
        consumer, rendered, reads, everything = 0.0, [], [], []
        for _ in range(30):
            cell.step()
            rendered += [(f.camera, round(f.time, 6)) for f in cell.capture(before=consumer)]
            if cell.time + 1e-9 >= consumer:
                reads.append(round(cell.time, 6))
                consumer += 1 / 15
        # Every read gets a frame of each camera, taken at the read: none is wasted.
        for name in ("fast", "slow"):
            assert [t for c, t in rendered if c == name] == reads
        assert len(reads) == 16
    finally:
        cell.close()
    cell = SimulatedCell(config)
    try:
        for _ in range(30):
            cell.step()
            everything += [f.camera for f in cell.capture()]
        assert everything.count("fast") == 30
    finally:
        cell.close()
