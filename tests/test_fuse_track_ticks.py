"""fuse_track's event-time ticks with plain arrays: when a tick closes, late and glitched cameras, clocks
that step, and caps."""

from __future__ import annotations

import numpy as np
import pytest
from fuse_track_fixtures import MS, frame

from services.fuse_track.ticks import TickBuffer, TickConfig


def test_tick_closes_when_every_camera_is_past_it_and_late_items_are_dropped():
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, watermark_ms=150, max_wait_ms=300))
    assert buffer.add("A", 10 * MS, "a0", 0.0)
    assert buffer.add("B", 60 * MS, "b0", 0.01)
    assert buffer.add("A", 110 * MS, "a1", 0.02)
    assert buffer.pop_ready(0.02) == []  # B may still send a frame of tick 0
    buffer.add("B", 160 * MS, "b1", 0.03)
    (tick,) = buffer.pop_ready(0.03)
    assert (tick.index, tick.start_ns, tick.end_ns, tick.t_ref_ns) == (0, 0, 100 * MS, 50 * MS)
    assert tick.closed_by == "complete" and tick.items() == ["a0", "b0"]
    assert tick.batches == {"A": [(10 * MS, "a0")], "B": [(60 * MS, "b0")]}
    assert not buffer.add("B", 90 * MS, "late", 0.04)  # its tick has closed: counted and dropped
    assert buffer.late == 1
    tick1 = buffer.pop_ready(0.04) + buffer.flush()
    assert [t.items() for t in tick1] == [["a1", "b1"]]


def test_a_camera_whose_clock_jumps_ahead_is_dropped_not_followed():
    """One camera's clock steps an hour forward: its batches are dropped as ahead instead of closing every tick by
    the watermark and making the other cameras late; when every camera's clock jumps, they are followed again."""
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, max_lead_ms=2000))
    hour = 3600 * 1000 * MS
    emitted = []
    for k in range(30):
        now = k * 0.1
        buffer.add("A", k * 100 * MS + 10 * MS, f"a{k}", now)
        ok = buffer.add("B", k * 100 * MS + 20 * MS + (hour if 10 <= k < 20 else 0), f"b{k}", now)
        assert ok == (not 10 <= k < 20)
        emitted += buffer.pop_ready(now)
    assert buffer.ahead == 10 and buffer.late == 0 and buffer.refusal.startswith("ahead: captured 3600.")
    assert [t.index for t in emitted] == list(range(len(emitted))) and len(emitted) >= 28  # no tick lost to it
    assert sum("a" in " ".join(t.items()) for t in emitted) == len(emitted)  # A's batches all used
    # both clocks jump: the first to jump waits for the other, then both are followed
    for k in range(30, 40):
        assert buffer.add("A", k * 100 * MS + 2 * hour, f"a{k}", k * 0.1) == (k > 30)
        assert buffer.add("B", k * 100 * MS + 2 * hour + 10 * MS, f"b{k}", k * 0.1)
    assert buffer.ahead == 11 and buffer.late == 0
    with pytest.raises(ValueError, match="max_lead_ms"):
        TickConfig(max_lead_ms=0)


def test_watermark_closes_a_tick_without_a_late_camera():
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, watermark_ms=150, max_wait_ms=10_000))
    buffer.add("B", 50 * MS, "b0", 0.0)
    for k, now in ((0, 0.0), (1, 0.01), (2, 0.02)):
        buffer.add("A", k * 100 * MS + 10 * MS, f"a{k}", now)
    assert buffer.pop_ready(0.02) == []  # newest 210 ms is not past 100 + 150 ms
    buffer.add("A", 310 * MS, "a3", 0.03)
    ticks = buffer.pop_ready(0.03)
    assert [(t.index, t.closed_by) for t in ticks] == [(0, "watermark")]  # 310 > 100 + 150 ms; 310 < 200 + 150 ms
    assert ticks[0].items() == ["b0", "a0"]


def test_silent_camera_is_waited_for_max_wait_then_not_at_all_until_it_returns():
    cfg = TickConfig(tick_ms=100, watermark_ms=10_000, max_wait_ms=300, camera_timeout_ms=1000)
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], cfg)
    buffer.add("A", 10 * MS, "a0", 0.0)
    buffer.add("A", 110 * MS, "a1", 0.1)
    assert buffer.pop_ready(0.2) == []  # B has not delivered: wait
    (tick,) = buffer.pop_ready(0.31)  # max_wait after tick 0's first item
    assert tick.index == 0 and tick.closed_by == "max_wait"
    assert buffer.live(0.5) == ["A", "B"] and buffer.live(1.05) == ["A"]  # B silent for over 1 s
    buffer.add("A", 210 * MS, "a2", 1.05)
    assert [(t.index, t.closed_by) for t in buffer.pop_ready(1.05)] == [(1, "complete")]
    buffer.add("B", 260 * MS, "b2", 1.1)  # B is back: waited for again
    buffer.add("A", 310 * MS, "a3", 1.1)
    assert buffer.pop_ready(1.1) == []
    buffer.add("B", 360 * MS, "b3", 1.2)
    (tick,) = buffer.pop_ready(1.2)
    assert tick.closed_by == "complete" and tick.items() == ["a2", "b2"]
    assert buffer.closed_by == {"complete": 2, "watermark": 0, "max_wait": 1, "flush": 0}


def test_one_glitched_capture_time_costs_one_batch_not_the_camera():
    """A camera arriving after the other sends one batch stamped an hour ahead: that batch is dropped and nothing
    else (its newest time is not moved, so its later batches are not late and do not close ticks early); with a
    single camera the same; a camera stuck an hour ahead for longer than max_lead_ms does not drag the other
    camera's batches along."""
    hour = 3600 * 1000 * MS
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, max_lead_ms=2000))
    accepted = {"A": 0, "B": 0}
    for k in range(100):
        now = k * 0.1
        accepted["B"] += buffer.add("B", k * 100 * MS + 10 * MS, f"b{k}", now)
        glitch = hour if k == 50 else 0
        accepted["A"] += buffer.add("A", k * 100 * MS + 20 * MS + glitch, f"a{k}", now + 0.03)
        buffer.pop_ready(now + 0.03)
    assert accepted == {"A": 99, "B": 100} and buffer.ahead == 1 and buffer.late == 0
    alone: TickBuffer[str] = TickBuffer(["A"], TickConfig(tick_ms=100, max_lead_ms=2000))
    got = [alone.add("A", k * 100 * MS + (hour if k == 5 else 0), f"a{k}", k * 0.1) for k in range(20)]
    assert got == [k != 5 for k in range(20)] and alone.late == 0 and alone.ahead == 1
    stuck: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, max_lead_ms=2000))
    for k in range(100):  # B an hour ahead for 10 s of event time, five times max_lead_ms
        assert stuck.add("A", k * 100 * MS, f"a{k}", k * 0.1)
        assert stuck.add("B", k * 100 * MS + (hour if k >= 2 else 0), f"b{k}", k * 0.1) == (k < 2)
        stuck.pop_ready(k * 0.1)
    assert stuck.ahead == 98 and stuck.late == 0



def test_a_camera_whose_every_batch_is_refused_is_not_waited_for_until_one_is_used_again():
    """B's clock runs five minutes behind for 4 s: every batch of it is refused as behind. After camera_timeout_ms B
    is not waited for, as if it were dead, so ticks close as soon as A has delivered, not by the watermark or max_wait
    (all of the site's tracks late for as long as B runs). Once B's clock is right again it is waited for again, though
    its first good batch comes after A has closed its tick (B's frames arrive later than A's)."""
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, max_lead_ms=60_000))
    behind, t0 = 300 * 1000 * MS, 3600 * 1000 * MS
    arrivals = []  # (wall time, camera, capture time, k): A 20 ms into each tick, 40 ms transport; B 60 ms, 50 ms
    for k in range(100):
        arrivals.append(((k * 100 + 60) / 1e3, "A", t0 + (k * 100 + 20) * MS, k))
        arrivals.append(((k * 100 + 110) / 1e3, "B", t0 + (k * 100 + 60) * MS - (behind if 20 <= k < 60 else 0), k))
    arrivals.sort()
    closed: dict[int, tuple[str, float, list[str]]] = {}  # k: (closed by, wall time, items)
    first = t0 // (100 * MS)
    accepted_b = []
    now = 0.0
    for wall, camera, t_ns, k in arrivals:
        while now < wall:  # pop_ready every 5 ms, as fuse_track's loop does
            now = round(now + 0.005, 6)
            closed.update({t.index - first: (t.closed_by, now, t.items()) for t in buffer.pop_ready(now)})
        if buffer.add(camera, t_ns, f"{camera.lower()}{k}", wall) and camera == "B":
            accepted_b.append(k)
        if k == 45 and camera == "A":
            assert buffer.live(wall) == ["A"]  # B delivers but every batch is refused: not waited for
    assert buffer.late == 41  # 40 behind, and B's first good batch (below)
    assert accepted_b == [*range(20), *range(61, 100)]  # 60 arrives after A closed its tick: it makes B live again
    for k in range(32, 60):  # from camera_timeout_ms after B's last good batch: closed as soon as A's frame is in
        reason, at, items = closed[k]
        assert reason == "complete" and at <= (k * 100 + 65) / 1e3 and items == [f"a{k}"], (k, closed[k])
    for k in range(61, 99):  # B waited for again: each tick closes with both cameras' frames
        reason, at, items = closed[k]
        assert reason == "complete" and items == [f"a{k}", f"b{k}"], (k, closed[k])

def test_every_clock_stepping_back_restarts_the_buffer():
    """An NTP step of the cabinet's clock: every camera an hour back. The first camera's batch waits (a camera
    alone could be wrong), the second's confirms it: the open ticks are handed out first, then ticks go on from
    the new time; `restarts` tells the tracker to start again."""
    hour = 3600 * 1000 * MS
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(tick_ms=100, max_lead_ms=2000))
    emitted = []
    for k in range(60):
        now = k * 0.1
        back = hour if k >= 30 else 0
        a = buffer.add("A", hour + k * 100 * MS - back, f"a{k}", now)
        b = buffer.add("B", hour + k * 100 * MS + 10 * MS - back, f"b{k}", now)
        assert (a, b) == ((False, True) if k == 30 else (True, True))
        emitted += buffer.pop_ready(now)
    assert buffer.restarts == 1 and buffer.late == 1 and buffer.refusal.startswith("behind: captured 3599.9")
    old = [t for t in emitted if t.start_ns >= hour]
    new = [t for t in emitted if t.start_ns < hour]
    assert emitted == old + new and len(new) >= 25  # the old clock's ticks first, then the new clock's
    assert "b30" in new[0].items() and sum(len(t.items()) for t in new) >= 55
    assert [t.index for t in new] == list(range(new[0].index, new[0].index + len(new)))
    # a restart's closed ticks are not lost when the stream ends before the next pop_ready
    ended: TickBuffer[str] = TickBuffer(["A"], TickConfig(tick_ms=100, max_lead_ms=2000))
    for k, t in enumerate([hour, hour + 100 * MS, 0, 100 * MS]):
        ended.add("A", t, f"a{k}", k * 0.01)
    assert [t.items() for t in ended.flush()] == [["a0"], ["a1"], ["a3"]] and ended.restarts == 1


def test_a_camera_flooding_one_tick_is_cut_at_max_per_camera():
    buffer: TickBuffer[str] = TickBuffer(["A", "B"], TickConfig(max_per_camera=3))
    got = [buffer.add("A", 10 * MS, f"a{i}", 0.0) for i in range(5)]
    assert got == [True, True, True, False, False] and buffer.full == 2 and buffer.refusal.startswith("full: A has 3")
    assert buffer.add("B", 10 * MS, "b", 0.0)  # the other camera's batch still goes in
    assert buffer.flush()[0].items() == ["a0", "a1", "a2", "b"]
    with pytest.raises(ValueError, match="max_per_camera must be an integer >= 1"):
        TickConfig(max_per_camera=0)


def test_a_tick_keeps_its_highest_scoring_objects_up_to_the_cap():
    from services.fuse_track.__main__ import capped

    batches = [frame("A", 0, [[0.0, 0.0], [5.0, 0.0]], score=np.array([0.2, 0.9])),
               frame("B", 0, [[9.0, 0.0]], score=0.5)]
    same, dropped = capped(batches, limit=3)
    assert same is batches and dropped == 0
    (kept,), dropped = capped(batches, limit=2)
    assert dropped == 1 and kept.score.tolist() == [0.9, 0.5] and kept.xy[:, 0].tolist() == [5.0, 9.0]


def test_long_gap_emits_at_most_max_empty_ticks():
    buffer: TickBuffer[str] = TickBuffer(["A"], TickConfig(max_empty_ticks=4))
    buffer.add("A", 0, "first", 0.0)
    # an hour's jump of the only camera is followed once its next frame confirms it
    assert not buffer.add("A", 3600 * 10**9, "an hour later", 0.1)
    assert buffer.refusal.startswith("ahead: captured 3600.")
    assert buffer.add("A", 3600 * 10**9 + 100 * MS, "and the next", 0.2)
    ticks = buffer.pop_ready(0.2)
    assert ticks[0].items() == ["first"] and len(ticks) == 5 and all(t.empty for t in ticks[1:])
    assert ticks[-1].index == 36_001 - 1 and buffer.empty == 4 and buffer.ahead == 1


def test_tick_closes_without_waiting_for_the_next_frame_once_periods_are_known():
    """Two cameras at 10 Hz with phases 20 and 70 ms: once their periods are known, a tick closes when
    the later camera's frame of that tick arrives, not when the next frames do."""
    buffer: TickBuffer[int] = TickBuffer(["A", "B"])
    closed_at = {}
    for k in range(8):
        for cam, phase in (("A", 20), ("B", 70)):
            t_ns = (k * 100 + phase) * MS
            now = t_ns / 1e9 + 0.03
            buffer.add(cam, t_ns, k, now)
            for tick in buffer.pop_ready(now):
                closed_at[tick.index] = (cam, k)
    # from tick 3 on, B's frame of the same tick closes it
    assert all(closed_at[k] == ("B", k) for k in range(3, 8))
