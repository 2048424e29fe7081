"""ONNX export of the detector (fp32, and fp16 with fp32 inputs and outputs) and a PyTorch / ONNX Runtime
parity check on decoded detections."""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from shared.decode import CONFIG_KEY, Detections, decode, model_stride
from training.model import Detector, ExportWrapper

OPSET = 17
INPUT_NAME = "image"
PARITY_UV_PX = 0.5
PARITY_SCORE_FP32 = 1e-3
PARITY_SCORE_FP16 = 0.02


def export_onnx(model: Detector, path_fp32: str | Path, path_fp16: str | Path | None,
                input_hw: tuple[int, int] = (512, 512)) -> None:
    """Write the export graph (input "image" (B, 1, H, W) float in [0, 1], outputs ExportWrapper.outputs) with
    dynamic batch, height and width; then an fp16 copy with fp32 inputs and outputs unless path_fp16 is None.
    input_hw is the tracing size (multiples of 32)."""
    wrapper = ExportWrapper(model)
    was_training = model.training
    model.eval()
    dynamic = {INPUT_NAME: {0: "batch", 2: "height", 3: "width"}}
    dynamic |= {name: {0: "batch", 2: "out_height", 3: "out_width"} for name in wrapper.outputs}
    try:
        with torch.no_grad(), warnings.catch_warnings():
            # the torch.export-based exporter needs onnxscript, which this project does not install
            warnings.filterwarnings("ignore", "You are using the legacy TorchScript-based ONNX export")
            warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.onnx")
            torch.onnx.export(wrapper, (torch.zeros(1, 1, *input_hw),), str(path_fp32), input_names=[INPUT_NAME],
                              output_names=list(wrapper.outputs), dynamic_axes=dynamic, opset_version=OPSET,
                              dynamo=False)
    finally:
        model.train(was_training)
    proto = onnx.load(str(path_fp32))
    onnx.helper.set_model_props(proto, {CONFIG_KEY: json.dumps(asdict(model.config))})
    onnx.save(proto, str(path_fp32))
    if path_fp16 is not None:
        from onnxconverter_common import float16  # optional dependency: only the fp16 copy needs it

        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "the float32 number .* will be truncated to")  # tiny weights -> 1e-7
            onnx.save(float16.convert_float_to_float16(proto, keep_io_types=True), str(path_fp16))


def _decode_batch(names: tuple[str, ...], outputs: list[np.ndarray], stride: int, score_thr: float) -> list[Detections]:
    return [decode(**{n: o[i] for n, o in zip(names, outputs, strict=True)}, stride=stride, score_thr=score_thr)
            for i in range(len(outputs[0]))]


def _match(ref: Detections, got: Detections, score_tol: float) -> bool:
    """Same count and, greedily by reference score, each reference detection has its own detection within
    PARITY_UV_PX whose score is within score_tol."""
    if len(ref) != len(got):
        return False
    free = np.ones(len(got), bool)
    for uv, score in zip(ref.uv, ref.score, strict=True):
        dist = np.where(free, np.linalg.norm(got.uv - uv, axis=1), np.inf)
        j = int(np.argmin(dist))
        if dist[j] > PARITY_UV_PX or abs(got.score[j] - score) > score_tol:
            return False
        free[j] = False
    return True


def parity(model: Detector, fp32_path: str | Path, fp16_path: str | Path | None, images: np.ndarray,
           score_thr: float = 0.3) -> dict:
    """Compare PyTorch with ONNX Runtime (CPU) fp32 and fp16 on images (N, H, W) uint8 grey (H, W multiples
    of 32): max abs heat-map difference and whether the decoded detections match (uv within PARITY_UV_PX,
    score within PARITY_SCORE_FP32 / PARITY_SCORE_FP16)."""
    if images.ndim != 3 or images.dtype != np.uint8:
        raise ValueError(f"images must be (N, H, W) uint8, got {images.shape} {images.dtype}")
    x = images[:, None].astype(np.float32) / 255.0
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            wrapper = ExportWrapper(model)
            ref_out = [t.numpy() for t in wrapper(torch.from_numpy(x))]
    finally:
        model.train(was_training)
    stride = model.config.stride
    ref = _decode_batch(wrapper.outputs, ref_out, stride, score_thr)
    report: dict = {"images": len(images), "detections_torch": sum(len(d) for d in ref)}
    for label, path, tol in (("fp32", fp32_path, PARITY_SCORE_FP32), ("fp16", fp16_path, PARITY_SCORE_FP16)):
        if path is None:
            continue
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1  # a correctness check: one thread is deterministic and never waits
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        names = tuple(o.name for o in session.get_outputs())
        out = session.run(list(names), {INPUT_NAME: x})
        got = _decode_batch(names, out, model_stride(session.get_modelmeta().custom_metadata_map), score_thr)
        report[f"heat_max_abs_diff_{label}"] = float(np.max(np.abs(out[0] - ref_out[0])))
        report[f"detections_{label}"] = sum(len(d) for d in got)
        report[f"detections_match_{label}"] = all(_match(r, g, tol) for r, g in zip(ref, got, strict=True))
    return report
