"""`roadside metrics` (shared/metrics.py): the services' Status reports as Prometheus metrics."""

from __future__ import annotations

import re
import threading
import urllib.error
import urllib.request

import pytest
from pipeline_fixtures import free_port_base, wait_until

from shared.bus import BadInput
from shared.messages import Status
from shared.metrics import CONTENT_TYPE, FAMILIES, escape, render, serve
from shared.status import StatusReporter, collect_status

NOW = 10**18
# a sample line of the exposition format: name{label="value",...} number
SAMPLE = re.compile(r'^([a-z_]+)\{((?:[a-z_]+="(?:[^"\\\\\n]|\\\\.)*",?)*)\} (-?[0-9.e+]+|NaN|[+-]Inf)$')


def status(**fields) -> Status:
    base = dict(site="se", seq=3, t_capture_ns=NOW - 2 * 10**9, service="detect", instance="cab-1",
                started_ns=NOW - 600 * 10**9, period_s=2.0, cpu_s=12.5, rss_mb=200.25, peak_rss_mb=212.5)
    return Status(**{**base, **fields})


def samples(text: str) -> dict[tuple[str, frozenset], float]:
    out = {}
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        m = SAMPLE.match(line)
        assert m, f"not a sample line: {line!r}"
        labels = frozenset(re.findall(r'([a-z_]+)="((?:[^"\\]|\\.)*)"', m.group(2)))
        out[(m.group(1), labels)] = float(m.group(3))
    return out


def test_render_gives_each_family_once_and_every_report_its_samples() -> None:
    text = render([status(counts={"frames_in": 40, "frames_skipped.NE": 3}, rates={"frames_in": 19.5},
                          bad={"garbage": 2, "wrong version": 1}, gauges={"infer_ms": 61.25},
                          last_output_ns=NOW - 500_000_000),
                   status(service="fuse_track", instance="t1", counts={"tracks_out": 9})], now_ns=NOW)
    for family, (kind, _) in FAMILIES.items():
        assert text.count(f"# TYPE roadside_{family} {kind}\n") == 1, family
    got = samples(text)
    detect = {("site", "se"), ("service", "detect"), ("instance", "cab-1")}
    assert got[("roadside_up", frozenset(detect))] == 1
    assert got[("roadside_messages_total", frozenset(detect | {("name", "frames_in")}))] == 40
    assert got[("roadside_messages_total", frozenset(detect | {("name", "frames_skipped"), ("camera", "NE")}))] == 3
    assert got[("roadside_message_rate", frozenset(detect | {("name", "frames_in")}))] == 19.5
    assert got[("roadside_bad_messages_total", frozenset(detect))] == 3
    assert got[("roadside_reading", frozenset(detect | {("name", "infer_ms")}))] == 61.25
    assert got[("roadside_cpu_seconds_total", frozenset(detect))] == 12.5
    assert got[("roadside_resident_memory_bytes", frozenset(detect))] == 200.25 * 2**20
    assert got[("roadside_peak_resident_memory_bytes", frozenset(detect))] == 212.5 * 2**20
    assert got[("roadside_start_time_seconds", frozenset(detect))] == (NOW - 600 * 10**9) / 1e9
    assert got[("roadside_last_output_age_seconds", frozenset(detect))] == 0.5
    assert got[("roadside_report_age_seconds", frozenset(detect))] == 2.0
    fuse = frozenset({("site", "se"), ("service", "fuse_track"), ("instance", "t1")})
    assert ("roadside_last_output_age_seconds", fuse) not in got  # never published: no age, not a huge one
    assert render([], now_ns=NOW).count("# TYPE") == len(FAMILIES)  # nobody answered: families, no samples


def test_label_values_are_escaped() -> None:
    assert escape('a"b\\c\nd') == 'a\\"b\\\\c\\nd'


def test_metrics_are_served_from_the_reports_on_the_bus() -> None:
    import zenoh

    from shared.bus import zenoh_config
    from shared.settings import BusSettings

    port_base = free_port_base()
    service = zenoh.open(zenoh_config(BusSettings(port_base=port_base), "localize"))  # where localize listens
    reporter = StatusReporter(service, "se", "localize", BadInput("localize"), 0.1, instance="main")
    watcher = zenoh.open(zenoh_config(BusSettings(port_base=port_base), None, 0))
    stop, ready = threading.Event(), []
    server = threading.Thread(target=serve, args=("127.0.0.1", 0, lambda: collect_status(watcher, "se", 1.0)[0]),
                              kwargs={"ready": ready.append, "stop": stop.is_set}, daemon=True)
    server.start()
    try:
        reporter.count("objects_out", 7, output=True)
        assert wait_until(lambda: ready, 10)
        url = f"http://127.0.0.1:{ready[0]}"

        def scraped() -> bool:
            with urllib.request.urlopen(url + "/metrics", timeout=5) as reply:
                assert reply.headers["Content-Type"] == CONTENT_TYPE
                body = reply.read().decode()
            key = ("roadside_messages_total",
                   frozenset({("site", "se"), ("service", "localize"), ("instance", "main"), ("name", "objects_out")}))
            return samples(body).get(key) == 7

        assert wait_until(scraped, 20, 0.2)
        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(url + "/", timeout=5)
    finally:
        stop.set()
        server.join(5)
        reporter.close()
        watcher.close()
        service.close()
    assert not server.is_alive()


def test_roadside_metrics_refuses_a_port_off_the_range(capsys) -> None:
    from roadside.cli import main

    with pytest.raises(SystemExit):
        main(["metrics", "--port", "70000"])
    assert "must be a port from 1 to 65535, got 70000" in capsys.readouterr().err
