"""Tools the robot holds in the cell: Paper I's calibration checkerboard (7 × 5 squares
of 30 mm, one corner square hollow so the board's orientation can be told, on a rigid
mount) and Paper II's obstacle plate (10 × 20 cm) for the danger-map experiment.

A tool is rendered as a textured quad (or a thin box) placed every step at
world_from_tool = world_from_flange · flange_from_tool; its geometry in the tool frame
is known exactly (ground truth for calibration).
"""

from __future__ import annotations

import struct
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Checkerboard", "ObstaclePlate", "write_png"]


def write_png(path: Path, rgb: np.ndarray) -> None:
    """A minimal PNG writer (8-bit RGB), so textures need no imaging library."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


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

    def visual_shape(self, client) -> tuple[int, int]:
        """A textured quad (OBJ with texture coordinates) facing +z: (shape, texture)."""
        folder = Path(tempfile.mkdtemp(prefix="earcore_board_"))
        write_png(folder / "board.png", self.texture())
        w, h = self.size
        (folder / "board.obj").write_text(
            "v {0} {1} 0\nv {2} {1} 0\nv {2} {3} 0\nv {0} {3} 0\n".format(-w / 2, -h / 2, w / 2, h / 2)
            + "vt 0 1\nvt 1 1\nvt 1 0\nvt 0 0\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n"
        )
        shape = client.createVisualShape(client.GEOM_MESH, fileName=str(folder / "board.obj"))
        return shape, client.loadTexture(str(folder / "board.png"))


@dataclass(frozen=True)
class ObstaclePlate:
    """Paper II's obstacle plate: 10 × 20 cm, 5 mm thick."""

    width: float = 0.10
    length: float = 0.20
    thickness: float = 0.005

    def visual_shape(self, client) -> tuple[int, int]:
        half = [self.width / 2, self.length / 2, self.thickness / 2]
        return client.createVisualShape(client.GEOM_BOX, halfExtents=half, rgbaColor=(0.9, 0.5, 0.1, 1)), -1
