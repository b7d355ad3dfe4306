"""The pybullet world's visual shapes as meshes for the core's rasterizer
(`earcore.render`): the cell's cameras drawn in a few milliseconds a frame, with depth
that is the shapes' exact geometry, labels that are pybullet body ids (as its
segmentation reports them) and Lambert-shaded colour.

Boxes, spheres, capsules, cylinders and meshes from files (STL, OBJ, COLLADA) are
drawn in their shape's colour; textures are not (a robot's textured meshes show their
base colour; the cell refuses textured tools such as the calibration board, which need
pybullet's renderer).
"""

from __future__ import annotations

import numpy as np

from earcore.mesh import box, capsule, frustum
from earcore.render import Light, Rasterizer
from earcore.urdf import read_mesh

__all__ = ["CellScene"]


def _pose(p, position, orientation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = np.reshape(p.getMatrixFromQuaternion(orientation), (3, 3))
    m[:3, 3] = position
    return m


class CellScene:
    """Every body's visual shapes in one pybullet client, read when first drawn and again
    whenever bodies are added; each shape a mesh in its link's frame."""

    def __init__(self, client) -> None:
        self.p = client
        self._bodies = -1
        self._raster: Rasterizer | None = None
        #: Per mesh: (body, link, link_from_mesh).
        self._placement: list[tuple[int, int, np.ndarray]] = []
        self._mesh_cache: dict[tuple[str, tuple[float, ...]], tuple[np.ndarray, np.ndarray]] = {}

    def _shape(self, data) -> tuple[np.ndarray, np.ndarray]:
        p = self.p
        body, link, kind, dims, filename = data[0], data[1], data[2], data[3], data[4]
        if kind == p.GEOM_BOX:
            m = box(np.maximum(np.asarray(dims, float) / 2, 1e-6))
        elif kind == p.GEOM_SPHERE:
            m = capsule(dims[0], 0.0)
        elif kind == p.GEOM_CAPSULE:
            m = capsule(dims[1], dims[0])
        elif kind == p.GEOM_CYLINDER:
            m = frustum(dims[1], dims[1], dims[0]).moved(_translation(0.0, 0.0, dims[0] / 2))
        elif kind == p.GEOM_MESH and filename:
            key = (filename.decode(), tuple(float(d) for d in dims))
            if key not in self._mesh_cache:
                vertices, triangles = read_mesh(key[0])
                self._mesh_cache[key] = (vertices * np.asarray(dims, float), triangles)
            return self._mesh_cache[key]
        else:
            raise ValueError(f"body {body} link {link}: the rasterizer draws boxes, spheres, capsules, cylinders and mesh files, not pybullet shape type {kind}")
        return m.vertices, m.triangles

    def _build(self) -> None:
        p = self.p
        meshes, self._placement = [], []
        for index in range(p.getNumBodies()):
            body = p.getBodyUniqueId(index)
            for data in p.getVisualShapeData(body):
                vertices, triangles = self._shape(data)
                rgb = np.clip(np.asarray(data[7][:3], float), 0.0, 1.0)
                meshes.append((vertices, triangles, rgb, body))
                self._placement.append((body, data[1], _pose(p, data[5], data[6])))
        self._raster = Rasterizer(meshes)
        self._bodies = p.getNumBodies()

    def world_from_mesh(self) -> np.ndarray:
        """(M, 4, 4): where each mesh is now."""
        p = self.p
        if self._raster is None or p.getNumBodies() != self._bodies:
            self._build()
        frames: dict[tuple[int, int], np.ndarray] = {}
        out = np.empty((len(self._placement), 4, 4))
        for k, (body, link, link_from_mesh) in enumerate(self._placement):
            key = (body, link)
            if key not in frames:
                if link < 0:
                    # pybullet places the base by its inertial frame; visuals hang off
                    # the link frame, the inertial frame's local offset away.
                    position, orientation = p.getBasePositionAndOrientation(body)
                    info = p.getDynamicsInfo(body, -1)
                    frames[key] = _pose(p, position, orientation) @ np.linalg.inv(_pose(p, info[3], info[4]))
                else:
                    state = p.getLinkState(body, link, computeForwardKinematics=True)
                    frames[key] = _pose(p, state[4], state[5])
            out[k] = frames[key] @ link_from_mesh
        return out

    def render(
        self, world_from_camera: np.ndarray, K: np.ndarray, width: int, height: int, near: float, far: float, light_direction=None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb, depth, label) of the world through a pinhole at `world_from_camera`
        (OpenCV axes); `light_direction` (towards the light, world frame) defaults to
        above and behind the camera."""
        world_from_mesh = self.world_from_mesh()
        assert self._raster is not None
        camera_from_world = np.linalg.inv(world_from_camera)
        towards = np.asarray(light_direction if light_direction is not None else (0.3, 0.2, 1.0), float)
        light = Light(camera_from_world[:3, :3] @ towards)
        return self._raster.render(camera_from_world @ world_from_mesh, K, width, height, near=near, far=far, light=light, background=(255, 255, 255))


def _translation(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m
