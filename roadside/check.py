"""`roadside check`: a site's pre-flight, every service's start-up checks at once, before `roadside up` or
`docker compose up`.

Each service refuses to start on a bad site (a missing masks file, a model that does not load, a source not found)
with one error line, and under compose it is restarted, ever more slowly, to fail the same way; with four services
the errors come one restart at a time. This runs what each service runs at start (the same functions) and reports
every problem at once, with what it found where all is well: each camera's masks and how much of its image they
cover, the detector and the providers it runs on (one inference per camera size), the sources (each camera's first
frame read and checked against the camera's size, recorded frames' spans), fusion's camera positions, the files the
services write, and whether the bus's ports are free.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from shared.settings import Settings

SOURCE_SCAN_MAX = 2000  # frames read from a recorded source to find each camera's first one
LIVE_READ_S = 10.0  # how long a live camera may take to give its first frame


@dataclass
class Check:
    """One check: `name` (what was checked), `ok`, `detail` (what was found, or the error)."""

    name: str
    ok: bool
    detail: str


def _failed(name: str, exc: Exception) -> Check:
    return Check(name, False, str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}")


def _run(name: str, fn: Callable[[], str]) -> Check:
    try:
        return Check(name, True, fn())
    except Exception as exc:  # every failure is reported, the checks after it still run
        return _failed(name, exc)


def check_masks(settings: Settings, camera: str) -> str:
    from services.localize.__main__ import camera_masks

    cam = settings.camera(camera)
    masks = camera_masks(settings, cam)
    share = float(masks.valid.mean())
    zones = f" ({len(cam.exclude_px)} exclusion zones)" if cam.exclude_px else ""
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


def check_sources(settings: Settings, live: bool = True) -> list[Check]:
    """The source opened as ingest opens it, then each camera's first frame read and made into a Frame's image as
    ingest makes it (decoded, its size checked against the camera's). Live streams are read only with `live`."""
    from services.ingest.__main__ import decode_scale_for, to_frame_fields
    from services.ingest.sources import open_source

    cfg = settings.ingest
    cams = {c.name: c for c in settings.cameras}

    def resolve(src: str | None) -> str | None:
        return src if not src or "://" in src else str(settings.path(src))

    try:
        source = open_source(resolve(cfg.source) or "", list(cams), {c.name: resolve(c.source) for c in cams.values()},
                             cfg.fps, cfg.tzinfo())
    except Exception as exc:  # reported as the check's failure
        return [_failed("source", exc)]
    parts = getattr(source, "parts", [source])
    if any(getattr(p, "live", False) for p in parts) and not live:
        return [Check("source", True, "live streams, not read (--no-live)")]
    recorded: dict[str, list[int]] = {}  # recorded files: each camera's capture times
    for t, cam, _ in getattr(source, "items", None) or []:
        recorded.setdefault(cam, []).append(t)
    first = {}
    deadline = time.monotonic() + LIVE_READ_S
    for n, sf in enumerate(source):
        if sf.camera in cams and sf.camera not in first:
            first[sf.camera] = sf
        if len(first) == len(cams) or n >= SOURCE_SCAN_MAX or time.monotonic() > deadline:
            break
    out = []
    for name, cam in cams.items():
        def one(name=name, cam=cam) -> str:
            sf = first.get(name)
            if sf is None:
                raise ValueError(f"camera {name}: no frame within the first {SOURCE_SCAN_MAX} frames or "
                                 f"{LIVE_READ_S:.0f} s of the source")
            if sf.error:
                raise ValueError(sf.error)
            scale = decode_scale_for(cam.width, cam.height, cfg.decode_long_side)
            fields = to_frame_fields(sf, cam, cfg.encoding, scale)
            size = f"{cam.width}x{cam.height}, published at {fields['width']}x{fields['height']}"
            times = recorded.get(name)
            if not times:
                return f"{sf.origin or 'stream'}: {size}"
            first_file = Path(sf.origin).resolve()
            return f"{len(times)} frames over {(times[-1] - times[0]) / 1e9:.1f} s, the first {first_file}: {size}"
        out.append(_run(f"source {name}", one))
    return out


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


def check_writable(folder: Path, setting: str, min_free_mb: float = 0.0) -> str:
    """A folder a service writes to (`setting` names it): there and writable, or one the service can make (the
    check makes nothing), with its free space."""
    folder = folder.resolve()
    there = next(p for p in (folder, *folder.parents) if p.exists())
    if not there.is_dir():
        raise ValueError(f"{setting}: {folder} cannot be made: {there} is a file, not a folder")
    if not os.access(there, os.W_OK | os.X_OK):
        raise ValueError(f"{setting}: {there} is not writable by this user (uid "
                         f"{os.getuid()})")
    free_mb = shutil.disk_usage(there).free / 1e6
    if free_mb < min_free_mb:
        raise ValueError(f"{setting}: {there}: {free_mb:.0f} MB free, under the {min_free_mb:.0f} MB it needs")
    made = "writable" if there == folder else f"to be made in {there}"
    return f"{setting}: {folder}: {made}, {free_mb / 1e3:.1f} GB free"


def check_bus(settings: Settings) -> str:
    from shared.bus import ports_in_use

    bus = settings.bus
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
    out += check_sources(settings, live)
    out.append(_run("fusion", lambda: check_fusion(settings)))
    if settings.fuse_track.record is not None:
        out.append(_run("tracks recording", lambda: check_writable(settings.path(settings.fuse_track.record).parent,
                                                                    "fuse_track.record")))
    if settings.ingest.record_dir is not None:
        out.append(_run("frames recording", lambda: check_writable(settings.path(settings.ingest.record_dir),
                                                                    "ingest.record_dir",
                                                                    settings.ingest.record_min_free_mb)))
    out.append(_run("bus", lambda: check_bus(settings)))
    return out


def as_json(site: str, checks: list[Check]) -> dict:
    return {"site": site, "ok": all(c.ok for c in checks), "checks": [asdict(c) for c in checks]}
