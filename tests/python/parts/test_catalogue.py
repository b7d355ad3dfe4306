"""The part meshes: closed, outward, and their volumes and centres of gravity against
closed-form geometry."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from earcore.parts.catalogue import PARTS, SEGMENTS, part, part_names


def polygon_circle_area(r: float) -> float:
    """Area of the SEGMENTS-gon inscribed in a circle of radius r."""
    return SEGMENTS / 2 * r**2 * np.sin(2 * np.pi / SEGMENTS)


@pytest.mark.parametrize("p", PARTS, ids=lambda p: p.name)
def test_mesh_is_closed_and_outward(p):
    t = p.mesh.triangles
    edges = Counter()
    for a, b, c in t:
        for e in ((a, b), (b, c), (c, a)):
            edges[e] += 1
    # every directed edge once and its reverse once: a closed, consistently oriented surface
    assert all(n == 1 for n in edges.values())
    assert all(edges[(b, a)] == 1 for a, b in edges)
    volume, _ = p.mesh.volume_and_centroid()
    assert volume > 0  # outward normals give a positive volume
    assert p.mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)  # resting on the table


def test_the_thirteen_types():
    assert len(part_names()) == 13 and len(set(part_names())) == 13
    with pytest.raises(ValueError, match="unknown part"):
        part("M42")


def test_profile_volume_and_centre():
    p = part("S40_40_G")
    volume, cog = p.mesh.volume_and_centroid()
    assert volume == pytest.approx((0.04**2 - polygon_circle_area(0.0042)) * 0.1, rel=1e-9)
    assert cog == pytest.approx([0.0, 0.0, 0.02], abs=1e-9)
    assert p.extent == pytest.approx([0.1, 0.04, 0.04])


def test_nut_volume_is_hexagon_minus_bore():
    p = part("M30")
    apothem, bore, height = 0.023, 0.015, 0.024
    hexagon = 2 * np.sqrt(3) * apothem**2
    volume, cog = p.mesh.volume_and_centroid()
    assert volume == pytest.approx((hexagon - polygon_circle_area(bore)) * height, rel=1e-9)
    assert cog == pytest.approx([0, 0, height / 2], abs=1e-9)
    assert p.round


def test_bolt_centre_of_gravity_by_hand():
    p = part("M20_100")
    head = 2 * np.sqrt(3) * 0.015**2 * 0.0125  # hexagonal head, 12.5 mm long
    shaft = polygon_circle_area(0.010) * 0.100
    # along the axis (x): head centre at 6.25 mm, shaft centre at 12.5 + 50 mm; the part is
    # centred on its 112.5 mm length, so subtract 56.25 mm
    x = (head * 0.00625 + shaft * 0.0625) / (head + shaft) - 0.05625
    volume, cog = p.mesh.volume_and_centroid()
    assert volume == pytest.approx(head + shaft, rel=1e-9)
    assert cog == pytest.approx([x, 0.0, 0.015], abs=1e-9)  # the head rests on a flat: axis 15 mm up
    assert p.extent[2] == pytest.approx(0.030)


def test_colours_stay_in_range():
    rng = np.random.default_rng(0)
    black = part("F20_20_B")
    for _ in range(50):
        assert max(black.colour(rng)) <= 0.2 + 1e-9
