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

from earcore.calibration.board import Checkerboard

__all__ = ["Checkerboard", "ObstaclePlate", "visual_shape", "write_png"]


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
class ObstaclePlate:
    """Paper II's obstacle plate: 10 × 20 cm, 5 mm thick."""

    width: float = 0.10
    length: float = 0.20
    thickness: float = 0.005

    def visual_shape(self, client) -> tuple[int, int]:
        half = [self.width / 2, self.length / 2, self.thickness / 2]
        return client.createVisualShape(client.GEOM_BOX, halfExtents=half, rgbaColor=(0.9, 0.5, 0.1, 1)), -1


def board_visual_shape(board: Checkerboard, client) -> tuple[int, int]:
    """A textured quad (OBJ with texture coordinates) facing +z: (shape, texture)."""
    folder = Path(tempfile.mkdtemp(prefix="earcore_board_"))
    write_png(folder / "board.png", board.texture())
    w, h = board.size
    (folder / "board.obj").write_text(
        "v {0} {1} 0\nv {2} {1} 0\nv {2} {3} 0\nv {0} {3} 0\n".format(-w / 2, -h / 2, w / 2, h / 2)
        + "vt 0 1\nvt 1 1\nvt 1 0\nvt 0 0\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n"
    )
    shape = client.createVisualShape(client.GEOM_MESH, fileName=str(folder / "board.obj"))
    return shape, client.loadTexture(str(folder / "board.png"))


def visual_shape(tool, client) -> tuple[int, int]:
    """The pybullet visual shape and texture (-1: none) of a tool the cell can mount."""
    if isinstance(tool, Checkerboard):
        return board_visual_shape(tool, client)
    return tool.visual_shape(client)
