"""earcore's PNG codec against OpenCV's, both ways, and its errors on damaged files."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from earcore.learning import png
from earcore.learning.errors import DatasetError

cv2 = pytest.importorskip("cv2")


def images():
    rng = np.random.default_rng(0)
    return [
        rng.integers(0, 256, (7, 5), dtype=np.uint8),
        rng.integers(0, 256, (106, 128, 3), dtype=np.uint8),
        rng.integers(0, 256, (3, 9, 4), dtype=np.uint8),
        np.zeros((1, 1), dtype=np.uint8),
    ]


def to_rgb_order(image: np.ndarray) -> np.ndarray:
    """OpenCV's BGR(A) order to RGB(A)."""
    if image.ndim == 2:
        return image
    return image[..., [2, 1, 0, 3]] if image.shape[2] == 4 else image[..., ::-1]


@pytest.mark.parametrize("index", range(4))
def test_opencv_reads_what_earcore_writes(index):
    image = images()[index]
    data = png.encode(image)
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(to_rgb_order(decoded).reshape(image.shape), image)


@pytest.mark.parametrize("index", range(4))
def test_earcore_reads_what_opencv_writes(index):
    """OpenCV filters its rows (Sub, Up, Paeth): the fallback decoder reads them."""
    image = images()[index]
    ok, data = cv2.imencode(".png", to_rgb_order(image))
    assert ok
    assert np.array_equal(png.decode(data.tobytes()).reshape(image.shape), image)


def test_fast_path_reads_its_own_files_without_any_library(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_imaging(name, *args, **kwargs):
        if name in ("cv2", "PIL"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_imaging)
    for image in images():
        assert np.array_equal(png.decode(png.encode(image)), image)
    ok, data = cv2.imencode(".png", np.full((4, 4), 7, np.uint8) + np.arange(4, dtype=np.uint8))
    with pytest.raises(DatasetError, match="needs OpenCV or Pillow"):
        png.decode(data.tobytes(), "filtered.png")


def test_every_row_is_unfiltered_and_the_data_is_zlib():
    image = images()[1]
    data = png.encode(image)
    start = data.index(b"IDAT") + 4
    length = int.from_bytes(data[start - 8 : start - 4], "big")
    raw = zlib.decompress(data[start : start + length])
    rows = np.frombuffer(raw, np.uint8).reshape(106, 1 + 128 * 3)
    assert not rows[:, 0].any()


def test_damaged_files_are_named_in_the_error(tmp_path):
    data = bytearray(png.encode(images()[1]))
    path = tmp_path / "x.png"
    flipped = data.copy()
    flipped[data.index(b"IDAT") + 20] ^= 0xFF
    path.write_bytes(bytes(flipped))
    with pytest.raises(DatasetError, match="x.png.*checksum"):
        png.read(path)
    path.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(DatasetError, match="x.png.*truncated"):
        png.read(path)
    path.write_bytes(b"GIF89a" + bytes(data[6:]))
    with pytest.raises(DatasetError, match="not a PNG"):
        png.read(path)


def test_encode_rejects_what_png_cannot_hold():
    with pytest.raises(ValueError, match="uint8"):
        png.encode(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="shape"):
        png.encode(np.zeros((4, 4, 2), np.uint8))
