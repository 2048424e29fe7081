"""Detector evaluation: VOC07 AP, matching with ignore vehicles, the ground lift, and an oracle
detector built from the ground truth scoring perfectly on a real (small) recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eval.detector import (
    GroundLifter,
    best_f1,
    box_iou,
    breakdown_frame,
    evaluate,
    match_frame,
    near_frame,
    voc07_ap,
)
from shared.decode import Detections
from shared.inference import OnnxDetector


def _dets(boxes, scores, uv=None) -> Detections:
    n = len(scores)
    boxes = np.asarray(boxes, float).reshape(n, 4)
    uv = np.asarray(uv, float).reshape(n, 2) if uv is not None else boxes[:, 2:]
    return Detections(np.asarray(scores, float), uv, boxes, np.tile([1.0, 0.0], (n, 1)), np.ones((n, 3)),
                      np.zeros(n, int), np.ones((n, 5)) / 5)


def test_best_f1_picks_the_threshold_and_keeps_ties_together():
    # scores 0.9 hit, 0.8 hit, 0.7 miss, 0.6 hit, 0.5 miss; 4 positives
    r = best_f1(np.array([0.5, 0.9, 0.6, 0.8, 0.7]), np.array([False, True, True, True, False]), 4)
    # thresholds: 0.9 -> p 1, r .25 (f1 .4); 0.8 -> 1, .5 (.667); 0.7 -> .667, .5 (.571); 0.6 -> .75, .75 (.75)
    assert r["best_f1_score_thr"] == 0.6 and r["best_f1"] == 0.75
    assert r["best_f1_precision"] == 0.75 and r["best_f1_recall"] == 0.75
    # two detections with the same score are kept or dropped together
    r = best_f1(np.array([0.9, 0.5, 0.5]), np.array([True, False, True]), 2)
    assert r["best_f1_score_thr"] in (0.9, 0.5)
    assert r["best_f1"] == pytest.approx(max(2 * 0.5 / 1.5, 2 * (2 / 3) * 1 / (2 / 3 + 1)), abs=1e-4)
    assert best_f1(np.array([]), np.array([], bool), 3)["best_f1"] is None


def test_voc07_ap_on_hand_made_rankings():
    assert voc07_ap(np.array([0.9, 0.8]), np.array([True, True]), 2) == pytest.approx(1.0)
    # half the positives found, both at the top: precision 1 up to recall 0.5 -> 6 of 11 points
    assert voc07_ap(np.array([0.9, 0.1]), np.array([True, False]), 2) == pytest.approx(6 / 11)
    # a false alarm ranked first: precision 0.5 at recall 1
    assert voc07_ap(np.array([0.9, 0.8]), np.array([False, True]), 1) == pytest.approx(0.5)
    assert np.isnan(voc07_ap(np.zeros(0), np.zeros(0, bool), 0))


def test_matching_takes_each_vehicle_once_and_skips_ignore_vehicles():
    gt = np.array([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10]], float)
    weight = np.array([1.0, 1.0, 0.0])
    det = _dets([[0, 0, 10, 10], [1, 0, 11, 10], [40, 0, 50, 10], [60, 0, 70, 10]], [0.9, 0.8, 0.7, 0.6])
    gt_of, counts = match_frame(det, gt, weight)
    assert list(gt_of) == [0, -1, -1, -1]  # the duplicate is a false alarm
    assert list(counts) == [True, True, False, True]  # the ignore vehicle's detection does not count
    assert box_iou(gt[:1], gt[:1])[0, 0] == pytest.approx(1.0)


def test_ground_lifter_is_bilinear_and_nan_outside():
    xyz = np.stack(np.meshgrid(np.arange(4.0), np.arange(3.0)), -1)
    xyz = np.concatenate([xyz, np.zeros((3, 4, 1))], -1)
    lift = GroundLifter(xyz, np.ones((3, 4), bool))
    got = lift(np.array([[1.25, 0.5], [3.0, 2.0], [-1.0, 0.0]]))
    np.testing.assert_allclose(got[:2, :2], [[1.25, 0.5], [3.0, 2.0]], atol=1e-9)
    assert np.isnan(got[2]).all()


def test_an_oracle_detector_scores_perfectly(small_recording):
    """Detections made from the labels themselves: AP 1 and (near) zero pose errors, which checks the
    matching, the lift to the ground and the heading conversion against the recorded truth."""
    from tests.pipeline_fixtures import labels_of_image

    labels = labels_of_image(small_recording)

    def oracle(grey: np.ndarray) -> Detections:
        s = labels(grey)
        n = len(s)
        prob = np.eye(5)[np.clip(s.vtype, 0, 4)]
        heading = np.where(np.isfinite(s.heading_uv), s.heading_uv, [1.0, 0.0])
        return Detections(np.linspace(1.0, 0.5, n), s.bottom_uv, s.box, heading, s.size_lwh, s.vtype, prob)

    result = evaluate(small_recording, oracle)
    overall = result["overall"]
    assert overall["positives"] > 5 and overall["ap50"] == pytest.approx(1.0)
    assert overall["loc_err_m"] < 0.02
    assert overall["yaw_err_median_deg"] < 3.0  # a finite pixel step along a projected heading
    assert overall["yaw_axis_err_median_deg"] == pytest.approx(overall["yaw_err_median_deg"], abs=1e-6)

    def reversed_oracle(grey: np.ndarray) -> Detections:
        d = oracle(grey)
        return Detections(d.score, d.uv, d.box, -d.heading_uv, d.size_lwh, d.vtype, d.vtype_prob)

    rev = evaluate(small_recording, reversed_oracle)["overall"]
    assert rev["yaw_err_median_deg"] > 170.0 and rev["yaw_axis_err_median_deg"] < 10.0  # the axis is still right
    assert overall["size_err_m"] == pytest.approx(0.0) and overall["type_acc"] == pytest.approx(1.0)
    assert set(result["per_kind"]) == {"fisheye", "thermal"}
    assert overall["false_alarms"] == {"box": 0, "duplicate": 0, "background": 0}
    bands = [b for b in overall["recall_by_size"] if b["positives"]]
    assert bands and all(b["matched"] == 1.0 and b["found"] == 1.0 for b in bands)
    assert sum(b["positives"] for b in overall["recall_by_size"]) == overall["positives"]
    # near the camera, on the ground: every vehicle to detect found, every detection on one, placed exactly
    assert overall["near_positives"] > 0 and overall["near_recall"] == 1.0 and overall["near_precision"] == 1.0
    assert overall["near_f1"] == 1.0 and overall["near_loc_err_m"] < 0.02
    by_type = overall["near_by_type"]
    assert by_type and sum(t["positives"] for t in by_type.values()) == overall["near_positives"]
    assert all(t["recall"] == 1.0 and t["loc_err_median_m"] < 0.02 for t in by_type.values())
    assert evaluate(small_recording, oracle, near_m=1e-3)["overall"]["near_positives"] == 0
    with pytest.raises(ValueError, match="near_m must be > 0"):
        evaluate(small_recording, oracle, near_m=0.0)
    # detections kept from 0.6 up: the figures "at 0.3" are at 0.6, and say so
    high = evaluate(small_recording, oracle, detections_score_thr=0.6)["overall"]
    assert high["breakdown_score_thr"] == high["near_score_thr"] == high["detections_score_thr"] == 0.6

    def off_target(grey: np.ndarray) -> Detections:  # every detection 400 px off its vehicle
        d = oracle(grey)
        return Detections(d.score, d.uv + 400.0, d.box + 400.0, d.heading_uv, d.size_lwh, d.vtype, d.vtype_prob)

    off = evaluate(small_recording, off_target)["overall"]
    assert off["near_recall"] == 0.0 and off["near_precision"] == 0.0 and off["near_f1"] == 0.0  # none, not unknown


def test_false_alarm_breakdown_by_kind():
    """Vehicles 0 and 1 to detect (40 px boxes, bottom centres at their lower edges), vehicle 2 ignored."""
    box = np.array([[0, 0, 40, 40], [100, 0, 140, 40], [200, 0, 240, 40]], float)
    bottom = np.array([[20, 40], [120, 40], [220, 40]], float)
    weight = np.array([1.0, 1.0, 0.0])
    det_box = np.array([
        [0, 0, 40, 40],  # matches vehicle 0
        [2, 2, 42, 42],  # a second detection of vehicle 0
        [110, 20, 180, 80],  # on vehicle 1, but its box is off (IoU < 0.5)
        [400, 400, 440, 440],  # background
        [105, 0, 145, 40],  # would match vehicle 1, but scores under the breakdown threshold
    ], float)
    uv = np.array([[20, 40], [22, 42], [122, 42], [420, 440], [125, 40]], float)
    score = np.array([0.9, 0.8, 0.7, 0.6, 0.1])
    n = len(score)
    det = Detections(score, uv, det_box, np.tile([1.0, 0.0], (n, 1)), np.ones((n, 3)), np.zeros(n, int),
                     np.full((n, 5), 0.2))
    gt_of, counts = match_frame(det, box, weight)
    alarms, matched, found = breakdown_frame(det, box, bottom, weight, gt_of, counts)
    assert alarms == {"box": 1, "duplicate": 1, "background": 1}
    assert list(matched) == [True, False, False]  # vehicle 1's match scores under the threshold
    assert list(found[:2]) == [True, True]


def test_a_box_overlapping_the_next_car_does_not_find_it():
    """Two cars side by side in a parking row, the detector finds A alone: its box overlaps B's (IoU 0.14) but its
    bottom centre is 45 px from B's, beyond a third of B's size (14 px). B is not found, and a second detection
    whose box overlaps both (A's IoU 0.64, B's 0.15) but whose bottom centre is on neither is a background alarm,
    not a box alarm on B."""
    box = np.array([[100, 100, 160, 130], [145, 100, 205, 130]], float)  # A, B
    bottom = np.array([[130, 130], [175, 130]], float)
    weight = np.ones(2)
    det = _dets([[100, 100, 160, 130], [95, 95, 165, 135]], [0.9, 0.8], uv=[[130, 130], [130, 112]])
    assert box_iou(det.box, box)[0, 1] > 0.1 and box_iou(det.box, box)[1, 1] > 0.1
    gt_of, counts = match_frame(det, box, weight)
    alarms, matched, found = breakdown_frame(det, box, bottom, weight, gt_of, counts)
    assert list(matched) == [True, False]
    assert list(found) == [True, False]
    assert alarms == {"box": 0, "duplicate": 0, "background": 1}
    # the same detection with its bottom centre on B's (whatever its box) finds B: a box alarm
    det = _dets([[100, 100, 160, 130], [95, 95, 165, 135]], [0.9, 0.8], uv=[[130, 130], [180, 128]])
    alarms, matched, found = breakdown_frame(det, box, bottom, weight, *match_frame(det, box, weight))
    assert list(found) == [True, True] and alarms == {"box": 1, "duplicate": 0, "background": 0}


def test_onnx_detector_rejects_missing_and_corrupt_models(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        OnnxDetector(tmp_path / "none.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"bad\.onnx"):
        OnnxDetector(bad)


def test_onnx_detector_threads_sleep_between_jobs_unless_asked_to_spin():
    from shared.settings import DetectSettings

    model = Path(__file__).resolve().parents[1] / "models" / "detector_fp32.onnx"
    assert DetectSettings().spin is False
    spinning = OnnxDetector(model, threads=1)
    assert spinning.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning") == "1"
    sleeping = OnnxDetector(model, threads=1, spin=False)
    assert sleeping.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert len(sleeping.detect(np.zeros((96, 128), np.uint8))) == 0


def test_fisheye_area_reaches_the_fisheye_frames_only(small_recording):
    """`evaluate(..., fisheye_area_deg)` detects fisheye frames as `detect(grey, area_px=...)`, the camera's circle up
    to that angle, as a site's detect_area_px has the detect service do; thermal frames on the whole image."""
    from sim.recording import Recording

    seen = []

    def detect(grey: np.ndarray, area_px=None) -> Detections:
        seen.append((grey.shape, area_px))
        return Detections(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros((0, 3)),
                          np.zeros(0, np.int64), np.zeros((0, 5)))

    result = evaluate(small_recording, detect, fisheye_area_deg=90.0)
    assert result["fisheye_area_deg"] == 90.0
    circle = Recording(small_recording).cameras["NE"].image_area_px(90.0)
    assert {a for shape, a in seen if shape == (960, 1280)} == {circle}
    assert {a for shape, a in seen if shape != (960, 1280)} == {None}
    assert 0 < circle[0] and circle[2] < 1280  # narrower than the frame


def test_near_frame_counts_on_the_ground_around_the_camera():
    centre = np.array([0.0, 0.0])
    labels = np.array([[5.0, 0.0], [10.0, 0.0], [40.0, 0.0], [0.0, 8.0]])  # the third is far, the fourth ignored
    positive = np.array([True, True, True, False])
    dets = np.array([[5.4, 0.0],     # on vehicle 0, 0.4 m off
                     [10.0, 2.0],    # 2 m from vehicle 1: beyond the 1.5 m gate, a false alarm
                     [0.0, 8.5],     # on the ignored vehicle: counts neither way
                     [39.0, 0.0],    # on the far vehicle, outside the 25 m: not counted
                     [np.nan, np.nan],  # off the ground
                     [24.0, 0.0]])   # near and on nothing: a false alarm
    n = near_frame(dets, labels, positive, centre, 25.0)
    assert n["positives"] == 2 and n["found"] == 1
    assert n["detections"] == 3 and n["true"] == 1
    assert n["loc"] == pytest.approx([0.4])
    # per label: 0.4 m for the found one, NaN for the missed near one, -1 for the far and the ignored (not counted)
    assert np.allclose(n["label_dist"], [0.4, np.nan, -1.0, -1.0], equal_nan=True)
    # a detection just outside the radius still finds a vehicle just inside it
    n = near_frame(np.array([[25.5, 0.0]]), np.array([[24.5, 0.0]]), np.array([True]), centre, 25.0)
    assert (n["positives"], n["found"], n["detections"], n["true"]) == (1, 1, 0, 0)
    # nothing detected, nothing labelled
    n = near_frame(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), centre, 25.0)
    assert (n["positives"], n["found"], n["detections"], n["true"], n["loc"]) == (0, 0, 0, 0, [])
    n = near_frame(np.array([[1.0, 1.0]]), np.zeros((0, 2)), np.zeros(0, bool), centre, 25.0)
    assert (n["detections"], n["true"]) == (1, 0)
