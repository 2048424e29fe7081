"""fuse_track: fuse every camera's objects by map region and track them (SORT) in world coordinates.

`python -m services.fuse_track --site SITE`

Subscribes to `roadside/<site>/cam/*/objects` (objects of another site, or of a camera not at this site, are bad
input: counted and skipped); groups them into event-time ticks (capture time, bounded watermark:
services/fuse_track/ticks.py); fuses by camera region with a distance-gated merge (fusion.py); tracks with SORT
on [x, y, s, r, vx, vy, vs, vr] (tracker.py); publishes Tracks on `roadside/<site>/tracks`, answers
`roadside/<site>/tracks/latest` with the newest Tracks (a vehicle that joins late gets the current tracks at
once), and appends every Tracks message to the recording file (`fuse_track.record`, JSON lines, flushed per line
so a kill loses nothing written before it; a write that fails is logged and counted, and tracking goes on; rotated
by size: recorder.py). When every camera's clock steps back, the tracker starts again under a new id (ticks.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable

import numpy as np

from calibration.masks import read_masks_meta
from services.fuse_track.fusion import CameraRegion, Fusion, FusionConfig, ObjectBatch
from services.fuse_track.player import current_payload, held_latest
from services.fuse_track.recorder import Recorder
from services.fuse_track.ticks import Tick, TickBuffer, TickConfig
from services.fuse_track.tracker import Tracker, TrackerConfig, TrackState
from shared.bus import BadInput, Receiver, Stopper, declare_alive, open_session
from shared.codec import encode
from shared.geo import GeoFrame
from shared.keys import all_cameras_key, latest_tracks_key, tracks_key
from shared.messages import MAX_ROWS, Objects, Tracks
from shared.service import run
from shared.settings import FuseTrackSettings, Settings
from shared.status import StatusReporter

log = logging.getLogger("roadside.fuse_track")
POLL_S = 0.02  # the longest sleep without a message: max_wait is checked this often
MAX_RANGE_M = 1e6  # objects are on the ground near the site: farther ones are bad input
SIZE_RANGE_M = (1e-6, 1e3)  # vehicle length, width, height outside this are bad input


def implausible(o: Objects) -> str | None:
    """Why finite but absurd values make an Objects message unusable (they overflow the tracker or the
    Tracks message), None when it is fine."""
    if not len(o):
        return None
    far = float(np.abs(o.xy).max())
    if far > MAX_RANGE_M:
        return f"objects of {o.camera}: coordinate {far:g} m is beyond {MAX_RANGE_M:g} m of the site"
    lo, hi = float(o.size_lwh.min()), float(o.size_lwh.max())
    if lo < SIZE_RANGE_M[0] or hi > SIZE_RANGE_M[1]:
        return f"objects of {o.camera}: size {lo:g}..{hi:g} m outside [{SIZE_RANGE_M[0]:g}, {SIZE_RANGE_M[1]:g}] m"
    return None


def camera_positions(settings: Settings) -> tuple[dict[str, tuple[float, float]], GeoFrame]:
    """Each camera's ground position (site metres) from its masks file's metadata (only that array is read),
    and the site frame (settings.origin, else the first masks file's origin)."""
    positions, geo = {}, None
    site_geo = GeoFrame.from_dict(settings.origin) if settings.origin else None
    for cam in settings.cameras:
        if cam.masks is None:
            raise ValueError(f"camera {cam.name}: no lookup masks (fuse_track reads the camera position from them)")
        path = settings.path(cam.masks)
        try:
            meta = read_masks_meta(path)
        except ValueError as exc:
            raise ValueError(f"camera {cam.name}: {exc} (fuse_track reads the camera position from them)") from None
        masks_geo = GeoFrame.from_dict(meta["geo_origin"])
        try:
            pos = np.asarray(meta["camera"]["pose"]["position_m"], float).reshape(-1)[:3]
        except (KeyError, TypeError, ValueError) as exc:  # metadata without a camera pose
            raise ValueError(f"{path}: not a lookup masks file ({type(exc).__name__}: {exc}; its metadata has no "
                             "camera pose: build it with roadside calibrate)") from None
        site_geo = site_geo or masks_geo
        if masks_geo != site_geo:
            pos = masks_geo.reframe(pos[:2], site_geo)[0]
        positions[cam.name] = (float(pos[0]), float(pos[1]))
        geo = site_geo
    return positions, geo


def tracks_message(site: str, state: TrackState, t_ns: int, seq: int, geo: GeoFrame,
                   stamps: list[tuple[str, int]], frames: list[tuple[str, int, int, int]]) -> Tracks:
    """The Tracks message of a tracker state at event time t_ns (latitude/longitude from the site frame)."""
    latlon = geo.to_geodetic(state.xy)[:, :2] if len(state) else np.zeros((0, 2))
    f4 = np.float32
    return Tracks(
        site=site, seq=seq, t_capture_ns=int(t_ns), tracker=state.tracker, stamps=stamps,
        id=state.id.astype(np.int64), xy=state.xy.astype(np.float64), latlon=latlon.astype(np.float64),
        velocity=state.velocity.astype(f4), yaw=state.yaw.astype(f4), size_lwh=state.size_lwh.astype(f4),
        vtype=state.vtype.astype(np.int8), score=state.score.astype(f4), age=state.age.astype(np.int32),
        hits=state.hits.astype(np.int32), cameras=[list(c) for c in state.cameras], xy_cov=state.xy_cov.astype(f4),
        velocity_cov=state.velocity_cov.astype(f4), yaw_confirmed=state.yaw_confirmed.astype(bool),
        yaw_std=state.yaw_std.astype(f4), frames=frames)


def tick_frames(tick: Tick) -> list[tuple[str, int, int, int]]:
    """(camera, seq, t_capture_ns, t_arrival_ns) of every frame in a tick (items are (seq, t_arrival, batch))."""
    return [(cam, s, t_cap, t_arr) for cam, items in tick.batches.items() for t_cap, (s, t_arr, _) in items]


def build(settings: Settings) -> tuple[Fusion, Tracker, TickBuffer, dict[str, tuple[float, float]], GeoFrame]:
    """The fusion, tracker and tick buffer of a site's settings, as the service runs them (also used offline:
    eval/budget.py replays a run's objects through them), with the cameras' ground positions and the site frame."""
    cfg = settings.fuse_track
    positions, geo = camera_positions(settings)
    regions = [CameraRegion(c.name, positions[c.name], np.asarray(c.region_m) if c.region_m else None)
               for c in settings.cameras]
    fusion = Fusion(regions, fusion_config(cfg))
    tracker = new_tracker(settings)
    ticks: TickBuffer = TickBuffer(positions, TickConfig(tick_ms=cfg.tick_ms, watermark_ms=cfg.watermark_ms,
                                                         max_wait_ms=cfg.max_wait_ms,
                                                         camera_timeout_ms=cfg.camera_timeout_ms))
    return fusion, tracker, ticks, positions, geo


def fusion_config(cfg: FuseTrackSettings) -> FusionConfig:
    """The fusion's configuration from a site's fuse_track settings (its score pools split at high_score)."""
    return FusionConfig(merge_gate_m=cfg.merge_gate_m, out_of_region_weight=cfg.out_of_region_weight,
                        position_sigma=cfg.position_sigma, crowded_sigma_factor=cfg.crowded_sigma_factor,
                        occlusion_fallback=cfg.occlusion_fallback, extend_range_m=cfg.extend_range_m,
                        split_score=cfg.high_score, yaw_size_range_m=cfg.yaw_size_range_m,
                        handover_s=cfg.handover_s, handover_min_score=cfg.handover_min_score,
                        long_vehicle_m=cfg.long_vehicle_m, long_footprint=cfg.long_footprint)


def tracker_config(cfg: FuseTrackSettings) -> TrackerConfig:
    """The tracker's configuration from a site's fuse_track settings."""
    return TrackerConfig(gate_m=cfg.gate_m, max_age_ticks=cfg.max_age_ticks, min_hits=cfg.min_hits,
                         high_score=cfg.high_score, standing_hits=cfg.standing_hits,
                         relink_s=cfg.relink_s, relink_gate_m=cfg.relink_gate_m, bias_share=cfg.bias_share,
                         along_length_share=cfg.along_length_share, yaw_confirm_travel_m=cfg.yaw_confirm_travel_m,
                         yaw_reverse_s=cfg.yaw_reverse_s, yaw_std_deg=cfg.yaw_std_deg)


def new_tracker(settings: Settings) -> Tracker:
    """A tracker of a site's settings (a new id, no tracks)."""
    return Tracker(tracker_config(settings.fuse_track))


def capped(batches: list[ObjectBatch], limit: int = MAX_ROWS) -> tuple[list[ObjectBatch], int]:
    """A tick's batches with at most `limit` objects in all (the highest-scoring; fusion's cost grows with the
    square of the count), and how many were dropped."""
    n = sum(len(b) for b in batches)
    if n <= limit:
        return batches, 0
    objs = ObjectBatch.concat(batches)
    return [objs.select(np.sort(np.argsort(-objs.score, kind="stable")[:limit]))], n - limit


def fuse_and_track(fusion: Fusion, tracker: Tracker, batches: list[ObjectBatch], t_ref_ns: int,
                   delivered: Iterable[str] | None = None) -> TrackState:
    """One closed tick: its cameras' objects fused, then the tracker's update at the tick's reference time;
    `delivered`: the cameras that delivered a frame to the tick (the fusion hands a down camera's region over)."""
    objs = ObjectBatch.concat(batches) if batches else ObjectBatch.empty()
    return tracker.update(fusion.fuse(objs, t_ref_ns, tracker.velocity_hints(objs), delivered), t_ref_ns)


def main(settings: Settings, stopper: Stopper) -> int:
    cfg = settings.fuse_track
    fusion, tracker, ticks, positions, geo = build(settings)
    recorder = Recorder(settings.path(cfg.record), round(cfg.record_rotate_mb * 2**20), cfg.record_keep)
    bad = BadInput("fuse_track")
    session = open_session(settings, "fuse_track")
    latest: list[tuple[float, float, bytes]] = []  # the newest payload, as held_latest keeps it
    try:
        receiver = Receiver(session, all_cameras_key(settings.site, "objects"), Objects, bad)
        pub = session.declare_publisher(tracks_key(settings.site))

        def answer(query) -> None:  # runs in Zenoh's thread: only hands over bytes already encoded
            payload = current_payload(latest, query)  # none while no tick was sent for a while (every camera down)
            if payload is not None:
                query.reply(latest_tracks_key(settings.site), payload)

        queryable = session.declare_queryable(latest_tracks_key(settings.site), answer)
        # after the subscriber and queryable: a token means ready
        tokens = declare_alive(session, settings.site, "fuse_track", [tracker.id.replace("tracker-", "t")])
        status = StatusReporter(session, settings.site, "fuse_track", bad, settings.bus.status_period_s)
        seq = 0
        log.info("tracker %s, %d cameras, tick %g ms", tracker.id, len(fusion.regions), cfg.tick_ms)

        last_ref: int | None = None  # the reference time of the last tick tracked

        def close(closed: list[Tick]) -> None:
            nonlocal seq, tracker, tokens, last_ref
            for tick in closed:
                t_closed = time.time_ns()
                if last_ref is not None and tick.t_ref_ns < last_ref:  # the clocks stepped back (ticks.py): start again
                    log.warning("capture times went back %.3f s: tracker %s ends, a new one starts",
                                (last_ref - tick.t_ref_ns) / 1e9, tracker.id)
                    tracker = new_tracker(settings)
                    for token in tokens:
                        token.undeclare()
                    tokens = declare_alive(session, settings.site, "fuse_track", [tracker.id.replace("tracker-", "t")])
                last_ref = tick.t_ref_ns
                batches, dropped = capped([b for _, _, b in tick.items()])
                if dropped:
                    bad(f"tick at {tick.t_ref_ns}: {dropped} objects over the {MAX_ROWS} one tick may hold dropped "
                        "(the lowest scores)", "tick")
                try:
                    state = fuse_and_track(fusion, tracker, batches, tick.t_ref_ns, tick.batches.keys())
                    msg = tracks_message(settings.site, state, tick.t_ref_ns, seq, geo, [("tick_closed", t_closed)],
                                         tick_frames(tick))
                except ValueError as exc:  # what validation let through and fusion, the tracker or Tracks cannot take
                    bad(f"tick at {tick.t_ref_ns} dropped: {exc}", "tick")
                    continue
                except Exception as exc:  # a bug: its traceback logged, the tick counted as dropped, the next one taken
                    log.exception("tick at %d: internal error", tick.t_ref_ns)
                    bad(f"tick at {tick.t_ref_ns} dropped: internal error ({type(exc).__name__}: {exc})", "tick")
                    continue
                # the tracks-published stamp, once the message is built and validated and just before it is encoded:
                # the encoding and the put come after it and are left out of it (a stamp the message carries cannot
                # cover the encoding of that message)
                msg.stamps.append(("fuse_track", time.time_ns()))
                payload = encode(msg)
                pub.put(payload)
                held_latest(latest, payload)
                recorder.write(msg)  # counts and logs what it cannot record itself
                status.count("tracks_out", output=True)
                status.gauge("tracks", len(msg))
                status.gauge("cameras_down", len(fusion.down))  # regions handed to their neighbours (fusion.py, 5)
                status.gauge("not_recorded", recorder.failed)
                status.gauge("rotations_failed", recorder.rotation_failed)
                seq += 1

        while not stopper.is_set():
            now = time.monotonic()
            received = receiver.poll()
            if received:
                status.count("objects_in", len(received))
            for o in received:
                if o.site != settings.site:
                    bad(f"objects of site {o.site!r} on the bus of site {settings.site!r}", o.camera)
                    continue
                if o.camera not in positions:
                    bad(f"objects from camera {o.camera!r}, not at this site", o.camera)
                    continue
                try:
                    batch = ObjectBatch.from_frame(o.camera, o.t_capture_ns, o.xy, o.yaw.astype(np.float64),
                                                   o.size_lwh.astype(np.float64), o.vtype.astype(np.int64),
                                                   o.score.astype(np.float64))
                except ValueError as exc:
                    bad(str(exc), o.camera)
                    continue
                if (reason := implausible(o)) is not None:
                    bad(reason, o.camera)
                    continue
                if not ticks.add(o.camera, o.t_capture_ns, (o.seq, time.time_ns(), batch), now):
                    bad(f"objects of {o.camera} captured at {o.t_capture_ns} dropped, {ticks.refusal}", o.camera)
            close(ticks.pop_ready(time.monotonic()))
            receiver.wait(POLL_S)
        close(ticks.flush())
        log.info("stopped: %d Tracks messages, %d ticks (%s), %d late, %d ahead, %d over a tick's share, %d restarts, "
                 "%d bad %s, %d not recorded", seq, ticks.emitted, ticks.closed_by, ticks.late, ticks.ahead, ticks.full,
                 ticks.restarts, bad.total, dict(bad.counts), recorder.failed)
        status.close()
        queryable.undeclare()
        del tokens
    finally:
        recorder.close()
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run("fuse_track", main))
