"""A tracks recording played back onto the bus (`roadside play`): fuse_track's output without the pipeline.

A vehicle developer, or a researcher with a recorded session, needs the cabinet's tracks on the bus to run a
subscriber against, and not the four services, their models and the cameras' footage. `play` reads the JSON lines
fuse_track's recorder wrote (one Tracks message per line: `Tracks.from_record`; rotated files one after the other)
and publishes each message on `roadside/<site>/tracks` at its recorded pace (its capture times, 1 = real time, N
times as fast, or `max`), answering `roadside/<site>/tracks/latest` with the newest one published (when it was
published within the last LATEST_MAX_AGE_S) and holding a liveliness token `roadside/<site>/alive/fuse_track/playback`
and reporting its Status as fuse_track's instance `playback` (`roadside status`, `roadside health --service
fuse_track`), as fuse_track does: every subscriber (`roadside tracks`, `shared.client.TrackClient`, the standalone
listener of docs/wire-format.md, `roadside viz --live`) reads it as it reads a cabinet. The site is the first
record's; in the embedded default the player listens where fuse_track would (`bus.port_base` + 3), so it stands in
for it.

A line that does not parse, or breaks the contract, or names another site, is counted, logged once per reason with
its file and line, and skipped. With `loop` the files start again when they end, each pass's capture times moved
on by the recording's span plus one message interval and its sequence numbers by the largest plus one, so a
subscriber sees time and `seq` go on increasing; each pass after the first is paced from the last message published,
its first message one interval after it. A capture time that goes back within a recording (fuse_track restarted with
a new tracker after a clock step) is published at once and the pace counts from it.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from shared.bus import BadInput, declare_alive
from shared.codec import encode
from shared.keys import LATEST_ANY_AGE, latest_tracks_key, tracks_key
from shared.messages import Tracks
from shared.status import StatusReporter
from shared.tracks_file import file_lines

log = logging.getLogger("roadside.play")
DEFAULT_GAP_NS = 100_000_000  # a loop's step from the last message to the first of the next pass, if one message
TOKEN = "playback"  # the liveliness token's instance: roadside/<site>/alive/fuse_track/playback
MAX_LINE_BYTES = 64 * 1024 * 1024  # a longer line is not a Tracks message (4096 tracks of ~500 bytes is 2 MB)
# the latest-tracks query is answered with a message published at most this long ago (monotonic clock; fuse_track's
# too), or twice the time between the last two messages where that is longer (a playback slowed down, `--pace 0.05`):
# longer than the longest tick (1 s) and its wait; with every camera down, or a playback paused, nothing is sent and an
# older message is not "the current tracks" (docs/wire-format.md). A query with the parameter LATEST_ANY_AGE (a
# restarted ingest asking where fuse_track's tracks reached, services/ingest resume_point) is answered whatever its age.
LATEST_MAX_AGE_S = 2.0


def held_latest(latest: list[tuple[float, float, bytes]], payload: bytes) -> None:
    """Keep `payload` as the newest message published (in `latest`, fuse_track's and the player's: [(monotonic time
    it was published, seconds since the one before, payload)])."""
    now = time.monotonic()
    latest[:] = [(now, now - latest[-1][0] if latest else 0.0, payload)]


def current_payload(latest: list[tuple[float, float, bytes]], query=None) -> bytes | None:
    """The payload to answer the latest-tracks query with: the newest of `latest` (`held_latest`) when it was published
    within LATEST_MAX_AGE_S (or twice the gap before it, where longer), or whatever its age for a query with the
    parameter LATEST_ANY_AGE; else None."""
    held = latest[-1] if latest else None  # one read: the publishing thread replaces the entry meanwhile
    if held is None:
        return None
    if query is not None and query.parameters.get(LATEST_ANY_AGE) is not None:
        return held[2]
    if time.monotonic() - held[0] > max(LATEST_MAX_AGE_S, 2 * held[1]):
        return None
    return held[2]


def records(paths: Iterable[Path], bad: Callable[[str, str], None]) -> Iterator[tuple[str, Tracks]]:
    """(file:line, message) of the files' lines, in order; each bad line counted by `bad(reason, file:line)`.
    ValueError for a file that cannot be opened."""
    for path in paths:
        for where, line in file_lines(path):
            if len(line) > MAX_LINE_BYTES:
                bad(f"a line of {len(line)} characters, more than a Tracks message holds", where)
                continue
            try:
                msg = Tracks.from_record(json.loads(line))
            except json.JSONDecodeError as exc:
                bad(f"not JSON ({exc.msg})", where)
            except (ValueError, RecursionError) as exc:  # pydantic's ValidationError is a ValueError
                bad(" ".join(str(exc).split())[:300] or type(exc).__name__, where)
            else:
                yield where, msg


@dataclass
class Played:
    """What a playback did: messages published, passes over the files, bad lines (each counted once), the site."""

    published: int = 0
    passes: int = 0
    bad: int = 0
    site: str | None = None
    first_ns: int | None = None
    last_ns: int | None = None


def play(paths: list[Path], publish: Callable[[Tracks], None], speed: float | None, loop: bool,
         stopped: Callable[[float], bool], bad: BadInput) -> Played:
    """Publish the files' messages at `speed` x their capture times' pace (None: as fast as `publish` takes them),
    over again with `loop`, until they end or `stopped(wait_s)` (waits up to wait_s, True once asked to stop).
    Bad lines are counted in `bad` on the first pass. ValueError when a pass publishes nothing (no file holds a good
    line)."""
    out = Played()
    shift_ns = shift_seq = 0
    clock: tuple[int, float] | None = None  # (capture time, monotonic time) that the pace counts from
    prev: int | None = None  # the capture time of the message published last
    published_s = 0.0  # the monotonic time it was published at
    step_ns = 0  # a loop's step from the last pass's newest time to the next pass's first
    while True:
        first = newest = None
        max_seq, gap_ns = -1, 0
        count = bad if out.passes == 0 else (lambda reason, where: None)
        for where, msg in records(paths, count):
            if out.site is None:
                out.site = msg.site
            elif msg.site != out.site:
                count(f"site {msg.site!r}, not the recording's {out.site!r}", where)
                continue
            msg.t_capture_ns += shift_ns
            msg.seq += shift_seq
            t = msg.t_capture_ns
            if first is not None and t > prev:  # an interval of this pass (not the step from the last one)
                gap_ns = t - prev
            if first is None and out.passes:  # a new pass: one interval after the last message published (the pace
                clock = (t - step_ns, published_s)  # before counts from the last step back, which may be long past)
            if clock is None or speed is None or (prev is not None and t < prev):  # the clock stepped back
                clock = (t, time.monotonic())
            else:
                wait_s = clock[1] + (t - clock[0]) / 1e9 / speed - time.monotonic()
                if wait_s > 0 and stopped(wait_s):
                    return _done(out, bad)
            if stopped(0):
                return _done(out, bad)
            publish(msg)
            prev, published_s = t, time.monotonic()
            out.published += 1
            out.first_ns = t if out.first_ns is None else out.first_ns
            out.last_ns = t
            first = t if first is None else first
            newest = t if newest is None else max(newest, t)
            max_seq = max(max_seq, msg.seq)
        if first is None:
            raise ValueError(f"no tracks message in {', '.join(map(str, paths))} ({bad.total} bad lines)")
        out.passes += 1
        if not loop:
            return _done(out, bad)
        # the next pass starts one interval after the newest time sent (the span, with any step back in it)
        step_ns = gap_ns or DEFAULT_GAP_NS
        shift_ns += newest - first + step_ns
        shift_seq = max_seq + 1


def _done(out: Played, bad: BadInput) -> Played:
    out.bad = bad.total
    return out


class TracksPublisher:
    """fuse_track's side of the bus: each message on its site's tracks key, and the newest one for subscribers that
    join late (declared for the first message's site, on its arrival). `block`: wait for a slow subscriber rather
    than drop (as fast as the player can go, nothing is lost)."""

    def __init__(self, session, block: bool = False, status_period_s: float = 2.0) -> None:
        self.session, self.block, self.status_period_s = session, block, status_period_s
        self.latest: list[tuple[float, float, bytes]] = []  # the newest payload, as held_latest keeps it
        self.pub = self.queryable = self.status = None
        self.tokens: list = []

    def _declare(self, site: str) -> None:
        import zenoh

        congestion = zenoh.CongestionControl.BLOCK if self.block else zenoh.CongestionControl.DROP
        self.pub = self.session.declare_publisher(tracks_key(site), congestion_control=congestion)

        def answer(query) -> None:  # Zenoh's thread: bytes already encoded
            payload = current_payload(self.latest, query)
            if payload is not None:
                query.reply(latest_tracks_key(site), payload)

        self.queryable = self.session.declare_queryable(latest_tracks_key(site), answer)
        # a Status report as fuse_track's (its instance "playback"): `roadside status` and `health` see the player
        self.status = StatusReporter(self.session, site, "fuse_track", BadInput("play"), self.status_period_s,
                                     instance=TOKEN)
        self.tokens = declare_alive(self.session, site, "fuse_track", [TOKEN])

    def __call__(self, msg: Tracks) -> None:
        if self.pub is None:
            self._declare(msg.site)
        msg.stamps = [("playback", time.time_ns())]  # when it was sent (the recording keeps no stamps)
        payload = encode(msg)
        held_latest(self.latest, payload)
        self.pub.put(payload)
        self.status.count("tracks_out", output=True)

    def close(self) -> None:
        if self.status is not None:
            self.status.close()
        for entity in (*self.tokens, self.queryable, self.pub):
            if entity is not None:
                entity.undeclare()
