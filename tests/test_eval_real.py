"""roadside eval real: hand labels vs detections on the ground, on a synthetic camera with known answers, and
on the real State/Ellsworth frames when ../shared/data and the site's masks are present."""

from __future__ import annotations

import json
from datetime import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.masks import LookupMasks
from eval.real import evaluate_real, evaluate_tracks_real, label_sheet, load_labels
from roadside.cli import main
from shared.decode import Detections
from shared.settings import LocalizeSettings

W, H = 320, 240
M_PER_PX = 0.25  # the ROI (25 m) is 100 px around the camera's foot at the image centre
CX, CY = 160.0, 120.0
REPO = Path(__file__).resolve().parents[1]
FOOTAGE = REPO.parent / "shared" / "data" / "state_ellsworth" / "sample_data"
SITE = REPO / "deploy" / "sites" / "state_ellsworth"


def _site(root: Path, camera: str = "C1") -> tuple[Path, Path]:
    """Masks and two frames of one camera; returns (site folder, footage folder)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xy = np.stack([(u - CX) * M_PER_PX, (CY - v) * M_PER_PX], axis=2)
    meta = {"format": "roadside-lookup-masks", "version": 1, "kind": "fisheye", "width": W, "height": H,
            "geo_origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0},
            "camera": {"cx": CX, "cy": CY, "pose": {"position_m": [0.0, 0.0, 10.0]}}}
    LookupMasks(42 + xy[..., 1] / 111e3, -83 + xy[..., 0] / 82e3, xy.astype(np.float32), np.ones((H, W), bool),
                meta).save(root / "site" / "masks" / f"{camera}.npz")
    frames = root / "footage" / f"gs_State_Ellsworth_{camera}"
    frames.mkdir(parents=True)
    for name in ("2023-12-19 11-00-41-000000.jpg", "2023-12-19 11-00-43-000000.jpg"):
        cv2.imwrite(str(frames / name), np.full((H, W), 100, np.uint8))
    return root / "site", root / "footage"


def _labels(site: Path, frames: dict, camera: str = "C1") -> None:
    (site / "labels").mkdir(parents=True, exist_ok=True)
    (site / "labels" / f"{camera}.json").write_text(json.dumps({"camera": camera, "frames": frames}))


def _detector(points_by_call: list[np.ndarray], scores: list[list[float]] | None = None):
    calls = iter(points_by_call)
    score_calls = iter(scores) if scores is not None else None

    def detect(_grey: np.ndarray) -> Detections:
        uv = np.asarray(next(calls), np.float64).reshape(-1, 2)
        n = len(uv)
        score = np.asarray(next(score_calls), np.float64) if score_calls else np.full(n, 0.9)
        return Detections(score, uv, np.c_[uv - 5, uv + 5], np.tile([1.0, 0.0], (n, 1)),
                          np.tile([4.5, 1.8, 1.5], (n, 1)), np.zeros(n, np.int64), np.tile([1.0, 0, 0, 0, 0], (n, 1)))
    return detect


def test_counts_hits_misses_false_alarms_and_the_band_outside_the_roi(tmp_path):
    site, footage = _site(tmp_path)
    # frame 1: a vehicle 10 m east (u + 40 px) and one 25.5 m north (outside the ROI, inside the label radius)
    # frame 2: a vehicle 5 m south
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120], [160, 18]],
                   "2023-12-19 11-00-43-000000.jpg": [[160, 140]]})
    detect = _detector([
        # frame 1: a hit 1 m off, a detection 1 m from the outside vehicle (24.5 m: inside the ROI, no false alarm),
        # and a false alarm 10 m west
        [[204, 120], [160, 22], [120, 120]],
        # frame 2: 2 m off (beyond MATCH_M = 1.5 m): a miss and a false alarm
        [[160, 148]],
    ])
    r = evaluate_real(site / "labels", footage, site / "masks", detect)
    c = r["per_camera"]["C1"]
    assert (c["labels"], c["detections"], c["true_positives"]) == (2, 3, 1)
    assert c["precision"] == pytest.approx(1 / 3, abs=1e-4) and c["recall"] == 0.5
    assert c["loc_err_median_m"] == pytest.approx(1.0, abs=1e-3)
    assert r["overall"]["true_positives"] == 1


def test_a_hit_from_just_outside_the_roi_on_a_vehicle_inside_counts_as_a_detection():
    """A label at 24.6 m matched by a detection at 25.4 m: one true positive of one detection, precision 1, never
    more (it used to be a true positive of no detection)."""
    from eval.real import ROI_M, _count

    assert ROI_M == 25.0
    acc = {"tp": 0, "n_det": 0, "n_lab": 0, "errors": []}
    _count(acc, np.array([[25.4, 0.0], [0.0, 10.0]]), np.array([[24.6, 0.0], [0.0, 10.2]]), np.zeros(2))
    assert (acc["tp"], acc["n_det"], acc["n_lab"]) == (2, 2, 2)


def test_the_curve_scores_every_threshold_from_one_detector_pass(tmp_path):
    site, footage = _site(tmp_path)
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120]], "2023-12-19 11-00-43-000000.jpg": [[160, 140]]})
    # the hit in frame 1 scores 0.5, its false alarm 0.2; frame 2's hit scores 0.25
    detect = _detector([[[200, 121], [120, 120]], [[160, 141]]], [[0.5, 0.2], [0.25]])
    r = evaluate_real(site / "labels", footage, site / "masks", detect, score_thr=0.3, curve=(0.1, 0.22, 0.6))
    assert (r["overall"]["true_positives"], r["overall"]["detections"]) == (1, 1)  # at 0.3
    assert [(c["true_positives"], c["detections"]) for c in r["curve"]] == [(2, 3), (2, 2), (0, 0)]
    assert r["curve"][1]["precision"] == 1.0 and r["curve"][1]["recall"] == 1.0 and r["curve"][2]["recall"] == 0.0


def test_exclusion_zones_drop_the_detections_in_them_as_localize_does(tmp_path):
    site, footage = _site(tmp_path)
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120]]})
    def detect():  # a hit and a false alarm at (120, 120)
        return _detector([[[200, 121], [120, 120]]], [[0.5, 0.5]])

    plain = evaluate_real(site / "labels", footage, site / "masks", detect())
    assert (plain["overall"]["true_positives"], plain["overall"]["detections"]) == (1, 2)
    zone = [[(114, 114), (126, 114), (126, 126), (114, 126)]]
    r = evaluate_real(site / "labels", footage, site / "masks", detect(), exclude_px={"C1": zone, "C9": zone})
    assert (r["overall"]["true_positives"], r["overall"]["detections"]) == (1, 1)
    assert r["overall"]["precision"] == 1.0
    # a vehicle standing in a zone is still a label to find: the zone drops detections, not labels
    over_label = [[(194, 114), (206, 114), (206, 126), (194, 126)]]
    r = evaluate_real(site / "labels", footage, site / "masks", detect(), exclude_px={"C1": over_label})
    assert (r["overall"]["labels"], r["overall"]["true_positives"], r["overall"]["detections"]) == (1, 0, 1)


def test_a_second_peak_on_one_vehicle_is_dropped_as_localize_drops_it(tmp_path):
    site, footage = _site(tmp_path)
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120]]})
    def detect():  # heading east (+u): a hit, and a weaker peak 13 px = 3.25 m along the same vehicle
        return _detector([[[200, 121], [213, 121]]], [[0.6, 0.4]])

    plain = evaluate_real(site / "labels", footage, site / "masks", detect())
    assert (plain["overall"]["true_positives"], plain["overall"]["detections"]) == (1, 2)
    r = evaluate_real(site / "labels", footage, site / "masks", detect(), curve=(0.5,),
                     localize=LocalizeSettings(footprint_overlap=1.5, footprint_merge=False))
    assert (r["overall"]["true_positives"], r["overall"]["detections"]) == (1, 1)
    assert (r["curve"][0]["true_positives"], r["curve"][0]["detections"]) == (1, 1)
    # merged, the kept peak moves to the middle of both (1.625 m east of the label: beyond the 1.5 m match) at the
    # lowest threshold; at 0.5 the weaker peak is not among the detections localize would get, so nothing merges
    # and the hit stays
    r = evaluate_real(site / "labels", footage, site / "masks", detect(), curve=(0.5,),
                     localize=LocalizeSettings(footprint_overlap=1.5, footprint_merge=True))
    assert (r["overall"]["true_positives"], r["overall"]["detections"]) == (0, 1)
    assert (r["curve"][0]["true_positives"], r["curve"][0]["detections"]) == (1, 1)


def test_perfect_detections_score_one(tmp_path):
    site, footage = _site(tmp_path)
    frames = {"2023-12-19 11-00-41-000000.jpg": [[150, 100], [180, 130]], "2023-12-19 11-00-43-000000.jpg": []}
    _labels(site, frames)
    for p in (site / "labels").glob("*.json"):  # copied from a Mac: AppleDouble files beside the labels, not labels
        (site / "labels" / f"._{p.name}").write_bytes(b"\x00\x05\x16\x07")
    r = evaluate_real(site / "labels", footage, site / "masks", _detector([frames[k] for k in sorted(frames)]))
    assert r["overall"]["precision"] == 1.0 and r["overall"]["recall"] == 1.0


def _tracks_file(path: Path, lines: list[tuple[int, list[tuple]]]) -> Path:
    """Tracks lines of (t_ns, [(id, x, y) or (id, x, y, xy_cov), ...])."""
    path.write_text("".join(json.dumps({"t_ns": t, "tracker": "t1", "tracks": [
        {"id": tr[0], "x": tr[1], "y": tr[2], **({"xy_cov": tr[3]} if len(tr) > 3 else {})} for tr in tracks]}) + "\n"
        for t, tracks in lines))
    return path


def test_tracks_are_interpolated_to_each_labelled_frame_and_scored_like_detections(tmp_path):
    from services.ingest.sources import capture_time_from_name

    site, _ = _site(tmp_path)
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120]], "2023-12-19 11-00-43-000000.jpg": [[160, 140]]})
    t1 = capture_time_from_name("2023-12-19 11-00-41-000000.jpg")
    ms = 1_000_000
    tracks = _tracks_file(tmp_path / "tracks.jsonl", [
        # around frame 1 (ticks 50 ms before and 150 ms after it): track 1 drives from 9 to 13 m east, so it is at
        # 10 m at the frame (the label); track 2 is only in the earlier, nearer tick (a false alarm 10 m west);
        # track 3 only in the later, farther one (not there yet: left out)
        (t1 - 50 * ms, [(1, 9.0, 0.0), (2, -10.0, 0.0)]),
        (t1 + 150 * ms, [(1, 13.0, 0.0), (3, 0.0, 10.0)]),
        # frame 2 (2 s later) has no tick within 250 ms: not scored
        (t1 + 1500 * ms, [(1, 0.0, -5.0)]),
    ])
    r = evaluate_tracks_real(site / "labels", tracks, site / "masks")
    c = r["per_camera"]["C1"]
    assert r["frames_without_tracks"] == 1 and c["frames"] == 1
    assert (c["labels"], c["detections"], c["true_positives"]) == (1, 2, 1)
    assert c["loc_err_median_m"] == pytest.approx(0.0, abs=1e-3)
    assert r["overall"]["precision"] == 0.5 and r["overall"]["recall"] == 1.0
    assert r["pos_cov_n"] == 0  # no xy_cov in these tracks
    # track 1 half a metre east of its label with a sigma of 0.6 m each way, then 0.25 m: squared distances 0.69, 4,
    # the covariance interpolated between the ticks like the position
    for sigma, nees in ((0.6, 0.25 / 0.36), (0.25, 4.0)):
        cov = [[sigma**2, 0.0], [0.0, sigma**2]]
        with_cov = _tracks_file(tmp_path / "cov.jsonl", [(t1 - 50 * ms, [(1, 9.5, 0.0, cov)]),
                                                         (t1 + 150 * ms, [(1, 13.5, 0.0, cov)])])
        rc = evaluate_tracks_real(site / "labels", with_cov, site / "masks")
        assert rc["pos_cov_n"] == 1 and rc["pos_cov_nees_mean"] == pytest.approx(nees, rel=1e-3)
        assert rc["pos_cov_within_95"] == 1.0 and rc["pos_cov_within_1sigma"] == (1.0 if nees <= 1 else 0.0)
    # the same tracks in a site frame 100 m west of the masks' origin: every x is 100 m larger
    from shared.geo import GeoFrame

    masks_geo = GeoFrame(42.0, -83.0, 0.0)
    ll = masks_geo.to_geodetic(np.array([[-100.0, 0.0]]))[0]
    shifted = _tracks_file(tmp_path / "shifted.jsonl", [
        (t1 - 50 * ms, [(1, 109.0, 0.0), (2, 90.0, 0.0)]), (t1 + 150 * ms, [(1, 113.0, 0.0), (3, 100.0, 10.0)])])
    r2 = evaluate_tracks_real(site / "labels", shifted, site / "masks", GeoFrame(ll[0], ll[1], 0.0))
    assert (r2["overall"]["true_positives"], r2["overall"]["detections"]) == (1, 2)
    # frames named in Ann Arbor's clock (ingest.timezone), the tracks at the UTC times ingest gave them: 5 h later
    from zoneinfo import ZoneInfo

    later = _tracks_file(tmp_path / "later.jsonl", [(t1 + 5 * 3600 * 10**9 - 50 * ms, [(1, 9.0, 0.0)]),
                                                    (t1 + 5 * 3600 * 10**9 + 150 * ms, [(1, 13.0, 0.0)])])
    r3 = evaluate_tracks_real(site / "labels", later, site / "masks", tz=ZoneInfo("America/Detroit"))
    assert r3["overall"]["true_positives"] == 1
    with pytest.raises(ValueError, match="no tracks within 250 ms of any labelled frame"):
        evaluate_tracks_real(site / "labels", later, site / "masks")  # read as UTC: 5 h apart
    # tracks of another time (a simulated run's): nothing to score, said so rather than precision None
    other = _tracks_file(tmp_path / "other.jsonl", [(t1 - 3600 * 10**9, [(1, 9.0, 0.0)])])
    with pytest.raises(ValueError, match=r"other\.jsonl: no tracks within 250 ms of any labelled frame \(2 frames\)"):
        evaluate_tracks_real(site / "labels", other, site / "masks")
    with pytest.raises(ValueError, match=r"tracks\.jsonl: line 1: missing key 'tracks'"):
        (tmp_path / "tracks.jsonl").write_text(json.dumps({"t_ns": 1, "tracker": "t"}) + "\n")
        evaluate_tracks_real(site / "labels", tmp_path / "tracks.jsonl", site / "masks")


def test_bad_labels_name_the_problem(tmp_path):
    site, footage = _site(tmp_path)
    path = tmp_path / "l.json"
    path.write_text(json.dumps({"frames": {"2023-12-19 11-00-20-000000.jpg": [[10, 10]]}}))
    with pytest.raises(ValueError, match=r"11-00-20-000000\.jpg' is before 11:00:40: only held-out frames"):
        load_labels(path, W, H, time(11, 0, 40))
    path.write_text(json.dumps({"frames": {"2023-12-19 11-00-41-000000.jpg": [[10, 10], [400, 10]]}}))
    with pytest.raises(ValueError, match=r"label 1 \(400.0, 10.0\) is outside the 320x240 image"):
        load_labels(path, W, H)
    for labels in (None, 5, [{"u": 1, "v": 2}], [[639, 77, 805, 120]], [[1, "2"]]):
        path.write_text(json.dumps({"frames": {"2023-12-19 11-00-41-000000.jpg": labels}}))
        with pytest.raises(ValueError, match=r"11-00-41-000000\.jpg': labels must be a list of \[u, v\] pixel pairs"):
            load_labels(path, W, H)
    path.write_text('{"frames": {"2023-12-19 11-00-41-000000.jpg": [], "2023-12-19 11-00-41-000000.jpg": []}}')
    with pytest.raises(ValueError, match=r"11-00-41-000000\.jpg' is given twice"):
        load_labels(path, W, H)
    path.write_text("{")
    with pytest.raises(ValueError, match=r"l\.json: not valid JSON"):
        load_labels(path, W, H)
    with pytest.raises(ValueError, match="label file not found"):
        load_labels(tmp_path / "none.json", W, H)
    _labels(site, {"2023-12-19 11-00-45-000000.jpg": [[100, 100]]})
    with pytest.raises(ValueError, match=r"11-00-45-000000\.jpg: labelled frame is missing or unreadable"):
        evaluate_real(site / "labels", footage, site / "masks", _detector([[]]))
    with pytest.raises(ValueError, match="no label files"):
        evaluate_real(tmp_path / "nowhere", footage, site / "masks", _detector([]))


def test_label_sheet_draws_marks_inside_the_label_radius(tmp_path):
    site, _ = _site(tmp_path)
    from calibration.masks import load_masks

    sheet = label_sheet(np.full((H, W), 100, np.uint8), load_masks(site / "masks" / "C1.npz"), zoom=2,
                        marks=np.array([[160.0, 120.0]]))
    assert sheet.shape[0] > 200 and sheet.shape[1] > 200
    assert (sheet[..., 2] > 200).any()  # the red cross


@pytest.mark.skipif(not FOOTAGE.is_dir(), reason="../shared/data/state_ellsworth is absent (real footage)")
@pytest.mark.skipif(not (SITE / "masks" / "SE.npz").is_file(),
                    reason="site masks not built: bash deploy/sites/state_ellsworth/calibrate.sh")
def test_the_real_labels_load_and_the_shipped_model_is_scored(capsys):
    for cam in ("NE", "NW", "SE", "SW"):
        labels = load_labels(SITE / "labels" / f"{cam}.json", 1280, 960, time(11, 0, 40))
        assert len(labels) >= 10
    assert main(["eval", "real", "--model", str(REPO / "models" / "detector_fp32.onnx"), "--site", str(SITE),
                 "--footage", str(FOOTAGE), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["overall"]["frames"] == 40 and r["overall"]["labels"] >= 100
    assert (r["footprint_overlap"], r["footprint_merge"]) == (1.5, False)  # the site's localize rule, as scored


def test_the_cli_takes_the_sites_site_yaml_as_well_as_its_folder(tmp_path, monkeypatch, capsys):
    """`eval real --site <folder>/site.yaml` looked for site.yaml/labels and site.yaml/masks: labels/ and masks/ are
    the ones beside the file, with the model's detections and with tracks alike."""
    import yaml

    import shared.inference
    from services.ingest.sources import capture_time_from_name

    site, footage = _site(tmp_path)
    (site / "site.yaml").write_text(yaml.safe_dump({"site": "t", "cameras": [
        {"name": "C1", "kind": "fisheye", "width": W, "height": H, "masks": "masks/C1.npz"}]}))
    _labels(site, {"2023-12-19 11-00-41-000000.jpg": [[200, 120]], "2023-12-19 11-00-43-000000.jpg": [[160, 140]]})

    class FakeDetector:  # the labels' own points: every label found
        def __init__(self, *_args, **_kwargs) -> None:
            self.detect = _detector([[[200, 120]], [[160, 140]]])

    monkeypatch.setattr(shared.inference, "OnnxDetector", FakeDetector)
    t1 = capture_time_from_name("2023-12-19 11-00-41-000000.jpg")
    tracks = tmp_path / "tracks.jsonl"  # rows with lat and lon too, as the CLI's site check reads them
    tracks.write_text("".join(json.dumps({"site": "t", "t_ns": t, "tracker": "t1", "tracks": [
        {"id": 1, "x": x, "y": y, "lat": 42.0 + y / 111e3, "lon": -83.0 + x / 82e3}]}) + "\n"
        for t, x, y in ((t1, 10.0, 0.0), (t1 + 2 * 10**9, 0.0, -5.0))))
    for flags in (["--model", str(tmp_path / "model.onnx")], ["--tracks", str(tracks)]):
        assert main(["eval", "real", *flags, "--site", str(site / "site.yaml"), "--footage", str(footage),
                     "--json"]) == 0, capsys.readouterr().err
        r = json.loads(capsys.readouterr().out)
        assert (r["overall"]["labels"], r["overall"]["true_positives"], r["overall"]["precision"]) == (2, 2, 1.0)
