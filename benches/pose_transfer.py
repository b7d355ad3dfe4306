"""New robots from a few hundred images (Papers VI and VII) on the 2-core CPU:

- Paper VI: the multi-objective network trained on the UR robots (`--source`) is
  transferred to the iiwa with its convolutions frozen (`--trainable paper-vi`), on N
  randomly drawn iiwa images for each N of `--sizes`, each within 1/8 of the full
  training's time (and stopped earlier when the joint error stops falling); the full
  training: the same network from scratch on every iiwa training image for
  `--full-minutes`. Table II's layout, the sweep (Fig. 4c's accuracy and training
  time against N), and what the transferred network still knows of the UR robots
  (Paper VI forgets them).
- Paper VII: the same UR network, two stages on the old and the new robots in equal
  numbers (`--per-robot` training images of each: the UR ones from the source's own
  training images `--ur`, the new ones from `--new`): stage 1 trains only the dense
  layers until the joint error stops falling, stage 2 also the later convolutions.
  Table II's layout per robot, and every old robot before and after on its own test
  split.

    earcore dataset robots --out data/iiwa --robots iiwa --seed 11
    earcore dataset robots --out data/mixed --robots ur3,ur5,ur10,iiwa,panda --count 400 --seed 12
    PYTHONPATH=python python benches/pose_transfer.py --source runs/ur-multi --ur data/ur --iiwa data/iiwa \\
        --new data/mixed --new-robots iiwa,panda --out benches/out/transfer

Runs already in `--out` are kept (rerunning only reports). One thread per run; two
runs at once where they are independent.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from datetime import date
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import machine  # noqa: E402

EARCORE = [sys.executable, "-m", "earcore.pose.train"]
ROWS = (
    ("mask_accuracy", "Mask accuracy", "{:.1%}"),
    ("type_accuracy", "Robot type accuracy", "{:.1%}"),
    ("joints_median_cm", "Joint position error (median)", "{:.2f} cm"),
    ("base_median_cm", "Base position error (median)", "{:.2f} cm"),
)


def train_command(out: Path, data: Path, minutes: float, *more: str) -> list[str]:
    return [*EARCORE, "--data", str(data), "--network", "multi", "--out", str(out), "--minutes", f"{minutes:g}", "--threads", "1", "--no-progress", *more]


def start(command: list[str], log: Path) -> subprocess.Popen | None:
    if (log.parent / log.stem / "results.json").is_file():
        return None
    log.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT)


def wait(*procs: subprocess.Popen | None) -> None:
    for p in procs:
        if p is not None and p.wait() != 0:
            raise SystemExit(f"a run failed: {' '.join(map(str, p.args))}")


def evaluated(checkpoint: Path, data: Path, robots: list[str] | None, other: bool = False) -> dict[str, dict[str, float]]:
    from earcore.learning.dataset import ImageDataset
    from earcore.pose.evaluate import evaluate
    from earcore.pose.train import load_trained

    network, meta = load_trained(checkpoint)
    test = ImageDataset(data, split="test", robots=robots, noise=False)
    return evaluate(network, test, "cpu", robots=meta["robots"], timing=False, foreign=other).metrics


def run_info(folder: Path) -> dict[str, Any]:
    rows = [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines() if line.strip()]
    last = rows[-1]
    results = json.loads((folder / "results.json").read_text())["metrics"]
    return {"minutes": last["seconds"] / 60.0, "steps": last["step"], "metrics": results}


def cell(values: dict[str, float], key: str, fmt: str) -> str:
    v = values.get(key)
    return "n/a" if v is None else fmt.format(v)


def summary(m: dict[str, float]) -> str:
    nan = float("nan")
    return f"{m.get('joints_median_cm', nan):.2f} / {m.get('base_median_cm', nan):.2f}, {m.get('type_accuracy', nan):.1%}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", type=Path, required=True, help="the multi-objective network trained on the UR robots (run folder)")
    parser.add_argument("--iiwa", type=Path, required=True, help="earcore-images folder of iiwa recordings")
    parser.add_argument(
        "--ur",
        type=Path,
        required=True,
        help="the UR images the source was trained on (its train split joins Paper VII's transfer set, its test split measures forgetting)",
    )
    parser.add_argument("--new", type=Path, required=True, help="earcore-images folder with the new robots' recordings")
    parser.add_argument("--new-robots", default="iiwa,panda", help="the new robots (of --new)")
    parser.add_argument("--per-robot", type=int, default=320, help="Paper VII: training images of each robot, old and new")
    parser.add_argument("--out", type=Path, default=Path("benches/out/transfer"))
    parser.add_argument("--full-minutes", type=float, default=30.0)
    parser.add_argument("--sizes", default="300,50,100,1000,1470")
    parser.add_argument("--stage1-minutes", type=float, default=6.0)
    parser.add_argument("--stage2-minutes", type=float, default=12.0)
    args = parser.parse_args()
    out = args.out
    sizes = [int(n) for n in args.sizes.split(",")]
    budget = args.full_minutes / 8.0

    # Paper VI: the full training beside the sweep, then Paper VII's two stages.
    full = start(train_command(out / "iiwa-full", args.iiwa, args.full_minutes, "--eval-minutes", "2.5"), out / "iiwa-full.log")
    for n in sizes:
        more = (
            "--transfer-from",
            str(args.source),
            "--trainable",
            "paper-vi",
            "--train-samples",
            str(n),
            "--batch",
            str(64 if n >= 64 else n // 2),
            "--patience",
            "3",
            "--eval-minutes",
            "0.5",
        )
        wait(start(train_command(out / f"vi-n{n}", args.iiwa, budget, *more), out / f"vi-n{n}.log"))
    small = max((n for n in sizes if n <= 300), default=min(sizes))
    for t in ("late", "all"):  # the same small set with more of the network training
        more = ("--transfer-from", str(args.source), "--trainable", t, "--train-samples", str(small), "--patience", "3", "--eval-minutes", "0.5")
        wait(start(train_command(out / f"vi-n{small}-{t}", args.iiwa, budget, *more), out / f"vi-n{small}-{t}.log"))
    new_robots = args.new_robots.split(",")
    union = ("--robots", *new_robots, "--join", str(args.ur), "--train-samples", str(args.per_robot), "--per-robot")
    stage1 = (*union, "--transfer-from", str(args.source), "--trainable", "dense", "--patience", "3", "--eval-minutes", "0.5")
    wait(start(train_command(out / "vii-stage1", args.new, args.stage1_minutes, *stage1), out / "vii-stage1.log"))
    stage2 = (*union, "--transfer-from", str(out / "vii-stage1"), "--trainable", "late", "--eval-minutes", "1")
    wait(start(train_command(out / "vii-stage2", args.new, args.stage2_minutes, *stage2), out / "vii-stage2.log"))
    wait(full)

    full_info = run_info(out / "iiwa-full")
    sweep = {n: run_info(out / f"vi-n{n}") for n in sizes}
    vi = sweep[small]
    lines = [
        f"Transfer to new robots, {date.today().isoformat()}, {machine()}",
        f"source: {args.source}; one thread per run",
        "",
        f"Paper VI, Table II's layout (iiwa test split; transfer on {small} images, convolutions frozen):",
        "",
        f"| Measure | Full training (iiwa, from scratch) | Transfer learning ({small} images) |",
        "|---|---|---|",
    ]
    for key, label, fmt in ROWS:
        if key != "type_accuracy":
            lines.append(f"| {label} | {cell(full_info['metrics']['all'], key, fmt)} | {cell(vi['metrics']['all'], key, fmt)} |")
    lines.append(f"| Training time | {full_info['minutes']:.1f} min | {vi['minutes']:.1f} min |")
    lines += [
        "",
        "The sweep (Fig. 4c): transfer on N iiwa images, at most 1/8 of the full training's time, stopped after 3 evaluations without a lower joint error:",
        "",
        "| N | Trains | Joints median (cm) | Base median (cm) | Mask accuracy | Training time (min) | Steps |",
        "|---|---|---|---|---|---|---|",
    ]
    variants = [(n, "paper-vi", sweep[n]) for n in sorted(sweep)] + [(small, t, run_info(out / f"vi-n{small}-{t}")) for t in ("late", "all")]
    for n, trains, info in variants:
        m = info["metrics"]["all"]
        lines.append(
            f"| {n} | {trains} | {m['joints_median_cm']:.2f} | {m['base_median_cm']:.2f} | {m['mask_accuracy']:.1%} | {info['minutes']:.1f} | {info['steps']} |"
        )

    before = evaluated(args.source, args.ur, None)
    forgot = evaluated(out / f"vi-n{small}", args.ur, None, other=True)
    after_old = evaluated(out / "vii-stage2", args.ur, None)
    stage1_info, after_info = run_info(out / "vii-stage1"), run_info(out / "vii-stage2")
    after = after_info["metrics"]
    robots = [r for r in after if r != "all"]
    lines += [
        "",
        f"Paper VII, Table II's layout ({args.per_robot} training images per robot; test splits of {args.ur} and {args.new}; "
        f"stage 1 {stage1_info['minutes']:.1f} min, stage 2 {after_info['minutes']:.1f} min):",
        "",
        "| Measure | " + " | ".join(robots) + " |",
        "|---|" + "---|" * len(robots),
    ]
    for key, label, fmt in ROWS:
        lines.append(f"| {label} | " + " | ".join(cell(after[r], key, fmt) for r in robots) + " |")
    lines += [
        "",
        f"The old robots on their own test split ({args.ur}) before and after (joint / base median in cm, type accuracy), "
        "and Paper VI's one-stage network (iiwa only) on them:",
        "",
        "| Robot | Before (UR network) | After two stages | Change of the joint error | Paper VI's network |",
        "|---|---|---|---|---|",
    ]
    for r in [r for r in before if r != "all"]:
        b, a, f = before[r], after_old.get(r, {}), forgot.get(r, {})
        change = 100.0 * (a["joints_median_cm"] / b["joints_median_cm"] - 1.0) if a else float("nan")
        lines.append(f"| {r} | {summary(b)} | {summary(a)} | {change:+.1f} % | {summary(f)} |")
    text = "\n".join(lines) + "\n"
    (out / "report.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
