"""Helpers of the fuse_track core tests: one camera frame's objects, ticks -> fusion -> tracker over plain
arrays, and which track ids followed which true vehicle."""

from __future__ import annotations

import numpy as np

from services.fuse_track.fusion import (
    CameraRegion,
    Fusion,
    FusionConfig,
    ObjectBatch,
)
from services.fuse_track.ticks import TickBuffer
from services.fuse_track.tracker import (
    Tracker,
    TrackState,
)

MS = 1_000_000  # ns
CAR = (4.5, 1.8, 1.5)


def frame(camera: str, t_ns: int, xy, yaw=0.0, score=0.9, vtype=0) -> ObjectBatch:
    """One camera frame's objects: xy (N, 2) m; yaw, score and vtype scalars or (N,)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    return ObjectBatch.from_frame(camera, t_ns, xy, np.broadcast_to(yaw, (n,)), np.tile(CAR, (n, 1)),
                                  np.broadcast_to(vtype, (n,)), np.broadcast_to(score, (n,)))


def pipeline(frames: list[tuple[float, str, int, ObjectBatch]], cameras: dict[str, tuple[float, float]],
             tracker: Tracker | None = None, fusion_log: list | None = None,
             fusion_config: FusionConfig | None = None) -> list[TrackState]:
    """Feed (arrival_s, camera, t_capture_ns, batch) in arrival order through ticks -> fusion -> tracker."""
    buffer: TickBuffer[ObjectBatch] = TickBuffer(cameras)
    fusion = Fusion([CameraRegion(name, pos) for name, pos in cameras.items()], fusion_config)
    tracker = tracker or Tracker()
    out = []

    def run(ticks):
        for tick in ticks:
            objects = ObjectBatch.concat(tick.items())
            fused = fusion.fuse(objects, tick.t_ref_ns, tracker.velocity_hints(objects), tick.batches.keys())
            if fusion_log is not None:
                fusion_log.append((tick, fused))
            out.append(tracker.update(fused, tick.t_ref_ns))

    for arrival_s, camera, t_ns, batch in sorted(frames, key=lambda f: f[0]):
        buffer.add(camera, t_ns, batch, arrival_s)
        run(buffer.pop_ready(arrival_s))
    run(buffer.flush())
    return out


def ids_by_truth(states: list[TrackState], truth) -> dict[int, set[int]]:
    """For each true vehicle (truth(t_s) -> (V, 2) positions), the track ids reported within 1.5 m of it."""
    seen: dict[int, set[int]] = {}
    for s in states:
        gt = truth(s.t_ns / 1e9)
        for v, p in enumerate(gt):
            d = np.linalg.norm(s.xy - p, axis=1) if len(s) else np.zeros(0)
            seen.setdefault(v, set()).update(s.id[d < 1.5].tolist())
    return seen
