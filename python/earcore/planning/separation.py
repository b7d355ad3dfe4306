"""Speed and separation monitoring (ISO/TS 15066, 5.5.4) and the physical limit of
avoiding a reaching hand.

    protective_separation(1.6, 0.5, reaction_time=0.1, stopping_time=0.3)   # S_p (m)
    ssm_speed_limit(0.8, 1.6, reaction_time=0.1, deceleration=2.0)           # v_r allowed (m/s)
    shortest_avoidable_distance(1.6, reach=0.6, latency=0.1, max_speed=1.0, acceleration=2.0)

`protective_separation` is the standard's formula. `ssm_speed_limit` inverts it: the
fastest the robot may move at a given separation, its stopping time growing with its
speed at a constant deceleration. `shortest_avoidable_distance` is the limit the arm's
speed, acceleration and the loop's latency set: a hand reaching straight at the robot
from closer than that touches it whatever the robot does.
"""

from __future__ import annotations

import math

__all__ = ["protective_separation", "shortest_avoidable_distance", "ssm_speed_limit"]


def _non_negative(**values: float) -> None:
    """Speeds, times and distances: finite and >= 0, else a ValueError naming them."""
    bad = [f"{name}={value!r}" for name, value in values.items() if not (math.isfinite(value) and value >= 0)]
    if bad:
        raise ValueError(f"need finite values >= 0, got {', '.join(bad)}")


def protective_separation(
    human_speed: float,
    robot_speed: float,
    *,
    reaction_time: float,
    stopping_time: float,
    intrusion: float = 0.0,
    sensor_uncertainty: float = 0.05,
    robot_uncertainty: float = 0.005,
) -> float:
    """ISO/TS 15066 (5.5.4.2) S_p = v_h (T_r + T_s) + v_r T_r + S_s + C + Z_d + Z_r, with
    the robot's stopping distance S_s = v_r T_s / 2 (constant deceleration)."""
    _non_negative(human_speed=human_speed, robot_speed=robot_speed, reaction_time=reaction_time, stopping_time=stopping_time,
                  intrusion=intrusion, sensor_uncertainty=sensor_uncertainty, robot_uncertainty=robot_uncertainty)
    s_h = human_speed * (reaction_time + stopping_time)
    s_r = robot_speed * reaction_time
    s_s = 0.5 * robot_speed * stopping_time
    return s_h + s_r + s_s + intrusion + sensor_uncertainty + robot_uncertainty


def ssm_speed_limit(
    separation: float,
    human_speed: float,
    *,
    reaction_time: float,
    deceleration: float,
    intrusion: float = 0.0,
    sensor_uncertainty: float = 0.05,
    robot_uncertainty: float = 0.005,
) -> float:
    """The largest robot speed v_r (m/s) whose protective separation, with the stopping
    time v_r / `deceleration`, is at most `separation`; 0 when even a still robot is too
    close. The positive root of v²/(2a) + (T_r + v_h/a)·v + v_h·T_r + C + Z_d + Z_r − S = 0."""
    _non_negative(separation=separation, human_speed=human_speed, reaction_time=reaction_time, intrusion=intrusion,
                  sensor_uncertainty=sensor_uncertainty, robot_uncertainty=robot_uncertainty)
    if not deceleration > 0:  # (an infinite one stops at once)
        raise ValueError(f"need deceleration > 0, got {deceleration!r}")
    constant = human_speed * reaction_time + intrusion + sensor_uncertainty + robot_uncertainty - separation
    if constant >= 0:
        return 0.0
    a = 0.5 / deceleration
    b = reaction_time + human_speed / deceleration
    # The positive root in the form that keeps its digits when 4ac is small against b².
    denominator = b + math.sqrt(b * b - 4 * a * constant)
    return -2 * constant / denominator if denominator > 0 else math.inf


def shortest_avoidable_distance(hand_speed: float, *, reach: float, latency: float, max_speed: float, acceleration: float, robot_speed: float = 0.0) -> float:
    """The smallest initial gap (m) from which the robot avoids a hand coming straight at
    it at `hand_speed` over `reach` (m, then it stops). The robot notices after `latency`
    (s: sensing, the map frame, the command), meanwhile moving on towards the hand at
    `robot_speed`; then it accelerates away at `acceleration` up to `max_speed` (its
    point nearest the hand, m/s and m/s²). The gap closes by the largest value of
    ∫(v_hand + v_robot towards the hand) dt over the reach."""
    _non_negative(hand_speed=hand_speed, reach=reach, latency=latency, max_speed=max_speed, acceleration=acceleration,
                  robot_speed=robot_speed)
    if acceleration == 0 or max_speed == 0:
        raise ValueError("max_speed and acceleration must be > 0")
    if hand_speed == 0 or reach == 0:
        return 0.0
    end = reach / hand_speed  # when the hand stops

    def closed(t: float) -> float:
        """The gap closed by time t (hand moving)."""
        first = min(t, latency)
        closure = (hand_speed + robot_speed) * first
        if t <= latency:
            return closure
        # braking the approach, then speeding away, until moving away at max_speed
        turning = (robot_speed + max_speed) / acceleration
        second = min(t - latency, turning)
        closure += (hand_speed + robot_speed) * second - 0.5 * acceleration * second * second
        if t - latency > turning:
            closure += (hand_speed - max_speed) * (t - latency - turning)
        return closure

    # the closure grows while the robot moves away slower than the hand comes: its
    # largest value is at the end of the reach or where the two speeds match
    candidates = [end, min(end, latency)]
    matched = latency + (hand_speed + robot_speed) / acceleration
    if hand_speed < max_speed and matched < end:
        candidates.append(matched)
    return max(closed(t) for t in candidates)
