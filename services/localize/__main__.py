"""localize: lift every camera's detections to the ground with its calibrated lookup masks.

`python -m services.localize --site SITE`

Loads each camera's masks file (`cameras[].masks`, from `roadside calibrate`) at start: a missing
or unreadable one stops the service with one error line. The site frame is the site file's `origin`, else the
first camera's masks' origin (as fuse_track's): masks made around another origin are re-expressed in it.
Subscribes to `roadside/<site>/cam/<camera>/detections` of each camera, publishes Objects (site metres,
latitude/longitude, world yaw, size) on `roadside/<site>/cam/<camera>/objects`, dropping detections outside the
calibrated area and those inside the ground footprint of a higher-scoring one (`localize.footprint_overlap`;
`lift.lift_kept`). Detections of another site, of another camera than their key's, or on the key of a camera
that is not at this site are bad input: counted and skipped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

import numpy as np

from calibration.masks import excluded, load_masks
from services.localize.lift import GroundLookup, lift_kept
from shared.bus import FIFO_BYTES, BadInput, Receiver, Stopper, declare_alive, open_session
from shared.codec import encode
from shared.geo import GeoFrame
from shared.keys import all_cameras_key, camera_key
from shared.messages import Detections, Objects
from shared.service import run
from shared.settings import Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.localize")
IDLE_WAIT_S = 0.1
MAX_STRAY_NAMES = 64  # cameras not at this site counted by name (StrayCameras)


def load_all_masks(settings: Settings) -> dict[str, GroundLookup]:
    """Each camera's lookup, in the site frame: settings.origin, else the first camera's masks' origin (fuse_track's
    `camera_positions` takes the same), every other camera's metres re-expressed in it."""
    site_geo = GeoFrame.from_dict(settings.origin) if settings.origin else None
    out = {}
    for cam in settings.cameras:
        if cam.masks is None:
            raise ValueError(f"camera {cam.name}: no lookup masks in the site file (cameras[].masks)")
        masks = load_masks(settings.path(cam.masks), with_latlon=False)
        if masks.shape != (cam.height, cam.width):
            raise ValueError(f"camera {cam.name}: masks {settings.path(cam.masks)} are {masks.shape[1]}x"
                             f"{masks.shape[0]}, the camera is {cam.width}x{cam.height}")
        if cam.exclude_px:
            before = int(masks.valid.sum())
            masks.valid = excluded(masks.valid, cam.exclude_px)
            log.info("camera %s: %d exclusion polygon(s) take %d calibrated pixels out", cam.name,
                     len(cam.exclude_px), before - int(masks.valid.sum()))
        site_geo = site_geo or masks.geo
        if masks.geo != site_geo:
            log.info("camera %s: masks made around another origin, re-expressed in the site frame", cam.name)
        out[cam.name] = GroundLookup(masks, site_geo)
        del masks
    return out


def in_capture_order(msgs: list[tuple[str, Detections]]) -> list[tuple[str, Detections]]:
    """(camera, Detections) of every camera's queue, in capture-time order across the cameras (each queue is in
    it already): after a stall, one camera's backlog published before the others' would let fuse_track close the
    ticks the others still need, and drop them as late."""
    return sorted(msgs, key=lambda m: m[1].t_capture_ns)


def misaddressed(det: Detections, site: str, camera: str) -> str | None:
    """Why Detections that came on camera `camera`'s key of site `site` are not that camera's (bad input), None when
    they are."""
    if det.site != site:
        return f"detections of site {det.site!r} on the bus of site {site!r}"
    if det.camera != camera:
        return f"detections of camera {det.camera!r} on the key of camera {camera!r}"
    return None


def objects_message(det: Detections, masks: GroundLookup, step_px: float, footprint_overlap: float,
                    merge: bool) -> Objects:
    if (det.height, det.width) != masks.shape:
        raise ValueError(f"camera {det.camera}: detections for a {det.width}x{det.height} image, "
                         f"masks are {masks.shape[1]}x{masks.shape[0]}")
    lifted, k, size_lwh = lift_kept(masks, det, step_px, footprint_overlap, merge)
    f4 = np.float32
    return Objects(
        site=det.site, camera=det.camera, seq=det.seq, t_capture_ns=det.t_capture_ns,
        stamps=[*det.stamps, ("localize", time.time_ns())], infer_ms=det.infer_ms,
        xy=lifted.xy[k], latlon=lifted.latlon[k], yaw=lifted.yaw[k].astype(f4), size_lwh=size_lwh[k].astype(f4),
        vtype=det.vtype[k].astype(np.int8), score=det.score[k].astype(f4), uv=det.uv[k].astype(f4))


class StrayCameras:
    """Counts the messages on the detections keys of cameras that are not at this site, by the key's camera chunk
    (nothing is decoded; at most MAX_STRAY_NAMES names, the rest counted as "others"). `take()` gives {camera:
    messages} since the last call."""

    def __init__(self, session, site: str, cameras: set[str], wake: threading.Event) -> None:
        self.counts: Counter[str] = Counter()
        self.lock = threading.Lock()

        def on_sample(sample) -> None:
            camera = str(sample.key_expr).split("/")[3][:64]  # a match of roadside/<site>/cam/*/detections
            if camera not in cameras:
                with self.lock:
                    self.counts[camera if camera in self.counts or len(self.counts) < MAX_STRAY_NAMES
                                else "others"] += 1
                wake.set()

        self.sub = session.declare_subscriber(all_cameras_key(site, "detections"), on_sample)

    def take(self) -> dict[str, int]:
        with self.lock:
            out = dict(self.counts)
            self.counts.clear()
        return out


def main(settings: Settings, stopper: Stopper) -> int:
    masks = load_all_masks(settings)
    cams = list(masks)
    bad = BadInput("localize")
    session = open_session(settings, "localize")
    try:
        wake = threading.Event()
        # one subscriber per camera, so that the key a message came on is known; the FIFOs share one byte budget
        receivers = {c: Receiver(session, camera_key(settings.site, c, "detections"), Detections, bad, wake=wake,
                                 fifo_bytes=FIFO_BYTES // len(cams)) for c in cams}
        strays = StrayCameras(session, settings.site, set(cams), wake)
        pubs = {c: session.declare_publisher(camera_key(settings.site, c, "objects")) for c in cams}
        tokens = declare_alive(session, settings.site, "localize", cams)  # after the subscribers: ready
        status = StatusReporter(session, settings.site, "localize", bad, settings.bus.status_period_s)
        done = 0
        while not stopper.is_set():
            msgs = in_capture_order([(c, det) for c, r in receivers.items() for det in r.poll()])
            stray = strays.take()
            if not msgs and not stray:
                wake.wait(IDLE_WAIT_S)
                wake.clear()
                continue
            status.count("detections_in", len(msgs) + sum(stray.values()))
            for camera, count in stray.items():
                bad(f"detections from camera {camera!r}, not at this site", camera, count=count)
            for camera, det in msgs:
                if (reason := misaddressed(det, settings.site, camera)) is not None:
                    bad(reason, camera)
                    continue
                try:
                    msg = objects_message(det, masks[camera], settings.localize.heading_step_px,
                                          settings.localize.footprint_overlap, settings.localize.footprint_merge)
                except ValueError as exc:
                    bad(str(exc), camera)
                    continue
                pubs[camera].put(encode(msg))
                status.count("objects_out", output=True)
                done += 1
        log.info("stopped: %d messages localized, %d bad %s", done, bad.total, dict(bad.counts))
        status.close()
        strays.sub.undeclare()
        del tokens
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run("localize", main))
