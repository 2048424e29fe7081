"""roadside autolabel on a synthetic scene with known answers: a flat ground seen straight down at 0.1 m per
pixel, vehicles drawn as dark rectangles moving over a textured road."""

from __future__ import annotations

import json
import shutil
from datetime import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from calibration.masks import LookupMasks
from roadside.cli import main
from training.autolabel import AutolabelConfig, autolabel_camera, list_frames
from training.data import samples_from_coco

W, H = 640, 480
M_PER_PX = 0.1
CX, CY = 320.0, 240.0
HZ = 5.0
# flat rectangles: no height to deflate
CFG = AutolabelConfig(scale=1.0, vehicle_height_m=0.01, roi_m=40.0)


def _masks(path: Path, pose: bool = True) -> Path:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xy = np.stack([(u - CX) * M_PER_PX, (CY - v) * M_PER_PX], axis=2)
    meta = {"format": "roadside-lookup-masks", "version": 1, "kind": "pinhole", "width": W, "height": H,
            "geo_origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0},
            "camera": {"cx": CX, "cy": CY, **({"pose": {"position_m": [0.0, 0.0, 12.0]}} if pose else {})}}
    lat = 42.0 + xy[..., 1] / 111_000
    lon = -83.0 + xy[..., 0] / 82_000
    LookupMasks(lat, lon, xy.astype(np.float32), np.ones((H, W), bool), meta).save(path)
    return path


def _uv(xy) -> np.ndarray:
    return np.array([CX + xy[0] / M_PER_PX, CY - xy[1] / M_PER_PX])


# (start xy m, velocity m/s, length m, width m): a car going east, a car going south, a 0.6 x 0.6 m "pedestrian"
MOVERS = [((-12.0, 6.0), (10.0, 0.0), 4.5, 1.8), ((8.0, 10.0), (0.0, -8.0), 1.8, 4.5),
          ((-5.0, -12.0), (1.0, 1.0), 0.6, 0.6)]


POLE_U = 290  # 3 m west of the camera's foot, 0.8 m wide


def _frames(folder: Path, n: int = 10, extra_after: bool = True) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    road = cv2.GaussianBlur(rng.integers(90, 160, (H, W), dtype=np.uint8), (0, 0), 2)
    for k in range(n + (1 if extra_after else 0)):
        t = k / HZ
        img = cv2.cvtColor(road, cv2.COLOR_GRAY2BGR)
        for start, vel, length, width in MOVERS:
            c = _uv(np.array(start) + t * np.array(vel))
            half = np.array([length, width]) / M_PER_PX / 2
            p1, p2 = (c - half).round().astype(int), (c + half).round().astype(int)
            cv2.rectangle(img, tuple(p1), tuple(p2 - 1), (20, 20, 20), -1)
        # a lamp post in front of everything: the eastbound car passes behind it and is cut in two
        img[:, POLE_U:POLE_U + 8] = 200
        # 11:00:00.000 + t; the frame after `until` (11:00:02) must be left out
        stamp = f"2023-12-19 11-00-{int(t):02d}-{round((t % 1) * 1e6):06d}"
        cv2.imwrite(str(folder / f"{stamp}.png"), img)
    return folder


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("autolabel")
    return _frames(root / "frames"), _masks(root / "masks.npz")


def test_labels_moving_vehicles_with_centre_heading_and_drops_the_small_one(scene, tmp_path):
    frames, masks = scene
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None)
    assert report["frames"] == 10  # the 11th frame is at 11:00:02
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    labs = [a for a in doc["annotations"] if not a.get("iscrowd")]
    assert report["vehicles"] == len(labs) == 20  # two cars in ten frames
    assert report["dropped"]["too_small"] == 10  # the pedestrian: fewer pixels than min_area_px
    assert report["tracks_long_enough"] == 2
    assert report["dropped"]["merged"] >= 1  # the car behind the post
    for a in labs:
        t = doc["images"][a["image_id"]]["t_ns"] % 10**10 / 1e9
        truth = [np.array(s) + t * np.array(v) for s, v, length, _ in MOVERS if length > 1][:2]
        err = [np.hypot(*(np.array(a["ground_xy_m"]) - g)) for g in truth]
        k = int(np.argmin(err))
        assert err[k] < 0.25
        uv = np.array(a["bottom_center"]) - 0.5
        assert np.hypot(*(uv - _uv(truth[k]))) < 2.5
        want = np.array([1.0, 0.0]) if k == 0 else np.array([0.0, 1.0])  # east -> +u, south -> +v
        assert np.dot(a["heading_uv"], want) > 0.99
    # the file is a training set the detector's COCO reader takes as it is
    refs = samples_from_coco(tmp_path / "out" / "labels.json")
    assert len(refs) == 10 and sum(r.n_positive for r in refs) == 20
    assert refs[0].load().image.shape == (H, W)


@pytest.mark.parametrize("ignore_small", [True, False])
def test_a_footprint_too_small_for_a_vehicle_is_an_ignore_region_or_dropped(scene, tmp_path, ignore_small):
    frames, masks = scene
    cfg = AutolabelConfig(scale=1.0, vehicle_height_m=0.01, roi_m=40.0, length_m=(5.0, 20.0),
                          ignore_small=ignore_small)
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=cfg, log=None)
    assert report["vehicles"] == 0  # 4.5 m cars are short of this config's 5 m
    small = report["ignored_small"] if ignore_small else report["dropped"]["not_vehicle_size"]
    assert small >= 20  # two cars in ten frames (the one behind the post in two pieces where it is cut)
    assert (report["dropped"]["not_vehicle_size"] if ignore_small else report["ignored_small"]) == 0


class _Teacher:
    """A detector that sees a parked car at (10, -8) m (which the background model cannot) and the
    eastbound car (which already has a label)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self, grey: np.ndarray) -> SimpleNamespace:
        assert grey.shape == (H, W)
        moving = _uv(np.array(MOVERS[0][0]) + self.t * np.array(MOVERS[0][1]))
        self.t += 1 / HZ
        uv = np.array([_uv((10.0, -8.0)), moving, _uv((0.0, 0.0))])
        half = np.array([20.0, 10.0])
        box = np.column_stack([uv - half, uv + half])
        return SimpleNamespace(score=np.array([0.3, 0.9, 0.05]), uv=uv, box=box)


def test_teacher_detections_away_from_the_labels_become_ignore_regions(scene, tmp_path):
    frames, masks = scene
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                              teacher=_Teacher())
    assert report["vehicles"] == 20 and report["ignored_teacher"] == 10  # the parked car, once per frame
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    parked = _uv((10.0, -8.0)) + 0.5  # COCO coordinates
    crowd = [a for a in doc["annotations"] if a.get("iscrowd") and abs(a["bbox"][0] + 20 - parked[0]) < 5]
    assert len(crowd) == 10 and all(a["bbox"][2:] == [40.0, 20.0] for a in crowd)
    # the teacher's box is in pixel-centre coordinates: in COCO's its corner is half a pixel further on
    assert all(a["bbox"][:2] == pytest.approx(parked - [20.0, 10.0], abs=1e-9) for a in crowd)


def test_outside_the_roi_is_blanked_and_a_blob_bigger_than_a_vehicle_is_ignored(scene, tmp_path):
    frames, masks = scene
    cfg = AutolabelConfig(scale=1.0, vehicle_height_m=0.01, roi_m=16.0, length_m=(1.0, 1.5), width_m=(0.3, 1.2))
    autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=cfg, log=None)
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    # 4.5 x 1.8 m cars are bigger than this config's vehicles: ignore regions, never positives
    assert doc["annotations"] and all(a.get("iscrowd") for a in doc["annotations"])
    img = cv2.imread(str(tmp_path / "out" / doc["images"][0]["file_name"]), cv2.IMREAD_GRAYSCALE)
    corner = img[:20, :20]  # 38+ m from the camera's foot
    assert corner.min() == corner.max()


def test_bad_input_names_the_problem(scene, tmp_path):
    frames, masks = scene
    with pytest.raises(ValueError, match="frames folder not found"):
        autolabel_camera(tmp_path / "nope", masks, tmp_path / "o", "CAM", cfg=CFG)
    with pytest.raises(ValueError, match="no camera pose"):
        autolabel_camera(frames, _masks(tmp_path / "nopose.npz", pose=False), tmp_path / "o", "CAM", cfg=CFG)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "2023-12-19 11-00-00-000000.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match=r"11-00-00-000000\.jpg: not a readable image"):
        autolabel_camera(bad, masks, tmp_path / "o", "CAM", cfg=CFG)
    (bad / "2023-12-19 11-00-00-000000.jpg").unlink()
    cv2.imwrite(str(bad / "2023-12-19 11-00-01-000000.png"), np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(ValueError, match=r"11-00-01-000000.png: image is 100x100, the masks are for 640x480"):
        autolabel_camera(bad, masks, tmp_path / "o", "CAM", cfg=CFG)
    (bad / "frame.png").write_bytes(b"")
    with pytest.raises(ValueError, match=r"frame\.png: no capture time"):
        list_frames(bad)
    with pytest.raises(ValueError, match="no frames before 10:00:00"):
        list_frames(frames, until=time(10, 0, 0))
    # footage copied from a Mac: an AppleDouble `._<name>` beside each image is not a frame (as for ingest)
    mac = tmp_path / "mac"
    shutil.copytree(frames, mac)
    for p in sorted(mac.iterdir()):
        (mac / f"._{p.name}").write_bytes(b"\x00\x05\x16\x07 resource fork")
    assert [t for t, _ in list_frames(mac)] == [t for t, _ in list_frames(frames)]
    with pytest.raises(ValueError, match="length_m"):
        AutolabelConfig(length_m=(5.0, 2.0))


def test_cli_writes_the_report(scene, tmp_path, capsys):
    frames, masks = scene
    assert main(["autolabel", "--frames", str(frames), "--masks", str(masks), "--camera", "CAM",
                 "--out", str(tmp_path / "o"), "--until", "11:00:02", "--roi-m", "40"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 10 and report["camera"] == "CAM"
    assert main(["autolabel", "--frames", str(frames), "--masks", str(masks), "--camera", "CAM",
                 "--out", str(tmp_path / "o"), "--until", "noon"]) == 2
    assert "--until must be a time of day" in capsys.readouterr().err
    before = (tmp_path / "o" / "labels.json").read_bytes()
    for flags, message in [(["--camera", "CAM", "--truth", str(tmp_path / "none")], "not a recording"),
                           (["--camera", "../CAM"], "camera name must be 1-64 letters")]:
        assert main(["autolabel", "--frames", str(frames), "--masks", str(masks), *flags,
                     "--out", str(tmp_path / "o"), "--until", "11:00:02"]) == 2
        assert message in capsys.readouterr().err
    assert (tmp_path / "o" / "labels.json").read_bytes() == before  # checked before anything was written


def test_track_labels_are_written_in_cocos_pixel_convention(scene, tmp_path, monkeypatch):
    """A label from the pipeline's tracks has its box in pixel-centre coordinates, as its bottom centre: both get
    COCO's half pixel (the box once did not, and training read it back half a pixel up and left)."""
    import training.autolabel as autolabel

    frames, masks = scene
    label = {"uv": np.array([100.0, 50.0]), "box": np.array([90.0, 40.0, 110.0, 60.0]),
             "heading_uv": np.array([1.0, 0.0])}
    monkeypatch.setattr(autolabel, "label_from_track", lambda _v, _view: label)
    tracks = SimpleNamespace(at=lambda _t: [SimpleNamespace(xy=np.array([15.0, -15.0]), yaw=0.0, key="k")],
                             times=[0, 2**62], lines_after_end=0)  # a teacher whose tracks span every frame
    monkeypatch.setattr(autolabel, "TrackTeacher", lambda _path, t_end_ns: tracks)
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                              tracks=tmp_path / "tracks.jsonl")
    assert report["from_tracks"] == 10
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    got = [a for a in doc["annotations"] if a.get("from_tracks")]
    assert len(got) == 10
    for a in got:
        assert a["bbox"] == [90.5, 40.5, 20.0, 20.0] and a["bottom_center"] == [100.5, 50.5]
    # read back for training: the box and the bottom centre where the label put them
    s = samples_from_coco(tmp_path / "out" / "labels.json")[0].load()
    k = int(np.argmin(np.abs(s.bottom_uv - label["uv"]).sum(axis=1)))
    np.testing.assert_allclose(s.box[k], label["box"])
    np.testing.assert_allclose(s.bottom_uv[k], label["uv"])


def _truth_recording(path: Path, times: list[int]) -> Path:
    """A simulator recording of the scene's camera with no vehicles at the given frame times."""
    camera = {"name": "CAM", "kind": "pinhole", "width": W, "height": H, "fx": 300.0, "fy": 300.0, "cx": CX, "cy": CY,
              "pose": {"position_m": [0.0, 0.0, 12.0], "yaw_deg": 0.0, "pitch_deg": 90.0}, "gt": "gt/CAM.jsonl"}
    (path / "gt").mkdir(parents=True)
    (path / "recording.json").write_text(json.dumps({"format": "roadside-recording", "version": 1,
                                                     "cameras": [camera]}))
    (path / "gt" / "CAM.jsonl").write_text("".join(json.dumps({"t_ns": t, "vehicles": []}) + "\n" for t in times))
    return path


def test_cli_checks_that_the_truth_recording_has_every_frames_time_before_labelling(scene, tmp_path, capsys):
    """`autolabel --truth` with a recording of other frames once labelled everything and then stopped with a
    KeyError traceback: the times are checked first, and the first frame without truth is named."""
    frames, masks = scene
    listed = list_frames(frames, until=time(11, 0, 2))
    argv = ["autolabel", "--frames", str(frames), "--masks", str(masks), "--camera", "CAM", "--until", "11:00:02",
            "--roi-m", "40"]
    other = _truth_recording(tmp_path / "other", [t for t, _ in listed[:-1]] + [listed[-1][0] + 1])
    assert main([*argv, "--out", str(tmp_path / "o"), "--truth", str(other)]) == 2
    err = capsys.readouterr().err
    assert f"{listed[-1][1]}: the truth recording {other} has no ground truth of CAM at its capture time" in err
    assert not (tmp_path / "o").exists()  # nothing written
    assert main([*argv, "--out", str(tmp_path / "o"), "--truth", str(other), "--camera", "NE"]) == 2
    assert "has no camera 'NE' (has: CAM)" in capsys.readouterr().err
    same = _truth_recording(tmp_path / "same", [t for t, _ in listed])
    assert main([*argv, "--out", str(tmp_path / "o"), "--truth", str(same)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["score"]["true_vehicles"] == 0 and report["score"]["labels"] == report["vehicles"] > 0


def _epoch_frames(scene_frames: Path, folder: Path) -> Path:
    """The scene's frames named as a simulator names them: UTC nanoseconds since the epoch (11:00:00 UTC + t)."""
    from datetime import UTC, datetime

    folder.mkdir()
    t0 = int(datetime(2023, 12, 19, 11, 0, 0, tzinfo=UTC).timestamp()) * 10**9
    for k, (_, path) in enumerate(list_frames(scene_frames)):
        (folder / f"{t0 + k * 200_000_000}.png").write_bytes(path.read_bytes())
    return folder


def test_until_is_the_clock_written_in_the_names_whatever_the_time_zone(scene, tmp_path, capsys):
    """--until once moved with --timezone on frames named by epoch time (a simulator's): read in Ann Arbor's zone,
    every frame of 11:00 UTC was before 11:00:02 (06:00 there), and the held-out frame was labelled; --truth's
    check read the names as UTC whatever --timezone said, so it checked other times than the labels got."""
    from zoneinfo import ZoneInfo

    frames, masks = scene
    epoch = _epoch_frames(frames, tmp_path / "epoch")
    detroit = ZoneInfo("America/Detroit")
    for folder in (frames, epoch):  # date-time names: as written; epoch names: their UTC time of day
        for tz in (detroit, ZoneInfo("UTC")):
            assert len(list_frames(folder, time(11, 0, 2), tz)) == 10
    argv = ["autolabel", "--masks", str(masks), "--camera", "CAM", "--until", "11:00:02", "--roi-m", "40",
            "--timezone", "America/Detroit"]
    assert main([*argv, "--frames", str(epoch), "--out", str(tmp_path / "e")]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 10
    # the truth at the capture times the labels get in that zone (5 h after the names read as UTC): accepted
    local = [t for t, _ in list_frames(frames, time(11, 0, 2), detroit)]
    truth = _truth_recording(tmp_path / "truth", local)
    assert main([*argv, "--frames", str(frames), "--out", str(tmp_path / "o"), "--truth", str(truth)]) == 0
    assert json.loads(capsys.readouterr().out)["score"]["labels"] > 0


def test_area_leaves_out_the_frames_at_or_after_until(tmp_path, capsys):
    """`roadside area` read every n-th frame of the whole folder, a held-out slice's too: --until as `static` has."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, x0 in enumerate((100, 120, 10)):  # the frame at 11:00:02 shows a lit patch further left
        img = np.zeros((H, W), np.uint8)
        img[:, x0:500] = 200
        cv2.imwrite(str(folder / f"2023-12-19 11-00-0{k}-000000.png"), img)
    assert main(["area", "--frames", str(folder), "--every", "1", "--until", "11:00:02"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 2 and out["detect_area_px"] == [100, 0, 500, H] and out["until"] == "11:00:02"
    assert main(["area", "--frames", str(folder), "--every", "1"]) == 0  # without it, every frame
    assert json.loads(capsys.readouterr().out)["detect_area_px"] == [10, 0, 500, H]
    assert main(["area", "--frames", str(folder), "--until", "11:00:00"]) == 2
    assert "no frames before 11:00:00" in capsys.readouterr().err


def _truth_with(path: Path, t_ns: int, vehicles: list[dict]) -> Path:
    _truth_recording(path, [t_ns])
    (path / "gt" / "CAM.jsonl").write_text(json.dumps({"t_ns": t_ns, "vehicles": vehicles}) + "\n")
    return path


def test_a_label_on_any_true_vehicle_is_right_though_recall_counts_only_the_moving_visible_ones(tmp_path):
    """score_labels matched the labels only against the vehicles counted for recall: a label on a parked car, a
    mostly hidden one or one just outside the ROI counted as wrong."""
    from training.autolabel import score_labels

    def vehicle(xy, parked=False, visible=1.0):
        return {"xyz": [*xy, 0.0], "yaw": 0.0, "in_image": True, "visible_fraction": visible, "parked": parked}

    truth = _truth_with(tmp_path / "rec", 1000, [vehicle((5.0, 0.0)), vehicle((-5.0, 5.0), parked=True),
                                                 vehicle((0.0, -8.0), visible=0.2), vehicle((0.0, 31.0))])
    labels = [(5.2, 0.0), (-5.0, 5.3), (0.1, -8.0), (0.0, 30.5), (-9.0, -9.0)]  # the last one on nothing
    doc = {"info": {"config": {"roi_m": 30.0}}, "images": [{"id": 0, "file_name": "x.png", "camera": "CAM",
                                                           "t_ns": 1000}],
           "annotations": [{"id": k, "image_id": 0, "category_id": 0, "bbox": [0, 0, 1, 1], "ground_xy_m": list(xy),
                            "ground_yaw_rad": 0.0} for k, xy in enumerate(labels)]}
    (tmp_path / "labels.json").write_text(json.dumps(doc))
    r = score_labels(tmp_path / "labels.json", truth)
    assert (r["labels"], r["precision"]) == (5, 0.8)
    assert (r["true_vehicles"], r["recall"], r["headings"]) == (1, 1.0, 1)


def test_the_ground_view_samples_the_masks_at_the_working_pixels_centre(tmp_path):
    """At scale 0.5 working pixel p is centred on full-resolution position 2p + 0.5: the masks were read at 2p (the
    nearest pixel, numpy rounding half to even), a quarter working pixel off."""
    from calibration.masks import load_masks
    from training.autolabel import GroundView

    view = GroundView(load_masks(_masks(tmp_path / "masks.npz")), 0.5, 40.0)
    assert view.valid.shape == (H // 2, W // 2) and view.valid.all()
    v, u = np.mgrid[0:H // 2, 0:W // 2].astype(np.float64)
    q_u, q_v = 2 * u + 0.5, 2 * v + 0.5
    np.testing.assert_allclose(view.xy, np.stack([(q_u - CX) * M_PER_PX, (CY - q_v) * M_PER_PX], axis=2), atol=1e-5)
    # a ground point back to its working pixel: (u, v) = ((q_u, q_v) - 0.5) / 2
    p = view.to_pixel(np.array([3.0, -4.0]), (0, 0, W // 2 - 1, H // 2 - 1))
    np.testing.assert_allclose(p, ((_uv((3.0, -4.0)) + 0.5) / 2 - 0.5), atol=1e-4)
