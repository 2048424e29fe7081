"""A vehicle's view of the bus: subscribe to a site's live tracks.

    from shared.client import TrackClient
    from shared.messages import err95_m

    with TrackClient("state_ellsworth", connect=["tcp/192.168.1.10:7447"]) as client:
        for tracks in client.stream():          # shared.messages.Tracks: the current ones, then the newest
            for row in tracks.rows():           # id, x, y, lat, lon, vx, vy, yaw, length, ..., cameras, xy_cov
                print(row["id"], row["lat"], row["lon"], row["type"])
            worst = err95_m(tracks.xy_cov)      # (N,) m: each position's 95 % error ellipse, longest half-axis
            axis_only = ~tracks.yaw_confirmed   # (N,) bool: not seen travelling, the heading may point backwards
            heading_sd = tracks.yaw_std         # (N,) rad: 1 sigma of the heading's error on its axis
            now = tracks.predicted(time.time_ns())  # moved on from the capture to now (a clock the cabinet shares)

Positions are where the vehicles were when the images were taken; by the time a vehicle uses them they have moved
on (a metre in 70 ms at 50 km/h): `Tracks.predicted(t_ns)` moves them to t_ns at their velocities and grows their
uncertainty to match (docs/wire-format.md, "Where a vehicle is now").

A client that joins late gets the current tracks at once: `stream()` first asks fuse_track's
queryable (`roadside/<site>/tracks/latest`) for the newest message, then follows the live ones. A loop slower than
the cabinet's tick (10 Hz) does not fall behind: `stream()` gives the newest of the messages that came while the
loop was busy and counts the older ones in `client.skipped`; a tool that needs every message (a recorder, counts)
asks for them with `stream(latest=False)`.
`connect` is the cabinet's Zenoh router (or, on the embedded default, any service's loopback port); without it, the
router of a `bus` in client mode (a site's settings at the cabinet), else fuse_track's port of the bus; over TLS
(`tls/HOST:7448`) give the cabinet's CA certificate as `bus=BusSettings(tls_root_ca=...)`, and the client refuses a
router whose certificate does not chain to it; a cabinet that lets only enrolled vehicles in (mutual TLS) also
wants the vehicle's own certificate and key, `BusSettings(tls_certificate=..., tls_private_key=...)`.
Bad messages are counted in `client.bad` and skipped. A vehicle written in another language reads the same
messages with its own Zenoh and msgpack libraries: docs/wire-format.md (and examples/vehicle_listener.py).

A vehicle is not always in reach of the cabinet: the client waits up to `wait_s` (None: as long as it takes) for
the first connection, raising ConnectionError naming the endpoints when none answers, and after a dropped link
reconnects by itself (tried every 0.25 s at first, then every 2 s at most); `stream()` goes on with the tracks of
after the gap (a `timeout_s` given to it ends it when the gap is longer).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Iterator

import zenoh

from shared.bus import BadInput, Receiver, bus_sites, set_tls
from shared.codec import DecodeError, decode
from shared.keys import latest_tracks_key, tracks_key
from shared.messages import Tracks
from shared.settings import BusSettings, check_endpoint
from shared.tracks_file import REPLAYED_NS

MAX_WAIT_S = 7 * 86400.0  # a longer wait is None: Zenoh's timeout is in milliseconds
RECONNECT = {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2}  # Zenoh's connect/retry


class TrackClient:
    def __init__(self, site: str, connect: list[str] | None = None, bus: BusSettings | None = None,
                 wait_s: float | None = 10.0) -> None:
        if wait_s is not None and not (wait_s > 0 and math.isfinite(wait_s)):
            raise ValueError(f"wait_s must be a finite number of seconds > 0 or None (no limit), got {wait_s!r}")
        if wait_s is not None and wait_s > MAX_WAIT_S:
            raise ValueError(f"wait_s must be at most {MAX_WAIT_S:.0f} s (None: no limit), got {wait_s!r}")
        bus = bus or BusSettings()
        if not connect:
            connect = bus.connect if bus.mode == "client" else [bus.service_endpoint("fuse_track")]
        endpoints = [check_endpoint(e) for e in connect]
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        conf.insert_json5("connect/timeout_ms", json.dumps(-1 if wait_s is None else max(1, round(wait_s * 1000))))
        conf.insert_json5("connect/retry", json.dumps(RECONNECT))
        conf.insert_json5("scouting/multicast/enabled", "false")
        set_tls(conf, bus)
        self.site = site
        self.bad = BadInput("tracks-client")
        self.skipped = 0  # messages stream() passed over for a newer one (the caller's loop was slower than them)
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise ConnectionError(f"no answer from {', '.join(endpoints)} within {wait_s} s: is the cabinet's "
                                  f"router (or the local fuse_track) up and in reach? ({exc})") from None
        self.receiver = Receiver(self.session, tracks_key(site), Tracks, self.bad)

    def latest(self, timeout_s: float = 2.0) -> Tracks | None:
        """The newest Tracks message fuse_track holds (None when none answers)."""
        for reply in self.session.get(latest_tracks_key(self.site), timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                msg = decode(reply.ok.payload.to_bytes(), Tracks)
            except DecodeError as exc:
                self.bad(str(exc), "latest")
                continue
            return msg  # type: ignore[return-value]
        return None

    def sites(self, timeout_s: float = 1.0) -> set[str]:
        """The sites whose services are on this bus (their liveliness tokens, `roadside/<site>/alive/...`): what
        to tell a client that asked for a site none of them is."""
        return bus_sites(self.session, timeout_s)

    def stream(self, timeout_s: float | None = None, poll_s: float = 0.1,
               stop: threading.Event | None = None, current: Tracks | object | None = ...,
               latest: bool = True) -> Iterator[Tracks]:
        """The current tracks at once, then the new messages; stops after `timeout_s` without one, or within
        `poll_s` of `stop` being set (e.g. by a signal handler: the caller's loop then ends normally).
        `latest`: of the messages that arrived while the caller was busy with the last one, only the newest is
        given and the others are counted in `self.skipped` (a vehicle's loop slower than the tick would otherwise
        fall further and further behind, its tracks too old for `Tracks.predicted` to move on to now); False: every
        message, in order (a recorder, counts, a viewer's timeline).
        Messages of the same tracker not newer than the last one given (queued when the current one was asked
        for, duplicates, out of order) are skipped; a restarted fuse_track (another tracker id, seq from 0) is
        followed at once, and so is a recording played again (`roadside play`: the same tracker, its seq and
        capture time back to their start, more than REPLAYED_NS before the last message given).
        `timeout_s` counts from the last message received, skipped ones too. `current`: the answer of a `latest()`
        the caller already asked (None: none came), instead of asking again."""
        last: tuple[str, int, int] | None = None  # tracker, seq, capture time of the last message given
        if current is ...:
            current = self.latest()
        if current is not None:
            last = (current.tracker, current.seq, current.t_capture_ns)
            yield current
        quiet_since = time.monotonic()
        while stop is None or not stop.is_set():
            received = self.receiver.poll()
            fresh = []  # the new ones, in the order they came
            for msg in received:
                if (last is not None and msg.tracker == last[0] and msg.seq <= last[1]
                        and msg.t_capture_ns >= last[2] - REPLAYED_NS):
                    continue  # a duplicate or one older than what the caller already has
                last = (msg.tracker, msg.seq, msg.t_capture_ns)
                fresh.append(msg)
            if latest and len(fresh) > 1:
                self.skipped += len(fresh) - 1
                fresh = fresh[-1:]
            yield from fresh  # type: ignore[misc]
            if received:
                quiet_since = time.monotonic()
            elif timeout_s is not None and time.monotonic() - quiet_since > timeout_s:
                return
            self.receiver.wait(poll_s)  # sleeps until a message arrives (or poll_s)

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> TrackClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
