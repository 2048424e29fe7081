"""localize: lift every camera's detections to the ground with its calibrated lookup masks.

`python -m services.localize --site SITE`

Loads each camera's masks file (`cameras[].masks`, from `roadside calibrate`) at start: a missing
or unreadable one stops the service with one error line. The site frame is the site file's `origin`, else the
first camera's masks' origin (as fuse_track's): masks made around another origin are re-expressed in it.
Subscribes to `roadside/<site>/cam/*/detections` (the key says whose they are), publishes Objects (site metres,
latitude/longitude, world yaw, size) on `roadside/<site>/cam/<camera>/objects`, dropping detections outside the
calibrated area and those inside the ground footprint of a higher-scoring one (`localize.footprint_overlap`;
`lift.lift_kept`). Detections of another site, of another camera than their key's, or on the key of a camera
that is not at this site are bad input: counted and skipped.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from calibration.masks import LookupMasks, excluded, load_masks
from services.localize.lift import GroundLookup, lift_kept
from shared.bus import BadInput, Receiver, Stopper, declare_alive, open_session
from shared.codec import encode
from shared.geo import GeoFrame
from shared.keys import all_cameras_key, camera_key, camera_of
from shared.messages import Detections, Objects
from shared.service import run
from shared.settings import CameraSettings, Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.localize")
IDLE_WAIT_S = 0.1


def masks_camera(meta: dict) -> str | None:
    """The camera a masks file was calibrated for: the one its landmark file names (`landmarks_camera`, since
    2026-11-30), else that file's name without its suffix (`landmarks/NE.json`); None when unknown."""
    named = meta.get("landmarks_camera")
    if named:
        return str(named)
    file = meta.get("landmarks_file")
    return Path(str(file)).stem if file else None


def camera_masks(settings: Settings, cam: CameraSettings) -> LookupMasks:
    """A camera's lookup masks (site metres, no latitude and longitude) with its exclusion zones taken out;
    ValueError when it has none, or they are not its image's size."""
    if cam.masks is None:
        raise ValueError(f"camera {cam.name}: no lookup masks in the site file (cameras[].masks)")
    path = settings.path(cam.masks)
    masks = load_masks(path, with_latlon=False)
    if masks.shape != (cam.height, cam.width):
        raise ValueError(f"camera {cam.name}: masks {path} are {masks.shape[1]}x{masks.shape[0]}, the camera is "
                         f"{cam.width}x{cam.height}: set the camera's width and height to its images' size, or "
                         "calibrate it again at that size (roadside calibrate --width --height)")
    other = masks_camera(masks.meta)
    if other != cam.name and other in {c.name for c in settings.cameras}:
        raise ValueError(f"camera {cam.name}: masks {path} were calibrated from camera {other}'s landmarks "
                         f"({masks.meta.get('landmarks_file')}): are the masks of {cam.name} and {other} swapped in "
                         "the site file? (If the cameras were renamed: give each landmark file its camera's new name, "
                         "`camera` in its header, and calibrate again)")
    if cam.exclude_px:
        before = int(masks.valid.sum())
        masks.valid = excluded(masks.valid, cam.exclude_px)
        log.info("camera %s: %d exclusion polygon(s) take %d calibrated pixels out", cam.name,
                 len(cam.exclude_px), before - int(masks.valid.sum()))
    return masks


def load_all_masks(settings: Settings) -> dict[str, GroundLookup]:
    """Each camera's lookup, in the site frame: settings.origin, else the first camera's masks' origin (fuse_track's
    `camera_positions` takes the same), every other camera's metres re-expressed in it."""
    site_geo = GeoFrame.from_dict(settings.origin) if settings.origin else None
    out = {}
    for cam in settings.cameras:
        masks = camera_masks(settings, cam)
        site_geo = site_geo or masks.geo
        if masks.geo != site_geo:
            log.info("camera %s: masks made around another origin, re-expressed in the site frame", cam.name)
        out[cam.name] = GroundLookup(masks, site_geo)
        del masks
    return out


def in_capture_order(msgs: list[tuple[str, Detections]]) -> list[tuple[str, Detections]]:
    """(camera, Detections) waiting now, in capture-time order across the cameras (stable: each camera's are in it
    already): after a stall, one camera's backlog published before the others' would let fuse_track close the
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


def main(settings: Settings, stopper: Stopper) -> int:
    masks = load_all_masks(settings)
    cams = list(masks)
    bad = BadInput("localize")
    session = open_session(settings, "localize")
    try:
        # one subscriber on every camera's key; the key a message came on says whose it is
        receiver = Receiver(session, all_cameras_key(settings.site, "detections"), Detections, bad)
        pubs = {c: session.declare_publisher(camera_key(settings.site, c, "objects")) for c in cams}
        tokens = declare_alive(session, settings.site, "localize", cams)  # after the subscriber: ready
        status = StatusReporter(session, settings.site, "localize", bad, settings.bus.status_period_s)
        done = 0
        while not stopper.is_set():
            msgs = in_capture_order([(camera_of(key), det) for key, det in receiver.poll_keyed()])
            if not msgs:
                receiver.wait(IDLE_WAIT_S)
                continue
            status.count("detections_in", len(msgs))
            for camera, det in msgs:
                if camera not in masks:
                    bad(f"detections from camera {camera!r}, not at this site", camera)
                    continue
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
        del tokens
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run("localize", main))
