"""Turning-movement counts from tracks (`roadside counts`): how many vehicles went from which leg of the junction
to which, per time bin, as a traffic engineer counts them.

A site's junction (`movements:` in site.yaml, `MovementSettings`) is its centre (latitude, longitude), the compass
bearing of each leg from the centre, and two radii: inside `inner_radius_m` a vehicle is in the junction (the
roundabout's ring or the intersection's box); between it and `outer_radius_m` it is on the leg whose bearing is
nearest, within `half_width_deg` (else on none). Each track (its id within its tracker: fuse_track keeps the id of
a vehicle it lost and found again, `relink_s`) is a sequence of positions; its movement is

- entry: the leg it was last on before it first entered the junction; exit: the leg it was first on after it last
  left it; its time: when it first entered;
- complete when both are known; a vehicle first seen inside the junction has no entry, one last seen there (or
  still there when the recording ends) no exit, and each of those counts in its leg's `entered_only` or
  `exited_only`; a track that never enters the junction (a parked car, a vehicle that turned off before it, a
  false track) is no movement.

The legs before its first entry and after its last exit are what count, so a track that grazes a leg's mouth while
in the ring, or whose position jitters across the inner radius, is counted once. Positions come from the tracks'
latitude and longitude, so a tracks file counts the same whatever site frame its tracker had.
Counts are binned by the movement's time in `bin_s` bins aligned to the clock (UTC: 900 s, the traffic
engineer's 15 minutes, starts at :00, :15, :30, :45).

Each complete movement is also a turn (`Junction.turn`), from the legs' bearings: the angle from the direction the
vehicle came in on (its entry leg's bearing turned round) to the one it left on (its exit leg's), "T" (through)
within 45 degrees of straight on, "R" clockwise beyond it, "L" anticlockwise, "U" back out on the leg it came in on.
A bin also says how much of it the tracks covered (`observed_s`): the time between consecutive Tracks messages (empty
ones too: fuse_track publishes one a tick) no more than COVER_GAP_S apart. A bin of a cabinet that was down for
part of it, or at the start or end of a recording, covers less than its length: its counts are a part of the
traffic, not all of it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared.geo import GeoFrame
from shared.tracks_file import file_lines

INSIDE = -2  # zone codes beside the legs' indices
NOWHERE = -1
MIN_BIN_S, MAX_BIN_S = 1.0, 7 * 86400.0  # the counts' bins: from a second (times print in whole seconds) to a week
COVER_GAP_S = 2.0  # Tracks messages further apart than this leave the time between them uncovered
TURNS = ("U", "L", "T", "R")
THROUGH_DEG = 45.0  # a turn within this of straight on is through
CSV_HEADER = ("start", "end", "observed_s", "from", "to", "turn", "vehicles")


@dataclass(frozen=True)
class Junction:
    """The junction's centre (degrees), its legs (name, bearing in degrees from north, clockwise), and its radii (m)
    and legs' half-width (degrees); see the module doc."""

    lat_deg: float
    lon_deg: float
    legs: tuple[tuple[str, float], ...]
    inner_radius_m: float
    outer_radius_m: float
    half_width_deg: float = 35.0

    def __post_init__(self) -> None:
        GeoFrame(self.lat_deg, self.lon_deg)  # checks the centre
        if not 0 < self.inner_radius_m < self.outer_radius_m or not math.isfinite(self.outer_radius_m):
            raise ValueError(f"junction radii must be 0 < inner < outer, got {self.inner_radius_m} and "
                             f"{self.outer_radius_m} m")
        if not 0 < self.half_width_deg <= 90:
            raise ValueError(f"half_width_deg must be in (0, 90], got {self.half_width_deg}")
        if len(self.legs) < 2:
            raise ValueError(f"a junction needs at least two legs, got {len(self.legs)}")
        names = [n for n, _ in self.legs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate leg names in {names}")
        for i, (a, ba) in enumerate(self.legs):
            if not math.isfinite(ba):
                raise ValueError(f"leg {a}: bearing must be finite, got {ba}")
            for b, bb in self.legs[i + 1:]:
                gap = abs((ba - bb + 180.0) % 360.0 - 180.0)
                if gap < 2 * self.half_width_deg:
                    raise ValueError(f"legs {a} and {b} are {gap:g} deg apart, less than twice half_width_deg "
                                     f"({self.half_width_deg:g}): a position between them would be on both")

    @property
    def names(self) -> list[str]:
        return [n for n, _ in self.legs]

    def turn(self, entry: str, exit_: str) -> str:
        """The turn ("U", "L", "T" or "R") of a vehicle in on leg `entry` and out on leg `exit_` (module doc)."""
        bearing = dict(self.legs)
        if entry == exit_:
            return "U"
        angle = (bearing[exit_] - bearing[entry]) % 360.0 - 180.0  # from the way it came in (entry's + 180)
        return "T" if abs(angle) <= THROUGH_DEG else "R" if angle > 0 else "L"

    def zones(self, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
        """(N,) int: the leg index of each position, INSIDE the junction, or NOWHERE."""
        en = GeoFrame(self.lat_deg, self.lon_deg).to_enu(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
        r = np.hypot(en[:, 0], en[:, 1])
        bearing = np.degrees(np.arctan2(en[:, 0], en[:, 1]))  # from north, clockwise
        legs = np.array([b for _, b in self.legs], float)
        off = np.abs((bearing[:, None] - legs[None, :] + 180.0) % 360.0 - 180.0)
        nearest = np.argmin(off, axis=1) if len(r) else np.zeros(0, int)
        on_leg = (r >= self.inner_radius_m) & (r <= self.outer_radius_m) & (off[np.arange(len(r)), nearest]
                                                                            <= self.half_width_deg)
        return np.where(r < self.inner_radius_m, INSIDE, np.where(on_leg, nearest, NOWHERE))


@dataclass(frozen=True)
class Movement:
    """One vehicle's passage: its track, entry and exit leg (None: not seen), when it entered (ns)."""

    key: tuple[str, int]
    entry: str | None
    exit: str | None
    t_ns: int


def movement(key: tuple[str, int], t_ns: np.ndarray, zones: np.ndarray, names: Sequence[str]) -> Movement | None:
    """The movement of one trajectory (times in order, its zones; module doc), None if it never enters."""
    inside = np.flatnonzero(zones == INSIDE)
    if not inside.size:
        return None
    before, after = zones[: inside[0]], zones[inside[-1] + 1:]
    before, after = before[before >= 0], after[after >= 0]
    return Movement(key, names[before[-1]] if before.size else None, names[after[0]] if after.size else None,
                    int(t_ns[inside[0]]))


@dataclass
class Passage:
    """One track's movement so far, position by position (the live counterpart of `movement`: the same rule)."""

    key: tuple[str, int]
    entry: int | None = None  # the leg it was last on before entering (before it enters: the leg it is on)
    t_in: int | None = None  # when it first entered the junction (None: not yet)
    exit: int | None = None  # the first leg it was on after it last left the junction
    last_ns: int = 0  # when it was last seen

    def add(self, t_ns: int, zone: int) -> None:
        self.last_ns = t_ns
        if self.t_in is None:
            if zone >= 0:
                self.entry = zone
            elif zone == INSIDE:
                self.t_in = t_ns
        elif zone == INSIDE:
            self.exit = None  # in again: the exit is the first leg after the last time inside
        elif zone >= 0 and self.exit is None:
            self.exit = zone

    def movement(self, names: Sequence[str]) -> Movement | None:
        if self.t_in is None:
            return None
        return Movement(self.key, None if self.entry is None else names[self.entry],
                        None if self.exit is None else names[self.exit], self.t_in)


class LiveCounts:
    """Turning movements counted from live Tracks messages (`roadside counts --live`), and the time they covered (as
    `binned` counts it from a file's messages): each track's passage is followed position by position; a track unseen
    for `linger_s` of capture time is done, and its movement is counted in the bin of its entry. A bin is closed, and
    returned by `update` (empty too: nothing went through), once capture time is `close_after_s` past its end; a
    passage that entered in it and is still open then is counted as it stands (an exit not yet seen counts as entering
    only) and its track is not counted again. After a silence of more than MAX_EMPTY_BINS bins (or a clock set
    forward) only the bins with something in them are returned. Capture time going back by more than `close_after_s`
    (a clock step, a recording played again) counts what is open, returns every bin and starts again; a smaller step
    back (a restarted tracker's first tick) is taken as it comes."""

    MAX_EMPTY_BINS = 96  # a day of 15-minute bins

    def __init__(self, junction: Junction, bin_s: float = 900.0, linger_s: float = 10.0,
                 close_after_s: float = 120.0) -> None:
        binned([], bin_s)  # checks bin_s
        if not (0 < linger_s <= close_after_s and math.isfinite(close_after_s)):
            raise ValueError(f"need 0 < linger_s <= close_after_s (finite), got {linger_s} and {close_after_s}")
        self.junction, self.width = junction, round(bin_s * 1e9)
        self.linger, self.close_after = round(linger_s * 1e9), round(close_after_s * 1e9)
        self.gap = round(COVER_GAP_S * 1e9)
        self._reset()

    def _reset(self) -> None:
        self.open: dict[tuple[str, int], Passage] = {}
        self.done: dict[tuple[str, int], int] = {}  # tracks counted at a bin's close, still seen: when last seen
        self.bins: dict[int, Counts] = {}
        self.next_start: int | None = None  # the first bin not yet closed
        self.now: int | None = None  # the newest capture time seen

    def update(self, tracks) -> list[Counts]:
        """One Tracks message (shared.messages.Tracks) -> the bins it closes, in order."""
        t = int(tracks.t_capture_ns)
        out = self.flush() if self.now is not None and t < self.now - self.close_after else []
        if self.now is not None and 0 < t - self.now <= self.gap:  # covered since the newest message before
            cover(self.bins, self.width, self.now, t, self.next_start)
        self.now = t if self.now is None else max(self.now, t)
        if self.next_start is None:
            self.next_start = t // self.width * self.width
        if len(tracks):
            zones = self.junction.zones(tracks.latlon[:, 0], tracks.latlon[:, 1])
            for i, z in zip(tracks.id.tolist(), zones.tolist(), strict=True):
                key = (tracks.tracker, i)
                if key in self.done:
                    self.done[key] = max(self.done[key], t)
                else:
                    self.open.setdefault(key, Passage(key)).add(t, z)
        now = self.now
        for key in [k for k, p in self.open.items() if p.last_ns < now - self.linger]:
            self._count(self.open.pop(key))
        self.done = {k: last for k, last in self.done.items() if last >= now - self.linger}
        last = now - self.close_after - self.width  # the bins starting at or before it close
        if (last - self.next_start) // self.width > self.MAX_EMPTY_BINS:
            held = {*self.bins, *(p.t_in // self.width * self.width for p in self.open.values() if p.t_in is not None)}
            out += [self._close(b) for b in sorted(held) if self.next_start <= b <= last]
            self.next_start = last // self.width * self.width + self.width
        while self.next_start <= last:
            out.append(self._close(self.next_start))
        return out

    def _close(self, start: int) -> Counts:
        """Bin `start` closed (its open passages counted as they stand) and the next one the first open."""
        end = start + self.width
        for key in [k for k, p in self.open.items() if p.t_in is not None and p.t_in < end]:
            p = self.open.pop(key)
            self._count(p)
            self.done[key] = p.last_ns
        self.next_start = max(self.next_start, end)
        return self.bins.pop(start, None) or Counts(start, end)

    def flush(self) -> list[Counts]:
        """Every open passage counted as it stands and every bin with a movement returned (the stream ended, or
        its clock went back), in order; then it starts again."""
        for p in self.open.values():
            self._count(p)
        out = [self.bins[b] for b in sorted(self.bins)]
        self._reset()
        return out

    def _count(self, p: Passage) -> None:
        m = p.movement(self.junction.names)
        if m is not None and (m.entry is not None or m.exit is not None):  # seen only inside: on no leg
            start = max(m.t_ns // self.width * self.width, self.next_start or 0)  # never into a closed bin
            self.bins.setdefault(start, Counts(start, start + self.width)).add(m)


def movements(tracks: Iterable[tuple[tuple[str, int], int, float, float]], junction: Junction) -> list[Movement]:
    """The movements of tracks given as (key, t_ns, lat, lon) positions, in any order."""
    by_key: dict[tuple[str, int], list[tuple[int, float, float]]] = {}
    for key, t, lat, lon in tracks:
        by_key.setdefault(key, []).append((t, lat, lon))
    out = []
    for key, rows in by_key.items():
        rows.sort()
        t = np.array([r[0] for r in rows], np.int64)  # nanoseconds stay integers (a float64 rounds them by 128 ns)
        a = np.array([r[1:] for r in rows], float).reshape(-1, 2)
        m = movement(key, t, junction.zones(a[:, 0], a[:, 1]), junction.names)
        if m is not None:
            out.append(m)
    return sorted(out, key=lambda m: (m.t_ns, m.key))


@dataclass
class Counts:
    """Movements counted per bin: `complete[(entry, exit)]`, `entered_only[entry]`, `exited_only[exit]`, and how much
    of the bin the tracks covered (`observed_ns`, module doc)."""

    start_ns: int
    end_ns: int
    complete: dict[tuple[str, str], int] = field(default_factory=dict)
    entered_only: dict[str, int] = field(default_factory=dict)
    exited_only: dict[str, int] = field(default_factory=dict)
    observed_ns: int = 0

    def add(self, m: Movement) -> None:
        if m.entry is not None and m.exit is not None:
            self.complete[(m.entry, m.exit)] = self.complete.get((m.entry, m.exit), 0) + 1
        elif m.entry is not None:
            self.entered_only[m.entry] = self.entered_only.get(m.entry, 0) + 1
        elif m.exit is not None:
            self.exited_only[m.exit] = self.exited_only.get(m.exit, 0) + 1

    def to_json(self, junction: Junction) -> dict:
        """The bin as JSON: its times, how much of it was observed, the entry x exit matrix (rows entries, columns
        exits, the legs' order), each entry leg's turns, and the approach volumes (entering each leg: complete and
        entered-only; leaving it: complete and exited-only)."""
        legs = junction.names
        matrix = [[self.complete.get((a, b), 0) for b in legs] for a in legs]
        turns = {a: dict.fromkeys(TURNS, 0) for a in legs}
        for (a, b), n in self.complete.items():
            turns[a][junction.turn(a, b)] += n
        return {"start_ns": self.start_ns, "end_ns": self.end_ns, "observed_s": round(self.observed_ns / 1e9, 1),
                "legs": list(legs), "complete": matrix, "complete_total": sum(self.complete.values()), "turns": turns,
                "entered_only": {leg: self.entered_only.get(leg, 0) for leg in legs},
                "exited_only": {leg: self.exited_only.get(leg, 0) for leg in legs},
                "entering": {leg: sum(matrix[i]) + self.entered_only.get(leg, 0) for i, leg in enumerate(legs)},
                "leaving": {leg: sum(row[j] for row in matrix) + self.exited_only.get(leg, 0)
                            for j, leg in enumerate(legs)}}

    def csv_rows(self, junction: Junction) -> list[tuple]:
        """The bin as rows of CSV_HEADER (times as ISO 8601 UTC): one a pair of legs (zeros too, so that every bin
        has the same rows), then one a leg for the vehicles seen entering only (`to` empty) and one for those seen
        leaving only (`from` empty)."""
        start, end, seen = iso_utc(self.start_ns), iso_utc(self.end_ns), round(self.observed_ns / 1e9, 1)
        legs = junction.names
        rows = [(start, end, seen, a, b, junction.turn(a, b), self.complete.get((a, b), 0)) for a in legs for b in legs]
        rows += [(start, end, seen, a, "", "", self.entered_only.get(a, 0)) for a in legs]
        rows += [(start, end, seen, "", b, "", self.exited_only.get(b, 0)) for b in legs]
        return rows


def iso_utc(t_ns: int) -> str:
    """A time (ns since the epoch) as ISO 8601 UTC to the second: 2023-12-19T16:00:00Z."""
    from datetime import UTC, datetime

    return datetime.fromtimestamp(t_ns // 10**9, UTC).isoformat().replace("+00:00", "Z")


def cover(bins: dict[int, Counts], width: int, a_ns: int, b_ns: int, first_ns: int | None = None) -> None:
    """Adds the span [a_ns, b_ns) to the `observed_ns` of the `width`-ns bins it overlaps (from the bin starting at
    `first_ns` on, when given: closed bins are not reopened), creating the bins it needs."""
    if b_ns <= a_ns:
        return
    start = max(a_ns // width * width, first_ns if first_ns is not None else a_ns // width * width)
    while start < b_ns:
        overlap = min(b_ns, start + width) - max(a_ns, start)
        if overlap > 0:
            bins.setdefault(start, Counts(start, start + width)).observed_ns += overlap
        start += width


def binned(found: Sequence[Movement], bin_s: float, times_ns: Iterable[int] = ()) -> list[Counts]:
    """The movements counted in clock-aligned bins of `bin_s` seconds, and how much of each bin the Tracks messages
    at `times_ns` (any order) covered: the bins that hold a movement or were observed, in order."""
    if not MIN_BIN_S <= bin_s <= MAX_BIN_S:
        raise ValueError(f"bin_s must be {MIN_BIN_S:g} to {MAX_BIN_S:g} seconds (a week), got {bin_s}")
    width = round(bin_s * 1e9)
    bins: dict[int, Counts] = {}
    times = np.unique(np.fromiter(times_ns, np.int64))
    gap = round(COVER_GAP_S * 1e9)
    for a, b in zip(times[:-1].tolist(), times[1:].tolist(), strict=True):
        if b - a <= gap:
            cover(bins, width, a, b)
    for m in found:
        if m.entry is None and m.exit is None:  # seen only in the junction: counts on no leg
            continue
        start = m.t_ns // width * width
        bins.setdefault(start, Counts(start, start + width)).add(m)
    return [bins[k] for k in sorted(bins)]


@dataclass
class TrackPositions:
    """What `read_tracks` found: every track position (key, t_ns, lat, lon), the lines read and the bad ones."""

    positions: list[tuple[tuple[str, int], int, float, float]] = field(default_factory=list)
    times_ns: list[int] = field(default_factory=list)  # each good line's capture time: what the tracks covered
    sites: set[str] = field(default_factory=set)  # the sites the good lines name
    lines: int = 0
    bad: list[str] = field(default_factory=list)  # "file:line: reason", the first 20
    bad_lines: int = 0


def read_tracks(paths: Sequence[Path]) -> TrackPositions:
    """The positions of tracks files (fuse_track's recording; rotated files in any order: positions are sorted by
    time per track). A line that is not a tracks line (half written, not JSON, a row without a finite id, lat
    or lon) is counted and skipped. ValueError for a file that cannot be read."""
    out = TrackPositions()
    for path in paths:
        for where, line in file_lines(Path(path)):
            out.lines += 1
            try:
                obj = json.loads(line)
                out.positions += list(_positions(obj))
                out.times_ns.append(obj["t_ns"])
                if isinstance(obj.get("site"), str):
                    out.sites.add(obj["site"])
            except (ValueError, TypeError, KeyError, RecursionError) as exc:  # JSONDecodeError is a ValueError
                out.bad_lines += 1
                if len(out.bad) < 20:
                    out.bad.append(f"{where}: {type(exc).__name__}: {exc}"[:300])
    return out


def _positions(obj: dict) -> Iterator[tuple[tuple[str, int], int, float, float]]:
    t, tracker = obj["t_ns"], obj["tracker"]
    if not isinstance(t, int) or isinstance(t, bool) or not isinstance(tracker, str):
        raise ValueError("t_ns must be an integer and tracker a string")
    rows = obj["tracks"]
    if not isinstance(rows, list):
        raise ValueError("tracks must be a list")
    found = []
    for r in rows:
        i, lat, lon = r["id"], r["lat"], r["lon"]
        if not isinstance(i, int) or isinstance(i, bool) or not all(
                isinstance(v, int | float) and math.isfinite(v) for v in (lat, lon)):
            raise ValueError(f"track {i!r}: id must be an integer, lat and lon finite numbers")
        found.append(((tracker, i), t, float(lat), float(lon)))
    return iter(found)
