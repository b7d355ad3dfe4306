"""Transfer learning for the pose networks (Papers VI and VII): start from a network
trained on other robots, keep what fits, and name which parts train.

`transfer_weights` copies every tensor of the trained network whose shape the new one
shares (the output scaling and camera included) and adapts the output layers whose
size follows the robots: the type head's rows are matched by robot name (an old robot
keeps its row, a new one starts fresh: "robot type becomes a class more"), the
keypoint rows by keypoint index (a 7-joint robot's extra joint starts fresh). Every
other tensor of another shape keeps its fresh initialisation, and the report says so.

`TRAINABLE` names the parts that train, per network:
- ``paper-vi``: Paper VI, the fully connected layers, the output layers and the mask
  branch's last two convolutions;
- ``dense``: Paper VII's stage 1, the dense layers only;
- ``late``: Paper VII's stage 2, the dense layers and the later convolutions (the
  blue branch and the mask branch after its shared part; the first convolutions stay);
- ``all``: everything.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from earcore.errors import ConfigError
from earcore.pose.networks import PoseNetwork

__all__ = ["TRAINABLE", "Transferred", "trainable_modules", "transfer_weights"]

_DENSE = {
    "multi": ["blue_fc", "green_fc", "joints_head", "type_head", "base_head"],
    "keypoint": ["heat", "depth", "type_head"],
    "cascade": ["fc"],
}
_LATE = {
    "multi": ["blue", "red_b", "mask_out"],
    "keypoint": ["down8", "merge", "mask_out"],
    "cascade": ["joint_net"],
}

TRAINABLE = ("all", "paper-vi", "dense", "late")


def trainable_modules(network: PoseNetwork, trainable: str | Sequence[str]) -> list[str]:
    """The module paths that train: `TRAINABLE` names and module paths, in any mix."""
    parts = [trainable] if isinstance(trainable, str) else [str(p) for p in trainable]
    out: list[str] = []
    for part in parts:
        for path in _named_set(network, part) if part in TRAINABLE else [part]:
            if path not in out:
                out.append(path)
    return out


def _named_set(network: PoseNetwork, name: str) -> list[str]:
    if name == "all":
        return [""]
    dense = list(_DENSE.get(network.name, []))
    if name == "dense":
        return dense
    if name == "late":
        return dense + list(_LATE.get(network.name, []))
    if network.name != "multi":
        raise ConfigError(f"paper-vi names Paper V's layers; the {network.name} network has other ones (use dense, late, all or module paths)")
    last_red = len(network.red_b) - 1  # type: ignore[arg-type]
    return dense + ([f"red_b.{last_red}"] if last_red >= 0 else []) + ["mask_out"]


@dataclass
class Transferred:
    copied: list[str] = field(default_factory=list)
    adapted: dict[str, str] = field(default_factory=dict)
    fresh: list[str] = field(default_factory=list)

    def describe(self) -> str:
        parts = [f"{len(self.copied)} tensors copied"]
        if self.adapted:
            parts.append("adapted: " + "; ".join(f"{k} ({v})" for k, v in self.adapted.items()))
        if self.fresh:
            parts.append("fresh: " + ", ".join(self.fresh))
        return ", ".join(parts)


def _row_pairs(network: str, key: str, old: Mapping[str, Any], new_robots: Sequence[str], k_old: int, k_new: int) -> tuple[list[tuple[int, int]], str] | None:
    """(new row, old row) pairs for an output layer whose rows follow robots or keypoints."""
    if key.startswith("type_head.2."):
        old_robots = list(old.get("robots", []))
        pairs = [(i, old_robots.index(r)) for i, r in enumerate(new_robots) if r in old_robots]
        kept = [new_robots[i] for i, _ in pairs]
        return pairs, f"robots kept: {', '.join(kept) or 'none'}; new: {', '.join(r for r in new_robots if r not in kept) or 'none'}"
    shared = min(k_old, k_new)
    if network == "multi" and key.startswith("joints_head.2."):
        return [(3 * k + a, 3 * k + a) for k in range(shared) for a in range(3)], f"keypoints 1-{shared} of {k_new}"
    if network == "cascade" and key.startswith("fc.2."):
        base = [(3 * k_new + a, 3 * k_old + a) for a in range(3)]
        return [(3 * k + a, 3 * k + a) for k in range(shared) for a in range(3)] + base, f"keypoints 1-{shared} of {k_new} and the base"
    if network == "keypoint" and (key.startswith("heat.") or key.startswith("depth.")):
        return [(k, k) for k in range(shared)] + [(k_new, k_old)], f"keypoints 1-{shared} of {k_new} and the base"
    return None


def transfer_weights(network: PoseNetwork, state: Mapping[str, torch.Tensor], meta: Mapping[str, Any], robots: Sequence[str]) -> Transferred:
    """Load what fits of a trained network's `state` (its checkpoint `meta`: robots,
    options) into `network`, built for `robots`."""
    old_options = dict(meta.get("options", {}))
    if meta.get("network") not in (None, network.name):
        raise ConfigError(f"the checkpoint holds a {meta.get('network')} network, not a {network.name} network")
    ours = network.state_dict()
    old_size = tuple(old_options.get("input_size", network.options.input_size))
    if old_size != tuple(network.options.input_size):
        raise ConfigError(
            f"the checkpoint's network reads {old_size[0]}×{old_size[1]} images, this data is {network.options.input_size[0]}×{network.options.input_size[1]}"
        )
    k_old = int(old_options.get("num_keypoints", network.K))
    report = Transferred()
    merged = dict(ours)
    for key, value in ours.items():
        if key not in state:
            report.fresh.append(key)
            continue
        theirs = state[key]
        rows = _row_pairs(network.name, key, meta, robots, k_old, network.K)
        if rows is not None and theirs.shape[1:] == value.shape[1:]:
            pairs, what = rows
            target = value.detach().clone()
            for new_row, old_row in pairs:
                target[new_row] = theirs[old_row]
            merged[key] = target
            if all(a == b for a, b in pairs) and theirs.shape == value.shape and len(pairs) == value.shape[0]:
                report.copied.append(key)
            else:
                report.adapted[key] = what
        elif theirs.shape == value.shape:
            merged[key] = theirs.detach().clone().to(value.dtype)
            report.copied.append(key)
        else:
            report.fresh.append(key)
    network.load_state_dict(merged)
    return report
