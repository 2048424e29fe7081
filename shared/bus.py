"""Zenoh at the edges: one helper builds every process's session from its settings, and small pieces
every service uses (a decoding receiver that counts bad input, liveliness, clean shutdown).

Heavy work never runs in a Zenoh callback: subscribers use Zenoh's channels (a ring that keeps only
the newest samples for frames, a FIFO for the small messages) and the service's own loop receives.
"""

from __future__ import annotations

import errno
import json
import logging
import re
import signal
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Iterable
from pathlib import Path

import zenoh

from shared.codec import DecodeError, decode
from shared.keys import SERVICES, alive_key
from shared.messages import Message
from shared.settings import BusSettings, Settings

log = logging.getLogger("roadside.bus")
MAX_REASONS = 256  # distinct reasons counted and logged; more (names chosen by a sender) go under one key


def zenoh_config(bus: BusSettings, service: str | None = None, client_index: int = 0) -> zenoh.Config:
    """The Zenoh configuration of one process.

    peer mode (embedded default): listen on this service's own loopback port and connect to every other
    service's, multicast scouting off. A process that is not one of the services (a vehicle client, a
    test) listens on `port_base + 4 + client_index` (0 = listen nowhere) and connects to all services.
    client mode: connect to `bus.connect` (the router at the cabinet), listen nowhere.
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(bus.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    set_shared_memory(conf, bus.shared_memory)
    conf.insert_json5("transport/link/tx/queue/size/data", json.dumps(bus.tx_queue_batches))
    listen = list(bus.listen)
    if bus.mode == "peer":
        others = [bus.service_endpoint(s) for s in SERVICES if s != service]
        connect = [*bus.connect, *others]
        if service is not None:
            listen.append(bus.service_endpoint(service))
        elif client_index > 0:
            listen.append(f"tcp/{bus.host}:{bus.port_base + len(SERVICES) + client_index - 1}")
    else:
        if not bus.connect:
            raise ValueError("bus.mode is client but bus.connect names no router (e.g. tcp/zenoh:7447)")
        connect = list(bus.connect)
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    set_tls(conf, bus)
    return conf


def set_tls(conf, bus: BusSettings) -> None:
    """TLS for tls/ endpoints: check the router's certificate against `bus.tls_root_ca` (None: Zenoh's default, the
    system's roots), and with `bus.tls_certificate` and `tls_private_key` present this process's own to a router
    that asks for one (mutual TLS). ValueError naming the setting and the file when one is missing."""
    files = (("tls_root_ca", "CA certificate", "root_ca_certificate"),
             ("tls_certificate", "certificate", "connect_certificate"),
             ("tls_private_key", "private key", "connect_private_key"))
    for name, what, key in files:
        path = getattr(bus, name)
        if path is None:
            continue
        if not Path(path).is_file():
            raise ValueError(f"bus.{name}: {what} not found: {path}")
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(str(path)))
    if bus.tls_certificate is not None:
        conf.insert_json5("transport/link/tls/enable_mtls", "true")


def set_shared_memory(conf, enabled: bool) -> None:
    """Zenoh's shared-memory transport on or off (`bus.shared_memory`). A Zenoh built without it has no such key:
    off is then what it is anyway; on is an error naming the setting."""
    try:
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(enabled))
    except zenoh.ZError as exc:
        if enabled:
            msg = f"bus.shared_memory is true but this Zenoh has no shared-memory transport ({exc})"
            raise ValueError(msg) from None


def ports_in_use(bus: BusSettings, wait_s: float = 0.0) -> list[str]:
    """Peer mode: the services' endpoints on this machine that something already listens on ("localize
    tcp/127.0.0.1:7453"), after waiting up to `wait_s` for them to be freed (a pipeline that is stopping). A port
    in TIME_WAIT is free, as it is to Zenoh, which reuses addresses; client mode listens nowhere: []. ValueError
    for a `bus.host` that is no address of this machine or that cannot be resolved."""
    if bus.mode != "peer":
        return []
    host = bus.host.removeprefix("[").removesuffix("]")  # an IPv6 address may be given in brackets
    try:  # the address the services would listen on (an IPv6 one too); a name that does not resolve is no address
        family, _, _, _, sockaddr = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise ValueError(f"bus.host {bus.host} cannot be resolved ({getattr(exc, 'strerror', None) or exc}): the "
                         "services cannot listen there (127.0.0.1 for one machine)") from None
    deadline = time.monotonic() + wait_s
    while True:
        busy = []
        for service in SERVICES:
            port = bus.port_base + SERVICES.index(service)
            with socket.socket(family, socket.SOCK_STREAM) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                try:
                    s.bind((sockaddr[0], port, *sockaddr[2:]))
                except OSError as exc:
                    if exc.errno == errno.EADDRNOTAVAIL:  # no restart would mend it
                        raise ValueError(f"bus.host {bus.host} is not an address of this machine: the services "
                                         "cannot listen there (127.0.0.1 for one machine)") from None
                    if exc.errno == errno.EADDRINUSE:  # other errors: the service says
                        busy.append(f"{service} {bus.service_endpoint(service)}")
        if not busy or time.monotonic() >= deadline:
            return busy
        time.sleep(0.2)


def open_session(settings: Settings, service: str | None = None, client_index: int = 0) -> zenoh.Session:
    return zenoh.open(zenoh_config(settings.bus, service, client_index))


FIFO_BYTES = 256 * 1024 * 1024  # what a FIFO receiver holds at most: a flood of large messages cannot exhaust memory


class BadInput:
    """Counts rejected messages by reason and logs each reason once (then every 100th time). Reasons that
    differ only in their numbers (sequence numbers, sizes) count as one."""

    def __init__(self, service: str) -> None:
        self.service = service
        self.counts: Counter[str] = Counter()

    def __call__(self, reason: str, where: str = "", count: int = 1) -> None:
        """`count` messages dropped for `reason` (several at once: a queue that overflowed)."""
        key = re.sub(r"\d+", "#", reason)[:160]
        if key not in self.counts and len(self.counts) >= MAX_REASONS:
            key = "other reasons"
        before = self.counts[key]
        self.counts[key] += count
        n = self.counts[key]
        if before == 0 or before // 100 != n // 100:
            log.warning("%s: dropped %s message (%d so far with this reason): %s", self.service, where or "a", n,
                        reason)

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class Receiver:
    """A subscriber whose samples are decoded outside Zenoh's callback. The callback only appends the
    payload to a buffer and wakes the service loop (`wait`), so an idle service sleeps instead of
    polling. `ring` > 0 keeps only the newest `ring` samples (frames: a slow consumer drops old ones);
    otherwise a FIFO of at most `fifo` samples and `fifo_bytes` bytes: overflow drops the oldest, counts them in
    `overflow` and reports them to `bad` at the next `poll` (a service that falls behind says so).
    Several receivers may share one `wake` event."""

    def __init__(self, session: zenoh.Session, key: str, expect: type[Message] | None, bad: BadInput,
                 ring: int = 0, fifo: int = 4096, wake: threading.Event | None = None,
                 fifo_bytes: int = FIFO_BYTES) -> None:
        self.buffer: deque[tuple[str, bytes]] = deque(maxlen=ring if ring > 0 else fifo)
        self.wake = wake or threading.Event()
        self.overflow = 0
        self.skipped = 0  # ring: older samples pushed out unread by newer ones (a detector behind the cameras)
        self._reported = 0
        self.ring = ring > 0
        self.bytes = 0  # held in the FIFO
        self._lock = threading.Lock()

        def on_sample(sample) -> None:
            payload = sample.payload.to_bytes()
            if self.ring:
                if len(self.buffer) == self.buffer.maxlen:
                    self.skipped += 1
                self.buffer.append((str(sample.key_expr), payload))
            else:
                with self._lock:
                    while self.buffer and (len(self.buffer) == self.buffer.maxlen
                                           or self.bytes + len(payload) > fifo_bytes):
                        self.bytes -= len(self.buffer.popleft()[1])
                        self.overflow += 1
                    self.buffer.append((str(sample.key_expr), payload))
                    self.bytes += len(payload)
            self.wake.set()

        self.sub = session.declare_subscriber(key, on_sample)
        self.key = key
        self.expect = expect
        self.bad = bad

    def wait(self, timeout_s: float) -> None:
        """Sleep until a sample arrives (or the timeout)."""
        self.wake.wait(timeout_s)
        self.wake.clear()

    def poll(self) -> list[Message]:
        """Every message waiting now, decoded (bad ones counted and skipped)."""
        return [msg for _, msg in self.poll_keyed()]

    def poll_keyed(self) -> list[tuple[str, Message]]:
        """`poll`, each message with the key it came on (a wildcard subscriber's: which camera's)."""
        out = []
        if self.overflow > self._reported:
            dropped, self._reported = self.overflow - self._reported, self.overflow
            self.bad(f"{dropped} messages dropped unread: the service fell behind and its queue was full",
                     self.key, count=dropped)
        while self.buffer:
            try:
                if self.ring:
                    key, payload = self.buffer.popleft()
                else:
                    with self._lock:
                        key, payload = self.buffer.popleft()
                        self.bytes -= len(payload)
            except IndexError:
                break
            try:
                out.append((key, decode(payload, self.expect)))
            except DecodeError as exc:
                self.bad(str(exc), key)
        return out

    def undeclare(self) -> None:
        self.sub.undeclare()


class Stopper:
    """Set on SIGINT/SIGTERM (or by `stop()`); services loop `while not stopper.is_set()`."""

    def __init__(self, install_signals: bool = True) -> None:
        self.event = threading.Event()
        if install_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: self.event.set())

    def is_set(self) -> bool:
        return self.event.is_set()

    def stop(self) -> None:
        self.event.set()

    def wait(self, seconds: float) -> bool:
        return self.event.wait(seconds)


def declare_alive(session: zenoh.Session, site: str, service: str, instances: Iterable[str]) -> list:
    """Liveliness tokens `roadside/<site>/alive/<service>/<instance>`; they vanish when the process dies."""
    return [session.liveliness().declare_token(alive_key(site, service, i)) for i in instances]


def wait_for_peers(session: zenoh.Session, key: str, want: int, timeout_s: float,
                   stopper: Stopper | None = None) -> int:
    """Wait until `want` distinct liveliness tokens match `key` (or the timeout, or `stopper` set: a service told to
    stop while it waits stops at once); returns how many were seen.

    Distinct keys: a session in client mode gets its own tokens twice (its own and the router's answer), so a plain
    count let ingest at the cabinet start before the last services were ready."""
    deadline = time.monotonic() + timeout_s
    seen = 0
    while time.monotonic() < deadline and not (stopper is not None and stopper.is_set()):
        seen = len({str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=1.0) if r.ok is not None})
        if seen >= want:
            break
        time.sleep(0.1)
    return seen


def bus_sites(session, timeout_s: float = 1.0) -> set[str]:
    """The sites whose services are on the bus: their liveliness tokens `roadside/<site>/alive/<service>/...` (an
    observer's token, `.../alive/observer/...`, is no service's): what to tell a client that asked for another site."""
    found = set()
    for reply in session.liveliness().get("roadside/*/alive/**", timeout=timeout_s):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) > 3 and parts[3] in SERVICES:
                found.add(parts[1])
    return found
