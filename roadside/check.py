"""`roadside check`: a site's pre-flight, every service's start-up checks at once, before `roadside up` or
`docker compose up`.

Each service refuses to start on a bad site (a missing masks file, a model that does not load, a source not found)
with one error line, and under compose it is restarted, ever more slowly, to fail the same way; with four services
the errors come one restart at a time. This runs what each service runs at start (the same functions) and reports
every problem at once, with what it found where all is well: each camera's masks and how much of its image they
cover, the detector and the providers it runs on (one inference per camera size), the sources (each camera's first
frame read and checked against the camera's size, recorded frames' spans), fusion's camera positions, the files the
services write (nothing is made: a folder to be made is said to be), the GPU model opened on the CPU where no GPU
would load it, each service's Zenoh configuration and whether the bus's ports are free. What passes with something
the services work around (a bad first frame ingest skips, too little disk for the frames' recording, which then
pauses, a camera without frames in the played slice) is a warning.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from shared.settings import Settings

FIRST_FRAMES = 5  # frames tried per camera: ingest skips a bad one and plays the next
LIVE_READ_S = 10.0  # how long live cameras and video files may take to give their first frames


@dataclass
class Check:
    """One check: `name` (what was checked), `ok`, `detail` (what was found, or the error), `warning`: passed, but
    with something the services work around that a person should know (the detail says what)."""

    name: str
    ok: bool
    detail: str
    warning: bool = False


class Warned(Exception):
    """A check that passes with a warning: its text is the detail."""


def _failed(name: str, exc: Exception) -> Check:
    return Check(name, False, str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}")


def _run(name: str, fn: Callable[[], str]) -> Check:
    try:
        return Check(name, True, fn())
    except Warned as w:
        return Check(name, True, str(w), warning=True)
    except Exception as exc:  # every failure is reported, the checks after it still run
        return _failed(name, exc)


def check_masks(settings: Settings, camera: str) -> str:
    from services.localize.__main__ import camera_masks

    cam = settings.camera(camera)
    masks = camera_masks(settings, cam)
    share = float(masks.valid.mean())
    n = len(cam.exclude_px or ())
    zones = f" ({n} exclusion zone{'s' * (n > 1)})" if n else ""
    return (f"{settings.path(cam.masks).resolve()}: {masks.shape[1]}x{masks.shape[0]}, ground lookup for {share:.0%} "
            f"of the image{zones}")


def check_detector(settings: Settings) -> str:
    from services.detect.__main__ import load_detector
    from services.ingest.__main__ import decode_scale_for

    detector = load_detector(settings)
    timings = []
    for cam in settings.cameras:  # one inference at each camera's size, as detect gets its frames
        s = decode_scale_for(cam.width, cam.height, settings.ingest.decode_long_side)
        grey = np.zeros((cam.height // s, cam.width // s), np.uint8)
        t = time.perf_counter()
        detector.detect(grey, 1.0 / s, cam.detect_area_px)
        timings.append(f"{cam.name} {(time.perf_counter() - t) * 1e3:.0f} ms")
    runs_on = ", ".join(detector.providers)
    return f"{Path(detector.path).resolve()} on {runs_on}; one blank frame each: {', '.join(timings)}"


def _gpu_here() -> bool:
    """Whether this ONNX Runtime has a GPU provider (the detector check then loads the GPU model itself)."""
    from shared.inference import available_providers

    return any(p != "CPUExecutionProvider" for p in available_providers())


def check_gpu_model(settings: Settings) -> str:
    """The GPU model (detect.model_gpu) where this machine runs the CPU one: opened on the CPU and run once, so that a
    missing or broken fp16 file is found here rather than on the cabinet's GPU."""
    from shared.inference import OnnxDetector

    path = settings.path(settings.detect.model_gpu)
    if not path.is_file():  # detect then runs the CPU model on the GPU
        raise Warned(f"detect.model_gpu: {path} not found: a GPU would run detect.model instead (give the fp16 "
                     "file, or set model_gpu to null)")
    cam = settings.cameras[0]
    detector = OnnxDetector(path, providers=["CPUExecutionProvider"], threads=1, score_thr=settings.detect.score_thr,
                            mirror=settings.detect.mirror)
    detector.detect(np.zeros((min(cam.height, 480), min(cam.width, 640)), np.uint8))
    return f"{path.resolve()}: opens and runs (here on the CPU, for a GPU provider at the cabinet)"


def check_sources(settings: Settings, live: bool = True) -> list[Check]:
    """The source opened as ingest opens it, then each camera's first frames made into a Frame's image as ingest
    makes them (decoded, the size checked against the camera's): the first good one passes, with a warning when
    frames before it are bad (ingest skips them). Recorded files are read camera by camera; live streams and video
    files are played until each camera has given a frame (live streams only with `live`: else not even opened)."""
    from services.ingest.__main__ import play_window, site_sources
    from services.ingest.sources import open_source

    cfg = settings.ingest
    cams = {c.name: c for c in settings.cameras}
    main, own = site_sources(settings)
    streams = sorted({s for s in (main, *own.values()) if s and "://" in s})
    if streams and not live:
        if cfg.play_from is not None or cfg.play_until is not None:  # as ingest refuses it, without opening them
            return [Check("source", False, "ingest.play_from / play_until apply to recorded files, not to live "
                                           f"streams ({', '.join(streams)})")]
        return [Check("source", True, f"live streams not read (--no-live): {', '.join(streams)}")]
    stop = threading.Event()  # ends the reader threads of live streams, and their reconnecting
    try:
        try:
            source = open_source(main, list(cams), own, cfg.fps, cfg.tzinfo(), stop)
            play_window(cfg, source)  # as ingest cuts it to ingest.play_from / play_until
        except Exception as exc:  # reported as the check's failure
            return [_failed("source", exc)]
        frames, recorded = _first_frames(source, set(cams))
    finally:
        stop.set()
    sliced = cfg.play_from is not None or cfg.play_until is not None
    return [_run(f"source {name}", lambda name=name: _camera_frames(settings, cams[name], frames.get(name, []),
                                                                   recorded.get(name), sliced))
            for name in cams]


def _first_frames(source, cameras: set[str]) -> tuple[dict[str, list], dict[str, list[int]]]:
    """Each camera's first FIRST_FRAMES frames, and for recorded files each camera's capture times."""
    from services.ingest.sources import SourceFrame

    frames: dict[str, list] = {}
    items = getattr(source, "items", None)
    if items:  # recorded files: each camera's own first files, however late it starts
        times: dict[str, list[int]] = {}
        for t, cam, path in items:
            times.setdefault(cam, []).append(t)
            if cam in cameras and len(frames.setdefault(cam, [])) < FIRST_FRAMES:
                try:
                    frames[cam].append(SourceFrame(cam, t, jpeg=path.read_bytes(), origin=str(path)))
                except OSError as exc:
                    frames[cam].append(SourceFrame(cam, t, origin=str(path), error=f"cannot read {path}: {exc}"))
        return frames, times
    deadline = time.monotonic() + LIVE_READ_S
    for sf in source:
        if sf.camera in cameras and len(frames.setdefault(sf.camera, [])) < FIRST_FRAMES:
            frames[sf.camera].append(sf)
        done = all(len(frames.get(c, ())) >= FIRST_FRAMES or any(not f.error for f in frames.get(c, ()))
                   for c in cameras)
        if done or time.monotonic() > deadline:
            break
    return frames, {}


def _camera_frames(settings: Settings, cam, frames: list, times: list[int] | None, sliced: bool = False) -> str:
    from services.ingest.__main__ import decode_scale_for, to_frame_fields

    if not frames and sliced:  # the others play
        raise Warned(f"camera {cam.name}: no frame within ingest.play_from / play_until")
    if not frames:
        raise ValueError(f"camera {cam.name}: no frame within {LIVE_READ_S:.0f} s of the source")
    bad = []
    for sf in frames:
        try:
            if sf.error:
                raise ValueError(sf.error)
            scale = decode_scale_for(cam.width, cam.height, settings.ingest.decode_long_side)
            fields = to_frame_fields(sf, cam, settings.ingest.encoding, scale)
        except (ValueError, cv2.error) as exc:
            bad.append(str(exc))
            continue
        size = f"{cam.width}x{cam.height}, published at {fields['width']}x{fields['height']}"
        where = f"{Path(sf.origin).resolve()}" if times else (sf.origin or "stream")
        first = "the first good one" if bad else "the first"
        found = f"{len(times)} frames over {(times[-1] - times[0]) / 1e9:.1f} s, {first} {where}: {size}" \
            if times else f"{where}: {size}"
        if bad:
            raise Warned(f"{found}; {len(bad)} before it refused (ingest skips them): {bad[0]}")
        return found
    raise ValueError(bad[0] + (f" (and the {len(bad) - 1} frames after it)" if len(bad) > 1 else ""))


def check_fusion(settings: Settings) -> str:
    from services.fuse_track.__main__ import build

    fusion, _, _, positions, _ = build(settings)
    where = ", ".join(f"{c} ({x:.1f}, {y:.1f}) m" for c, (x, y) in positions.items())
    own = [r.name for r in fusion.regions if r.polygon_xy is not None]
    rest = [r.name for r in fusion.regions if r.polygon_xy is None]
    regions = [f"{', '.join(own)}: the region_m of the site file"] if own else []
    if rest:
        regions.append(f"{', '.join(rest)}: the ground nearer {'it' if len(rest) == 1 else 'each'} than any other "
                       "camera")
    return f"cameras at {where}; regions: {'; '.join(regions)}"


def check_writable(folder: Path, setting: str, min_free_mb: float = 0.0, file: Path | None = None) -> str:
    """A folder a service writes to (`setting` names it; `file`: the file it writes there, named instead): there and
    writable, or one the service can make (the check makes nothing), with its free space."""
    folder = folder.resolve()
    there = next(p for p in (folder, *folder.parents) if p.exists())
    if not there.is_dir():
        raise ValueError(f"{setting}: {folder} cannot be made: {there} is a file, not a folder")
    if not os.access(there, os.W_OK | os.X_OK):
        raise ValueError(f"{setting}: {there} is not writable by this user (uid {os.getuid()})")
    free_mb = shutil.disk_usage(there).free / 1e6
    made = "writable" if there == folder else f"to be made in {there}"
    found = f"{setting}: {file or folder}: {made}, {free_mb / 1e3:.1f} GB free"
    if free_mb < min_free_mb:
        raise Warned(f"{found}: under the {min_free_mb:.0f} MB below which recording pauses")
    return found


def check_tracks_file(settings: Settings) -> str:
    """fuse_track's recording: a file it can append to, in a folder it can make."""
    path = settings.path(settings.fuse_track.record).resolve()
    if path.is_dir():
        raise ValueError(f"fuse_track.record: {path} is a folder; name the file to append the tracks to "
                         "(e.g. tracks.jsonl in it)")
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"fuse_track.record: {path} is not writable by this user (uid {os.getuid()})")
    return check_writable(path.parent, "fuse_track.record", file=path)


def check_frames_folder(settings: Settings) -> str:
    """ingest's recording of the frames: outside the folder it plays, in a folder it can make, with room."""
    from services.ingest.__main__ import record_folder

    return check_writable(record_folder(settings), "ingest.record_dir", settings.ingest.record_min_free_mb)


def check_bus(settings: Settings) -> str:
    """Each service's Zenoh configuration built as it builds it (TLS files, endpoints), and in peer mode the ports."""
    from shared.bus import ports_in_use, zenoh_config
    from shared.keys import SERVICES

    bus = settings.bus
    for service in SERVICES:
        zenoh_config(bus, service)
    if bus.mode == "peer" and bus.listen:
        raise ValueError(f"bus.listen {bus.listen}: in peer mode on one machine every service would listen there, "
                         "and only the first can; give the endpoint to one service only (its own environment, "
                         "ROADSIDE_BUS__LISTEN) or connect through a router")
    if bus.mode != "peer":
        return f"client mode through {', '.join(bus.connect)} (the router is not checked)"
    busy = ports_in_use(bus)
    if busy:
        raise ValueError(f"ports in use: {', '.join(busy)}: another pipeline runs on this machine (`roadside status`), "
                         "or give this one its own bus.port_base")
    return f"peer mode on {bus.host}, ports {bus.port_base}-{bus.port_base + 3} free"


def check_site(settings: Settings, live: bool = True) -> list[Check]:
    """Every check of a loaded site, in the pipeline's order."""
    out = [_run(f"masks {c.name}", lambda c=c: check_masks(settings, c.name)) for c in settings.cameras]
    out.append(_run("detector", lambda: check_detector(settings)))
    if settings.detect.model_gpu is not None and not _gpu_here() and settings.path(
            settings.detect.model_gpu) != settings.path(settings.detect.model):
        out.append(_run("detector (GPU)", lambda: check_gpu_model(settings)))
    out += check_sources(settings, live)
    out.append(_run("fusion", lambda: check_fusion(settings)))
    if settings.fuse_track.record is not None:
        out.append(_run("tracks recording", lambda: check_tracks_file(settings)))
    if settings.ingest.record_dir is not None:
        out.append(_run("frames recording", lambda: check_frames_folder(settings)))
    out.append(_run("bus", lambda: check_bus(settings)))
    return out


def as_json(site: str, checks: list[Check]) -> dict:
    return {"site": site, "ok": all(c.ok for c in checks), "checks": [asdict(c) for c in checks]}
