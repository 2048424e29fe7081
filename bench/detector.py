"""Detector latency: ONNX Runtime ms per frame (median after warm-up) for one (1, 1, S, S) input, fp32 on
CPU with a fixed thread count and, where the CUDA or TensorRT providers exist, fp16 (and fp32) on them; plus MACs.
`cpu_fp32_throughput` compares, in the same run, frames/s of one inference at a time with `threads` threads
against `workers` single-threaded inferences side by side (how the detect service runs on a CPU).
The load average is recorded: on a shared machine the CPU numbers are upper bounds.
Without --model an untrained default model (or --stride variant) is exported and timed, labelled
untrained-for-timing-only. Prints one JSON document; every timing in it names its input shape (`input`).

The target (`target`: 25 ms median on the CPU, fp32) is the project issue's, per 512x512 frame: the default
input (`target.applies_to` is null when another input was timed). The detect service feeds the network something
else: a whole frame shrunk so that its longer side is the model's `input_long_side`, padded to 32 pixels
(`shared.inference.OnnxDetector.input_shape`): 640x480 for a 1280x960 camera and a 640 px model. `deployed` times
that input too (one inference at a time on the CPU, fp32, `threads` threads; its MACs) for a frame of `--frame`
(default 1280x960, the simulated cameras). A camera with a `detect_area_px` runs a crop of it instead (576x480 for
the simulated fisheye cameras: time it with --size/--height).

    python -m bench.detector [--model detector.onnx] [--model-fp16 detector_fp16.onnx] [--size 512]
                             [--height H] [--threads 2] [--workers 2] [--runs 50] [--warmup 10] [--stride 4]
                             [--frame 1280x960]

--height makes the input S wide and H high (a fisheye frame at full resolution: --size 1280 --height 960).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from bench import bench_parser
from shared.decode import CONFIG_KEY
from shared.jsonio import dumps
from training.export import INPUT_NAME, export_onnx
from training.model import Detector, DetectorConfig, count_macs

GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")
TARGET_MS = 25.0  # the target: median ms per 512x512 frame on the CPU, fp32
TARGET_HW = (512, 512)
DEFAULT_FRAME_WH = (1280, 960)  # the simulated cameras' full resolution (4:3)


@dataclass(frozen=True)
class BenchSettings:
    """model / model_fp16: exported files (None: export an untrained model with `stride`)."""

    model: Path | None = None
    model_fp16: Path | None = None
    size_px: int = 512
    threads: int = 2
    runs: int = 50
    warmup: int = 10
    stride: int = 4
    height_px: int | None = None  # None: square (size_px)
    workers: int = 2
    frame_wh: tuple[int, int] = DEFAULT_FRAME_WH  # the camera frame whose deployed network input is timed too

    @property
    def hw(self) -> tuple[int, int]:
        return (self.size_px if self.height_px is None else self.height_px, self.size_px)

    def __post_init__(self) -> None:
        """ValueError naming the setting and its flag."""
        for name, flag in (("size_px", "--size"), ("height_px", "--height")):
            v = getattr(self, name)
            if v is not None and (v % 32 or v < 32):
                raise ValueError(f"{name} ({flag}) must be a positive multiple of 32, got {v}")
        for name in ("threads", "runs", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} (--{name}) must be >= 1, got {getattr(self, name)}")
        if self.warmup < 0:
            raise ValueError(f"warmup (--warmup) must be >= 0, got {self.warmup}")
        if len(self.frame_wh) != 2 or min(self.frame_wh) < 1:
            raise ValueError(f"frame_wh (--frame) must be a width and a height >= 1, got {self.frame_wh}")
        if self.model_fp16 is not None and self.model is None:
            raise ValueError("model_fp16 (--model-fp16) goes with model (--model): without a model an untrained one "
                             "is exported and timed with its own fp16 copy")


def time_session(session: ort.InferenceSession, image: np.ndarray, runs: int, warmup: int) -> dict:
    """Median, mean and 90th-percentile ms of session.run over `runs` calls after `warmup` calls."""
    for _ in range(warmup):
        session.run(None, {INPUT_NAME: image})
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        session.run(None, {INPUT_NAME: image})
        times.append((time.perf_counter() - t0) * 1e3)
    return {"median_ms": round(statistics.median(times), 2), "mean_ms": round(statistics.fmean(times), 2),
            "min_ms": round(min(times), 2),
            "p90_ms": round(float(np.percentile(times, 90)), 2), "runs": runs}


def side_by_side_fps(path: Path, image: np.ndarray, workers: int, runs: int, warmup: int) -> float:
    """Frames/s of `workers` single-threaded inferences of one session run side by side (a thread pool;
    ONNX Runtime releases the GIL), over `runs` frames per worker after `warmup` each."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda _: session.run(None, {INPUT_NAME: image}), range(warmup * workers)))
        t0 = time.perf_counter()
        list(pool.map(lambda _: session.run(None, {INPUT_NAME: image}), range(runs * workers)))
        return runs * workers / (time.perf_counter() - t0)


def run(settings: BenchSettings, workdir: Path) -> dict:
    """Time the model(s) named in settings, exporting into workdir when none is given."""
    h, w = settings.hw
    out: dict = {"benchmark": "detector", "input": [1, 1, h, w],
                 "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
                 "load_average_1min": round(os.getloadavg()[0], 2), "onnxruntime": ort.__version__}
    fp32, fp16 = settings.model, settings.model_fp16
    if fp32 is None:
        model = Detector(DetectorConfig(stride=settings.stride))
        fp32, fp16 = workdir / "detector.onnx", workdir / "detector_fp16.onnx"
        export_onnx(model, fp32, fp16 if set(GPU_PROVIDERS) & set(ort.get_available_providers()) else None,
                    (h, w))
        out["model"] = "untrained-for-timing-only"
    else:
        out["model"] = str(fp32)
    options = ort.SessionOptions()
    options.intra_op_num_threads = settings.threads
    options.inter_op_num_threads = 1
    try:
        session = ort.InferenceSession(str(fp32), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for a missing or bad file
        raise ValueError(f"{fp32}: not a loadable ONNX model ({str(e).splitlines()[0][:300]})") from None
    meta = session.get_modelmeta().custom_metadata_map
    if CONFIG_KEY not in meta:
        raise ValueError(f"{fp32}: model metadata has no {CONFIG_KEY!r} (export it with `roadside export`)")
    config = DetectorConfig(**json.loads(meta[CONFIG_KEY]))
    out["config"] = asdict(config)
    out["macs"] = count_macs(Detector(config), h, w)
    # the target is per 512x512 frame: it applies to cpu_fp32 only when that is the input timed
    out["target"] = {"cpu_fp32_median_ms": TARGET_MS, "input": [1, 1, *TARGET_HW],
                     "applies_to": "cpu_fp32" if (h, w) == TARGET_HW else None}
    image = np.random.default_rng(0).random((1, 1, h, w), dtype=np.float32)
    out["cpu_fp32"] = {"input": out["input"], "threads": settings.threads,
                       **time_session(session, image, settings.runs, settings.warmup)}
    one = 1000.0 / out["cpu_fp32"]["mean_ms"]
    side = side_by_side_fps(fp32, image, settings.workers, settings.runs, settings.warmup)
    out["cpu_fp32_throughput"] = {"input": out["input"], f"one_at_a_time_{settings.threads}_threads_fps": round(one, 1),
                                  f"{settings.workers}_workers_1_thread_fps": round(side, 1),
                                  "ratio": round(side / one, 3)}
    long_side, dh, dw = deployed_input(fp32, settings.frame_wh)
    out["deployed"] = {"frame": [settings.frame_wh[1], settings.frame_wh[0]], "input_long_side": long_side,
                       "input": [1, 1, dh, dw], "macs": count_macs(Detector(config), dh, dw)}
    if (dh, dw) == (h, w):  # already timed above
        out["deployed"]["cpu_fp32"] = out["cpu_fp32"]
    else:
        deployed = np.random.default_rng(0).random((1, 1, dh, dw), dtype=np.float32)
        out["deployed"]["cpu_fp32"] = {"input": [1, 1, dh, dw], "threads": settings.threads,
                                       **time_session(session, deployed, settings.runs, settings.warmup)}
    gpu_providers = [p for p in GPU_PROVIDERS if p in ort.get_available_providers()]
    if gpu_providers:
        out["gpu"] = gpu_name()
    for provider in gpu_providers:
        name = provider.removesuffix("ExecutionProvider").lower()
        for precision, path in (("fp16", fp16), ("fp32", fp32)):
            if path is not None:
                out[f"{name}_{precision}"] = {"input": out["input"],
                                              **time_gpu(path, provider, image, settings.runs, settings.warmup)}
    return out


def deployed_input(path: Path, frame_wh: tuple[int, int]) -> tuple[int, int, int]:
    """(the model's input_long_side, height, width of the network input) that the detect service gives the model at
    `path` for a whole camera frame of `frame_wh` (width, height) pixels (`OnnxDetector.input_shape`)."""
    from shared.inference import OnnxDetector

    detector = OnnxDetector(path, providers=["CPUExecutionProvider"], threads=1)
    _, h, w = detector.input_shape(frame_wh[1], frame_wh[0])
    return detector.long_side, h, w


def time_gpu(path: Path, provider: str, image: np.ndarray, runs: int, warmup: int) -> dict:
    """time_session on `provider`, or why it could not run there. A provider that ONNX Runtime lists can
    still fail to load (TensorRT without its libraries, a CUDA mismatch): ONNX Runtime then falls back to
    the CPU, and a CPU time must not be reported as the GPU's."""
    try:
        session = ort.InferenceSession(str(path), providers=[provider])
    except Exception as e:  # any load failure is reported, not raised
        return {"skipped": f"{provider} failed to load {path.name}: {str(e).splitlines()[0][:300]}"}
    if session.get_providers()[0] != provider:
        return {"skipped": f"{provider} unavailable; ONNX Runtime chose {session.get_providers()}"}
    return {"input_output": "numpy on the host (copies to and from the GPU included)",
            **time_session(session, image, runs, warmup)}


def gpu_name() -> str | None:
    """The first GPU nvidia-smi names, or None."""
    try:
        run = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return run.stdout.strip().splitlines()[0] if run.stdout.strip() else None


def main(argv: list[str] | None = None) -> int:
    settings = _parse(argv)
    with tempfile.TemporaryDirectory() as tmp:
        print(dumps(run(settings, Path(tmp)), indent=1))
    return 0


def _parse(argv: list[str] | None = None) -> BenchSettings:
    p = bench_parser("detector", __doc__, argv)
    p.add_argument("--model", type=Path, help="exported fp32 ONNX model (default: untrained, for timing only)")
    p.add_argument("--model-fp16", type=Path, help="its fp16 copy, timed on CUDA / TensorRT where available")
    p.add_argument("--size", type=int, default=512, help="input width (and height, without --height) in pixels")
    p.add_argument("--height", type=int, help="input height in pixels (default: --size)")
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime intra-op threads on CPU")
    p.add_argument("--workers", type=int, default=2, help="single-threaded inferences side by side (throughput)")
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--stride", type=int, default=4, help="output stride of the untrained model")
    p.add_argument("--frame", type=_frame, default=DEFAULT_FRAME_WH, metavar="WxH",
                   help="camera frame whose deployed network input (the model's input_long_side) is timed too "
                        "(default 1280x960)")
    a = p.parse_args(argv)
    return BenchSettings(a.model, a.model_fp16, a.size, a.threads, a.runs, a.warmup, a.stride, a.height, a.workers,
                         a.frame)


def _frame(text: str) -> tuple[int, int]:
    """`WxH` -> (W, H), both whole numbers >= 1."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1280x960, got {text!r}") from None
    if min(w, h) < 1:
        raise argparse.ArgumentTypeError(f"width and height must be >= 1, got {text!r}")
    return w, h


if __name__ == "__main__":
    raise SystemExit(main())
