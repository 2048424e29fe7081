"""localize without transport: the footprint overlap rule and the Objects message it shapes."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.masks import LookupMasks
from services.localize.__main__ import objects_message
from services.localize.lift import (
    MERGE_MAX_LENGTH_M,
    GroundLookup,
    footprint_groups,
    footprint_rule,
    merge_along,
)
from shared.messages import Detections
from shared.settings import LocalizeSettings

CAR = (4.5, 1.8, 1.5)


def _drop(xy, yaw, size, score, scale=1.5):
    n = len(xy)
    kept, _, _ = footprint_rule(np.asarray(xy, float), np.full(n, yaw) if np.ndim(yaw) == 0 else np.asarray(yaw, float),
                                np.asarray(size, float).reshape(-1, 3) if np.ndim(size) > 1 else np.tile(size, (n, 1)),
                                np.asarray(score, float), scale, False)
    drop = np.ones(n, bool)
    drop[kept] = False
    return drop.tolist()


def test_a_second_peak_on_the_same_vehicle_is_dropped_and_the_higher_score_kept():
    # a truck read as two cars, one on each half: 3 m apart along its length (east)
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.4, 0.7]) == [True, False]
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.7, 0.4]) == [False, True]
    # the footprint follows the yaw: the same pair along a north-facing vehicle
    assert _drop([[0, 0], [0, 3]], np.pi / 2, CAR, [0.7, 0.4]) == [False, True]


def test_vehicles_that_only_stand_close_are_all_kept():
    assert _drop([[0, 0], [0, 3.5]], 0.0, CAR, [0.9, 0.5]) == [False, False]  # side by side, two lanes
    assert _drop([[0, 0], [7.0, 0]], 0.0, CAR, [0.9, 0.5]) == [False, False]  # queued, bumper to bumper
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.9, 0.5], scale=0.0) == [False, False]  # the rule switched off
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.9, 0.5], scale=1.2) == [False, False]  # 3 m > 1.2 * 4.5 / 2


def test_either_footprint_counts_and_suppression_is_greedy():
    # a bus (12 m) scored lower than a car-sized peak 4 m along it: the car's footprint does not hold the bus's
    # point, the bus's holds the car's; one vehicle, the higher score kept
    assert _drop([[0, 0], [4, 0]], 0.0, [[4.5, 1.8, 1.5], [12.0, 2.5, 3.2]], [0.8, 0.5]) == [False, True]
    # a chain of peaks 3 m apart: the middle one is dropped by the best, the far one survives the dropped one
    assert _drop([[0, 0], [3, 0], [6, 0]], 0.0, CAR, [0.9, 0.5, 0.4]) == [False, True, False]
    assert _drop([], 0.0, CAR, []) == []


def test_objects_without_a_finite_position_yaw_or_size_are_left_alone():
    xy = [[0, 0], [3, 0], [np.nan, 0]]
    assert _drop(xy, [0.0, np.nan, 0.0], CAR, [0.9, 0.5, 0.4]) == [False, False, False]
    assert _drop([[0, 0], [3, 0]], 0.0, [[np.nan, 1.8, 1.5], CAR], [0.9, 0.5]) == [False, False]


def test_settings_default_and_refuse_a_negative_scale():
    assert LocalizeSettings().footprint_overlap == 1.4
    with pytest.raises(ValueError, match="footprint_overlap"):
        LocalizeSettings(footprint_overlap=-1)


def _masks(w: int = 64, h: int = 48, m_per_px: float = 0.25) -> GroundLookup:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([u * m_per_px, -v * m_per_px], axis=2)  # east along u, north up the image
    meta = {"geo_origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0}}
    return GroundLookup(LookupMasks(42 + xy[..., 1] / 111e3, -83 + xy[..., 0] / 82e3, xy.astype(np.float32),
                                    np.ones((h, w), bool), meta))


def _cars_heading_east(u: list[float], score: list[float]) -> Detections:
    """Car-sized detections heading east at pixel columns u (row 20; 4 px per metre), types 0, 1, 2, ..."""
    f4, n = np.float32, len(u)
    return Detections(site="s", camera="C1", seq=1, t_capture_ns=5, width=64, height=48, infer_ms=1.0,
                      score=np.array(score, f4), uv=np.array([[x, 20] for x in u], f4),
                      box=np.zeros((n, 4), f4), heading_uv=np.tile(np.array([1, 0], f4), (n, 1)),
                      size_lwh=np.tile(np.array(CAR, f4), (n, 1)), vtype=np.arange(n, dtype=np.int8))


def _two_peaks_and_a_car() -> Detections:
    """Three car-sized detections heading east: two 12 px = 3 m apart on one vehicle (x 2.5 and 5.5 m), one 40 px
    = 10 m further."""
    return _cars_heading_east([10, 22, 50], [0.5, 0.8, 0.6])


def test_objects_message_drops_the_overlapping_detection_and_keeps_the_columns_aligned():
    det, masks = _two_peaks_and_a_car(), _masks()
    kept = objects_message(det, masks, 6.0, 1.5, False)
    assert kept.score.tolist() == pytest.approx([0.8, 0.6])
    assert kept.vtype.tolist() == [1, 2]
    np.testing.assert_allclose(kept.xy, [[5.5, -5.0], [12.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.uv, [[22, 20], [50, 20]])
    assert len(objects_message(det, masks, 6.0, 0.0, False)) == 3
    assert len(objects_message(det, masks, 6.0, 0.0, True)) == 3  # no rule, nothing to merge


def test_objects_message_merges_the_peaks_of_one_vehicle_along_its_axis():
    det, masks = _two_peaks_and_a_car(), _masks()  # a long vehicle read as two car-sized peaks, and a car
    kept = objects_message(det, masks, 6.0, 1.5, True)
    assert kept.score.tolist() == pytest.approx([0.8, 0.6])
    # the span of both peaks: 0.25 to 7.75 m east, its middle 4.0 m, 7.5 m long; the car untouched
    np.testing.assert_allclose(kept.xy, [[4.0, -5.0], [12.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.size_lwh, [[7.5, 1.8, 1.5], CAR], atol=1e-6)
    np.testing.assert_allclose(kept.uv, [[22, 20], [50, 20]])  # the pixel stays the detection's
    # latitude/longitude follow the moved point (1.5 m west of the kept peak)
    dropped = objects_message(det, masks, 6.0, 1.5, False)
    assert kept.latlon[1].tolist() == dropped.latlon[1].tolist()
    assert kept.latlon[0, 0] == pytest.approx(dropped.latlon[0, 0], abs=1e-9)
    assert kept.latlon[0, 1] < dropped.latlon[0, 1]
    assert (dropped.latlon[0, 1] - kept.latlon[0, 1]) * 111320 * np.cos(np.radians(42)) == pytest.approx(1.5, rel=1e-2)


def _merge(xy, yaw, size, score, scale=1.5):
    n = len(xy)
    xy, yaw = np.asarray(xy, float), np.full(n, yaw) if np.ndim(yaw) == 0 else np.asarray(yaw, float)
    size = np.asarray(size, float).reshape(-1, 3) if np.ndim(size) > 1 else np.tile(size, (n, 1))
    groups = footprint_groups(xy, yaw, size, np.asarray(score, float), scale)
    mxy, msize = merge_along(xy, yaw, size, np.asarray(score, float), groups)
    return sorted(groups), mxy, msize


def test_merge_spans_the_aligned_peaks_and_leaves_the_rest():
    # three peaks along a bus (east), 3 m apart: the best (middle) takes in both, 10.5 m long centred on it
    kept, xy, size = _merge([[3, 0], [0, 0], [-3, 0]], 0.0, CAR, [0.4, 0.9, 0.5], scale=2.0)
    assert kept == [1]
    np.testing.assert_allclose(xy[1], [0.0, 0.0], atol=1e-12)
    assert size[1, 0] == pytest.approx(10.5)
    assert size[1, 1:].tolist() == list(CAR[1:])
    # a peak off the axis (1.5 m across) or turned (45 deg) is dropped but not taken in
    for xy2, yaw2 in (([[0, 0], [2, 1.5]], [0.0, 0.0]), ([[0, 0], [3, 0]], [0.0, np.pi / 4])):
        kept, xy, size = _merge(xy2, yaw2, CAR, [0.9, 0.5], scale=2.0)
        assert kept == [0]
        np.testing.assert_allclose(xy[0], [0, 0])
        assert size[0, 0] == pytest.approx(CAR[0])
    # a reversed heading is the same axis: merged
    kept, xy, size = _merge([[0, 0], [3, 0]], [0.0, np.pi], CAR, [0.9, 0.5])
    np.testing.assert_allclose(xy[0], [1.5, 0])
    assert size[0, 0] == pytest.approx(7.5)


def test_merge_never_grows_past_a_long_bus_and_changes_nothing_alone():
    big = (14.0, 2.5, 3.2)
    kept, xy, size = _merge([[0, 0], [6, 0]], 0.0, big, [0.9, 0.5])  # the union would be 20 m
    assert kept == [0] and size[0, 0] == pytest.approx(14.0) and xy[0].tolist() == [0, 0]
    assert 20.0 > MERGE_MAX_LENGTH_M
    kept, xy, size = _merge([[0, 0], [0, 3.5]], 0.0, CAR, [0.9, 0.5])  # two lanes: both kept, both as they were
    assert kept == [0, 1]
    np.testing.assert_allclose(xy, [[0, 0], [0, 3.5]])
    np.testing.assert_allclose(size, [CAR, CAR])


def test_merge_takes_in_a_peak_the_grown_span_reaches_and_is_stable():
    # a bus (east) read as peaks at 0, 3 and 6 m, the best at one end: the first round spans 0 and 3 (7.5 m long,
    # centred at 1.5 m), whose footprint then holds the peak at 6 m; it joins in the second round
    xy, yaw, size = np.array([[0.0, 0], [3, 0], [6, 0]]), np.zeros(3), np.tile(CAR, (3, 1))
    score = np.array([0.9, 0.6, 0.5])
    kept, mxy, msize = footprint_rule(xy, yaw, size, score, 1.5, True)
    assert kept.tolist() == [0]
    np.testing.assert_allclose(mxy[0], [3.0, 0.0], atol=1e-12)
    assert msize[0, 0] == pytest.approx(6 + CAR[0])
    again, xy2, size2 = footprint_rule(mxy[kept], yaw[kept], msize[kept], score[kept], 1.5, True)
    assert again.tolist() == [0]
    np.testing.assert_allclose(xy2, mxy[kept])
    np.testing.assert_allclose(size2, msize[kept])
    # without merging the first round's drop stands: the peak at 6 m is outside the best one's own footprint
    kept, mxy, _ = footprint_rule(xy, yaw, size, score, 1.5, False)
    assert kept.tolist() == [0, 2]
    np.testing.assert_allclose(mxy, xy)


def test_settings_drop_without_merging_by_default():
    assert LocalizeSettings().footprint_merge is False
    assert LocalizeSettings(footprint_merge=True).footprint_merge is True


def test_objects_message_grows_a_vehicle_merged_on_both_sides_without_moving_it():
    # peaks 12 px = 3 m either side of the best one, all heading east: the span grows, its middle stays
    kept = objects_message(_cars_heading_east([10, 22, 34], [0.5, 0.8, 0.6]), _masks(), 6.0, 2.0, True)
    np.testing.assert_allclose(kept.xy, [[5.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.size_lwh, [[10.5, 1.8, 1.5]], atol=1e-6)
