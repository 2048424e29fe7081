"""detect: run the ONNX detector on every camera's newest frames and publish Detections.

`python -m services.detect --site SITE`

Subscribes to `roadside/<site>/cam/*/frame` with a latest-only ring per camera (`detect.ring`
frames): a detector slower than the cameras drops old frames, it never queues them. Frames waiting
from several cameras are taken oldest capture time first. Execution providers are chosen at start
(TensorRT -> CUDA -> CPU); on a GPU the fp16 model (`detect.model_gpu`) is used, on CPU the fp32 one.
Detections are published in original-sensor pixels on `roadside/<site>/cam/<camera>/detections`.
`detect.workers` frames are inferred at once, each with `detect.threads` ONNX Runtime threads (one session,
run from a thread pool; the runtime releases the GIL): on a CPU two single-threaded inferences side by side
take 47 % more frames per second than one two-threaded inference, at a higher latency per frame
(shared/settings.py). Each camera's detections are published in capture order all the same: a frame whose
inference ends before that of an older frame of its camera waits for it (fuse_track takes a camera's newer frame
to mean its older ones have come). A frame that comes after a newer one of its camera was published (a restarted
ingest replaying some frames) is detected and published all the same: ingest at pace `max` waits for each frame's
detections, and fuse_track drops it as late if its tick has closed.
A frame decoded smaller than the model's input needs (`Frame.scale`: ingest's `decode_long_side` below the
model's `input_long_side`) is enlarged back to the scale the model was trained at, with one warning per camera.
A camera's `detect_area_px` (its fisheye image circle) limits the inference to that rectangle, at the whole
image's scale.

Each Detections carries four stamps of detect's (wall clock): `detect_in` when the main loop takes the frame off the
bus, `detect_start` when it takes the frame out of its ring for a free worker (the time between is the frame's wait
in the ring), `detect_done` when the worker has its detections (the whole detect step: the frame's decode, the crop
and resize, the inference, the decoding of the maps and the calibrations) and `detect` when the message is built (after
any wait for an older frame of its camera). `infer_ms` is the inference proper, ONNX Runtime's `session.run` alone
(`OnnxDetector.detect_timed`). Detections of an older detect have `detect_in` and `detect` alone, and an `infer_ms`
that was the whole detect step.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from shared.bus import BadInput, Receiver, Stopper, declare_alive, open_session
from shared.codec import encode
from shared.inference import OnnxDetector, available_providers, runtime_errors
from shared.jpeg import decode_grey
from shared.keys import camera_key
from shared.messages import Detections, Frame
from shared.service import run
from shared.settings import Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.detect")
IDLE_WAIT_S = 0.1


def frame_image(frame: Frame, camera_size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) uint8 grey image of a Frame; ValueError for a corrupt one, or for one that is not its camera's
    `camera_size` (width, height) at its `scale` (within a pixel of the reduced image: a JPEG decoded at 1/s rounds
    a side up), checked before anything is decoded."""
    if camera_size is not None:
        full_w, full_h = frame.width / frame.scale, frame.height / frame.scale
        if max(abs(full_w - camera_size[0]), abs(full_h - camera_size[1])) > 1.0 / frame.scale:
            raise ValueError(f"camera {frame.camera} seq {frame.seq}: a {frame.width}x{frame.height} frame at scale "
                             f"{frame.scale:g} is {full_w:.0f}x{full_h:.0f}, the camera is "
                             f"{camera_size[0]}x{camera_size[1]}")
    if frame.encoding == "gray8":
        return np.frombuffer(frame.data, np.uint8).reshape(frame.height, frame.width)
    if frame.encoding == "bgr8":
        return cv2.cvtColor(np.frombuffer(frame.data, np.uint8).reshape(frame.height, frame.width, 3),
                            cv2.COLOR_BGR2GRAY)
    # the header's size is checked before decoding: OpenCV allocates what a header claims (up to 65535 x 65535);
    # other formats OpenCV reads (PNG) have no such check here, and a Frame that says jpeg must be one
    if frame.data and frame.data[:2] != b"\xff\xd8":
        raise ValueError(f"camera {frame.camera} seq {frame.seq}: encoding 'jpeg' but the data is not a JPEG "
                         f"(starts {frame.data[:4].hex()})")
    img = decode_grey(frame.data, frame.width, frame.height, reduce=0, what=f"camera {frame.camera} seq {frame.seq}")
    if img.shape != (frame.height, frame.width):
        raise ValueError(f"camera {frame.camera} seq {frame.seq}: JPEG is {img.shape[1]}x{img.shape[0]}, "
                         f"frame says {frame.width}x{frame.height}")
    return img


def usable_providers(wanted: list[str]) -> list[str]:
    """Of the execution providers a site asks for, those this ONNX Runtime has, in order (a warning names the rest);
    ValueError for a name ONNX Runtime does not know (a typo) or when none is left."""
    import onnxruntime as ort

    unknown = [p for p in wanted if p not in ort.get_all_providers()]
    if unknown:
        raise ValueError(f"detect.providers: {', '.join(unknown)} is not an ONNX Runtime execution provider "
                         f"(e.g. {', '.join(available_providers())})")
    have = set(ort.get_available_providers())
    usable = [p for p in wanted if p in have]
    if len(usable) < len(wanted):
        log.warning("detect.providers: %s not in this ONNX Runtime (it has %s)",
                    ", ".join(p for p in wanted if p not in have), ", ".join(sorted(have)))
    if not usable:
        raise ValueError(f"detect.providers: none of {', '.join(wanted)} is in this ONNX Runtime (it has "
                         f"{', '.join(sorted(have))})")
    return usable


# where `pip install` or a checkout keeps the shipped models (the image: /app/models)
SHIPPED_MODELS = Path(__file__).resolve().parents[2] / "models"


def load_detector(settings: Settings) -> OnnxDetector:
    cfg = settings.detect
    providers = usable_providers(cfg.providers) if cfg.providers else available_providers()
    gpu = any(p != "CPUExecutionProvider" for p in providers)  # the fp16 model only where a GPU provider is
    path = settings.path(cfg.model_gpu) if gpu and cfg.model_gpu is not None else settings.path(cfg.model)
    if not path.is_file() and gpu:
        path = settings.path(cfg.model)

    def opened(path: Path, providers: list[str]) -> OnnxDetector:
        if path.is_dir():
            raise ValueError(f"detector model {path} is a folder, not a model file (set detect.model in the site file)")
        if not path.is_file():
            raise ValueError(f"detector model not found: {path} (set detect.model in the site file: a path relative "
                             f"to the site folder, or absolute; the shipped ones are {SHIPPED_MODELS})")
        return OnnxDetector(path, providers=providers, threads=cfg.threads, score_thr=cfg.score_thr, spin=cfg.spin,
                            mirror=cfg.mirror, votes=cfg.votes)

    detector = opened(path, providers)
    # a GPU provider this ONNX Runtime lists can still fail to start (no GPU passed through, a driver too old): the
    # session then runs on the CPU, where the fp16 model is slower than the fp32 one (shared/inference.py)
    if path != settings.path(cfg.model) and not any(p != "CPUExecutionProvider" for p in detector.providers):
        log.warning("%s: ONNX Runtime runs it on %s, not on %s: the fp32 model on the CPU instead", path.name,
                    ", ".join(detector.providers), ", ".join(p for p in providers if p != "CPUExecutionProvider"))
        detector = opened(settings.path(cfg.model), ["CPUExecutionProvider"])
    return detector


def detections_message(frame: Frame, det, infer_ms: float, t_in_ns: int, t_start_ns: int, t_done_ns: int) -> Detections:
    """The Detections of a frame: `infer_ms` the inference proper (`session.run`), `t_in_ns` when the frame came
    off the bus, `t_start_ns` when it left the ring for a worker, `t_done_ns` when the worker had its detections
    (the `detect` stamp is now)."""
    inv = 1.0 / frame.scale
    # pixel centres: original q + 0.5 = (p + 0.5) / scale
    d = det.scaled(inv, inv, 0.5 * inv - 0.5, 0.5 * inv - 0.5) if frame.scale != 1.0 else det
    f4 = np.float32
    return Detections(
        site=frame.site, camera=frame.camera, seq=frame.seq, t_capture_ns=frame.t_capture_ns,
        stamps=[*frame.stamps, ("detect_in", t_in_ns), ("detect_start", t_start_ns), ("detect_done", t_done_ns),
                ("detect", time.time_ns())],
        width=round(frame.width / frame.scale), height=round(frame.height / frame.scale), infer_ms=round(infer_ms, 3),
        score=d.score.astype(f4), uv=d.uv.astype(f4), box=d.box.astype(f4), heading_uv=d.heading_uv.astype(f4),
        size_lwh=d.size_lwh.astype(f4), vtype=d.vtype.astype(np.int8))


def main(settings: Settings, stopper: Stopper) -> int:
    detector = load_detector(settings)
    workers = settings.detect.workers
    log.info("model %s on %s, %d workers x %d threads", detector.path, detector.providers, workers,
             settings.detect.threads)
    cams = [c.name for c in settings.cameras]
    bad = BadInput("detect")
    session = open_session(settings, "detect")
    pool = ThreadPoolExecutor(workers, thread_name_prefix="infer")
    try:
        wake = threading.Event()
        receivers = {c: Receiver(session, camera_key(settings.site, c, "frame"), Frame, bad,
                                 ring=settings.detect.ring, wake=wake) for c in cams}
        pubs = {c: session.declare_publisher(camera_key(settings.site, c, "detections")) for c in cams}
        tokens = declare_alive(session, settings.site, "detect", cams)  # after the subscribers: ready
        status = StatusReporter(session, settings.site, "detect", bad, settings.bus.status_period_s)
        infer_avg = math.nan  # exponential mean of the inference time (session.run) over ~10 frames
        step_avg = math.nan  # the same of the whole detect step (decode, crop, resize, inference, decode of the maps)
        ring_skipped = 0  # frames the channels' rings replaced by newer ones, counted so far
        waiting: list[tuple[int, Frame]] = []  # (when it came off the bus, the frame)
        running: list[tuple[Future, Frame, int, int]] = []  # (inference, frame, off the bus, out of the ring)
        warned: set[str] = set()  # cameras whose frames come too small for the model
        ort_errors = runtime_errors()
        done = 0

        areas = {c.name: c.detect_area_px for c in settings.cameras}
        sizes = {c.name: (c.width, c.height) for c in settings.cameras}

        def infer(img: np.ndarray, scale: float, area: tuple[int, int, int, int] | None):
            """In a worker thread: the detections, the ms of `session.run` alone (timed in this thread: the workers
            share one detector) and when they were done (wall clock)."""
            det, run_ms = detector.detect_timed(img, scale, area)
            return det, run_ms, time.time_ns()

        while not stopper.is_set():
            for c, r in receivers.items():
                for msg in r.poll():
                    if msg.camera != c:
                        bad(f"frame for camera {msg.camera} on the key of camera {c}", c)
                        continue
                    waiting.append((time.time_ns(), msg))
                    status.count("frames_in")
            before = len(waiting)
            waiting = newest_per_camera(waiting, settings.detect.ring)
            # frames a newer one of the same camera replaced before inference, in the channel or here
            now_skipped = sum(r.skipped for r in receivers.values())
            if now_skipped > ring_skipped or before > len(waiting):
                status.count("frames_skipped", now_skipped - ring_skipped + before - len(waiting))
                ring_skipped = now_skipped
            while waiting and len(running) < workers:
                t_in, frame = waiting.pop(0)
                t_start = time.time_ns()  # out of the ring for a free worker: its wait ends, its detect step starts
                try:
                    img = frame_image(frame, sizes[frame.camera])
                except ValueError as exc:
                    bad(str(exc), frame.camera)
                    continue
                if frame.camera not in warned and detector.input_shape(*img.shape, frame.scale)[0] > 1.0:
                    warned.add(frame.camera)
                    log.warning("camera %s: frames come at %dx%d, smaller than the model's input (longer side %d); "
                                "enlarged, detail lost: set ingest.decode_long_side to %d", frame.camera,
                                frame.width, frame.height, detector.long_side, detector.long_side)
                future = pool.submit(infer, img, frame.scale, areas[frame.camera])
                future.add_done_callback(lambda _: wake.set())
                running.append((future, frame, t_in, t_start))
            for item in sorted((r for r in running if r[0].done()), key=lambda r: r[1].t_capture_ns):
                if behind(item, running):
                    continue
                running.remove(item)
                future, frame, t_in, t_start = item
                try:
                    det, infer_ms, t_done = future.result()
                except ValueError as exc:  # the camera's detect area leaves nothing of a frame this size
                    bad(f"camera {frame.camera} seq {frame.seq}: {exc}", frame.camera)
                    continue
                except cv2.error as exc:  # e.g. an image too thin to resize to the network's input
                    bad(f"camera {frame.camera} seq {frame.seq}: cannot detect on a {frame.width}x{frame.height} "
                        f"image ({str(exc).strip().splitlines()[-1]})", frame.camera)
                    continue
                except ort_errors as exc:  # ONNX Runtime's own (not ValueErrors): the model refused this input
                    bad(f"camera {frame.camera} seq {frame.seq}: inference failed on a {frame.width}x{frame.height} "
                        f"image ({' '.join(str(exc).split())[:300]})", frame.camera)
                    continue
                try:
                    msg = detections_message(frame, det, infer_ms, t_in, t_start, t_done)
                except ValueError as exc:  # e.g. NaN out of the model: the frame's detections cannot be sent
                    bad(f"camera {frame.camera} seq {frame.seq}: detections refused ({exc})", frame.camera)
                    continue
                pubs[frame.camera].put(encode(msg))
                status.count("detections_out", output=True)
                infer_avg = infer_ms if math.isnan(infer_avg) else 0.9 * infer_avg + 0.1 * infer_ms
                status.gauge("infer_ms_avg", infer_avg)
                step_ms = (t_done - t_start) / 1e6
                step_avg = step_ms if math.isnan(step_avg) else 0.9 * step_avg + 0.1 * step_ms
                status.gauge("detect_step_ms_avg", step_avg)
                done += 1
            if not any(r[0].done() and not behind(r, running) for r in running) and (
                    not waiting or len(running) >= workers):
                wake.wait(IDLE_WAIT_S)
                wake.clear()
        log.info("stopped: %d frames detected, %d bad messages %s", done, bad.total, dict(bad.counts))
        status.close()
        del tokens
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        session.close()
    return 0


def behind(item: tuple[Future, Frame, int, int], running: list[tuple[Future, Frame, int, int]]) -> bool:
    """Whether an older frame of `item`'s camera is still running, in inference or done and not yet published:
    `item` is published after it. (Done or not: one that finished a moment ago is published first, being older.)"""
    frame = item[1]
    return any(r[1].camera == frame.camera and r[1].t_capture_ns < frame.t_capture_ns for r in running)


def newest_per_camera(waiting: list[tuple[int, Frame]], ring: int) -> list[tuple[int, Frame]]:
    """At most `ring` frames per camera (the newest, as the channel keeps), oldest capture time first."""
    per_cam: dict[str, int] = {}
    kept = []
    for w in sorted(waiting, key=lambda w: w[1].t_capture_ns, reverse=True):
        per_cam[w[1].camera] = per_cam.get(w[1].camera, 0) + 1
        if per_cam[w[1].camera] <= ring:
            kept.append(w)
    return kept[::-1]


if __name__ == "__main__":
    raise SystemExit(run("detect", main))
