"""The AAMAS 2019 one-shot protocol: train the segmenter with two part types held out,
for several held-out pairs, and the multi-task ablation (Table 2): the needle task only
("iou"), tasks 1-3 ("tasks1-3") and all four with the vector spread ("tasks1-4"), the
multi-task variants weighted by AuxNet. Per variant: the classification accuracy, IoU
and pickup rate on the held-out types averaged over the pairs, the iterations to
converge (Fig. 12's algorithm on each run's 1 − accuracy curve) and Table 1's
precision and recall per held-out type.

    earcore parts generate --out data/haystacks --count 2700 --seed 11
    earcore parts generate --out data/needles --count 900 --objects 1-1 --seed 12
    PYTHONPATH=python python benches/oneshot_ablation.py --haystacks data/haystacks \\
        --needles data/needles --pairs 6 --steps 3000 --jobs 2 --out benches/out/oneshot

The pairs: a seeded shuffle of the types taken two at a time (6 pairs cover 12 of the
13 types once each), then the remaining of the 78 pairs. Finished runs in `--out` are
kept; `--report` only re-reads them.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

from earcore.learning.compare_runs import compare_methods, eval_curve
from earcore.learning.config import key_values

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import claim_run, machine_note, run_jobs  # noqa: E402

VARIANTS: dict[str, tuple[str, ...]] = {
    "iou": ("needle",),
    "tasks1-3": ("needle", "all", "self"),
    "tasks1-4": ("needle", "all", "self", "spread"),
}


def held_out_pairs(classes: list[str], count: int, seed: int = 0) -> list[tuple[str, str]]:
    order = [classes[i] for i in np.random.default_rng(seed).permutation(len(classes))]
    disjoint = [(order[k], order[k + 1]) for k in range(0, len(order) - 1, 2)]
    rest = [p for p in itertools.combinations(order, 2) if p not in disjoint]
    pairs = (disjoint + rest)[:count]
    if count > len(pairs):
        raise ValueError(f"{len(classes)} types give only {len(pairs)} pairs, not {count}")
    return pairs


def variant_folder(variant: str, options: dict) -> str:
    """A variant's folder name, its network options included: runs with other options
    are never taken for these."""
    return variant + "".join(f"+{k}={json.dumps(v, separators=(',', ':'))}".replace('"', "") for k, v in sorted(options.items()))


def one_run(job: dict) -> str:
    import torch

    from earcore.learning.config import TrainConfig
    from earcore.parts.oneshot_train import NETWORK, run

    out = Path(job["out"])
    if not claim_run(out):
        return f"{out} (kept)"
    torch.set_num_threads(1)
    tasks = VARIANTS[job["variant"]]
    config = TrainConfig(
        network=NETWORK,
        network_options={**job["options"], "tasks": list(tasks), "in_channels": 3 if job["rgb"] else 4},
        steps=job["steps"],
        minutes=job["minutes"],
        batch_size=job["batch"],
        lr_start=job["lr"],
        lr_end=job["lr"],
        schedule="constant",
        threads=1,
        workers=job["workers"],
        device=job["device"],
        seed=job["seed"],
        eval_every_steps=job["eval_every"],
        eval_every_minutes=None,
        eval_samples=None,
        loss_combiner="auxnet" if len(tasks) > 1 else "fixed",
        combiner_options={"hidden": 64} if len(tasks) > 1 else {},
        loss_weights={t: 1.0 for t in tasks},
    )
    started = time.perf_counter()
    run(config, Path(job["haystacks"]), Path(job["needles"]), job["pair"], out, progress=False, log=None)
    return f"{out} ({time.perf_counter() - started:.0f} s)"


def report(out: Path, pairs: list[tuple[str, str]], variants: list[str], args: argparse.Namespace) -> str:
    curves: dict[str, list] = {}
    finals: dict[str, list[dict]] = {}
    for v in variants:
        folders = [out / variant_folder(v, args.options) / "-".join(p) for p in pairs]
        done = [f for f in folders if (f / "results.json").is_file()]
        curves[v] = [eval_curve(f, "val_error") for f in done]
        finals[v] = [json.loads((f / "results.json").read_text()) for f in done]
    comparison = compare_methods({v: c for v, c in curves.items() if c}, metric="1 − accuracy")
    budget = f"{args.minutes:g} minutes" if args.minutes else f"{args.steps} steps"
    options = json.dumps(args.options) if args.options else "the defaults"
    lines = [
        f"One-shot segmentation of held-out part types, {date.today().isoformat()}, {machine_note(out)}",
        f"haystacks {args.haystacks}, needles {args.needles}, {'RGB' if args.rgb else 'RGB-D'}, {len(pairs)} held-out pairs "
        f"({', '.join('+'.join(p) for p in pairs)}), {budget} of batch {args.batch}, Adam lr {args.lr:g}, "
        f"evaluation every {args.eval_every} steps on every held-out trial; network options {options}",
        "",
        "| Variant | Pairs | Accuracy | IoU | Pickup rate (correct) | Iterations to converge (median) | Trials "
        "| Marking every part | Accuracy on two trained types |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for v in variants:
        rows = finals[v]
        if not rows:
            lines.append(f"| {v} | 0 | - | - | - | - | - | - | - |")
            continue
        runs = comparison.methods.get(v)
        its = f"{np.median(runs.iterations):.0f}" if runs is not None and len(runs.points) else "-"
        known = [r["seen"]["accuracy"] for r in rows if "seen" in r]
        seen = f"{100 * np.mean(known):.1f} %" if known else "-"
        every = f"{100 * np.mean([r['every_part_accuracy'] for r in rows]):.1f} %" if all("every_part_accuracy" in r for r in rows) else "-"
        lines.append(
            f"| {v} | {len(rows)} | {100 * np.mean([r['accuracy'] for r in rows]):.1f} % | {np.mean([r['iou'] for r in rows]):.3f} | "
            f"{100 * np.nanmean([r['pickup_rate'] for r in rows]):.1f} % | {its} | {sum(r['trials'] for r in rows)} | {every} | {seen} |"
        )
    full = variants[-1]
    if finals[full]:
        lines += ["", f"Precision and recall per held-out type ({full}):", "", "| Type | Trials | Precision | Recall |", "|---|---|---|---|"]
        for r in finals[full]:
            for name, row in r["classes"].items():
                lines.append(f"| {name} | {row['trials']} | {row['precision']:.2f} | {row['recall']:.2f} |")
    if len(comparison.methods) > 1:
        lines += ["", comparison.markdown(full if full in comparison.methods else None)]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--haystacks", type=Path, required=True)
    parser.add_argument("--needles", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("benches/out/oneshot"))
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, from {', '.join(VARIANTS)}")
    parser.add_argument("--pairs", type=int, default=6, help="held-out pairs (of the 78)")
    parser.add_argument("--rgb", action="store_true", help="colour only (the paper's best)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--minutes", type=float, default=None, help="train each run this long instead of --steps")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0, help="the network's seed (the same for every run)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (one thread each)")
    parser.add_argument("--workers", type=int, default=0, help="data-loader processes per run")
    parser.add_argument("--skip-pairs", type=int, default=0, help="start at this pair of the order (e.g. one kept for choosing settings)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=JSON", help="a network option for every run, e.g. --option pooling=image")
    parser.add_argument("--report", action="store_true", help="only report the runs in --out")
    args = parser.parse_args()
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    classes = json.loads((args.haystacks / "manifest.json").read_text())["classes"]
    pairs = held_out_pairs(classes, args.skip_pairs + args.pairs)[args.skip_pairs :]
    args.options = key_values(args.option, "--option")
    if not args.report:
        jobs = [
            {
                "variant": v,
                "pair": list(p),
                "out": str(args.out / variant_folder(v, args.options) / "-".join(p)),
                "haystacks": str(args.haystacks),
                "needles": str(args.needles),
                "rgb": args.rgb,
                "steps": None if args.minutes else args.steps,
                "minutes": args.minutes,
                "batch": args.batch,
                "lr": args.lr,
                "eval_every": args.eval_every,
                "seed": args.seed,
                "device": args.device,
                "workers": args.workers,
                "options": args.options,
            }
            for p in pairs
            for v in variants
        ]
        run_jobs(one_run, jobs, args.jobs, note=args.out)
    text = report(args.out, pairs, variants, args)
    (args.out / "report.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
