"""The charging connectors: Type 2 (IEC 62196-2, "Mennekes") and Type 1 (SAE J1772)
faces as geometry: the housing's outline, the contacts (position, pin radius), the
reference points the vision finds (the contacts' centres) and closed triangle meshes of
the car's port (a face plate with one hole per contact) and of the robot's plug (a
body with one pin per contact).

Frames. A port's frame has its origin at the centre of the face, z pointing out of the
car (towards the robot), x to the right and y up for an upright car. A plug's tip frame
has its origin at the centre of the plug's front face and the same axes as the port's
frame when the two are mated; the pins stand out of the front face along −z. Mated
(fully in), `port_from_tip` is the identity; the pins' tips first touch the face at
`port_from_tip = translation(0, 0, insertion_depth)`.

Gender follows the charging-station model of Paper III, not the cars: the port holds
holes and the plug carries the pins, so a pin that misses its hole lands on the face.

Dimensions: the layouts of the standards' drawings (seven contacts for Type 2: two small
signal contacts CP and PP in the top row under the flat edge, N, PE and L1 in the
middle, L2 and L3 below; five for Type 1: L1 and N above, PE below, CP and PP at the
sides), rounded to 0.5 mm. The standard sheets are not public, so positions are
approximate; what the system relies on is that the layout is rigid, known and not
symmetric under a turn about the axis (Type 2's flat edge and two small top contacts,
Type 1's latch notch and its single PE contact below).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from earcore.errors import ConfigError
from earcore.mesh import Mesh, circle, densify, extrude, frustum, offset_polygon

__all__ = ["COLLAR", "CONNECTORS", "GAP", "PLUG_CLEARANCE", "RECESS", "Connector", "Contact", "connector", "hole_polygon"]

#: Points around a contact's hole or pin (a polygon inscribed in its circle).
SEGMENTS = 32
#: How a port is installed in a car's side: a round collar COLLAR wider than the face,
#: the face RECESS deep inside it, and a dark gap GAP wide between the collar and the
#: car's body (m). The simulated cell builds it so and the matcher looks for its edges.
COLLAR = 0.010
RECESS = 0.006
GAP = 0.002
#: How much smaller than the port's face outline the plug's nose is (m).
PLUG_CLEARANCE = 0.0005
#: How far the plug's nose reaches into its shell (m), and how steeply the shell
#: narrows behind its front rim (degrees from the axis).
NOSE_OVERLAP = 0.001
PLUG_TAPER = 35.0


@dataclass(frozen=True)
class Contact:
    """One contact: its name, centre (x, y) in the face frame (m) and pin radius (m)."""

    name: str
    x: float
    y: float
    radius: float


@dataclass(frozen=True)
class Connector:
    """A connector face: `outline` (N, 2) the housing opening counter-clockwise (m),
    the contacts, the holes' depth, the pins' length and the radial clearance of a pin
    in its hole."""

    name: str
    outline: np.ndarray
    contacts: tuple[Contact, ...]
    hole_depth: float = 0.024
    pin_length: float = 0.020
    clearance: float = 0.0004

    def __post_init__(self) -> None:
        if not 0 < self.clearance < 0.001:
            raise ConfigError(f"{self.name}: the pins' clearance must be in (0, 1 mm), got {self.clearance * 1000:.2f} mm")
        if self.pin_length >= self.hole_depth:
            raise ConfigError(f"{self.name}: pins ({self.pin_length} m) must be shorter than their holes ({self.hole_depth} m)")

    @property
    def insertion_depth(self) -> float:
        """How far the plug travels from its pins touching the port's face to mated (m)."""
        return self.pin_length

    @cached_property
    def reference_points(self) -> np.ndarray:
        """(K, 3) the contacts' centres on the face (z = 0), in the port's frame."""
        return np.array([[c.x, c.y, 0.0] for c in self.contacts])

    @property
    def radius(self) -> float:
        """The face's outer radius (m)."""
        return float(np.linalg.norm(self.outline, axis=1).max())

    def hole_radius(self, contact: Contact) -> float:
        return contact.radius + self.clearance

    def port_mesh(self, depth: float = 0.035) -> Mesh:
        """The port as a solid in its frame: the face (z = 0) with one blind hole per
        contact, `depth` deep behind it."""
        holes = [(hole_polygon(c.x, c.y, self.hole_radius(c)), self.hole_depth) for c in self.contacts]
        return extrude(self.outline, depth, holes)

    def plug_body_mesh(self, length: float = 0.04) -> Mesh:
        """The plug's body in its tip frame: a nose of the face's outline (PLUG_CLEARANCE
        inside it) from the front face (z = 0) back to RECESS, the depth it enters an
        installed port's recess, then a shell as wide as the port's collar at its front,
        narrowing back to z = `length` at PLUG_TAPER (as a plug's housing narrows to its
        grip). Seen less than PLUG_TAPER off its axis, the shell's front rim is the plug's
        outline: its side hides behind it."""
        back = self.radius + COLLAR - (length - RECESS) * np.tan(np.radians(PLUG_TAPER))
        if back < 0.005:
            raise ConfigError(f"{self.name}: a plug {length * 1000:.0f} mm long narrows to {back * 1000:.1f} mm at its back (at least 5 mm)")
        shift = np.eye(4)
        shift[2, 3] = RECESS + NOSE_OVERLAP
        # (reaching NOSE_OVERLAP into the shell: no two faces share the plane z = RECESS)
        nose = extrude(offset_polygon(self.outline, -PLUG_CLEARANCE), RECESS + NOSE_OVERLAP).moved(shift)
        shell = frustum(back, self.radius + COLLAR, length - RECESS)
        shift[2, 3] = length
        return Mesh.union([nose, shell.moved(shift)])

    def pin_meshes(self) -> list[Mesh]:
        """One solid pin per contact in the tip frame, standing out of the front face
        to z = −pin_length (a polygon inside the pin's circle)."""
        pins = []
        for c in self.contacts:
            pins.append(extrude(circle(c.radius, SEGMENTS, (c.x, c.y)), self.pin_length))
        return pins


def hole_polygon(x: float, y: float, radius: float, segments: int = SEGMENTS) -> np.ndarray:
    """(segments, 2) a circle's inscribed polygon, counter-clockwise, scaled so that
    the polygon's inner radius (its flats) is `radius`: a pin of that radius fits."""
    angles = np.arange(segments) * 2 * np.pi / segments
    outer = radius / np.cos(np.pi / segments)
    return np.stack([x + outer * np.cos(angles), y + outer * np.sin(angles)], 1)


def _d_outline(radius: float, flat: float, segments: int = 96) -> np.ndarray:
    """A circle of `radius` cut by the line y = `flat` (Type 2's opening): the arc from
    the flat's left end down and round to its right end; the closing edge is the flat."""
    top = np.arcsin(flat / radius)
    arc = np.linspace(np.pi - top, 2 * np.pi + top, segments)
    return densify(np.stack([radius * np.cos(arc), radius * np.sin(arc)], 1), 0.0015)


def _notched_outline(radius: float, notch_half: float, notch_depth: float, segments: int = 96) -> np.ndarray:
    """A circle with a rectangular notch cut into its top (Type 1's latch): the arc from
    the notch's left edge round to its right edge, then the notch's floor."""
    start = np.arcsin(notch_half / radius)
    arc = np.linspace(np.pi / 2 + start, 2 * np.pi + np.pi / 2 - start, segments)
    floor = radius * np.cos(start) - notch_depth
    notch = np.array([[notch_half, floor], [-notch_half, floor]])
    return densify(np.concatenate([np.stack([radius * np.cos(arc), radius * np.sin(arc)], 1), notch]), 0.0015)


def _type2() -> Connector:
    big, small = 0.0030, 0.0015
    contacts = (
        Contact("PP", -0.0073, 0.0115, small),
        Contact("CP", 0.0073, 0.0115, small),
        Contact("N", -0.0155, 0.0, big),
        Contact("PE", 0.0, 0.0, big),
        Contact("L1", 0.0155, 0.0, big),
        Contact("L3", -0.0090, -0.0135, big),
        Contact("L2", 0.0090, -0.0135, big),
    )
    return Connector("type2", _d_outline(0.0245, 0.0175), contacts)


def _type1() -> Connector:
    big, small = 0.0028, 0.0015
    contacts = (
        Contact("L1", -0.0085, 0.0055, big),
        Contact("N", 0.0085, 0.0055, big),
        Contact("CP", -0.0100, -0.0065, small),
        Contact("PP", 0.0100, -0.0065, small),
        Contact("PE", 0.0, -0.0095, big),
    )
    return Connector("type1", _notched_outline(0.0215, 0.004, 0.004), contacts)


CONNECTORS = {"type2": _type2(), "type1": _type1()}


def connector(name: str) -> Connector:
    key = name.lower().replace(" ", "").replace("_", "")
    if key not in CONNECTORS:
        raise ConfigError(f"unknown connector {name!r}; known: {', '.join(CONNECTORS)}")
    return CONNECTORS[key]
