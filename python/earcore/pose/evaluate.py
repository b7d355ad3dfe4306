"""Per-robot results in the papers' terms: mask pixel accuracy (the thresholded mask,
logit > 0, against the ground truth) and IoU (which an all-background mask cannot
game), joint error (per image the mean 3D distance over the robot's keypoints; mean
and median over images, cm), base error (cm, mean and median), type accuracy,
per-keypoint errors and inference time; a table with one column per robot (Paper IV's
Table II layout), as markdown and JSON."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from earcore.learning.train import collate, to_device
from earcore.pose.errors import PoseError
from earcore.pose.zoom import two_looks

__all__ = ["Evaluation", "check_keypoints", "evaluate", "evaluator", "inference_ms", "predict", "refine_predictions", "robot_lookup", "subset"]

ROWS = (
    ("mask_accuracy", "Mask pixel accuracy", "{:.1%}"),
    ("mask_iou", "Mask IoU", "{:.1%}"),
    ("type_accuracy", "Robot type accuracy", "{:.1%}"),
    ("joints_mean_cm", "Joint error, mean (cm)", "{:.2f}"),
    ("joints_median_cm", "Joint error, median (cm)", "{:.2f}"),
    ("base_mean_cm", "Base error, mean (cm)", "{:.2f}"),
    ("base_median_cm", "Base error, median (cm)", "{:.2f}"),
    ("inference_ms", "Inference (ms per image)", "{:.1f}"),
    ("samples", "Test images", "{:d}"),
)


@dataclass
class Evaluation:
    """Per robot name (and "all"): the metrics; per robot: the per-keypoint mean errors (cm)."""

    metrics: dict[str, dict[str, float]]
    per_keypoint_cm: dict[str, list[float]] = field(default_factory=dict)
    keypoint_names: dict[str, list[str]] = field(default_factory=dict)

    def markdown(self, title: str = "") -> str:
        columns = list(self.metrics)
        lines = [f"### {title}", ""] if title else []
        lines += ["| | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
        for key, label, fmt in ROWS:
            cells = []
            for c in columns:
                value = self.metrics[c].get(key)
                cells.append("—" if value is None or (isinstance(value, float) and not np.isfinite(value)) else fmt.format(int(value) if fmt == "{:d}" else value))
            if any(cell != "—" for cell in cells):
                lines.append(f"| {label} | " + " | ".join(cells) + " |")
        for robot, errors in self.per_keypoint_cm.items():
            names = self.keypoint_names.get(robot) or [f"kp{i}" for i in range(len(errors))]
            lines += ["", f"Per keypoint, {robot} (mean cm): " + ", ".join(f"{n} {e:.2f}" for n, e in zip(names, errors))]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON: what was not measured (NaN) is null."""
        metrics = {robot: {k: (v if np.isfinite(v) else None) for k, v in values.items()} for robot, values in self.metrics.items()}
        return {"metrics": metrics, "per_keypoint_cm": self.per_keypoint_cm, "keypoint_names": self.keypoint_names}

    def save(self, folder: str | Path, stem: str = "results", title: str = "") -> tuple[Path, Path]:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        md, js = folder / f"{stem}.md", folder / f"{stem}.json"
        md.write_text(self.markdown(title))
        js.write_text(json.dumps(self.to_dict(), indent=2, allow_nan=False, default=float) + "\n")
        return md, js


def subset(length: int, limit: int | None, seed: int = 0) -> np.ndarray:
    """Indices of `limit` images of a set of `length` drawn at random across the whole set
    (the same for the same seed), in increasing order; every index without a limit.
    Datasets are stored one robot after another: the first `limit` images would
    leave robots out."""
    if limit is None or limit >= length:
        return np.arange(length)
    return np.sort(np.random.default_rng([seed, length, limit]).choice(length, size=max(0, limit), replace=False))


def predict(
    model: torch.nn.Module, dataset: Any, device: torch.device, limit: int | None = None, batch_size: int = 32, seed: int = 0, counts: list[int] | None = None
) -> dict[str, np.ndarray]:
    """The model's outputs over `dataset` (with `limit`: that many images drawn at random
    across it, `subset`) beside the labels, as numpy arrays (the mask thresholded).
    `counts`: keypoints per robot type of the network (for a network that looks twice)."""
    indices = subset(len(dataset), limit, seed).tolist()
    n = len(indices)
    keep: dict[str, list[np.ndarray]] = {}
    was = model.training
    model.eval()
    try:
        with torch.no_grad():
            for start in range(0, n, batch_size):
                batch = to_device(collate([dataset[i] for i in indices[start : start + batch_size]]), device)
                if getattr(getattr(model, "options", None), "zoom", 1) > 1:
                    out = two_looks(model, batch["image"], batch["intrinsics"], counts)
                else:
                    out = model(batch["image"], None, batch["intrinsics"])
                parts = {
                    "mask": (out["mask_logits"] > 0)[:, 0],
                    "mask_true": batch["mask"][:, 0] > 0.5,
                    "keypoints": out["keypoints"],
                    "keypoints_true": batch["keypoints"],
                    "valid": batch["keypoint_valid"],
                    "base": out["base"],
                    "base_true": batch["base"],
                    "robot": batch["robot"],
                }
                if "type_logits" in out:
                    parts["type"] = out["type_logits"].argmax(1)
                if "pixels" in out:
                    parts["pixels"] = out["pixels"]
                    parts["intrinsics"] = batch["intrinsics"]
                    parts["joints"] = batch["joints"]
                for k, v in parts.items():
                    keep.setdefault(k, []).append(v.cpu().numpy())
    finally:
        model.train(was)
    return {k: np.concatenate(v) for k, v in keep.items()}


def _metrics(p: dict[str, np.ndarray], rows: np.ndarray) -> tuple[dict[str, float], list[float]]:
    mask, truth = p["mask"][rows], p["mask_true"][rows]
    inter = np.logical_and(mask, truth).sum()
    union = np.logical_or(mask, truth).sum()
    d = np.linalg.norm(p["keypoints"][rows] - p["keypoints_true"][rows], axis=-1)
    valid = p["valid"][rows]
    per_image = (d * valid).sum(1) / np.maximum(valid.sum(1), 1)
    per_image = per_image[valid.any(1)]
    base = np.linalg.norm(p["base"][rows] - p["base_true"][rows], axis=-1)
    out = {
        "samples": int(rows.sum()),
        "mask_accuracy": float((mask == truth).mean()),
        "mask_iou": float(inter / union) if union else 1.0,
        "joints_mean_cm": float(100 * per_image.mean()) if per_image.size else float("nan"),
        "joints_median_cm": float(100 * np.median(per_image)) if per_image.size else float("nan"),
        "base_mean_cm": float(100 * base.mean()),
        "base_median_cm": float(100 * np.median(base)),
    }
    if "type" in p:
        out["type_accuracy"] = float((p["type"][rows] == p["robot"][rows]).mean())
    per_kp = (d * valid).sum(0) / np.maximum(valid.sum(0), 1)
    return out, [float(100 * e) for e, c in zip(per_kp, valid.sum(0)) if c > 0]


#: What `refine_predictions` does with a network's 2D keypoints.
REFINEMENTS = ("fit", "pnp")
#: PnP leaves out keypoints this far (pixels) from the RANSAC consensus.
PNP_OUTLIER_PX = 4.0


def refine_predictions(p: dict[str, np.ndarray], robots: Sequence[str], frames: dict[str, list], *, starts: int = 4, mode: str = "fit") -> dict[str, np.ndarray]:
    """`p` with each image's keypoints and base replaced, for networks that give pixels
    (`earcore.pose.refine`; needs the compiled core). "fit": the robot's kinematic fit
    (joint angles and base pose) to the network's pixels and depths, the robot being the
    predicted type (the true one without a type head). "pnp": the joint angles known
    (the labels', as a robot controller reports them), the base pose by PnP on the
    pixels (DREAM's setting; outlying keypoints left out). `frames` are the dataset
    manifest's `keypoint_frames`."""
    if "pixels" not in p:
        raise ValueError("only a network with 2D keypoints (the keypoint variant) can be refined")
    if mode not in REFINEMENTS:
        raise ValueError(f"mode must be one of {', '.join(REFINEMENTS)}, got {mode!r}")
    from earcore import robots as robot_models
    from earcore.pose.refine import keypoints_in_base, pnp_base, refine

    models: dict[str, Any] = {}
    out = dict(p)
    out["keypoints"] = p["keypoints"].copy()
    out["base"] = p["base"].copy()
    kinds = p["robot"] if mode == "pnp" or "type" not in p else p["type"]
    for i, kind in enumerate(kinds.tolist()):
        name = robots[kind]
        if name not in frames:
            raise ValueError(f"the dataset's manifest has no keypoint_frames for {name} (made by an older earcore: regenerate it)")
        if name not in models:
            models[name] = robot_models.load(name)
        model = models[name]
        n = len(frames[name])
        if mode == "pnp":
            q = p["joints"][i, : model.dof].astype(np.float64)
            pixels, k = p["pixels"][i].astype(np.float64), p["intrinsics"][i].astype(np.float64)
            pose = pnp_base(model, q, pixels[:n], k, frames=frames[name], base_pixel=pixels[-1], outlier_px=PNP_OUTLIER_PX)
            points = keypoints_in_base(model, q, frames=frames[name])
            out["keypoints"][i, :n] = points @ pose[:3, :3].T + pose[:3, 3]
            out["base"][i] = pose[:3, 3]
            continue
        fit = refine(
            model,
            p["keypoints"][i, :n].astype(np.float64),
            frames=frames[name],
            base=p["base"][i].astype(np.float64),
            pixels=p["pixels"][i, :n].astype(np.float64),
            base_pixel=p["pixels"][i, -1].astype(np.float64),
            intrinsics=p["intrinsics"][i].astype(np.float64),
            starts=starts,
        )
        out["keypoints"][i, :n] = fit.keypoints
        out["base"][i] = fit.base
    return out


def check_keypoints(model: torch.nn.Module, dataset: Any) -> None:
    """A `PoseError` when a robot of the dataset has more keypoints (its manifest's
    names) than the network gives; fewer are fine (the network's extra keypoints, those
    of its robots with more joints, are left out)."""
    options = getattr(model, "options", None)
    network = getattr(options, "num_keypoints", None)
    if network is None:
        return
    names = getattr(dataset, "manifest", {}).get("keypoints", {})
    selected = list(getattr(dataset, "selected", getattr(dataset, "robots", [])))
    counts = {r: len(names[r]) for r in selected if r in names}
    if not counts and getattr(dataset, "num_keypoints", None) is not None:
        counts = {", ".join(selected) or "its robots": int(dataset.num_keypoints)}
    over = {r: c for r, c in counts.items() if c > int(network)}
    if over:
        robot, count = next(iter(over.items()))
        raise PoseError(f"the data's {robot} has {count} keypoints per image, the network gives {network}: evaluate it on data of robots with at most {network}")


def _align_keypoints(p: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Predicted and true keypoints to one count: the network's extra ones dropped, or
    the labels' beyond the network's when no image has them (a `PoseError` otherwise)."""
    k_net, k_data = p["keypoints"].shape[1], p["keypoints_true"].shape[1]
    if k_net > k_data:
        p["keypoints"] = p["keypoints"][:, :k_data]
    elif k_net < k_data:
        if p["valid"][:, k_net:].any():
            raise PoseError(f"images of the data have {k_data} keypoints, the network gives {k_net}")
        p["keypoints_true"], p["valid"] = p["keypoints_true"][:, :k_net], p["valid"][:, :k_net]
    return p


def robot_lookup(data_robots: Sequence[str], network_robots: Sequence[str], *, foreign: bool = False) -> np.ndarray:
    """For each of the dataset's robot indices, the network's index of the same robot
    (matched by name); a robot the network does not know is a `PoseError` naming it,
    or, with `foreign`, -1 (its images' type is then always wrong)."""
    unknown = [r for r in data_robots if r not in network_robots]
    if unknown and not foreign:
        raise PoseError(f"the network knows {', '.join(network_robots) or 'no robots'}, not {', '.join(unknown)} (in the data)")
    return np.array([list(network_robots).index(r) if r in network_robots else -1 for r in data_robots] or [0], dtype=np.int64)


def inference_ms(model: torch.nn.Module, image_shape: Sequence[int], device: torch.device, repeats: int = 20) -> float:
    """Median time of the forward passes for one image (torch, eval mode): one, or two for
    a network that looks twice (`earcore.pose.zoom`; the box's cut not counted)."""
    options = getattr(model, "options", None)
    looks = 2 if getattr(options, "zoom", 1) > 1 else 1
    if looks > 1:
        w, h = options.input_size  # type: ignore[union-attr]
        image_shape = (image_shape[0], h, w)
    x = torch.rand(1, *image_shape, device=device)
    was = model.training
    model.eval()
    times = []
    try:
        with torch.no_grad():
            for i in range(repeats + 3):
                t = time.perf_counter()
                for _ in range(looks):
                    model(x)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                if i >= 3:
                    times.append(time.perf_counter() - t)
    finally:
        model.train(was)
    return float(1000 * np.median(times))


def evaluate(
    model: torch.nn.Module,
    dataset: Any,
    device: torch.device | str = "cpu",
    *,
    limit: int | None = None,
    robots: Sequence[str] | None = None,
    keypoint_names: dict[str, list[str]] | None = None,
    timing: bool = True,
    refined: str | bool | None = None,
    foreign: bool = False,
) -> Evaluation:
    """Metrics per robot and over all images of `dataset` (`limit`: that many drawn at
    random, `subset`). `robots` are the network's robots (its type head's classes, in
    order; default: the dataset's `.robots`): the dataset's robots are matched to them by
    name, and a robot the network does not know, or another number of keypoints than
    the network gives, is a `PoseError`; with `foreign`, images of robots the network
    does not know are evaluated too (their type counts as wrong: what a network that
    forgot a robot still sees). `refined`: after the kinematic fit ("fit", or True) or
    PnP with the joint angles known ("pnp"): `refine_predictions`."""
    device = torch.device(device)
    names = list(robots if robots is not None else getattr(dataset, "robots", []))
    check_keypoints(model, dataset)
    data_names = list(getattr(dataset, "robots", names))
    robot_lookup(list(getattr(dataset, "selected", data_names)), names, foreign=foreign)  # the robots of the images evaluated
    lookup = robot_lookup(data_names, names, foreign=True)
    given = getattr(dataset, "manifest", {}).get("keypoints", {})
    counts = [len(given.get(name, [])) or int(getattr(model, "K", 0)) for name in names] or None
    p = _align_keypoints(predict(model, dataset, device, limit, counts=counts))
    shown = p["robot"].copy()  # the dataset's robot indices
    p["robot"] = lookup[shown]
    mode = "fit" if refined is True else (refined or None)
    if mode is not None:
        if (p["robot"] < 0).any():
            raise PoseError("refinement needs each image's robot among the network's (the kinematics are the robot's)")
        p = refine_predictions(p, names, getattr(dataset, "manifest", {}).get("keypoint_frames", {}), mode=mode)
    ms = inference_ms(model, dataset[0]["image"].shape, device) if timing else float("nan")
    metrics: dict[str, dict[str, float]] = {}
    per_keypoint: dict[str, list[float]] = {}
    for r in sorted(set(shown.tolist())):
        name = data_names[r] if r < len(data_names) else f"robot {r}"
        metrics[name], per_keypoint[name] = _metrics(p, shown == r)
        metrics[name]["inference_ms"] = ms
    metrics["all"], _ = _metrics(p, np.ones(len(p["robot"]), bool))
    metrics["all"]["inference_ms"] = ms
    return Evaluation(metrics, per_keypoint, dict(keypoint_names or {}))


def evaluator(model: torch.nn.Module, dataset: Any, device: torch.device, limit: int | None) -> dict[str, float]:
    """For the training loop's periodic evaluation: the "all" metrics (no timing)."""
    result = evaluate(model, dataset, device, limit=limit, timing=False).metrics["all"]
    return {k: float(v) for k, v in result.items() if k not in ("inference_ms",)}
