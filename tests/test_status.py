"""Status reports: what each running service has done, on the bus (shared/status.py, `roadside status`).

The services' own reports (counts of a real chain, bad input by reason) are checked in test_services.py; here the
reporter, the message and the command line, on a Zenoh session of the test's own."""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import yaml
from pipeline_fixtures import free_port_base, wait_until

from shared.bus import BadInput
from shared.codec import DecodeError, decode, encode
from shared.messages import Status
from shared.status import StatusReporter, instance_name, status_table


def status(**fields) -> Status:
    base = dict(site="se", seq=0, t_capture_ns=2_000_000_000, service="localize", instance="main",
                started_ns=1_000_000_000, period_s=2.0, cpu_s=1.5, rss_mb=72.0, peak_rss_mb=80.0)
    return Status(**{**base, **fields})


def test_reporter_counts_rates_readings_and_bad_input():
    bad = BadInput("localize")
    rep = StatusReporter(None, "se", "localize", bad, 0.0, instance="main")
    first = rep.report()
    assert first.counts == {} and first.last_output_ns == 0 and first.seq == 0
    rep.count("detections_in", 3)
    rep.count("objects_out", output=True)
    rep.gauge("held", 2.5)
    rep.gauge("mean_ms", math.nan)  # a mean of nothing: no reading
    bad("detections from camera 'SW', not at this site", "SW")
    bad("frame 12 refused", "NE")
    bad("frame 13 refused", "NE")  # the same reason but for its numbers: one key
    time.sleep(0.05)
    second = rep.report()
    assert second.seq == 1 and second.counts == {"detections_in": 3, "objects_out": 1}
    assert second.bad == {"detections from camera 'SW', not at this site": 1, "frame # refused": 2}
    assert second.gauges == {"held": 2.5}
    assert second.last_output_ns >= second.started_ns > 0 and second.period_s >= 0.05
    assert second.rates["detections_in"] == pytest.approx(3 / second.period_s, rel=0.02)
    # rates cover the time since the report before: nothing new, nothing per second
    assert rep.report().rates == {"detections_in": 0.0, "objects_out": 0.0}
    rep.gauge("held", math.inf)
    assert rep.report().gauges == {}
    assert decode(encode(second), Status) == second


def test_a_report_gives_the_memory_of_now_beside_the_peak():
    """200 MB taken and given back: the report of now rises by it and falls again, the peak stays."""
    rep = StatusReporter(None, "se", "localize", BadInput("localize"), 0.0, instance="main")
    before = rep.report()
    block = np.ones(200 * 2**20, np.uint8)  # touched: resident
    held = rep.report()
    del block
    after = rep.report()
    # the kernel updates its high-water mark lazily: it may trail the resident figure by a little
    assert held.rss_mb - before.rss_mb > 150 and held.peak_rss_mb >= held.rss_mb - 2
    assert held.rss_mb - after.rss_mb > 150 and after.peak_rss_mb >= held.rss_mb - 2


def test_reporter_refuses_a_bad_period_and_names_its_process():
    with pytest.raises(ValueError, match="period_s must be a finite number >= 0, got -1"):
        StatusReporter(None, "se", "detect", BadInput("detect"), -1.0)
    with pytest.raises(ValueError, match="service must be one of"):
        StatusReporter(None, "se", "tracker", BadInput("x"), 1.0)
    name = instance_name()
    assert 0 < len(name) <= 64 and StatusReporter(None, "se", "detect", BadInput("d"), 1.0).instance == name


@pytest.mark.parametrize(("fields", "message"), [
    ({"service": "tracker"}, "service"),
    ({"instance": "a/b"}, "instance name must be"),
    ({"counts": {"frames_in": -1}}, "greater than or equal to 0"),
    ({"counts": {"": 1}}, "at least 1 character"),
    ({"rates": {"frames_in": math.nan}}, "finite number"),
    ({"gauges": {"held": math.inf}}, "finite number"),
    ({"bad": {str(i): 1 for i in range(301)}}, "at most 300 items"),
    ({"period_s": 0.0}, "greater than 0"),
    ({"peak_rss_mb": math.nan}, "finite number"),
    ({"rss_mb": -1.0}, "greater than or equal to 0"),
])
def test_a_status_message_validates_what_it_carries(fields, message):
    with pytest.raises(ValueError, match=message):
        status(**fields)


def test_a_status_map_on_the_wire_is_a_map_not_an_array():
    payload = msgpack.unpackb(encode(status(counts={"frames_in": 4})), raw=False)
    assert payload["counts"] == {"frames_in": 4}  # not {dtype, shape, data}
    payload["counts"] = {"dtype": "<f4", "shape": [1], "data": b"\x00\x00\x80?"}  # an array where a map belongs
    with pytest.raises(DecodeError, match=r"status does not validate: counts\.dtype"):
        decode(msgpack.packb(payload, use_bin_type=True))


def test_status_table_reads_like_the_service_it_describes():
    text = status_table([status(counts={"objects_out": 10}, rates={"objects_out": 5.0}, bad={"not msgpack": 2},
                                gauges={"held": 3.0}, last_output_ns=1_500_000_000)], now_ns=3_000_000_000)
    assert text.splitlines()[0] == ("localize/main: up 2 s, last output 1.5 s ago, CPU 1.5 s, memory 72 MB, peak "
                                    "80 MB (reported 1.0 s ago)")
    assert "objects_out" in text and "5.0/s" in text and "bad x2: not msgpack" in text and "held" in text


def test_roadside_status_asks_the_services_on_the_bus(capsys):
    import zenoh

    from roadside.cli import main
    from shared.bus import zenoh_config
    from shared.settings import BusSettings

    port_base = free_port_base()
    assert main(["status", "--port-base", str(port_base), "--timeout", "0.5"]) == 1
    assert "no service of site state_ellsworth answered" in capsys.readouterr().out

    session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), "localize"))  # where localize listens
    rep = StatusReporter(session, "state_ellsworth", "localize", BadInput("localize"), 0.1, instance="main")
    try:
        rep.count("objects_out", 7, output=True)

        def answered() -> bool:
            rc = main(["status", "--port-base", str(port_base), "--timeout", "1", "--json", "--require", "localize"])
            return rc == 0 and json.loads(capsys.readouterr().out.splitlines()[-1])["services"][0]["counts"] == {
                "objects_out": 7}

        assert wait_until(answered, 20.0, 0.2)
        assert main(["status", "--port-base", str(port_base), "--timeout", "1", "--require", "detect"]) == 1
        out = capsys.readouterr().out
        assert "localize/main: up" in out and "not answering: detect" in out
    finally:
        rep.close()
        session.close()


def test_roadside_status_takes_a_site_file_for_its_name_and_bus(tmp_path, monkeypatch, capsys):
    """`--site` as a site folder or its site.yaml: the site's name and its bus (environment overrides included), as a
    cabinet's compose metrics service asks; a file that does not load is named."""
    import zenoh

    from roadside.cli import main
    from shared.bus import zenoh_config
    from shared.settings import BusSettings

    port_base = free_port_base()
    folder = Path(__file__).resolve().parent.parent / "deploy" / "sites" / "example"
    name = yaml.safe_load((folder / "site.yaml").read_text())["site"]
    assert name != "state_ellsworth"  # not the default name: the file's name is the one asked for
    monkeypatch.setenv("ROADSIDE_BUS__PORT_BASE", str(port_base))
    session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), "localize"))  # where localize listens
    rep = StatusReporter(session, name, "localize", BadInput("localize"), 0.1, instance="main")
    try:
        rep.count("objects_out", 3, output=True)
        for site in (folder, folder / "site.yaml"):
            def answered(site=site) -> bool:
                rc = main(["status", "--site", str(site), "--timeout", "1", "--json", "--require", "localize"])
                doc = json.loads(capsys.readouterr().out.splitlines()[-1])
                return rc == 0 and [(r["site"], r["counts"]) for r in doc["services"]] == [(name, {"objects_out": 3})]

            assert wait_until(answered, 20.0, 0.2), site
        # --port-base over the file's bus: nothing listens there
        assert main(["status", "--site", str(folder), "--port-base", str(free_port_base()), "--timeout", "0.5"]) == 1
        assert f"no service of site {name} answered" in capsys.readouterr().out
    finally:
        rep.close()
        session.close()
    bad = tmp_path / "site.yaml"
    bad.write_text("site: x\ncameras: 3\n")
    assert main(["status", "--site", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err


# --- health: alive and working ------------------------------------------------------------------------------------

NOW = 10**18  # ns


def at(seconds_ago: float) -> int:
    return int(NOW - seconds_ago * 1e9)


def test_a_fed_service_that_publishes_nothing_is_stalled_an_idle_one_is_not():
    from shared.status import stall_reasons

    ingest = status(service="ingest", instance="cam", counts={"frames_out.NE": 900}, rates={"frames_out.NE": 10.0},
                    t_capture_ns=at(1), last_output_ns=at(1))
    detect = status(service="detect", instance="gpu", counts={"frames_in": 50, "detections_out": 50},
                    rates={"frames_in": 0.0, "detections_out": 0.0}, t_capture_ns=at(1), started_ns=at(60),
                    last_output_ns=at(20), bad={"frame NE: corrupt JPEG": 3})
    # its upstream publishes, its loop takes nothing in (wedged): stalled, with what it dropped
    assert stall_reasons("detect", [ingest, detect], NOW, 15.0) == [
        "detect/gpu: fed 10.0 messages/s but published nothing more for 19 s "
        "(3 bad inputs dropped so far: roadside status)"]
    assert stall_reasons("detect", [ingest, detect], NOW, 25.0) == []  # not yet that long
    # nothing fed (the playback ended): idle, not stalled
    idle = ingest.model_copy(update={"rates": {"frames_out.NE": 0.0}})
    assert stall_reasons("detect", [idle, detect], NOW, 15.0) == []
    # a stopping upstream feeds nothing more
    assert stall_reasons("detect", [ingest.model_copy(update={"final": True}), detect], NOW, 15.0) == []
    # its own inputs count without its upstream's report; never published: since its start
    fuse = status(service="fuse_track", counts={"objects_in": 400}, rates={"objects_in": 38.0}, t_capture_ns=at(1),
                  started_ns=at(30), last_output_ns=0)
    assert stall_reasons("fuse_track", [fuse], NOW, 15.0) == [
        "fuse_track/main: fed 38.0 messages/s but published nothing for 29 s"]
    # quiet is counted as of the report: a report some seconds old (a long period) of a service that had just
    # published is neither stalled nor stale
    fresh = detect.model_copy(update={"t_capture_ns": at(10), "last_output_ns": at(10)})
    assert stall_reasons("detect", [ingest, fresh], NOW, 5.0, period_s=4.0) == []
    # another service's reports say nothing of this one
    assert stall_reasons("localize", [ingest, detect], NOW, 15.0) == []


def test_stale_and_final_reports_and_ingest_by_staleness_alone():
    from shared.status import stall_reasons

    stale = status(service="localize", t_capture_ns=at(40), last_output_ns=at(40))
    assert stall_reasons("localize", [stale], NOW, 15.0) == [
        "localize/main: its newest status report is 40 s old (reporting stopped)"]
    assert stall_reasons("localize", [stale], NOW, 15.0, period_s=20.0) == []  # reports every 20 s: not yet stale
    assert stall_reasons("localize", [stale.model_copy(update={"final": True})], NOW, 15.0) == [
        "localize/main: stopping"]
    ingest = status(service="ingest", counts={"frames_out.NE": 9}, rates={"frames_out.NE": 0.0},
                    t_capture_ns=at(1), last_output_ns=at(500))  # its source ended long ago
    assert stall_reasons("ingest", [ingest], NOW, 15.0) == []
    with pytest.raises(ValueError, match="stalled_after_s"):
        stall_reasons("ingest", [ingest], NOW, 0.0)


def test_roadside_health_says_alive_but_not_working_then_working(tmp_path, monkeypatch, capsys):
    """Over a real bus: detect's token is up and ingest feeds it, but it publishes nothing -> exit 1 naming why;
    once it publishes -> exit 0. Without the status check the token alone decides."""
    import zenoh

    from roadside.cli import main
    from shared.bus import declare_alive, zenoh_config
    from shared.settings import BusSettings

    port_base = free_port_base()
    monkeypatch.setenv("ROADSIDE_BUS__PORT_BASE", str(port_base))
    monkeypatch.setenv("ROADSIDE_BUS__STATUS_PERIOD_S", "0.2")
    site = str(Path(__file__).resolve().parent.parent / "deploy" / "sites" / "example" / "site.yaml")
    name = yaml.safe_load(open(site))["site"]
    args = ["health", "--site", site, "--service", "detect", "--timeout", "2"]
    assert main(args) == 1 and "detect: not seen (0 tokens)" in capsys.readouterr().out

    session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), "detect"))  # where detect listens
    tokens = declare_alive(session, name, "detect", ["NE"])
    feeder = StatusReporter(session, name, "ingest", BadInput("ingest"), 0.2, instance="cam")
    detect = StatusReporter(session, name, "detect", BadInput("detect"), 0.2, instance="gpu")
    feeding = threading.Event()

    def feed() -> None:  # ingest publishes all along, as at 20 frames/s
        while not feeding.wait(0.05):
            feeder.count("frames_out.NE", output=True)

    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    try:
        def stalled() -> bool:
            rc = main([*args, "--stalled-after", "0.3"])
            out = capsys.readouterr().out
            return rc == 1 and "messages/s but published nothing for" in out and "detect: not working" in out

        assert wait_until(stalled, 20.0, 0.3)
        assert main([*args, "--stalled-after", "0"]) == 0 and "detect: alive (1 tokens)" in capsys.readouterr().out

        def working() -> bool:
            detect.count("detections_out", output=True)
            rc = main([*args, "--stalled-after", "5"])
            return rc == 0 and "detect: working (1 tokens)" in capsys.readouterr().out

        assert wait_until(working, 20.0, 0.3)
    finally:
        feeding.set()
        thread.join()
        detect.close()
        feeder.close()
        for t in tokens:
            t.undeclare()
        session.close()


def test_a_site_path_that_is_not_there_is_named_and_the_flags_go_over_the_site_files_bus(tmp_path, capsys):
    import argparse

    from roadside.cli import main
    from roadside.cli_bus import _bus, _site, add_bus_jobs

    assert main(["status", "--site", str(tmp_path / "exmaple"), "--timeout", "0.2"]) == 2
    assert f"site not found: {tmp_path / 'exmaple'}" in capsys.readouterr().err
    assert main(["status", "--site", "nosuch.yaml", "--timeout", "0.2"]) == 2
    site = tmp_path / "site.yaml"
    site.write_text(yaml.safe_dump({"site": "elm", "cameras": [{"name": "NE", "kind": "fisheye", "width": 64,
                                                                    "height": 64}],
                                    "bus": {"mode": "client", "connect": ["tcp/10.0.0.2:7447"], "host": "10.0.0.9",
                                            "tls_root_ca": "/etc/ca.pem"}}))
    parser = argparse.ArgumentParser()
    add_bus_jobs(parser.add_subparsers(dest="job"))

    def bus(*flags: str):
        args = parser.parse_args(["status", "--site", str(site), *flags])
        _site(args)
        return args.site, _bus(args)

    name, b = bus()
    assert name == "elm"
    assert (b.mode, b.connect, b.tls_root_ca) == ("client", ["tcp/10.0.0.2:7447"], Path("/etc/ca.pem"))
    _, b = bus("--connect", "tls/10.0.0.3:7448")  # another router: the file's CA still checks it
    assert (b.mode, b.connect, b.tls_root_ca) == ("client", ["tls/10.0.0.3:7448"], Path("/etc/ca.pem"))
    _, b = bus("--port-base", "20000", "--ca", "/tmp/other.pem")  # the embedded default on the file's host
    assert (b.mode, b.port_base, b.host, b.connect, b.tls_root_ca) == ("peer", 20000, "10.0.0.9", [],
                                                                        Path("/tmp/other.pem"))


def test_roadside_status_without_site_names_the_sites_whose_services_are_on_the_bus(capsys):
    """`roadside status --connect` (or --port-base) without --site asks for the default site; when the bus is another
    site's, the answer names the sites whose services are there (their liveliness tokens; an observer's is none)."""
    import zenoh

    from roadside.cli import main
    from shared.bus import declare_alive, zenoh_config
    from shared.keys import observer_alive_key
    from shared.settings import BusSettings

    port_base = free_port_base()
    session = zenoh.open(zenoh_config(BusSettings(port_base=port_base), "localize"))  # where localize listens
    tokens = [*declare_alive(session, "elm", "localize", ["main"]), *declare_alive(session, "oak", "detect", ["gpu"]),
              session.liveliness().declare_token(observer_alive_key("pine", "recorder"))]
    try:
        for flags in (["--port-base", str(port_base)], ["--connect", f"tcp/127.0.0.1:{port_base + 2}"]):
            def told(flags=flags) -> bool:
                rc = main(["status", *flags, "--timeout", "1"])
                out = capsys.readouterr().out
                return rc == 1 and "no service of site state_ellsworth answered; this bus has sites elm, oak (--site)" \
                    in out and "pine" not in out

            assert wait_until(told, 20.0, 0.2), flags
        # the site asked for has a token but no status report: the other sites named
        assert main(["status", "--port-base", str(port_base), "--site", "elm", "--timeout", "0.5"]) == 1
        assert "no service of site elm answered; this bus has site oak (--site)" in capsys.readouterr().out
    finally:
        for t in tokens:
            t.undeclare()
        session.close()


def test_watched_readings_are_taken_when_a_report_is_made():
    """`watch`: readings a service keeps itself (ingest's frame recording) are read at each report, not handed over at
    every message; a later reading replaces the earlier one."""
    kept = {"recorded.NE": 0}
    reporter = StatusReporter(None, "site", "ingest", BadInput("ingest"), 0.0)
    reporter.watch(lambda: dict(kept))
    reporter.gauge("ack_timeouts", 2)
    assert reporter.report().gauges == {"ack_timeouts": 2.0, "recorded.NE": 0.0}
    kept["recorded.NE"] = 7
    assert reporter.report().gauges["recorded.NE"] == 7.0
