"""Robot pose from one colour image: train the pose networks within a time budget each,
then report them side by side in the papers' table layout, on the test split (the
papers' protocol: random 80/20 split of the recordings) and on held-out recordings
(camera placements, lighting and seeds never seen in training).

Runs from the source tree with Python, numpy and torch only (no compiled core), so the
same command serves the 2-core CPU machine and a GPU machine:

    earcore dataset robots --out data/ur                                  # the papers' UR set
    earcore dataset robots --out data/ur-heldout --seed 1001 --scale 0.2   # held-out recordings
    PYTHONPATH=python python benches/pose_accuracy.py --data data/ur --heldout data/ur-heldout \\
        --networks multi,cascade,keypoint --minutes 60 --out benches/out/pose

`--extra FOLDER` adds every image of another set to the training images (a random-camera
set beside the recordings, for the held-out placements). `--ship [NETWORK]` exports a
network (default multi) to python/earcore/pose/weights/ (the weights
`earcore.pose.estimate` uses)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import date
from pathlib import Path

from earcore.learning.dataset import ImageDataset
from earcore.learning.metrics_log import plot_comparison, read_metrics
from earcore.pose.evaluate import evaluate
from earcore.pose.train import build_parser, config_from_args, load_trained, run

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import machine  # noqa: E402

#: The accuracy-vs-time curves drawn side by side (curves.png).
CURVES = ("joints_median_cm", "base_median_cm", "mask_iou", "type_accuracy")
SHIPPED = Path(__file__).resolve().parents[1] / "python" / "earcore" / "pose" / "weights" / "pose.onnx"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="earcore-images folder with train/test splits")
    parser.add_argument("--extra", type=Path, action="append", default=[], help="more training images (every image of this earcore-images folder), repeatable")
    parser.add_argument("--heldout", type=Path, default=None, help="earcore-images folder of held-out recordings (all of it is evaluated)")
    parser.add_argument("--networks", default="multi,cascade,keypoint")
    parser.add_argument("--minutes", type=float, default=60.0, help="training budget per network")
    parser.add_argument("--steps", type=int, default=None, help="a step budget instead (comparisons that CPU contention must not skew)")
    parser.add_argument("--preset", default="small", choices=("small", "paper"))
    parser.add_argument("--device", default="auto", choices=("cpu", "cuda", "auto"))
    parser.add_argument("--zoom", type=int, default=None, help="keypoint network: a second look at a box this many times sharper (data that many times the input)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--schedule", default="cosine", help="learning-rate schedule (exponential, cosine, linear, constant)")
    parser.add_argument("--workers", type=int, default=0, help="data-loading worker processes")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--eval-minutes", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("benches/out/pose"))
    parser.add_argument("--refine", action="store_true", help="also report the keypoint network after the kinematic fit and with PnP (needs the compiled core)")
    parser.add_argument(
        "--ship", nargs="?", const="multi", default=None, choices=("multi", "cascade", "keypoint"), help="export this network (default multi) as the shipped weights"
    )
    args = parser.parse_args()
    if args.ship is not None and args.ship not in args.networks.split(","):
        parser.error(f"--ship {args.ship}: that network is not among --networks {args.networks}")

    args.out.mkdir(parents=True, exist_ok=True)
    command = "python benches/pose_accuracy.py " + " ".join(sys.argv[1:])
    report = [f"# Robot pose from one colour image ({date.today().isoformat()})", "", f"machine: {machine()}", f"command: `{command}`", ""]
    summary: dict[str, dict] = {}
    heldout = ImageDataset(args.heldout, split=None, noise=False) if args.heldout else None
    for name in args.networks.split(","):
        train_args = [f"--data={args.data}", f"--out={args.out / name}", f"--network={name}", f"--preset={args.preset}"] + [f"--extra={e}" for e in args.extra]
        if args.zoom and name == "keypoint":
            train_args.append(f"--zoom={args.zoom}")
        budget = f"--steps={args.steps}" if args.steps else f"--minutes={args.minutes}"
        train_args += [budget, f"--batch={args.batch}", f"--schedule={args.schedule}", f"--device={args.device}", f"--workers={args.workers}"]
        train_args += [f"--eval-minutes={args.eval_minutes}", f"--seed={args.seed}"] + ([f"--threads={args.threads}"] if args.threads else [])
        config = config_from_args(build_parser().parse_args(train_args))
        started = time.perf_counter()
        result, table = run(config, args.data, args.out / name, extra=args.extra, progress=sys.stderr.isatty())
        wall = time.perf_counter() - started
        entry: dict = {"steps": result.steps, "training_minutes": result.seconds / 60, "wall_minutes": wall / 60}
        report.append(f"## {name} ({args.preset}): {result.steps} steps in {result.seconds / 60:.1f} training minutes")
        report.append("")
        if table is not None:
            entry["test"] = table.metrics
            report.append(table.markdown("test split (the papers' protocol)"))
        if heldout is not None:
            trained, _ = load_trained(args.out / name, "cpu")
            held = evaluate(trained, heldout, "cpu", robots=heldout.robots, keypoint_names=heldout.manifest.get("keypoints", {}))
            held.save(args.out / name, "heldout", f"{name}, held-out recordings")
            entry["heldout"] = held.metrics
            report.append(held.markdown("held-out recordings"))
        if name == "keypoint" and args.refine:
            # The same network's keypoints after the kinematic fit (needs the compiled core).
            trained, meta = load_trained(args.out / name, "cpu")
            test = ImageDataset(args.data, split="test", noise=False)
            sets = [("test", test, "test split")] + ([("heldout", heldout, "held-out recordings")] if heldout is not None else [])
            for key, data, label in sets:
                for mode, how in (("fit", "after the kinematic fit"), ("pnp", "the base by PnP, the joint angles known")):
                    fitted = evaluate(trained, data, "cpu", robots=data.robots, keypoint_names=meta.get("keypoints"), refined=mode)
                    fitted.save(args.out / name, f"{key}-{mode}", f"keypoint, {how}, {label}")
                    entry[f"{key}_{mode}"] = fitted.metrics
                    report.append(fitted.markdown(f"{label}, {how}"))
        summary[name] = entry
        (args.out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
        (args.out / "summary.md").write_text("\n".join(report) + "\n")
        print("\n".join(report[-3:]), flush=True)
    runs = {name: args.out / name / "metrics.jsonl" for name in summary if (args.out / name / "metrics.jsonl").is_file()}
    keys = [k for k in CURVES if any(k in r for path in runs.values() for r in read_metrics(path) if r.get("kind") == "eval")]
    if runs and keys:
        plot_comparison(runs, keys, args.out / "curves.png", title=f"{args.preset} preset, test split, {machine()}")
    if args.ship is not None and args.ship in summary:
        from earcore.pose.export import export_network

        SHIPPED.parent.mkdir(parents=True, exist_ok=True)
        network, meta = load_trained(args.out / args.ship)
        sidecar = export_network(network, meta, SHIPPED)
        print(f"onnxruntime parity: max |Δ| {max(sidecar['parity'].values()):.2e}")
        print(f"shipped weights: {SHIPPED}")
    print(f"summary: {args.out / 'summary.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
