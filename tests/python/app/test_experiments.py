"""The executive in the cell and Paper II's Fig. 7 experiment."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("ompl")



@pytest.mark.slow
def test_executive_shuttles_in_the_cell(tmp_path):
    pytest.importorskip("pybullet")
    from earcore.app.config import RunConfig
    from earcore.app.run import run

    config = RunConfig(duration=14.0, snapshots=[])
    config.cell.camera_scale = 0.25
    config.cell.person.enabled = False
    record = importlib.util.find_spec("rerun") is not None
    summary = run(config, tmp_path, progress=False, record=record, trips=2)
    trips = summary["trips"]
    assert len(trips) == 2 and all(t["completed"] for t in trips)
    assert summary["planning"]["collisions"] == 0
    # Without obstacles each trip is the direct motion at the limits: A to B and back
    # (the UR5's default waypoints, written out here).
    a, b = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0]), np.array([1.3, -1.3, 1.2, -1.5, -1.57, 0.0])
    assert trips[0]["path_length"] == pytest.approx(np.linalg.norm(b - a), rel=0.02)
    if record:  # the recording shows the planned paths
        out = subprocess.run(
            [sys.executable, "-m", "rerun", "rrd", "print", "-v", str(tmp_path / "cell.rrd")],
            capture_output=True, text=True, timeout=120,
        ).stdout
        assert "world/plan/tool_path" in out


def test_fig7_circles_put_the_tool_on_its_circles():
    """The Fig. 7 driver's reference: during each circle the tool stays at the circle's
    radius and height while the pan joint turns once."""
    pytest.importorskip("pybullet")
    from earcore.app.config import RunConfig
    from earcore.app.experiments.planning import CirclesDriver
    from earcore.perception import PerceptionPipeline
    from earcore.sim.cell import SimulatedCell

    config = RunConfig()
    config.cell.person.enabled = False
    config.cell.camera_scale = 0.1
    cell = SimulatedCell(config.cell)
    pipeline = PerceptionPipeline(config.perception, cell.model)
    driver = CirclesDriver(cell, pipeline, repetitions=1)
    circles = [(start, data) for start, kind, data in driver.segments if kind == "circle"]
    assert len(circles) == 3
    for (start, (_, _, duration)), radius in zip(circles, driver.radii):
        qs = np.array([driver.reference(start + f * duration) for f in np.linspace(0, 1, 9)])
        tool = cell.model.fk(qs)[:, -1, :3, 3]
        assert np.allclose(np.linalg.norm(tool[:, :2], axis=1), radius, atol=0.006)
        assert np.allclose(tool[:, 2], driver.height + 0.1, atol=0.006)
        assert abs(qs[-1, 0] - qs[0, 0]) == pytest.approx(2 * np.pi)
    cell.close()


def test_fig7_measures_how_often_fading_voxels_are_seen_free():
    """The occlusion figure of Fig. 7's bands: of the frames in which a voxel was fading
    (hit before, not hit now), the share in which its danger went down (a ray saw it
    free). Fed a scripted danger map: an inner voxel that decays every other frame, an
    outer one that decays every frame, a voxel hit again (not fading) in between."""
    pytest.importorskip("pybullet")
    from types import SimpleNamespace

    from earcore.app.config import RunConfig
    from earcore.app.experiments.planning import HIT_DANGER, CirclesDriver
    from earcore.perception import PerceptionPipeline
    from earcore.sim.cell import SimulatedCell

    config = RunConfig()
    config.cell.person.enabled = False
    config.cell.camera_scale = 0.1
    cell = SimulatedCell(config.cell)
    driver = CirclesDriver(cell, PerceptionPipeline(config.perception, cell.model), repetitions=1)
    cell.close()
    inner = np.array([0.2 + 0.025, 0.025, driver.height + 0.025])
    outer = np.array([0.46 + 0.025, 0.025, driver.height + 0.025])
    middle = np.array([0.32 + 0.025, 0.025, driver.height + 0.025])
    c_inner = [HIT_DANGER, 0.9, 0.9, 0.8, 0.8, 0.7, HIT_DANGER, 0.95]
    c_outer = [HIT_DANGER, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3]
    c_middle = [0.5, 0.4, 0.3, 0.2, 0.1, 0.0, 0.0, 0.0]  # danger, but never hit: not the sweep
    for a, b, m in zip(c_inner, c_outer, c_middle):
        tree = SimpleNamespace(
            danger_voxels=lambda a=a, b=b, m=m: (np.array([inner, outer, middle]), None, np.array([a, b, m], np.float32))
        )
        driver.pipeline = SimpleNamespace(tree=tree)
        driver.on_frame()
    bands = {b["radius_m"]: b for b in driver.bands()}
    # Inner: fading in frames 1-5 and 7 (frame 6 is a hit), decayed in 1, 3, 5, 7.
    assert bands[0.2]["seen_free_while_fading"] == pytest.approx(4 / 6)
    assert bands[0.46]["seen_free_while_fading"] == pytest.approx(1.0)
    assert bands[0.2]["mean_danger"] == pytest.approx(np.mean(np.float32(c_inner)), rel=1e-6)
    # The sweep (hit in at least half of the one repetition): inner and outer, not middle.
    assert bands[0.2]["swept_voxels"] == 1 and bands[0.2]["mean_danger_swept"] == bands[0.2]["mean_danger"]
    assert bands[0.32]["voxels"] == 1 and bands[0.32]["swept_voxels"] == 0 and bands[0.32]["mean_danger_swept"] == 0.0
    assert bands[0.32]["mean_danger"] == pytest.approx(np.mean(np.float32(c_middle)), rel=1e-6)

@pytest.mark.parametrize("scenario", ["stress", "paper"])
def test_table2_scenarios_reach_into_the_direct_path_at_their_pace(scenario):
    pytest.importorskip("pybullet")
    from earcore.app.experiments.planning import SCENARIOS, experiment_configs
    from earcore.sim.person import reach_duration

    configs = experiment_configs(seed=3, scenario=scenario, duration=300.0)
    person = configs["Exp. 3"].cell.person
    assert configs["Exp. 2"].cell.person.reach_starts == person.reach_starts  # the same reaches for both planners
    ranges = SCENARIOS[scenario]
    assert len(person.reach_starts) >= 10
    for name, values in (("speeds", person.reach_speeds), ("holds", person.reach_holds)):
        lo, hi = ranges[name]
        assert all(lo <= v <= hi for v in values)
    # one reach after another, the pause between them in the scenario's range
    for k in range(len(person.reach_starts) - 1):
        go = reach_duration(person.rest_hand, person.reach_targets[k], person.reach_speeds[k])
        pause = person.reach_starts[k + 1] - person.reach_starts[k] - 2 * go - person.reach_holds[k]
        assert ranges["gaps"][0] - 1e-9 <= pause <= ranges["gaps"][1] + 1e-9
    # the hand is held in the tool's A-B sweep (the UR5's A and B: the tool at x 0.2-0.45 m, y 0-0.5 m)
    targets = np.array(person.reach_targets)
    assert np.all((targets[:, 0] > 0.2) & (targets[:, 0] < 0.4) & (targets[:, 1] > 0.2) & (targets[:, 1] < 0.5))
    with pytest.raises(ValueError, match="scenario"):
        experiment_configs(scenario="calm")


def test_reflex_truth_records_the_reflex_layers_reflexes_with_the_persons_phase():
    """Of a frame's new log entries only the reflex layer's (with a rule) are recorded, with
    the arm's phase, hand speed and distance at that time; recoveries and frames without a
    person record nothing."""
    pytest.importorskip("pybullet")
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

    from earcore.app.experiments.planning import reflex_truth
    from earcore.sim.person import HumanArm, Reach

    client = BulletClient(pybullet.DIRECT)
    try:
        arm = HumanArm(client, (0.9, 0.4, 0.45), (0.8, 0.5, 0.05), [Reach(1.0, (0.8, 0.0, 0.05), 1.0, speed=1.0)])
        go = 1.875 * 0.5
        entries = [{"time": 1.0 + go / 2, "kind": "move_away", "rule": "predicted"}, {"time": 1.0 + go / 2, "kind": "recover_move_away"}]
        (truth,) = reflex_truth(entries, arm, 1.0 + go / 2, 0.3)
        assert truth["phase"] == "in" and truth["distance"] == 0.3
        assert truth["hand_speed"] == pytest.approx(1.0, rel=1e-3)  # the reach's peak, half-way in
        held = reflex_truth([{"rule": "close"}], arm, 1.0 + go + 0.5, 0.01)
        assert [r["phase"] for r in held] == ["held"] and held[0]["hand_speed"] == pytest.approx(0.0, abs=1e-9)
        assert reflex_truth([{"kind": "recover_backtrack"}], arm, 1.2, 0.3) == []
        assert reflex_truth(entries, None, 1.2, float("inf")) == []
    finally:
        client.disconnect()


def test_reflexes_by_phase_counts_the_completed_moves_reflexes():
    """Reflexes up to the end of the last completed move (its start plus its execution
    time) count by the arm's phase; one after it (in a move that never finished) does not."""
    from earcore.app.experiments.planning import reflexes_by_phase

    moves = [{"start_time": 0.5, "execution_time": 3.0}, {"start_time": 3.5, "execution_time": 4.0}]
    truth = [{"time": t, "phase": p} for t, p in ((1.0, "in"), (2.0, "in"), (4.0, "held"), (7.5, "back"), (7.6, "in"))]
    assert reflexes_by_phase(truth, moves) == {"in": 2, "held": 1, "back": 1}
    assert reflexes_by_phase(truth, []) == {}


def test_limit_analysis_counts_reaches_started_too_close_and_their_contacts():
    """Two reaches at 1.6 m/s: one starting 5 mm from the robot (inside any limit), one
    5 m away (outside). A contact while the first is on its way (0.88 s from its start)
    belongs to it; one while its hand is held is no reach's."""
    from types import SimpleNamespace

    import earcore
    from earcore.app.experiments.planning import limit_analysis

    ur5 = earcore.robots.load("ur5")
    q = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0])
    frames = [(1.0, q, np.zeros(6), 0.005), (2.0, q, np.zeros(6), 0.3), (5.0, q, np.zeros(6), 5.0), (6.0, q, np.zeros(6), 5.0)]
    executive = SimpleNamespace(
        frames=frames, robot=ur5, v_max=np.full(6, 1.57), a_max=np.full(6, 1.8), contact_times=[1.5, 2.5],
    )
    person = SimpleNamespace(
        rest_hand=(0.85, 0.5, 0.05), reach_starts=[1.0, 5.0, 100.0], reach_targets=[(0.3, 0.3, 0.5)] * 3,
        reach_speeds=[1.6, 1.6, 1.6],
    )
    result = limit_analysis(executive, person)
    assert result["reaches"] == 2  # the third starts after the last frame
    assert result["inside_limit"] == 1 and result["contacts"] == 2 and result["contacts_inside_limit"] == 1
    assert 0.005 < result["limits_m"][0] < 5.0
