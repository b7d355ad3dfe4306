"""Cameras: the interface the perception loop reads (frames + intrinsics + pose), and
the simulated RGB-D camera that renders the pybullet cell through a sensor model.

Real cameras or recorded frames plug in by implementing `Camera`.
"""

from __future__ import annotations

import numpy as np

from earcore.interfaces import Camera, Frame
from earcore.render import PixelMap
from earcore.sim.sensors import SensorModel

__all__ = ["Camera", "Frame", "SimulatedCamera", "opengl_projection", "opengl_view"]


def opengl_projection(K: np.ndarray, width: int, height: int, near: float = 0.05, far: float = 10.0) -> list[float]:
    """pybullet's (column-major) projection matrix reproducing the pinhole K exactly,
    with OpenCV's pixel convention (pixel (u, v) centred at (u, v), v downward).

    The tiny renderer samples pixel u at window x = u and row v at window y = H - 1 - v
    (measured: tilted planes back-project within 15 µm with these offsets, and half a
    pixel off without them), hence cx and cy + 1 below rather than the textbook + 0.5."""
    w, h = width, height
    p = np.zeros((4, 4))
    p[0, 0] = 2 * K[0, 0] / w
    p[0, 2] = 1 - 2 * K[0, 2] / w
    p[1, 1] = 2 * K[1, 1] / h
    p[1, 2] = 2 * (K[1, 2] + 1.0) / h - 1
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2 * far * near / (far - near)
    p[3, 2] = -1
    return p.T.reshape(-1).tolist()


def opengl_view(base_from_camera: np.ndarray) -> list[float]:
    """pybullet's view matrix for an OpenCV-convention camera pose (z forward, y down)."""
    gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    world_from_gl = base_from_camera @ gl_from_cv
    return np.linalg.inv(world_from_gl).T.reshape(-1).tolist()


class _Lens:
    """Renders a distorted camera with a pinhole renderer: a pinhole image wide enough
    to cover the distorted field of view is rendered, then each output pixel samples
    it where its (undistorted) ray lands (`earcore.render.PixelMap`). The rays come
    from the same Brown-Conrady inversion the depth back-projection uses."""

    def __init__(self, K: np.ndarray, distortion, width: int, height: int) -> None:
        from earcore.cloud import depth_to_points

        self.distortion = np.asarray(distortion, dtype=np.float64)
        self.width, self.height = width, height
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        self.render_K = K.copy()
        self.pixels: PixelMap | None = None
        if not self.distortion.any():
            return
        rays, pixels = depth_to_points(
            np.ones((height, width)), fx, fy, cx, cy, distortion=self.distortion, return_pixels=True
        )
        if len(pixels) != width * height:
            raise ValueError(f"distortion {tuple(self.distortion)} cannot be inverted over the whole image")
        x, y = rays[:, 0], rays[:, 1]
        # Shrink the render's focal length until every ray falls inside it (with a margin).
        spread = max(np.abs(x).max() * fx / cx, np.abs(y).max() * fy / cy, 1.0) * 1.02
        self.render_K = np.array([[fx / spread, 0, cx], [0, fy / spread, cy], [0, 0, 1.0]])
        u = (fx / spread * x + cx).reshape(height, width)
        v = (fy / spread * y + cy).reshape(height, width)
        self.pixels = PixelMap(width, height, u, v)

    def nearest(self, image: np.ndarray) -> np.ndarray:
        return image if self.pixels is None else self.pixels.nearest(image)

    def bilinear(self, image: np.ndarray) -> np.ndarray:
        return image if self.pixels is None else self.pixels.bilinear(image)

    def depth(self, z: np.ndarray, edge: float = 0.02) -> np.ndarray:
        """Depth along each distorted pixel's ray: inverse depth interpolated bilinearly
        (1/z is affine across a plane's image, so planes stay exact) where the four
        neighbours are one surface; the nearest pixel's depth at edges and holes."""
        return z if self.pixels is None else self.pixels.depth(z, edge)


def _downsample(rgb: np.ndarray, z: np.ndarray, body: np.ndarray, s: int, edge: float = 0.02):
    """s×s blocks to one pixel: colour averaged (anti-aliasing); depth as the mean of
    1/z (exact for a plane: 1/z is affine across its image) where the block is one
    surface, else the sample nearest the block's centre, as are the labels."""
    h, w = z.shape[0] // s, z.shape[1] // s
    colour = rgb.reshape(h, s, w, s, 3).astype(np.float64).mean(axis=(1, 3))
    blocks = z.reshape(h, s, w, s)
    centre = blocks[:, s // 2, :, s // 2]
    smooth = (blocks.min(axis=(1, 3)) > 0) & (np.ptp(blocks, axis=(1, 3)) < edge)
    inv = (1.0 / np.where(blocks > 0, blocks, 1.0)).mean(axis=(1, 3))
    depth = np.where(smooth, 1.0 / inv, centre)
    labels = body.reshape(h, s, w, s)[:, s // 2, :, s // 2]
    return np.rint(colour).astype(np.uint8), depth, labels


class SimulatedCamera:
    """A camera in the pybullet cell: renders colour, true depth and segmentation with
    pybullet's tiny renderer, or with the core's rasterizer when given the cell's
    `scene` (`earcore.sim.raster.CellScene`: the same geometry, untextured, several
    times faster), then applies its sensor's noise model.

    `mount` is None for a fixed camera or a (body id, link index, link_from_camera)
    triple for one carried by the robot (e.g. on the end-effector)."""

    def __init__(
        self,
        client,
        name: str,
        sensor: SensorModel,
        base_from_camera: np.ndarray,
        *,
        rng: np.random.Generator,
        mount: tuple[int, int, np.ndarray] | None = None,
        world_from_base: np.ndarray | None = None,
        supersample: int = 1,
        lighting: dict | None = None,
        scene=None,
    ) -> None:
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.client = client
        #: Render s×s samples per pixel and average them: anti-aliased edges, for the
        #: checkerboard's corners (the tiny renderer itself does not anti-alias).
        self.supersample = supersample
        #: pybullet's light settings for the tiny renderer (lightDirection,
        #: lightAmbientCoeff, ...); None: its defaults.
        self.lighting = dict(lighting or {})
        self.scene = scene
        self.name = name
        self.sensor = sensor
        self._pose = np.asarray(base_from_camera, dtype=np.float64)
        self.mount = mount
        self.rng = rng
        self.world_from_base = np.eye(4) if world_from_base is None else world_from_base
        self._near, self._far = 0.05, sensor.far + 1.0
        self._lens = _Lens(sensor.intrinsics, sensor.distortion, sensor.width, sensor.height)
        self._render_K = self._supersampled(self._lens.render_K)
        self._projection = self._projection_for(self._lens.render_K, sensor.width, sensor.height)
        self._colour_lens: _Lens | None = None
        if sensor.colour is not None:
            c = sensor.colour
            self._colour_lens = _Lens(c.intrinsics, c.distortion, c.width, c.height)
            self._colour_render_K = self._supersampled(self._colour_lens.render_K)
            self._colour_projection = self._projection_for(self._colour_lens.render_K, c.width, c.height)

    def _supersampled(self, K: np.ndarray) -> np.ndarray:
        """The render's pinhole; with supersampling, s× the pixels, each output pixel
        (u, v) covering render pixels s·u … s·u + s − 1 (centre s·u + (s − 1)/2)."""
        s = self.supersample
        hi = K.copy()
        hi[:2] *= s
        hi[0, 2] = s * K[0, 2] + (s - 1) / 2
        hi[1, 2] = s * K[1, 2] + (s - 1) / 2
        return hi

    def _projection_for(self, K: np.ndarray, width: int, height: int) -> list[float]:
        s = self.supersample
        return opengl_projection(self._supersampled(K), s * width, s * height, self._near, self._far)
    @property
    def base_from_camera(self) -> np.ndarray:
        """True pose (ground truth; the perception loop uses calibrated poses)."""
        if self.mount is None:
            return self._pose.copy()
        body, link, link_from_camera = self.mount
        p = self.client
        state = p.getLinkState(body, link, computeForwardKinematics=True)
        world_from_link = np.eye(4)
        world_from_link[:3, :3] = np.reshape(p.getMatrixFromQuaternion(state[5]), (3, 3))
        world_from_link[:3, 3] = state[4]
        return np.linalg.inv(self.world_from_base) @ world_from_link @ link_from_camera

    def _render(self, base_from_camera: np.ndarray, width: int, height: int, projection: list[float], K: np.ndarray, lens: _Lens):
        s = self.supersample
        world_from_camera = self.world_from_base @ base_from_camera
        if self.scene is not None:
            rgb, z, body = self.scene.render(
                world_from_camera, K, s * width, s * height, self._near, self._far, self.lighting.get("lightDirection")
            )
        else:
            p = self.client
            _, _, rgba, depth_buffer, seg = p.getCameraImage(
                s * width, s * height, opengl_view(world_from_camera), projection, renderer=p.ER_TINY_RENDERER, **self.lighting
            )
            rgb = np.reshape(np.asarray(rgba, dtype=np.uint8), (s * height, s * width, 4))[..., :3]
            buf = np.reshape(np.asarray(depth_buffer, dtype=np.float64), (s * height, s * width))
            n, f = self._near, self._far
            z = f * n / (f - (f - n) * buf)
            z = np.where(buf < 1.0, z, 0.0)
            seg = np.reshape(np.asarray(seg, dtype=np.int64), (s * height, s * width))
            body = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)
        if s > 1:
            rgb, z, body = _downsample(rgb, z, body, s)
        # Through the lens: depth and labels are never blended across edges.
        return lens.bilinear(rgb), lens.depth(z), lens.nearest(body)

    def place(self, base_from_camera: np.ndarray) -> None:
        """Move a fixed camera (someone bumped it, or it stands off its nominal place)."""
        if self.mount is not None:
            raise ValueError(f"camera {self.name!r} rides on the robot; it cannot be placed")
        self._pose = np.asarray(base_from_camera, dtype=np.float64).copy()

    def render_true(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The depth camera's view through its lens: image (H, W, 3; the IR image of
        a real sensor, in colour here), true metric depth (H, W; 0 where nothing within
        range) and segmentation (H, W; body id, -1 background)."""
        return self._render(self.base_from_camera, self.sensor.width, self.sensor.height, self._projection, self._render_K, self._lens)

    def render_colour(self) -> np.ndarray:
        """The colour camera's image (its own resolution, lens and pose beside the depth
        camera); the depth camera's view when the sensor has no separate colour camera."""
        if self.sensor.colour is None or self._colour_lens is None:
            return self.render_true()[0]
        c = self.sensor.colour
        pose = self.base_from_camera @ c.depth_from_colour
        return self._render(pose, c.width, c.height, self._colour_projection, self._colour_render_K, self._colour_lens)[0]

    def capture(self, time: float) -> Frame:
        colour, z, body = self.render_true()
        depth = self.sensor.corrupt(z, self.rng)
        return Frame(
            self.name, time, colour, depth, self.sensor.intrinsics, self.base_from_camera, body,
            np.asarray(self.sensor.distortion, dtype=np.float64),
        )
