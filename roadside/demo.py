"""`roadside demo`: the State/Ellsworth roundabout through the live pipeline, scored against ground truth.

1. Simulate the roundabout's four fisheye cameras (default 60 s at 10 Hz) unless the recording exists.
2. Calibrate every camera from its first `landmarks` simulated landmarks (noisy clicks, as a person
   would enter them) and write a site folder (site.yaml + lookup masks).
3. Time the detector alone on the recording's frames (the same decoded images the pipeline feeds it), and
   with each frame's JPEG decoded as ingest decodes it (one process doing the pipeline's work without the bus),
   before the pipeline runs and again after it (the throughput ratio is against both passes pooled). It is loaded
   as the detect service loads it (`services.detect.load_detector`: the same model and execution providers).
4. `roadside up`: the four services as OS processes on Zenoh peer-to-peer loopback, playing the
   recording as fast as the pipeline takes it; a collector on the bus keeps every Objects and Tracks
   message (for latency and the single-camera comparison); fuse_track writes `tracks.jsonl`.
5. Score: MOTA, IDF1, id switches, trajectory error in the ROI (fused, and each camera tracked alone),
   latency per stage, throughput against the detector alone, memory per service; write
   `summary.json`, `demo.rrd` and print a table.
"""

from __future__ import annotations

import ast
import json
import math
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from shared.bus import BadInput, Receiver, zenoh_config
from shared.geo import GeoFrame
from shared.jsonio import dumps
from shared.keys import all_cameras_key, tracks_key
from shared.messages import Objects, Tracks
from shared.settings import BusSettings, Settings

REPO = Path(__file__).resolve().parent.parent
# the simulated replica of the State/Ellsworth roundabout: same origin and the same UTC minute as the real footage,
# so a site name of its own keeps its tracks apart from the real site's (`eval real`, `counts` refuse tracks of
# another site than the one they are given)
DEMO_SITE = "state_ellsworth_sim"
DEFAULT_MODEL = REPO / "models" / "detector_fp32.onnx"


@dataclass
class DemoConfig:
    out: Path = Path("out/demo")
    seconds: float = 60.0
    hz: float = 10.0
    seed: int = 2024
    landmarks: int = 20
    model: Path = DEFAULT_MODEL
    pace: str = "max"
    # chosen by fused MOTA on a validation recording of the roundabout (seed 77, 60 s at 10 Hz, the same
    # cameras and calibration procedure), never on the demo's own (seed 2024), with the shipped model (run 11,
    # models/README.md), detections at 0.2 rescored offline (`roadside eval budget --scenario as_run`): tracks
    # started at 0.33 and extended by detections down to 0.30 (fuse_track.high_score, ByteTrack's second round)
    # gave MOTA 0.749; 0.30 / 0.32 0.749, 0.32 / 0.34 0.749, 0.28 / 0.33 0.743, 0.27 / 0.30 0.737, 0.30 / 0.34
    # 0.733, 0.36 / 0.40 0.712, 0.33 / 0.36 0.700, 0.40 / 0.43 0.685 (docs/pipeline.md).
    score_thr: float = 0.30
    high_score: float = 0.33  # fuse_track.high_score: objects below it only extend confirmed tracks
    port_base: int = 7451
    baseline_frames: int = 120
    # identities kept across camera regions are scored over the ground within this distance of a camera, not the
    # 25 m ROI: the regions' borders lie between the ROIs (the demo's cameras stand ~54 m apart), so within the
    # ROI alone a vehicle is hardly ever seen on both sides of one (1 crossing in the whole demo)
    handoff_radius_m: float = 40.0

    def __post_init__(self) -> None:
        """Everything checkable is checked here, before minutes of simulation and calibration."""
        from pydantic import ValidationError

        from shared.settings import BusSettings, IngestSettings

        if not (1.0 <= self.hz <= 100.0):  # fuse_track ticks once per frame interval, at most every second
            raise ValueError(f"hz must be from 1 to 100 (a tick per frame interval), got {self.hz}")
        if not (self.seconds > 0 and self.seconds * self.hz >= 2):
            raise ValueError(f"seconds {self.seconds:g} at hz {self.hz:g} is fewer than two frames per camera")
        if not 5 <= self.landmarks <= 1000:
            raise ValueError(f"landmarks must be from 5 to 1000 per camera (the simulator makes 5-30), got "
                             f"{self.landmarks}")
        for build, what in ((lambda: IngestSettings(pace=self.pace), "pace"),
                            (lambda: BusSettings(port_base=self.port_base), "port_base")):
            try:
                build()
            except ValidationError as exc:
                raise ValueError(f"{what}: {exc.errors()[0]['msg']}") from None
        if not Path(self.model).is_file():
            raise ValueError(f"detector model not found: {self.model}")


def make_recording(cfg: DemoConfig, log) -> Path:
    from sim.clip import ClipConfig, simulate_clip

    rec = cfg.out / "recording"
    meta = rec / "recording.json"
    if meta.is_file():
        m = json.loads(meta.read_text())
        if (m.get("seed"), m.get("hz"), m.get("seconds")) == (cfg.seed, cfg.hz, cfg.seconds):
            log(f"recording exists: {rec}")
            return rec
    log(f"simulating {cfg.seconds:g} s at {cfg.hz:g} Hz, four fisheye cameras (a few minutes)")
    simulate_clip(ClipConfig(site="state_ellsworth", out=rec, seconds=cfg.seconds, hz=cfg.hz, seed=cfg.seed,
                             cameras="fisheye", overwrite=True), log=lambda s: log(s))
    return rec


def make_site(cfg: DemoConfig, rec_dir: Path, log) -> tuple[Path, dict]:
    """Calibrate each camera from its landmarks; write <out>/site/site.yaml. Returns (path, reports)."""
    from calibration.run import CalibrateJob, run_calibration
    from sim.recording import Recording
    from sim.site import SiteSpec

    rec = Recording(rec_dir)
    site_dir = cfg.out / "site"
    (site_dir / "landmarks").mkdir(parents=True, exist_ok=True)
    origin = rec.meta["site"]["origin"]
    cameras, reports = [], {}
    for name in rec.camera_names:
        cam = rec.cameras[name]
        if cam.kind != "fisheye":
            continue
        lm = rec.landmarks(name)
        lm = {**lm, "landmarks": lm["landmarks"][: cfg.landmarks]}
        for item in lm["landmarks"]:  # what a person enters: no truth
            item.pop("truth", None)
            item.pop("gross", None)
        lm_path = site_dir / "landmarks" / f"{name}.json"
        lm_path.write_text(json.dumps(lm, indent=1))
        circle = (cam.cx, cam.cy, cam.image_circle_radius_px()) if cam.kind == "fisheye" else None
        job = CalibrateJob(landmarks=lm_path, kind=cam.kind, out=site_dir / "masks" / f"{name}.npz",
                           width=cam.width, height=cam.height, image_circle=circle, fov_deg=2 * cam.max_angle_deg,
                           origin=(origin["lat_deg"], origin["lon_deg"], origin.get("alt_m", 0.0)))
        rep = run_calibration(job)
        reports[name] = {k: rep.get(k) for k in ("in_roi", "out_roi", "rejected", "leave_one_out") if k in rep}
        log(f"calibrated {name} from {len(lm['landmarks'])} landmarks")
        cameras.append({"name": name, "kind": cam.kind, "width": cam.width, "height": cam.height,
                        "masks": f"masks/{name}.npz", "detect_area_px": list(cam.image_area_px())})
    site = {
        "site": DEMO_SITE,
        "origin": origin,
        "cameras": cameras,
        "bus": {"mode": "peer", "port_base": cfg.port_base},
        "ingest": {"source": str(rec_dir.resolve()), "pace": cfg.pace, "encoding": "gray8", "wait_extra_peers": 1,
                   "decode_long_side": model_long_side(cfg.model)},
        "detect": {"model": str(Path(cfg.model).resolve()), "model_gpu": None, "score_thr": cfg.score_thr},
        "fuse_track": {"tick_ms": 1000.0 / cfg.hz, "high_score": cfg.high_score,
                       "record": str((cfg.out / "tracks.jsonl").resolve())},
        "movements": SiteSpec.model_validate(rec.meta["site_spec"]).movements(),  # `roadside counts`
    }
    path = site_dir / "site.yaml"
    path.write_text(yaml.safe_dump(site, sort_keys=False))
    return path, reports


def model_long_side(model: str | Path) -> int:
    """The detector's input size (longer side), from the model's metadata."""
    from shared.inference import OnnxDetector

    return OnnxDetector(model, providers=["CPUExecutionProvider"], threads=1).long_side


class DetectorAlone:
    """The detector by itself on the pipeline's input (JPEG decoded as ingest does, grey), loaded as the detect
    service loads it (`services.detect.load_detector` with the site's settings: the same model file and execution
    providers, threads, spinning, mirror and threshold) and run as it runs it (`detect.workers` inferences at once,
    `detect.threads` threads each, on each camera's `detect_area_px`): frames/s and ms per frame, without and with
    each frame's JPEG decode. The providers its session runs on are kept (`providers`).

    This shared machine's speed drifts by a quarter within minutes, so one pass of a few seconds before the
    pipeline is a poor baseline for a ratio: `run_demo` times a pass before the pipeline and one after it and
    pools them (`pooled`), and the summary keeps both passes."""

    def __init__(self, cfg: DemoConfig, rec_dir: Path, settings: Settings) -> None:
        import cv2

        from services.detect.__main__ import load_detector
        from services.ingest.__main__ import REDUCED, decode_scale_for
        from sim.recording import Recording

        rec = Recording(rec_dir)
        self.detect = settings.detect
        # the service's own loader: on a GPU machine the pipeline's detect runs on CUDA or TensorRT, and a baseline
        # pinned to the CPU would make the throughput ratio a GPU's frames/s over a CPU's
        self.det = load_detector(settings)
        area = {c.name: c.detect_area_px for c in settings.cameras}
        cams = {c: rec.cameras[c] for c in rec.camera_names}
        frames = [(p, decode_scale_for(cams[c].width, cams[c].height, self.det.long_side), area[c])
                  for c in rec.camera_names for _, p in rec.frames(c)]
        step = max(1, len(frames) // cfg.baseline_frames)
        self.files = [(p.read_bytes(), n, a) for p, n, a in frames[::step]]
        self.reduced = REDUCED
        self.images = [(cv2.imdecode(np.frombuffer(b, np.uint8), REDUCED[n]), 1.0 / n, a) for b, n, a in self.files]
        # one untimed pass: a new ONNX Runtime session runs its first hundred frames 10-15 % slower (measured on
        # this machine: a first pass of 82.9 frames/s, then 89.5 and 94.9), which would flatter the pipeline
        self.run()

    def _timed(self, item) -> float:
        t0 = time.perf_counter()
        self.det.detect(*item)
        return (time.perf_counter() - t0) * 1e3

    def _decoded_and_timed(self, item) -> float:
        import cv2

        t0 = time.perf_counter()
        data, n, area = item
        self.det.detect(cv2.imdecode(np.frombuffer(data, np.uint8), self.reduced[n]), 1.0 / n, area)
        return (time.perf_counter() - t0) * 1e3

    def run(self) -> dict:
        """One pass: every frame without decode, then every frame with it. Times per frame are kept (`times`,
        `with_decode_times`) for pooling."""
        from concurrent.futures import ThreadPoolExecutor

        out = {"frames": len(self.images), "workers": self.detect.workers, "threads": self.detect.threads,
               "providers": self.det.providers}
        with ThreadPoolExecutor(self.detect.workers) as pool:
            for key, fn, items in (("", self._timed, self.images), ("with_decode_", self._decoded_and_timed,
                                                                    self.files)):
                t_all, cpu_all = time.perf_counter(), time.process_time()
                times = list(pool.map(fn, items))
                out |= {f"{key}wall_s": time.perf_counter() - t_all, f"{key}cpu_s": time.process_time() - cpu_all,
                        f"{key}times": times}
        return out


def pooled(passes: list[dict]) -> dict:
    """Passes of `DetectorAlone.run` -> frames/s over all of them (frames / wall time, so the same as one long
    pass), the median and 99th percentile of their times and the CPU time per frame (the process's, inference
    threads included); each pass's own frames/s under `passes`."""
    out = {"frames": sum(p["frames"] for p in passes), "workers": passes[0]["workers"],
           "threads": passes[0]["threads"], "providers": passes[0].get("providers")}
    for key in ("", "with_decode_"):
        times = [t for p in passes for t in p[f"{key}times"]]
        out |= {f"{key}fps": len(times) / sum(p[f"{key}wall_s"] for p in passes),
                f"{key}ms_p50": float(np.median(times)), f"{key}ms_p99": float(np.percentile(times, 99)),
                f"{key}cpu_ms_per_frame": 1e3 * sum(p[f"{key}cpu_s"] for p in passes) / len(times)}
    out["passes"] = [{"fps": round(p["frames"] / p["wall_s"], 2),
                      "with_decode_fps": round(p["frames"] / p["with_decode_wall_s"], 2)} for p in passes]
    return out


class Collector:
    """Keeps every Objects and Tracks message seen on the bus (a peer of the services)."""

    def __init__(self, site: str, port_base: int, on_first_objects=None) -> None:
        import zenoh

        self.session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), None, client_index=1))
        self.bad = BadInput("demo-collector")
        self.objects_rx = Receiver(self.session, all_cameras_key(site, "objects"), Objects, self.bad, fifo=100_000)
        self.tracks_rx = Receiver(self.session, tracks_key(site), Tracks, self.bad, fifo=100_000,
                                  wake=self.objects_rx.wake)
        self.objects: list[Objects] = []
        self.tracks: list[Tracks] = []
        self.t_objects: list[int] = []
        self.on_first_objects = on_first_objects  # called once, in the collector's thread, when objects first arrive
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.site = site
        self.token = None

    def _declare_when_linked(self) -> None:
        """Declare a liveliness token once linked to all four services (ingest waits for it, site.yaml
        `ingest.wait_extra_peers: 1`): the collector dials the services' ports and Zenoh retries a refused dial only
        after a back-off, so without it the first second of objects (18 frames per camera) went unseen."""
        from shared.keys import SERVICES, observer_alive_key

        while not self._stop.is_set():
            if len(list(self.session.info.peers_zid())) >= len(SERVICES):
                self.token = self.session.liveliness().declare_token(observer_alive_key(self.site, "demo-collector"))
                return
            self._stop.wait(0.05)

    def _run(self) -> None:
        self._declare_when_linked()
        while not self._stop.is_set():
            self.objects_rx.wait(0.1)
            fresh = self.objects_rx.poll()
            if fresh and not self.objects and self.on_first_objects is not None:
                self.on_first_objects()
            self.objects += fresh
            self.tracks += self.tracks_rx.poll()

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.thread.join()
        self.objects += self.objects_rx.poll()
        self.tracks += self.tracks_rx.poll()
        self.token = None
        self.session.close()


HOPS = ("ingest_to_detect_in", "detect_in_to_detect_start", "detect_start_to_detect_done", "detect_done_to_detect",
        "detect_to_localize", "localize_to_fuse_track", "tick_wait", "tick_closed_to_published")


def optional_stamp(msg, stage: str) -> int | None:
    """The time `stage` stamped a message (ns), None if it did not (a stamp an older service did not take)."""
    try:
        return msg.stamp(stage)
    except KeyError:
        return None


def latency(objects: list[Objects], tracks: list[Tracks]) -> dict:
    """Per frame: end to end = tracks published - frame published by ingest; detector = the inference proper, ONNX
    Runtime's `session.run` (`infer_ms`); detect step = the whole detect step (`detect_start` -> `detect_done`: the
    frame's decode, crop, resize, inference, decoding of the maps and calibrations); tick wait = time the frame's
    objects waited at fuse_track for the other cameras of its tick; overhead = end to end - detector (the issue's
    definition: everything but the inference, the detector's pre- and post-processing and the tick wait included);
    `overhead_without_tick_wait` = end to end - detector - tick wait (transport, serialisation, decoding, lookup,
    fusion and tracking: what the microservice split costs beside the fusion's wait for the cameras of a tick, which
    one process fusing unsynchronised cameras would wait as well).

    `hops` splits end to end by the stamps: ingest -> detect_in (serialisation, transport and wake-up: the frame
    taken off the bus by detect's main loop), detect_in -> detect_start (the frame's wait in detect's latest-only
    ring for a free worker), detect_start -> detect_done (the whole detect step), detect_done -> detect (the wait for
    an older frame of its camera to be published first, and the message built), detect -> localize (transport and
    lift), localize -> fuse_track arrival (transport), arrival -> tick closed (tick wait), tick closed -> tracks
    published (fusion, tracking and the Tracks message built; its encoding and put come after the stamp).
    `overhead_without_queue` leaves out the tick wait and the wait in detect's ring: the split's own cost when the
    detector keeps up with the frames.

    Objects of an older detect (no `detect_start` or `detect_done` stamp, an `infer_ms` that was the whole detect
    step): their `infer_ms` stands for both the detector and the detect step, and they are left out of the hops
    those stamps bound and of `overhead_without_queue` (their wait in the ring was not stamped)."""
    by_frame = {(o.camera, o.seq, o.t_capture_ns): o for o in objects}
    e2e, det, step, wait, over, over_nw, over_nq = [], [], [], [], [], [], []
    hops: dict[str, list[float]] = {k: [] for k in HOPS}
    for tr in tracks:
        t_pub = tr.stamp("fuse_track")
        t_closed = tr.stamp("tick_closed")
        for cam, seq, t_cap, t_arrive in tr.frames:
            o = by_frame.get((cam, seq, t_cap))
            if o is None:
                continue
            t_ing, t_in, t_det, t_loc = (o.stamp(s) for s in ("ingest", "detect_in", "detect", "localize"))
            t_start, t_done = optional_stamp(o, "detect_start"), optional_stamp(o, "detect_done")
            e = (t_pub - t_ing) / 1e6
            w = max(0.0, (t_closed - t_arrive) / 1e6)
            e2e.append(e)
            det.append(o.infer_ms)
            step.append((t_done - t_start) / 1e6 if t_start is not None and t_done is not None else o.infer_ms)
            wait.append(w)
            over.append(e - o.infer_ms)
            over_nw.append(e - o.infer_ms - w)
            if t_start is not None:
                over_nq.append(e - o.infer_ms - w - (t_start - t_in) / 1e6)
            points = (t_ing, t_in, t_start, t_done, t_det, t_loc, t_arrive, t_closed, t_pub)
            for name, a, b in zip(HOPS, points[:-1], points[1:], strict=True):
                if name == "tick_wait":
                    hops[name].append(w)
                elif a is not None and b is not None:
                    hops[name].append((b - a) / 1e6)

    def pct(x, q):
        return round(float(np.percentile(x, q)), 2) if x else None

    return {"frames": len(e2e), "end_to_end_p50": pct(e2e, 50), "end_to_end_p99": pct(e2e, 99),
            "detector_p50": pct(det, 50), "detect_step_p50": pct(step, 50),
            "tick_wait_p50": pct(wait, 50), "tick_wait_p99": pct(wait, 99),
            "overhead_p50": pct(over, 50), "overhead_p99": pct(over, 99),
            "overhead_without_tick_wait_p50": pct(over_nw, 50), "overhead_without_tick_wait_p99": pct(over_nw, 99),
            "overhead_without_queue_p50": pct(over_nq, 50), "overhead_without_queue_p99": pct(over_nq, 99),
            "hops_p50": {k: pct(v, 50) for k, v in hops.items()}, "hops_p99": {k: pct(v, 99) for k, v in hops.items()}}


# detect's start-up line (services/detect: "model <path> on [<providers>], <n> workers x <n> threads")
DETECT_STARTED = re.compile(r"\bmodel \S.* on (\[[^\]\n]*\]), \d+ workers x \d+ threads")


def logged_providers(log: Path, start: int = 0) -> list[str] | None:
    """The execution providers the detect service says its session runs on: the last start-up line in its log
    written after byte `start` (this run's); None where there is none."""
    try:
        with open(log, "rb") as f:
            f.seek(start)
            text = f.read().decode(errors="replace")
    except OSError:
        return None
    for found in reversed(DETECT_STARTED.findall(text)):
        try:
            providers = ast.literal_eval(found)
        except (ValueError, SyntaxError):
            continue
        if isinstance(providers, list) and all(isinstance(p, str) for p in providers):
            return providers
    return None


def objects_rows(objects: list[Objects]) -> list[dict]:
    return [{"camera": o.camera, "seq": o.seq, "t_ns": o.t_capture_ns, "xy": o.xy.tolist(), "yaw": o.yaw.tolist(),
             "size_lwh": o.size_lwh.tolist(), "vtype": o.vtype.tolist(), "score": o.score.tolist(),
             "infer_ms": o.infer_ms, "stamps": [list(x) for x in o.stamps]}  # stamps: per-hop latency analysis
            for o in objects]


def site_basemap(rec_dir: Path, max_side_px: int = 2048):
    """A top-down map of the simulated site (the renderer's own ground albedo) for the Rerun view."""
    import cv2

    from services.rerun_sink.basemap import Basemap
    from sim.recording import Recording
    from sim.render import site_seed
    from sim.roads import build_network
    from sim.site import SiteSpec
    from sim.texture import paint_ground

    spec = SiteSpec.model_validate(Recording(rec_dir).meta["site_spec"])
    ground = paint_ground(build_network(spec), spec.extent_m, site_seed(spec), res_m=0.1)
    img = ground.albedo
    if max(img.shape[:2]) > max_side_px:
        img = cv2.resize(img, (max_side_px, max_side_px), interpolation=cv2.INTER_AREA)
    e = spec.extent_m
    return Basemap.from_array(img, (-e, e, -e, e))


def track_single_camera(objects: list[Objects], camera: str, tracker_config, geo) -> list[dict]:
    """The paper's 'before fusion' baseline: one camera's objects tracked alone, one update per frame at
    its capture time. Rows in the tracks-file format."""
    from services.fuse_track.__main__ import tracks_message
    from services.fuse_track.fusion import ObjectBatch
    from services.fuse_track.tracker import Tracker

    tracker = Tracker(tracker_config, tracker_id=f"single-{camera}")
    rows = []
    for o in sorted((o for o in objects if o.camera == camera), key=lambda o: o.t_capture_ns):
        batch = ObjectBatch.from_frame(camera, o.t_capture_ns, o.xy, o.yaw.astype(np.float64),
                                       o.size_lwh.astype(np.float64), o.vtype.astype(np.int64),
                                       o.score.astype(np.float64))
        msg = tracks_message(o.site, tracker.update(batch, o.t_capture_ns), o.t_capture_ns, o.seq, geo, [], [])
        rows.append({"site": o.site, "seq": o.seq, "t_ns": o.t_capture_ns, "tracker": tracker.id,
                     "tracks": msg.rows()})
    return rows


def throughput(pipeline_fps: float, alone: dict, pace: str, pipeline_providers: list[str] | None) -> dict:
    """The summary's throughput part: the detector alone (`pooled`), the execution providers each side ran on, the
    playback pace and the pipeline's frames/s against the detector alone's."""
    return {
        "detector_alone": alone,
        # the execution providers the pipeline's detect service ran on (its log's start-up line; None where it is not
        # found) and those of the detector alone, loaded the same way: a ratio of two different providers is no ratio
        "providers": {"pipeline_detect": pipeline_providers, "detector_alone": alone.get("providers")},
        # the playback pace: the throughput figures below measure the pipeline's capacity only at "max" (ingest
        # publishes a frame as soon as detect takes it); at "1" or "N" ingest publishes at the cameras' rate (N
        # times it), which caps pipeline_fps and the ratios whatever the pipeline could do
        "pace": pace,
        "pipeline_fps": round(pipeline_fps, 2),
        # pipeline frames/s over the detector alone's (the same run, both passes pooled): the pipeline's capacity
        # against the detector's at pace "max" only (see `pace`)
        "throughput_ratio": round(pipeline_fps / alone["fps"], 3),
        # against one process that decodes each JPEG and runs the detector on it: what the split into services
        # costs, the decoding every design needs left out (the ratio above charges the pipeline for it)
        "throughput_ratio_vs_decode_and_detect": round(pipeline_fps / alone["with_decode_fps"], 3),
    }


def run_demo(cfg: DemoConfig, log=print) -> dict:
    from eval.movements import evaluate_movements
    from eval.tracking import GroundTruth, TrackingEvalConfig, evaluate_many, evaluate_tracks
    from roadside.launcher import Launcher, UpConfig
    from services.fuse_track.__main__ import tracker_config
    from services.rerun_sink import tracks_file_to_rrd
    from shared.settings import load_settings
    from sim.recording import Recording

    cfg.out.mkdir(parents=True, exist_ok=True)
    rec_dir = make_recording(cfg, log)
    site_path, calib = make_site(cfg, rec_dir, log)
    settings = load_settings(site_path)
    cams = [c.name for c in settings.cameras]
    log("timing the detector alone (before the pipeline; again after it)")
    timer = DetectorAlone(cfg, rec_dir, settings)
    passes = [timer.run()]
    tracks_path = settings.path(settings.fuse_track.record)
    tracks_path.unlink(missing_ok=True)
    launcher = Launcher(UpConfig(site=site_path, log_dir=cfg.out / "logs", restart=False))
    detect_log = cfg.out / "logs" / "detect.log"  # appended to: this run's lines are those after its present size
    detect_log_start = detect_log.stat().st_size if detect_log.is_file() else 0
    cpu_at_start: dict[str, float] = {}  # each service's CPU seconds when the first objects arrive: start-up left out
    collector = Collector(settings.site, cfg.port_base, on_first_objects=lambda: cpu_at_start.update(launcher.cpu_s))
    collector.start()
    log(f"running the pipeline: roadside up (logs in {cfg.out / 'logs'})")
    status = launcher.run(log=log)
    collector.stop()
    if launcher.signalled:  # Ctrl-C: a run cut short is not scored (its summary would replace the last whole one's)
        log(f"the pipeline was stopped by {launcher.signalled}: not scored, {cfg.out / 'summary.json'} left as it was")
        raise KeyboardInterrupt
    if status != 0:
        raise RuntimeError(f"the pipeline stopped with status {status}; see {cfg.out / 'logs'}")
    log("timing the detector alone again")
    passes.append(timer.run())
    alone = pooled(passes)
    del timer
    objects = collector.objects
    if not objects:
        raise RuntimeError(f"no objects came through the pipeline; see {cfg.out / 'logs'}")
    t_first = min(o.stamp("ingest") for o in objects)
    t_last = max(o.stamp("detect") for o in objects)
    pipeline_fps = (len(objects) - 1) / max((t_last - t_first) / 1e9, 1e-9)
    lat = latency(objects, collector.tracks)
    cpu_run = {k: v - cpu_at_start.get(k, 0.0) for k, v in launcher.cpu_s.items()}
    (cfg.out / "objects.jsonl").write_text("".join(json.dumps(r) + "\n" for r in objects_rows(objects)))

    log("scoring against the ground truth")
    tcfg = tracker_config(settings.fuse_track)  # each camera alone tracked as fuse_track tracks them all
    geo = GeoFrame.from_dict(settings.origin)
    sources = {"fused": tracks_path, **{c: track_single_camera(objects, c, tcfg, geo) for c in cams}}
    gt = GroundTruth(rec_dir)
    scores = evaluate_many(gt, sources, cameras=cams)
    fused = scores["sources"]["fused"]
    wide = evaluate_tracks(gt, tracks_path, cams, TrackingEvalConfig(eval_radius_m=cfg.handoff_radius_m))
    # the fused tracks in each camera's own ROI, against that camera tracked alone there (the same ground): the
    # best single camera above is the easiest ROI, not the same ground as the fused figure
    fused_in = {c: evaluate_tracks(gt, tracks_path, [c], seen_by=cams)["traj_err_in_roi_m"] for c in cams}

    mv = evaluate_movements(gt, tracks_path, settings.movements.junction(), cams)
    log("writing the Rerun recording")
    origin = settings.origin
    viz = tracks_file_to_rrd(tracks_path, cfg.out / "demo.rrd", site_origin=origin, basemap=site_basemap(rec_dir),
                             junction=settings.movements.junction())
    recording = Recording(rec_dir)
    summary = {
        "recording": str(rec_dir), "seconds": cfg.seconds, "hz": cfg.hz, "cameras": cams,
        # frames localized (the collector saw their Objects) of the recording's: fewer means frames lost on the way
        "frames": len(objects), "frames_recorded": sum(len(recording.frames(c)) for c in cams),
        "tracks_messages": len(collector.tracks),
        "mota": fused["mota"], "idf1": fused["idf1"], "id_switches": fused["id_switches"],
        "precision": fused["precision"], "recall": fused["recall"],
        "traj_err_in_roi_m": fused["traj_err_in_roi_m"], "traj_err_in_roi_std_m": fused["traj_err_in_roi_std_m"],
        "traj_err_best_single_camera_m": scores["traj_err_best_single_camera_m"],
        "best_single_camera": scores["best_single_camera"],
        # the tracks' heading against the vehicles' (full circle), in the ROI; moving: 1 m/s or faster
        **{k: fused[k] for k in ("yaw_err_in_roi_deg", "yaw_err_in_roi_median_deg", "yaw_err_in_roi_moving_deg",
                                 "yaw_err_in_roi_standing_deg")},
        # the share of those headings the tracks' travel confirmed (yaw_confirmed), and of each kind those pointing
        # backwards (more than 90 deg off)
        **{k: fused[k] for k in ("yaw_confirmed_share", "yaw_reversed_confirmed", "yaw_reversed_unconfirmed",
                                 "yaw_err_confirmed_deg", "yaw_err_unconfirmed_deg")},
        # the tracks' own heading uncertainty (yaw_std) against those headings' errors on their axis: consistent when
        # 0.95 of them lie within 1.96 sigma and the mean squared error over sigma^2 is 1 (eval.tracking)
        **{k: fused[k] for k in ("yaw_std_n", "yaw_std_z2_mean", "yaw_std_within_1sigma", "yaw_std_within_95",
                                 "yaw_std_median_deg")},
        # the tracks' own position and velocity uncertainty (xy_cov, velocity_cov) against their errors in the ROI:
        # consistent when the 95 % ellipses hold 0.95 of the true values and the mean squared Mahalanobis distance is 2
        # (eval.tracking)
        **{k: fused[k] for k in ("pos_cov_n", "pos_cov_nees_mean", "pos_cov_within_1sigma", "pos_cov_within_95",
                                 "pos_cov_err95_median_m", "vel_cov_n", "vel_cov_nees_mean", "vel_cov_within_95")},
        # where a vehicle finds the tracks 100 and 300 ms after their capture (the cabinet's latency and a radio
        # hop): as sent and moved on at their velocities (Tracks.predicted), and how often the moved-on 95 % ellipse
        # holds the vehicle (eval.tracking)
        **{f"ahead_{h}ms_{k}": fused[f"ahead_{h}ms_{k}"] for h in (100, 300)
           for k in ("stale_err_m", "err_m", "cov_within_95")},
        # over `handoff_radius_m` around the cameras: region crossings seen tracked on both sides, the fraction that
        # kept their id, and the fraction of vehicles that kept theirs through every crossing (eval.tracking)
        "handoff_radius_m": cfg.handoff_radius_m,
        "handoff_crossings": wide["handoff_crossings"],
        "handoff_crossings_kept": wide["handoff_crossings_kept"],
        "handoff_crossing_kept_fraction": wide["handoff_crossing_kept_fraction"],
        "handoff_kept_fraction": wide["handoff_kept_fraction"],
        # turning movements counted from the tracks (`roadside counts`, the site's junction) against the vehicles'
        # (eval/movements.py): the count board's error, and per vehicle the movements counted right
        "movements": {k: mv[k] for k in ("complete_true", "complete_counted", "count_error", "entering_error",
                                         "leaving_error", "movement_recall", "movement_precision")},
        "single_camera": {c: {**{k: scores["sources"][c][k] for k in ("mota", "idf1", "traj_err_in_roi_m")},
                              "fused_traj_err_in_roi_m": fused_in[c]} for c in cams},
        "latency_ms": lat,
        **throughput(pipeline_fps, alone, cfg.pace, logged_providers(detect_log, detect_log_start)),
        # the same comparison in CPU time, which drifts less with the machine's load than frames/s: the detector's
        # CPU per frame alone (JPEG decode included) over the four services' together; on a CPU-bound machine the
        # frames/s ratio tends to it
        "cpu_ratio_vs_decode_and_detect": round(alone["with_decode_cpu_ms_per_frame"] / max(
            sum(cpu_run.values()) * 1e3 / max(len(objects), 1), 1e-9), 3),
        "peak_rss_mb": launcher.peak_rss_mb,
        # CPU per frame of each service from the first objects to the end, start-up left out (the detector's
        # includes its inference threads)
        "cpu_ms_per_frame": {k: round(1000 * v / max(len(objects), 1), 2) for k, v in cpu_run.items()},
        "bad_messages_seen_by_collector": collector.bad.total,
        "calibration": calib,
        "rerun": {k: viz.get(k) for k in ("rrd", "messages", "bad_lines", "tracks")},
        "tracks_file": str(tracks_path),
    }
    (cfg.out / "summary.json").write_text(dumps(summary, indent=1))
    return summary


def crossings_kept(s: dict) -> str:
    """'32 of 33': the region crossings that kept their id, of those tracked on both sides (as the README writes
    them); from the fraction for a summary written before the count was kept."""
    n = int(s["handoff_crossings"])
    kept = s.get("handoff_crossings_kept")
    if kept is None:
        fraction = s["handoff_crossing_kept_fraction"]
        kept = round(fraction * n) if n and math.isfinite(fraction) else 0
    return f"{int(kept)} of {n}"


def summary_table(s: dict) -> str:
    lat, mv = s["latency_ms"], s["movements"]
    pace, providers = s.get("pace", "?"), s.get("providers", {})  # an older summary has neither
    capped = "" if pace in ("max", "?") else ": capped by the cameras' frame rate, not the pipeline's capacity"
    rows = [
        ("MOTA / IDF1 / id switches", f"{s['mota']:.3f} / {s['idf1']:.3f} / {s['id_switches']}"),
        ("trajectory error in ROI (fused)", f"{s['traj_err_in_roi_m']:.3f} m"),
        ("best single camera", f"{s['traj_err_best_single_camera_m']:.3f} m ({s['best_single_camera']})"),
        ("  fused / alone in each camera's ROI", ", ".join(
            f"{c} {v['fused_traj_err_in_roi_m']:.2f} / {v['traj_err_in_roi_m']:.2f}"
            for c, v in s["single_camera"].items()) + " m"),
        ("heading error in ROI: mean (median)", f"{s['yaw_err_in_roi_deg']:.1f} ({s['yaw_err_in_roi_median_deg']:.1f}) "
                                                f"deg; moving {s['yaw_err_in_roi_moving_deg']:.1f}, standing "
                                                f"{s['yaw_err_in_roi_standing_deg']:.1f} deg"),
        ("  confirmed by travel: share; backwards", f"{s['yaw_confirmed_share']:.3f}; "
                                                    f"{s['yaw_reversed_confirmed']:.3f} of them, "
                                                    f"{s['yaw_reversed_unconfirmed']:.3f} of the others"),
        ("  axis within 1.96 yaw_std", f"{s['yaw_std_within_95']:.3f} (1 sigma: {s['yaw_std_within_1sigma']:.3f}; "
                                      f"median sigma {s['yaw_std_median_deg']:.1f} deg)"),
        ("true position within the 95 % ellipse", f"{s['pos_cov_within_95']:.3f} (1 sigma: "
                                                   f"{s['pos_cov_within_1sigma']:.3f}; median half-axis "
                                                   f"{s['pos_cov_err95_median_m']:.2f} m); velocity "
                                                   f"{s['vel_cov_within_95']:.3f}"),
        ("100 / 300 ms after capture: as sent; moved on",
         f"{s['ahead_100ms_stale_err_m']:.2f} / {s['ahead_300ms_stale_err_m']:.2f} m; {s['ahead_100ms_err_m']:.2f} / "
         f"{s['ahead_300ms_err_m']:.2f} m (95 % ellipse holds {s['ahead_100ms_cov_within_95']:.3f} / "
         f"{s['ahead_300ms_cov_within_95']:.3f})"),
        ("turning movements counted (true)", f"{mv['complete_counted']} ({mv['complete_true']}): count error "
                                             f"{mv['count_error']:.3f}, entering {mv['entering_error']:.3f}; per "
                                             f"vehicle recall {mv['movement_recall']:.3f}, precision "
                                             f"{mv['movement_precision']:.3f}"),
        ("frames through the pipeline", f"{s['frames']} of {s['frames_recorded']}"),
        ("region crossings kept", f"{crossings_kept(s)} (within {s['handoff_radius_m']:g} m of a camera)"),
        ("end to end p50 / p99", f"{lat['end_to_end_p50']} / {lat['end_to_end_p99']} ms"),
        ("detector p50 (session.run) / detect step p50", f"{lat['detector_p50']} / {lat.get('detect_step_p50')} ms"),
        ("overhead (end to end - inference) p50 / p99", f"{lat['overhead_p50']} / {lat['overhead_p99']} ms"),
        ("  without the tick wait", f"{lat['overhead_without_tick_wait_p50']} / "
                                    f"{lat['overhead_without_tick_wait_p99']} ms"),
        ("  and without the ring wait", f"{lat['overhead_without_queue_p50']} / "
                                        f"{lat['overhead_without_queue_p99']} ms"),
        ("tick wait p50 / p99", f"{lat['tick_wait_p50']} / {lat['tick_wait_p99']} ms"),
        ("throughput vs detector alone", f"{s['throughput_ratio']:.3f} ({s['pipeline_fps']:.1f} frames/s at pace "
                                         f"{pace}{capped})"),
        ("  detector alone before / after", " / ".join(f"{p['fps']:.1f}" for p in s["detector_alone"]["passes"])
         + " frames/s"),
        ("  vs JPEG decode + detector", f"{s['throughput_ratio_vs_decode_and_detect']:.3f} (in CPU time: "
                                         f"{s['cpu_ratio_vs_decode_and_detect']:.3f})"),
        ("execution providers: pipeline / alone", " / ".join(", ".join(providers.get(k) or ["?"])
                                                              for k in ("pipeline_detect", "detector_alone"))),
        ("peak memory (MB)", ", ".join(f"{k} {v:.0f}" for k, v in s["peak_rss_mb"].items())),
        ("CPU per frame (ms)", ", ".join(f"{k} {v:.1f}" for k, v in s.get("cpu_ms_per_frame", {}).items())),
    ]
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{a:<{w}}  {b}" for a, b in rows)
