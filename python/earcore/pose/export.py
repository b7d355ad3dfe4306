"""A trained pose network as ONNX plus its sidecar JSON (what `earcore.pose.estimate`
needs to use it without torch), checked against onnxruntime."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from earcore.learning.export import export_onnx, onnx_parity
from earcore.pose.networks import PoseNetwork

__all__ = ["SIDECAR_FORMAT", "export_network", "sidecar_path"]

SIDECAR_FORMAT = "earcore-pose-onnx"


def sidecar_path(onnx_path: str | Path) -> Path:
    return Path(onnx_path).with_suffix(".json")


def export_network(network: PoseNetwork, meta: dict[str, Any], path: str | Path, *, check: bool = True, seed: int = 0) -> dict[str, Any]:
    """Write `path` (.onnx) and its sidecar (.json); returns the sidecar, with the
    parity check's max abs difference per output under "parity" when `check`."""
    path = Path(path)
    w, h = network.options.input_size
    network = network.cpu().eval()
    outputs = export_onnx(network, path, (3, h, w))
    sidecar: dict[str, Any] = {
        "format": SIDECAR_FORMAT,
        "version": 1,
        "network": network.name,
        "options": network.options.to_dict(),
        "input_size": [w, h],
        "intrinsics": network.intrinsics().tolist(),
        "robots": list(meta.get("robots", [])),
        "keypoints": meta.get("keypoints", {}),
        # where each keypoint sits on the robot, for `refine(..., frames=...)`
        "keypoint_frames": meta.get("keypoint_frames", {}),
        "num_keypoints": network.K,
        "outputs": outputs,
    }
    if check:
        image = torch.rand(4, 3, h, w, generator=torch.Generator().manual_seed(seed))
        sidecar["parity"] = onnx_parity(network, path, image)
    tmp = sidecar_path(path).with_name(sidecar_path(path).name + ".tmp")
    tmp.write_text(json.dumps(sidecar, indent=2) + "\n")
    tmp.replace(sidecar_path(path))
    return sidecar
