"""One charging session at the station: look, decide, plug in, unplug.

    outcome = charge(station, robot, flange_link, base_from_camera, plug="type2", standby=q)
    outcome.status        # "plugged", "blocked" (stopped by the force), "refused" (before
                          # moving), "not reached" (no contact: the port deeper than
                          # estimated) or "stuck" (unplugging stopped by the force)
    outcome.reason        # why it was refused or blocked

The stereo pair's images are searched for each known port type; the best match's type
must be the plug's. The port's pose must be found in both images and not flagged, and
the robot must reach it along the three steps (`plug_in.plan_plug_in`). Anything else
is a refusal, before the robot moves toward the car. The station is what `plug_in`
needs plus `capture() -> (left, right)` and `rig` (the calibrated stereo pair).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from earcore.charging.connectors import CONNECTORS, connector
from earcore.charging.locate import PortEstimate, locate
from earcore.charging.matching import ShapeModel, find
from earcore.charging.plug_in import PlugInConfig, PlugInResult, PlugStuck, PortOutOfReach, plan_plug_in, plug_in, unplug

__all__ = ["ChargeOutcome", "charge", "identify_port"]


@dataclass
class ChargeOutcome:
    status: str
    reason: str
    port_type: str | None
    estimate: PortEstimate | None
    #: The port's estimated pose in the robot's base frame.
    base_from_port: np.ndarray | None
    result: PlugInResult | None
    unplug_trace: np.ndarray | None
    images: tuple[np.ndarray, np.ndarray]
    #: What `judge` said with the plug at its deepest (e.g. the simulation's truth).
    judged: bool | None = None


def identify_port(image: np.ndarray, K: np.ndarray, distortion) -> tuple[str | None, dict[str, float]]:
    """The known port type that best explains `image` (highest score on the contacts'
    edges), or None when no type is found; with every type's score."""
    scores = {}
    for name, k in CONNECTORS.items():
        match = find(image, ShapeModel.port(k), K, distortion)
        if match is not None and not match.flagged:
            scores[name] = float(match.inner_score)
    if not scores:
        return None, scores
    return max(scores, key=lambda n: scores[n]), scores


def charge(
    station,
    robot,
    flange_link: int,
    base_from_camera: np.ndarray,
    *,
    plug: str,
    standby: np.ndarray,
    config: PlugInConfig | None = None,
    flange_from_tip: np.ndarray,
    judge: Callable[[], bool] | None = None,
) -> ChargeOutcome:
    """Run one session with the robot at stand-by (`base_from_camera`: the left camera's
    pose in the base frame, from calibration). `judge` is called with the plug at its
    deepest, before unplugging (an independent check of the insertion). Unplugs after a full insertion and backs
    out after a blocked one, ending at stand-by either way."""
    c = config or PlugInConfig()
    k = connector(plug)
    left, right = station.capture()
    rig = station.rig
    port_type, scores = identify_port(left, rig.K_left, rig.dist_left)

    def refused(reason: str, estimate: PortEstimate | None = None, base_from_port: np.ndarray | None = None) -> ChargeOutcome:
        return ChargeOutcome("refused", reason, port_type, estimate, base_from_port, None, None, (left, right))

    if port_type is None:
        return refused("no charging port in view")
    if port_type != k.name:
        return refused(f"the plug ({k.name}) does not fit the car's port ({port_type}; scores {', '.join(f'{n} {s:.2f}' for n, s in scores.items())})")
    estimate = locate(left, right, ShapeModel.port(k), rig)
    if estimate is None:
        return refused("the port is not in both cameras' view")
    if estimate.flagged:
        return refused("the port's pose is uncertain: " + "; ".join(estimate.reasons), estimate)
    base_from_port = base_from_camera @ estimate.camera_from_port
    try:
        plan = plan_plug_in(robot, flange_link, flange_from_tip, base_from_port, station.joints, k.insertion_depth, c)
    except PortOutOfReach as exc:
        return refused(str(exc), estimate, base_from_port)
    result = plug_in(station, plan)
    judged = judge() if judge is not None else None
    try:
        # no pause against a blocked pin: straight back out
        trace = unplug(station, result, standby, c if result.inserted else replace(c, pause=0.0))
    except PlugStuck as exc:
        return ChargeOutcome("stuck", str(exc), port_type, estimate, base_from_port, result, None, (left, right), judged)
    if result.inserted:
        return ChargeOutcome("plugged", "", port_type, estimate, base_from_port, result, trace, (left, right), judged)
    if not result.stopped_by_force:
        reason = f"the plug went {result.depth * 1000:.1f} mm past the pins' contact without meeting the port: it lies deeper than estimated"
        return ChargeOutcome("not reached", reason, port_type, estimate, base_from_port, result, trace, (left, right), judged)
    reason = f"insertion blocked {result.depth * 1000:.1f} mm in (force {result.peak_force:.0f} N)"
    return ChargeOutcome("blocked", reason, port_type, estimate, base_from_port, result, trace, (left, right), judged)
