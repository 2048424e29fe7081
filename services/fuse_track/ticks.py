"""Event-time ticks with a bounded watermark (no transport here).

Cameras are not synchronized and playback may run faster than real time, so batches are grouped by
their capture time: tick k holds the batches with k * tick <= t_capture < (k + 1) * tick, and its
reference time is the tick's centre (every capture time in it is within tick/2 of it). Ticks close
in order, a tick as soon as one of these holds:

- `complete`: every live camera has delivered a batch captured at or after the tick's end, or its
  last batch is so close to the end that its next frame (at the camera's own measured frame period,
  less a margin of three times its jitter) will fall in a later tick: no wait when everyone is on
  time, not even for the next frame;
- `watermark`: the newest capture time seen from any camera is past the tick's end + watermark_ms
  (a late or silent camera is not waited for in event time);
- `max_wait`: max_wait_ms of wall time have passed since the tick (or a later one) got its first
  batch (nothing else arrives: the other cameras are dead, or the stream has stopped).

A camera is live (waited for) while a batch of it was used within camera_timeout_ms of wall time (cameras
that never delivered: since the buffer's first batch): accepted, or late only because its tick closed without
waiting for it (the newest capture time not yet past that tick's end + watermark_ms, so the tick would have waited
for it). A silent camera stops being waited for, and so does a camera whose every batch is refused (a clock far
off, or behind by more than the watermark: it would otherwise hold every tick until the watermark or max_wait);
either is waited for again as soon as a batch of it is used. A batch for a tick already closed is late: counted and
dropped.

Clock jumps. A batch captured more than max_lead_ms away from the reference time (the newest capture time of the
other live cameras not themselves in doubt, i.e. whose last batch was not a jump; with none, its own camera's
newest) is a jump: counted (`ahead` forwards,
`late` backwards) and dropped, and its time remembered as the camera's pending clock, without touching the
camera's newest time or the watermark: one glitched time neither closes every tick nor makes a camera's next
batches late. A jump is followed once it is confirmed: by another live camera whose pending clock is within
max_lead_ms of it (several cameras' clocks jumped together), or, with no other camera to compare with, by a second
batch of the same camera within max_lead_ms after its pending time. A confirmed step back starts the buffer again: the
open ticks are closed ("flush") and returned first by the next pop_ready, every camera's history is cleared and
`restarts` counts it (the tracker downstream must start again too: its time would go back).
Ticks in which no camera delivered are emitted too (empty), so that tracks age; after a gap of
more than max_empty_ticks only the last max_empty_ticks of it are emitted. Wall time `now_s` is
always passed in (monotonic seconds), so tests are deterministic.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")
CLOSE_REASONS = ("complete", "watermark", "max_wait", "flush")
PERIOD_HISTORY = 15  # capture-time steps kept per camera to estimate its frame period
MIN_MARGIN_NS = 5_000_000  # the least margin before a camera's next expected frame


@dataclass(frozen=True)
class TickConfig:
    """tick_ms: tick length (event time); watermark_ms: how far event time may run past a tick's end
    before it closes without the late cameras; max_wait_ms: wall time a tick waits at most after its
    first batch; camera_timeout_ms: wall time without a batch after which a camera is not waited for;
    max_empty_ticks: the most empty ticks emitted for one gap in the stream; max_lead_ms: how far a batch's
    capture time may run ahead of every other live camera's newest before it is dropped as ahead;
    max_per_camera: the most batches one camera may put in one tick (more are dropped as `full`: a camera
    flooding one capture time would otherwise grow a tick without bound)."""

    tick_ms: float = 100.0
    watermark_ms: float = 150.0
    max_wait_ms: float = 300.0
    camera_timeout_ms: float = 1000.0
    max_empty_ticks: int = 50
    max_lead_ms: float = 60000.0  # above the event time a live camera's 1 s of silence spans at playback speeds
    max_per_camera: int = 16  # a 10 Hz camera puts one batch in a 100 ms tick

    def __post_init__(self) -> None:
        for name in ("tick_ms", "max_wait_ms", "camera_timeout_ms", "max_lead_ms"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not (isinstance(self.watermark_ms, int | float) and math.isfinite(self.watermark_ms)
                and self.watermark_ms >= 0):
            raise ValueError(f"watermark_ms must be a finite number >= 0, got {self.watermark_ms!r}")
        for name in ("max_empty_ticks", "max_per_camera"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {getattr(self, name)!r}")
        if round(self.tick_ms * 1e6) < 1:
            raise ValueError(f"tick_ms must be at least 1 ns, got {self.tick_ms!r}")


@dataclass
class Tick(Generic[T]):
    """A closed tick: [start_ns, end_ns) of capture time, its reference time t_ref_ns (the centre),
    and per camera the (t_capture_ns, item) pairs it got, in arrival order. closed_by: one of
    CLOSE_REASONS."""

    index: int
    start_ns: int
    end_ns: int
    t_ref_ns: int
    batches: dict[str, list[tuple[int, T]]] = field(default_factory=dict)
    closed_by: str = ""

    @property
    def empty(self) -> bool:
        return not self.batches

    def items(self) -> list[T]:
        """Every item of the tick, camera by camera (in order of first arrival), in arrival order."""
        return [item for pairs in self.batches.values() for _, item in pairs]


class TickBuffer(Generic[T]):
    """Groups per-camera batches into event-time ticks; see the module docstring.

    cameras: the cameras expected (others that deliver are added). Counters: `late`, `ahead` and `full` batches
    dropped, `restarts` after a clock's step back, `emitted` ticks, `empty` ticks, `closed_by` per reason;
    `refusal`: why the last batch refused was.
    """

    def __init__(self, cameras: Iterable[str], config: TickConfig | None = None) -> None:
        self.config = config or TickConfig()
        self._tick_ns = round(self.config.tick_ms * 1e6)
        self._watermark_ns = round(self.config.watermark_ms * 1e6)
        self._lead_ns = round(self.config.max_lead_ms * 1e6)
        self._last_seen_s: dict[str, float | None] = {}  # a camera's last batch, refused or not
        self._last_used_s: dict[str, float] = {}  # a camera's last batch that makes it live (module docstring)
        for camera in cameras:
            self._check_camera(camera)
            self._last_seen_s[camera] = None
        self._newest_ns: dict[str, int] = {}
        self._pending_ns: dict[str, int] = {}  # a camera's last refused jump (module docstring)
        self._ready: list[Tick[T]] = []  # ticks closed by a restart, handed out by the next pop_ready
        self._periods_ns: dict[str, list[int]] = {}  # recent capture-time steps per camera
        self._open: dict[int, Tick[T]] = {}
        self._first_s: dict[int, float] = {}  # wall time of each open tick's first batch
        self._next: int | None = None  # every tick below it is closed
        self._max_ns: int | None = None
        self._start_s: float | None = None
        self.late = 0
        self.ahead = 0
        self.full = 0
        self.restarts = 0
        self.refusal = ""
        self.emitted = 0
        self.empty = 0
        self.closed_by = dict.fromkeys(CLOSE_REASONS, 0)

    @property
    def cameras(self) -> list[str]:
        return list(self._last_seen_s)

    @staticmethod
    def _check_camera(camera: object) -> None:
        if not isinstance(camera, str) or not camera:
            raise ValueError(f"camera must be a non-empty string, got {camera!r}")

    @staticmethod
    def _check_now(now_s: float) -> float:
        if isinstance(now_s, bool) or not isinstance(now_s, numbers.Real) or not math.isfinite(now_s):
            raise ValueError(f"now_s must be a finite number of seconds, got {now_s!r}")
        return float(now_s)

    def live(self, now_s: float) -> list[str]:
        """The cameras still waited for at wall time now_s: a batch used within camera_timeout_ms (module docstring)."""
        return self._within_timeout(self._last_used_s, now_s)

    def _within_timeout(self, last_s: Mapping[str, float | None], now_s: float) -> list[str]:
        """The cameras whose time in last_s (none: the buffer's first batch) is within camera_timeout_ms of now_s."""
        timeout_s = self.config.camera_timeout_ms / 1e3
        out = []
        for camera in self._last_seen_s:
            seen = last_s.get(camera)
            since = seen if seen is not None else self._start_s
            if since is None or now_s - since <= timeout_s:
                out.append(camera)
        return out

    def add(self, camera: str, t_capture_ns: int, item: T, now_s: float) -> bool:
        """One camera's batch captured at t_capture_ns (ns), arriving at wall time now_s (s).
        Returns False when it is late (its tick has closed), ahead or behind (module docstring) or its tick holds
        max_per_camera of the camera's batches already: it is counted and dropped, and `refusal` says which."""
        self._check_camera(camera)
        if isinstance(t_capture_ns, bool) or not isinstance(t_capture_ns, numbers.Integral) or t_capture_ns < 0:
            raise ValueError(f"t_capture_ns must be an integer >= 0 (ns), got {t_capture_ns!r}")
        t_capture_ns = int(t_capture_ns)
        now_s = self._check_now(now_s)
        if self._start_s is None:
            self._start_s = now_s
        # the cameras delivering, refused or not: the reference, and the pending clocks that confirm a jump
        live = [c for c in self._within_timeout(self._last_seen_s, now_s) if c != camera]
        # a camera in doubt (its last batch a jump) is no reference: its newest time may be long past
        others = [self._newest_ns[c] for c in live if c in self._newest_ns and c not in self._pending_ns]
        self._last_seen_s[camera] = now_s
        ref = max(others) if others else self._newest_ns.get(camera)
        if ref is not None and abs(t_capture_ns - ref) > self._lead_ns:
            if not self._confirmed(camera, t_capture_ns, live, bool(others)):
                self._pending_ns[camera] = t_capture_ns
                forward = t_capture_ns > ref
                self.ahead += forward
                self.late += not forward
                whose = "of the other cameras" if others else "so far"
                self.refusal = (f"{'ahead' if forward else 'behind'}: captured {abs(t_capture_ns - ref) / 1e9:.3f} s "
                                f"{'after' if forward else 'before'} the newest {whose} "
                                f"(a clock jump? followed once another frame confirms it)")
                return False
            if t_capture_ns < ref:
                self._restart()
        self._pending_ns.pop(camera, None)
        prev = self._newest_ns.get(camera)
        if prev is not None and t_capture_ns > prev:
            steps = self._periods_ns.setdefault(camera, [])
            steps.append(t_capture_ns - prev)
            del steps[:-PERIOD_HISTORY]
        self._newest_ns[camera] = max(prev if prev is not None else t_capture_ns, t_capture_ns)
        self._max_ns = t_capture_ns if self._max_ns is None else max(self._max_ns, t_capture_ns)
        k = t_capture_ns // self._tick_ns
        if self._next is not None and k < self._next:
            self.late += 1
            self.refusal = "late: its tick has closed"
            if self._max_ns <= (k + 1) * self._tick_ns + self._watermark_ns:
                self._last_used_s[camera] = now_s  # its tick would have waited for it: live again
            return False
        tick = self._open.get(k)
        if tick is not None and len(tick.batches.get(camera, ())) >= self.config.max_per_camera:
            self.full += 1
            self.refusal = f"full: {camera} has {self.config.max_per_camera} batches in this tick already"
            return False
        if tick is None:
            start = k * self._tick_ns
            tick = self._open[k] = Tick(k, start, start + self._tick_ns, start + self._tick_ns // 2)
            self._first_s[k] = now_s
        tick.batches.setdefault(camera, []).append((t_capture_ns, item))
        self._last_used_s[camera] = now_s
        return True

    def pop_ready(self, now_s: float) -> list[Tick[T]]:
        """The ticks that can close at wall time now_s, oldest first (empty ticks included)."""
        now_s = self._check_now(now_s)
        out, self._ready = self._ready, []
        while self._open:
            k = self._head()
            reason = self._close_reason(k, now_s)
            if reason is None:
                break
            out.append(self._close(k, reason))
        return out

    def flush(self) -> list[Tick[T]]:
        """Close every open tick (end of stream), oldest first (after those a restart closed)."""
        out, self._ready = self._ready, []
        while self._open:
            out.append(self._close(self._head(), "flush"))
        return out

    def _confirmed(self, camera: str, t_ns: int, live: list[str], others: bool) -> bool:
        """Whether a jump to t_ns is confirmed (module docstring): by another live camera's pending clock, or, with
        other camera to compare with, by this camera's own pending time a little before it."""
        if any(abs(t_ns - self._pending_ns[c]) <= self._lead_ns for c in live if c in self._pending_ns):
            return True
        mine = self._pending_ns.get(camera)
        return not others and mine is not None and 0 <= t_ns - mine <= self._lead_ns

    def _restart(self) -> None:
        """A confirmed step back of the clock: the open ticks closed for the next pop_ready, the history cleared."""
        self._ready = self.flush()
        self._newest_ns.clear()
        self._pending_ns.clear()
        self._periods_ns.clear()
        self._next = self._max_ns = None
        self.restarts += 1

    def _head(self) -> int:
        """The oldest tick not closed yet; skips all but max_empty_ticks of a gap before the first open tick."""
        first = min(self._open)
        if self._next is None:
            return first
        self._next = max(self._next, first - self.config.max_empty_ticks)
        return self._next

    def next_frame_ns(self, camera: str) -> int | None:
        """The earliest capture time expected for the camera's next frame: its newest capture time plus
        its median frame period less three times the spread of its periods (None until 3 are seen)."""
        steps = self._periods_ns.get(camera, [])
        if len(steps) < 3 or camera not in self._newest_ns:
            return None
        period = sorted(steps)[len(steps) // 2]
        spread = sorted(abs(s - period) for s in steps)[len(steps) // 2]
        margin = min(max(3 * spread, MIN_MARGIN_NS), period // 2)
        return self._newest_ns[camera] + period - margin

    def _close_reason(self, k: int, now_s: float) -> str | None:
        end = (k + 1) * self._tick_ns
        live = self.live(now_s)

        def done(c: str) -> bool:
            if self._newest_ns.get(c, -1) >= end:
                return True
            nxt = self.next_frame_ns(c)
            return nxt is not None and nxt >= end and self._newest_ns[c] >= k * self._tick_ns

        if all(done(c) for c in live):
            return "complete"
        if self._max_ns is not None and self._max_ns > end + self._watermark_ns:
            return "watermark"
        first_s = min(self._first_s.values())  # every open tick is at or after k
        if (now_s - first_s) * 1e3 >= self.config.max_wait_ms:
            return "max_wait"
        return None

    def _close(self, k: int, reason: str) -> Tick[T]:
        tick = self._open.pop(k, None)
        self._first_s.pop(k, None)
        if tick is None:
            start = k * self._tick_ns
            tick = Tick(k, start, start + self._tick_ns, start + self._tick_ns // 2)
            self.empty += 1
        tick.closed_by = reason
        self._next = k + 1
        self.emitted += 1
        self.closed_by[reason] += 1
        return tick
