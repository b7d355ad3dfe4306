"""Meshes from outlines and the connectors' geometry, against hand-computed areas and
volumes and the standards' layout properties the vision relies on."""

import numpy as np
import pytest

from earcore.charging.connectors import CONNECTORS, connector, hole_polygon
from earcore.errors import ConfigError
from earcore.mesh import densify, extrude, inside_polygon, offset_polygon, polygon_area, triangulate


def square(cx, cy, half):
    return np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]])


def edges_are_closed(mesh):
    """Every directed edge appears once and its reverse once: a closed, consistently
    oriented surface."""
    t = mesh.triangles
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    pairs = {tuple(e) for e in directed}
    return len(pairs) == len(directed) and all((b, a) in pairs for a, b in pairs)


def test_face_with_holes_covers_exactly_the_outline_minus_the_holes():
    outline = densify(square(0, 0, 0.05), 0.01)
    holes = [densify(square(-0.02, 0.01, 0.01), 0.005), hole_polygon(0.02, -0.02, 0.008, 16)]
    points, tris = triangulate(outline, holes)
    a, b, c = (points[tris[:, i]] for i in range(3))
    signed = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    assert (signed > 0).all()  # counter-clockwise
    hole_area = 0.02**2 + polygon_area(holes[1])
    assert signed.sum() == pytest.approx(0.1**2 - hole_area, rel=1e-9)
    # every polygon edge is an edge of the triangulation
    edges = {frozenset(e) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    start = 0
    for poly in [outline, *holes]:
        ring = np.arange(start, start + len(poly))
        assert all(frozenset((int(i), int(j))) in edges for i, j in zip(ring, np.roll(ring, -1)))
        start += len(poly)


def test_extruded_plate_is_closed_and_its_volume_is_by_hand():
    outline = densify(square(0, 0, 0.05), 0.01)
    hole = densify(square(0.01, 0.0, 0.01), 0.005)
    mesh = extrude(outline, 0.05, [(hole, 0.03)])
    assert edges_are_closed(mesh)
    volume, centroid = mesh.volume_and_centroid()
    assert volume == pytest.approx(0.1 * 0.1 * 0.05 - 0.02 * 0.02 * 0.03, rel=1e-9)
    # the hole removes material right of centre and near the face: the centre moves left and down
    assert centroid[0] < 0 and centroid[2] < -0.025


def test_bad_polygons_and_depths_are_refused():
    with pytest.raises(ValueError, match="counter-clockwise"):
        triangulate(square(0, 0, 1)[::-1])
    with pytest.raises(ValueError, match="spacing"):
        triangulate(square(0, 0, 1), spacing=0.1)
    with pytest.raises(ValueError, match="depth"):
        extrude(square(0, 0, 1), 0.1, [(square(0, 0, 0.1), 0.2)])


@pytest.mark.parametrize("name", sorted(CONNECTORS))
def test_connector_layout_is_a_valid_rigid_asymmetric_pattern(name):
    c = CONNECTORS[name]
    assert len(c.contacts) == {"type2": 7, "type1": 5}[name]
    assert polygon_area(c.outline) > 0
    centres = c.reference_points[:, :2]
    radii = np.array([c.hole_radius(k) for k in c.contacts])
    # every hole inside the outline with at least a millimetre of wall, no two holes touching
    for k, (p, r) in enumerate(zip(centres, radii)):
        ring = hole_polygon(*p, r)
        d = np.linalg.norm(c.outline[:, None] - ring[None], axis=2).min()
        assert d > 0.001, (c.contacts[k].name, d)
        others = np.delete(np.arange(len(centres)), k)
        gaps = np.linalg.norm(centres[others] - p, axis=1) - radii[others] - r
        assert gaps.min() > 0.001
    # no turn about the axis maps the pattern onto itself: the turn is observable from the pins
    for degrees in range(15, 346):
        a = np.radians(degrees)
        turned = centres @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).T
        nearest = np.linalg.norm(turned[:, None] - centres[None], axis=2).min(1)
        assert nearest.max() > 0.002, degrees


@pytest.mark.parametrize("name", sorted(CONNECTORS))
def test_port_and_plug_meshes(name):
    c = CONNECTORS[name]
    port = c.port_mesh(depth=0.035)
    assert edges_are_closed(port)
    holes = sum(polygon_area(hole_polygon(k.x, k.y, c.hole_radius(k))) for k in c.contacts)
    assert port.volume_and_centroid()[0] == pytest.approx(polygon_area(c.outline) * 0.035 - holes * c.hole_depth, rel=1e-9)
    body = c.plug_body_mesh(0.04)
    assert body.vertices[:, 2].min() == pytest.approx(0.0) and body.vertices[:, 2].max() == pytest.approx(0.04)
    for contact, pin in zip(c.contacts, c.pin_meshes()):
        assert edges_are_closed(pin)
        assert pin.vertices[:, 2].min() == pytest.approx(-c.pin_length)
        # the pin fits its hole with the stated clearance: its farthest point from the
        # axis is the clearance inside the hole polygon's flats
        radial = np.linalg.norm(pin.vertices[:, :2] - [contact.x, contact.y], axis=1).max()
        assert c.hole_radius(contact) - radial == pytest.approx(c.clearance, abs=1e-12)


def test_connector_names_and_settings_are_checked():
    assert connector("Type 2") is CONNECTORS["type2"] and connector("type_1") is CONNECTORS["type1"]
    with pytest.raises(ConfigError, match="unknown connector"):
        connector("chademo")
    from dataclasses import replace

    with pytest.raises(ConfigError, match="clearance"):
        replace(CONNECTORS["type2"], clearance=0.002)
    with pytest.raises(ConfigError, match="shorter"):
        replace(CONNECTORS["type2"], pin_length=0.03)


def test_through_holes_and_the_inside_test():
    plate = extrude(densify(square(0, 0, 0.05), 0.01), 0.02, [(densify(square(0.01, 0.0, 0.01), 0.005), 0.02), (square(-0.03, 0.03, 0.005), 0.01)])
    assert edges_are_closed(plate)
    assert plate.volume_and_centroid()[0] == pytest.approx(0.1 * 0.1 * 0.02 - 0.02 * 0.02 * 0.02 - 0.01 * 0.01 * 0.01, rel=1e-9)
    # an L-shaped (concave) polygon: points in its notch are outside
    ell = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    points = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5], [1.5, 1.5], [2.5, 0.5], [-0.1, 1.0]])
    assert inside_polygon(points, ell).tolist() == [True, True, True, False, False, False]


def test_offsets_and_concave_blind_holes():
    ell = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float) * 0.01
    inset = offset_polygon(ell, -0.001)
    # every edge moved inwards by exactly the distance (the lines, measured by hand)
    expected = np.array([[0.001, 0.001], [0.019, 0.001], [0.019, 0.009], [0.009, 0.009], [0.009, 0.019], [0.001, 0.019]])
    assert np.abs(inset - expected).max() < 1e-12
    # an L-shaped blind hole: its floor covers exactly its footprint
    plate = extrude(densify(square(0.01, 0.01, 0.02), 0.005), 0.01, [(densify(ell, 0.004), 0.004)])
    assert edges_are_closed(plate)
    assert plate.volume_and_centroid()[0] == pytest.approx(0.04 * 0.04 * 0.01 - 3e-4 * 0.004, rel=1e-9)


def test_bad_meshing_inputs_are_refused_not_left_open():
    outline = densify(square(0, 0, 0.5), 0.1)
    with pytest.raises(ValueError, match="repeats a vertex"):
        triangulate(np.concatenate([square(0, 0, 1), square(0, 0, 1)[:1]]))
    with pytest.raises(ValueError, match="non-finite"):
        triangulate(np.array([[0, 0], [1, 0], [np.nan, 1]]))
    with pytest.raises(ValueError, match="lost"):
        triangulate(outline, [densify(square(0.05, -0.39, 0.1), 0.1)])  # a hole nearer the outline than its edges allow
    with pytest.raises(ValueError, match="not inside"):
        extrude(square(0, 0, 0.05), 0.02, [(square(0.06, 0, 0.01), 0.01)])
    with pytest.raises(ValueError, match="overlap"):
        extrude(densify(square(0, 0, 0.05), 0.01), 0.02, [(square(0, 0, 0.01), 0.01), (square(0.005, 0, 0.01), 0.01)])
