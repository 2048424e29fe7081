"""The demo's latency split: end to end, detector, tick wait, overhead and each hop, from the messages' stamps."""

from __future__ import annotations

import pytest
from test_contract import T0, make_objects, make_tracks

from roadside.demo import HOPS, latency, pooled

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
    assert r["overhead_p50"] == 32.0  # 62 - 30: everything but the inference
    assert r["overhead_without_tick_wait_p50"] == 20.0  # 62 - 30 - 12: ring 10, decode 5, localize 2, hop 1, track 2
    assert r["overhead_without_queue_p50"] == 10.0
    assert r["hops_p50"] == dict(zip(HOPS, (10.0, 35.0, 2.0, 1.0, 12.0, 2.0), strict=True))
    assert sum(r["hops_p50"].values()) == pytest.approx(r["end_to_end_p50"])


def test_no_matching_frames_gives_none():
    r = latency([make_objects(stamps=[("ingest", T0), ("detect_in", T0), ("detect", T0), ("localize", T0)])],
                [make_tracks(frames=[("NW", 1, T0, T0)])])
    assert r["frames"] == 0 and r["overhead_p50"] is None and r["hops_p50"]["tick_wait"] is None


def test_detector_alone_passes_pool_as_one_long_pass():
    # a slow pass (4 frames in 0.2 s) and a fast one (4 in 0.1 s): 8 frames in 0.3 s, not the mean of 20 and 40
    slow = {"frames": 4, "workers": 2, "threads": 1, "wall_s": 0.2, "cpu_s": 0.36, "times": [40.0, 40.0, 50.0, 50.0],
            "with_decode_wall_s": 0.4, "with_decode_cpu_s": 0.6, "with_decode_times": [80.0] * 4}
    fast = {"frames": 4, "workers": 2, "threads": 1, "wall_s": 0.1, "cpu_s": 0.2, "times": [20.0, 20.0, 25.0, 25.0],
            "with_decode_wall_s": 0.2, "with_decode_cpu_s": 0.2, "with_decode_times": [40.0] * 4}
    p = pooled([slow, fast])
    assert p["frames"] == 8 and p["workers"] == 2 and p["threads"] == 1
    assert p["fps"] == pytest.approx(8 / 0.3) and p["with_decode_fps"] == pytest.approx(8 / 0.6)
    assert p["ms_p50"] == pytest.approx(32.5) and p["with_decode_ms_p50"] == pytest.approx(60.0)
    assert p["cpu_ms_per_frame"] == pytest.approx(70.0) and p["with_decode_cpu_ms_per_frame"] == pytest.approx(100.0)
    assert p["passes"] == [{"fps": 20.0, "with_decode_fps": 10.0}, {"fps": 40.0, "with_decode_fps": 20.0}]


def test_summary_table_renders_a_summary():
    from roadside.demo import summary_table

    lat = {k: 1.0 for k in ("end_to_end_p50", "end_to_end_p99", "detector_p50", "overhead_p50", "overhead_p99",
                            "overhead_without_tick_wait_p50", "overhead_without_tick_wait_p99",
                            "overhead_without_queue_p50", "overhead_without_queue_p99", "tick_wait_p50",
                            "tick_wait_p99")}
    s = {"mota": 0.7, "idf1": 0.7, "id_switches": 4, "traj_err_in_roi_m": 0.5, "traj_err_best_single_camera_m": 0.4,
         "best_single_camera": "SW", "yaw_err_in_roi_deg": 14.33, "yaw_err_in_roi_median_deg": 7.1,
         "yaw_err_in_roi_moving_deg": 6.0, "yaw_err_in_roi_standing_deg": 22.5, "yaw_confirmed_share": 0.6846,
         "yaw_reversed_confirmed": 0.0, "yaw_reversed_unconfirmed": 0.0724, "pos_cov_within_95": 0.93,
         "pos_cov_within_1sigma": 0.45, "pos_cov_err95_median_m": 1.234, "vel_cov_within_95": 0.9215,
         "yaw_std_within_95": 0.9512, "yaw_std_within_1sigma": 0.6801, "yaw_std_median_deg": 8.04,
         "single_camera": {"NE": {"traj_err_in_roi_m": 0.62, "fused_traj_err_in_roi_m": 0.71},
                           "SW": {"traj_err_in_roi_m": 0.35, "fused_traj_err_in_roi_m": 0.36}},
         "handoff_crossings": 33, "handoff_crossing_kept_fraction": 32 / 33, "frames": 2393, "frames_recorded": 2400,
         "handoff_radius_m": 40.0, "latency_ms": lat, "throughput_ratio": 0.8, "pipeline_fps": 60.0,
         "detector_alone": {"passes": [{"fps": 80.0}, {"fps": 75.0}]}, "throughput_ratio_vs_decode_and_detect": 0.8,
         "cpu_ratio_vs_decode_and_detect": 0.8, "peak_rss_mb": {"detect": 220.0}, "cpu_ms_per_frame": {"detect": 22.0},
         "ahead_100ms_stale_err_m": 0.581, "ahead_300ms_stale_err_m": 0.962, "ahead_100ms_err_m": 0.497,
         "ahead_300ms_err_m": 0.583, "ahead_100ms_cov_within_95": 0.9031, "ahead_300ms_cov_within_95": 0.891,
         "movements": {"complete_true": 23, "complete_counted": 17, "count_error": 0.2609, "entering_error": 0.0357,
                       "leaving_error": 0.0345, "movement_recall": 0.7391, "movement_precision": 1.0}}
    table = summary_table(s)
    assert "17 (23): count error 0.261, entering 0.036; per vehicle recall 0.739, precision 1.000" in table
    assert "0.970 of 33 (within 40 m of a camera)" in table
    assert "frames through the pipeline" in table and "2393 of 2400" in table
    assert "80.0 / 75.0 frames/s" in table
    assert "NE 0.71 / 0.62, SW 0.36 / 0.35 m" in table
    assert "14.3 (7.1) deg; moving 6.0, standing 22.5 deg" in table
    assert "0.685; 0.000 of them, 0.072 of the others" in table
    assert "0.930 (1 sigma: 0.450; median half-axis 1.23 m); velocity 0.921" in table
    assert "0.951 (1 sigma: 0.680; median sigma 8.0 deg)" in table
    assert "0.58 / 0.96 m; 0.50 / 0.58 m (95 % ellipse holds 0.903 / 0.891)" in table
