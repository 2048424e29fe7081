"""Tracking evaluation (eval/tracking.py) on a tiny hand-made recording: two fisheye cameras 40 m apart, three
vehicles on straight lines and two parked ones (one mostly hidden), 10 Hz with per-camera capture offsets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from eval.tracking import (
    FrameMatch,
    GroundTruth,
    TrackingEvalConfig,
    evaluate_many,
    evaluate_tracks,
    handoff_measure,
    load_tracks,
)

T0 = 1_700_000_000_000_000_000
HZ = 10
N_FRAMES = 40
CAMS = {"A": ((-20.0, 0.0, 10.0), 0), "B": ((20.0, 0.0, 10.0), 37_000_000)}  # ground position, capture offset ns
LISTED_M = 30.0  # a camera lists a vehicle within this ground distance (in_image)
TICK_OFFSET_NS = 20_000_000  # tracker ticks fall between the cameras' capture times


def pos(vid: int, s: float) -> np.ndarray:
    """Vehicle vid's ground position at s seconds after T0."""
    return {
        1: np.array([-20.0 + 10.0 * s, 0.0]),  # east along y=0: A's region until x=0 (s=2), then B's
        2: np.array([-15.0, -10.0 + 4.0 * s]),
        3: np.array([12.0 + 1.5 * s, -8.0 + 2.0 * s]),
        4: np.array([0.0, 12.0]),  # parked, mostly hidden (visible_fraction 0.1)
        5: np.array([-10.0, -12.0]),  # parked, visible
    }[vid]


NORMAL = {1: np.array([0.0, 1.0]), 2: np.array([-1.0, 0.0]), 3: np.array([-0.8, 0.6]), 5: np.array([0.0, 1.0])}
DIRECTION = {1: np.array([1.0, 0.0]), 2: np.array([0.0, 1.0]), 3: np.array([0.6, 0.8]), 5: np.array([0.0, 0.0])}
GT_IDS = (1, 2, 3, 5)
YAW = {1: 0.0, 2: math.pi / 2, 3: math.atan2(0.8, 0.6), 4: 0.0, 5: 1.0}  # headings (rad ENU), 5 parked


def _write_recording(out: Path) -> Path:
    (out / "gt").mkdir(parents=True)
    cameras = []
    for name, (p, off) in CAMS.items():
        cameras.append({"name": name, "kind": "fisheye", "modality": "visible", "width": 1280, "height": 960,
                        "pose": {"position_m": list(p), "r_cam_from_world": np.eye(3).tolist()},
                        "frames": N_FRAMES, "frame_dir": f"frames/{name}", "gt": f"gt/{name}.jsonl",
                        "landmarks": f"landmarks/{name}.json"})
        lines = []
        for k in range(N_FRAMES):
            t = T0 + k * 100_000_000 + off
            s = (t - T0) / 1e9
            vehicles = []
            for vid in (1, 2, 3, 4, 5):
                xy = pos(vid, s)
                if np.linalg.norm(xy - np.array(p[:2])) > LISTED_M:
                    continue
                vehicles.append({"id": vid, "type": "car", "lwh": [4.5, 1.8, 1.5], "yaw": YAW[vid], "speed": 0.0,
                                 "xyz": [float(xy[0]), float(xy[1]), 0.0], "in_image": True,
                                 "visible_fraction": 0.1 if vid == 4 else 0.8 if vid == 5 else 1.0,
                                 "parked": vid in (4, 5)})
            lines.append(json.dumps({"t_ns": t, "file": f"frames/{name}/{t}.jpg", "vehicles": vehicles}))
        (out / "gt" / f"{name}.jsonl").write_text("\n".join(lines) + "\n")
    return _write_meta(out, cameras)


def _write_meta(out: Path, cameras: list[dict]) -> Path:
    """recording.json of a test recording with these cameras; the recording's folder."""
    meta = {"format": "roadside-recording", "version": 1,
            "site": {"name": "test", "origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0}},
            "hz": HZ, "seconds": N_FRAMES / HZ, "t0_ns": T0, "cameras": cameras}
    (out / "recording.json").write_text(json.dumps(meta))
    return out


@pytest.fixture(scope="module")
def gt(tmp_path_factory) -> GroundTruth:
    return GroundTruth(_write_recording(tmp_path_factory.mktemp("rec") / "clip"))


def tick(k: int) -> int:
    return T0 + k * 100_000_000 + TICK_OFFSET_NS


def track(tid: int, xy: np.ndarray) -> dict:
    return {"id": tid, "x": round(float(xy[0]), 3), "y": round(float(xy[1]), 3), "lat": 0.0, "lon": 0.0,
            "vx": 0.0, "vy": 0.0, "yaw": 0.0, "length": 4.5, "width": 1.8, "height": 1.5, "type": "car",
            "score": 0.9, "age": 1, "hits": 1, "cameras": ["A"]}


def make_rows(offset=None, ids=None, vehicles=GT_IDS, tracker=None, extra=None) -> list[dict]:
    """One line per tick; offset(vid, k) -> xy offset, ids(vid, k) -> track id, tracker(k) -> tracker id."""
    rows = []
    for k in range(N_FRAMES):
        s = (tick(k) - T0) / 1e9
        tracks = []
        for vid in vehicles:
            xy = pos(vid, s) + (offset(vid, k) if offset else 0.0)
            tracks.append(track(ids(vid, k) if ids else 10 + vid, xy))
        for tid, xy in (extra or []):
            tracks.append(track(tid, np.asarray(xy, float)))
        rows.append({"site": "test", "seq": k, "t_ns": tick(k), "tracker": tracker(k) if tracker else "t1",
                     "tracks": tracks})
    return rows


def write_jsonl(path: Path, rows: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_merged_trajectory_interpolates_between_cameras_and_does_not_extrapolate_far(gt):
    traj = gt.trajectories[1]
    assert len(traj.t_ns) > N_FRAMES  # samples from both cameras, merged in time order
    assert np.all(np.diff(traj.t_ns) > 0)
    ext, gap = 200_000_000, 500_000_000
    for k in (0, 7, 23, 38):
        t = tick(k) + 5_000_000
        np.testing.assert_allclose(traj.position_at(t, ext, gap)[:2], pos(1, (t - T0) / 1e9), atol=1e-9)
    end = int(traj.t_ns[-1])
    np.testing.assert_allclose(traj.position_at(end + 100_000_000, ext, gap)[:2], pos(1, (end - T0) / 1e9 + 0.1),
                               atol=1e-9)  # a short extrapolation along the last segment
    assert traj.position_at(end + 300_000_000, ext, gap) is None
    assert traj.position_at(int(traj.t_ns[0]) - 300_000_000, ext, gap) is None
    assert gt.frame_interval_ns == 100_000_000


def test_gt_objects_policy(gt):
    cfg = TrackingEvalConfig()
    t = tick(10)
    assert set(gt.gt_objects(t, ["A", "B"], cfg)) == {1, 2, 3, 5}  # parked 5 visible; parked 4 hidden (0.1)
    assert set(gt.gt_objects(t, ["A"], cfg)) == {1, 2, 5}  # vehicle 1 at x=-9: in A's 25 m
    assert set(gt.gt_objects(t, ["B"], cfg)) == {3}  # vehicle 1 listed by B but outside B's 25 m
    assert 4 in gt.gt_objects(t, ["A", "B"], TrackingEvalConfig(min_visible_fraction=0.05))
    assert gt.gt_objects(T0 + 10 * 10**9, ["A", "B"], cfg) == {}  # long after the clip


def test_a_camera_alone_is_charged_for_the_vehicles_of_its_area_any_camera_sees(gt, monkeypatch):
    """Vehicle 5 in A's area seen by B alone: a GT object of A's single-camera score with `seen_by` all cameras (as
    evaluate_many scores a camera alone), not without."""
    cfg = TrackingEvalConfig()
    seen = {("A",): {1, 2}, ("A", "B"): {1, 2, 3, 5}}
    monkeypatch.setattr(gt, "seen_by", lambda t_ns, cams, config: seen[tuple(cams)])
    assert set(gt.gt_objects(tick(10), ["A"], cfg)) == {1, 2}
    assert set(gt.gt_objects(tick(10), ["A"], cfg, seen_by=["A", "B"])) == {1, 2, 5}  # 3 is outside A's area


def test_perfect_tracks(gt):
    r = evaluate_tracks(gt, make_rows())
    assert r["mota"] == 1.0 and r["idf1"] == 1.0 and r["id_switches"] == 0
    assert r["precision"] == 1.0 and r["recall"] == 1.0
    assert r["num_frames"] == N_FRAMES and r["num_objects"] == 4 * N_FRAMES
    assert r["traj_err_in_roi_m"] == pytest.approx(0.0, abs=2e-3)
    assert r["traj_err_in_roi_n"] == 4 * N_FRAMES and r["traj_err_out_roi_n"] == 0
    assert math.isnan(r["traj_err_out_roi_m"])
    assert r["tracks"] == 4 and r["gt_vehicles"] == 4 and r["trackers"] == 1
    assert r["silent_ticks_filled"] == 0 and r["ignored_track_positions"] == 0


def test_tracked_heading_error_is_full_circle_and_split_by_speed(gt):
    """The moving vehicles' tracks head 10 deg off, the parked one's reversed: 10 and 180 deg; tracks with no yaw
    give no heading error and change nothing else."""
    rows = make_rows()
    for row in rows:
        for t in row["tracks"]:
            vid = t["id"] - 10
            t["yaw"] = YAW[vid] + (math.pi if vid == 5 else math.radians(10))
    r = evaluate_tracks(gt, rows)
    assert r["yaw_err_in_roi_n"] == 4 * N_FRAMES
    assert r["yaw_err_in_roi_moving_deg"] == pytest.approx(10.0)
    assert r["yaw_err_in_roi_standing_deg"] == pytest.approx(180.0)
    assert r["yaw_err_in_roi_deg"] == pytest.approx((3 * 10.0 + 180.0) / 4)
    assert r["yaw_err_in_roi_median_deg"] == pytest.approx(10.0)
    for row in rows:
        for t in row["tracks"]:
            del t["yaw"]
    r2 = evaluate_tracks(gt, rows)
    assert r2["yaw_err_in_roi_n"] == 0 and math.isnan(r2["yaw_err_in_roi_deg"])
    assert r2["mota"] == r["mota"] == 1.0 and r2["traj_err_in_roi_m"] == r["traj_err_in_roi_m"]


def test_a_tracks_position_covariance_is_scored_against_its_error(gt):
    """Tracks off their vehicle by draws of a known covariance, stating it: about 95 % of the true positions inside
    their 95 % ellipses and a mean squared Mahalanobis distance near 2; stating a covariance four times too small
    (sigmas halved): far fewer, 4 times the distance and a lower log-likelihood; the same by true type. Tracks
    without one are not scored; a malformed one is named."""
    rng = np.random.default_rng(1)
    cov = np.array([[0.09, 0.05], [0.05, 0.25]])
    draws = {(v, k): rng.multivariate_normal([0, 0], cov) for v in GT_IDS for k in range(N_FRAMES)}
    rows = make_rows(offset=lambda v, k: draws[(v, k)])
    loglik = []
    for stated, within in ((cov, (0.9, 1.0)), (cov / 4, (0.3, 0.7))):
        for row in rows:
            for t in row["tracks"]:
                t["xy_cov"] = stated.tolist()
        r = evaluate_tracks(gt, rows)
        assert r["pos_cov_n"] == r["traj_err_in_roi_n"] > 0.95 * 4 * N_FRAMES  # the matched positions in the ROI
        assert within[0] < r["pos_cov_within_95"] < within[1]
        scale = 1 if stated is cov else 4
        assert r["pos_cov_nees_mean"] == pytest.approx(2 * scale, rel=0.2)
        assert r["pos_cov_err95_median_m"] == pytest.approx(np.sqrt(5.991 * np.linalg.eigvalsh(stated).max()))
        expected = -0.5 * 2 * scale - 0.5 * math.log(np.linalg.det(stated)) - math.log(2 * math.pi)
        assert r["pos_cov_loglik"] == pytest.approx(expected, abs=0.2 * scale)
        loglik.append(r["pos_cov_loglik"])
        by_type = r["pos_cov_by_type"]
        assert by_type and sum(t["pos_cov_n"] for t in by_type.values()) == r["pos_cov_n"]
        assert all(set(t) == {k for k in r if k.startswith("pos_cov_") and k != "pos_cov_by_type"}
                   for t in by_type.values())
    assert loglik[0] > loglik[1] + 0.5  # right beats too sure
    assert r["pos_cov_within_1sigma"] < r["pos_cov_within_95"]
    for row in rows:
        for t in row["tracks"]:
            del t["xy_cov"]
    assert evaluate_tracks(gt, rows)["pos_cov_n"] == 0 and math.isnan(evaluate_tracks(gt, rows)["pos_cov_within_95"])
    rows[3]["tracks"][1]["xy_cov"] = [[0.1, 0.0], [0.0, -0.1]]
    with pytest.raises(ValueError, match=r"tracks line 4: track 1 \(id 12\): xy_cov .* not a symmetric positive"):
        evaluate_tracks(gt, rows)


def test_headings_are_split_by_whether_travel_confirmed_them(gt):
    """The moving vehicles' tracks head 10 deg off and say their heading is confirmed, the parked one's is reversed
    and says it is not: confirmed 3 of 4, none of them backwards, all the others; tracks that do not say are left
    out; a yaw_confirmed that is not true or false is named."""
    rows = make_rows()
    for row in rows:
        for t in row["tracks"]:
            vid = t["id"] - 10
            t["yaw"] = YAW[vid] + (math.pi if vid == 5 else math.radians(10))
            t["yaw_confirmed"] = vid != 5
    r = evaluate_tracks(gt, rows)
    assert r["yaw_confirmed_n"] == 4 * N_FRAMES and r["yaw_confirmed_share"] == pytest.approx(0.75)
    assert r["yaw_reversed_confirmed"] == 0.0 and r["yaw_reversed_unconfirmed"] == 1.0
    assert r["yaw_err_confirmed_deg"] == pytest.approx(10.0) and r["yaw_err_unconfirmed_deg"] == pytest.approx(180.0)
    for row in rows:
        for t in row["tracks"]:
            if t["id"] != 15:
                del t["yaw_confirmed"]
    r = evaluate_tracks(gt, rows)
    assert r["yaw_confirmed_n"] == N_FRAMES and r["yaw_confirmed_share"] == 0.0
    assert math.isnan(r["yaw_reversed_confirmed"]) and r["yaw_reversed_unconfirmed"] == 1.0
    rows[1]["tracks"][0]["yaw_confirmed"] = 1
    with pytest.raises(ValueError, match=r"tracks line 2: track 0 \(id \d+\): yaw_confirmed must be true or false"):
        evaluate_tracks(gt, rows)


def test_a_headings_sigma_is_scored_against_its_error_on_the_axis(gt):
    """Headings off by draws of a known sigma (5 deg), stating it: about 95 % within 1.96 sigma and a mean squared
    error over sigma^2 near 1; the parked vehicle's heading reversed as well counts by its axis alone (the same);
    stating half the sigma: fewer, and 4 times the ratio. Tracks without one are not scored; a bad one is named."""
    rng = np.random.default_rng(2)
    draws = {(v, k): rng.normal(0, math.radians(5)) for v in GT_IDS for k in range(N_FRAMES)}
    rows = make_rows()
    for k, row in enumerate(rows):
        for t in row["tracks"]:
            vid = t["id"] - 10
            t["yaw"] = YAW[vid] + draws[(vid, k)] + (math.pi if vid == 5 else 0.0)
    for stated, within in ((5.0, (0.9, 0.99)), (2.5, (0.5, 0.8))):
        for row in rows:
            for t in row["tracks"]:
                t["yaw_std"] = math.radians(stated)
        r = evaluate_tracks(gt, rows)
        assert r["yaw_std_n"] == r["yaw_err_in_roi_n"] == 4 * N_FRAMES
        assert within[0] < r["yaw_std_within_95"] < within[1] and r["yaw_std_within_1sigma"] < r["yaw_std_within_95"]
        assert r["yaw_std_z2_mean"] == pytest.approx(25 / stated**2, rel=0.25)
        assert r["yaw_std_median_deg"] == pytest.approx(stated)
        if stated == 5.0:
            loglik_right = r["yaw_std_loglik"]
    assert r["yaw_std_loglik"] < loglik_right  # a sigma too small scores worse
    for row in rows:
        for t in row["tracks"]:
            del t["yaw_std"]
    r = evaluate_tracks(gt, rows)
    assert r["yaw_std_n"] == 0 and math.isnan(r["yaw_std_within_95"])
    rows[2]["tracks"][0]["yaw_std"] = -0.1
    with pytest.raises(ValueError, match=r"tracks line 3: track 0 \(id \d+\): yaw_std must be a finite number > 0"):
        evaluate_tracks(gt, rows)


def test_a_tracks_velocity_covariance_is_scored_against_the_true_velocity(gt):
    """Track velocities off the vehicles' by draws of a known covariance, stating it: about 95 % inside the 95 %
    ellipse, mean squared distance near 2; a track without velocity_cov is not scored; a malformed one is named."""
    rng = np.random.default_rng(2)
    cov = np.array([[0.25, -0.05], [-0.05, 0.16]])
    velocity = {1: (10.0, 0.0), 2: (0.0, 4.0), 3: (1.5, 2.0), 5: (0.0, 0.0)}
    rows = make_rows()
    for row in rows:
        for t in row["tracks"]:
            t["vx"], t["vy"] = (np.array(velocity[t["id"] - 10]) + rng.multivariate_normal([0, 0], cov)).tolist()
            t["velocity_cov"] = cov.tolist()
    r = evaluate_tracks(gt, rows)
    assert r["vel_cov_n"] == r["traj_err_in_roi_n"] == 4 * N_FRAMES
    assert 0.9 < r["vel_cov_within_95"] <= 1.0 and r["vel_cov_nees_mean"] == pytest.approx(2.0, rel=0.25)
    assert r["pos_cov_n"] == 0  # no xy_cov in these tracks
    rows[2]["tracks"][0]["velocity_cov"] = [[0.1, 0.3], [0.3, 0.1]]
    with pytest.raises(ValueError, match=r"tracks line 3: track 0 \(id 11\): velocity_cov .* not a symmetric"):
        evaluate_tracks(gt, rows)


def test_recorder_file_and_rows_give_the_same_result(gt, tmp_path):
    rows = make_rows(offset=lambda v, k: 0.3 * NORMAL[v])
    a = evaluate_tracks(gt, rows)
    b = evaluate_tracks(gt.recording.path, write_jsonl(tmp_path / "tracks.jsonl", rows), cameras="A,B")
    for key in ("mota", "idf1", "traj_err_in_roi_m", "num_matches"):
        assert a[key] == pytest.approx(b[key])


def test_constant_offset_gives_trajectory_error_and_keeps_mota(gt):
    r = evaluate_tracks(gt, make_rows(offset=lambda v, k: 0.5 * NORMAL[v]))
    assert r["mota"] == 1.0 and r["idf1"] == 1.0
    assert r["traj_err_in_roi_m"] == pytest.approx(0.5, abs=2e-3)
    assert r["traj_err_in_roi_std_m"] == pytest.approx(0.0, abs=2e-3)
    assert r["pos_err_m"] == pytest.approx(0.5, abs=2e-3)
    # along the path: the paper's trajectory error (distance to the path) barely sees a time lag
    along = evaluate_tracks(gt, make_rows(offset=lambda v, k: 0.5 * DIRECTION[v]))
    assert along["mota"] == 1.0
    assert along["pos_err_m"] == pytest.approx(0.375, abs=2e-3)  # three moving vehicles of four
    assert along["traj_err_in_roi_m"] < 0.05


def test_out_of_roi_part_of_a_larger_evaluation_area(gt):
    cfg = TrackingEvalConfig(roi_radius_m=10.0, eval_radius_m=40.0)
    r = evaluate_tracks(gt, make_rows(offset=lambda v, k: 0.5 * NORMAL[v]), config=cfg)
    assert r["mota"] == 1.0
    assert r["traj_err_in_roi_n"] > 0 and r["traj_err_out_roi_n"] > 0
    assert r["traj_err_in_roi_n"] + r["traj_err_out_roi_n"] == 4 * N_FRAMES
    assert r["traj_err_in_roi_m"] == pytest.approx(0.5, abs=2e-3)
    assert r["traj_err_out_roi_m"] == pytest.approx(0.5, abs=2e-3)


def test_a_matched_track_is_in_the_roi_where_its_vehicle_is(gt):
    """Parked vehicle 5 lies 15.6 m from camera A, inside a 16 m ROI: its track 1 m off radially, outward (across the
    ROI's edge) or inward, is scored in the ROI either way, as its vehicle was chosen."""
    cfg = TrackingEvalConfig(roi_radius_m=16.0)
    away = (pos(5, 0.0) - np.array(CAMS["A"][0][:2])) / np.linalg.norm(pos(5, 0.0) - np.array(CAMS["A"][0][:2]))
    perfect = evaluate_tracks(gt, make_rows(), config=cfg)
    for sign in (1.0, -1.0):
        r = evaluate_tracks(gt, make_rows(offset=lambda v, k, sign=sign: sign * away if v == 5 else 0.0), config=cfg)
        assert r["mota"] == 1.0 and r["num_matches"] == perfect["num_matches"]
        assert r["traj_err_out_roi_n"] == 0 and r["traj_err_in_roi_matched_n"] == r["num_matches"]
        assert r["traj_err_in_roi_matched_m"] == pytest.approx(N_FRAMES / r["num_matches"], abs=2e-3)


def test_id_switch_is_counted(gt):
    r = evaluate_tracks(gt, make_rows(ids=lambda v, k: 100 + v if (v == 1 and k >= 20) else 10 + v))
    assert r["id_switches"] == 1
    assert r["idf1"] < 1.0
    assert r["mota"] == pytest.approx(1 - 1 / (4 * N_FRAMES))
    assert r["tracks"] == 5


def test_identity_is_tracker_and_id(gt):
    r = evaluate_tracks(gt, make_rows(tracker=lambda k: "t1" if k < 20 else "t2"))  # restart, same ids
    assert r["id_switches"] == 4 and r["trackers"] == 2 and r["tracks"] == 8


def test_missing_track_lowers_recall_and_mota(gt):
    r = evaluate_tracks(gt, make_rows(vehicles=(1, 2, 5)))
    assert r["recall"] == pytest.approx(0.75) and r["mota"] == pytest.approx(0.75)
    assert r["num_misses"] == N_FRAMES and r["precision"] == 1.0


def test_positions_beyond_the_gate_are_misses_and_false_positives(gt):
    r = evaluate_tracks(gt, make_rows(offset=lambda v, k: 2.0 * NORMAL[v] if v == 3 else 0.0))
    assert r["num_misses"] == N_FRAMES and r["num_false_positives"] == N_FRAMES
    assert r["mota"] == pytest.approx(0.5)
    assert r["traj_err_in_roi_matched_m"] == pytest.approx(0.0, abs=2e-3)  # the matched positions: on their paths
    # every position in the ROI counts in the trajectory error: vehicle 3's track, 2 m off its path, too
    n, matched = r["traj_err_in_roi_n"], r["traj_err_in_roi_matched_n"]
    assert n - matched == N_FRAMES and 0.1 < r["traj_err_in_roi_m"] <= 2.0 * N_FRAMES / n + 2e-3  # its nearest path


def test_tracks_on_unscored_vehicles_or_outside_the_area_are_ignored(gt):
    extra = [(90, pos(4, 0.0)), (91, (200.0, 200.0))]  # on the hidden parked car; far away
    r = evaluate_tracks(gt, make_rows(extra=extra))
    assert r["mota"] == 1.0 and r["num_false_positives"] == 0
    assert r["ignored_track_positions"] == 2 * N_FRAMES and r["tracks"] == 4 and r["tracks_total"] == 6
    strict = evaluate_tracks(gt, make_rows(extra=extra), config=TrackingEvalConfig(ignore_unscored_tracks=False))
    assert strict["num_false_positives"] == 2 * N_FRAMES


def test_empty_tracks_give_zero_mota(gt, tmp_path):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    for src in (empty, []):
        r = evaluate_tracks(gt, src)
        assert r["mota"] <= 0.0 and r["recall"] == 0.0
        assert r["num_frames"] == N_FRAMES and r["silent_ticks_filled"] == N_FRAMES
        assert r["tracks"] == 0 and math.isnan(r["traj_err_in_roi_m"])


def test_silent_ticks_and_lines_outside_the_recording(gt):
    rows = make_rows()
    rows = [*rows[:30], {"site": "test", "seq": 99, "t_ns": T0 + 100 * 10**9, "tracker": "t1", "tracks": []}]
    r = evaluate_tracks(gt, rows)
    assert r["lines_outside_recording"] == 1 and r["silent_ticks_filled"] == 10
    assert r["recall"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="none of the 1 tracks lines is within the recording's time span"):
        evaluate_tracks(gt, rows[-1:])  # another run's tracks: not scored as a tracker that saw nothing


def test_a_tracker_slower_than_the_cameras_is_silent_only_where_it_misses_its_own_ticks(gt):
    """A tracker ticking every 200 ms over 100 ms frames is not silent between its ticks; where it stops, one empty
    tick is charged per tick of its own it missed (not one per camera frame)."""
    slow = make_rows()[::2]  # 20 lines, 200 ms apart
    r = evaluate_tracks(gt, slow)
    assert r["silent_ticks_filled"] == 0 and r["mota"] == 1.0 and r["num_frames"] == N_FRAMES // 2
    stalled = slow[:10]  # then 2 s without a line: 10 of its ticks missed
    r = evaluate_tracks(gt, stalled)
    assert r["silent_ticks_filled"] == 10 and r["num_frames"] == 20 and r["recall"] == pytest.approx(0.5)
    # a 100 ms tracker that misses two ticks in three after its first six: not a 300 ms one, charged for them
    missing = [*make_rows()[:6], *make_rows()[6::3]]
    r = evaluate_tracks(gt, missing)
    assert r["num_frames"] == N_FRAMES and r["silent_ticks_filled"] == N_FRAMES - len(missing)


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ('{"t_ns": 1, "tracker": "t1", "tracks": [', "not valid JSON"),
        ('{"t_ns": 1, "tracker": "t1", "tracks": [{"id": 1, "y": 2.0}]}', "'x'"),
        ('{"tracker": "t1", "tracks": []}', "'t_ns'"),
        ('{"t_ns": 1, "tracker": "t1", "tracks": [{"id": 1, "x": NaN, "y": 2.0}]}', "non-finite"),
        ('{"t_ns": 1.5, "tracker": "t1", "tracks": []}', "t_ns"),
    ],
)
def test_malformed_line_names_the_line(tmp_path, bad, message):
    good = json.dumps(make_rows()[0])
    path = tmp_path / "bad.jsonl"
    path.write_text(good + "\n\n" + bad + "\n")
    with pytest.raises(ValueError, match=rf"line 3: .*{message}"):
        load_tracks(path)


def test_malformed_row_in_memory_names_the_row(gt):
    rows = make_rows()
    rows[4]["tracks"][0]["y"] = float("nan")
    with pytest.raises(ValueError, match="line 5"):
        evaluate_tracks(gt, rows)


def test_handoff_kept_versus_switched_identity(gt):
    kept = evaluate_tracks(gt, make_rows())
    assert kept["handoff_crossings"] == 1 and kept["handoff_kept_fraction"] == 1.0  # vehicle 1 at x=0
    # switch at the crossing (tick 19: x=-0.8, region A; tick 20: x=+0.2, region B)
    switched = evaluate_tracks(gt, make_rows(ids=lambda v, k: 100 + v if (v == 1 and k >= 20) else 10 + v))
    assert switched["handoff_crossings"] == 1 and switched["handoff_kept_fraction"] == 0.0
    # a switch well before the crossing is an id switch but not a lost handoff
    early = evaluate_tracks(gt, make_rows(ids=lambda v, k: 100 + v if (v == 1 and k >= 5) else 10 + v))
    assert early["id_switches"] == 1 and early["handoff_kept_fraction"] == 1.0
    # no match on one side: an untracked crossing
    lost = evaluate_tracks(gt, make_rows(offset=lambda v, k: 5.0 * NORMAL[v] if (v == 1 and k >= 10) else 0.0))
    assert lost["handoff_crossings"] == 0 and lost["handoff_crossings_untracked"] == 1
    assert math.isnan(lost["handoff_kept_fraction"])


def test_handoff_is_seen_only_where_the_area_reaches_the_region_border(gt):
    # the border between A and B (x = 0) lies 20 m from both: with 12 m ROIs alone vehicle 1 is never seen near it
    # (the demo scores handoff over a wider area for this reason: DemoConfig.handoff_radius_m)
    narrow = evaluate_tracks(gt, make_rows(), config=TrackingEvalConfig(roi_radius_m=12.0))
    assert narrow["handoff_crossings"] == 0 and narrow["handoff_crossings_untracked"] == 0
    wide = evaluate_tracks(gt, make_rows(), config=TrackingEvalConfig(roi_radius_m=12.0, eval_radius_m=25.0))
    assert wide["handoff_crossings"] == 1 and wide["handoff_kept_fraction"] == 1.0


def test_handoff_measure_directly():
    cams = {"A": (-20.0, 0.0), "B": (20.0, 0.0)}
    frames = [FrameMatch(k * 100_000_000, {7: np.array([-1.0 + k, 0.0])}, {}, {7: ("t", 1 if k < 2 else 2)})
              for k in range(4)]
    r = handoff_measure(frames, cams)
    assert r["handoff_crossings"] == 1 and r["handoff_crossings_kept"] == 0 and r["handoff_kept_fraction"] == 0.0


def test_evaluate_many_fused_against_single_cameras(gt):
    def single(cam: str, off: float) -> list[dict]:
        c = np.array(CAMS[cam][0][:2])
        rows = make_rows(offset=lambda v, k: off * NORMAL[v])
        for r in rows:  # the camera's own tracker only has the vehicles in its area
            r["tracks"] = [t for t in r["tracks"] if np.hypot(t["x"] - c[0], t["y"] - c[1]) <= 25.0]
        return rows

    out = evaluate_many(gt, {"fused": make_rows(), "A": single("A", 0.3), "B": single("B", 0.2)})
    fused, a, b = out["sources"]["fused"], out["sources"]["A"], out["sources"]["B"]
    assert fused["cameras"] == ["A", "B"] and a["cameras"] == ["A"] and b["cameras"] == ["B"]
    assert a["gt_vehicles"] == 3 and b["gt_vehicles"] == 2  # GT restricted to each camera's area
    assert a["mota"] == 1.0 and b["mota"] == 1.0
    assert out["traj_err_best_single_camera_m"] == pytest.approx(0.2, abs=2e-3)
    assert out["best_single_camera"] == "B"
    assert fused["traj_err_in_roi_m"] < out["traj_err_best_single_camera_m"]
    with pytest.raises(ValueError, match="unknown camera"):
        evaluate_many(gt, {"x": []}, cameras=["Z"])


def _write_fisheye_and_pinhole_recording(out: Path) -> Path:
    """Fisheye F at the origin (its 25 m ROI) and pinhole T 100 m east looking east (200 m ROI; its image holds
    x > 100). Vehicle 1 ahead of T; 2 behind T, 60 m from F, seen by F alone; 3 in F's disc; 4 in T's image but
    hidden from it (visible fraction 0.1), seen by F. Each camera lists every vehicle (`in_image` as it sees it)."""
    (out / "gt").mkdir(parents=True)
    where = {1: (110.0, 0.0), 2: (60.0, 3.0), 3: (10.0, 2.0), 4: (120.0, -3.0)}
    cameras = []
    for name, kind, x in (("F", "fisheye", 0.0), ("T", "pinhole", 100.0)):
        cameras.append({"name": name, "kind": kind, "modality": "visible", "width": 1280, "height": 960,
                        "pose": {"position_m": [x, 0.0, 10.0], "r_cam_from_world": np.eye(3).tolist()},
                        "frames": N_FRAMES, "frame_dir": f"frames/{name}", "gt": f"gt/{name}.jsonl",
                        "landmarks": f"landmarks/{name}.json"})
        lines = []
        for k in range(N_FRAMES):
            t = T0 + k * 100_000_000
            vehicles = [{"id": vid, "type": "car", "lwh": [4.5, 1.8, 1.5], "yaw": 0.0, "speed": 1.0,
                         "xyz": [xy[0] + 0.1 * k, xy[1], 0.0], "in_image": name == "F" or xy[0] > 100.0,
                         "visible_fraction": 0.1 if (name, vid) == ("T", 4) else 1.0, "parked": False}
                        for vid, xy in where.items()]
            lines.append(json.dumps({"t_ns": t, "file": f"frames/{name}/{t}.jpg", "vehicles": vehicles}))
        (out / "gt" / f"{name}.jsonl").write_text("\n".join(lines) + "\n")
    return _write_meta(out, cameras)


def test_a_pinhole_cameras_area_is_in_its_own_image(tmp_path):
    """A vehicle is in a pinhole camera's 200 m area only where that camera has it in its image: vehicle 2, behind
    T and seen by F beyond F's 25 m, is in nobody's area, for the fused tracks or for T tracked alone; vehicle 4, in
    T's image but hidden from it, is T's when another camera sees it (as a fisheye's hidden vehicles are)."""
    gt = GroundTruth(_write_fisheye_and_pinhole_recording(tmp_path / "clip"))
    cfg = TrackingEvalConfig()
    t = T0 + 10 * 100_000_000
    assert set(gt.gt_objects(t, ["F", "T"], cfg)) == {1, 3, 4}
    assert set(gt.gt_objects(t, ["T"], cfg, seen_by=["F", "T"])) == {1, 4}
    assert set(gt.gt_objects(t, ["T"], cfg)) == {1}  # 4: T alone does not see it
    assert set(gt.gt_objects(t, ["F"], cfg, seen_by=["F", "T"])) == {3}

    def rows(vehicles) -> list[dict]:
        return [{"t_ns": T0 + k * 100_000_000, "tracker": "t1",
                 "tracks": [{"id": 10 + v, "x": xy[0] + 0.1 * k, "y": xy[1]} for v, xy in vehicles.items()]}
                for k in range(N_FRAMES)]

    where = {1: (110.0, 0.0), 3: (10.0, 2.0), 4: (120.0, -3.0)}  # every vehicle some camera's area holds
    out = evaluate_many(gt, {"fused": rows(where), "T": rows({1: where[1], 4: where[4]}), "F": rows({3: where[3]})})
    for name, n in (("fused", 3), ("T", 2), ("F", 1)):
        r = out["sources"][name]
        assert r["mota"] == 1.0 and r["recall"] == 1.0 and r["gt_vehicles"] == n, name
    assert out["mota_best_single_camera"] == 1.0


def _line(t_s: float, tracks: list[tuple[int, float, float]], tracker: str = "t1") -> dict:
    return {"t_ns": int(1e9 * t_s), "tracker": tracker, "tracks": [{"id": i, "x": x, "y": y} for i, x, y in tracks]}


def test_handoff_without_truth_counts_kept_and_broken_crossings():
    from eval.tracking import handoff_without_truth

    cams = {"W": (-20.0, 0.0), "E": (20.0, 0.0)}  # the boundary is x = 0
    rows = []
    # vehicle 1 drives east across x = 0 under one id: kept
    # vehicle 2 drives west, its id 2 ends at x = 1 and id 3 starts 0.5 s later at x = -4, 2 m aside: broken
    # vehicle 4 ends at x = 15 going east, in the east region, and nothing follows: not a crossing
    for k in range(10):
        t = k * 0.25
        tr = [(1, -10.0 + 10 * t, 3.0)]
        if t <= 1.0:
            tr.append((2, 11.0 - 10 * t, -3.0))
        if t >= 1.5:
            tr.append((3, 11.0 - 10 * t, -1.0))  # 2 m off the extrapolated track
        if t <= 1.0:
            tr.append((4, 5.0 + 10 * t, 10.0))
        rows.append(_line(t, tr))
    r = handoff_without_truth(rows, cams)
    assert (r["crossings_kept"], r["crossings_broken"]) == (1, 1)
    assert r["handoff_kept_fraction"] == 0.5
    # a new track far from where the ended one would be is not its continuation
    r = handoff_without_truth(rows, cams, join_m=0.5)
    assert r["crossings_broken"] == 0
    # nor one that starts too late
    assert handoff_without_truth(rows, cams, max_gap_s=0.3)["crossings_broken"] == 0
    # a track along the border, flickering across it for 0.1-0.2 s at a time, and once into the east for 1 s
    flicker = [_line(k * 0.1, [(7, 0.2 if k in (5, 6, 20, 31) or 40 <= k < 50 else -0.2, 0.0)]) for k in range(60)]
    assert handoff_without_truth(flicker, cams)["crossings_kept"] == 2  # the settled stay: in and out again
    assert handoff_without_truth(flicker, cams, settle_s=0.0)["crossings_kept"] == 8
    with pytest.raises(ValueError, match="cameras' ground positions"):
        handoff_without_truth(rows, {})
    with pytest.raises(ValueError, match="no tracks to measure"):  # not a NaN fraction of nothing
        handoff_without_truth([], cams)


def test_json_documents_for_other_programs_have_no_nan():
    from shared.jsonio import dumps, strict

    doc = {"a": float("nan"), "b": [np.float32(1.5), np.inf, np.int64(3)], "c": np.array([1.0, np.nan]), "d": "x"}
    assert strict(doc) == {"a": None, "b": [1.5, None, 3], "c": [1.0, None], "d": "x"}
    assert json.loads(dumps(doc)) == strict(doc)


def test_tracks_moved_on_are_scored_where_their_vehicles_are_later(gt):
    """Tracks exactly on their vehicles with their true velocities: moved on 0.3 s they are still on them (the
    vehicles drive straight at constant speed), as they were they lag by speed x 0.3 s; their grown covariance
    holds the truth. Tracks without a velocity's covariance are left out."""
    speed = {1: np.array([10.0, 0.0]), 2: np.array([0.0, 4.0]), 3: np.array([1.5, 2.0]), 5: np.zeros(2)}
    rows = make_rows()
    for row in rows:
        for t in row["tracks"]:
            t["vx"], t["vy"] = (float(c) for c in speed[t["id"] - 10])
            t["xy_cov"], t["velocity_cov"] = [[0.04, 0.0], [0.0, 0.04]], [[0.01, 0.0], [0.0, 0.01]]
    r = evaluate_tracks(gt, rows, config=TrackingEvalConfig(predict_horizons_s=(0.3,)))
    assert r["ahead_300ms_n"] > 3 * N_FRAMES
    assert r["ahead_300ms_err_m"] < 0.01 and r["ahead_300ms_cov_within_95"] == 1.0
    lag = {v: 0.3 * float(np.hypot(*s)) for v, s in speed.items()}
    assert min(lag.values()) < r["ahead_300ms_stale_err_m"] < max(lag.values())
    assert r["ahead_300ms_moving_stale_err_m"] > r["ahead_300ms_stale_err_m"]  # the parked one lags by nothing
    assert r["ahead_300ms_stale_cov_within_95"] < 0.5  # vehicle 1 lags by 3 m against a 0.2 m sigma: out
    assert "ahead_100ms_n" not in r
    for row in rows:
        for t in row["tracks"]:
            del t["velocity_cov"]
    assert evaluate_tracks(gt, rows, config=TrackingEvalConfig(predict_horizons_s=(0.3,)))["ahead_300ms_n"] == 0
