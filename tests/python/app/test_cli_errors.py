"""Every command with nonsense: a one-line message on stderr naming the option (or the
configuration key), a non-zero exit, no traceback; `--debug` shows the traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest

from earcore.app.cli import main


def run_cli(capsys, argv: list[str]) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's exit
        code = exc.code if isinstance(exc.code, int) else 1
    err = capsys.readouterr().err
    return code, err


BAD_OPTIONS = [
    (["run", "--duration", "-1"], "--duration"),
    (["run", "--duration", "nan"], "--duration"),
    (["run", "--duration", "inf"], "--duration"),
    (["run", "--camera-scale", "-0.5"], "--camera-scale"),
    (["run", "--camera-scale", "0"], "--camera-scale"),
    (["run", "--seed", "-3"], "--seed"),
    (["run", "--seed", "x"], "--seed"),
    (["run", "--frobnicate"], "--frobnicate"),
    (["run", "--out", __file__], "--out"),
    (["experiment", "table2", "--trips", "-1"], "--trips"),
    (["experiment", "table2", "--trips", "0"], "--trips"),
    (["experiment", "table2", "--only", "Exp. 9"], "--only"),
    (["experiment", "table2", "--only"], "--only"),
    (["experiment", "table2", "--scenario", "calm"], "--scenario"),
    (["experiment", "fig7", "--repetitions", "0"], "--repetitions"),
    (["experiment", "table2", "--camera-scale", "-1"], "--camera-scale"),
    (["experiment", "nonsense"], "name"),
    (["experiment", "calibration", "--camera-scale", "0"], "--camera-scale"),
    (["calibrate", "--camera-scale", "0"], "--camera-scale"),
    (["calibrate", "--max-frames", "7"], "--max-frames"),
    (["calibrate", "--camera-scale", "0.01"], "--camera-scale"),
    (["calibrate", "--camera-scale", "1e9"], "--camera-scale"),
    (["calibrate", "--max-pose-sigma", "1", "x"], "--max-pose-sigma"),
    (["calibrate", "--max-pose-sigma", "-1", "0.2"], "--max-pose-sigma"),
    (["experiment", "calibration", "--camera-scale", "0.1"], "--camera-scale"),
    (["run", "--seed", "99999999999999999999999999"], "--seed"),
    (["demo", "--after", "1e300"], "--after"),
    (["demo", "--resolution", "-0.05"], "--resolution"),
    (["demo", "--after", "nan"], "--after"),
    (["config", "nonsense"], "config dump"),
    (["bogus"], "command"),
]


@pytest.mark.parametrize("argv,option", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_options_get_one_line_naming_the_option(capsys, argv, option):
    code, err = run_cli(capsys, argv)
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert option in lines[0] and "Traceback" not in err


BAD_CONFIGS = [
    ("cell = 3", "cell must be a table"),
    ("[cell]\ntime_step = 0", "cell.time_step"),
    ("[cell]\ntime_step = -0.01", "cell.time_step"),
    ("[cell]\ntime_step = 1e9", "cell.time_step"),
    ("[cell]\ncamera_scale = -1", "cell.camera_scale"),
    ("[cell]\nrobot = 'r2d2'", "cell.robot"),
    ("[cell]\nboxes = [[0, 0, 0, -1, 1, 1]]", "cell.boxes[0]"),
    ("[[cell.cameras]]\nname = 'a'\nsensor = 'kinect_v2'\nposition = [1.0, 0.0, 1.0]\nrate_hz = 0.0", "cell.cameras[0].rate_hz"),
    ("[[cell.cameras]]\nname = 'a'\nsensor = 'eyeball'", "cell.cameras[0].sensor"),
    ("[cell.person]\nreach_starts = [1.0, 2.0]", "cell.person.reach_targets"),
    ("waypoints = [[nan, 0, 0, 0, 0, 0]]", "waypoints[0][0]"),
    ("duration = -5", "duration"),
    ("duration = [1]", "duration"),
    ("snapshots = 3", "snapshots"),
    ("[planning]\nmode = 'fast'", "planning.mode"),
    ("[planning]\nresolution = 0", "planning.resolution"),
    ("[perception]\nresolution = 'big'", "perception.resolution"),
    ("[perception]\nrate_hz = 0", "perception.rate_hz"),
    ("[perception]\ndecay_mode = 'sometimes'", "perception.decay_mode"),
    ("[perception]\nunknown_key = 1", "unknown keys"),
    ("[cell\n", "not valid TOML"),
    ("duration = " + "9" * 400, "duration"),
    ("[cell]\nsupersample = 100000", "cell.supersample"),
    ("[cell]\ntime_step = 1e-300", "cell.time_step"),
    ("[cell]\nseed = 10000000000000000000000000000000000000000", "cell.seed"),
    ("[cell]\ntable_size = [1e30, 1e30]", "cell.table_size[0]"),
    ("[cell]\npadding = 1e30", "cell.padding"),
    ("[cell.person]\nenabled = 'false'", "cell.person.enabled"),
    ("[perception]\nrefine_poses = 'no'", "perception.refine_poses"),
    ("[perception]\ncalibration = 5", "perception.calibration"),
    ("[[cell.cameras]]\nname = 3\nsensor = 'kinect_v2'", "cell.cameras[0].name"),
    ("[[cell.cameras]]\nsensor = 'kinect_v2'", "missing name"),
    ("[planning]\nresolution = 1e-300", "planning.resolution"),
]


@pytest.mark.parametrize("text,key", BAD_CONFIGS, ids=[k for _, k in BAD_CONFIGS])
def test_bad_config_files_get_one_line_naming_the_key(capsys, tmp_path, text, key):
    path = tmp_path / "cell.toml"
    path.write_text(text + "\n")
    code, err = run_cli(capsys, ["run", "--config", str(path), "--out", str(tmp_path / "out"), "--quiet", "--no-recording"])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert key in lines[0] and str(path) in lines[0] and "Traceback" not in err
    assert not (tmp_path / "out").exists()  # nothing ran


def test_waypoints_outside_the_robots_limits_are_refused(capsys, tmp_path):
    pytest.importorskip("pybullet")
    path = tmp_path / "cell.toml"
    path.write_text("waypoints = [[9, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]\n")
    code, err = run_cli(capsys, ["run", "--config", str(path), "--out", str(tmp_path / "out"), "--quiet", "--no-recording"])
    assert code == 2 and "waypoints[0]" in err and "limits" in err and len(err.strip().splitlines()) == 1


def test_a_missing_config_file_is_one_line(capsys, tmp_path):
    code, err = run_cli(capsys, ["run", "--config", str(tmp_path / "nope.toml")])
    assert code == 2 and "nope.toml" in err and len(err.strip().splitlines()) == 1


def test_debug_shows_the_traceback_and_the_process_exits_non_zero(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text("[cell]\ntime_step = 0\n")
    plain = subprocess.run([sys.executable, "-m", "earcore", "run", "--config", str(path)], capture_output=True, text=True, timeout=120)
    assert plain.returncode == 2 and "Traceback" not in plain.stderr and "cell.time_step" in plain.stderr
    debug = subprocess.run(
        [sys.executable, "-m", "earcore", "--debug", "run", "--config", str(path)], capture_output=True, text=True, timeout=120
    )
    assert debug.returncode != 0 and "Traceback" in debug.stderr and "ConfigError" in debug.stderr
