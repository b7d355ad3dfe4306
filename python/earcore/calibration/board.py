"""Finding the checkerboard (Paper I): its inner corners in an image, in the board's
own order (the hollow square tells the four orientations apart), and their 3D
positions from the depth image.

OpenCV finds the corners (`findChessboardCornersSB`, sub-pixel). Its order is fixed up
to a turn of the board; of the candidate orders, the right one keeps the board's
handedness (its printed face toward the camera) and puts the hollow square first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Checkerboard", "Detection", "corner_points", "detect_board", "undistort_pixels"]


@dataclass(frozen=True)
class Checkerboard:
    """Squares in a `cols` × `rows` grid on a white plate with a `margin` border. The
    board frame: origin at the board's centre, x along the columns, y along the rows,
    z out of the printed face. The square at column 0, row 0 is hollow (an outline)."""

    cols: int = 7
    rows: int = 5
    square: float = 0.03
    margin: float = 0.015
    #: Pixels per square in the texture.
    resolution: int = 64

    @property
    def size(self) -> tuple[float, float]:
        return self.cols * self.square + 2 * self.margin, self.rows * self.square + 2 * self.margin

    def inner_corners(self) -> np.ndarray:
        """The (cols-1)·(rows-1) inner corners in the board frame, row by row (OpenCV's order)."""
        xs = (np.arange(1, self.cols) - self.cols / 2) * self.square
        ys = (np.arange(1, self.rows) - self.rows / 2) * self.square
        return np.array([[x, y, 0.0] for y in ys for x in xs])

    def is_dark(self, col: int, row: int) -> bool:
        return (col + row) % 2 == 0

    def square_centres(self) -> list[tuple[int, int, np.ndarray]]:
        return [
            (c, r, np.array([(c + 0.5 - self.cols / 2) * self.square, (r + 0.5 - self.rows / 2) * self.square, 0.0]))
            for r in range(self.rows)
            for c in range(self.cols)
        ]

    def texture(self) -> np.ndarray:
        """RGB image of the printed face; image x = board x, image rows = board y."""
        px = self.resolution
        m = round(self.margin / self.square * px)
        h, w = self.rows * px + 2 * m, self.cols * px + 2 * m
        img = np.full((h, w, 3), 255, np.uint8)
        for c in range(self.cols):
            for r in range(self.rows):
                if not self.is_dark(c, r):
                    continue
                y0, x0 = m + r * px, m + c * px
                img[y0 : y0 + px, x0 : x0 + px] = 0
                if c == 0 and r == 0:  # the hollow square: a thick outline only
                    t = px // 5
                    img[y0 + t : y0 + px - t, x0 + t : x0 + px - t] = 255
        return img


def _cv2():
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("calibration needs OpenCV: pip install 'earcore[calibration]'") from exc
    return cv2


@dataclass
class Detection:
    """The board's inner corners in one image: pixels (N, 2) in `Checkerboard.inner_corners`
    order; `sharpness` is OpenCV's edge-width estimate (pixels, lower is sharper)."""

    corners: np.ndarray
    image_size: tuple[int, int]

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(axis=0)

    def distance_from_image_centre(self) -> float:
        """Of the board's centre, as a fraction of the image's half-diagonal."""
        w, h = self.image_size
        return float(np.linalg.norm(self.centre - [(w - 1) / 2, (h - 1) / 2]) / np.hypot(w / 2, h / 2))


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = image[..., :3].mean(axis=2)
    return np.ascontiguousarray(np.clip(image, 0, 255).astype(np.uint8))


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    cv2 = _cv2()
    h, _ = cv2.findHomography(src.astype(np.float64), dst.astype(np.float64))
    return h


def _apply_h(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.c_[xy, np.ones(len(xy))] @ h.T
    return p[:, :2] / p[:, 2:]


def detect_board(
    image: np.ndarray, board: Checkerboard = Checkerboard(), *, border: int = 3, max_residual: float = 2.0
) -> Detection | None:
    """The board's inner corners in `image` (grey or colour, uint8), or None when the
    board is not seen whole, its orientation cannot be told, it is within `border`
    pixels of the image's edge, or the corners are not one flat grid: a homography
    from the board leaves a corner more than `max_residual` pixels off (a lens bends
    a board's image by far less; a corner found in the wrong place does not)."""
    cv2 = _cv2()
    grey = _grey(image)
    pattern = (board.cols - 1, board.rows - 1)
    # The sector-based detector is accurate (~0.1 px) where the classic one can miss a
    # corner by pixels (next to the hollow square), but slow on a whole 1080p image:
    # the classic one finds the board, the sector-based one measures it in a crop.
    sb_flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    found, rough = cv2.findChessboardCorners(grey, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found:
        rough = rough.reshape(-1, 2)
        margin = 1.5 * np.linalg.norm(np.diff(rough, axis=0), axis=1).max()
        lo = np.maximum(np.floor(rough.min(axis=0) - margin).astype(int), 0)
        hi = np.minimum(np.ceil(rough.max(axis=0) + margin).astype(int), [grey.shape[1], grey.shape[0]])
        found, corners = cv2.findChessboardCornersSB(np.ascontiguousarray(grey[lo[1] : hi[1], lo[0] : hi[0]]), pattern, flags=sb_flags)
        if found:
            corners = corners.reshape(-1, 2) + lo
    else:
        found, corners = cv2.findChessboardCornersSB(grey, pattern, flags=sb_flags)
    if not found:
        return None
    px = corners.reshape(-1, 2).astype(np.float64)
    h, w = grey.shape
    if (px < border).any() or (px[:, 0] > w - 1 - border).any() or (px[:, 1] > h - 1 - border).any():
        return None
    grid = board.inner_corners()[:, :2]
    nx, ny = pattern
    index = np.arange(nx * ny).reshape(ny, nx)
    best = None
    for order in (index, index[::-1, ::-1], index[::-1, :], index[:, ::-1]):
        candidate = px[order.reshape(-1)]
        hom = _homography(grid, candidate)
        # Handedness: with the printed face toward the camera, board x then y turn
        # clockwise in the image (v points down).
        origin, ex, ey = _apply_h(hom, np.array([[0.0, 0.0], [board.square, 0.0], [0.0, board.square]]))
        a, b = ex - origin, ey - origin
        if a[0] * b[1] - a[1] * b[0] >= 0:
            continue
        # The hollow square's centre is light; the other corner squares' are dark.
        centres = {(c, r): xy[:2] for c, r, xy in board.square_centres()}
        hollow = _apply_h(hom, centres[(0, 0)][None])[0]
        opposite = _apply_h(hom, centres[(board.cols - 1, board.rows - 1)][None])[0]
        light = _sample(grey, hollow) - _sample(grey, opposite)
        if best is None or light > best[0]:
            best = (light, candidate)
    if best is None or best[0] < 40:  # no clear hollow square: orientation unknown
        return None
    hom = _homography(grid, best[1])
    if np.linalg.norm(_apply_h(hom, grid) - best[1], axis=1).max() > max_residual:
        return None
    return Detection(best[1], (w, h))


def _sample(grey: np.ndarray, xy: np.ndarray, radius: int = 1) -> float:
    u, v = int(round(xy[0])), int(round(xy[1]))
    h, w = grey.shape
    if not (0 <= u < w and 0 <= v < h):
        return 0.0
    return float(grey[max(v - radius, 0) : v + radius + 1, max(u - radius, 0) : u + radius + 1].mean())


def undistort_pixels(pixels: np.ndarray, K: np.ndarray, distortion) -> np.ndarray:
    """Normalised image coordinates (N, 2) (x/z, y/z) of distorted pixels (N, 2)."""
    cv2 = _cv2()
    pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(pts, np.asarray(K, np.float64), np.asarray(distortion, np.float64)).reshape(-1, 2)


def corner_points(
    detection: Detection,
    depths: np.ndarray,
    K: np.ndarray,
    distortion,
    *,
    method: str = "median",
    window: int = 10,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """The corners' 3D positions (N, 3) in the depth camera's frame, NaN where no depth.

    `depths` (F, H, W): consecutive depth frames of the still board (Paper I: 5).
    "median" (Paper I): each corner's depth is the median over the frames of a
    `window`-pixel neighbourhood. "plane": a plane fitted to every depth pixel inside
    the board's corners in every frame, each corner's ray intersected with it (many
    more pixels average the noise and the depth steps out). `depths` may be a crop of
    the images whose pixel (0, 0) is image pixel `origin` (u, v)."""
    depths = np.asarray(depths, dtype=np.float64)
    if depths.ndim == 2:
        depths = depths[None]
    rays = np.c_[undistort_pixels(detection.corners, K, distortion), np.ones(len(detection.corners))]
    _, h, w = depths.shape
    if method == "median":
        r = window // 2
        out = np.full((len(rays), 3), np.nan)
        for i, (u, v) in enumerate(np.rint(detection.corners - origin).astype(int)):
            patch = depths[:, max(v - r, 0) : v + r, max(u - r, 0) : u + r]
            valid = patch[patch > 0]
            if len(valid):
                out[i] = rays[i] * np.median(valid)
        return out
    if method == "plane":
        cv2 = _cv2()
        # Pixels inside the corners' hull, shrunk a little: away from the board's edge.
        hull = cv2.convexHull(detection.corners.astype(np.float32)).reshape(-1, 2)
        centre = hull.mean(axis=0)
        hull = centre + 0.9 * (hull - centre)
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, np.rint(hull - origin).astype(np.int32), 1)
        vs, us = np.nonzero(mask)
        if len(us) < 10:
            return np.full((len(rays), 3), np.nan)
        pix_rays = np.c_[undistort_pixels(np.c_[us, vs] + np.asarray(origin), K, distortion), np.ones(len(us))]
        z = depths[:, vs, us]
        valid = z > 0
        pts = (pix_rays[None] * z[..., None])[valid]
        if len(pts) < 10:
            return np.full((len(rays), 3), np.nan)
        normal, offset = _fit_plane(pts)
        denom = rays @ normal
        return rays * (offset / denom)[:, None]
    raise ValueError(f"method must be 'median' or 'plane', got {method!r}")


def _fit_plane(points: np.ndarray, trims: int = 2) -> tuple[np.ndarray, float]:
    """Least-squares plane n·p = d, refitted after dropping points beyond 3 σ."""
    keep = np.ones(len(points), bool)
    for _ in range(trims + 1):
        p = points[keep]
        c = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        n = vt[2]
        dist = (points - c) @ n
        sigma = dist[keep].std()
        keep = np.abs(dist) <= 3 * sigma + 1e-9
    return n, float(n @ c)
