"""The demo's latency split: end to end, detector, tick wait, overhead and each hop, from the messages' stamps; the
detector alone loaded as the detect service loads it; the throughput part of the summary."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from test_contract import T0, make_objects, make_tracks

from roadside.demo import HOPS, latency, logged_providers, pooled, throughput
from shared.settings import load_settings

MS = 1_000_000


def test_hops_add_up_to_end_to_end_and_overhead_leaves_out_detector_wait_and_ring():
    # ingest at +0, detect takes it off the bus at +4 ms (transport), out of its ring for a free worker at +10 (a
    # wait of 6 ms), the worker done at +43 (the detect step: 33 ms, of which session.run 30 ms), published at +45,
    # localize at +47, fuse_track gets it at +48, closes the tick at +60 and publishes at +62
    obj = make_objects(stamps=[("ingest", T0), ("detect_in", T0 + 4 * MS), ("detect_start", T0 + 10 * MS),
                               ("detect_done", T0 + 43 * MS), ("detect", T0 + 45 * MS), ("localize", T0 + 47 * MS)],
                       infer_ms=30.0, seq=7, camera="NE")
    tr = make_tracks(stamps=[("tick_closed", T0 + 60 * MS), ("fuse_track", T0 + 62 * MS)],
                     frames=[("NE", 7, T0, T0 + 48 * MS), ("SW", 1, T0, T0 + 50 * MS)])  # SW: no objects seen
    r = latency([obj], [tr])
    assert r["frames"] == 1
    assert r["end_to_end_p50"] == 62.0 and r["detector_p50"] == 30.0 and r["tick_wait_p50"] == 12.0
    assert r["detect_step_p50"] == 33.0  # the whole detect step, its pre- and post-processing with the inference
    assert r["overhead_p50"] == 32.0  # 62 - 30: everything but the inference
    # 62 - 30 - 12: transport 4, ring 6, pre- and post-processing 3, in order 2, localize 2, hop 1, track 2
    assert r["overhead_without_tick_wait_p50"] == 20.0
    assert r["overhead_without_queue_p50"] == 14.0  # the wait in the ring (6 ms) left out, not the transport (4 ms)
    assert r["hops_p50"] == dict(zip(HOPS, (4.0, 6.0, 33.0, 2.0, 2.0, 1.0, 12.0, 2.0), strict=True))
    assert sum(r["hops_p50"].values()) == pytest.approx(r["end_to_end_p50"])


def test_objects_of_an_older_detect_without_its_start_and_done_stamps_are_handled():
    """A recording of before `detect_start` and `detect_done`: its infer_ms (the whole detect step then) stands for
    the detector and the step; its wait in the ring is unknown, not taken to be the transport to detect."""
    obj = make_objects(stamps=[("ingest", T0), ("detect_in", T0 + 4 * MS), ("detect", T0 + 45 * MS),
                               ("localize", T0 + 47 * MS)], infer_ms=30.0, seq=7, camera="NE")
    tr = make_tracks(stamps=[("tick_closed", T0 + 60 * MS), ("fuse_track", T0 + 62 * MS)],
                     frames=[("NE", 7, T0, T0 + 48 * MS)])
    r = latency([obj], [tr])
    assert r["frames"] == 1 and r["end_to_end_p50"] == 62.0
    assert r["detector_p50"] == 30.0 and r["detect_step_p50"] == 30.0
    assert r["overhead_p50"] == 32.0 and r["overhead_without_tick_wait_p50"] == 20.0
    assert r["overhead_without_queue_p50"] is None
    assert r["hops_p50"] == dict(zip(HOPS, (4.0, None, None, None, 2.0, 1.0, 12.0, 2.0), strict=True))


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


def test_the_summary_records_the_pace_and_the_providers_and_keeps_the_ratio():
    """At pace 1 ingest publishes at the cameras' rate: the ratio is what it is, and the summary says at which pace."""
    alone = {"fps": 68.5, "with_decode_fps": 63.0, "providers": ["CPUExecutionProvider"]}
    out = throughput(40.0, alone, "1", ["CPUExecutionProvider"])
    assert out["pace"] == "1" and out["pipeline_fps"] == 40.0
    assert out["throughput_ratio"] == round(40.0 / 68.5, 3)
    assert out["throughput_ratio_vs_decode_and_detect"] == round(40.0 / 63.0, 3)
    assert out["providers"] == {"pipeline_detect": ["CPUExecutionProvider"], "detector_alone": ["CPUExecutionProvider"]}
    assert out["detector_alone"] is alone
    assert throughput(40.0, alone, "max", None)["pace"] == "max"


def test_the_pipeline_providers_are_read_from_this_runs_start_up_line_of_detect(tmp_path):
    log = tmp_path / "detect.log"
    log.write_text("2026-11-29 14:28:05,010 detect INFO model /m/detector_fp32.onnx on ['CPUExecutionProvider'], "
                   "2 workers x 1 threads\n")
    start = log.stat().st_size  # an older run's line before it
    assert logged_providers(log, start) is None
    with open(log, "a") as f:
        f.write("2026-12-01 10:00:00,000 detect INFO model /m/a b.onnx on ['CUDAExecutionProvider', "
                "'CPUExecutionProvider'], 2 workers x 1 threads\n2026-12-01 10:00:01,000 detect INFO other\n")
    assert logged_providers(log, start) == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert logged_providers(log) == ["CUDAExecutionProvider", "CPUExecutionProvider"]  # the last one
    assert logged_providers(tmp_path / "none.log") is None


def test_the_detector_alone_is_loaded_as_the_detect_service_loads_it(tmp_path, monkeypatch):
    """Where ONNX Runtime has CUDA the detect service asks for it (TensorRT -> CUDA -> CPU): the detector alone asked
    for the CPU alone, so on a GPU machine the throughput ratio divided a GPU's frames/s by a CPU's. Both are asked
    for the same providers now, and the providers each session runs on are recorded."""
    import cv2
    import onnxruntime as ort

    import services.detect.__main__ as detect
    import shared.inference
    import sim.recording
    from roadside.demo import DEFAULT_MODEL, DemoConfig, DetectorAlone

    model = DEFAULT_MODEL
    available = ort.get_available_providers
    monkeypatch.setattr(ort, "get_available_providers",
                        lambda: ["CUDAExecutionProvider", *(p for p in available() if p != "CUDAExecutionProvider")])
    asked = []

    class Recorded(shared.inference.OnnxDetector):
        def __init__(self, path, providers=None, **kw) -> None:
            asked.append(providers)
            super().__init__(path, providers=providers, **kw)

    monkeypatch.setattr(shared.inference, "OnnxDetector", Recorded)
    monkeypatch.setattr(detect, "OnnxDetector", Recorded)
    image = tmp_path / "frame.jpg"
    cv2.imwrite(str(image), np.full((96, 128), 90, np.uint8))

    class Recording:  # a one-camera recording of two frames
        def __init__(self, path) -> None:
            self.cameras = {"NE": SimpleNamespace(width=128, height=96)}
            self.camera_names = ["NE"]

        def frames(self, camera: str) -> list:
            return [(0, image), (1, image)]

    monkeypatch.setattr(sim.recording, "Recording", Recording)
    site = {"site": "t", "cameras": [{"name": "NE", "kind": "fisheye", "width": 128, "height": 96}],
            "detect": {"model": str(model), "model_gpu": None, "threads": 1}}  # as the demo's site: no providers
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(site))
    settings = load_settings(tmp_path / "site.yaml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ONNX Runtime's own: CUDA is not in this build
        timer = DetectorAlone(DemoConfig(out=tmp_path, model=model, baseline_frames=2), tmp_path, settings)
        service = detect.load_detector(settings)
    assert asked == [["CUDAExecutionProvider", "CPUExecutionProvider"]] * 2  # the baseline's, then the service's
    one = timer.run()
    assert one["providers"] == timer.det.providers == service.providers
    assert pooled([one, timer.run()])["providers"] == service.providers


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
    assert "32 of 33 (within 40 m of a camera)" in table
    assert "frames through the pipeline" in table and "2393 of 2400" in table
    assert "80.0 / 75.0 frames/s" in table
    assert "NE 0.71 / 0.62, SW 0.36 / 0.35 m" in table
    assert "14.3 (7.1) deg; moving 6.0, standing 22.5 deg" in table
    assert "0.685; 0.000 of them, 0.072 of the others" in table
    assert "0.930 (1 sigma: 0.450; median half-axis 1.23 m); velocity 0.921" in table
    assert "0.951 (1 sigma: 0.680; median sigma 8.0 deg)" in table
    assert "0.58 / 0.96 m; 0.50 / 0.58 m (95 % ellipse holds 0.903 / 0.891)" in table
    assert "0.800 (60.0 frames/s at pace ?)" in table  # a summary of before the pace was recorded
    s |= {"pace": "1", "providers": {"pipeline_detect": ["CUDAExecutionProvider", "CPUExecutionProvider"],
                                     "detector_alone": ["CUDAExecutionProvider", "CPUExecutionProvider"]}}
    s["latency_ms"] = {**lat, "detect_step_p50": 2.0}
    table = summary_table(s)
    assert "0.800 (60.0 frames/s at pace 1: capped by the cameras' frame rate, not the pipeline's capacity)" in table
    assert "CUDAExecutionProvider, CPUExecutionProvider / CUDAExecutionProvider, CPUExecutionProvider" in table
    assert "1.0 / 2.0 ms" in table
