"""Speed and separation monitoring (ISO/TS 15066) and the physical limit of avoiding a
reaching hand, against the standard's formula, hand-computed cases and a brute-force
simulation of the gap."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.planning.separation import protective_separation, shortest_avoidable_distance, ssm_speed_limit


def test_protective_separation_formula():
    # ISO/TS 15066: v_h (T_r + T_s) + v_r T_r + v_r T_s / 2 + C + Z_d + Z_r.
    got = protective_separation(1.6, 0.5, reaction_time=0.1, stopping_time=0.3, intrusion=0.02, sensor_uncertainty=0.05, robot_uncertainty=0.01)
    assert got == pytest.approx(1.6 * 0.4 + 0.5 * 0.1 + 0.5 * 0.3 / 2 + 0.02 + 0.05 + 0.01)


@pytest.mark.parametrize("separation", [0.3, 0.6, 1.0, 2.5])
@pytest.mark.parametrize("human_speed", [0.0, 0.5, 1.6])
def test_the_speed_limit_keeps_exactly_the_protective_separation(separation, human_speed):
    """At the limit the standard's separation (stopping time v/a) equals the separation;
    any faster would need more."""
    a, tr = 2.5, 0.12
    v = ssm_speed_limit(separation, human_speed, reaction_time=tr, deceleration=a)
    needed = protective_separation(human_speed, v, reaction_time=tr, stopping_time=v / a)
    if v > 0:
        assert needed == pytest.approx(separation, rel=1e-9)
        faster = v * 1.01
        assert protective_separation(human_speed, faster, reaction_time=tr, stopping_time=faster / a) > separation
    else:
        # too close even standing still
        assert protective_separation(human_speed, 0.0, reaction_time=tr, stopping_time=0.0) >= separation


def test_the_speed_limit_by_hand():
    # v_h = 0, no margins: v²/(2a) + T_r v = S, a = 2, T_r = 0.5, S = 1: v² + 2v - 4 = 0, v = -1 + √5
    v = ssm_speed_limit(1.0, 0.0, reaction_time=0.5, deceleration=2.0, sensor_uncertainty=0.0, robot_uncertainty=0.0)
    assert v == pytest.approx(-1 + np.sqrt(5))
    assert ssm_speed_limit(0.04, 1.6, reaction_time=0.1, deceleration=2.0) == 0.0  # inside the margins
    with pytest.raises(ValueError):
        ssm_speed_limit(1.0, 1.6, reaction_time=0.1, deceleration=0.0)


def _brute_force_gap(hand_speed, reach, latency, max_speed, acceleration, robot_speed, dt=2e-6):
    """The largest gap closure by stepping time: the hand at constant speed until it has
    gone `reach`, the robot on towards it for `latency`, then accelerating away."""
    t, closed, worst, v_robot, hand_gone = 0.0, 0.0, 0.0, robot_speed, 0.0
    while hand_gone < reach:
        if t >= latency:
            v_robot = max(v_robot - acceleration * dt, -max_speed)
        step = min(hand_speed * dt, reach - hand_gone)
        hand_gone += step
        closed += step + v_robot * dt * (step / (hand_speed * dt))
        worst = max(worst, closed)
        t += dt
    return worst


@pytest.mark.parametrize(
    ("hand_speed", "reach", "latency", "max_speed", "acceleration", "robot_speed"),
    [
        (1.6, 0.6, 0.1, 1.0, 2.0, 0.0),  # the hand faster than the robot can leave: closes all the reach
        (1.0, 0.8, 0.08, 1.5, 3.0, 0.0),  # the robot outruns the hand: closes until the speeds match
        (1.6, 0.6, 0.1, 1.0, 2.0, 0.5),  # the robot was moving towards the hand
        (0.3, 0.5, 0.2, 1.0, 1.0, 0.2),  # an operator's pace
        (1.6, 0.1, 0.15, 1.0, 2.0, 0.3),  # the reach ends before the robot notices
    ],
)
def test_the_avoidable_distance_matches_a_stepped_simulation(hand_speed, reach, latency, max_speed, acceleration, robot_speed):
    got = shortest_avoidable_distance(hand_speed, reach=reach, latency=latency, max_speed=max_speed, acceleration=acceleration, robot_speed=robot_speed)
    assert got == pytest.approx(_brute_force_gap(hand_speed, reach, latency, max_speed, acceleration, robot_speed), abs=2e-5)


def test_the_avoidable_distance_by_hand():
    # a still robot that cannot move away (tiny speed): the whole reach closes
    assert shortest_avoidable_distance(1.6, reach=0.5, latency=0.1, max_speed=1e-9, acceleration=1.0) == pytest.approx(0.5, abs=1e-6)
    # robot faster than the hand, no latency: closes v_h²/(2a) until the speeds match
    assert shortest_avoidable_distance(1.0, reach=2.0, latency=0.0, max_speed=3.0, acceleration=2.0) == pytest.approx(0.25)
    assert shortest_avoidable_distance(0.0, reach=1.0, latency=0.1, max_speed=1.0, acceleration=1.0) == 0.0
    with pytest.raises(ValueError):
        shortest_avoidable_distance(1.0, reach=1.0, latency=0.1, max_speed=1.0, acceleration=0.0)


@pytest.mark.parametrize(
    "call",
    [
        lambda: protective_separation(-1.0, 0.5, reaction_time=0.1, stopping_time=0.3),
        lambda: protective_separation(1.6, float("nan"), reaction_time=0.1, stopping_time=0.3),
        lambda: ssm_speed_limit(float("nan"), 1.0, reaction_time=0.1, deceleration=2.0),
        lambda: ssm_speed_limit(0.8, 1.0, reaction_time=0.1, deceleration=float("nan")),
        lambda: shortest_avoidable_distance(0.5, reach=0.6, latency=0.1, max_speed=1.0, acceleration=2.0, robot_speed=-5.0),
        lambda: shortest_avoidable_distance(1.6, reach=0.6, latency=0.1, max_speed=1.0, acceleration=float("inf")),
        lambda: shortest_avoidable_distance(float("nan"), reach=0.6, latency=0.1, max_speed=1.0, acceleration=2.0),
    ],
)
def test_negative_or_non_finite_speeds_and_times_are_refused(call):
    """A negative speed (a robot moving away, which the formulas do not model) or a NaN
    gave a negative separation, a gap of 9.7 m for a 0.6 m reach, or NaN."""
    with pytest.raises(ValueError, match="need"):
        call()


def test_the_speed_limit_at_the_extremes_of_braking():
    """An instant stop leaves the reaction distance: v = (S − C − Z) / T_r, by hand; a
    robot that can hardly brake may hardly move (the root's unstable form gave inf)."""
    assert ssm_speed_limit(0.8, 0.0, reaction_time=0.1, deceleration=float("inf")) == pytest.approx((0.8 - 0.055) / 0.1)
    crawl = ssm_speed_limit(0.8, 1.0, reaction_time=0.1, deceleration=1e-12)
    assert 0.0 <= crawl < 1e-9
    # It still keeps the separation it was asked for.
    assert protective_separation(1.0, crawl, reaction_time=0.1, stopping_time=crawl / 1e-12) <= 0.8 + 1e-9
