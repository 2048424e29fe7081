"""Run an exported detector (ONNX) on one image: bring it to the scale the model was trained at (the
camera's full-resolution image shrunk so its longer side is at most the model's input size), pad to a
multiple of 32, infer with ONNX Runtime, decode, and map the detections back to the given image's pixels.
NumPy, OpenCV and ONNX Runtime only (no PyTorch): the detect service uses this.

Execution providers are chosen at start from what the installed ONNX Runtime offers, in the order
TensorRT -> CUDA -> CPU unless given; an fp16 model is meant for GPUs, the fp32 one for CPUs (fp16 runs
slower on CPU execution providers).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from shared.decode import CONFIG_KEY, PAD_MULTIPLE, Detections, decode, detector_config
from shared.heads_calibration import BOX_CALIBRATION_KEY, SIZE_CALIBRATION_KEY, BoxCalibration, SizeCalibration
from shared.settings import MAX_THREADS

DEFAULT_LONG_SIDE = 640  # a model's input_long_side where its metadata has none
AREA_CONTEXT_PX = 32  # network pixels of the image kept around a camera's detect area (see `OnnxDetector.detect`)
PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")


def available_providers(wanted: tuple[str, ...] = PREFERRED_PROVIDERS) -> list[str]:
    import onnxruntime as ort

    have = set(ort.get_available_providers())
    return [p for p in wanted if p in have]


OUTPUT_NAMES = {"heat", "size", "heading", "vtype_prob", "offset", "axis", "vote"}
# the output channels that change sign when the image is mirrored left to right: the x of the bottom centre's and
# the box centre's offsets, the x of the heading vector, the sin(2a) of the axis (a -> pi - a), the x of the vote
MIRROR_NEGATED = {"offset": (0, 2), "heading": (0,), "axis": (1,), "vote": (0,)}


def mirror_average(outputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The output maps of a batch of two, an image and its left-right mirror, as one image's: the mirror's maps
    turned back (columns reversed, x-like channels negated) and averaged with the image's (test-time flip)."""
    out = {}
    for name, o in outputs.items():
        back = o[1][..., ::-1].copy()
        for c in MIRROR_NEGATED.get(name, ()):
            back[c] = -back[c]
        out[name] = 0.5 * (o[0] + back)
    return out


def input_scale(width: int, height: int, long_side: int) -> float:
    """Resize factor that brings an image's longer side down to `long_side` (1.0 if it is no longer:
    enlarging adds compute, not detail). Training (`training.train`) and the detect service both use it."""
    return min(1.0, long_side / max(width, height))


def runtime_errors() -> tuple[type[Exception], ...]:
    """ONNX Runtime's own exception types (InvalidArgument, Fail, RuntimeException, ...: they derive from Exception
    only, not from ValueError), for catching what one inference raises."""
    from onnxruntime.capi import onnxruntime_pybind11_state as state

    return tuple(v for v in vars(state).values() if isinstance(v, type) and issubclass(v, Exception))


def check_input(inputs: list, path: Path, batch: int) -> str:
    """The name of a model's one input, a (batch, 1, height, width) float grey image with free height and width
    (frames and detect areas come in any size) and a free batch or one of `batch` (2 for `mirror`); ValueError naming
    the file otherwise, at start rather than at the first frame. A free dimension: a name, or None / -1."""
    if len(inputs) != 1:
        raise ValueError(f"{path}: {len(inputs)} inputs {[i.name for i in inputs]}, a detector has one (its image)")
    name, shape, dtype = inputs[0].name, inputs[0].shape, inputs[0].type

    def free(d) -> bool:
        return not isinstance(d, int) or d < 0

    wrong = []
    if dtype != "tensor(float)":
        wrong.append(f"its type is {dtype}, not tensor(float)")
    if len(shape) != 4:
        wrong.append(f"it has {len(shape)} dimensions, not 4 (batch, 1, height, width)")
    else:
        if not free(shape[0]) and shape[0] != batch:
            mirror = " (mirror infers a batch of 2: the image and its mirror)" if batch == 2 else ""
            wrong.append(f"its batch is fixed at {shape[0]}{mirror}")
        if shape[1] != 1:
            wrong.append(f"its channels are {shape[1]!r}, not 1 (a grey image)")
        if not (free(shape[2]) and free(shape[3])):
            wrong.append("its height and width are fixed (frames and detect areas come in any size: export it "
                         "with free height and width)")
    if wrong:
        raise ValueError(f"{path}: input {name!r} {list(shape)} is not a detector's: {'; '.join(wrong)}")
    return name


class OnnxDetector:
    """An exported detector. `detect(grey)` -> Detections in the image's own pixels."""

    def __init__(self, path: str | Path, providers: list[str] | None = None, threads: int = 2,
                 score_thr: float = 0.3, top_k: int = 200, spin: bool = True, mirror: bool = False,
                 votes: bool = False, calibrated_heads: bool = True) -> None:
        """`calibrated_heads`: apply the model's box and size calibrations (shared/heads_calibration.py, in its
        metadata when they were fitted) to the decoded 2D boxes and sizes; False gives the heads' own."""
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise ValueError(f"detector model not found: {path}")
        if not (isinstance(threads, int) and 1 <= threads <= MAX_THREADS):
            raise ValueError(f"threads must be a whole number from 1 to {MAX_THREADS}, got {threads!r}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        # spin=False: worker threads sleep between jobs instead of busy-waiting (see shared/settings.py)
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=providers or available_providers())
        except Exception as e:  # onnxruntime raises its own exception types for bad files
            raise ValueError(f"{path}: not a loadable ONNX model ({e})") from e
        meta = self.session.get_modelmeta().custom_metadata_map
        if CONFIG_KEY not in meta:
            raise ValueError(f"{path}: model metadata has no {CONFIG_KEY!r} (export it with `roadside export`)")
        self.config = detector_config(meta[CONFIG_KEY], path)
        self.size_calibration = self.box_calibration = None
        if calibrated_heads and SIZE_CALIBRATION_KEY in meta:
            self.size_calibration = SizeCalibration.from_json(meta[SIZE_CALIBRATION_KEY], f"{path}: metadata")
        if calibrated_heads and BOX_CALIBRATION_KEY in meta:
            self.box_calibration = BoxCalibration.from_json(meta[BOX_CALIBRATION_KEY], f"{path}: metadata")
            types = self.config.get("num_types", self.box_calibration.num_types)
            if self.box_calibration.num_types != types:
                raise ValueError(f"{path}: metadata: the box calibration is for {self.box_calibration.num_types} "
                                 f"vehicle types, the model has {types}")
        self.stride = self.config["stride"]
        self.long_side = self.config.get("input_long_side", DEFAULT_LONG_SIDE)
        self.output_names = tuple(o.name for o in self.session.get_outputs())
        missing = {"heat", "size", "heading", "vtype_prob", "offset"} - set(self.output_names)
        if missing or not set(self.output_names) <= OUTPUT_NAMES:
            raise ValueError(f"{path}: outputs {list(self.output_names)} are not a detector's "
                             f"(heat, size, heading, vtype_prob, offset and optionally axis, vote)")
        self.input_name = check_input(self.session.get_inputs(), path, 2 if mirror else 1)
        self.path = path
        self.score_thr = score_thr
        self.top_k = top_k
        self.mirror = mirror  # infer the image and its mirror as a batch of two and average (`mirror_average`)
        self.votes = votes  # a model with a vote head: decoding moves peaks far from their centre (shared/decode.py)

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def input_shape(self, height: int, width: int, source_scale: float = 1.0) -> tuple[float, int, int]:
        """(scale, network height, network width) for an image of this size that is a copy of the camera's
        image at `source_scale` of its full size (ingest may decode at 1/2 or 1/4). The network sees what it
        was trained on: the full-size image shrunk to at most `long_side`; a copy decoded smaller than that
        is enlarged back to it (scale > 1: the vehicles keep the size the model learnt, the detail is lost)."""
        scale = self.scale_for(height, width, source_scale)
        h, w = round(height * scale), round(width * scale)
        return scale, -(-h // PAD_MULTIPLE) * PAD_MULTIPLE, -(-w // PAD_MULTIPLE) * PAD_MULTIPLE

    def scale_for(self, height: int, width: int, source_scale: float = 1.0) -> float:
        """The resize factor from an image of this size (a copy of the camera's at `source_scale`) to the network
        input (`input_shape`)."""
        if not source_scale > 0:
            raise ValueError(f"source_scale must be > 0, got {source_scale!r}")
        full_w, full_h = width / source_scale, height / source_scale
        scale = input_scale(round(full_w), round(full_h), self.long_side) / source_scale
        return 1.0 if abs(scale - 1.0) < 1e-6 else scale

    def preprocess(self, grey: np.ndarray, source_scale: float = 1.0,
                   scale: float | None = None) -> tuple[np.ndarray, float]:
        """(1, 1, H, W) float32 network input and the resize factor (`scale`: given, e.g. the whole image's for a
        part of it; default that of `grey` itself)."""
        if grey.ndim != 2 or grey.dtype != np.uint8:
            raise ValueError(f"detector input must be a (H, W) uint8 grey image, got {grey.shape} {grey.dtype}")
        if scale is None:
            scale = self.scale_for(*grey.shape, source_scale)
        h, w = round(grey.shape[0] * scale), round(grey.shape[1] * scale)
        hp, wp = -(-h // PAD_MULTIPLE) * PAD_MULTIPLE, -(-w // PAD_MULTIPLE) * PAD_MULTIPLE
        small = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        x = np.empty((1, 1, hp, wp), np.float32)
        if (hp, wp) != (h, w):
            x.fill(0.5)  # the padding
        # into the input directly: no float copy of the image to allocate and copy again (1.0 -> 0.1 ms at 640x480,
        # the same values to the bit)
        np.divide(small, np.float32(255.0), out=x[0, 0, :h, :w], dtype=np.float32)
        return x, scale

    def detect(self, grey: np.ndarray, source_scale: float = 1.0,
               area_px: tuple[int, int, int, int] | None = None) -> Detections:
        """Detections in `grey`'s own pixels; `source_scale`: see `input_shape`. `area_px` (x0, y0, x1, y1), in the
        camera's full-resolution pixels: look only at that rectangle (a fisheye's image circle: the black sides
        beside it are not computed) and its surroundings (`area_crop`), at the scale of the whole image, so the
        vehicles keep the size the model learnt."""
        return self.detect_timed(grey, source_scale, area_px)[0]

    def detect_timed(self, grey: np.ndarray, source_scale: float = 1.0,
                     area_px: tuple[int, int, int, int] | None = None) -> tuple[Detections, float]:
        """`detect`'s Detections and the time (ms) ONNX Runtime's `session.run` took for them: the inference proper,
        without the crop, the resize to the network's input, the decoding of its maps or the calibrations. A frame
        runs the network once (`mirror` runs the image and its mirror as one batch of two: both are in that time).
        Timed with the calling thread's own clock readings, nothing stored on the detector, so the detect service's
        worker threads may call it on one shared detector at once."""
        if area_px is None:
            det, run_ms = self._detect_timed(grey, source_scale, None)
        else:
            x0, y0, x1, y1 = self.area_crop(grey.shape, source_scale, area_px)
            scale = self.scale_for(*grey.shape, source_scale)
            det, run_ms = self._detect_timed(grey[y0:y1, x0:x1], source_scale, scale)
            det = det.scaled(1.0, 1.0, x0, y0)
        return self.calibrate(det, grey.shape[1], grey.shape[0]), run_ms

    def calibrate(self, det: Detections, width: int, height: int) -> Detections:
        """Decoded detections of a width x height image with the model's box and size calibrations applied (the box
        from the heads' own sizes, then the sizes); as given for a model without them."""
        if len(det) == 0:
            return det
        if self.box_calibration is not None:
            det = self.box_calibration.apply(det, width, height)
        if self.size_calibration is not None:
            det = replace(det, size_lwh=self.size_calibration.apply(det.size_lwh, det.vtype))
        return det

    def area_crop(self, shape: tuple[int, int], source_scale: float,
                  area_px: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        """The part of an image of `shape` (H, W, decoded at `source_scale`) that `detect` runs the network on for a
        detect area: the area widened by `AREA_CONTEXT_PX` network pixels where the image reaches, then out to the
        network's 32-pixel grid of the whole image.

        The network is not shift-invariant below that grid: on a frame of the simulated roundabout a crop 6 pixels
        off it moved 34 of 35 detections by more than half a pixel or 0.03 in score. On the grid the detections
        are the whole image's but near the crop's edges, where the network's view reaches past them: on 25 frames
        of the validation recording 91 % of the detections were identical with the circle alone, 97.6 % with 32
        pixels of context around it (tracking MOTA 0.559 and 0.586 against 0.593 on the whole image)."""
        scale = self.scale_for(*shape, source_scale)
        m = AREA_CONTEXT_PX / scale / source_scale  # in full-resolution pixels
        wider = (area_px[0] - m, area_px[1] - m, area_px[2] + m, area_px[3] + m)
        return area_box(wider, shape, source_scale, PAD_MULTIPLE / scale)

    def _detect_timed(self, grey: np.ndarray, source_scale: float,
                      scale: float | None) -> tuple[Detections, float]:
        """The Detections of `grey` (a whole image or an area crop, resized by `scale`) and the ms `session.run`
        took (a local timer: nothing shared is written)."""
        x, scale = self.preprocess(grey, source_scale, scale)
        batch = np.concatenate([x, x[..., ::-1]]) if self.mirror else x  # mirror: the image and its mirror at once
        t0 = time.perf_counter()
        outs = self.session.run(None, {self.input_name: batch})
        run_ms = (time.perf_counter() - t0) * 1e3
        if self.mirror:
            maps = mirror_average(dict(zip(self.output_names, outs, strict=True)))
        else:
            maps = {name: o[0] for name, o in zip(self.output_names, outs, strict=True)}
        if not self.votes:
            maps.pop("vote", None)
        det = decode(**maps, stride=self.stride, score_thr=self.score_thr, top_k=self.top_k)
        return network_to_image(det, grey.shape, scale), run_ms


def network_to_image(det: Detections, shape: tuple[int, int], scale: float) -> Detections:
    """Detections in the network input of an image of `shape` (H, W) that `preprocess` resized by `scale`, in the
    image's own pixels. Network pixel p (centre convention) <- image pixel q: p + 0.5 = (q + 0.5) * s, with s each
    axis's own factor of the whole-pixel size it was resized to, as training's resize_sample maps its labels (the
    nominal scale is up to 0.75 px off at the far edge of an image whose side does not scale to whole pixels)."""
    sx = round(shape[1] * scale) / shape[1]
    sy = round(shape[0] * scale) / shape[0]
    return det.scaled(1.0 / sx, 1.0 / sy, 0.5 / sx - 0.5, 0.5 / sy - 0.5)


def area_box(area_px: tuple[int, int, int, int], shape: tuple[int, int], source_scale: float = 1.0,
             grid: float = 1.0) -> tuple[int, int, int, int]:
    """A full-resolution rectangle (x0, y0, x1, y1) as whole pixels of an image of `shape` (H, W) decoded at
    `source_scale`: its corner moved out to a multiple of `grid` pixels of that image, its size out to a multiple of
    `grid` as far as the image reaches, clipped to the image. ValueError when nothing is left."""
    h, w = shape
    lo = np.array(area_px[:2], float) * source_scale
    hi = np.array(area_px[2:], float) * source_scale
    lo = np.maximum(0, np.floor(np.floor(lo / grid) * grid + 1e-6)).astype(int)
    size = np.ceil((hi - lo) / grid - 1e-6) * grid
    hi = np.minimum([w, h], np.round(lo + size)).astype(int)
    if (hi - lo < 1).any():
        raise ValueError(f"detect area {list(area_px)} leaves nothing of a {w}x{h} image at scale {source_scale:g}")
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])
