"""Overlays in the papers' convention: green crosses on the truth, red circles round the
predictions, a magenta circle round the base, the mask tinted."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.pose.overlay import GREEN, MAGENTA, RED, overlay, project


def test_marks_land_where_they_should():
    image = np.zeros((60, 80, 3), np.uint8)
    mask = np.zeros((60, 80), bool)
    mask[40:50, 5:15] = True
    out = overlay(image, mask=mask, truth=[[20, 20]], predicted=[[50, 30]], base=[70, 45], radius=5)
    assert tuple(out[20, 20]) == GREEN and tuple(out[23, 23]) == GREEN and tuple(out[17, 23]) == GREEN
    ys, xs = np.nonzero(np.all(out == RED, axis=2))
    assert len(xs) > 10 and np.allclose(np.hypot(xs - 50, ys - 30), 5, atol=1.0)
    assert tuple(out[30, 50]) == (0, 0, 0)  # a circle, not a disc
    ys, xs = np.nonzero(np.all(out == MAGENTA, axis=2))
    assert len(xs) > 10 and np.allclose(np.hypot(xs - 70, ys - 45), 6.5, atol=1.0)
    assert out[45, 10].any() and not out[45, 30].any()  # tinted inside the mask only
    assert not image.any()  # the input is left alone


def test_projection_and_bad_input():
    k = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    uv = project(np.array([[0.1, -0.2, 2.0], [0, 0, -1.0]]), k)
    assert uv[0] == pytest.approx([45.0, 20.0]) and np.isnan(uv[1]).all()
    overlay(np.zeros((10, 10, 3), np.uint8), predicted=uv)  # points behind the camera are skipped
    with pytest.raises(ValueError, match="uint8"):
        overlay(np.zeros((10, 10, 3)))
    with pytest.raises(ValueError, match="mask"):
        overlay(np.zeros((10, 10, 3), np.uint8), mask=np.zeros((5, 5), bool))
