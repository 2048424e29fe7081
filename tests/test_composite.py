"""roadside composite: simulated vehicles drawn over a camera's "real" background. The real camera here is the
small simulator recording's fisheye NE (its frames the background, its exact lookup masks with its camera model
the calibration), so every label can be checked against what was drawn."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from pipeline_fixtures import write_exact_masks

from calibration.masks import load_masks
from roadside.cli import main
from training.composite import CompositeConfig, composite_camera, load_placements, real_background
from training.data import samples_from_coco

CAMERA = "NE"
CFG = CompositeConfig(seconds=2.0, hz=1.0, seed=4, roi_m=45.0, demand_scale=2.0)


@pytest.fixture(scope="module")
def masks(small_recording: Path, tmp_path_factory) -> Path:
    return write_exact_masks(small_recording, CAMERA, tmp_path_factory.mktemp("composite") / "NE.npz")


@pytest.fixture(scope="module")
def made(small_recording: Path, masks: Path, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("composite") / "out"
    calls = []

    def teacher(grey):  # one confident detection (a "parked car" in the background), one unsure
        calls.append(grey.shape)
        return SimpleNamespace(score=np.array([0.9, 0.3]), uv=np.array([[320.0, 300.0], [300.0, 200.0]]),
                               box=np.array([[310.0, 290.0, 330.0, 301.0], [290.0, 190.0, 310.0, 201.0]]))

    report = composite_camera(small_recording / "frames" / CAMERA, masks, out, CAMERA, None, CFG, log=None,
                              teacher=teacher)
    assert calls == [(480, 640)]  # run once, on the background at the output size
    return out, report


def test_labels_sit_on_the_drawn_vehicles_over_the_untouched_background(small_recording, masks, made):
    out, report = made
    assert report["images"] == 2 and report["vehicles"] >= 2, report
    samples = [r.load() for r in samples_from_coco(out / "labels.json")]
    assert len(samples) == 2 and all(s.shape == (480, 640) for s in samples)
    bg_full, used = real_background(small_recording / "frames" / CAMERA, (1280, 960), None, 10)
    assert used == 2
    bg = cv2.resize(cv2.cvtColor(bg_full, cv2.COLOR_BGR2GRAY), (640, 480), interpolation=cv2.INTER_AREA)
    m = load_masks(masks)
    # as GroundView: working pixel p <-> full-resolution position 2p + 0.5, the lookup sampled there
    q = np.stack(np.meshgrid(np.arange(640) * 2 + 0.5, np.arange(480) * 2 + 0.5), axis=2).reshape(-1, 2)
    _, xy, ok = m.lookup(q, geodetic=False)
    foot = np.asarray(m.meta["camera"]["pose"]["position_m"][:2])
    roi = ok.reshape(480, 640) & (np.hypot(*(xy.reshape(480, 640, 2) - foot).transpose(2, 0, 1)) <= CFG.roi_m)
    drawn = np.zeros((480, 640), bool)
    for s in samples:
        img = s.image.astype(np.float32)
        diff = np.abs(img - bg)
        assert np.all(s.image[~roi] == s.image[~roi][0]), "outside the region: one flat grey"
        pos = np.nonzero(s.weight > 0)[0]
        for k in pos:
            u, v = np.round(s.bottom_uv[k]).astype(int)
            assert roi[v, u], "a positive label's bottom centre is inside the region"
            x1, y1, x2, y2 = np.round(s.box[k]).astype(int)
            assert x1 <= u <= x2 + 1 and y1 <= v <= y2 + 1
            assert diff[max(y1, 0):y2, max(x1, 0):x2].mean() > 8, "a vehicle is drawn in its box"
            drawn[max(y1 - 12, 0):y2 + 12, max(x1 - 12, 0):x2 + 12] = True
        for k in np.nonzero(s.weight <= 0)[0]:
            x1, y1, x2, y2 = np.round(s.box[k]).astype(int)
            drawn[max(y1 - 12, 0):y2 + 12, max(x1 - 12, 0):x2 + 12] = True
        assert np.median(diff[roi & ~drawn]) <= 3, "away from the vehicles the image is the background"
        assert np.isfinite(s.heading_uv[pos]).all() and np.all(s.vtype[pos] >= 0)
        assert np.all((s.size_lwh[pos, 0] > 1.5) & (s.size_lwh[pos, 0] < 20))
    assert report["teacher_regions"] == 1 and report["ignored_teacher"] == 2


def test_bad_input_is_named(small_recording, masks, tmp_path):
    frames = small_recording / "frames" / CAMERA
    m = load_masks(masks)
    moved = dict(m.meta, geo_origin={"lat_deg": 40.0, "lon_deg": -80.0, "alt_m": 0.0})
    other = type(m)(m.lat, m.lon, m.xy, m.valid, moved).save(tmp_path / "moved.npz")
    with pytest.raises(ValueError, match=r"moved\.npz: site origin 40\.0, -80\.0 is not simulator site 'state_"):
        composite_camera(frames, other, tmp_path / "o1", CAMERA, None, CFG, log=None)
    bare = type(m)(m.lat, m.lon, m.xy, m.valid, {k: v for k, v in m.meta.items() if k != "camera"})
    with pytest.raises(ValueError, match=r"bare\.npz: the masks carry no camera model"):
        composite_camera(frames, bare.save(tmp_path / "bare.npz"), tmp_path / "o2", CAMERA, None, CFG, log=None)
    with pytest.raises(ValueError, match="frames folder not found"):
        composite_camera(tmp_path / "none", masks, tmp_path / "o3", CAMERA, None, CFG, log=None)
    with pytest.raises(ValueError, match="shadow must be in"):
        CompositeConfig(shadow=1.5)
    assert main(["composite", "--frames", str(frames), "--masks", str(masks), "--camera", CAMERA, "--out",
                 str(tmp_path / "o4"), "--until", "noon"]) == 2


def test_the_labels_file_says_how_it_was_made(made):
    out, report = made
    doc = json.loads((out / "labels.json").read_text())
    assert doc["info"]["config"]["seed"] == CFG.seed and doc["info"]["environment"]["name"] == "clear"
    assert json.loads((out / "report.json").read_text()) == report


def _placements(recording: Path, masks: Path, path: Path) -> Path:
    """A labels file as roadside autolabel writes it: ground positions and headings of vehicles near NE."""
    m = load_masks(masks)
    foot = np.asarray(m.meta["camera"]["pose"]["position_m"][:2])
    anns = []
    for line in (recording / "gt" / f"{CAMERA}.jsonl").read_text().splitlines():
        for v in json.loads(line)["vehicles"]:
            if not v["parked"] and np.hypot(*(np.asarray(v["xyz"][:2]) - foot)) < 25:
                anns.append({"ground_xy_m": v["xyz"][:2], "ground_yaw_rad": v["yaw"]})
    anns.append({"bbox": [0, 0, 5, 5], "iscrowd": 1})  # an ignore region: no placement
    path.write_text(json.dumps({"images": [], "annotations": anns, "categories": []}))
    return path


def test_placements_put_vehicles_where_the_labels_file_saw_them(small_recording, masks, tmp_path):
    pool = load_placements(_placements(small_recording, masks, tmp_path / "found.json"))
    assert len(pool) >= 2 and pool.shape[1] == 3
    cfg = CompositeConfig(seconds=2.0, hz=1.0, seed=5, roi_m=45.0, vehicles_per_image=(2, 4), along_m=3.0)
    report = composite_camera(small_recording / "frames" / CAMERA, masks, tmp_path / "out", CAMERA, None, cfg,
                              log=None, placements=tmp_path / "found.json")
    assert report["placements"] == len(pool) and report["vehicles"] >= 2, report
    m = load_masks(masks)
    for ref in samples_from_coco(tmp_path / "out" / "labels.json"):
        s = ref.load()
        assert 1 <= int(np.sum(s.weight > 0)) <= 4
        full_uv = (s.bottom_uv[s.weight > 0] + 0.5) * 2 - 0.5
        _, xy, ok = m.lookup(full_uv)
        assert ok.all()
        # moved along its heading by up to 3 m; the masks' ground is the simulator's terrain, the placements'
        # a plane, which moves a point seen obliquely by a few decimetres
        nearest = np.min(np.linalg.norm(xy[:, None] - pool[None, :, :2], axis=2), axis=1)
        assert np.all(nearest < 3.0 + 1.0), nearest


def test_bad_placements_are_named(tmp_path):
    with pytest.raises(ValueError, match="placements file not found"):
        load_placements(tmp_path / "none.json")
    (tmp_path / "empty.json").write_text(json.dumps({"images": [], "annotations": [{"bbox": [0, 0, 1, 1]}]}))
    with pytest.raises(ValueError, match="no vehicle with a ground position and heading"):
        load_placements(tmp_path / "empty.json")
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a roadside autolabel labels file"):
        load_placements(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="vehicles_per_image"):
        CompositeConfig(vehicles_per_image=(5, 2))
