"""Helpers for the subprocess smoke tests of the live services (tests/test_services.py).

- a site folder built from a simulator recording in seconds: lookup masks from the recording's exact ground
  lookup (no calibration) and a tiny untrained detector exported to ONNX;
- `labels_of_image`: a recording's labelled frames looked up by their pixels (for detectors made of the labels);
- free loopback ports for one test's bus (`port_base` .. `port_base + 9`);
- `ServiceProcess`: `python -m services.<name> --site ... --set ...` with its stderr in a file;
- `Peer`: the test's own Zenoh session on the bus (a client of the embedded peer-to-peer layout) that
  subscribes, publishes and holds liveliness tokens.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
CAMERA = "NE"  # the small recording's fisheye camera (1280 x 960)


# --- the site folder ------------------------------------------------------------------------------------------------


def write_exact_masks(recording_dir: Path, camera: str, path: Path) -> Path:
    """Lookup masks of `camera` from the recording's exact pixel -> ground lookup, in the recording's site frame."""
    from calibration.masks import FORMAT, VERSION, LookupMasks
    from sim.recording import Recording

    rec = Recording(recording_dir)
    xyz, valid = rec.ground_lookup(camera)
    lat = np.full(valid.shape, np.nan)
    lon = np.full(valid.shape, np.nan)
    ll = rec.geo.to_geodetic(xyz[valid])
    lat[valid], lon[valid] = ll[:, 0], ll[:, 1]
    xy = np.where(valid[..., None], xyz[..., :2], np.nan).astype(np.float32)
    entry = next(c for c in rec.meta["cameras"] if c["name"] == camera)
    h, w = valid.shape
    meta = {"format": FORMAT, "version": VERSION, "kind": entry["kind"], "width": w, "height": h,
            "camera": entry, "geo_origin": rec.meta["site"]["origin"], "source": "exact ground lookup (test)"}
    return LookupMasks(lat, lon, xy, valid, meta).save(path)


def export_tiny_detector(path: Path) -> Path:
    """An untrained, tiny detector as ONNX (its heat map is ~flat at sigmoid(-4) ~ 0.018)."""
    import torch

    from training.export import export_onnx
    from training.model import Detector, DetectorConfig

    torch.manual_seed(0)
    model = Detector(DetectorConfig(width_mult=0.25, decoder_channels=16, head_channels=8, stride=4))
    export_onnx(model, path, None, (64, 64))
    return path


def labels_of_image(recording_dir: Path) -> Callable[[np.ndarray], object]:
    """grey image of one of the recording's frames -> that frame's Sample (training.data), found by its pixels (for
    test detectors made from the labels themselves)."""
    from training.data import samples_from_recording

    labels = {}
    for ref in samples_from_recording(recording_dir):
        s = ref.load()
        labels[(s.image.shape, int(s.image.sum()))] = s
    return lambda grey: labels[(grey.shape, int(grey.sum()))]


def site_config(recording_dir: Path, masks: str = f"masks/{CAMERA}.npz") -> dict:
    """site.yaml of a one-camera site on the recording. The detector's threshold is below the untrained
    net's flat heat map, so every frame has detections (top-k): these tests check transport, not accuracy."""
    import json

    meta = json.loads((Path(recording_dir) / "recording.json").read_text())
    cam = next(c for c in meta["cameras"] if c["name"] == CAMERA)
    return {
        "site": meta["site"]["name"],
        "origin": meta["site"]["origin"],
        "cameras": [{"name": CAMERA, "kind": cam["kind"], "width": cam["width"], "height": cam["height"],
                     "masks": masks}],
        "bus": {"mode": "peer"},
        "ingest": {"source": str(Path(recording_dir).resolve()), "pace": "max", "encoding": "gray8",
                   "decode_long_side": 640},
        "detect": {"model": "model.onnx", "model_gpu": None, "threads": 1, "score_thr": 0.01},
        "fuse_track": {"tick_ms": 100.0},
    }


def write_site(folder: Path, config: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "site.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


# --- ports and processes --------------------------------------------------------------------------------------------


def free_port_base(span: int = 10, tries: int = 200) -> int:
    """A port base in 20000-60000 (step 10) whose `span` ports are all free on loopback now."""
    for _ in range(tries):
        base = random.randrange(20000, 60000, 10)
        socks = []
        try:
            for port in range(base, base + span):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no {span} free consecutive ports found")


def bus_sets(port_base: int) -> list[str]:
    """--set flags that put a service on this test's bus and make it dial the test's peer (port_base + 4), so
    the link is up as soon as the service is (no waiting for Zenoh's connect retries)."""
    return [f"bus.port_base={port_base}", f"bus.connect=[tcp/127.0.0.1:{port_base + 4}]"]


def service_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROADSIDE_")}
    env.update(PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    return env


class ServiceProcess:
    """One service as an OS process (its own process group); stderr goes to `log_path`."""

    def __init__(self, service: str, site: Path, sets: list[str], log_path: Path, env: dict | None = None) -> None:
        """`env`: ROADSIDE_* variables for the service (as compose.yaml gives them), over a clean environment."""
        cmd = [sys.executable, "-m", f"services.{service}", "--site", str(site)]
        for s in sets:
            cmd += ["--set", s]
        self.service = service
        self.log_path = log_path
        with open(log_path, "wb") as err:
            self.proc = subprocess.Popen(cmd, cwd=REPO, env={**service_env(), **(env or {})}, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"{self.service} still running after {timeout_s} s; log:\n{self.log()}") from None

    def terminate(self, timeout_s: float = 30.0) -> int:
        if self.running():
            self.proc.send_signal(signal.SIGTERM)
        return self.wait(timeout_s)

    def kill(self) -> int:
        if self.running():
            self.proc.kill()
        return self.proc.wait()


def wait_until(condition: Callable[[], object], timeout_s: float, interval_s: float = 0.05) -> bool:
    """Poll `condition` until it is true (returns True) or `timeout_s` passes (returns False)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(interval_s)


# --- the test's own peer on the bus ---------------------------------------------------------------------------------


class Peer:
    """A Zenoh session on the test's bus (listening on port_base + 4) that keeps what its subscribers get."""

    def __init__(self, port_base: int) -> None:
        import zenoh

        from shared.bus import BadInput, zenoh_config
        from shared.settings import BusSettings

        self.session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), None, client_index=1))
        self.bad = BadInput("test-peer")
        self.receivers: dict = {}
        self.got: dict[str, list] = {}
        self.tokens: list = []

    def subscribe(self, name: str, key: str, kind) -> None:
        from shared.bus import Receiver

        self.receivers[name] = Receiver(self.session, key, kind, self.bad, fifo=100_000)
        self.got[name] = []

    def poll(self) -> None:
        for name, r in self.receivers.items():
            self.got[name] += r.poll()

    def wait_for(self, condition: Callable[[], object], timeout_s: float) -> bool:
        def check() -> object:
            self.poll()
            return condition()

        return wait_until(check, timeout_s, 0.02)

    def put(self, key: str, payload: bytes) -> None:
        """Publish, blocking rather than dropping when Zenoh's queue is full: the services' default (drop)
        loses most 32 MB messages (hundreds of fragments), and a test must deliver its oversized frame."""
        import zenoh

        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def wait_alive(self, key: str, want: int = 1, timeout_s: float = 60.0) -> int:
        from shared.bus import wait_for_peers

        return wait_for_peers(self.session, key, want, timeout_s)

    def declare_tokens(self, keys: list[str]) -> None:
        self.tokens += [self.session.liveliness().declare_token(k) for k in keys]

    def close(self) -> None:
        for t in self.tokens:
            t.undeclare()
        for r in self.receivers.values():
            r.undeclare()
        self.session.close()


# --- a live camera --------------------------------------------------------------------------------------------------


@contextmanager
def mjpeg_camera(frame: Callable[[int], bytes], count: int, period_s: float, port: int = 0) -> Iterator[str]:
    """An MJPEG-over-HTTP camera on loopback (`port`, 0: any free one): each connection gets `count` JPEGs
    (`frame(k)`), `period_s` apart, then the connection drops (a camera's reboot, a network blip, or simply the end).
    Yields the stream's URL."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
    from threading import Thread

    class Camera(BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            try:
                for k in range(count):
                    jpg = frame(k)
                    self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpg)
                                     + jpg + b"\r\n")
                    self.wfile.flush()
                    time.sleep(period_s)
            except OSError:
                pass  # the reader hung up
            self.close_connection = True

    server = ThreadingHTTPServer(("127.0.0.1", port), Camera)
    Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/stream.mjpg"
    finally:
        server.shutdown()
