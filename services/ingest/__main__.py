"""ingest: decode camera streams and publish Frames on `roadside/<site>/cam/<camera>/frame`.

`python -m services.ingest --site SITE [--set ingest.source=PATH] [--set ingest.pace=max]`

Playback pace: `1` real time, `N` N x real time, `max` as fast as the pipeline takes it (at most
`max_in_flight` frames published and not yet detected, by default as many as detect has workers, and
never more of one camera than detect's ring keeps; an acknowledgement that does not come within
`ingest.ack_timeout_s` is given up, so a detect restart does not stall playback). With `loop`, the source
repeats with capture times shifted so event time keeps increasing (each round `loop_period` after the one before). A
frame that cannot be decoded (corrupt JPEG) is counted, logged and skipped. Exits 0 when the source ends (with
`ingest.at_end` `idle`, as in compose.yaml, it stays up publishing nothing more until told to stop), 143 when told to
stop (SIGTERM, Ctrl-C). Started again while fuse_track runs (a restart), it goes on from fuse_track's latest tracks in
recorded files rather than from their start, in the round of a loop they reached (`resume_point`).
"""

from __future__ import annotations

import logging
import time
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from services.ingest.recorder import FrameRecorder, RecorderConfig, check_not_the_source
from services.ingest.sources import SourceFrame, open_source
from shared.bus import BadInput, Receiver, Stopper, declare_alive, open_session, wait_for_peers
from shared.codec import DecodeError, decode, encode
from shared.jpeg import decode_grey, jpeg_size
from shared.keys import LATEST_ANY_AGE, all_alive_key, all_cameras_key, camera_key, latest_tracks_key
from shared.messages import Detections, Frame, Tracks
from shared.service import run
from shared.settings import CameraSettings, IngestSettings, Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.ingest")
PIPELINE_WAIT_S = 60.0
LOOP_GAP_NS = 100_000_000  # with ingest.loop: from a round's last frame to the next round's first
RESUME_ASK_S = 1.0  # how long a starting ingest waits for fuse_track's latest tracks
# the exit status of an ingest told to stop (SIGTERM, Ctrl-C) before its source ended, or idle after it (at_end)
STOPPED = 128 + 15
REDUCED = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4}


def decode_scale_for(width: int, height: int, long_side: int) -> int:
    """The largest JPEG reduction (4, 2 or 1) that keeps an image's longer side at least `long_side` and divides
    both sides (a JPEG decoded at 1/s rounds an odd side up, and one scale must map the image back to the
    camera's size)."""
    return next((s for s in (4, 2) if max(width, height) // s >= long_side and width % s == 0 and height % s == 0), 1)


def to_frame_fields(sf: SourceFrame, cam: CameraSettings, encoding: str, decode_scale: int) -> dict:
    """The image part of a Frame: encoding, width, height, scale, data. ValueError for a bad image."""
    if encoding == "jpeg" and sf.jpeg is not None and sf.jpeg[:2] == b"\xff\xd8":  # passed through as it is
        size = jpeg_size(sf.jpeg)
        if size is None:
            raise ValueError(f"{sf.origin}: corrupt JPEG: no frame header")
        if size != (cam.width, cam.height):
            raise ValueError(f"{sf.origin}: JPEG is {size[0]}x{size[1]}, camera {cam.name} is {cam.width}x{cam.height}")
        return {"encoding": "jpeg", "width": cam.width, "height": cam.height, "scale": 1.0, "data": sf.jpeg}
    if sf.jpeg is not None:
        # the header's size first: OpenCV allocates what a header claims (up to 65535 x 65535)
        grey = decode_grey(sf.jpeg, cam.width, cam.height, REDUCED[decode_scale], decode_scale, what=str(sf.origin))
    else:
        img = sf.image
        grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if decode_scale > 1:
            grey = cv2.resize(grey, (grey.shape[1] // decode_scale, grey.shape[0] // decode_scale),
                              interpolation=cv2.INTER_AREA)
    full_w, full_h = grey.shape[1] * decode_scale, grey.shape[0] * decode_scale
    if abs(full_w - cam.width) > decode_scale or abs(full_h - cam.height) > decode_scale:
        raise ValueError(f"{sf.origin}: image is {full_w}x{full_h}, camera {cam.name} is {cam.width}x{cam.height}")
    scale = grey.shape[1] / cam.width
    if encoding == "jpeg":
        _, buf = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, 90])
        return {"encoding": "jpeg", "width": grey.shape[1], "height": grey.shape[0], "scale": scale,
                "data": buf.tobytes()}
    grey = np.ascontiguousarray(grey)
    return {"encoding": "gray8", "width": grey.shape[1], "height": grey.shape[0], "scale": scale,
            "data": grey.tobytes()}


class Pacer:
    """Real-time or N x real-time pacing on capture times."""

    def __init__(self, pace: str, stopper: Stopper) -> None:
        self.speed = None if pace == "max" else float(pace)
        self.stopper = stopper
        self.t0_ns = None
        self.wall0 = 0.0

    def wait(self, t_capture_ns: int) -> None:
        if self.speed is None:
            return
        if self.t0_ns is None:
            self.t0_ns, self.wall0 = t_capture_ns, time.monotonic()
            return
        due = self.wall0 + (t_capture_ns - self.t0_ns) / 1e9 / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            self.stopper.wait(delay)


class Acks:
    """Frames published and not yet detected (pace `max`): detections for (camera, seq) acknowledge. At most
    `limit` in all and `per_camera` of one camera (detect's ring keeps that many per camera: a frame more
    would push an unprocessed one out, and its acknowledgement would never come)."""

    def __init__(self, receiver: Receiver, limit: int, stopper: Stopper, timeout_s: float,
                 per_camera: int = 1) -> None:
        self.receiver, self.limit, self.stopper, self.per_camera = receiver, limit, stopper, per_camera
        self.timeout_s = timeout_s
        self.pending: dict[tuple[str, int], float] = {}
        self.timeouts = 0

    def drain(self) -> None:
        for msg in self.receiver.poll():
            assert isinstance(msg, Detections)
            self.pending.pop((msg.camera, msg.seq), None)

    def wait_for_room(self, camera: str) -> None:
        while True:
            self.drain()
            now = time.monotonic()
            for key, t in list(self.pending.items()):
                if now - t > self.timeout_s:
                    del self.pending[key]
                    self.timeouts += 1
            own = sum(1 for c, _ in self.pending if c == camera)
            if (len(self.pending) < self.limit and own < self.per_camera) or self.stopper.is_set():
                return
            self.receiver.wait(0.05)

    def sent(self, camera: str, seq: int) -> None:
        self.pending[(camera, seq)] = time.monotonic()


def in_window(items: list, window: tuple[int | None, int | None]) -> list:
    """The recorded files' (t_capture_ns, camera, path) items within ingest.play_from / play_until."""
    start, end = window
    return [i for i in items if (start is None or i[0] >= start) and (end is None or i[0] < end)]


def play_window(cfg: IngestSettings, source) -> tuple[int | None, int | None]:
    """ingest.play_from / play_until in ns for this source (a time of day on the day of its first frame), with the
    source's files cut to them, so that those outside are not even read (every part of a merged source); ValueError
    for a video file or a stream (their capture times are the clock's as they play), or when no frame is left."""
    if cfg.play_from is None and cfg.play_until is None:
        return None, None
    items = getattr(source, "items", None)
    if not items or any(getattr(p, "timed_by_clock", False) for p in (source, *getattr(source, "parts", ()))):
        raise ValueError(f"ingest.play_from / play_until ({cfg.play_from or 'open'} to {cfg.play_until or 'open'}) "
                         "apply to recorded files whose names carry their capture times (image folders, a simulator "
                         "recording): a video file's, a stream's or a folder timed by ingest.fps are timed by the "
                         "clock as they play")
    window = cfg.window_ns(items[0][0])
    for part in (source, *getattr(source, "parts", ())):
        part.items = in_window(part.items, window)
    if not source.items:
        when = " to ".join(datetime.fromtimestamp(t / 1e9, cfg.tzinfo()).strftime("%Y-%m-%d %H:%M:%S") for t in
                           (items[0][0], items[-1][0]))
        raise ValueError(f"no frame of the source lies within ingest.play_from {cfg.play_from or '(open)'} / "
                         f"play_until {cfg.play_until or '(open)'}; its frames run {when} ({cfg.timezone})")
    return window


def loop_period(source) -> int | None:
    """With ingest.loop, the time from one round's first frame to the next's: the span of the source's frames (cut to
    play_from / play_until by `play_window`) and `LOOP_GAP_NS`, for recorded files (a source with `items`, whose rounds
    a restart must find again); None for a video file (its rounds are spaced as played)."""
    items = getattr(source, "items", None)
    return items[-1][0] - items[0][0] + LOOP_GAP_NS if items else None


def resume_point(session, site: str, source, loop: bool = False) -> int | None:
    """Where a restarted ingest playing recorded files (a recording, image folders) goes on: the capture time of the
    newest tracks fuse_track holds (its latest-tracks query), when that lies within the files' own times (with
    `loop`, from their first on: in a later round, `loop_period`); None otherwise (a first start, a live or video
    source, another recording), when it plays from the start. Without it a restart would play the files from their
    start again, every frame late for fuse_track's closed ticks."""
    items = getattr(source, "items", None)
    if not items:
        return None
    # whatever its age: fuse_track sends nothing while ingest is down, and a restart takes seconds
    for reply in session.get(f"{latest_tracks_key(site)}?{LATEST_ANY_AGE}", timeout=RESUME_ASK_S):
        if reply.ok is None:
            continue
        try:
            t = decode(reply.ok.payload.to_bytes(), Tracks).t_capture_ns
        except DecodeError:
            return None
        return t if items[0][0] <= t and (loop or t < items[-1][0]) else None
    return None


def site_sources(settings: Settings) -> tuple[str, dict[str, str | None]]:
    """ingest.source and each camera's own source as ingest opens them: a stream URL as given, a path resolved against
    the site folder ("" and None where none is given)."""
    def resolve(src: str | None) -> str | None:
        return src if not src or "://" in src else str(settings.path(src))

    return resolve(settings.ingest.source) or "", {c.name: resolve(c.source) for c in settings.cameras}


def record_folder(settings: Settings) -> Path:
    """ingest.record_dir resolved against the site folder; ValueError when it overlaps a folder being played."""
    folder = settings.path(settings.ingest.record_dir)
    main, own = site_sources(settings)
    for played in {main, *own.values()}:
        check_not_the_source(folder, played)
    return folder


def main(settings: Settings, stopper: Stopper) -> int:
    cfg = settings.ingest
    cams = {c.name: c for c in settings.cameras}
    main_source, own_sources = site_sources(settings)
    source = open_source(main_source, list(cams), own_sources, cfg.fps, cfg.tzinfo(), stopper.event)
    play_window(cfg, source)  # the files cut to the slice, before the bus: a slice without frames stops ingest at once
    recorder = None
    if cfg.record_dir is not None:
        record_dir = record_folder(settings)
        recorder = FrameRecorder(RecorderConfig(record_dir, cfg.record_jpeg_quality, cfg.record_queue_mb,
                                                cfg.record_min_free_mb))
        log.info("recording every frame published to %s", record_dir)
    bad = BadInput("ingest")
    session = open_session(settings, "ingest")
    try:
        pubs = {c: session.declare_publisher(camera_key(settings.site, c, "frame")) for c in cams}
        acks = None
        if cfg.pace == "max":
            acks = Acks(Receiver(session, all_cameras_key(settings.site, "detections"), Detections, bad),
                        cfg.max_in_flight or settings.detect.workers, stopper, cfg.ack_timeout_s,
                        per_camera=settings.detect.ring)
        tokens = declare_alive(session, settings.site, "ingest", list(cams))
        status = StatusReporter(session, settings.site, "ingest", bad, settings.bus.status_period_s)
        if recorder is not None:  # its counters read at each report, not handed over per frame
            status.watch(recorder.counts)
        seen = wait_for_peers(session, all_alive_key(settings.site), len(cams) * 3 + 1 + cfg.wait_extra_peers,
                              PIPELINE_WAIT_S, stopper)
        log.info("source %s, %d cameras, pace %s; %d liveliness tokens on the bus", cfg.source, len(cams),
                 cfg.pace, seen)
        scales = {c: decode_scale_for(cam.width, cam.height, cfg.decode_long_side) for c, cam in cams.items()}
        log.info("decoded at 1/n of full size, n per camera: %s", scales)
        resume_ns = resume_point(session, settings.site, source, cfg.loop)
        # rounds of max_frames frames are spaced by what they play, as before (a source's whole span would leave
        # most of each round's time empty); a restart then skips through the rounds to fuse_track's time
        period_ns = loop_period(source) if cfg.loop and not cfg.max_frames else None
        offset_ns = 0
        if resume_ns is not None:
            if period_ns is not None:  # the round fuse_track's tracks reached: its times shifted as it played them
                offset_ns = (resume_ns - source.items[0][0]) // period_ns * period_ns
            log.info("fuse_track's tracks reach %d: resuming the files after it (round %d)", resume_ns,
                     offset_ns // period_ns if period_ns else 0)
        pacer = Pacer(cfg.pace, stopper)
        seq = dict.fromkeys(cams, 0)
        published = 0
        loop_idx = 0  # rounds played by this process (ingest.max_frames counts per round)
        while not stopper.is_set():
            first = last = None  # this round's first and last capture times in the source, skipped on resuming or not
            for sf in source:
                if stopper.is_set():
                    break
                if sf.camera not in cams:
                    continue
                if cfg.max_frames is not None and seq[sf.camera] >= cfg.max_frames * (loop_idx + 1):
                    if all(n >= cfg.max_frames * (loop_idx + 1) for n in seq.values()):
                        break
                    continue
                first = sf.t_capture_ns if first is None else first
                last = sf.t_capture_ns
                t = sf.t_capture_ns + offset_ns
                if resume_ns is not None and t <= resume_ns:
                    continue  # played before this restart: fuse_track has closed its tick
                pacer.wait(t)
                try:
                    if sf.error:
                        raise ValueError(sf.error)
                    fields = to_frame_fields(sf, cams[sf.camera], cfg.encoding, scales[sf.camera])
                    msg = Frame(site=settings.site, camera=sf.camera, seq=seq[sf.camera], t_capture_ns=t,
                                camera_kind=cams[sf.camera].kind, **fields)  # validated: e.g. an oversized JPEG
                except (ValueError, cv2.error) as exc:
                    bad(f"{sf.origin}: {exc}" if isinstance(exc, cv2.error) else str(exc), sf.camera)
                    continue
                if acks is not None:
                    acks.wait_for_room(sf.camera)
                msg.stamps = [("ingest", time.time_ns())]  # when it leaves, after any wait for room
                pubs[sf.camera].put(encode(msg))
                status.count(f"frames_out.{sf.camera}", output=True)
                if recorder is not None:
                    recorder.put(sf.camera, t, jpeg=sf.jpeg, image=sf.image)
                if acks is not None:
                    acks.sent(sf.camera, msg.seq)
                    status.gauge("ack_timeouts", acks.timeouts)
                seq[sf.camera] += 1
                published += 1
            if not cfg.loop or first is None:
                break
            loop_idx += 1
            offset_ns += period_ns if period_ns is not None else last - first + LOOP_GAP_NS
        if acks is not None:
            deadline = time.monotonic() + cfg.ack_timeout_s
            while acks.pending and time.monotonic() < deadline and not stopper.is_set():
                acks.drain()
                time.sleep(0.005)
        log.info("done: %d frames published, %d bad, %d ack timeouts", published, bad.total,
                 acks.timeouts if acks else 0)
        if cfg.at_end == "idle" and not stopper.is_set():
            # under a supervisor that restarts a process that exits (compose), an exit would replay the source's
            # last frames (resumed after fuse_track's latest tracks) for ever: stay up, reporting, until told to stop
            log.info("the source is finished: publishing nothing more until told to stop (ingest.at_end idle)")
            while not stopper.wait(1.0):
                pass
        if recorder is not None:
            recorder.close()  # what is queued written before the last report
        status.close()
        del tokens
    finally:
        if recorder is not None:
            recorder.close()  # a second close returns at once
        session.close()
    return STOPPED if stopper.is_set() else 0  # 0: the source ended (`roadside up` ends the run), else told to stop


if __name__ == "__main__":
    raise SystemExit(run("ingest", main))
