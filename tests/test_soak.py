"""bench/soak.py's own parts: which processes are the services, memory growth, and the summary of samples (a
restarted service is a second process). The whole run is tested with `roadside up` in tests/test_services.py."""

from __future__ import annotations

import subprocess
import sys
import time

import psutil
import pytest

from bench.soak import growth_mb_per_hour, service_processes, summarize


def test_growth_is_the_least_squares_slope_in_mb_per_hour() -> None:
    flat = [(t, 100.0) for t in range(0, 600, 30)]
    assert growth_mb_per_hour(flat) == pytest.approx(0.0, abs=1e-9)
    leaking = [(t, 100.0 + t / 360.0) for t in range(0, 600, 30)]  # 10 MB an hour
    assert growth_mb_per_hour(leaking) == pytest.approx(10.0)
    assert growth_mb_per_hour(leaking[:2]) is None  # too few samples to say


def sample(t_s: float, rss: dict, status: dict | None = None) -> dict:
    return {"t_s": t_s, "rss_mb": {"ingest": {}, "detect": {}, "localize": {}, "fuse_track": {}, **rss},
            "status": status or {}}


def test_summary_leaves_the_warm_up_out_and_counts_a_restart() -> None:
    report = {"t_capture_ns": 1, "counts": {"frames_out.NE": 5, "frames_out.SW": 7}, "bad": {"late": 2},
              "cpu_s": 3.5, "peak_rss_mb": 99.0}
    samples = [sample(0, {"ingest": {11: 50.0}, "detect": {21: 300.0}}),  # warming up: not in the growth
               sample(60, {"ingest": {11: 80.0}, "detect": {21: 200.0}}),
               sample(120, {"ingest": {11: 80.0}, "detect": {22: 210.0}}),  # detect restarted: a new process
               sample(180, {"ingest": {11: 80.0}, "detect": {22: 220.0}}, {"ingest": report})]
    out = summarize(samples, warmup_s=60)
    ingest, detect = out["ingest"], out["detect"]
    assert (ingest["rss_mb_after_warmup"], ingest["rss_mb_end"], ingest["rss_mb_max"]) == (80.0, 80.0, 80.0)
    assert ingest["growth_mb_per_hour"] == pytest.approx(0.0, abs=1e-6)
    assert ingest["counts"] == {"frames_out": 12} and ingest["bad"] == 2 and ingest["cpu_s"] == 3.5
    assert (detect["processes"], detect["restarts"]) == (2, 1)
    assert detect["growth_mb_per_hour"] == pytest.approx(600.0)  # 10 MB a minute after the warm-up
    assert detect["rss_mb_max"] == 300.0 and detect["counts"] is None  # no report from it
    assert out["localize"]["rss_mb_end"] is None and out["localize"]["processes"] == 0


def test_service_processes_are_found_by_their_module_among_the_launchers_children() -> None:
    code = "import subprocess, sys, time; " \
           "kids = [subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)', arg]) " \
           "for arg in ('services.detect', 'services.unknown', 'other')]; time.sleep(30)"
    parent = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(psutil.Process(parent.pid).children()) < 3:
            time.sleep(0.1)
        assert sorted(service_processes(parent.pid).values()) == ["detect"]
    finally:
        for kid in psutil.Process(parent.pid).children(recursive=True):
            kid.kill()
        parent.kill()
        parent.wait()
