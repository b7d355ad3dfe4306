"""The installed package: wheel import, command line, stubs, demo, threads."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import threading
import time
from pathlib import Path

import pytest

import earcore

REPO = Path(__file__).resolve().parents[3]


def test_suite_runs_against_the_installed_wheel():
    """`make test` installs the wheel into a fresh venv: earcore must come from there."""
    location = Path(earcore.__file__).resolve()
    if REPO / "python" in location.parents:
        pytest.skip("running against the source tree (make develop), not the installed wheel")
    assert Path(sysconfig.get_paths()["purelib"]).resolve() in location.parents
    assert Path(earcore._earcore.__file__).suffix == ".so"


def test_version_command():
    out = subprocess.run([sys.executable, "-m", "earcore", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith(f"earcore {earcore.__version__} ")
    cargo = (REPO / "Cargo.toml").read_text()
    assert f'version = "{earcore.__version__}"' in cargo, "Cargo.toml is the one version source"


def test_version_command_reports_a_broken_extension(tmp_path):
    """A broken install must fail loudly with a hint, not with a bare traceback."""
    fake = tmp_path / "earcore"
    fake.mkdir()
    src = Path(earcore.__file__).parent
    (fake / "app").mkdir()
    for name in ("__init__.py", "__main__.py", "app/__init__.py", "app/cli.py", "app/arguments.py"):
        (fake / name).write_text((src / name).read_text())
    (fake / "_earcore.py").write_text("raise ImportError('simulated: undefined symbol')\n")
    out = subprocess.run([sys.executable, "-m", "earcore", "--version"], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 1
    assert "failed to load" in out.stderr and "simulated" in out.stderr


def test_stubs_match_the_extension():
    stubtest = pytest.importorskip("mypy.stubtest")
    assert stubtest is not None
    out = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "earcore._earcore"], capture_output=True, text=True, cwd="/"
    )
    assert out.returncode == 0, out.stdout + out.stderr


def test_demo_writes_a_picture_and_one_line(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "earcore", "demo", "--after", "1", "--out", str(tmp_path), "--quiet"],
        capture_output=True,
        text=True,
        check=True,
    )
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("earcore demo: 3 cameras")
    png = tmp_path / "map_danger.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert earcore.OcTree.read_binary(tmp_path / "map.bt").size() > 1000


def test_readers_run_while_a_writer_inserts():
    """Queries from other threads during insertions: never an error, always a
    consistent answer (a cell seen occupied by one scan stays known)."""
    points, origin = earcore.synthetic.benchmark_frame()
    tree = earcore.OcTree(0.05)
    tree.insert_point_cloud(points[:1000], origin)
    probe, _ = tree.occupied_voxels()  # cells are never forgotten, so these stay known
    errors: list[BaseException] = []
    stop = threading.Event()
    counts = [0, 0]

    def reader(i: int) -> None:
        try:
            while not stop.is_set():
                known = tree.is_occupied(probe)
                assert (known >= 0).all()
                tree.cast_ray(origin, probe[0] - origin)
                counts[i] += 1
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=reader, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for k in range(6):
        tree.insert_point_cloud(points[k::6], origin)
        tree.end_frame(0.1)
    stop.set()
    for t in threads:
        t.join()
    assert not errors, errors
    assert min(counts) > 0


def test_insertion_releases_the_gil():
    """A pure-Python thread keeps running while a large insertion is in progress."""
    points, origin = earcore.synthetic.benchmark_frame()
    ticks = []
    done = threading.Event()

    def ticker() -> None:
        while not done.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.001)

    t = threading.Thread(target=ticker)
    t.start()
    time.sleep(0.01)
    start = time.perf_counter()
    tree = earcore.OcTree(0.02)
    tree.insert_point_cloud(points, origin)
    end = time.perf_counter()
    done.set()
    t.join()
    during = [x for x in ticks if start < x < end]
    assert len(during) >= 3, f"only {len(during)} ticks during a {end - start:.3f} s insertion"


def test_threads_sets_the_count_for_this_thread_within_the_block():
    """`earcore.threads(n)`: n inside the block on this thread, the setting before it
    afterwards (also when the block raises), nested blocks unwind in order, and another
    thread and the process-wide setting never see it."""
    before = earcore.get_num_threads()
    seen_elsewhere = []
    with pytest.raises(RuntimeError):
        with earcore.threads(1):
            assert earcore.get_num_threads() == 1
            with earcore.threads(3):
                assert earcore.get_num_threads() == 3
                worker = threading.Thread(target=lambda: seen_elsewhere.append(earcore.get_num_threads()))
                worker.start()
                worker.join()
            assert earcore.get_num_threads() == 1
            raise RuntimeError("a failing step")
    assert earcore.get_num_threads() == before
    assert seen_elsewhere == [before]
