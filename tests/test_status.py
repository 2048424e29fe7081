"""Status reports: what each running service has done, on the bus (shared/status.py, `roadside status`).

The services' own reports (counts of a real chain, bad input by reason) are checked in test_services.py; here the
reporter, the message and the command line, on a Zenoh session of the test's own."""

from __future__ import annotations

import json
import math
import time

import msgpack
import pytest
from pipeline_fixtures import free_port_base, wait_until

from shared.bus import BadInput
from shared.codec import DecodeError, decode, encode
from shared.messages import Status
from shared.status import StatusReporter, instance_name, status_table


def status(**fields) -> Status:
    base = dict(site="se", seq=0, t_capture_ns=2_000_000_000, service="localize", instance="main",
                started_ns=1_000_000_000, period_s=2.0, cpu_s=1.5, peak_rss_mb=80.0)
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
    assert text.splitlines()[0] == ("localize/main: up 2 s, last output 1.5 s ago, CPU 1.5 s, peak memory 80 MB "
                                    "(reported 1.0 s ago)")
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
