"""A minimal PNG codec for 8-bit images, so the training path needs no imaging library.

`encode` / `write` store gray (H, W), RGB (H, W, 3) or RGBA (H, W, 4) uint8 images and
16-bit gray (H, W) uint16 images (depth in mm) with filter 0 on every row and zlib
compression. `decode` / `read` read such files with numpy and zlib alone
(non-interlaced, filter 0 on every row); any other PNG (other filters, bit depths,
palettes, interlacing) is handed to OpenCV, then to Pillow, whichever is installed.
Corrupt data raises `DatasetError`.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning.errors import DatasetError

__all__ = ["decode", "encode", "read", "write"]

SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour type per channel count (0 gray, 2 RGB, 6 RGBA) and back.
_COLOUR_TYPE = {1: 0, 3: 2, 4: 6}
_CHANNELS = {v: k for k, v in _COLOUR_TYPE.items()}


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode(image: np.ndarray, level: int = 6) -> bytes:
    """The PNG bytes of a uint8 image (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), or of
    a uint16 gray image (H, W) (16 bits per pixel)."""
    a = np.asarray(image)
    if a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG images must be uint8 (or uint16 gray), got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    channels = 1 if a.ndim == 2 else (a.shape[2] if a.ndim == 3 else 0)
    if channels not in _COLOUR_TYPE or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"expected an (H, W), (H, W, 3) or (H, W, 4) image, got shape {a.shape}")
    if a.dtype == np.uint16 and channels != 1:
        raise ValueError(f"16-bit PNG images must be gray (H, W), got shape {a.shape}")
    h, w = a.shape[:2]
    bits = 8 * a.dtype.itemsize
    row_bytes = w * channels * a.dtype.itemsize
    rows = np.empty((h, 1 + row_bytes), dtype=np.uint8)
    rows[:, 0] = 0  # filter type 0 (none) on every row
    rows[:, 1:] = np.ascontiguousarray(a.astype(a.dtype.newbyteorder(">"), copy=False)).view(np.uint8).reshape(h, row_bytes)
    header = struct.pack(">IIBBBBB", w, h, bits, _COLOUR_TYPE[channels], 0, 0, 0)
    return SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows.tobytes(), level)) + _chunk(b"IEND", b"")


def write(path: str | Path, image: np.ndarray, level: int = 6) -> None:
    Path(path).write_bytes(encode(image, level))


def _chunks(data: bytes, name: str):
    """(kind, payload) of each chunk, CRCs checked."""
    pos = len(SIGNATURE)
    while pos < len(data):
        if pos + 8 > len(data):
            raise DatasetError(f"{name}: truncated PNG (chunk header at byte {pos})")
        (length,) = struct.unpack_from(">I", data, pos)
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise DatasetError(f"{name}: truncated PNG ({kind.decode('latin-1')} chunk at byte {pos})")
        payload = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack_from(">I", data, pos + 8 + length)
        if zlib.crc32(kind + payload) & 0xFFFFFFFF != crc:
            raise DatasetError(f"{name}: corrupt PNG (bad checksum of the {kind.decode('latin-1')} chunk at byte {pos})")
        yield kind, payload
        if kind == b"IEND":
            return
        pos = end
    raise DatasetError(f"{name}: truncated PNG (no IEND chunk)")


def decode(data: bytes, name: str = "PNG data") -> np.ndarray:
    """The image in PNG bytes: (H, W) for gray, (H, W, 3) RGB, (H, W, 4) RGBA, uint8
    (or uint16 for 16-bit files read by a fallback). `name` is used in errors."""
    if not data.startswith(SIGNATURE):
        raise DatasetError(f"{name}: not a PNG file (bad signature)")
    header: bytes | None = None
    idat = []
    other = False
    for kind, payload in _chunks(data, name):
        if kind == b"IHDR":
            header = payload
        elif kind == b"IDAT":
            idat.append(payload)
        elif kind == b"PLTE":
            other = True
    if header is None or len(header) != 13:
        raise DatasetError(f"{name}: PNG without a valid IHDR chunk")
    w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", header)
    if w == 0 or h == 0:
        raise DatasetError(f"{name}: PNG of size {w}×{h}")
    if other or colour not in _CHANNELS or interlace != 0 or not (depth == 8 or (depth == 16 and colour == 0)):
        return _fallback(data, name)
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        raise DatasetError(f"{name}: corrupt PNG image data ({exc})") from None
    channels = _CHANNELS[colour]
    size = depth // 8
    stride = 1 + w * channels * size
    if len(raw) != h * stride:
        raise DatasetError(f"{name}: corrupt PNG: {len(raw)} bytes of image data for {w}×{h}×{channels}×{depth} bits")
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(h, stride)
    if rows[:, 0].any():
        return _fallback(data, name)  # filtered rows: a general decoder undoes them
    if size == 2:
        return np.ascontiguousarray(rows[:, 1:]).view(">u2").reshape(h, w).astype(np.uint16)
    image = rows[:, 1:].reshape(h, w, channels)
    return image[..., 0].copy() if channels == 1 else image.copy()


def _fallback(data: bytes, name: str) -> np.ndarray:
    cv2: Any
    try:
        import cv2
    except ImportError:
        cv2 = None
    if cv2 is not None:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DatasetError(f"{name}: OpenCV could not decode this PNG")
        if image.ndim == 3:  # OpenCV's channel order is BGR(A)
            image = image[..., [2, 1, 0, 3][: image.shape[2]]] if image.shape[2] == 4 else image[..., ::-1]
        return np.ascontiguousarray(image)
    try:
        import io

        from PIL import Image
    except ImportError:
        raise DatasetError(
            f"{name}: this PNG (filtered rows, a palette, interlacing or not 8-bit) needs OpenCV or Pillow to read; earcore's own PNGs do not"
        ) from None
    try:
        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img).copy()
    except Exception as exc:
        raise DatasetError(f"{name}: Pillow could not decode this PNG ({exc})") from None


def read(path: str | Path) -> np.ndarray:
    path = Path(path)
    return decode(path.read_bytes(), str(path))
