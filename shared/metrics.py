"""The services' Status reports as Prometheus metrics (`roadside metrics`): what a cabinet's monitoring scrapes.

`render(reports, now_ns)` turns the newest Status report of each service (shared/status.py `collect_status`) into the
Prometheus text exposition format (version 0.0.4); `serve(...)` answers `GET /metrics` with it, asking the bus for
the reports at each scrape. Counts named `<what>.<camera>` (e.g. `frames_out.NE`) get a `camera` label. The reasons of
bad input are free text and stay in the logs and `roadside status`: here only their total.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from shared.messages import Status

log = logging.getLogger("roadside.metrics")

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
PREFIX = "roadside_"
# name -> (type, help) of every family, in the order they are written
FAMILIES = {
    "up": ("gauge", "1 for each service whose status report answered this scrape"),
    "messages_total": ("counter", "messages by what they were since the service started (Status counts)"),
    "message_rate": ("gauge", "the same per second over the service's last report period"),
    "bad_messages_total": ("counter", "bad input dropped since the service started, all reasons"),
    "reading": ("gauge", "the service's readings of now (Status gauges)"),
    "cpu_seconds_total": ("counter", "CPU time of the service's process"),
    "resident_memory_bytes": ("gauge", "resident memory of the service's process at its last report"),
    "peak_resident_memory_bytes": ("gauge", "peak resident memory of the service's process"),
    "start_time_seconds": ("gauge", "when the service started, UNIX time"),
    "last_output_age_seconds": ("gauge", "seconds since the service last published its output (absent: never)"),
    "report_age_seconds": ("gauge", "seconds since the service took the report"),
}


def escape(value: str) -> str:
    """A label value as the exposition format wants it: backslash, double quote and newline escaped."""
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _number(value: float) -> str:
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(int(value)) if float(value).is_integer() and abs(value) < 2**53 else repr(float(value))


def render(reports: list[Status], now_ns: int | None = None) -> str:
    """The metrics of these reports (one newest report per service instance), Prometheus text format."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    samples: dict[str, list[tuple[dict[str, str], float]]] = {name: [] for name in FAMILIES}
    for r in reports:
        base = {"site": r.site, "service": r.service, "instance": r.instance}
        samples["up"].append((base, 1))
        for family, values in (("messages_total", r.counts), ("message_rate", r.rates)):
            for name, value in sorted(values.items()):
                what, _, camera = name.partition(".")
                samples[family].append(({**base, "name": what, **({"camera": camera} if camera else {})}, value))
        samples["bad_messages_total"].append((base, sum(r.bad.values())))
        for name, value in sorted(r.gauges.items()):
            samples["reading"].append(({**base, "name": name}, value))
        samples["cpu_seconds_total"].append((base, r.cpu_s))
        samples["resident_memory_bytes"].append((base, round(r.rss_mb * 2**20)))
        samples["peak_resident_memory_bytes"].append((base, round(r.peak_rss_mb * 2**20)))
        samples["start_time_seconds"].append((base, r.started_ns / 1e9))
        if r.last_output_ns:
            samples["last_output_age_seconds"].append((base, max(now_ns - r.last_output_ns, 0) / 1e9))
        samples["report_age_seconds"].append((base, max(now_ns - r.t_capture_ns, 0) / 1e9))
    lines = []
    for family, (kind, text) in FAMILIES.items():
        name = PREFIX + family
        lines += [f"# HELP {name} {text}", f"# TYPE {name} {kind}"]
        for labels, value in samples[family]:
            label_text = ",".join(f'{k}="{escape(v)}"' for k, v in labels.items())
            lines.append(f"{name}{{{label_text}}} {_number(value)}")
    return "\n".join(lines) + "\n"


def serve(host: str, port: int, scrape: Callable[[], list[Status]], ready: Callable[[int], None] | None = None,
          stop: Callable[[], bool] = lambda: False) -> None:
    """Answer `GET /metrics` with `render(scrape())` on host:port until `stop()` (checked every half second);
    `ready(port)` once listening (port 0: any free port, the one taken)."""

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            if self.path.split("?")[0] != "/metrics":
                self.send_error(404, "only /metrics is served here")
                return
            try:
                body = render(scrape()).encode()
            except Exception as exc:  # the bus failed this scrape: say so, keep serving
                log.warning("scrape failed: %s: %s", type(exc).__name__, exc)
                self.send_error(503, f"the bus did not answer: {type(exc).__name__}")
                return
            self.send_response(200)
            self.send_header("Content-Type", CONTENT_TYPE)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, fmt: str, *args) -> None:  # scrapes every few seconds: not one log line each
            log.debug(fmt, *args)

    with ThreadingHTTPServer((host, port), Handler) as server:
        server.timeout = 0.5
        if ready is not None:
            ready(server.server_address[1])
        while not stop():
            server.handle_request()
