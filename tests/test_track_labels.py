"""Labels from the pipeline's own tracks (training/track_labels.py) on the synthetic scene of test_autolabel: a flat
ground seen straight down from 12 m at 0.1 m per pixel."""

from __future__ import annotations

import json
import math
from datetime import time
from pathlib import Path

import numpy as np
import pytest
from test_autolabel import CFG, CY, HZ, M_PER_PX, MOVERS, H, W, _frames, _masks, _uv

from training.autolabel import autolabel_camera, list_frames
from training.track_labels import TrackLabelConfig, TrackTeacher, footprint_corners

HIDDEN = ((5.0, -10.0), (0.0, 3.0))  # a car another camera followed going north; this one shows road only
PARKED = (0.0, -5.0)  # a steady track that never moved: a lamp head, or a parked car


def _row(tid: int, xy, v, yaw: float, length: float = 4.5, width: float = 1.8) -> dict:
    return {"id": tid, "x": xy[0], "y": xy[1], "vx": v[0], "vy": v[1], "yaw": yaw, "length": length, "width": width,
            "type": "car"}


def _tracks(path: Path, frame_times: list[int], offset_ns: int = 30_000_000) -> Path:
    """One line per frame, `offset_ns` after it: the eastbound car (already labelled by the background model), the
    hidden car, the parked track, and a fast track seen in two lines only."""
    lines = []
    for k, t_ns in enumerate(frame_times):
        t = k / HZ + offset_ns / 1e9
        east = np.array(MOVERS[0][0]) + t * np.array(MOVERS[0][1])
        hidden = np.array(HIDDEN[0]) + t * np.array(HIDDEN[1])
        rows = [_row(1, east, MOVERS[0][1], 0.0), _row(2, hidden, HIDDEN[1], math.pi / 2),
                _row(3, PARKED, (0.0, 0.0), 0.3)]
        if k < 2:
            rows.append(_row(4, (-10.0, -10.0), (6.0, 0.0), 0.0))
        lines.append({"site": "se", "seq": k, "t_ns": t_ns + offset_ns, "tracker": "tracker-a", "tracks": rows})
    path.write_text("".join(json.dumps(ln) + "\n" for ln in lines))
    return path


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, Path, list[int]]:
    root = tmp_path_factory.mktemp("track_labels")
    frames = _frames(root / "frames")
    return frames, _masks(root / "masks.npz"), [t for t, _ in list_frames(frames, time(11, 0, 2))]


def test_the_teacher_gives_moving_tracks_carried_to_the_frame_time(scene, tmp_path):
    _, _, times = scene
    teacher = TrackTeacher(_tracks(tmp_path / "tracks.jsonl", times))
    assert teacher.tracks_seen == 4 and teacher.vehicles == {"tracker-a/1", "tracker-a/2"}
    got = {v.key: v for v in teacher.at(times[3])}
    assert set(got) == {"tracker-a/1", "tracker-a/2"}
    # the line is 30 ms after the frame: carried back by the velocity
    assert got["tracker-a/2"].xy == pytest.approx(np.array(HIDDEN[0]) + 3 / HZ * np.array(HIDDEN[1]))
    assert got["tracker-a/2"].height == 1.5 and got["tracker-a/2"].length == 4.5
    assert teacher.at(times[-1] + 10**9) == []  # no line within max_gap_s
    corners = footprint_corners(got["tracker-a/2"])  # heading north: 4.5 m along y, 1.8 m along x
    assert np.ptp(corners[:, 0]) == pytest.approx(1.8) and np.ptp(corners[:, 1]) == pytest.approx(4.5)


def test_a_hidden_moving_vehicle_becomes_a_label_and_nothing_else_does(scene, tmp_path):
    frames, masks, times = scene
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                              tracks=_tracks(tmp_path / "tracks.jsonl", times))
    assert report["from_tracks"] == 10 and report["vehicles"] == 30  # the two drawn cars, and the hidden one
    assert report["track_lines_after_slice"] == 0
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    labs = [a for a in doc["annotations"] if a.get("from_tracks")]
    assert {a["track_id"] for a in labs} == {"tracker-a/2"}
    for a in labs:
        k = a["image_id"]
        truth = np.array(HIDDEN[0]) + k / HZ * np.array(HIDDEN[1])
        assert np.hypot(*(np.array(a["bottom_center"]) - 0.5 - _uv(truth))) < 0.6  # pixels
        assert np.dot(a["heading_uv"], [0.0, -1.0]) > 0.999  # north is up the image
        # the box holds the footprint (1.8 x 4.5 m) and its roof, 1.5 m up, seen from the camera 12 m above (0, 0):
        # where the ray through a roof corner meets the ground, 12 / 10.5 times as far from the camera's foot
        foot = np.array([[truth[0] + dx, truth[1] + dy] for dx in (-0.9, 0.9) for dy in (-2.25, 2.25)])
        pts = np.array([_uv(p) for p in np.vstack([foot, foot * 12 / 10.5])])
        x, y, w, h = a["bbox"]
        assert [x, y, x + w, y + h] == pytest.approx([*pts.min(axis=0), *pts.max(axis=0)], abs=0.6), a["bbox"]


def test_frames_named_in_local_time_meet_the_tracks_only_in_their_time_zone(scene, tmp_path):
    """The pipeline's tracks carry UTC capture times; frames named in Ann Arbor's clock are 5 h earlier read as UTC:
    named in the time zone the site's ingest used, the labels come; read as UTC, refused, not a silent nothing."""
    from zoneinfo import ZoneInfo

    frames, masks, times = scene
    later = _tracks(tmp_path / "tracks.jsonl", [t + 5 * 3600 * 10**9 for t in times])
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                              tracks=later, tz=ZoneInfo("America/Detroit"))
    assert report["from_tracks"] == 10
    with pytest.raises(ValueError, match=r"holds no tracks before \d+ ns .* in another time zone"):
        autolabel_camera(frames, masks, tmp_path / "out2", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                         tracks=later)


def test_a_bad_tracks_file_is_named(tmp_path):
    with pytest.raises(ValueError, match="tracks file missing"):
        TrackTeacher(tmp_path / "none.jsonl")
    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps({"site": "se", "seq": 0, "t_ns": 1, "tracker": "t", "tracks": []}) + "\n{not json\n")
    with pytest.raises(ValueError, match=r"bad\.jsonl: line 2"):
        TrackTeacher(bad)
    bad.write_text(json.dumps({"site": "se", "seq": 0, "t_ns": 1, "tracker": "t",
                               "tracks": [_row(1, (math.nan, 0.0), (1.0, 0.0), 0.0)]}) + "\n")
    with pytest.raises(ValueError, match="line 1"):
        TrackTeacher(bad)
    bad.write_text("\n")
    with pytest.raises(ValueError, match="holds no tracks"):
        TrackTeacher(bad)
    with pytest.raises(ValueError, match="moving_mps must be a positive number"):
        TrackLabelConfig(moving_mps=0.0)


def test_a_vehicle_at_the_edge_of_the_calibrated_ground_gets_a_finite_box_or_none(tmp_path):
    """Pixels off the calibrated ground hold NaN in the masks (sky, a pole): the corners of a vehicle there must
    not make its box NaN (training refuses such a file)."""
    from calibration.masks import load_masks
    from training.autolabel import GroundView
    from training.track_labels import TrackedVehicle, label_from_track

    masks = load_masks(_masks(tmp_path / "masks.npz"))
    masks.xy[:150] = np.nan  # the image's top rows: not ground
    masks.valid[:150] = False
    view = GroundView(masks, 1.0, 40.0)
    # a point between the last row off the ground and the first on it: the Newton step lands at v = 149.7, on the
    # edge's cells (the Jacobian, read at the nearest pixel, is fine; the bilinear lookup there reads NaN)
    assert view.to_pixel(np.array([3.0, (CY - 149.7) * M_PER_PX]), (0, 0, W - 1, H - 1)) is None
    made = 0
    for k in range(60):  # northbound cars ever closer to the edge at v = 150 (y = 9 m), then past it
        y = 4.0 + k * 0.125
        lab = label_from_track(TrackedVehicle("t/1", np.array([3.0, y]), math.pi / 2, 4.5, 1.8, 1.5, "car"), view)
        if lab is not None:
            made += 1
            assert np.isfinite(lab["box"]).all() and np.isfinite(lab["uv"]).all(), lab
            assert lab["box"][1] >= 149.5  # the box stays on the calibrated ground
    assert 0 < made < 60


def test_only_the_lines_before_the_end_decide_which_tracks_moved(tmp_path):
    """A car that waits through the training slice and drives off after it: with the whole file it was a moving
    vehicle, and so labelled where it waited; lines at or after `t_end_ns` are not read at all."""
    path = tmp_path / "tracks.jsonl"
    lines = [{"site": "se", "seq": k, "t_ns": k * 200_000_000, "tracker": "tr",
              "tracks": [_row(5, (5.0, -10.0), (0.0, 0.0 if k < 10 else 3.0), math.pi / 2)]} for k in range(15)]
    path.write_text("".join(json.dumps(ln) + "\n" for ln in lines))
    assert TrackTeacher(path).vehicles == {"tr/5"}  # the whole file: it moved
    before = TrackTeacher(path, t_end_ns=10 * 200_000_000)
    assert before.vehicles == set() and before.at(9 * 200_000_000) == []
    assert before.lines_after_end == 5 and before.times[-1] == 9 * 200_000_000 and before.tracks_seen == 1
    with pytest.raises(ValueError, match=r"holds no tracks before 0 ns \(the end of the frames' slice; 15 lines"):
        TrackTeacher(path, t_end_ns=0)


def test_autolabel_reads_the_tracks_only_up_to_the_until_instant(scene, tmp_path):
    """`autolabel --until --tracks` with the tracks of the whole footage: a track standing through the labelled frames
    that moves from the until instant on gives no labels, and the lines left out are reported."""
    frames, masks, _ = scene
    every = [t for t, _ in list_frames(frames)]  # the 11th frame, at 11:00:02 (the until instant), is held out
    cut = every[-1]
    lines = []
    for k, t_ns in enumerate([*every, cut + 200_000_000, cut + 400_000_000]):
        t = k / HZ + 0.03
        hidden = np.array(HIDDEN[0]) + t * np.array(HIDDEN[1])
        waiting = _row(5, (-8.0, -6.0), (0.0, 0.0) if t_ns < cut else (4.0, 0.0), 0.0)
        lines.append({"site": "se", "seq": k, "t_ns": t_ns + 30_000_000, "tracker": "tracker-a",
                      "tracks": [_row(2, hidden, HIDDEN[1], math.pi / 2), waiting]})
    path = tmp_path / "tracks.jsonl"
    path.write_text("".join(json.dumps(ln) + "\n" for ln in lines))
    assert TrackTeacher(path).vehicles == {"tracker-a/2", "tracker-a/5"}  # on all its lines the waiting car moved
    report = autolabel_camera(frames, masks, tmp_path / "out", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                              tracks=path)
    doc = json.loads((tmp_path / "out" / "labels.json").read_text())
    assert {a["track_id"] for a in doc["annotations"] if a.get("from_tracks")} == {"tracker-a/2"}
    assert report["from_tracks"] == 10 and report["track_lines_after_slice"] == 3
    # without --until the slice ends just after the last frame it lists: the line 30 ms after it is left out too
    listed = tmp_path / "listed"
    listed.mkdir()
    for _, p in list_frames(frames, time(11, 0, 2)):
        (listed / p.name).write_bytes(p.read_bytes())
    report = autolabel_camera(listed, masks, tmp_path / "out2", "CAM", cfg=CFG, log=None, tracks=path)
    assert report["track_lines_after_slice"] == 4 and report["from_tracks"] == 9
    # tracks all before the frames: refused as before
    early = tmp_path / "early.jsonl"
    early.write_text("".join(json.dumps({**ln, "t_ns": ln["t_ns"] - 3600 * 10**9}) + "\n" for ln in lines))
    with pytest.raises(ValueError, match="do not span the frames' capture times"):
        autolabel_camera(frames, masks, tmp_path / "out3", "CAM", until=time(11, 0, 2), cfg=CFG, log=None,
                         tracks=early)
