"""No hangs: earcore keeps working in a forked child after the parent used its thread
pool, and Ctrl-C stops long core calls. Each case runs in a fresh interpreter (its own
process group, killed whole on a timeout) so that a hang fails the test instead of
the run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")

# Parallel calls of every kind: the octree's ray insertion, k-neighbour work
# (normals, outliers), the voxel grid, robot collision checks, synthetic rendering and
# ICP. Several threads even on a small machine, so the pool is really used.
WORK = """
import os, pickle, signal, sys, time
import multiprocessing
import numpy as np
import earcore

# Python leaves Ctrl-C ignored when the test run was started with it ignored (in the
# background, under nohup): this child must hear it.
signal.signal(signal.SIGINT, signal.default_int_handler)
from earcore import _earcore, robots

earcore.set_num_threads(4)
rng = np.random.default_rng(0)
cloud = rng.uniform(-1, 1, (120_000, 3))
model = robots.load("ur5")
qs = model.random_configurations(600, seed=1)
corner = np.vstack([
    np.c_[np.zeros(900), rng.uniform(0, 1, (900, 2))],
    np.c_[rng.uniform(0, 1, 900), np.zeros(900), rng.uniform(0, 1, 900)],
    np.c_[rng.uniform(0, 1, (900, 2)), np.zeros(900)],
])

def work(_=None):
    tree = earcore.OcTree(0.05)
    tree.insert_point_cloud(cloud, (0.0, 0.0, 2.5))
    centres, _log_odds = tree.occupied_voxels()
    normals = earcore.estimate_normals(cloud[:40_000], 12)
    kept = earcore.remove_statistical_outliers(cloud[:40_000], 12, return_index=True)[1]
    down = earcore.voxel_downsample(cloud, 0.05)
    free = model.check_configurations(tree, qs)
    frame = _earcore.benchmark_frame()[0]
    target = earcore.PlaneTarget(corner, earcore.estimate_normals(corner, 10, viewpoint=(1, 1, 1)))
    moved = corner + (0.02, -0.01, 0.0)
    icp = earcore.icp_point_to_plane(moved, target).transform
    return [np.asarray(a) for a in (centres, normals, kept, down, free, frame, icp)]

def same(a, b):
    return len(a) == len(b) and all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, b))

def wait(pid, seconds):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        time.sleep(0.05)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    sys.exit(f"the forked child {pid} hung for {seconds} s")
"""


def run_script(script: str, timeout: float) -> subprocess.CompletedProcess:
    """Run `script` in a new interpreter and process group; a run past `timeout`
    kills the whole group (forked children included) and fails the test."""
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        out = f"hung for {timeout} s\n{out}"
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_a_forked_child_runs_parallel_calls_after_the_parent_used_the_pool():
    script = WORK + textwrap.dedent(
        """
        import tempfile
        reference = work()  # the parent builds its pool and uses every parallel path
        path = os.path.join(tempfile.mkdtemp(), "child.pickle")
        pid = os.fork()
        if pid == 0:
            try:
                data = pickle.dumps(work())
            except BaseException as e:
                data = pickle.dumps(repr(e))
            with open(path, "wb") as f:
                f.write(data)
            os._exit(0)
        assert wait(pid, 120) == 0, "the forked child failed"
        with open(path, "rb") as f:
            got = pickle.loads(f.read())
        assert not isinstance(got, str), got
        assert same(got, reference), "the forked child computed something else"

        # multiprocessing's fork start method (DataLoader workers, pipelines).
        with multiprocessing.get_context("fork").Pool(2) as pool:
            results = pool.map_async(work, range(2)).get(timeout=120)
        assert all(same(r, reference) for r in results), "a fork worker computed something else"

        # The parent's pool still works and gives the same results.
        assert same(work(), reference)
        # Single-threaded, the same results again: the reference is not the pool's own.
        with earcore.threads(1):
            assert same(work(), reference)
        print("ok")
        """
    )
    result = run_script(script, timeout=400)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr[-3000:]


def test_a_forked_child_of_a_parent_with_a_busy_thread_builds_its_own_pool():
    """Forking while another thread is inside parallel calls: the fork hooks keep the
    pool's lock out of the child's way, and the child's calls complete."""
    script = WORK + textwrap.dedent(
        """
        import threading
        reference = work()
        stop = threading.Event()
        def busy():
            while not stop.is_set():
                earcore.estimate_normals(cloud[:20_000], 8)
        threads = [threading.Thread(target=busy) for _ in range(2)]
        for t in threads:
            t.start()
        pids = []
        for _ in range(6):
            time.sleep(0.05)
            pid = os.fork()
            if pid == 0:
                os._exit(0 if same(work(), reference) else 3)
            pids.append(pid)
        codes = [wait(pid, 120) for pid in pids]
        stop.set()
        for t in threads:
            t.join()
        assert codes == [0] * len(pids), codes
        print("ok")
        """
    )
    result = run_script(script, timeout=600)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr[-3000:]


def test_the_map_stays_usable_while_a_long_insertion_runs():
    """An insertion traces its rays holding no lock on the map, so that another thread,
    and a signal handler run between its rounds, can read and change the map meanwhile
    (with the tree locked while Python ran, a getter on another thread waited for the
    lock holding the GIL, and the insertion for the GIL: a deadlock)."""
    script = WORK + textwrap.dedent(
        """
        import threading
        octree = earcore.OcTree(1e-4)
        scan = np.random.default_rng(7).normal(0, 2e-4, (200_000, 3)) + (3.0, 0.0, 0.0)
        seen = []
        signal.signal(signal.SIGUSR1, lambda *_: seen.append(octree.resolution))
        inserting = threading.Thread(target=lambda: octree.insert_point_cloud(scan, (0.0, 0.0, 0.0)))
        inserting.start()
        time.sleep(0.3)
        assert inserting.is_alive(), "the insertion ended too soon to test anything"
        assert octree.resolution == 1e-4 and octree.prob_hit == 0.7
        octree.danger_alpha = 0.5
        inserting.join()
        threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGUSR1)).start()
        octree.insert_point_cloud(scan, (0.0, 0.0, 0.0))  # the handler runs during it
        assert seen == [1e-4], seen
        assert octree.danger_alpha == 0.5 and octree.occupied_voxels()[0].shape[0] > 0
        print("ok")
        """
    )
    result = run_script(script, timeout=300)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr[-3000:]


def test_a_surface_map_stays_usable_during_icp_against_it():
    """ICP against a SurfaceMap holds it for reading while Python's signal handlers run
    between iterations: another thread's getter must not wait for the lock holding the
    GIL (it deadlocked with a writer queued), a handler may read the map past a queued
    writer, and a handler that writes it gets a RuntimeError instead of waiting on its
    own thread forever."""
    script = WORK + textwrap.dedent(
        """
        import threading
        surface = earcore.SurfaceMap(0.02)
        surface.insert(corner)
        surface.insert(corner)
        source = np.repeat(corner, 20, axis=0) + np.random.default_rng(2).normal(0, 0.003, (54_000, 3))
        # Runs until interrupted.
        long_icp = lambda: earcore.icp_point_to_plane(source, surface, max_iterations=10**12, sigma_tolerance=0.0)
        queue_writer = lambda: threading.Thread(target=lambda: (time.sleep(0.2), surface.insert(corner)))

        # A writer queued behind the ICP, then a getter on another thread (which waits for
        # the writer), then Ctrl-C, which the ICP must still be able to take.
        got = []
        def getter():
            time.sleep(0.5)
            got.append(surface.resolution)
        threads = [queue_writer(), threading.Thread(target=getter)]
        for t in threads:
            t.start()
        threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        try:
            long_icp()
        except KeyboardInterrupt:
            pass
        else:
            sys.exit("the ICP ended without the interrupt")
        for t in threads:
            t.join()
        assert got == [0.02], got

        # Signal handlers run by ICP on this thread, a writer queued on another: reading
        # works, writing is refused.
        sizes = []
        def handler(*_):
            sizes.append(surface.size())
            surface.insert(corner)
        signal.signal(signal.SIGUSR1, handler)
        writer = queue_writer()
        writer.start()
        threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGUSR1)).start()
        try:
            long_icp()
        except RuntimeError as e:
            assert "being read by ICP on this thread" in str(e), e
        else:
            sys.exit("the ICP ended without the handler's error")
        writer.join()
        assert len(sizes) == 1 and sizes[0] > 0
        surface.insert(corner)  # after the ICP: allowed again
        print("ok")
        """
    )
    result = run_script(script, timeout=300)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr[-3000:]


# Each call below is sized to run for many minutes (or hours) if it is not stopped.
LONG_CALLS = {
    "normals with k near N": """
        points = np.random.default_rng(1).uniform(-1, 1, (150_000, 3))
        call = lambda: earcore.estimate_normals(points, len(points) - 1)
        """,
    "ICP against a PlaneTarget with a huge iteration cap": """
        target = earcore.PlaneTarget(corner, np.repeat(np.eye(3), 900, axis=0))
        source = np.repeat(corner, 20, axis=0) + np.random.default_rng(2).normal(0, 0.003, (54_000, 3))
        call = lambda: earcore.icp_point_to_plane(
            source, target, max_iterations=10**12, sigma_tolerance=0.0)
        """,
    "ICP against a SurfaceMap with a huge iteration cap": """
        surface = earcore.SurfaceMap(0.02)
        surface.insert(corner)
        surface.insert(corner)
        before = surface.nodes()
        source = np.repeat(corner, 20, axis=0) + np.random.default_rng(2).normal(0, 0.003, (54_000, 3))
        call = lambda: earcore.icp_point_to_plane(
            source, surface, max_iterations=10**12, sigma_tolerance=0.0)
        """,
    "RANSAC with a huge iteration cap": """
        src = np.random.default_rng(3).uniform(-1, 1, (50_000, 3))
        call = lambda: earcore.rigid_fit_ransac(src, src + 0.1, 0.01, iterations=10**12)
        """,
    "map insertion of a long scan": """
        # 0.1 mm cells: each ray from the origin takes 30,000 steps (a minute in all on
        # two cores).
        octree = earcore.OcTree(1e-4)
        blob = lambda n, seed: np.random.default_rng(seed).normal(0, 2e-4, (n, 3)) + (3.0, 0.0, 0.0)
        octree.insert_point_cloud(blob(1000, 6), (0.0, 0.0, 0.0))
        octree_before = pickle.dumps(octree)
        scan = blob(4_000_000, 7)
        call = lambda: octree.insert_point_cloud(scan, (0.0, 0.0, 0.0))
        """,
    "outlier removal with k near N": """
        points = np.random.default_rng(4).uniform(-1, 1, (150_000, 3))
        call = lambda: earcore.remove_statistical_outliers(points, len(points) - 1)
        """,
}


@pytest.mark.parametrize("name", list(LONG_CALLS))
def test_ctrl_c_stops_a_long_call(name):
    script = WORK + textwrap.dedent(LONG_CALLS[name]) + textwrap.dedent(
        """
        print("started", flush=True)
        start = time.monotonic()
        try:
            call()
        except KeyboardInterrupt:
            # Raised out of the call itself: it was running when the signal came.
            inside = time.monotonic() - start
            print(f"KeyboardInterrupt after {inside:.2f} s", flush=True)
        else:
            sys.exit("the call finished instead of being interrupted")
        # Nothing changed, and the core still works on the same thread and pool.
        if "surface" in globals():
            after = surface.nodes()
            assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(before, after))
        if "octree" in globals():
            assert pickle.dumps(octree) == octree_before, "the interrupted insertion changed the map"
        small = earcore.icp_point_to_plane(corner + (0.02, 0, 0), earcore.PlaneTarget(corner, np.repeat(np.eye(3), 900, axis=0)))
        assert abs(small.transform[0, 3] + 0.02) < 1e-6, small.transform
        assert earcore.estimate_normals(corner, 10).shape == corner.shape
        print("ok", flush=True)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    hung = False
    try:
        assert proc.stdout is not None and proc.stderr is not None
        line = proc.stdout.readline()
        assert line.strip() == "started", line + proc.stderr.read()
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        # Uninterrupted, the call runs for minutes at least; a generous limit.
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        hung = True
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert not hung, f"{name}: still running 60 s after Ctrl-C"
    assert proc.returncode == 0, err[-3000:]
    assert "KeyboardInterrupt after" in out and out.strip().endswith("ok"), out + err[-3000:]
