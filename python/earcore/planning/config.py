"""The planning layers' settings (Paper II, Table I); field names are the TOML keys of
`[planning]` in `earcore run`'s configuration and the keyword arguments they feed
(`resolution` of the motion checks, the risk's `beta` and `threshold`, `straight_share`
of `time_parameterize`)."""

from __future__ import annotations

from dataclasses import dataclass

from earcore.validate import ConfigError, count, finite, fraction, non_negative, one_of, positive

__all__ = ["PlanningConfig"]


@dataclass
class PlanningConfig:
    """Paper II's planning layers (Table I)."""

    #: "predictive" (danger-costed choice + reflexes, Paper II), "reactive" (the
    #: paper's baseline: shortest path, stop and re-plan when blocked) or "none" (the
    #: robot shuttles along the straight joint-space path, no planning).
    mode: str = "predictive"
    #: RRT-Connect: time limit per attempt (s) and attempts (solutions to choose from).
    time_limit: float = 1.0
    attempts: int = 3
    #: Largest joint step (rad) between checked configurations along a motion.
    resolution: float = 0.02
    #: Re-plan the rest of the path every this many seconds when the danger map offers
    #: a path cheaper by `replan_gain` (0 = only when the path is blocked).
    replan_period: float = 1.0
    replan_gain: float = 0.15
    #: Reflexes (Eqs. 2-3): risk D = |v|² / (β d) against the threshold T.
    reflexes: bool = True
    beta: float = 1.5
    threshold: float = 1.0
    #: When a reflex fires: "prediction": a moving obstacle's course over the reaction
    #: and stopping time meets the robot's committed motion (`reflex.predicted_contact`,
    #: the obstacle grown by `prediction_margin`, m; `Executive._fires`), or "eq2", the
    #: paper's rule (risk D ≥ T). `min_separation` fires under either.
    reflex_rule: str = "prediction"
    prediction_margin: float = 0.05
    #: The prediction rule looks at least this far ahead (s) beyond the reaction time:
    #: what a reflex needs to get clear when the robot stands or moves slowly.
    escape_time: float = 0.3
    #: Speed and separation monitoring (ISO/TS 15066) beside the reflexes: a plan's path
    #: speed is scaled down so that every tracked obstacle stays at least its protective
    #: separation from the robot, and back up as it leaves (`Executive.ssm_scale`).
    #: The obstacle's speed towards the robot is the tracked one, at least
    #: `ssm_human_speed` (m/s; the standard's 1.6 for people nobody tracks makes the arm
    #: stand still within ~0.2 m of a hand); `ssm_uncertainty` (m) is added to the
    #: separation for what the map misses (C + Z_d + Z_r of the standard). It runs in the
    #: reflex layer: with the predictive planner and `reflexes` on.
    ssm: bool = True
    #: With `ssm` and the prediction rule, a plan brakes to a protective stop on its path
    #: when its motion would meet a predicted course if it reacted this much (s) after
    #: the next frame, but not if it braked now (cheaper than the reflex it forestalls).
    stop_lookahead: float = 0.2
    ssm_human_speed: float = 0.0
    ssm_uncertainty: float = 0.02
    #: v in Eq. 2: the obstacle's velocity relative to the robot's closest point (true),
    #: or the obstacle's own velocity as in the paper (false).
    relative_velocity: bool = True
    #: Backtracking: this fraction of the executed path; else move the end-effector
    #: this far away from the closest obstacle point (m).
    backtrack_fraction: float = 0.1
    move_away_distance: float = 0.15
    #: Beyond the paper: an approaching obstacle closer than this (m) also fires the
    #: reflex, as a move away (a slow hand's risk D stays below T until it touches).
    min_separation: float = 0.06
    #: Beyond the paper: paths keep this much clearance (m) from the tracked moving
    #: obstacles (people) on top of not touching what the map holds of them: the cameras
    #: see one side of a hand, and a tight path brushed its other side. 0 = off.
    person_margin: float = 0.04
    #: Round planned paths' corners by arcs at most this far (rad) from each corner
    #: before they run, where the rounded path is still valid (else a quarter of it,
    #: else none); corners are otherwise taken at a crawl. 0 = off, the default: with
    #: 0.1 rad every experiment ran 25-35 % faster, Exp. 1 most (10.7 -> 7.0 s per
    #: return trip, Exp. 3 11.1 -> 7.9 s), and Exp. 3 touched the person once in five
    #: seeds (a faster robot meets more fast reaches while moving).
    blend_deviation: float = 0.0
    #: The share of each joint's acceleration limit that planned paths and backtracks
    #: use along straight stretches away from corners (`time_parameterize`'s
    #: `straight_share`): 0.5, the default, splits it with the curvature everywhere; 1.0
    #: uses it all where no curvature competes, so straight moves run ~30 % faster (A to
    #: B: 2.63 -> 1.86 s); the experiments with people reaching in are measured at 0.5.
    #: Reflexes' moves away are per-joint transfers either way.
    straight_share: float = 0.5
    #: Goal tolerances for end-effector pose goals (m, rad).
    position_tolerance: float = 0.01
    orientation_tolerance: float = 0.1
    #: Seconds of the run before planning starts, used to learn the static scene (the
    #: reflex layer tracks what is not part of it).
    warmup: float = 0.5

    def validate(self, where: str = "planning") -> PlanningConfig:
        """Raise `ConfigError` naming the first setting out of its range; returns self."""
        one_of(self.mode, ("predictive", "reactive", "none"), f"{where}.mode")
        positive(self.time_limit, f"{where}.time_limit")
        count(self.attempts, f"{where}.attempts")
        positive(self.resolution, f"{where}.resolution", at_most=3.15)
        if self.resolution < 1e-4:
            raise ConfigError(f"{where}.resolution must be at least 0.0001 rad, got {self.resolution!r}")
        non_negative(self.replan_period, f"{where}.replan_period")
        v = finite(self.replan_gain, f"{where}.replan_gain")
        if not 0 <= v < 1:
            raise ConfigError(f"{where}.replan_gain must be in [0, 1), got {self.replan_gain!r}")
        positive(self.beta, f"{where}.beta")
        positive(self.threshold, f"{where}.threshold")
        one_of(self.reflex_rule, ("eq2", "prediction"), f"{where}.reflex_rule")
        non_negative(self.prediction_margin, f"{where}.prediction_margin")
        non_negative(self.escape_time, f"{where}.escape_time")
        non_negative(self.ssm_human_speed, f"{where}.ssm_human_speed")
        non_negative(self.ssm_uncertainty, f"{where}.ssm_uncertainty")
        non_negative(self.stop_lookahead, f"{where}.stop_lookahead")
        fraction(self.backtrack_fraction, f"{where}.backtrack_fraction")
        positive(self.move_away_distance, f"{where}.move_away_distance")
        non_negative(self.min_separation, f"{where}.min_separation")
        non_negative(self.person_margin, f"{where}.person_margin")
        non_negative(self.blend_deviation, f"{where}.blend_deviation")
        fraction(self.straight_share, f"{where}.straight_share", zero=False)
        positive(self.position_tolerance, f"{where}.position_tolerance")
        positive(self.orientation_tolerance, f"{where}.orientation_tolerance")
        non_negative(self.warmup, f"{where}.warmup")
        return self
