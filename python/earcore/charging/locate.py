"""The port's pose from a stereo pair: matched in each image, the pins triangulated, the
pose by Paper III's route (plane fit and the pins' layout), then the model fitted to
both images at once.

    estimate = locate(left, right, ShapeModel.port(connector("type2")), rig)
    estimate.camera_from_port        # in the left camera; estimate.paper: the paper's route
    estimate.flagged, estimate.reasons

One image leaves a planar pattern's tilt ambiguous in sign; each image's few best
hypotheses are paired and the pair whose triangulated pins fit the connector's layout
best wins. The estimate is flagged (and must not be acted on) when a match scores
under `min_score` or the pins do not fit their layout within `max_fit_mm`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from earcore.charging.matching import Match, ShapeModel, edge_field, find_all, refine_pose
from earcore.charging.port_pose import pose_from_points
from earcore.charging.stereo import StereoRig, triangulate

__all__ = ["PortEstimate", "locate"]


@dataclass(frozen=True)
class PortEstimate:
    """`camera_from_port` (left camera) fitted to both images; `paper` the pose by the
    paper's route; the two matches; the pins' fit to their layout (mm, RMS); whether it
    is `flagged` and why; the time taken."""

    camera_from_port: np.ndarray
    paper: np.ndarray
    matches: tuple[Match, Match]
    fit_mm: float
    flagged: bool
    reasons: tuple[str, ...]
    seconds: float


def _on_epipolar_lines(rig: StereoRig, centres_left: list[np.ndarray], near: float = 0.3, far: float = 6.0):
    """A test of a right-image ellipse (centre px, major semi-axis px): does its centre
    lie on the epipolar line of one of the left image's finds (their centres' rays from
    `near` to `far` m, projected), within 8 px and a quarter of its size?"""
    segments = []
    for centre in centres_left:
        ray = np.asarray(centre, dtype=np.float64) / np.linalg.norm(centre)
        _, ends = rig.project(np.stack([ray * near, ray * far]))
        segments.append(ends)

    def accept(centre_px: np.ndarray, major_px: float) -> bool:
        for a, b in segments:
            ab = b - a
            t = np.clip((centre_px - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0)
            if np.linalg.norm(centre_px - (a + t * ab)) <= 8.0 + 0.25 * major_px:
                return True
        return False

    return accept


def locate(
    left: np.ndarray, right: np.ndarray, model: ShapeModel, rig: StereoRig, *, min_score: float = 0.55, max_fit_mm: float = 2.0, pairs: int = 3, **options
) -> PortEstimate | None:
    """The object's pose from a stereo pair, or None when either image shows no
    candidate. `options` go to `matching.find_all`."""
    import cv2

    start = time.perf_counter()
    found_left = find_all(left, model, rig.K_left, rig.dist_left, min_score=min_score, **options)
    if not found_left:
        return None
    # the right image searched only along the left finds' epipolar lines
    on_lines = _on_epipolar_lines(rig, [m.camera_from_object[:3, 3] for m in found_left[:pairs]])
    found_right = find_all(right, model, rig.K_right, rig.dist_right, min_score=min_score, where=on_lines, **options)
    if not found_right:
        return None
    found = [found_left, found_right]
    # fitted in the model's frame, whose z faces the camera as the plane fit's normal does
    best = None
    for a in found[0][:pairs]:
        for b in found[1][:pairs]:
            fit = pose_from_points(model.reference, triangulate(rig, a.reference_pixels, b.reference_pixels))
            if best is None or fit.rms_m < best[0].rms_m:
                best = (fit, a, b)
    assert best is not None
    fit, a, b = best
    fields = []
    for image, match in ((left, a), (right, b)):
        x0, y0, x1, y1 = match.window
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        fields.append(edge_field(gray[y0:y1, x0:x1], offset=(x0, y0)))
    cameras = [(rig.K_left, rig.dist_left, np.eye(4)), (rig.K_right, rig.dist_right, rig.right_from_left)]
    model_from_object = np.linalg.inv(model.object_from_model)
    both = refine_pose(fields, model, fit.camera_from_port, cameras, sharp_only=False) @ model_from_object
    reasons = []
    for side, match in (("left", a), ("right", b)):
        if match.flagged:
            reasons.append(f"the {side} image's match scores {match.score:.2f} < {min_score}")
    if fit.rms_m * 1000 > max_fit_mm:
        reasons.append(f"the triangulated pins fit their layout to {fit.rms_m * 1000:.1f} mm > {max_fit_mm} mm")
    return PortEstimate(both, fit.camera_from_port @ model_from_object, (a, b), fit.rms_m * 1000, bool(reasons), tuple(reasons), time.perf_counter() - start)
