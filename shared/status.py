"""What each running service has done, on the bus for whoever looks after the cabinet (`roadside status`).

Every service keeps a `StatusReporter`: it counts what the service receives and publishes (`count`), holds a few
readings of now (`gauge`), and every `bus.status_period_s` publishes a Status message (shared/messages.py) on
`roadside/<site>/status/<service>/<instance>`: the counts since the start and their rates over the last period,
the bad input dropped so far by reason (the service's `BadInput`, which also logs each reason), when the service
last published its output, its CPU time and peak memory. A queryable on the same key answers with the newest
report at once, so `roadside status` need not wait a period. The report is built and sent from the reporter's own
thread; the service's loop only adds to counters (under a lock: a few hundred nanoseconds per call).

`collect_status` is the other end: the newest report of every service of a site that answers; `stall_reasons`
reads them for `roadside health`: a service whose token is on the bus but that publishes nothing while it is fed,
or whose reports stopped, is alive and not working.
"""

from __future__ import annotations

import logging
import math
import os
import re
import resource
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable

import zenoh

from shared.bus import BadInput
from shared.codec import DecodeError, decode, encode
from shared.keys import all_status_key, status_key
from shared.messages import SERVICES, Status

log = logging.getLogger("roadside.status")

UPSTREAM = {"detect": "ingest", "localize": "detect", "fuse_track": "localize"}  # whose output feeds whom


def _proc_status_mb(key: str) -> float | None:
    """A memory figure of /proc/self/status (e.g. "VmHWM", "VmRSS") in MB; None where there is none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB): VmHWM, which starts again at exec (getrusage's maximum would carry
    the parent's over: a service started by a large process)."""
    peak = _proc_status_mb("VmHWM")
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 if peak is None else peak


def rss_mb() -> float:
    """This process's resident memory now (MB): VmRSS; the peak where the system does not say."""
    now = _proc_status_mb("VmRSS")
    return peak_rss_mb() if now is None else now


def instance_name() -> str:
    """This process's name in its status key: host and process id (a container's host name is its id)."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", f"{socket.gethostname()}-{os.getpid()}")[-64:]


class StatusReporter:
    """Counts and readings of one service, reported on the bus every `period_s` (0: counted, never sent).

    `count(name, n)` adds n to a count (names as the Status message's: `<what>_<in|out>` or what was skipped);
    `output=True` also marks the service's output as just published. `gauge(name, value)` sets a reading.
    `watch(readings)` adds readings taken when a report is made (`readings()`: {name: value}), for what a service
    keeps itself and need not hand over at every message. `close()` stops the thread and sends a last report marked
    `final`."""

    def __init__(self, session: zenoh.Session | None, site: str, service: str, bad: BadInput, period_s: float,
                 instance: str | None = None) -> None:
        if not (period_s >= 0 and period_s < float("inf")):
            raise ValueError(f"period_s must be a finite number >= 0, got {period_s!r}")
        self.site, self.service, self.bad, self.period_s = site, service, bad, period_s
        self.instance = instance or instance_name()
        self.key = status_key(site, service, self.instance)
        self.started_ns = time.time_ns()
        self._counts: Counter[str] = Counter()
        self._gauges: dict[str, float] = {}
        self._watched: list[Callable[[], dict[str, float]]] = []
        self._last_output_ns = 0
        self._lock = threading.Lock()
        self._seq = 0
        self._before: tuple[float, Counter[str]] = (time.monotonic(), Counter())
        self._latest: bytes | None = None
        self._stop = threading.Event()
        self._pub = self._queryable = self._thread = None
        if session is not None and period_s > 0:
            self._pub = session.declare_publisher(self.key)
            self._queryable = session.declare_queryable(self.key, self._answer)
            self.publish()  # answers at once: a service that is up but has not yet reported is not a silent one
            self._thread = threading.Thread(target=self._run, name=f"status-{service}", daemon=True)
            self._thread.start()

    def count(self, name: str, n: int = 1, output: bool = False) -> None:
        with self._lock:
            self._counts[name] += n
            if output:
                self._last_output_ns = time.time_ns()

    def gauge(self, name: str, value: float) -> None:
        """Set a reading; a non-finite one (a mean of nothing) removes it until the next."""
        with self._lock:
            if math.isfinite(value):
                self._gauges[name] = float(value)
            else:
                self._gauges.pop(name, None)

    def watch(self, readings: Callable[[], dict[str, float]]) -> None:
        """Take `readings()` into every report from now on (read when the report is made, from the reporter's
        thread: `readings` must be safe to call from it)."""
        with self._lock:
            self._watched.append(readings)

    def report(self, final: bool = False) -> Status:
        """The Status message of now (rates over the time since the previous report)."""
        now, now_ns = time.monotonic(), time.time_ns()
        with self._lock:
            watched = list(self._watched)
        for readings in watched:
            for name, value in readings().items():
                self.gauge(name, value)
        with self._lock:
            counts, gauges, last_out = Counter(self._counts), dict(self._gauges), self._last_output_ns
        t0, before = self._before
        span = max(now - t0, 1e-3)
        self._before = (now, counts)
        msg = Status(site=self.site, seq=self._seq, t_capture_ns=now_ns, service=self.service,
                     instance=self.instance, started_ns=self.started_ns, period_s=round(span, 3),
                     counts=dict(counts), rates={k: round(max(v - before[k], 0) / span, 3) for k, v in counts.items()},
                     bad=dict(self.bad.counts), gauges=gauges,
                     last_output_ns=last_out, cpu_s=round(time.process_time(), 3),
                     rss_mb=round(rss_mb(), 1), peak_rss_mb=round(peak_rss_mb(), 1), final=final)
        self._seq += 1
        return msg

    def publish(self, final: bool = False) -> None:
        if self._pub is None:
            return
        try:
            payload = encode(self.report(final))
        except ValueError as exc:  # a reading the contract refuses: say so, keep the service running
            log.warning("%s: status report not sent: %s", self.service, exc)
            return
        self._latest = payload
        self._pub.put(payload)

    def _answer(self, query) -> None:  # Zenoh's thread: hands over bytes already encoded
        if self._latest is not None:
            query.reply(self.key, self._latest)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.publish()
            except Exception as exc:  # the session closing under a service that failed: never the service's end
                log.debug("status report not sent: %s", exc)

    def close(self) -> None:
        """Stop reporting; the last report says `final` (before the session closes)."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        try:
            self.publish(final=True)
        except zenoh.ZError as exc:
            log.debug("final status report not sent: %s", exc)
        self._queryable.undeclare()
        self._pub.undeclare()


def collect_status(session: zenoh.Session, site: str, timeout_s: float = 2.0) -> tuple[list[Status], list[str]]:
    """The newest Status of every service of `site` that answers within `timeout_s` (by service, then instance),
    and the reasons of replies that were not Status messages."""
    out: dict[str, Status] = {}
    errors: list[str] = []
    for reply in session.get(all_status_key(site), timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            msg = decode(reply.ok.payload.to_bytes(), Status)
        except DecodeError as exc:
            errors.append(f"{reply.ok.key_expr}: {exc}")
            continue
        key = f"{msg.service}/{msg.instance}"
        if key not in out or out[key].t_capture_ns < msg.t_capture_ns:
            out[key] = msg  # type: ignore[assignment]
    return sorted(out.values(), key=lambda m: (SERVICES.index(m.service), m.instance)), errors


def status_table(reports: list[Status], now_ns: int | None = None) -> str:
    """A readable table of reports: one block per service. Each service reports on its own clock: counts of two
    services may be up to a period apart (the header says how old each report is)."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    lines = []
    for m in reports:
        up = (now_ns - m.started_ns) / 1e9
        idle = f"{(now_ns - m.last_output_ns) / 1e9:.1f} s ago" if m.last_output_ns else "never"
        lines.append(f"{m.service}/{m.instance}: up {up:.0f} s, last output {idle}, CPU {m.cpu_s:.1f} s, "
                     f"memory {m.rss_mb:.0f} MB, peak {m.peak_rss_mb:.0f} MB (reported "
                     f"{(now_ns - m.t_capture_ns) / 1e9:.1f} s ago)"
                     f"{', stopping' if m.final else ''}")
        for name in sorted(m.counts):
            lines.append(f"  {name:<24} {m.counts[name]:>10}  {m.rates.get(name, 0.0):8.1f}/s")
        for name in sorted(m.gauges):
            lines.append(f"  {name:<24} {m.gauges[name]:>10.3g}")
        for reason, n in sorted(m.bad.items(), key=lambda kv: -kv[1]):
            lines.append(f"  bad x{n}: {reason}")
    return "\n".join(lines)


def _rate(report: Status, suffix: str) -> float:
    """Messages per second over the report's period of the counts named `<what>_<suffix>` (or `..._out.<camera>`)."""
    return sum(r for name, r in report.rates.items() if name.endswith(f"_{suffix}") or f"_{suffix}." in name)


def stall_reasons(service: str, reports: list[Status], now_ns: int, stalled_after_s: float,
                  period_s: float = 2.0) -> list[str]:
    """Why the instances of `service` among `reports` are not working though they answer, one line each (none: all
    work). An instance is stalled when it was fed in its last period (its own inputs, or its upstream service's
    output, which counts even when a wedged loop takes nothing in) and, when it reported, had published nothing for
    `stalled_after_s` (since its start, when it never had); its reports are stale when the newest is older than
    that and than three of its periods `period_s` (`bus.status_period_s`: its reporting thread stopped); a final
    report says it is stopping. Ingest, fed by its source, is only checked for staleness: a playback that ended is
    not a stall."""
    if not stalled_after_s > 0:
        raise ValueError(f"stalled_after_s must be > 0, got {stalled_after_s!r}")
    fed_upstream = sum(_rate(r, "out") for r in reports if r.service == UPSTREAM.get(service) and not r.final)
    reasons = []
    for r in reports:
        if r.service != service:
            continue
        name = f"{r.service}/{r.instance}"
        age = (now_ns - r.t_capture_ns) / 1e9
        quiet = (r.t_capture_ns - (r.last_output_ns or r.started_ns)) / 1e9  # as of the report: its age is not quiet
        fed = fed_upstream + _rate(r, "in")
        bad = sum(r.bad.values())
        if r.final:
            reasons.append(f"{name}: stopping")
        elif age > max(stalled_after_s, 3 * period_s):
            reasons.append(f"{name}: its newest status report is {age:.0f} s old (reporting stopped)")
        elif service in UPSTREAM and fed > 0 and quiet > stalled_after_s:
            reasons.append(f"{name}: fed {fed:.1f} messages/s but published "
                           f"{'nothing' if not r.last_output_ns else 'nothing more'} for {quiet:.0f} s"
                           + (f" ({bad} bad inputs dropped so far: roadside status)" if bad else ""))
    return reasons
