"""Writes the OctoMap reference fixture that `tests/rust/octomap_fixture.rs` checks.

The fixture was made with pyoctomap 1.2.2 (OctoMap's own C++ through Python):

    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install numpy pyoctomap==1.2.2
    /tmp/venv/bin/python tests/data/make_octomap_fixture.py

It writes, next to this script:

* `octomap_scene.txt`: the input and OctoMap's answers. The scene (a wall, a floor
  and a box top, seen by two scans in order, the second cut at 2 m and discretized) is computed
  here in closed form, no random numbers; every number is written with `repr`, so the
  Rust test reads back the exact doubles. Then single-cell updates (hits, misses and
  raw log-odds changes) on a second tree, and for both trees OctoMap's size, leaf
  count and log-odds at probe points.
* `octomap_scene.ot` / `octomap_scene.bt`: OctoMap's full (`write`) and binary
  (`writeBinary`) serialisations of the scanned tree, in that order (`writeBinary`
  turns the tree into its maximum-likelihood version in place).
* `octomap_updates.ot`: the full serialisation of the updated tree.

Line format of `octomap_scene.txt` (`#` starts a comment):

    resolution R
    p X Y Z                               # a point of the scene (every scan sees all)
    scan OX OY OZ MAX_RANGE DISCRETIZE    # MAX_RANGE -1: unlimited; DISCRETIZE 0/1
    probe scene|updates X Y Z LOGODDS     # OctoMap's log-odds there ("nan": unknown)
    size scene|updates N                  # OctoMap's node count
    leaves scene|updates N                # OctoMap's leaf count
    update X Y Z hit|miss|DELTA           # updateNode on the updates tree, in order
"""

from __future__ import annotations

from importlib.metadata import version
from pathlib import Path

import numpy as np
import pyoctomap

HERE = Path(__file__).resolve().parent
RESOLUTION = 0.1


def scene_points() -> np.ndarray:
    """A wall at x = 1.52, a floor at z = 0.03 and the top of a box, sampled on grids."""
    pts = []
    for i in range(14):
        for j in range(9):
            pts.append((1.52, -0.65 + 0.1 * i, 0.03 + 0.13 * j))
    for i in range(12):
        for j in range(12):
            pts.append((0.05 + 0.12 * i, -0.6 + 0.105 * j, 0.03))
    for i in range(5):
        for j in range(5):
            pts.append((0.62 + 0.041 * i, 0.11 + 0.043 * j, 0.47))
    return np.array(pts, dtype=np.float64)


SCANS = [
    # (origin, max_range, discretize): the second views the scene from above, its rays
    # to the far wall are cut at 2 m, and points sharing a cell are merged.
    (np.array([-0.21, 0.07, 0.64]), -1.0, False),
    (np.array([0.33, -0.92, 1.37]), 2.0, True),
]

# Updates on a fresh tree: a 2×2×2 block hit until every cell is clamped (it prunes
# into one node), a cell missed until clamped, a cell hit then missed, and raw changes.
BLOCK = [(0.05 + 0.1 * a, 0.05 + 0.1 * b, 0.05 + 0.1 * c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
UPDATES = (
    [(p, "hit") for _ in range(12) for p in BLOCK]
    + [((0.85, -0.35, 0.15), "miss")] * 8
    + [((-0.45, 0.25, 0.55), "hit"), ((-0.45, 0.25, 0.55), "miss")]
    + [((0.35, 0.65, -0.25), 1.25), ((0.35, 0.65, -0.25), -0.5), ((-0.95, -0.85, 0.05), 7.5)]
)

SCENE_PROBES = [(0.4, 0.0, 0.6), (1.55, 0.0, 0.4), (0.5, 0.0, 0.05), (0.7, 0.2, 0.45), (0.0, 0.0, 3.0)]
UPDATE_PROBES = [(0.05, 0.05, 0.05), (0.15, 0.15, 0.15), (0.85, -0.35, 0.15), (-0.45, 0.25, 0.55),
                 (0.35, 0.65, -0.25), (-0.95, -0.85, 0.05), (2.0, 2.0, 2.0)]


def log_odds_at(tree, p) -> float:
    node = tree.search(np.array(p, dtype=np.float64))
    return float("nan") if node is None else float(node.getLogOdds())


def main() -> None:
    lines = [
        f"# Made by tests/data/make_octomap_fixture.py with pyoctomap {version('pyoctomap')}.",
        f"resolution {RESOLUTION!r}",
    ]
    points = scene_points()
    lines += [f"p {x!r} {y!r} {z!r}" for x, y, z in points.tolist()]
    scene = pyoctomap.OcTree(RESOLUTION)
    for origin, max_range, discretize in SCANS:
        scene.insertPointCloud(points, origin, max_range=max_range, discretize=discretize)
        x, y, z = origin.tolist()
        lines.append(f"scan {x!r} {y!r} {z!r} {max_range!r} {int(discretize)}")
    lines.append(f"size scene {scene.size()}")
    lines.append(f"leaves scene {scene.getNumLeafNodes()}")
    lines += [f"probe scene {x!r} {y!r} {z!r} {log_odds_at(scene, (x, y, z))!r}" for x, y, z in SCENE_PROBES]
    (HERE / "octomap_scene.ot").write_bytes(scene.write())
    (HERE / "octomap_scene.bt").write_bytes(scene.writeBinary())

    updates = pyoctomap.OcTree(RESOLUTION)
    for p, what in UPDATES:
        arg = {"hit": True, "miss": False}.get(what, what)
        updates.updateNode(np.array(p, dtype=np.float64), arg)
        lines.append(f"update {p[0]!r} {p[1]!r} {p[2]!r} {what if isinstance(what, str) else repr(what)}")
    lines.append(f"size updates {updates.size()}")
    lines.append(f"leaves updates {updates.getNumLeafNodes()}")
    lines += [f"probe updates {x!r} {y!r} {z!r} {log_odds_at(updates, (x, y, z))!r}" for x, y, z in UPDATE_PROBES]
    (HERE / "octomap_updates.ot").write_bytes(updates.write())

    (HERE / "octomap_scene.txt").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
