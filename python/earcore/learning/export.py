"""ONNX export with a dynamic batch, and a parity check against onnxruntime.
onnx and onnxruntime are imported only here, when called."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

__all__ = ["export_onnx", "onnx_parity", "run_onnx"]


class _Named(torch.nn.Module):
    """A network returning a dict, as a module returning its values in `names` order."""

    def __init__(self, model: torch.nn.Module, names: Sequence[str]):
        super().__init__()
        self.model, self.names = model, list(names)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(image)
        return tuple(out[n] for n in self.names)


def export_onnx(model: torch.nn.Module, path: str | Path, input_shape: tuple[int, int, int], *, opset: int = 17) -> list[str]:
    """Export `model` (image (N, C, H, W) → dict of tensors) to `path` with input
    "image" of shape (batch, *input_shape) and one output per dict key, the batch axis
    dynamic. Returns the output names. The model is exported in eval mode."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training = model.training
    model.eval()
    try:
        device = next(model.parameters()).device
        example = torch.rand(2, *input_shape, device=device)
        with torch.no_grad():
            names = list(model(example).keys())
        wrapper = _Named(model, names)
        axes = {"image": {0: "batch"}, **{n: {0: "batch"} for n in names}}
        tmp = path.with_name(path.name + ".tmp")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and tracer notices
            torch.onnx.export(wrapper, (example,), str(tmp), input_names=["image"], output_names=names, dynamic_axes=axes, opset_version=opset, dynamo=False)
        tmp.replace(path)
    finally:
        model.train(was_training)
    return names


def run_onnx(path: str | Path, image: np.ndarray, *, threads: int | None = None) -> dict[str, np.ndarray]:
    """Run an exported network on `image` (N, C, H, W) float32 with onnxruntime."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    if threads is not None:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    values = session.run(names, {"image": np.ascontiguousarray(image, dtype=np.float32)})
    return dict(zip(names, values))


def onnx_parity(model: torch.nn.Module, path: str | Path, image: torch.Tensor | np.ndarray) -> dict[str, float]:
    """Max absolute difference per output between `model` (eval mode, CPU) and the ONNX
    file at `path`, on `image`."""
    array = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, dtype=np.float32)
    was_training = model.training
    model.eval()
    try:
        device = next(model.parameters()).device
        with torch.no_grad():
            expected = {k: v.detach().cpu().numpy() for k, v in model(torch.from_numpy(array).to(device)).items()}
    finally:
        model.train(was_training)
    got = run_onnx(path, array)
    missing = sorted(set(expected) - set(got))
    if missing:
        raise ValueError(f"{path} lacks the output(s) {missing}")
    return {k: float(np.max(np.abs(expected[k] - got[k]))) if expected[k].size else 0.0 for k in expected}
