"""Paper II's whole-system test (Table II) in the simulated cell.

A-B-A return trips of the UR5, four experiments with one seed:
  Exp. 1  reactive planner, a static pillar blocking the direct path;
  Exp. 2  reactive planner, a person's arm entering the direct path at random
          (peak hand speeds drawn between 0.25 and 1.6 m/s);
  Exp. 3  predictive planner + reflexes, the same arm (same reaches);
  Direct  no obstacle.
Prints mean ± std per return trip of planning, optimisation and execution time, path
length, and the totals of collisions (true contacts), reflexes and stops, and the
minimum true robot-person distance.

    earcore experiment table2 [--trips 15] [--seed 0] [--camera-scale 0.25] [--out out/table2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from copy import deepcopy
from pathlib import Path

import numpy as np

from earcore.sim.config import RunConfig

__all__ = ["experiment_configs", "main", "table2"]

#: A 10 × 10 cm pillar between the tool's A and B positions (Exp. 1).
PILLAR = (0.28, 0.33, 0.0, 0.38, 0.43, 0.8)


def _reaches(seed: int, duration: float) -> tuple[list[float], list[tuple[float, float, float]], list[float]]:
    """Random reaches into the direct path: a new one every 3-7 s, the hand aimed near
    the middle of the tool's A-B sweep, peak speed 0.25-1.6 m/s."""
    rng = np.random.default_rng([seed, 7])
    starts = list(np.cumsum(rng.uniform(3.0, 7.0, int(duration / 3) + 1)) - 1.0)
    targets = [tuple(t) for t in rng.uniform([0.15, 0.3, 0.35], [0.35, 0.5, 0.55], (len(starts), 3))]
    speeds = list(rng.uniform(0.25, 1.6, len(starts)))
    return starts, targets, speeds


def experiment_configs(seed: int = 0, camera_scale: float = 0.25, duration: float = 600.0) -> dict[str, RunConfig]:
    base = RunConfig(duration=duration, snapshots=[])
    base.cell.seed = seed
    base.cell.camera_scale = camera_scale
    base.cell.person.enabled = False
    configs = {}
    exp1 = deepcopy(base)
    exp1.cell.boxes = list(exp1.cell.boxes) + [PILLAR]
    exp1.planning.mode = "reactive"
    configs["Exp. 1"] = exp1
    person = deepcopy(base)
    person.cell.person.enabled = True
    starts, targets, speeds = _reaches(seed, duration)
    person.cell.person.reach_starts = starts
    person.cell.person.reach_targets = targets
    person.cell.person.reach_speeds = speeds
    person.cell.person.hold_s = 1.0
    exp2 = deepcopy(person)
    exp2.planning.mode = "reactive"
    configs["Exp. 2"] = exp2
    exp3 = deepcopy(person)
    exp3.planning.mode = "predictive"
    configs["Exp. 3"] = exp3
    configs["Direct"] = deepcopy(base)
    return configs


def table2(trips: int = 15, seed: int = 0, camera_scale: float = 0.25, out: Path = Path("out/table2"), only=None) -> dict:
    """Run the experiments; returns {experiment: figures per return trip}."""
    from earcore.run import run

    results = {}
    for name, config in experiment_configs(seed, camera_scale).items():
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        summary = run(config, out / name.replace(". ", "").lower(), progress=False, record=False, trips=2 * trips)
        moves = summary.get("trips", [])
        # A return trip is two moves (A→B, B→A).
        pairs = [moves[i : i + 2] for i in range(0, len(moves) - 1, 2)]
        per_trip = {
            key: [sum(m[key] for m in pair) for pair in pairs]
            for key in ("planning_time", "optimisation_time", "execution_time", "path_length")
        }
        results[name] = {
            "return_trips": len(pairs),
            **{k: (float(np.mean(v)), float(np.std(v))) if v else (float("nan"), float("nan")) for k, v in per_trip.items()},
            "collisions": sum(m["collisions"] for m in moves),
            "reflexes": sum(m["reflexes"] for m in moves),
            "stops": sum(m["stops"] for m in moves),
            "min_clearance_m": min((m["min_clearance"] for m in moves), default=float("inf")),
            "reflex_compute_ms": summary.get("planning", {}).get("reflex_compute_ms"),
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        print(f"  {name}: {len(pairs)} return trips in {results[name]['wall_s']} s", file=sys.stderr)
    return results


def format_table(results: dict) -> str:
    names = list(results)
    rows = [
        ("planning time (s)", "planning_time", "{:.4f} ± {:.4f}"),
        ("optimisation time (s)", "optimisation_time", "{:.4f} ± {:.4f}"),
        ("execution time (s)", "execution_time", "{:.2f} ± {:.2f}"),
        ("path length (rad)", "path_length", "{:.2f} ± {:.2f}"),
    ]
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, key, fmt in rows:
        lines.append(f"| {label} | " + " | ".join(fmt.format(*results[n][key]) for n in names) + " |")
    for label, key in (("return trips", "return_trips"), ("collisions", "collisions"), ("reflexes", "reflexes"), ("stops", "stops")):
        lines.append(f"| {label} | " + " | ".join(str(results[n][key]) for n in names) + " |")
    lines.append("| min. robot-person distance (m) | " + " | ".join(
        f"{results[n]['min_clearance_m']:.3f}" if np.isfinite(results[n]["min_clearance_m"]) else "–" for n in names) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="earcore experiment", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=["table2"], help="which experiment")
    parser.add_argument("--trips", type=int, default=15, help="A-B-A return trips per experiment (default 15)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera-scale", type=float, default=0.25, help="camera resolution factor (rendering dominates the run time)")
    parser.add_argument("--only", nargs="*", help="run only these experiments, e.g. 'Exp. 3' Direct")
    parser.add_argument("--out", type=Path, default=Path("out/table2"))
    args = parser.parse_args(argv)
    results = table2(args.trips, args.seed, args.camera_scale, args.out, args.only)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table2.json").write_text(json.dumps(results, indent=2, default=float))
    print(format_table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
