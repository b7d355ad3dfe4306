"""The IROS 2018 comparison on the parts detector: distance only, IoU only, their sum,
KGC, KGC+ε, KGC/Mean and AuxNet, many runs per method that differ only in their seed,
a constant learning rate, evaluation on the test split every `--eval-every` steps, each
run's convergence point by the Fig. 12 algorithm on its combined-error curve (pickup
error + IoU error, the paper's Figs. 10 and 13), the two-sample KS tests of AuxNet
against each method, Fig. 13's box plot, and the runs that did not converge.

    earcore parts generate --out data/parts64 --count 3000 --size 64x48 --seed 1
    PYTHONPATH=python python benches/parts_combiners.py --data data/parts64 --runs 8 --steps 1500 \\
        --jobs 2 --out benches/out/parts-combiners

The paper divides the pixel distance by 100 for KGC and KGC+ε (their weights assume
losses in [0, 1]) and gives the raw pixels to the rest; so does this script. Runs
already finished in `--out` are kept (the command resumes a sweep); `--report` only
re-reads them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

from earcore.learning.compare_runs import compare_methods, eval_curve, plot_convergence_boxes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import claim_run, machine_note, run_jobs  # noqa: E402

#: method → (combiner, fixed weights, pixels per unit of the distance loss)
METHODS: dict[str, tuple[str, dict[str, float], float]] = {
    "distance": ("fixed", {"iou": 0.0, "distance": 1.0}, 1.0),
    "iou": ("fixed", {"iou": 1.0, "distance": 0.0}, 1.0),
    "sum": ("sum", {"iou": 1.0, "distance": 1.0}, 1.0),
    "kgc": ("kgc", {"iou": 1.0, "distance": 1.0}, 100.0),
    "kgc-eps": ("kgc-eps", {"iou": 1.0, "distance": 1.0}, 100.0),
    "kgc-mean": ("kgc-mean", {"iou": 1.0, "distance": 1.0}, 1.0),
    "auxnet": ("auxnet", {"iou": 1.0, "distance": 1.0}, 1.0),
}


def one_run(job: dict) -> str:
    import torch

    from earcore.learning.config import TrainConfig
    from earcore.parts.detector import PRESETS
    from earcore.parts.train import NETWORK, run

    out = Path(job["out"])
    if not claim_run(out, ("results.json", "failed.json")):
        return f"{out} (kept)"
    torch.set_num_threads(1)
    combiner, weights, unit = METHODS[job["method"]]
    config = TrainConfig(
        network=NETWORK,
        network_options={k: list(v) if isinstance(v, tuple) else v for k, v in PRESETS["small"].items()},
        steps=job["steps"],
        minutes=None,
        batch_size=job["batch"],
        lr_start=job["lr"],
        lr_end=job["lr"],
        schedule="constant",
        threads=1,
        device=job["device"],
        seed=job["seed"],
        eval_every_steps=job["eval_every"],
        eval_every_minutes=None,
        eval_samples=job["eval_samples"],
        loss_combiner=combiner,
        loss_weights=weights,
    )
    started = time.perf_counter()
    try:
        run(config, Path(job["data"]), out, distance_unit=unit, progress=False, log=None)
    except FloatingPointError as exc:  # a diverged run (KGC's exploding weights): counted, not converged
        out.mkdir(parents=True, exist_ok=True)
        (out / "failed.json").write_text(json.dumps({"error": str(exc)}) + "\n")
        return f"{out} diverged: {exc}"
    return f"{out} ({time.perf_counter() - started:.0f} s)"


def report(out: Path, methods: list[str], runs: int, args: argparse.Namespace) -> str:
    curves, finals, failed = {}, {}, {}
    for m in methods:
        folders = [out / m / f"seed{s}" for s in range(runs)]
        failed[m] = sum((f / "failed.json").is_file() for f in folders)
        done = [f for f in folders if (f / "results.json").is_file()]
        if not done:
            continue
        curves[m] = [eval_curve(f, "val_combined") for f in done]
        finals[m] = [json.loads((f / "results.json").read_text())["all"] for f in done]
    comparison = compare_methods(curves, metric="combined error (pickup + IoU)")
    reference = "auxnet" if "auxnet" in curves else next(iter(curves))
    plot_convergence_boxes(comparison, out / "fig13-parts.png", title="Convergence vs combined error (parts detector)")
    lines = [
        f"Loss combiners on the parts detector, {date.today().isoformat()}, {machine_note(out)}",
        f"data {args.data}, {runs} runs per method (seeds 0-{runs - 1}), {args.steps} steps of batch {args.batch}, "
        f"Adam lr {args.lr:g} constant, evaluation every {args.eval_every} steps on {args.eval_samples} test images",
        "",
        "Final test-split figures (mean over the runs that finished; picks by k-means with the counts known):",
        "",
        "| Method | Pickup rate | Median distance (cm) | IoU | Runs | Diverged |",
        "|---|---|---|---|---|---|",
    ]
    for m in methods:
        rows = finals.get(m, [])
        if rows:
            mean = {k: float(np.mean([r[k] for r in rows])) for k in ("pickup_rate", "median_cm", "iou")}
            lines.append(f"| {m} | {100 * mean['pickup_rate']:.1f} % | {mean['median_cm']:.2f} | {100 * mean['iou']:.1f} % | {len(rows)} | {failed[m]} |")
        else:
            lines.append(f"| {m} | - | - | - | 0 | {failed[m]} |")
    lines += ["", comparison.markdown(reference)]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a parts dataset folder (earcore parts generate)")
    parser.add_argument("--out", type=Path, default=Path("benches/out/parts-combiners"))
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated, from {', '.join(METHODS)}")
    parser.add_argument("--runs", type=int, default=8, help="runs (seeds) per method")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=50)
    parser.add_argument("--eval-samples", type=int, default=256)
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (one thread each)")
    parser.add_argument("--report", action="store_true", help="only report the runs in --out")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        parser.error(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    if not args.report:
        jobs = [
            {
                "method": m,
                "seed": s,
                "out": str(args.out / m / f"seed{s}"),
                "data": str(args.data),
                "steps": args.steps,
                "batch": args.batch,
                "lr": args.lr,
                "eval_every": args.eval_every,
                "eval_samples": args.eval_samples,
                "device": args.device,
            }
            for s in range(args.runs)
            for m in methods
        ]
        run_jobs(one_run, jobs, args.jobs, note=args.out)
    text = report(args.out, methods, args.runs, args)
    (args.out / "report.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
