"""localize: lift every camera's detections to the ground with its calibrated lookup masks.

`python -m services.localize --site SITE`

Loads each camera's masks file (`cameras[].masks`, from `roadside calibrate`) at start: a missing
or unreadable one stops the service with one error line. Subscribes to
`roadside/<site>/cam/*/detections`, publishes Objects (site metres, latitude/longitude, world yaw,
size) on `roadside/<site>/cam/<camera>/objects`, dropping detections outside the calibrated area and those
inside the ground footprint of a higher-scoring one (`localize.footprint_overlap`; `lift.lift_kept`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from calibration.masks import excluded, load_masks
from services.localize.lift import GroundLookup, lift_kept
from shared.bus import BadInput, Receiver, Stopper, declare_alive, open_session
from shared.codec import encode
from shared.geo import GeoFrame
from shared.keys import all_cameras_key, camera_key
from shared.messages import Detections, Objects
from shared.service import run
from shared.settings import Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.localize")
IDLE_WAIT_S = 0.1


def load_all_masks(settings: Settings) -> dict[str, GroundLookup]:
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
        out[cam.name] = GroundLookup(masks, site_geo)
        del masks
    return out


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


def main(settings: Settings, stopper: Stopper) -> int:
    masks = load_all_masks(settings)
    cams = list(masks)
    bad = BadInput("localize")
    session = open_session(settings, "localize")
    try:
        receiver = Receiver(session, all_cameras_key(settings.site, "detections"), Detections, bad)
        pubs = {c: session.declare_publisher(camera_key(settings.site, c, "objects")) for c in cams}
        tokens = declare_alive(session, settings.site, "localize", cams)  # after the subscriber: ready
        status = StatusReporter(session, settings.site, "localize", bad, settings.bus.status_period_s)
        done = 0
        while not stopper.is_set():
            msgs = receiver.poll()
            if not msgs:
                receiver.wait(IDLE_WAIT_S)
                continue
            status.count("detections_in", len(msgs))
            for det in msgs:
                if det.camera not in masks:
                    bad(f"detections from camera {det.camera!r}, not at this site", det.camera)
                    continue
                try:
                    msg = objects_message(det, masks[det.camera], settings.localize.heading_step_px,
                                          settings.localize.footprint_overlap, settings.localize.footprint_merge)
                except ValueError as exc:
                    bad(str(exc), det.camera)
                    continue
                pubs[det.camera].put(encode(msg))
                status.count("objects_out", output=True)
                done += 1
        log.info("stopped: %d messages localized, %d bad %s", done, bad.total, dict(bad.counts))
        status.close()
        del tokens
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run("localize", main))
