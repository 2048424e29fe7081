"""fuse_track's cores with plain arrays: event-time ticks, fusion by camera region, SORT in metres."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from fuse_track_fixtures import CAR, MS, frame, ids_by_truth, pipeline

from services.fuse_track.fusion import (
    CameraRegion,
    Fusion,
    FusionConfig,
    ObjectBatch,
    inverse_2x2,
    wrap_angle,
)
from services.fuse_track.ticks import TickBuffer, TickConfig
from services.fuse_track.tracker import (
    Tracker,
    TrackerConfig,
    TrackState,
    kf_predict,
    kf_update,
    process_noise,
    transition,
    turn_noise,
)
from shared.position_error import POSITION_SIGMA, position_information


# ---- tracking ------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_crossing_vehicles_keep_their_ids(seed):
    """Two vehicles on crossing paths, 0.25 s apart at the crossing (1.8 m at closest), noisy
    detections with some 180-degree heading flips: each keeps one id, and its yaw follows its motion."""
    rng = np.random.default_rng(seed)
    speed = 10.0

    def truth(t):
        return np.array([[-30 + speed * t, 0.0], [0.0, -30 + speed * (t - 0.25)]])

    frames = []
    for k in range(60):
        t = 0.1 * k + 0.02
        xy = truth(t) + rng.normal(0, 0.2, (2, 2))
        yaw = np.array([0.0, math.pi / 2]) + np.where(rng.random(2) < 0.2, math.pi, 0.0)
        frames.append((t + 0.03, "A", round(t * 1e9), frame("A", round(t * 1e9), xy, yaw)))
    states = pipeline(frames, {"A": (0.0, 0.0)})
    seen = ids_by_truth(states, truth)
    assert len(seen[0]) == 1 and len(seen[1]) == 1 and seen[0] != seen[1]
    last = states[-3]
    order = np.argsort(last.xy[:, 0])[::-1]  # vehicle 0 is far east by then
    assert np.allclose(np.cos(last.yaw[order] - [0.0, math.pi / 2]), 1.0, atol=0.02)
    assert np.allclose(last.velocity[order], [[speed, 0.0], [0.0, speed]], atol=1.0)


def test_vehicle_keeps_its_id_from_one_camera_region_to_the_next():
    """Cameras 40 m apart, 40 ms out of phase, each seeing 25 m around it: one id across the handover,
    and the fused objects in the overlap come from both cameras."""
    rng = np.random.default_rng(3)
    cams = {"west": (-20.0, 0.0), "east": (20.0, 0.0)}
    phase = {"west": 0.013, "east": 0.053}

    def truth(t):
        return np.array([[-40 + 12 * t, 1.5]])

    frames = []
    for name, pos in cams.items():
        for k in range(65):
            t = 0.1 * k + phase[name]
            xy = truth(t)
            seen = np.linalg.norm(xy - pos, axis=1) < 25
            t_ns = round(t * 1e9)
            frames.append((t + 0.02, name, t_ns, frame(name, t_ns, xy[seen] + rng.normal(0, 0.2, (seen.sum(), 2)))))
    log: list = []
    states = pipeline(frames, cams, fusion_log=log)
    assert ids_by_truth(states, truth)[0] == {1}
    both = [fused for _, fused in log if len(fused) and fused.sources_of(0) == ["east", "west"]]
    assert len(both) >= 5  # the ~1 s the vehicle spends where both cameras see it
    assert all(len(fused) <= 1 for _, fused in log)


def test_a_vehicle_in_a_dead_cameras_region_is_tracked_from_its_neighbours_view():
    """Two cameras 40 m apart; east stops delivering after 2 s, and then a vehicle drives through its region, 25-45 m
    from west, which sees it: a second after east's last frame its region is west's, and the vehicle is tracked; with
    the handover off (`handover_s` 0), west's view of it never starts a track."""
    cams = {"west": (-20.0, 0.0), "east": (20.0, 0.0)}

    def truth(t):
        return np.array([[5.0 + 4.0 * (t - 4.0), 3.0]])

    frames = []
    for k in range(80):
        t = 0.1 * k
        t_ns = round(t * 1e9)
        xy = truth(t) if t >= 4.0 else np.zeros((0, 2))
        frames.append((t + 0.02, "west", t_ns, frame("west", t_ns, xy)))
        if t < 2.0:
            frames.append((t + 0.03, "east", t_ns + 30 * MS, frame("east", t_ns + 30 * MS, np.zeros((0, 2)))))
    tracked = ids_by_truth(pipeline(frames, cams, fusion_config=FusionConfig(handover_s=1.0)), truth)
    assert tracked.get(0) and len(tracked[0]) == 1
    assert not ids_by_truth(pipeline(frames, cams, fusion_config=FusionConfig(handover_s=0.0)), truth).get(0)


def test_low_score_objects_extend_confirmed_tracks_but_never_start_one():
    """ByteTrack's second round (high_score): a vehicle whose score dips below high_score for a few ticks keeps
    its track and id (one round drops the track and starts a new id); a low-score object alone, with no track
    to extend, never starts one; a low-score object never takes a track from a high-score one."""
    def run(high_score: float) -> tuple[list[set[int]], Tracker]:
        tracker = Tracker(TrackerConfig(high_score=high_score, max_age_ticks=1, report_coasting_ticks=0))
        ids = []
        for k in range(20):
            t_ns = k * 100 * MS
            x = 10.0 * k * 0.1
            score = 0.3 if 6 <= k < 12 else 0.9  # the vehicle's score dips for 6 ticks
            objs = [frame("A", t_ns, [[x, 0.0]], score=score),
                    frame("A", t_ns, [[x, 40.0]], score=0.3),  # a low-score object alone, every tick
                    frame("A", t_ns, [[x + 0.4, 0.3]], score=0.35)]  # a weaker duplicate of the vehicle
            ids.append(set(tracker.update(ObjectBatch.concat(objs), t_ns).id.tolist()))
        return ids, tracker

    two_rounds, _ = run(0.5)
    assert set().union(*two_rounds[2:]) == {1} and all(two_rounds[k] == {1} for k in range(2, 20))
    one_round, _ = run(0.0)  # every object alike: the lone object and the duplicate start tracks of their own
    assert len(set().union(*one_round)) > 1
    # with one round and only the vehicle above the threshold (what a detector threshold of 0.5 gives): the
    # dip breaks the track and the vehicle comes back under a new id, unless relink gives it its old one back
    for relink_s, last in ((0.0, {2}), (3.0, {1})):
        tracker = Tracker(TrackerConfig(max_age_ticks=1, report_coasting_ticks=0, relink_s=relink_s))
        ids = []
        for k in range(20):
            objs = frame("A", k * 100 * MS, [[1.0 * k, 0.0]], score=0.9) if not 6 <= k < 12 else ObjectBatch.empty()
            ids.append(set(tracker.update(objs, k * 100 * MS).id.tolist()))
        assert ids[2] == {1} and ids[9] == set() and ids[19] == last


def test_standing_hits_confirms_a_persistent_low_score_object_and_nothing_that_flickers():
    """standing_hits: a low-score object seen at one place tick after tick (a parked car the detector is unsure
    of) becomes a track after that many consecutive ticks, not min_hits; one that misses a tick starts over;
    a low-score object that flickers never becomes one; without standing_hits none ever does."""
    def run(standing_hits: int, present) -> list[set[int]]:
        tracker = Tracker(TrackerConfig(high_score=0.5, standing_hits=standing_hits, max_age_ticks=2,
                                        report_coasting_ticks=0))
        out = []
        for k in range(30):
            t_ns = k * 200 * MS
            objs = [frame("A", t_ns, [[100.0 + 0.1 * k, 0.0]], score=0.9)]  # a moving high-score vehicle
            if present(k):
                objs.append(frame("A", t_ns, [[5.0 + 0.05 * (k % 3), 5.0]], score=0.2))  # a standing one
            out.append(set(tracker.update(ObjectBatch.concat(objs), t_ns).id.tolist()))
        return out

    always = run(10, lambda k: True)
    standing = [k for k, ids in enumerate(always) if len(ids) == 2]
    assert standing[0] == 9 and standing == list(range(9, 30))  # confirmed at its 10th consecutive hit
    assert len(set().union(*always)) == 2
    # a miss at tick 5 restarts the count (the tentative track is dropped): confirmed at tick 6 + 9
    gap = run(10, lambda k: k != 5)
    assert min(k for k, ids in enumerate(gap) if len(ids) == 2) == 15
    # present every other tick: never 10 in a row
    assert all(len(ids) <= 1 for ids in run(10, lambda k: k % 2 == 0))
    # off (the default): a low-score object never starts a track
    assert all(len(ids) <= 1 for ids in run(0, lambda k: True))


def test_fusion_split_score_keeps_low_and_high_score_objects_apart():
    """With split_score, a low-score object inside its camera's region no longer lets a high-score object from
    outside that region join it (the paper's rule drops the outsider, as without the low one)."""
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))]
    objects = ObjectBatch.concat([frame("A", 0, [[-15.0, 0.0]], score=0.3), frame("B", 0, [[-14.5, 0.0]], score=0.8)])
    pooled = Fusion(regions, FusionConfig(merge_gate_m=2.5)).fuse(objects, 0)
    assert len(pooled) == 1 and pooled.score[0] == pytest.approx(0.8)  # the outsider rode on the low object
    split = Fusion(regions, FusionConfig(merge_gate_m=2.5, split_score=0.5)).fuse(objects, 0)
    assert len(split) == 1 and split.score[0] == pytest.approx(0.3) and split.sources_of(0) == ["A"]
    high_only = Fusion(regions, FusionConfig(merge_gate_m=2.5)).fuse(objects.select(np.array([1])), 0)
    assert len(high_only) == 0


def test_inverse_2x2_is_numpys_and_marks_a_singular_matrix():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(50, 2, 2))
    a = m @ m.transpose(0, 2, 1) + 0.1 * np.eye(2)  # information matrices: symmetric positive definite
    np.testing.assert_allclose(inverse_2x2(a), np.linalg.inv(a), rtol=1e-10, atol=1e-12)
    assert not np.isfinite(inverse_2x2(np.array([[[1.0, 2.0], [2.0, 4.0]]]))).all()
    assert inverse_2x2(np.zeros((0, 2, 2))).shape == (0, 2, 2)


@pytest.mark.parametrize("seed, cfg", [(0, {}), (1, {}), (2, {"occlusion_fallback": True}),
                                       (3, {"position_sigma": None}), (4, {"crowded_sigma_factor": 1.0})])
def test_fusion_of_two_pools_in_one_pass_equals_each_pool_fused_alone(seed, cfg):
    """Both pools of a tick go through one pass (fusion's cost is mostly per call), with exactly the result of
    fusing the high-scoring objects alone, then the low-scoring ones alone: a crowded, noisy tick of three cameras
    and one without a region (extend-only and fallback objects too), at several capture times."""
    rng = np.random.default_rng(seed)
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0)), CameraRegion("C", (0.0, 30.0))]
    cfg = dict(merge_gate_m=3.0, extend_range_m=40.0, **cfg)
    truth = rng.uniform(-35, 35, (25, 2))
    batches = []
    for cam, t_ms in (("A", -30), ("B", 10), ("C", 40), ("D", 0)):  # D: a camera without a region
        seen = truth[rng.random(len(truth)) < 0.8]
        xy = np.concatenate([seen + rng.normal(0, 0.6, seen.shape), rng.uniform(-35, 35, (3, 2))])
        n = len(xy)
        batches.append(ObjectBatch.from_frame(cam, t_ms * MS, xy, rng.uniform(-np.pi, np.pi, n),
                                              np.tile(CAR, (n, 1)) * rng.uniform(0.9, 1.1, (n, 1)),
                                              rng.integers(0, 3, n), rng.uniform(0.2, 0.95, n)))
    objects = ObjectBatch.concat(batches)
    vel = rng.normal(0, 5, (len(objects), 2))
    got = Fusion(regions, FusionConfig(split_score=0.5, **cfg)).fuse(objects, 0, vel)
    alone = Fusion(regions, FusionConfig(**cfg))
    high = objects.score >= 0.5
    want = ObjectBatch.concat([alone.fuse(objects.select(k), 0, vel[k]) for k in (high, ~high)])
    assert len(got) == len(want) > 20
    for k in ("camera", "t_ns", "vtype"):
        assert getattr(got, k).tolist() == getattr(want, k).tolist(), k
    for k in ("xy", "yaw", "size_lwh", "score"):
        np.testing.assert_allclose(getattr(got, k), getattr(want, k), rtol=0, atol=1e-9, err_msg=k)
    assert [got.sources_of(i) for i in range(len(got))] == [want.sources_of(i) for i in range(len(want))]
    assert got.extend_mask().tolist() == want.extend_mask().tolist()
    assert want.extend_mask().any() != cfg.get("occlusion_fallback", False)  # the fallback keeps them whole instead


def test_empty_ticks_age_tracks_out_after_max_age():
    """A vehicle seen for 10 ticks, then only empty batches: reported while it coasts one tick, dropped
    after max_age_ticks empty ticks; empty ticks are emitted across a gap in the stream too."""
    buffer: TickBuffer[ObjectBatch] = TickBuffer(["A"])
    tracker = Tracker(TrackerConfig(max_age_ticks=3, report_coasting_ticks=1))
    reported, alive = [], []
    for k in range(20):
        t_ns = k * 100 * MS + 10 * MS
        batch = frame("A", t_ns, [[5.0 * k * 0.1, 0.0]]) if k < 10 else ObjectBatch.empty()
        buffer.add("A", t_ns, batch, k * 0.1)
        for tick in buffer.pop_ready(k * 0.1):
            reported.append(len(tracker.update(ObjectBatch.concat(tick.items()), tick.t_ref_ns)))
            alive.append(len(tracker))
    # Every tick closes as soon as its frame arrives (the camera's next frame is due in the next tick),
    # except the first three (its frame period is not known yet); confirmed on the third hit.
    assert reported == [0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    assert alive[9:14] == [1, 1, 1, 1, 0]
    # A gap: ticks with no batch at all are still emitted, empty, in order.
    buffer.add("A", 25 * 100 * MS + 10 * MS, ObjectBatch.empty(), 2.5)
    ticks = buffer.pop_ready(2.5) + buffer.flush()
    assert [t.index for t in ticks] == list(range(20, 26))
    assert [t.empty for t in ticks] == [True] * 5 + [False]


def test_a_moving_track_heads_where_it_goes_and_a_standing_one_as_detected():
    """Detections whose heading is 12 deg off (and reversed one time in four): a vehicle at 8 m/s is reported heading
    along its motion (within 2 deg); without yaw_motion_full_mps the detections' 12 deg stay; a standing vehicle
    keeps the detections' heading either way, and one that stops keeps the heading it had."""
    off = math.radians(12.0)

    def run(config: TrackerConfig, speed: float, stop_at: int | None = None) -> TrackState:
        rng = np.random.default_rng(5)
        tracker = Tracker(config)
        x = 0.0
        for k in range(40):
            v = 0.0 if stop_at is not None and k >= stop_at else speed
            x += v * 0.1
            yaw = math.pi / 2 + off + (math.pi if rng.random() < 0.25 else 0.0)  # the vehicle heads north
            state = tracker.update(frame("A", k * 100 * MS, [[0.0, x]], yaw=yaw), k * 100 * MS)
        return state

    def err_deg(state: TrackState) -> float:
        return math.degrees(abs(wrap_angle(np.array([state.yaw[0] - math.pi / 2]))[0]))

    assert err_deg(run(TrackerConfig(), 8.0)) < 2.0
    assert err_deg(run(TrackerConfig(yaw_motion_full_mps=0.0), 8.0)) == pytest.approx(12.0, abs=1.0)
    # standing: the detections' heading, its sign the detections' majority at birth (no motion to tell)
    standing = err_deg(run(TrackerConfig(), 0.0))
    assert min(standing, 180.0 - standing) == pytest.approx(12.0, abs=1.0)
    # stopped after 2 s of motion: the heading of its motion, drawn back towards the detections' as they come
    stopped = err_deg(run(TrackerConfig(), 8.0, stop_at=38))
    assert stopped < 12.0
    assert stopped < 2.0  # the motion's heading, not the detections' 12 deg (which it gives without the setting)
    assert err_deg(run(TrackerConfig(yaw_motion_full_mps=0.0), 8.0, stop_at=38)) == pytest.approx(12.0, abs=1.0)


def test_a_heading_confirmed_by_travel_is_not_reversed_by_a_standing_vehicles_jitter():
    """A vehicle drives north at 8 m/s for 2 s, stops, and 2 s later its detections jump 1.5 m back and return
    within a second (a standing vehicle's detections do): the filter's velocity points south at 1.8 m/s for a moment,
    yet the heading its travel confirmed stays north (yaw_reverse_s); with yaw_reverse_s 0 the jitter reverses it
    for good. A vehicle that really backs up (2 m/s south for 2 s) is turned round after yaw_reverse_s.
    yaw_confirmed is False until the track has travelled yaw_confirm_travel_m, and stays False for a vehicle that
    only jitters in place; a vehicle the detector sees backwards at birth is turned round by its motion at once."""
    def run(config: TrackerConfig, path: list[float], yaw: float = math.pi / 2) -> list[TrackState]:
        tracker = Tracker(config)
        return [tracker.update(frame("A", k * 100 * MS, [[0.0, y]], yaw=yaw), k * 100 * MS)
                for k, y in enumerate(path)]

    def north(state: TrackState) -> bool:
        return abs(wrap_angle(np.array([state.yaw[0] - math.pi / 2]))[0]) < math.pi / 2

    drive = [0.8 * k for k in range(20)]
    stop = drive[-1]
    jitter = [stop] * 20 + [stop - 0.5 * k for k in range(1, 4)] + [stop - 1.5] * 4 + [stop - 1.0, stop - 0.5]
    jitter += [stop] * 10
    states = run(TrackerConfig(), drive + jitter)
    assert not states[2].yaw_confirmed[0] and states[19].yaw_confirmed[0] and north(states[19])
    assert all(north(s) and s.yaw_confirmed[0] for s in states[19:])
    assert min(s.velocity[0, 1] for s in states[40:]) < -1.5  # faster than yaw_from_motion_mps, backwards
    assert not any(north(s) for s in run(TrackerConfig(yaw_reverse_s=0.0), drive + jitter)[45:])
    backing = [stop - 0.2 * k for k in range(1, 21)]
    states = run(TrackerConfig(), drive + [stop] * 10 + backing)
    turned = [k for k, s in enumerate(states) if len(s) and not north(s)]
    assert turned and 30 + 10 <= turned[0] <= 30 + 18 and all(not north(s) for s in states[turned[0]:])
    assert all(s.yaw_confirmed[0] for s in states[19:])
    in_place = run(TrackerConfig(), [0.0] * 5 + jitter)
    assert not any(s.yaw_confirmed.any() for s in in_place)
    backwards = run(TrackerConfig(), drive, yaw=-math.pi / 2)  # the detector's heading is reversed
    assert north(backwards[3]) and backwards[-1].yaw_confirmed[0]


def test_a_headings_sigma_is_the_detectors_until_the_vehicle_moves_and_its_velocitys_while_it_does():
    """yaw_std: a standing vehicle's is yaw_std_deg throughout (detections without jitter); one driving north at
    8 m/s with detections 0.3 m apart across its path gets its heading from its velocity, and the sigma with it: down
    to the velocity's error across the motion over the speed (a few degrees), smaller at 16 m/s than at 8, and back up
    to yaw_std_deg once it has stopped (its detections' heading errors persist)."""
    rng = np.random.default_rng(3)

    def run(config: TrackerConfig, path: list[float], noise_m: float = 0.3) -> list[TrackState]:
        tracker = Tracker(config)
        return [tracker.update(frame("A", k * 100 * MS, [[rng.normal(0, noise_m), y]], yaw=math.pi / 2), k * 100 * MS)
                for k, y in enumerate(path)]

    sd = math.radians(TrackerConfig().yaw_std_deg)
    standing = run(TrackerConfig(), [0.0] * 30, noise_m=0.0)
    assert all(np.allclose(s.yaw_std, sd) for s in standing if len(s))
    drive = [0.8 * k for k in range(40)]
    states = run(TrackerConfig(), drive + [drive[-1]] * 40)
    moving = [s for s in states[20:40]]
    assert all(0.005 < s.yaw_std[0] < math.radians(5) for s in moving), [round(s.yaw_std[0], 3) for s in moving]
    e = moving[-1].velocity_cov[0]
    assert moving[-1].yaw_std[0] == pytest.approx(math.sqrt(e[0, 0]) / np.linalg.norm(moving[-1].velocity[0]),
                                                  rel=0.05)  # across a northward motion: east's variance
    fast = run(TrackerConfig(), [1.6 * k for k in range(40)])
    assert np.median([s.yaw_std[0] for s in fast[20:]]) < np.median([s.yaw_std[0] for s in moving])
    assert 0.9 * sd < states[-1].yaw_std[0] <= sd
    assert np.all(np.diff([s.yaw_std[0] for s in states[55:]]) >= -1e-12)
    assert run(TrackerConfig(yaw_std_deg=20.0), [0.0] * 5, noise_m=0.0)[-1].yaw_std[0] == pytest.approx(
        math.radians(20.0))


def test_a_vehicle_lost_for_a_moment_keeps_its_id():
    """A vehicle at 8 m/s missed for 1 s (ten ticks, far beyond max_age) comes back on its path: the new track takes
    the lost one's id, age and hits (relink, default on), not while it is lost, and never an id of a vehicle elsewhere;
    without relink, or lost for longer than relink_s, it is a new id."""
    def run(config: TrackerConfig, gap: range, other_at: tuple[float, float] | None = None) -> list[TrackState]:
        tracker = Tracker(config)
        states = []
        for k in range(60):
            t_ns = k * 100 * MS
            xy = [] if k in gap else [[0.8 * k, 0.0]]
            if other_at is not None and k >= gap.start + 5:  # appears once the first is lost (tick 24)
                xy.append(list(other_at))
            states.append(tracker.update(frame("A", t_ns, np.array(xy, float).reshape(-1, 2)), t_ns))
        return states

    def ids_on_path(states):
        return sorted({int(i) for s in states for i, (x, y) in zip(s.id, s.xy, strict=True) if abs(y) < 1.0})

    states = run(TrackerConfig(), range(20, 30))
    assert ids_on_path(states) == [1]
    assert all(len(s) == 0 for s in states[25:32])  # max_age ends the lost track; the new one is confirmed at 32
    # and it goes on as the lost track: its age counts from the lost one's birth, its hits add up
    assert states[40].age.tolist() == [40] and states[40].hits.tolist() == [20 + 11]
    # and with the heading the lost track's travel confirmed, before its own 3 m (2.4 m at its confirmation)
    assert states[32].yaw_confirmed.tolist() == [True]
    assert run(TrackerConfig(relink_s=0), range(20, 30))[32].yaw_confirmed.tolist() == [False]
    assert ids_on_path(run(TrackerConfig(relink_s=0), range(20, 30))) == [1, 2]
    assert ids_on_path(run(TrackerConfig(), range(20, 55))) == [1, 2]  # lost (at tick 24) 3.3 s before it is back
    # a second vehicle appears 6 m from where the lost one would be by now: it gets its own id, the first keeps its own
    states = run(TrackerConfig(), range(20, 30), other_at=(21.6, 6.0))
    assert ids_on_path(states) == [1]
    other = {int(i) for s in states for i, (x, y) in zip(s.id, s.xy, strict=True) if abs(y - 6.0) < 1.0}
    assert len(other) == 1 and 1 not in other
    assert all(len(set(s.id.tolist())) == len(s) for s in states)


def test_no_track_is_born_next_to_an_existing_one():
    """An unmatched object within birth_separation_m of a track is a duplicate (a second peak on one vehicle the
    fusion did not merge): no new track; one farther away starts its own."""
    def run(offset_m: float, separation_m: float) -> int:
        tracker = Tracker(TrackerConfig(birth_separation_m=separation_m))
        for k in range(5):
            xy = [[0.5 * k, 0.0]] if k < 3 else [[0.5 * k, 0.0], [0.5 * k, offset_m]]
            tracker.update(frame("A", k * 100 * MS, xy), k * 100 * MS)
        return len(tracker)

    assert TrackerConfig().birth_separation_m == 2.25
    assert run(2.0, 2.25) == 1  # inside: the duplicate is taken by nobody and starts nothing
    assert run(2.5, 2.25) == 2  # outside: a new (tentative) track
    assert run(2.0, 1.5) == 2
    with pytest.raises(ValueError, match="birth_separation_m must be >= 0"):
        TrackerConfig(birth_separation_m=float("nan"))


@pytest.mark.parametrize(("config", "bound_m"), [
    (FusionConfig(), 0.12),
    # a scalar weighted mean at the members' mean time is exact whatever their speed; weighted by matrices, a
    # member's time shift moves the fused position across the motion too, until the velocity hints are known
    (FusionConfig(position_sigma=None), 0.1),
])
def test_two_cameras_at_different_capture_times_make_one_accurate_track(config, bound_m):
    """A vehicle at 15 m/s seen by two cameras 80 ms apart in every tick (1.2 m of travel): one fused
    object per tick, one track, within about 10 cm of the truth at the tick time and exact once settled."""
    cams = {"A": (-10.0, 0.0), "B": (10.0, 0.0)}
    speed = 15.0

    def truth(t):
        return np.array([[-20 + speed * t, 2.0]])

    frames = []
    for k in range(30):
        for name, dt in (("A", 0.01), ("B", 0.09)):
            t = 0.1 * k + dt
            t_ns = round(t * 1e9)
            frames.append((t + 0.02, name, t_ns, frame(name, t_ns, truth(t))))
    log: list = []
    states = pipeline(frames, cams, fusion_log=log, fusion_config=config)
    assert all(len(fused) == 1 for _, fused in log[1:])
    assert ids_by_truth(states, truth)[0] == {1}
    errors = [np.linalg.norm(s.xy[0] - truth(s.t_ns / 1e9)[0]) for s in states if len(s)]
    # Uncorrected, the two views would be 1.2 m apart and the track ~0.6 m off.
    assert len(errors) >= 25 and max(errors) < bound_m and max(errors[-10:]) < 0.005


def test_measurements_off_the_tick_time_add_no_error():
    """A track fed at capture times up to 50 ms off the tick time follows the truth exactly (noise-free)."""
    tracker = Tracker(TrackerConfig(min_hits=1))
    for k in range(30):
        t_ref = k * 100 * MS + 50 * MS
        t_cap = t_ref + (-45 if k % 2 else 45) * MS
        state = tracker.update(frame("A", t_cap, [[12.0 * t_cap / 1e9, 3.0]]), t_ref)
    assert np.allclose(state.xy[0], [12.0 * t_ref / 1e9, 3.0], atol=0.01)
    assert np.allclose(state.velocity[0], [12.0, 0.0], atol=0.05)


def test_track_reports_size_type_majority_and_cameras():
    tracker = Tracker(TrackerConfig(min_hits=2))
    for k in range(6):
        objs = frame("A", k * 100 * MS, [[0.0, 0.0]], vtype=1 if k != 3 else 2)
        state = tracker.update(objs, k * 100 * MS)
    assert state.vtype.tolist() == [1]
    assert np.allclose(state.size_lwh[0], CAR, atol=0.01)
    assert state.cameras == [["A"]] and state.hits.tolist() == [6] and state.age.tolist() == [5]
    assert state.tracker == tracker.id


def test_a_shrinking_vehicle_missed_for_a_tick_keeps_a_finite_size():
    """The size's rate carries area and aspect below zero when a shrinking vehicle is missed: the prediction keeps
    them positive, as the update does (the square root of a negative area was a NaN length that ended the service)."""
    tracker = Tracker(TrackerConfig())
    lengths = 6 * np.exp(-np.arange(12) / 3) + 0.02
    t_ns = 10**12
    for length in lengths:
        t_ns += 100 * MS
        size = np.array([[length, length, 1.5]])
        tracker.update(ObjectBatch.from_frame("A", t_ns, np.zeros((1, 2)), np.zeros(1), size, np.zeros(1, np.int64),
                                              np.full(1, 0.9)), t_ns)
    sizes = []
    for _ in range(3):  # missed three times: reported while it coasts, then not
        t_ns += 100 * MS
        sizes.append(tracker.update(ObjectBatch.empty(), t_ns).size_lwh)
    assert len(sizes[0]) == 1 and all(np.isfinite(s).all() and (s > 0).all() for s in sizes)


def test_track_ids_are_unique_per_instance():
    one, two = Tracker(TrackerConfig(min_hits=1)), Tracker(TrackerConfig(min_hits=1))
    a = one.update(frame("A", 0, [[0.0, 0.0], [10.0, 0.0]]), 0)
    b = two.update(frame("A", 0, [[0.0, 0.0]]), 0)
    assert a.id.tolist() == [1, 2] and b.id.tolist() == [1]
    assert one.id != two.id
    assert Tracker(tracker_id="site-1").id == "site-1"


def test_process_noise_is_filterpys_white_noise_per_pair():
    from filterpy.common import Q_discrete_white_noise

    variances = (4.0, 3.0, 0.25, 0.0025)
    for dt in (0.05, 0.1, 0.37):
        q = process_noise(dt, variances)
        for k, var in enumerate(variances):
            np.testing.assert_allclose(q[np.ix_([k, k + 4], [k, k + 4])], Q_discrete_white_noise(dim=2, dt=dt, var=var))
        off = q.copy()
        for k in range(4):
            off[np.ix_([k, k + 4], [k, k + 4])] = 0
        assert not off.any()


def test_batched_kalman_filter_equals_filterpy():
    """kf_predict / kf_update on a batch give filterpy's KalmanFilter, with a time-offset H and true dt."""
    rng = np.random.default_rng(0)
    variances = (4.0, 4.0, 0.25, 0.0025)
    kf = KalmanFilter(dim_x=8, dim_z=4)
    kf.x = np.array([0.0, 0.0, 8.0, 2.5, 0, 0, 0, 0])
    kf.P = np.diag([0.09, 0.09, 1.0, 0.1, 100, 100, 0.25, 0.0025])
    x, p = kf.x[None].copy(), kf.P[None].copy()
    for dt in (0.1, 0.1, 0.2, 0.09):
        kf.F, kf.Q = transition(dt), process_noise(dt, variances)
        kf.predict()
        x, p = kf_predict(x, p, kf.F, kf.Q)
        h = np.hstack([np.eye(4), rng.uniform(-0.05, 0.05) * np.eye(4)])
        r = np.diag(rng.uniform(0.05, 1.0, 4))
        z = rng.normal(0, 1, 4) + np.array([1.0, 0.5, 8.0, 2.5])
        kf.update(z, R=r, H=h)
        x, p, k = kf_update(x, p, z[None], h[None], r[None])
        assert np.allclose(x[0], kf.x) and np.allclose(p[0], kf.P) and np.allclose(k[0], kf.K)


def test_turn_noise_lies_across_the_motion_of_moving_tracks_only():
    dt, extra = 0.1, 12.0
    velocity = np.array([[8.0, 0.0], [0.0, -5.0], [3.0, 3.0], [1.0, 0.5], [0.0, 0.0]])
    q = turn_noise(dt, velocity, extra, 2.0)
    white = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    np.testing.assert_allclose(q[0][np.ix_([1, 5], [1, 5])], extra * white)  # east: all of it on y and vy
    assert np.count_nonzero(q[0]) == 4
    np.testing.assert_allclose(q[1][np.ix_([0, 4], [0, 4])], extra * white)  # south: on x and vx
    assert np.count_nonzero(q[1]) == 4
    across = np.array([-1.0, 1.0]) / math.sqrt(2)  # north-east: along (-1, 1) / sqrt 2
    np.testing.assert_allclose(q[2][np.ix_([0, 1], [0, 1])], extra * white[0, 0] * np.outer(across, across))
    np.testing.assert_allclose(q[2][np.ix_([0, 1], [4, 5])], extra * white[0, 1] * np.outer(across, across))
    assert not q[3].any() and not q[4].any()  # slower than 2 m/s, standing
    assert not turn_noise(dt, velocity, 0.0, 2.0).any()
    # per-track Q through the batched predict is filterpy's predict with that track's Q
    x = np.column_stack([np.zeros((5, 4)), velocity, np.zeros((5, 2))])
    p = np.tile(np.diag([0.09, 0.09, 1.0, 0.1, 4.0, 4.0, 0.25, 0.0025]), (5, 1, 1))
    base = process_noise(dt, (4.0, 4.0, 0.25, 0.0025))
    xb, pb = kf_predict(x, p, transition(dt), base + q)
    for i in range(5):
        kf = KalmanFilter(dim_x=8, dim_z=4)
        kf.x, kf.P, kf.F, kf.Q = x[i].copy(), p[i].copy(), transition(dt), base + q[i]
        kf.predict()
        assert np.allclose(xb[i], kf.x) and np.allclose(pb[i], kf.P)


def test_a_vehicle_round_a_bend_is_tracked_on_its_path_not_outside_it():
    """8 m/s round a 20 m circle (3.2 m/s^2 towards its centre), seen exactly at 10 Hz: with the paper's 2 m/s^2 either
    way the constant-velocity filter runs outside the bend; with 4 m/s^2 across the motion it keeps nearer the path."""
    radius, speed = 20.0, 8.0
    outside = {}
    for turn in (2.0, 4.0):
        tracker = Tracker(TrackerConfig(min_hits=1, turn_accel_std_mps2=turn))
        off = []
        for k in range(80):
            a, t_ns = speed / radius * k * 0.1, k * 100 * MS
            state = tracker.update(frame("A", t_ns, [[radius * math.cos(a), radius * math.sin(a)]]), t_ns)
            if k >= 30:  # settled
                assert len(state) == 1
                off.append(float(np.hypot(*state.xy[0])) - radius)
        outside[turn] = float(np.mean(off))
    assert outside[2.0] > 0.3  # the paper's model: 0.39 m outside the bend
    assert 0 <= outside[4.0] < 0.6 * outside[2.0]  # 0.19 m


def test_thirty_vehicles_seen_by_two_cameras_make_thirty_tracks():
    """A 30-vehicle tick seen by two cameras 50 ms apart, 20 ticks: one track per vehicle, each on its vehicle.
    (Its cost per tick is measured by `roadside bench fuse_track`, not here: speed lives in benchmarks.)"""
    rng = np.random.default_rng(0)
    cams = {"A": (-20.0, 0.0), "B": (20.0, 0.0)}
    fusion, tracker = Fusion([CameraRegion(n, p) for n, p in cams.items()]), Tracker()
    start = np.column_stack([rng.uniform(-40, 40, 30), 6.0 * np.arange(30) - 90])  # one vehicle per lane
    for k in range(20):
        t_ref = k * 100 * MS + 50 * MS
        batches = []
        for name, off_ms in (("A", -30), ("B", 20)):
            xy = start + np.array([10 * (t_ref / 1e9 + off_ms / 1e3), 0]) + rng.normal(0, 0.2, (30, 2))
            batches.append(frame(name, t_ref + off_ms * MS, xy))
        objects = ObjectBatch.concat(batches)
        state = tracker.update(fusion.fuse(objects, t_ref, tracker.velocity_hints(objects)), t_ref)
    truth = start + np.array([10 * t_ref / 1e9, 0])
    assert len(state) == 30 and len(set(state.id.tolist())) == 30
    d = np.hypot(*(state.xy[:, None, :] - truth[None]).transpose(2, 0, 1))
    assert sorted(np.argmin(d, axis=1).tolist()) == list(range(30)) and d.min(axis=1).max() < 0.5


def test_bench_fuse_track_smoke():
    """The benchmark runs on its synthetic roundabout and prints one JSON document; bad flags stop it."""
    args = ["--vehicles", "12", "--ticks", "20", "--warmup", "10"]
    run = subprocess.run([sys.executable, "-m", "bench.fuse_track", *args], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    doc = json.loads(run.stdout)
    assert doc["benchmark"] == "fuse_track" and doc["ticks"] == 20 and doc["cameras"] == 4
    assert 0 < doc["tick_ms"]["p50"] <= doc["tick_ms"]["p99"]
    assert doc["objects_per_tick"] > 12 and 6 <= doc["tracks_per_tick"] <= 14  # each camera sees most of them
    bad = subprocess.run([sys.executable, "-m", "bench.fuse_track", "--vehicles", "2"], capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "vehicles must be at least 4" in bad.stderr


# ---- position uncertainty --------------------------------------------------------------------------
def test_a_fused_objects_covariance_is_its_members_error_combined():
    """One camera's object carries the inverse of its information matrix; two cameras looking at it from the east
    and from the north pin it down where each alone is weak (along its line of sight)."""
    fusion = Fusion([CameraRegion("E", (40.0, 0.0)), CameraRegion("N", (0.0, 40.0))])
    table = np.asarray(POSITION_SIGMA)
    one = fusion.fuse(frame("E", 0, [[0.5, 0.0]]), 0)
    own = np.linalg.inv(position_information(np.array([[0.5, 0.0]]), np.array([[40.0, 0.0]]), table))
    np.testing.assert_allclose(one.xy_cov, own)
    assert one.xy_cov[0, 0, 0] > 4 * one.xy_cov[0, 1, 1]  # 39.5 m east of E: weak east-west, along its line
    both = fusion.fuse(ObjectBatch.concat([frame("E", 0, [[0.5, 0.0]]), frame("N", 0, [[0.0, 0.5]])]), 0)
    assert len(both) == 1
    assert both.xy_cov[0, 0, 0] < 0.5 * one.xy_cov[0, 0, 0]  # N sees east-west across its line: well
    assert np.all(np.linalg.eigvalsh(both.xy_cov[0]) > 0)
    assert Fusion([CameraRegion("E", (40.0, 0.0))], FusionConfig(position_sigma=None)).fuse(
        frame("E", 0, [[0.5, 0.0]]), 0).xy_cov is None  # no error model, no covariance


def _nees_of_a_convoy(config: TrackerConfig, rng, noise: str, with_cov: bool = True,
                      velocity: bool = False) -> np.ndarray:
    """200 vehicles 25 m apart driving east at 8 m/s for 4 s at 10 Hz, measured with errors of covariance
    C = diag(0.8^2, 0.2^2) m^2 (wider east-west than the filter's 0.3 m): fresh every frame ("white"), or one offset
    per vehicle for the whole run ("bias"). Returns each vehicle's squared Mahalanobis distance at the end under its
    reported covariance, of its position or (`velocity`) of its velocity."""
    n, cov = 200, np.diag([0.8**2, 0.2**2])
    start = np.column_stack([np.zeros(n), 25.0 * np.arange(n)])
    offset = rng.multivariate_normal([0, 0], cov, n)
    tracker = Tracker(config)
    for k in range(41):
        t_ns = k * 100 * MS
        truth = start + np.array([0.8 * k, 0.0])
        err = rng.multivariate_normal([0, 0], cov, n) if noise == "white" else offset
        batch = frame("A", t_ns, truth + err)
        if with_cov:
            batch = ObjectBatch(batch.camera, batch.t_ns, batch.xy, batch.yaw, batch.size_lwh, batch.vtype,
                                batch.score, xy_cov=np.tile(cov, (n, 1, 1)))
        state = tracker.update(batch, t_ns)
    assert len(state) == n
    order = np.argsort(state.xy[:, 1])
    if velocity:
        d, cov = state.velocity[order] - [8.0, 0.0], state.velocity_cov[order]
    else:
        d, cov = state.xy[order] - truth, state.xy_cov[order]
    return np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov), d)


def test_the_reported_covariance_is_the_error_of_the_estimate_the_filter_makes():
    """The filter weighs measurements with its own 0.3 m; what it reports is the covariance of the estimate that
    weighing gives under the measurements' real error: with fresh errors every frame (bias_share 0) the squared
    Mahalanobis distance averages 2 (chi-square, 2 dof), where the filter's own covariance would claim far less.
    (The vehicles do not accelerate: with the model's process noise near 0, its share of the covariance is too.)"""
    rng = np.random.default_rng(3)
    steady = TrackerConfig(bias_share=0.0, along_length_share=0.0, accel_std_mps2=0.001, turn_accel_std_mps2=0.001)
    nees = _nees_of_a_convoy(steady, rng, "white")
    assert 1.6 < nees.mean() < 2.4 and 0.9 < np.mean(nees <= 5.991) <= 1.0
    own = _nees_of_a_convoy(steady, rng, "white", with_cov=False)  # the filter's R only
    assert own.mean() > 3.5
    moving = _nees_of_a_convoy(steady, rng, "white", velocity=True)  # the velocity's covariance is E's too
    assert 1.6 < moving.mean() < 2.4


def test_an_error_that_persists_is_not_averaged_away():
    """Each vehicle's measurements off by one fixed offset: a filter averages nothing away. With bias_share 1 the
    reported covariance keeps the measurements' own (distance 2 on average); with 0 it shrinks as if averaging
    helped."""
    rng = np.random.default_rng(4)
    steady = {"along_length_share": 0.0, "accel_std_mps2": 0.001, "turn_accel_std_mps2": 0.001}
    kept = _nees_of_a_convoy(TrackerConfig(bias_share=1.0, **steady), rng, "bias")
    assert 1.6 < kept.mean() < 2.4
    averaged = _nees_of_a_convoy(TrackerConfig(bias_share=0.0, **steady), rng, "bias")
    assert averaged.mean() > 2 * kept.mean()


def test_a_long_vehicle_is_less_sure_along_its_body():
    """along_length_share: where on its body the detector puts a vehicle is uncertain in proportion to its length,
    along its heading: a 12 m bus heading north-east reports (0.07 x 12 m)^2 more variance along that line than
    without, none across it."""
    def last(share: float):
        tracker = Tracker(TrackerConfig(along_length_share=share))
        for k in range(5):
            batch = frame("A", k * 100 * MS, [[0.5 * k, 0.5 * k]], yaw=math.pi / 4)
            batch = ObjectBatch(batch.camera, batch.t_ns, batch.xy, batch.yaw, np.array([[12.0, 2.5, 3.2]]),
                                batch.vtype, batch.score)
            state = tracker.update(batch, k * 100 * MS)
        return state

    with_, without = last(0.07), last(0.0)
    u, v = np.array([1.0, 1.0]) / math.sqrt(2), np.array([-1.0, 1.0]) / math.sqrt(2)
    extra = with_.xy_cov[0] - without.xy_cov[0]
    assert u @ extra @ u == pytest.approx((0.07 * with_.size_lwh[0, 0]) ** 2, rel=1e-6)
    assert with_.size_lwh[0, 0] == pytest.approx(12.0, rel=0.01)
    assert v @ extra @ v == pytest.approx(0.0, abs=1e-12)


def test_a_coasting_track_reports_a_growing_covariance():
    tracker = Tracker(TrackerConfig(max_age_ticks=3, report_coasting_ticks=1))
    for k in range(5):
        state = tracker.update(frame("A", k * 100 * MS, [[0.8 * k, 0.0]]), k * 100 * MS)
    seen = state.xy_cov[0]
    state = tracker.update(ObjectBatch.empty(), 500 * MS)
    assert len(state) == 1 and np.all(np.linalg.eigvalsh(state.xy_cov[0] - seen) > 0)
    assert np.array_equal(state.xy_cov[0], state.xy_cov[0].T)


# ---- bad input -----------------------------------------------------------------------------------
def test_bad_objects_raise_value_errors_naming_the_field():
    ok = {"camera": ["A"], "t_ns": [0], "xy": [[0.0, 0.0]], "yaw": [0.0], "size_lwh": [CAR], "vtype": [0],
          "score": [0.9]}
    ObjectBatch(**ok)
    for field, value, match in [
        ("xy", [[np.nan, 0.0]], "ObjectBatch.xy contains a non-finite"),
        ("xy", [0.0, 0.0], r"ObjectBatch.xy must have shape \(N, 2\)"),
        ("size_lwh", [[4.5, 1.8]], r"ObjectBatch.size_lwh must have shape \(N, 3\)"),
        ("size_lwh", [[4.5, 0.0, 1.5]], "ObjectBatch.size_lwh must be > 0"),
        ("yaw", [0.0, 1.0], "ObjectBatch.yaw has 2 rows"),
        ("score", [1.5], "ObjectBatch.score must be within"),
        ("vtype", [-1], "ObjectBatch.vtype must be within"),
        ("t_ns", [0.5], "ObjectBatch.t_ns has dtype"),
        ("camera", [3], "ObjectBatch.camera"),
    ]:
        with pytest.raises(ValueError, match=match):
            ObjectBatch(**{**ok, field: value})
    with pytest.raises(ValueError, match=r"ObjectBatch\.sources"):
        ObjectBatch(**ok, sources=[])
    for cov, match in [([[[1.0, 0.0], [0.0, -1.0]]], "positive definite"), ([[[1.0, 0.5], [0.0, 1.0]]], "symmetric"),
                       ([[[np.nan, 0.0], [0.0, 1.0]]], "non-finite"), ([[1.0, 0.0]], r"shape \(1, 2, 2\)")]:
        with pytest.raises(ValueError, match=r"ObjectBatch\.xy_cov.*" + match):
            ObjectBatch(**ok, xy_cov=cov)
    two = {"camera": ["A", "A"], "t_ns": [0, 0], "xy": [[0.0, 0.0], [9.0, 0.0]], "yaw": [0.0, 0.0],
           "size_lwh": [CAR, CAR], "vtype": [0, 0], "score": [0.9, 0.8]}
    batch = ObjectBatch(**two, xy_cov=[np.eye(2), 2 * np.eye(2)])
    np.testing.assert_array_equal(batch.select(np.array([1])).xy_cov, [2 * np.eye(2)])
    np.testing.assert_array_equal(ObjectBatch.concat([batch, batch]).xy_cov[2:], batch.xy_cov)
    assert ObjectBatch.concat([batch, ObjectBatch(**ok)]).xy_cov is None  # one without: unknown for all


def test_bad_configs_and_calls_raise_value_errors_naming_the_parameter():
    for make, match in [
        (lambda: TrackerConfig(gate_m=-1.0), "gate_m"),
        (lambda: TrackerConfig(max_age_ticks=1.5), "max_age_ticks"),
        (lambda: TrackerConfig(min_hits=0), "min_hits"),
        (lambda: TrackerConfig(high_score=1.5), "high_score"),
        (lambda: TrackerConfig(bias_share=-0.1), "bias_share"),
        (lambda: TrackerConfig(standing_hits=-1), "standing_hits"),
        (lambda: TrackerConfig(accel_std_mps2=math.nan), "accel_std_mps2"),
        (lambda: TrackerConfig(turn_accel_std_mps2=0.0), "turn_accel_std_mps2"),
        (lambda: TrackerConfig(turn_speed_mps=-1.0), "turn_speed_mps"),
        (lambda: TrackerConfig(turn_speed_mps=math.inf), "turn_speed_mps"),
        (lambda: TrackerConfig(report_coasting_ticks=5), "report_coasting_ticks"),
        (lambda: TrackerConfig(yaw_gain=0.0), "yaw_gain"),
        (lambda: TrackerConfig(relink_s=-1.0), "relink_s"),
        (lambda: TrackerConfig(relink_gate_m=0.0), "relink_gate_m"),
        (lambda: TrackerConfig(yaw_motion_full_mps=1.0), "yaw_motion_full_mps"),
        (lambda: TrackerConfig(yaw_confirm_travel_m=-1.0), "yaw_confirm_travel_m"),
        (lambda: TrackerConfig(yaw_reverse_s=math.nan), "yaw_reverse_s"),
        (lambda: TickConfig(tick_ms=0), "tick_ms"),
        (lambda: TickConfig(watermark_ms=-1), "watermark_ms"),
        (lambda: TickConfig(max_empty_ticks=0), "max_empty_ticks"),
        (lambda: FusionConfig(merge_gate_m=0), "merge_gate_m"),
        (lambda: FusionConfig(out_of_region_weight=2), "out_of_region_weight"),
        (lambda: FusionConfig(split_score=-0.1), "split_score"),
        (lambda: FusionConfig(crowded_sigma_factor=0.5), "crowded_sigma_factor"),
        (lambda: FusionConfig(crowd_ahead_m=(5.0, 2.0)), "crowd_ahead_m"),
        (lambda: FusionConfig(crowd_ahead_m=(1.0, 2.0, 3.0)), "crowd_ahead_m"),
        (lambda: FusionConfig(crowd_across_m=0.0), "crowd_across_m"),
        (lambda: CameraRegion("A", (0.0, math.inf)), "position_xy"),
        (lambda: CameraRegion("A", (0.0, 0.0), polygon_xy=np.zeros((2, 2))), "polygon_xy"),
        (lambda: Fusion([CameraRegion("A", (0.0, 0.0)), CameraRegion("A", (1.0, 0.0))]), "regions"),
        (lambda: Tracker(tracker_id=""), "tracker_id"),
        (lambda: TickBuffer(["A"]).add("A", -1, None, 0.0), "t_capture_ns"),
        (lambda: TickBuffer(["A"]).add("A", 0, None, math.nan), "now_s"),
        (lambda: TickBuffer([""]), "camera"),
    ]:
        with pytest.raises(ValueError, match=match):
            make()
    fusion = Fusion([CameraRegion("A", (0.0, 0.0))])
    with pytest.raises(ValueError, match=r"fuse\.velocity contains"):
        fusion.fuse(frame("A", 0, [[0.0, 0.0]]), 0, np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"fuse\.velocity must have shape \(N, 2\)"):
        fusion.fuse(frame("A", 0, [[0.0, 0.0]]), 0, np.zeros((2, 2)))
    tracker = Tracker()
    tracker.update(ObjectBatch.empty(), 10 * MS)
    with pytest.raises(ValueError, match="t_ns must not go back"):
        tracker.update(ObjectBatch.empty(), 0)
    with pytest.raises(ValueError, match=r"objects\.t_ns must lie within"):
        tracker.update(frame("A", 10 * 10**9, [[0.0, 0.0]]), 20 * MS)


