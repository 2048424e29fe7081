"""fuse_track's fusion with plain arrays: by camera region, along and across each camera's line of sight,
crowded views, extend-only objects, regions."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from fuse_track_fixtures import MS, frame

from services.fuse_track.fusion import (
    CameraRegion,
    Fusion,
    FusionConfig,
    ObjectBatch,
    crowded,
    frame_labels,
    points_in_polygon,
)
from services.fuse_track.tracker import (
    Tracker,
    TrackerConfig,
)
from shared.geo import FOOTPRINT_ROWS
from shared.messages import MAX_ROWS
from shared.position_error import POSITION_SIGMA, position_information


def test_fusion_prefers_the_region_camera_and_keeps_occluded_objects_when_asked():
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))]
    # a scalar weighted mean (the paper's; the default weighs by matrices, below)
    fusion = Fusion(regions, FusionConfig(merge_gate_m=2.5, occlusion_fallback=True, position_sigma=None))
    objects = ObjectBatch.concat([
        frame("A", 0, [[-15.0, 0.0]], score=0.8),
        # B sees A's vehicle (merged, low weight), a second object next to it (dropped: A's region, and A
        # saw something there), and a vehicle in A's region that A missed (kept: occlusion fallback).
        frame("B", 0, [[-14.5, 0.0], [-14.0, 1.2], [-10.0, 8.0]], score=0.8),
    ])
    fused = fusion.fuse(objects, 0)
    assert len(fused) == 2
    assert fused.sources_of(0) == ["A", "B"] and fused.sources_of(1) == ["B"]
    w = FusionConfig().out_of_region_weight  # B's object outside its region counts this much against A's 1
    assert w == 0.5 and fused.xy[0, 0] == pytest.approx((-15.0 * 1.0 + -14.5 * w) / (1.0 + w))
    assert np.allclose(fused.xy[1], [-10.0, 8.0])
    assert fused.camera.tolist() == ["A", "B"]
    # by default (the paper's rule) B's object in A's region that A did not see is dropped
    strict = Fusion(regions, FusionConfig(merge_gate_m=2.5, position_sigma=None)).fuse(objects, 0)
    assert len(strict) == 1 and strict.sources_of(0) == ["A", "B"]
    assert strict.xy[0, 0] == pytest.approx(fused.xy[0, 0])
    lighter = Fusion(regions, FusionConfig(merge_gate_m=2.5, out_of_region_weight=0.1, position_sigma=None))
    assert lighter.fuse(objects, 0).xy[0, 0] == pytest.approx((-15.0 * 1.0 + -14.5 * 0.1) / 1.1)


def test_position_information_is_sharp_across_the_line_from_the_camera_and_blunt_along_it():
    assert POSITION_SIGMA[4] == (45.0, 1.6, 0.58)
    table = np.asarray(POSITION_SIGMA)
    # 45 m east of its camera: along the line is east; 45 m north: along is north; at 40 m halfway between rows
    info = position_information(np.array([[45.0, 0.0], [3.0, 47.0], [40.0, 0.0]]),
                                np.array([[0.0, 0.0], [3.0, 2.0], [0.0, 0.0]]), table)
    assert np.allclose(np.linalg.inv(info[0]), np.diag([1.6**2, 0.58**2]))
    assert np.allclose(np.linalg.inv(info[1]), np.diag([0.58**2, 1.6**2]))
    assert np.allclose(np.linalg.inv(info[2]), np.diag([1.4**2, 0.54**2]))
    # at the camera itself, and beyond the last row: the ends hold
    info = position_information(np.array([[0.0, 0.0], [0.0, -200.0]]), np.zeros((2, 2)), table)
    assert np.allclose(np.linalg.inv(info[0]), np.diag([0.25**2, 0.40**2]))
    assert np.allclose(np.linalg.inv(info[1]), np.diag([0.80**2, 2.5**2]))


def test_two_far_views_from_different_sides_pin_a_vehicle_down():
    """A vehicle 45 m south of camera N and 45 m west of camera E, in a third camera's region that missed it
    (extend-only): N places it 2 m too far south (along its line), E 2 m too far west (along its line), each
    0.1 m off across. Weighted by matrices the fused object lies within 0.25 m; a scalar mean ~1.4 m off."""
    regions = [CameraRegion("N", (0.0, 45.0)), CameraRegion("E", (45.0, 0.0)), CameraRegion("C", (5.0, 5.0))]
    objects = ObjectBatch.concat([frame("N", 0, [[0.1, -2.0]], score=0.8), frame("E", 0, [[-2.0, 0.1]], score=0.6)])
    fused = Fusion(regions, FusionConfig(extend_range_m=50.0)).fuse(objects, 0)
    assert len(fused) == 1 and fused.sources_of(0) == ["E", "N"] and fused.extend_mask().tolist() == [True]
    # x from N's across (0.6 m at 47 m) and E's along (1.66 m), y the other way round, each weighted by its score
    x = (0.8 / 0.604**2 * 0.1 + 0.6 / 1.66**2 * -2.0) / (0.8 / 0.604**2 + 0.6 / 1.66**2)
    y = (0.8 / 1.66**2 * -2.0 + 0.6 / 0.604**2 * 0.1) / (0.8 / 1.66**2 + 0.6 / 0.604**2)
    assert np.allclose(fused.xy[0], [x, y], atol=0.01) and np.linalg.norm(fused.xy[0]) < 0.25
    scalar = Fusion(regions, FusionConfig(extend_range_m=50.0, position_sigma=None)).fuse(objects, 0)
    assert np.linalg.norm(scalar.xy[0]) > 1.3
    # hints that disagree (two tracks' velocities near one vehicle), each along its member's weak direction: the
    # group's time stays within its members' capture times and its position finite
    moving = ObjectBatch.concat([frame("N", 0, [[0.1, -1.5]]), frame("E", 40_000_000, [[-1.5, 0.1]])])
    fused = Fusion(regions, FusionConfig(extend_range_m=50.0)).fuse(moving, 0, np.array([[0.0, 5.0], [5.0, 0.0]]))
    assert len(fused) == 1 and np.isfinite(fused.xy).all() and 0 <= fused.t_ns[0] <= 40_000_000
    # a near view and a far one: the far one's line of sight adds little along it
    objects = ObjectBatch.concat([frame("C", 0, [[0.3, 0.0]], score=0.8), frame("E", 0, [[-2.0, 0.0]], score=0.8)])
    fused = Fusion(regions, FusionConfig()).fuse(objects, 0)
    assert len(fused) == 1 and 0.0 < fused.xy[0, 0] < 0.3


def test_crowded_objects_have_another_of_their_frame_just_in_front():
    cam = np.zeros((7, 2))
    xy = np.array([
        [10.0, 0.0],  # nothing nearer on its line
        [15.0, 0.5],  # 5 m behind the first, 0.5 m off its line: crowded
        [20.0, 3.5],  # the second 5.4 m in front, 2.1 m off its line: crowded
        [10.5, 0.0],  # 0.5 m behind the first: too close to be in front (one vehicle, two peaks); not crowded
        [20.0, -5.5],  # the second 6.4 m in front but 4.5 m off its line: not crowded
        [30.0, 0.0],  # the nearest in front 10 m nearer: not crowded
        [16.0, 0.0],  # another camera's frame: the first is not its neighbour
    ])
    frames = np.array([0, 0, 0, 0, 0, 0, 1])
    got = crowded(xy, cam, frames, (1.0, 8.0), 4.0)
    assert got.tolist() == [False, True, True, False, False, False, False]
    assert crowded(xy, cam, frames, (1.0, 8.0), 4.0, block=2).tolist() == got.tolist()  # in blocks, the same
    assert not crowded(xy[:1], cam[:1], frames[:1], (1.0, 8.0), 4.0).any()
    assert crowded(xy[:2], cam[:2], np.array([3, 3]), (1.0, 8.0), 0.2).tolist() == [False, False]  # 0.33 m across


def test_a_crowded_view_counts_less_in_a_fused_position():
    """A vehicle 20 m east of camera A and 20 m north of camera B: A sees another vehicle 4 m in front of it and
    places this one 1 m off across its line; B's view is clear and exact. The crowded member's sigmas count double."""
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (0.0, -20.0)), CameraRegion("C", (1.0, 1.0))]
    objects = ObjectBatch.concat([frame("A", 0, [[0.0, 1.0], [-4.0, 0.0]]), frame("B", 0, [[0.0, 0.0]])])
    labels = frame_labels(objects.camera, objects.t_ns)
    assert crowded(objects.xy[:2], np.array([[-20.0, 0.0]] * 2), labels[:2], (1.0, 8.0), 4.0).tolist() == [True, False]
    plain = Fusion(regions, FusionConfig(crowded_sigma_factor=1.0, occlusion_fallback=True)).fuse(objects, 0)
    fused = Fusion(regions, FusionConfig(occlusion_fallback=True)).fuse(objects, 0)
    assert FusionConfig().crowded_sigma_factor == 2.0
    i, j = (int(np.argmin(np.linalg.norm(f.xy - [0.0, 0.5], axis=1))) for f in (plain, fused))
    assert plain.sources_of(i) == fused.sources_of(j) == ["A", "B"]
    # y: A's information across its line against B's along its own (about as sharp at 20 m): about an even split
    # without the factor, A's share a quarter as large with it
    info = position_information(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[-20.0, 0.0], [0.0, -20.0]]),
                                np.asarray(POSITION_SIGMA))
    a_y, b_y = info[0, 1, 1], info[1, 1, 1]
    assert plain.xy[i, 1] == pytest.approx(a_y / (a_y + b_y), abs=0.01) and 0.45 < plain.xy[i, 1] < 0.55
    assert fused.xy[j, 1] == pytest.approx(a_y / 4 / (a_y / 4 + b_y), abs=0.01) and fused.xy[j, 1] < 0.25
    assert np.allclose([plain.xy[i, 0], fused.xy[j, 0]], 0.0, atol=0.01)


def test_fusion_keeps_an_object_its_region_camera_missed_as_extend_only_within_range():
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))]
    fusion = Fusion(regions, FusionConfig(merge_gate_m=2.5, extend_range_m=40.0))
    objects = ObjectBatch.concat([
        frame("A", 0, [[-15.0, 0.0]], score=0.8),
        # B: A's vehicle (merged), one in A's region that A missed 31 m from B (extend-only), one 52 m from B
        # (beyond the range: dropped), and one in its own region (an ordinary object)
        frame("B", 0, [[-14.5, 0.0], [-10.0, 8.0], [-32.0, 0.0], [15.0, 0.0]], score=0.8),
    ])
    fused = fusion.fuse(objects, 0)
    assert [fused.sources_of(i) for i in range(len(fused))] == [["A", "B"], ["B"], ["B"]]
    assert np.allclose(fused.xy[1:], [[15.0, 0.0], [-10.0, 8.0]])
    assert fused.extend_mask().tolist() == [False, False, True]
    # a fallback object joined by an ordinary one of a camera without a region is ordinary
    mixed = fusion.fuse(ObjectBatch.concat([objects, frame("C", 0, [[-10.5, 8.0]])]), 0)
    assert mixed.extend_mask().tolist() == [False, False, False] and mixed.sources_of(2) == ["B", "C"]
    # range 0 is the paper's rule; the full occlusion fallback keeps it as an ordinary object
    assert len(Fusion(regions, FusionConfig(merge_gate_m=2.5)).fuse(objects, 0)) == 2
    full = Fusion(regions, FusionConfig(merge_gate_m=2.5, occlusion_fallback=True, extend_range_m=40.0))
    assert not full.fuse(objects, 0).extend_mask().any() and len(full.fuse(objects, 0)) == 4
    with pytest.raises(ValueError, match="extend_range_m"):
        FusionConfig(extend_range_m=-1.0)


def test_extend_only_objects_extend_a_confirmed_track_but_never_start_one():
    tracker = Tracker(TrackerConfig(min_hits=2, max_age_ticks=3, report_coasting_ticks=0))

    def hidden(t_ns: int, xy) -> ObjectBatch:  # B's objects in A's region, kept by the fusion as extend-only
        b = frame("B", t_ns, xy, score=0.95)
        return ObjectBatch(b.camera, b.t_ns, b.xy, b.yaw, b.size_lwh, b.vtype, b.score,
                           extend_only=np.ones(len(b), bool))

    # extend-only objects alone never start a track, whatever their score or how long they last
    for k in range(5):
        assert len(tracker.update(hidden(k * 100 * MS, [[5.0, 0.0]]), k * 100 * MS)) == 0
    assert len(tracker) == 0
    # a confirmed track goes on with them while its region's camera misses the vehicle, under its id
    ids = []
    for k in range(5, 15):
        t = k * 100 * MS
        seen = frame("A", t, [[5.0, 0.0]]) if k < 8 else hidden(t, [[5.0, 0.0]])
        ids.append(tracker.update(seen, t).id.tolist())
    assert ids[0] == [] and all(i == ids[1] for i in ids[1:]) and len(ids[1]) == 1
    # an ordinary object on the track takes it before an extend-only one does (which then starts nothing)
    t = 15 * 100 * MS
    state = tracker.update(ObjectBatch.concat([hidden(t, [[5.0, 0.0]]), frame("A", t, [[5.2, 0.0]])]), t)
    assert state.id.tolist() == ids[1] and state.xy[0, 0] > 5.0 and len(tracker) == 1
    b = hidden(t, [[5.0, 0.0], [9.0, 0.0]])
    with pytest.raises(ValueError, match="extend_only"):
        ObjectBatch(b.camera, b.t_ns, b.xy, b.yaw, b.size_lwh, b.vtype, b.score, extend_only=np.array([1, 0]))


def test_fusion_aligns_reversed_headings_and_brings_objects_to_a_common_time():
    fusion = Fusion([CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))])
    # One vehicle at 15 m/s east seen by A at t=-40 ms and by B at t=+40 ms with its heading reversed.
    objects = ObjectBatch.concat([frame("A", -40 * MS, [[-0.6 - 0.1, 0.0]], yaw=0.1),
                                  frame("B", 40 * MS, [[0.6 + 0.1, 0.0]], yaw=math.pi)])
    velocity = np.array([[15.0, 0.0], [15.0, 0.0]])
    fused = fusion.fuse(objects, 0, velocity)
    assert len(fused) == 1 and fused.t_ns[0] == 0
    assert np.allclose(fused.xy[0], [0.0, 0.0])
    assert fused.yaw[0] == pytest.approx(0.05)
    without = fusion.fuse(objects, 0)  # no hints: 1.4 m apart is still within the gate, position averaged
    assert len(without) == 1


def test_a_far_cameras_heading_and_size_count_less_in_the_fused_ones():
    """A vehicle 20 m from camera A (its region's) and 40 m from B: B's heading and size weigh 0.5 (out of its
    region) over 1 + (40 / 20)^2 against A's 1 over 1 + 1 with yaw_size_range_m 20 m; with yaw_size_range_m 0 as in the
    position (0.5 and 1), which stays the same either way."""
    cameras = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (40.0, 0.0))]

    def seen(camera: str, yaw: float, length: float) -> ObjectBatch:
        return ObjectBatch.from_frame(camera, 0, np.zeros((1, 2)), np.array([yaw]), np.array([[length, 1.8, 1.5]]),
                                      np.zeros(1, np.int64), np.array([0.9]))

    objects = ObjectBatch.concat([seen("A", 0.0, 4.5), seen("B", 0.3, 6.0)])

    def circular_mean(w_a: float, w_b: float) -> float:
        return math.atan2(w_b * math.sin(0.3), w_a + w_b * math.cos(0.3))

    ranged = Fusion(cameras).fuse(objects, 0)
    plain = Fusion(cameras, FusionConfig(yaw_size_range_m=0.0)).fuse(objects, 0)
    assert len(ranged) == len(plain) == 1
    assert ranged.yaw[0] == pytest.approx(circular_mean(1 / 2, 0.5 / 5))
    assert plain.yaw[0] == pytest.approx(circular_mean(1.0, 0.5))
    assert ranged.size_lwh[0, 0] == pytest.approx((4.5 / 2 + 6.0 * 0.5 / 5) / (1 / 2 + 0.5 / 5))
    assert plain.size_lwh[0, 0] == pytest.approx((4.5 + 6.0 * 0.5) / 1.5)
    np.testing.assert_allclose(ranged.size_lwh[0, 1:], [1.8, 1.5])
    np.testing.assert_allclose(ranged.xy, plain.xy)
    with pytest.raises(ValueError, match="yaw_size_range_m must be >= 0"):
        FusionConfig(yaw_size_range_m=-1.0)


def test_fusion_of_an_empty_tick_and_of_unknown_cameras():
    fusion = Fusion([CameraRegion("A", (0.0, 0.0))])
    assert len(fusion.fuse(ObjectBatch.empty(), 0)) == 0
    objects = ObjectBatch.concat([frame("X", 0, [[1.0, 1.0]]), frame("Y", 0, [[1.5, 1.0]])])
    fused = fusion.fuse(objects, 0)  # cameras without a region: fallback objects, merged by the gate
    assert len(fused) == 1 and fused.sources_of(0) == ["X", "Y"]


def test_polygon_and_range_regions():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    pts = np.array([[5, 5], [11, 5], [-1, -1], [9.9, 0.1]])
    assert points_in_polygon(pts, square).tolist() == [True, False, False, True]
    fusion = Fusion([CameraRegion("P", (5.0, 5.0), polygon_xy=square), CameraRegion("V1", (-20.0, 0.0)),
                     CameraRegion("V2", (20.0, 0.0), max_range_m=15.0)])
    inside = fusion.contains(np.array([[5.0, 5.0], [-5.0, 0.0], [30.0, 0.0], [1.0, 0.0]]))
    # (5, 5) is nearer V2 than V1 but 15.8 m from it; (1, 0) lies on the square's edge.
    assert inside.tolist() == [[True, False, False], [False, True, False], [False, False, True],
                               [True, False, False]]


def test_frame_labels_number_camera_and_time_pairs_in_sorted_order():
    from services.fuse_track.fusion import frame_labels

    rng = np.random.default_rng(0)
    for _ in range(100):
        n = int(rng.integers(1, 60))
        cam = rng.choice(np.array(["NE", "NW", "SE", "SW"]), n)
        t = rng.choice(np.array([5, 3, 9, 10**18, 2**62], np.int64), n)
        _, code = np.unique(cam, return_inverse=True)
        _, want = np.unique(np.stack([code.reshape(-1), t]), axis=1, return_inverse=True)
        assert (frame_labels(cam, t) == want.reshape(-1)).all()
    assert frame_labels(np.array(["B", "A", "B"]), np.array([2, 7, 1])).tolist() == [2, 0, 1]
    assert frame_labels(np.zeros(0, "U1"), np.zeros(0, np.int64)).shape == (0,)


def test_select_and_concat_keep_every_column_and_the_sources():
    a = ObjectBatch.from_frame("A", 5, np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([0.1, 0.2]),
                               np.ones((2, 3)), np.array([0, 2]), np.array([0.5, 0.9]))
    b = ObjectBatch(np.array(["B"]), np.array([7]), np.array([[9.0, 9.0]]), np.array([0.3]), np.full((1, 3), 2.0),
                    np.array([1]), np.array([0.4]), sources=[["B", "C"]])
    ab = ObjectBatch.concat([a, ObjectBatch.empty(), b])
    assert ab.camera.tolist() == ["A", "A", "B"] and ab.t_ns.tolist() == [5, 5, 7] and ab.t_ns.dtype == np.int64
    assert ab.xy.tolist() == [[1.0, 2.0], [3.0, 4.0], [9.0, 9.0]] and ab.size_lwh.shape == (3, 3)
    assert [ab.sources_of(i) for i in range(3)] == [["A"], ["A"], ["B", "C"]]
    last = ab.select(np.array([False, True, True]))
    assert last.vtype.tolist() == [2, 1] and last.score.tolist() == [0.9, 0.4] and last.yaw.tolist() == [0.2, 0.3]
    assert [last.sources_of(i) for i in range(2)] == [["A"], ["B", "C"]]
    assert ObjectBatch.concat([a, a]).sources is None and len(a.select(np.zeros(0, int))) == 0
    assert ab.extend_only is None
    e = ObjectBatch(b.camera, b.t_ns, b.xy, b.yaw, b.size_lwh, b.vtype, b.score, extend_only=np.array([True]))
    ae = ObjectBatch.concat([a, e])
    assert ae.extend_mask().tolist() == [False, False, True]
    assert ae.select(np.array([2, 0])).extend_mask().tolist() == [True, False]


def test_a_camera_down_hands_its_region_to_the_nearest_camera_up():
    """Three cameras in a row; A goes silent. While it delivered (and for handover_s after), B's view of a vehicle in
    A's region is extend-only; once A is down, A's ground is B's (its nearest camera up), where B's objects start
    groups as in its own region; C's region is unchanged. A's next frame takes its region back. A camera never
    heard from counts as down from handover_s after the first tick; without `delivered`, or with handover_s 0, every
    camera is up."""
    regions = [CameraRegion("A", (-40.0, 0.0)), CameraRegion("B", (0.0, 0.0)), CameraRegion("C", (40.0, 0.0))]
    fusion = Fusion(regions, FusionConfig(extend_range_m=50.0, handover_s=1.0))
    def in_a(t_ns: int) -> ObjectBatch:
        return frame("B", t_ns, [[-30.0, 1.0]])  # B's object 30 m west, in A's region

    s = 1_000_000_000
    assert fusion.fuse(in_a(0), 0, delivered=["A", "B", "C"]).extend_mask().tolist() == [True]
    assert fusion.fuse(in_a(s), s, delivered=["B", "C"]).extend_mask().tolist() == [True]  # 1 s: not yet
    assert fusion.down == frozenset()
    t = s + 100 * MS
    assert fusion.fuse(in_a(t), t, delivered=["B", "C"]).extend_mask().tolist() == [False]
    assert fusion.down == {"A"}
    owners = fusion.contains(np.array([[-30.0, 1.0], [-25.0, 0.0], [30.0, 0.0]]), np.array([True, False, False]))
    assert owners.tolist() == [[False, True, False], [False, True, False], [False, False, True]]
    t = s + 200 * MS
    assert fusion.fuse(in_a(t), t, delivered=["A", "B", "C"]).extend_mask().tolist() == [True]  # A is back
    assert fusion.down == frozenset()
    fresh = Fusion(regions, FusionConfig(extend_range_m=50.0, handover_s=1.0))  # A never heard from
    assert fresh.fuse(in_a(0), 0, delivered=["B", "C"]).extend_mask().tolist() == [True] and fresh.down == set()
    assert fresh.fuse(in_a(t), t, delivered=["B", "C"]).extend_mask().tolist() == [False] and fresh.down == {"A"}
    assert fresh.fuse(in_a(t), t).extend_mask().tolist() == [True]  # without `delivered`: all up
    off = Fusion(regions, FusionConfig(extend_range_m=50.0, handover_s=0.0))
    assert off.fuse(in_a(0), 0, delivered=["B"]).extend_mask().tolist() == [True]
    with pytest.raises(ValueError, match="handover_s must be >= 0"):
        FusionConfig(handover_s=-1.0)


def test_the_cameras_watch_starts_again_when_the_clocks_go_back():
    """A recording played again from its start (capture times back by a minute): a camera that delivered a minute
    "later" is not taken to be up until then; the watch starts again, every camera given handover_s."""
    regions = [CameraRegion("A", (-40.0, 0.0)), CameraRegion("B", (0.0, 0.0))]
    fusion = Fusion(regions, FusionConfig(extend_range_m=50.0, handover_s=1.0))
    s = 1_000_000_000
    fusion.fuse(frame("B", 60 * s, [[-30.0, 1.0]]), 60 * s, delivered=["A", "B"])
    assert fusion.fuse(frame("B", 0, [[-30.0, 1.0]]), 0, delivered=["B"]).extend_mask().tolist() == [True]
    late = 2 * s
    assert fusion.fuse(frame("B", late, [[-30.0, 1.0]]), late, delivered=["B"]).extend_mask().tolist() == [False]
    assert fusion.down == {"A"}


def test_another_cameras_peak_on_a_long_vehicle_is_dropped_and_a_car_beside_it_is_not():
    """An 11 m bus heading east, seen by A (its object at the bus's near end, long) and by B, which reads its far end
    as a car 5 m away (beyond the merge gate); a car beside that end, 3.5 m across the bus's axis, is a car of its
    own. The car-sized peak inside the bus's footprint (times long_footprint) goes, the car beside it stays; with
    long_vehicle_m 0 both stay, and a car-sized object never removes anything."""
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))]
    bus = ObjectBatch.from_frame("A", 0, np.array([[-2.0, 0.0]]), np.zeros(1), np.array([[11.0, 2.6, 3.2]]),
                                 np.array([3]), np.array([0.8]))
    objects = ObjectBatch.concat([bus, frame("B", 0, [[3.0, 0.2], [3.0, 3.5]], score=0.7)])
    config = FusionConfig(position_sigma=None, merge_gate_m=3.0)
    fused = Fusion(regions, config).fuse(objects, 0)
    assert config.long_vehicle_m == 7.0 and config.long_footprint == 1.4
    assert sorted(map(tuple, np.round(fused.xy, 1).tolist())) == [(-2.0, 0.0), (3.0, 3.5)]
    off = Fusion(regions, FusionConfig(position_sigma=None, merge_gate_m=3.0, long_vehicle_m=0.0)).fuse(objects, 0)
    assert len(off) == 3
    cars = ObjectBatch.concat([frame("A", 0, [[-2.0, 0.0]], score=0.8), frame("B", 0, [[0.5, 0.0]], score=0.7)])
    assert len(Fusion(regions, FusionConfig(position_sigma=None, merge_gate_m=2.0)).fuse(cars, 0)) == 2
    with pytest.raises(ValueError, match="long_footprint must be > 0"):
        FusionConfig(long_footprint=0.0)


def test_the_longest_object_acts_first_and_a_dropped_one_drops_nothing():
    """A 14 m object, a 9 m one inside its footprint, and a car inside the 9 m one's footprint only: the 14 m one
    drops the 9 m one, which then drops nothing, so the car stays, whatever their scores."""
    regions = [CameraRegion("A", (-20.0, 0.0)), CameraRegion("B", (20.0, 0.0))]

    def one(camera, x, length, score):
        return ObjectBatch.from_frame(camera, 0, np.array([[x, 0.0]]), np.zeros(1), np.array([[length, 2.5, 3.0]]),
                                      np.array([2]), np.array([score]))

    for s14, s9 in ((0.95, 0.9), (0.5, 0.9)):
        chain = ObjectBatch.concat([one("A", -8.0, 14.0, s14), one("B", 1.0, 9.0, s9), one("B", 6.0, 4.5, 0.4)])
        kept = Fusion(regions, FusionConfig(position_sigma=None, merge_gate_m=2.0)).fuse(chain, 0)
        assert sorted(np.round(kept.xy[:, 0], 1).tolist()) == [-8.0, 6.0], (s14, s9)


def test_a_tick_whose_only_object_is_a_low_scoring_one_dropped_fuses_to_nothing():
    """With two score pools (`split_score`, the site's `high_score`) a lone low-scoring object in another camera's
    region and beyond the extend range groups with nothing: no object, not an IndexError that stopped fuse_track."""
    regions = [CameraRegion("A", (0.0, 0.0)), CameraRegion("B", (100.0, 0.0))]
    fusion = Fusion(regions, FusionConfig(split_score=0.3, extend_range_m=50.0))
    assert len(fusion.fuse(frame("A", 0, [[90.0, 0.0]], score=0.25), 0)) == 0
    both = ObjectBatch.concat([frame("A", 0, [[90.0, 0.0]], score=0.25), frame("B", 0, [[95.0, 0.0]], score=0.9)])
    fused = fusion.fuse(both, 0)
    assert len(fused) == 1 and fused.camera.tolist() == ["B"]


def test_the_long_vehicle_rule_in_blocks_is_the_whole_matrix_rule_and_its_memory_is_bounded():
    """Fused objects of many lengths, crowded: a block of FOOTPRINT_ROWS footprints at a time drops exactly what
    the N x N rule dropped; a tick of MAX_ROWS long objects on one spot no longer needs N x N float64 matrices
    (~650 MB)."""
    fusion = Fusion([CameraRegion("A", (0.0, 0.0))], FusionConfig())
    lmin, scale = fusion.config.long_vehicle_m, fusion.config.long_footprint

    def whole_matrix_rule(fused: ObjectBatch) -> np.ndarray:
        half = 0.5 * scale * fused.size_lwh[:, :2]
        d = fused.xy[None, :, :] - fused.xy[:, None, :]
        c, s = np.cos(fused.yaw)[:, None], np.sin(fused.yaw)[:, None]
        inside = (np.abs(d[..., 0] * c + d[..., 1] * s) <= half[:, :1]) & (
            np.abs(d[..., 1] * c - d[..., 0] * s) <= half[:, 1:])
        length = fused.size_lwh[:, 0]
        long_ = np.flatnonzero(length >= lmin)
        drop = np.zeros(len(fused), bool)
        for i in long_[np.lexsort((-fused.score[long_], -length[long_]))]:
            if not drop[i]:
                drop |= inside[i] & (length < length[i])
        return np.flatnonzero(~drop)

    rng = np.random.default_rng(11)
    for trial in range(6):
        n = int(rng.integers(2, 3 * FOOTPRINT_ROWS))
        fused = ObjectBatch.from_frame("A", 0, rng.uniform(-40, 40, (n, 2)), rng.uniform(-np.pi, np.pi, n),
                                       np.column_stack([rng.choice([4.5, 7.0, 9.0, 12.0, 14.0], n),
                                                        np.full(n, 2.5), np.full(n, 3.0)]),
                                       np.zeros(n, int), np.round(rng.uniform(0.3, 1, n), 1))
        kept = fusion._under_long_vehicles(fused)
        assert kept.xy.tolist() == fused.xy[whole_matrix_rule(fused)].tolist(), trial
    n = MAX_ROWS
    crowd = ObjectBatch.from_frame("A", 0, rng.uniform(-3, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n),
                                   np.column_stack([rng.uniform(7, 15, n), np.full(n, 2.5), np.full(n, 3.0)]),
                                   np.zeros(n, int), rng.uniform(0.3, 1, n))
    tracemalloc.start()
    try:
        kept = fusion._under_long_vehicles(crowd)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(kept) < n and peak < 64e6, (len(kept), peak)


def test_fusion_without_regions_keeps_every_object():
    """No regions (the constructor's default): every camera is one without a region, so its objects are kept, and
    merged by the gate."""
    objects = ObjectBatch.concat([frame("A", 0, [[0.0, 0.0]]), frame("B", 0, [[10.0, 0.0], [0.5, 0.0]])])
    fused = Fusion().fuse(objects, 0)
    assert len(fused) == 2 and sorted(map(tuple, fused.xy.round(6).tolist())) == [(0.25, 0.0), (10.0, 0.0)]
    assert sorted(fused.sources_of(i) for i in range(2)) == [["A", "B"], ["B"]]


def test_an_object_behind_the_camera_is_never_in_front():
    """Two objects on either side of their camera's pole, 5 m east and 2 m west of it: along the east one's line the
    west one lies 7 m nearer, but behind the camera, not between it and its camera; and the other way round."""
    got = crowded(np.array([[5.0, 0.0], [-2.0, 0.0]]), np.zeros((2, 2)), np.zeros(2, int), (1.0, 8.0), 4.0)
    assert got.tolist() == [False, False]
    # one on the camera's side, 2 m from it, 3 m in front of the one 5 m east: crowded
    got = crowded(np.array([[5.0, 0.0], [2.0, 0.5]]), np.zeros((2, 2)), np.zeros(2, int), (1.0, 8.0), 4.0)
    assert got.tolist() == [True, False]


def test_an_out_of_region_members_error_counts_as_its_weight_says():
    """out_of_region_weight is the variance ratio of in- and out-of-region localization: the fused covariance takes
    an out-of-region member's error as 1 / out_of_region_weight times its range model's, as the mean weighs it."""
    regions = [CameraRegion("A", (-30.0, 0.0)), CameraRegion("B", (0.0, 50.0))]
    config = FusionConfig(extend_range_m=60.0)
    rw = config.out_of_region_weight
    p = np.array([[0.0, 0.0]])  # in A's region, 30 m from A; B sees it from 50 m north, outside its region
    table = np.asarray(POSITION_SIGMA)
    info_a = position_information(p, np.array([[-30.0, 0.0]]), table)[0]
    info_b = position_information(p, np.array([[0.0, 50.0]]), table)[0]
    both = Fusion(regions, config).fuse(ObjectBatch.concat([frame("A", 0, p), frame("B", 0, p)]), 0)
    assert len(both) == 1 and both.sources_of(0) == ["A", "B"]
    np.testing.assert_allclose(both.xy_cov[0], np.linalg.inv(info_a + rw * info_b))
    alone = Fusion(regions, config).fuse(frame("B", 0, p), 0)  # extend-only: twice its in-region covariance
    assert alone.extend_mask().tolist() == [True]
    np.testing.assert_allclose(alone.xy_cov[0], np.linalg.inv(rw * info_b))
    # in its own region, its range model's alone
    np.testing.assert_allclose(Fusion(regions, config).fuse(frame("A", 0, p), 0).xy_cov[0], np.linalg.inv(info_a))


def test_the_nearest_views_heading_sets_the_axis_and_the_heaviest_member_which_way_it_points():
    """A car heading east seen 10 m and 12 m from cameras A and B at 5 and -5 deg, and from 60 m by C, the member
    heaviest in position weight (score 0.95 at 0.5 out of its region against A's 0.4 in its own): C's heading counts
    least (its range), so the others are not aligned to its axis (at 90 deg from it they would fall on either side of
    the flip and cancel, leaving C's heading); which way the fused heading points is still C's."""
    regions = [CameraRegion("A", (-10.0, 0.0)), CameraRegion("B", (0.0, -12.0)), CameraRegion("C", (60.0, 0.0))]
    p = [[0.0, 0.0]]

    def fused_yaw_deg(c_deg: float) -> float:
        objects = ObjectBatch.concat([frame("A", 0, p, yaw=math.radians(5), score=0.4),
                                      frame("B", 0, p, yaw=math.radians(-5), score=0.9),
                                      frame("C", 0, p, yaw=math.radians(c_deg), score=0.95)])
        fused = Fusion(regions).fuse(objects, 0)
        assert len(fused) == 1 and fused.camera.tolist() == ["C"]  # the camera that of the heaviest member
        return math.degrees(fused.yaw[0])

    yaw = fused_yaw_deg(90.0)  # aligned to C's axis, A's and B's headings fell either side of the flip: 95.9 deg
    assert min(abs(yaw), 180 - abs(yaw)) < 10  # east-west (which way: a toss-up, C's heading at 94 deg from both)
    assert abs(fused_yaw_deg(80.0)) < 10  # east, the way C's heading points
    assert abs(abs(fused_yaw_deg(170.0)) - 180) < 10  # C sees it reversed: the fused heading points its way
