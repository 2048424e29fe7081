"""The demo's latency split: end to end, detector, tick wait, overhead and each hop, from the messages' stamps."""

from __future__ import annotations

import pytest
from test_contract import T0, make_objects, make_tracks

from roadside.demo import HOPS, latency

MS = 1_000_000


def test_hops_add_up_to_end_to_end_and_overhead_leaves_out_detector_wait_and_ring():
    # ingest at +0, detect pulls it at +10 ms, publishes at +45 (inference 30 ms), localize at +47,
    # fuse_track gets it at +48, closes the tick at +60 and publishes at +62
    obj = make_objects(stamps=[("ingest", T0), ("detect_in", T0 + 10 * MS), ("detect", T0 + 45 * MS),
                               ("localize", T0 + 47 * MS)], infer_ms=30.0, seq=7, camera="NE")
    tr = make_tracks(stamps=[("tick_closed", T0 + 60 * MS), ("fuse_track", T0 + 62 * MS)],
                     frames=[("NE", 7, T0, T0 + 48 * MS), ("SW", 1, T0, T0 + 50 * MS)])  # SW: no objects seen
    r = latency([obj], [tr])
    assert r["frames"] == 1
    assert r["end_to_end_p50"] == 62.0 and r["detector_p50"] == 30.0 and r["tick_wait_p50"] == 12.0
    assert r["overhead_p50"] == 20.0  # 62 - 30 - 12: ring wait 10, decode/resize 5, localize 2, transport 1, track 2
    assert r["overhead_without_queue_p50"] == 10.0
    assert r["hops_p50"] == dict(zip(HOPS, (10.0, 35.0, 2.0, 1.0, 12.0, 2.0), strict=True))
    assert sum(r["hops_p50"].values()) == pytest.approx(r["end_to_end_p50"])


def test_no_matching_frames_gives_none():
    r = latency([make_objects(stamps=[("ingest", T0), ("detect_in", T0), ("detect", T0), ("localize", T0)])],
                [make_tracks(frames=[("NW", 1, T0, T0)])])
    assert r["frames"] == 0 and r["overhead_p50"] is None and r["hops_p50"]["tick_wait"] is None
