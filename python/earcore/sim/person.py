"""A person's arm reaching into the cell: upper arm, forearm and hand as capsules,
moved kinematically along reaches with a minimum-jerk profile whose peak hand speed
stays within a limit (1.6 m/s by default, the human speed ISO/TS 15066 assumes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.transforms import turn_from_z

__all__ = ["ArmGeometry", "HumanArm", "Reach", "minimum_jerk", "reach_duration"]


@dataclass(frozen=True)
class ArmGeometry:
    upper_arm: float = 0.30
    forearm: float = 0.27
    hand: float = 0.15
    upper_arm_radius: float = 0.05
    forearm_radius: float = 0.04
    hand_radius: float = 0.035


@dataclass(frozen=True)
class Reach:
    """Move the hand from rest to `target` starting at `start` (s), hold for `hold`
    seconds, and return. Durations follow from the peak speed."""

    start: float
    target: tuple[float, float, float]
    hold: float = 1.0
    #: Peak hand speed of this reach (m/s); None = the arm's default.
    speed: float | None = None
    #: While held, the hand moves about the target by up to this much (m): a person
    #: holding something into the robot's path does not hold it still. 0 = still.
    wander: float = 0.0


def minimum_jerk(s: np.ndarray | float) -> np.ndarray | float:
    """Position fraction along a minimum-jerk move at time fraction s ∈ [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


#: Peak speed of a minimum-jerk move = 1.875 × distance / duration.
MINIMUM_JERK_PEAK = 1.875


def reach_duration(rest, target, peak_speed: float) -> float:
    """Seconds one way from `rest` to `target` by a minimum-jerk move peaking at
    `peak_speed` (m/s)."""
    return MINIMUM_JERK_PEAK * float(np.linalg.norm(np.asarray(target) - np.asarray(rest))) / peak_speed


class HumanArm:
    """The arm of a person standing at the cell with the shoulder at `shoulder`."""

    def __init__(
        self,
        client,
        shoulder,
        rest_hand,
        reaches: list[Reach],
        *,
        peak_speed: float = 1.6,
        geometry: ArmGeometry = ArmGeometry(),
        colour=(0.85, 0.6, 0.45, 1.0),
        arrive: float = 0.0,
    ) -> None:
        if not 0 < peak_speed <= 3.0:
            raise ValueError(f"peak_speed must be in (0, 3] m/s, got {peak_speed}")
        if not (np.isfinite(arrive) and arrive >= 0):
            raise ValueError(f"arrive must be a time >= 0 s, got {arrive}")
        early = [r.start for r in reaches if r.start < arrive]
        if early:
            raise ValueError(f"a reach starts at {early[0]} s, before the person arrives at {arrive} s")
        #: Until then (s) the arm is out of the scene (below the floor).
        self.arrive = float(arrive)
        self.client = client
        self.shoulder = np.asarray(shoulder, dtype=np.float64)
        self.rest = np.asarray(rest_hand, dtype=np.float64)
        self.reaches = sorted(reaches, key=lambda r: r.start)
        # The held hand's motion per reach: three sinusoids, periods and phases fixed
        # by the reach's start time (so a run repeats).
        self._wander_terms = []
        for reach in self.reaches:
            rng = np.random.default_rng(int(round(reach.start * 1000)))
            self._wander_terms.append((rng.uniform(1.3, 2.6, 3), rng.uniform(0, 2 * np.pi, 3)))
        self.peak_speed = peak_speed
        self.geometry = geometry
        g = geometry
        p = client
        self.bodies = []
        for length, radius in ((g.upper_arm, g.upper_arm_radius), (g.forearm, g.forearm_radius), (g.hand, g.hand_radius)):
            shape = p.createCollisionShape(p.GEOM_CAPSULE, radius=radius, height=length)
            visual = p.createVisualShape(p.GEOM_CAPSULE, radius=radius, length=length, rgbaColor=colour)
            self.bodies.append(p.createMultiBody(0, shape, visual, [0, 0, -10]))
        self.set_time(0.0)

    def duration(self, target, speed: float | None = None) -> float:
        """Seconds one way from rest to `target` at the peak speed (the arm's own, or
        `speed`)."""
        return reach_duration(self.rest, target, speed or self.peak_speed)

    def _stage(self, t: float):
        """The reach under way at time t: (reach, its wander terms, its target, stage,
        how far into the stage) with stage "in" (the fraction of the way there), "held"
        (seconds into the hold) or "back" (the fraction of the way back); None at rest."""
        for reach, terms in zip(self.reaches, self._wander_terms):
            target = np.asarray(reach.target, dtype=np.float64)
            go = self.duration(target, reach.speed)
            end = reach.start + 2 * go + reach.hold
            if reach.start <= t < end:
                if t < reach.start + go:
                    return reach, terms, target, "in", (t - reach.start) / go
                if t < reach.start + go + reach.hold:
                    return reach, terms, target, "held", t - reach.start - go
                return reach, terms, target, "back", (t - reach.start - go - reach.hold) / go
        return None

    def hand_position(self, t: float) -> np.ndarray:
        stage = self._stage(t)
        if stage is None:
            return self.rest.copy()
        reach, terms, target, name, into = stage
        offset: float | np.ndarray = 0.0
        if name == "in":
            f = minimum_jerk(into)
        elif name == "held":
            f, offset = 1.0, self._wander(reach, terms, into)
        else:
            f = 1.0 - minimum_jerk(into)
        return self.rest + f * (target - self.rest) + offset

    def phase(self, t: float) -> str:
        """What the arm does at time t: "in" (on its way to a reach's target), "held",
        "back" (on its way back to rest) or "rest"."""
        stage = self._stage(t)
        return "rest" if stage is None else stage[3]

    @staticmethod
    def _wander(reach: Reach, terms: tuple[np.ndarray, np.ndarray], tau: float) -> np.ndarray:
        """The held hand's offset from its target `tau` seconds into the hold: the
        reach's sinusoids (periods 1.3-2.6 s) under a sin² envelope, so the hand leaves
        and returns to the target with zero speed."""
        if reach.wander <= 0.0 or reach.hold <= 0.0:
            return np.zeros(3)
        periods, phases = terms
        envelope = np.sin(np.pi * tau / reach.hold) ** 2
        return reach.wander * envelope * np.array([1.0, 1.0, 0.5]) * np.sin(2 * np.pi * tau / periods + phases)

    def joints(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Shoulder, elbow, wrist and fingertip positions at time t (elbow pointing down)."""
        g = self.geometry
        hand_tip = self.hand_position(t)
        to_hand = hand_tip - self.shoulder
        dist = np.linalg.norm(to_hand)
        direction = to_hand / dist
        # The wrist sits `hand` back from the fingertip along the reach direction.
        wrist = hand_tip - direction * g.hand
        to_wrist = wrist - self.shoulder
        d = min(float(np.linalg.norm(to_wrist)), g.upper_arm + g.forearm - 1e-6)
        u = to_wrist / np.linalg.norm(to_wrist)
        # Two-link IK in the vertical plane through the reach: elbow below the line.
        a = (g.upper_arm**2 - g.forearm**2 + d**2) / (2 * d)
        h = np.sqrt(max(g.upper_arm**2 - a**2, 0.0))
        down = np.array([0.0, 0.0, -1.0])
        perp = down - u * (down @ u)
        perp = perp / np.linalg.norm(perp) if np.linalg.norm(perp) > 1e-9 else np.array([1.0, 0, 0])
        elbow = self.shoulder + u * a + perp * h
        wrist = self.shoulder + u * d
        return self.shoulder.copy(), elbow, wrist, wrist + direction * g.hand

    def segments(self, t: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """(start, end, radius) of the three capsules at time t (ground truth)."""
        s, e, w, f = self.joints(t)
        g = self.geometry
        return [(s, e, g.upper_arm_radius), (e, w, g.forearm_radius), (w, f, g.hand_radius)]

    def present(self, t: float) -> bool:
        return t >= self.arrive

    def set_time(self, t: float) -> None:
        p = self.client
        if not self.present(t):
            for body in self.bodies:
                p.resetBasePositionAndOrientation(body, [0, 0, -10], [0, 0, 0, 1])
            return
        for body, (a, b, _) in zip(self.bodies, self.segments(t)):
            quat = p.getQuaternionFromAxisAngle(*turn_from_z(b - a))
            p.resetBasePositionAndOrientation(body, ((a + b) / 2).tolist(), quat)

    def speed(self, t: float, dt: float = 1e-3) -> float:
        """Hand speed (m/s) at time t."""
        return float(np.linalg.norm(self.hand_position(t + dt) - self.hand_position(t - dt)) / (2 * dt))
