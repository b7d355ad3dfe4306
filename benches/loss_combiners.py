"""AuxNet against every loss combiner on the multi-objective pose network (Paper V's
four losses), the IROS 2018 protocol at CPU scale: many runs per method that differ
only in their seed (initial weights, batch order), a constant learning rate (a
decaying one would make every method "converge" when it runs out), evaluation on the
test split every `--eval-every` steps, each run's convergence point by the Fig. 12
algorithm on its joint-error curve and on its mask-error curve (1 - IoU), the
two-sample KS tests of AuxNet against each method, and Fig. 13's box plot.

    earcore dataset robots --out data/ur64 --size 64x53                  # the papers' UR set, small
    PYTHONPATH=python python benches/loss_combiners.py --data data/ur64 --runs 8 --steps 600 \\
        --jobs 2 --out benches/out/combiners

Runs already finished in `--out` are kept (the command resumes a sweep); `--report`
only re-reads them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

from earcore.learning.combiners import COMBINERS
from earcore.learning.compare_runs import compare_methods, eval_curve, plot_convergence_boxes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import claim_run, machine, run_jobs  # noqa: E402

#: The methods compared: fixed is the papers' weights (Paper V: 1, 1.5, 1.5, 0.3).
METHODS = ("sum", "fixed", "kgc", "kgc-eps", "kgc-mean", "uncertainty", "dwa", "auxnet")


def one_run(job: dict) -> str:
    import torch

    from earcore.learning.config import TrainConfig
    from earcore.learning.dataset import ImageDataset
    from earcore.pose.train import run

    out = Path(job["out"])
    if not claim_run(out):
        return f"{out} (kept)"
    torch.set_num_threads(1)
    config = TrainConfig(
        network="multi",
        steps=job["steps"],
        minutes=None,
        batch_size=job["batch"],
        lr_start=job["lr"],
        lr_end=job["lr"],
        schedule="constant",
        threads=1,
        seed=job["seed"],
        log_every=10,
        eval_every_steps=job["eval_every"],
        eval_every_minutes=None,
        eval_samples=job["eval_samples"],
        loss_combiner=job["method"],
        network_options=job["options"],
    )
    train_set = ImageDataset(job["data"], split="train", noise=True, seed=job["seed"])
    test_set = ImageDataset(job["data"], split="test", noise=False, seed=0)
    started = time.perf_counter()
    run(config, Path(job["data"]), out, datasets=(train_set, test_set), progress=False)
    return f"{out} ({time.perf_counter() - started:.0f} s)"


def report(out: Path, methods: list[str], runs: int, args: argparse.Namespace) -> str:
    joints, masks, finals = {}, {}, {}
    for m in methods:
        folders = [out / m / f"seed{s}" for s in range(runs) if (out / m / f"seed{s}" / "results.json").is_file()]
        if not folders:
            continue
        joints[m] = [eval_curve(f, "joints_mean_cm") for f in folders]
        masks[m] = [(s, 1.0 - v) for s, v in (eval_curve(f, "mask_iou") for f in folders)]
        finals[m] = [json.loads((f / "results.json").read_text())["metrics"]["all"] for f in folders]
    by_joints = compare_methods(joints, metric="joint error, mean (cm)")
    by_masks = compare_methods(masks, metric="mask error (1 - IoU)")
    reference = "auxnet" if "auxnet" in joints else next(iter(joints))
    plot_convergence_boxes(by_joints, out / "fig13-joints.png", title="Convergence vs joint error (multi-objective pose network)")
    plot_convergence_boxes(by_masks, out / "fig13-mask.png", title="Convergence vs mask error (multi-objective pose network)")
    lines = [
        f"Loss combiners on the multi-objective pose network, {date.today().isoformat()}, {machine()}",
        f"data {args.data}, {runs} runs per method (seeds 0-{runs - 1}), {args.steps} steps of batch {args.batch}, "
        f"Adam lr {args.lr:g} constant, evaluation every {args.eval_every} steps on {args.eval_samples} test images",
        "",
        "Final test-split figures (mean over runs):",
        "",
        "| Method | Joints median (cm) | Base median (cm) | Mask IoU | Type accuracy | Runs |",
        "|---|---|---|---|---|---|",
    ]
    for m, rows in finals.items():
        mean = {k: float(np.mean([r[k] for r in rows])) for k in ("joints_median_cm", "base_median_cm", "mask_iou", "type_accuracy")}
        lines.append(f"| {m} | {mean['joints_median_cm']:.2f} | {mean['base_median_cm']:.2f} | {mean['mask_iou']:.3f} | {mean['type_accuracy']:.3f} | {len(rows)} |")
    lines += ["", "Joint error curves:", "", by_joints.markdown(reference), "Mask error curves:", "", by_masks.markdown(reference)]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="an earcore-images folder with train/test splits")
    parser.add_argument("--out", type=Path, default=Path("benches/out/combiners"))
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated, from {', '.join(COMBINERS)}")
    parser.add_argument("--runs", type=int, default=8, help="runs (seeds) per method")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=25)
    parser.add_argument("--eval-samples", type=int, default=256)
    parser.add_argument("--option", action="append", default=[], metavar="KEY=JSON", help="a network option (default: width 0.25, fc 64, head 32)")
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (one thread each)")
    parser.add_argument("--report", action="store_true", help="only report the runs in --out")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = sorted(set(methods) - set(COMBINERS))
    if unknown:
        parser.error(f"unknown method(s) {unknown}; known: {', '.join(COMBINERS)}")
    options = {"width": 0.25, "fc": 64, "head": 32, "mask_stride": 2}
    for item in args.option:
        key, _, text = item.partition("=")
        options[key] = json.loads(text)
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
                "options": options,
            }
            for s in range(args.runs)
            for m in methods
        ]
        run_jobs(one_run, jobs, args.jobs)
    text = report(args.out, methods, args.runs, args)
    (args.out / "report.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
