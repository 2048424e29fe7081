"""What the benchmarks measure: the calibration bench reports how much of the ground beyond the ROI its out-of-ROI
error covers, the soak's tracks rate leaves start-up and shutdown out, and the detector bench names the input shape
of every timing and also times the input the detect service gives the model."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest


def ground_grid(half_m: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """Exact ground points of a camera at the origin: one pixel per metre, x and y from -half_m to half_m."""
    y, x = np.mgrid[-half_m:half_m + 1, -half_m:half_m + 1].astype(np.float64)
    return np.stack([x, y, np.zeros_like(x)], axis=-1), np.ones(x.shape, bool)


def test_calibration_scores_give_the_coverage_of_the_ground_beyond_the_roi():
    from bench.calibration import mask_errors

    truth, valid = ground_grid()
    dist = np.linalg.norm(truth[..., :2], axis=-1)
    got = truth[..., :2] + np.where(dist < 25, 0.1, 1.0)[..., None] / np.sqrt(2)  # 0.1 m off in the ROI, 1 m beyond
    covered = dist < 60  # the masks end at a calibrated area of 60 m
    out = mask_errors(truth, valid, got.astype(np.float32), covered, np.array([0.0, 0.0, 8.0]))
    assert out["in_roi_mean_m"] == pytest.approx(0.1, abs=1e-6)
    assert out["out_roi_mean_m"] == pytest.approx(1.0, abs=1e-6)  # over the covered part only
    assert out["in_roi_coverage"] == 1.0
    beyond = dist >= 25
    assert out["out_roi_coverage"] == pytest.approx((beyond & covered).sum() / beyond.sum())
    assert 0.3 < out["out_roi_coverage"] < 0.5
    assert out["band_25_50_coverage"] == 1.0
    band = (dist >= 50) & (dist < 100)
    assert out["band_50_100_coverage"] == pytest.approx((band & covered).sum() / band.sum())
    assert out["band_100_200_coverage"] == 0.0 and out["band_100_200_mean_m"] is None  # ground there, none covered
    # no ground beyond the ROI: no share to give
    near = mask_errors(truth[70:91, 70:91], valid[70:91, 70:91], got[70:91, 70:91], covered[70:91, 70:91],
                       np.zeros(3))
    assert near["out_roi_coverage"] is None and near["out_roi_mean_m"] is None


def calibration_row(kind: str, modality: str, n: int, out_roi_coverage: float) -> dict:
    row = {"kind": kind, "modality": modality, "n": n, "in_roi_mean_m": 0.1, "out_roi_mean_m": 1.0,
           "out_roi_coverage": out_roi_coverage}
    for band in ("25_50", "50_100", "100_200"):
        row |= {f"band_{band}_mean_m": 0.5, f"band_{band}_coverage": out_roi_coverage}
    return row


def test_calibration_aggregates_give_the_out_of_roi_coverage_beside_the_mean():
    from bench.calibration import group_means

    rows = [calibration_row("fisheye", "visible", 10, 0.6), calibration_row("fisheye", "visible", 20, 0.5),
            calibration_row("fisheye", "visible", 5, 0.2), calibration_row("pinhole", "thermal", 10, 0.9)]
    out = group_means(rows, [calibration_row("pinhole", "thermal", 10, 0.7)])
    assert out["fisheye_out_roi_mean_m"] == 1.0 and out["fisheye_out_roi_coverage"] == 0.55
    assert out["fisheye_out_roi_coverage_at5"] == 0.2 and out["fisheye_band_50_100_coverage"] == 0.55
    assert out["thermal_out_roi_coverage"] == 0.9 and out["pinhole_out_roi_coverage"] is None
    assert out["thermal_out_roi_coverage_site_ground"] == 0.7


def fuse_track_sample(t_s: float, tracks_out: int, t_ns: int) -> dict:
    report = {"t_capture_ns": t_ns, "counts": {"tracks_out": tracks_out}}
    return {"t_s": t_s, "rss_mb": {}, "status": {"fuse_track": report}}


def test_soak_tracks_rate_is_between_the_first_and_last_samples_that_counted_tracks():
    from bench.soak import tracks_rate

    s = 1_000_000_000
    samples = [fuse_track_sample(30, 0, 30 * s),  # still starting
               fuse_track_sample(60, 200, 60 * s), fuse_track_sample(90, 500, 90 * s),
               fuse_track_sample(120, 100, 120 * s),  # fuse_track restarted: 100 since its restart
               fuse_track_sample(150, 400, 150 * s)]
    rate, window = tracks_rate(samples)
    assert window == 90.0 and rate == pytest.approx((300 + 100 + 300) / 90)
    assert tracks_rate(samples[:2]) == (None, None)  # one sample that counted tracks: no rate
    assert tracks_rate([{"t_s": 30, "rss_mb": {}, "status": {}}]) == (None, None)


def test_soak_tracks_per_s_leaves_start_up_and_shutdown_out(tmp_path, monkeypatch):
    """A fake `roadside up` publishing 10 Tracks messages a second from 0.4 s on, and taking 0.5 s to stop."""
    import zenoh

    import shared.settings
    from bench import soak

    class FakeUp:
        pid = 999_999_999

        def __init__(self, *args, **kwargs) -> None:
            self.rc = None

        def poll(self):
            return self.rc

        def send_signal(self, signum) -> None:
            pass

        def wait(self, timeout=None) -> int:
            time.sleep(0.5)  # the services' shutdown
            self.rc = 0
            return 0

        def kill(self) -> None:
            pass

    def fake_sample(launcher_pid, session, site, t_s) -> dict:  # t_s: seconds since the launch
        tracks = max(0.0, 10 * (t_s - 0.4))
        report = {"t_capture_ns": time.time_ns(), "counts": {"tracks_out": tracks}, "bad": {}}
        return {"t_s": t_s, "rss_mb": {svc: {} for svc in soak.SERVICES}, "status": {"fuse_track": report}}

    monkeypatch.setattr(soak.subprocess, "Popen", FakeUp)
    monkeypatch.setattr(soak, "sample", fake_sample)
    monkeypatch.setattr(zenoh, "open", lambda *args, **kwargs: SimpleNamespace(close=lambda: None))
    monkeypatch.setattr(shared.settings, "load_settings",
                        lambda site, **sets: SimpleNamespace(bus=shared.settings.BusSettings(), site="test"))
    doc = soak.run(Path("site"), "recording", 1.5 / 60, "1", 0.3, 0.0, tmp_path, [], log=lambda m: None)
    assert doc["samples"] >= 3
    assert doc["tracks_per_s"] == pytest.approx(10.0, abs=0.05)
    assert 0.3 < doc["tracks_rate_window_s"] < 1.2


def test_detector_bench_names_each_timings_input_and_times_the_deployed_input_too(tmp_path, monkeypatch):
    import bench.detector
    from bench.detector import BenchSettings, _parse, deployed_input, run
    from training.export import export_onnx
    from training.model import Detector, count_macs

    path = tmp_path / "d.onnx"
    export_onnx(Detector(), path, None, (64, 64))
    # a 1280x960 camera and a model whose input_long_side is 640: the detect service feeds it 480x640
    assert deployed_input(path, (1280, 960)) == (640, 480, 640)
    assert _parse([]).frame_wh == (1280, 960) and _parse([]).hw == (512, 512)
    # a GPU provider as on a machine that has one, so that run's bookkeeping of a GPU entry (its input named beside
    # the timing) is exercised; the GPU timing itself cannot run on this machine and is stubbed
    have = bench.detector.ort.get_available_providers()
    monkeypatch.setattr(bench.detector.ort, "get_available_providers", lambda: [*have, "CUDAExecutionProvider"])
    monkeypatch.setattr(bench.detector, "time_gpu", lambda *a: {"median_ms": 1.0})
    monkeypatch.setattr(bench.detector, "gpu_name", lambda: "a GPU")
    out = run(BenchSettings(model=path, size_px=64, height_px=96, runs=1, warmup=0, frame_wh=(160, 120)), tmp_path)
    assert "cuda_fp32" in out
    assert out["cuda_fp32"] == {"input": [1, 1, 96, 64], "median_ms": 1.0}  # run's input beside the stubbed timing
    assert out["target"]["input"] == [1, 1, 512, 512] and out["target"]["applies_to"] is None  # not 512x512
    assert out["cpu_fp32"]["input"] == out["cpu_fp32_throughput"]["input"] == out["input"] == [1, 1, 96, 64]
    deployed = out["deployed"]
    assert deployed["frame"] == [120, 160] and deployed["input_long_side"] == 640
    assert deployed["input"] == deployed["cpu_fp32"]["input"] == [1, 1, 128, 160]  # not shrunk, padded to 32
    assert deployed["macs"] == count_macs(Detector(), 128, 160) and deployed["cpu_fp32"]["median_ms"] > 0
    for key, value in out.items():
        if key.startswith(("cuda", "tensorrt")) and isinstance(value, dict):
            assert value["input"] == out["input"]
