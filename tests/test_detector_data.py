"""Detector training data: recording and COCO-style importers, COCO export, augmentation geometry,
batches, and the errors for bad input."""

from __future__ import annotations

import functools
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from training.augment import AugmentConfig, augment, resize_sample, transform_labels, warp_sample
from training.data import (
    MIN_VISIBLE_FRACTION,
    MIN_VISIBLE_PX,
    Batcher,
    recording_labels,
    samples_from_coco,
    samples_from_recording,
    write_coco,
)
from training.sample import VEHICLE_TYPES, Sample

GEOMETRY_ONLY = AugmentConfig(photometric=False)


@pytest.fixture(scope="module")
def recording(small_recording) -> Path:
    return small_recording


# ---- recordings ---------------------------------------------------------------------------------


def test_recording_samples_have_consistent_labels(recording):
    refs = samples_from_recording(recording)
    assert [r.meta["camera"] for r in refs] == ["NE", "NE", "T_SW", "T_SW"]
    gt = {
        c: [json.loads(x) for x in (recording / "gt" / f"{c}.jsonl").read_text().splitlines()] for c in ("NE", "T_SW")
    }
    inside_box = positives = 0
    for k, ref in enumerate(refs):
        s = ref.load()
        meta = s.meta
        h, w = s.shape
        assert (h, w) == ((960, 1280) if meta["camera"] == "NE" else (512, 640))
        assert meta["kind"] == ("fisheye" if meta["camera"] == "NE" else "pinhole")
        assert meta["modality"] == ("visible" if meta["camera"] == "NE" else "thermal")
        assert meta["t_ns"] == int(Path(ref.image_path).stem)
        assert meta["recording"] == str(recording)
        frame = gt[meta["camera"]][k % 2]
        assert frame["t_ns"] == meta["t_ns"]
        # every visible vehicle is a label; the weight follows the policy
        by_id = {v["id"]: v for v in frame["vehicles"]}
        assert sorted(meta["track_id"]) == sorted(v["id"] for v in frame["vehicles"] if v["visible_px"] > 0)
        for i, vid in enumerate(meta["track_id"]):
            v = by_id[int(vid)]
            want = v["in_image"] and v["visible_px"] >= MIN_VISIBLE_PX and v["visible_fraction"] >= MIN_VISIBLE_FRACTION
            assert s.weight[i] == float(want)
            assert VEHICLE_TYPES[s.vtype[i]] == v["type"]
            np.testing.assert_allclose(s.size_lwh[i], v["lwh"])
            assert s.meta["parked"][i] == v["parked"]
        pos = s.weight > 0
        assert pos.sum() >= 3, ref.source
        uv, box = s.bottom_uv[pos], s.box[pos]
        assert ((uv >= -0.5) & (uv < [w - 0.5, h - 0.5])).all()
        np.testing.assert_allclose(np.linalg.norm(s.heading_uv[pos], axis=1), 1.0, atol=1e-9)
        assert ((s.box[:, :2] >= -0.5) & (s.box[:, 2:] <= [w - 0.5, h - 0.5]) & (s.box[:, 2:] > s.box[:, :2])).all()
        # The box is the visible part: a partly hidden vehicle's bottom centre can fall outside it
        # (its lower part behind another vehicle), but not far, and for most vehicles it is inside.
        margin = 0.25 * np.maximum(box[:, 2:] - box[:, :2], 4.0)
        assert ((uv >= box[:, :2] - margin) & (uv <= box[:, 2:] + margin)).all()
        inside_box += ((uv >= box[:, :2]) & (uv <= box[:, 2:])).all(axis=1).sum()
        positives += pos.sum()
        # heading agrees with the world yaw: the front is further along the heading than the rear
        for i in np.flatnonzero(pos):
            corners = np.array(by_id[int(meta["track_id"][i])]["corners_uv"])
            assert (corners[0] - corners[3]) @ s.heading_uv[i] > 0
    assert inside_box >= 0.9 * positives


def test_recording_every_and_scale(recording):
    full = samples_from_recording(recording, cameras=["T_SW"])
    half = samples_from_recording(recording, cameras=["T_SW"], every=2, scale=0.5)
    assert len(full) == 2 and len(half) == 1
    a, b = full[0].load(), half[0].load()
    assert b.shape == (256, 320)
    np.testing.assert_allclose(b.bottom_uv, (a.bottom_uv + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(b.box, (a.box + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(b.meta["principal_point"], (np.array(a.meta["principal_point"]) + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(b.heading_uv, a.heading_uv, atol=1e-12)
    np.testing.assert_array_equal(b.weight, a.weight)


def test_recording_bad_input_names_the_file(recording, tmp_path):
    with pytest.raises(ValueError, match=r"no camera 'XX'.*has: NE, T_SW"):
        samples_from_recording(recording, cameras=["XX"])
    with pytest.raises(ValueError, match="every must be"):
        samples_from_recording(recording, every=0)
    with pytest.raises(ValueError, match="scale must be"):
        samples_from_recording(recording, scale=-1.0)
    broken = tmp_path / "broken"
    shutil.copytree(recording, broken)
    refs = samples_from_recording(broken, cameras=["NE"])
    # corrupt JPEG: found on load
    refs[0].image_path.write_bytes(b"\xff\xd8 not a jpeg")
    with pytest.raises(ValueError, match="cannot decode") as err:
        refs[0].load()
    assert str(refs[0].image_path) in str(err.value)
    # missing JPEG: found when listing
    refs[1].image_path.unlink()
    with pytest.raises(ValueError, match="is missing") as err:
        samples_from_recording(broken, cameras=["NE"])
    assert str(refs[1].image_path) in str(err.value) and "NE.jsonl:2" in str(err.value)
    # ground-truth record without a key
    gt_path = broken / "gt" / "T_SW.jsonl"
    lines = gt_path.read_text().splitlines()
    bad = json.loads(lines[0])
    del bad["vehicles"][0]["box_visible"]
    gt_path.write_text("\n".join([json.dumps(bad), *lines[1:]]) + "\n")
    with pytest.raises(ValueError, match=r"T_SW\.jsonl:1: vehicle \d+ has no 'box_visible'"):
        samples_from_recording(broken, cameras=["T_SW"])


def _gt_vehicle(**change) -> dict:
    """A recording's ground-truth vehicle that is a positive label, with `change` applied."""
    vehicle = {"id": 7, "type": "car", "lwh": [4.5, 1.8, 1.5], "uv": [100.0, 80.0], "in_image": True,
               "box_visible": [80, 50, 120, 82], "corners_uv": [[110, 85], [110, 75], [90, 75], [90, 85]],
               "visible_px": 500, "visible_fraction": 0.9, "parked": False}
    return {**vehicle, **change}


def test_recording_ground_truth_that_is_not_finite_or_reversed_is_named(recording, tmp_path):
    """A NaN in a recording's truth once became a positive label and stopped the training at its batch ("cannot
    convert float NaN to integer", no file named): it is refused on loading, naming the line and the vehicle."""
    labels, ids, _ = recording_labels([_gt_vehicle()], "gt/NE.jsonl:3")
    assert ids == [7] and labels["weight"].tolist() == [1.0]
    np.testing.assert_allclose(labels["box"][0], [79.5, 49.5, 120.5, 82.5])
    nan = float("nan")
    for change, message in [
        ({"uv": [nan, 80.0]}, "uv must be finite"),
        ({"box_visible": [80, nan, 120, 82]}, "box_visible must be finite"),
        ({"box_visible": [120, 50, 80, 82]}, "box_visible must be .* with x1 <= x2 and y1 <= y2, got"),
        ({"corners_uv": [[110, 85], [110, nan], [90, 75], [90, 85]]}, "corners_uv must be finite"),
        ({"lwh": [4.5, float("inf"), 1.5]}, "lwh must be finite"),
        ({"uv": [100.0]}, "uv must be 2 numbers"),
    ]:
        with pytest.raises(ValueError, match=rf"^gt/NE\.jsonl:3: vehicle 7: {message}"):
            recording_labels([_gt_vehicle(**change)], "gt/NE.jsonl:3")
    # an ignore vehicle whose bottom centre is outside the lens model: its corners are not used, whatever they are
    labels, _, _ = recording_labels([_gt_vehicle(uv=None, in_image=False, corners_uv=[[nan, nan]] * 4)], "x")
    assert labels["weight"].tolist() == [0.0] and np.isnan(labels["heading_uv"]).all()
    # a bus reaching from behind a pinhole camera into its image: a corner it cannot project is null, the vehicle
    # a label with no heading (it stopped loading the whole recording)
    labels, ids, _ = recording_labels([_gt_vehicle(corners_uv=[[110, 85], None, None, [90, 85]])], "x")
    assert ids == [7] and np.isnan(labels["heading_uv"]).all()
    # through the recording reader: the file and line are named
    broken = tmp_path / "nan"
    shutil.copytree(recording, broken)
    gt_path = broken / "gt" / "T_SW.jsonl"
    lines = gt_path.read_text().splitlines()
    frame = json.loads(lines[1])
    positive = next(v for v in frame["vehicles"] if v["uv"] is not None and v["visible_px"] >= MIN_VISIBLE_PX)
    positive["uv"][0] = nan
    gt_path.write_text("\n".join([lines[0], json.dumps(frame), *lines[2:]]) + "\n")  # json writes NaN
    with pytest.raises(ValueError, match=rf"T_SW\.jsonl:2: vehicle {positive['id']}: uv must be finite"):
        samples_from_recording(broken, cameras=["T_SW"])


# ---- COCO-style annotations ---------------------------------------------------------------------


def _coco_folder(tmp_path: Path, annotations: list[dict], categories: list[dict] | None = None) -> Path:
    cv2.imwrite(str(tmp_path / "a.png"), np.full((60, 80), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((60, 80), 30, np.uint8))
    doc = {
        "images": [
            {"id": 1, "file_name": "a.png", "width": 80, "height": 60, "kind": "fisheye", "principal_point": [40, 30]},
            {"id": 7, "file_name": "b.png"},
        ],
        "annotations": annotations,
        "categories": categories or [{"id": 1, "name": "Car"}, {"id": 2, "name": "pickup"}, {"id": 3, "name": "bus"}],
    }
    path = tmp_path / "ann.json"
    path.write_text(json.dumps(doc))
    return path


def test_coco_import_reads_boxes_bottoms_and_aliases(tmp_path):
    rect = [[20.5, 40.5], [24.5, 40.5], [24.5, 30.5], [20.5, 30.5]]  # front-left ... rear-left; front is +v
    path = _coco_folder(
        tmp_path,
        [
            {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 20, 30, 25]},
            {"id": 2, "image_id": 1, "category_id": 2, "bbox": [15, 25, 15, 20], "bottom_rect": rect, "lwh": [5, 2, 2]},
            {"id": 3, "image_id": 1, "category_id": 3, "bbox": [50, 5, 20, 20], "bottom_center": [60.5, 22.5]},
            {"id": 4, "image_id": 1, "category_id": 1, "bbox": [1, 1, 4, 4], "iscrowd": 1},
        ],
    )
    refs = samples_from_coco(path)
    assert [len(r) for r in refs] == [4, 0]
    s = refs[0].load()
    assert s.shape == (60, 80) and s.image[0, 0] == 90
    assert s.meta["kind"] == "fisheye" and s.meta["principal_point"] == (39.5, 29.5)
    np.testing.assert_allclose(s.box[0], [9.5, 19.5, 39.5, 44.5])  # COCO edges -> our pixel-centre convention
    np.testing.assert_allclose(s.bottom_uv[0], [24.5, 44.5])  # middle of the box's bottom edge
    assert np.isnan(s.heading_uv[0]).all() and np.isnan(s.size_lwh[0]).all()
    np.testing.assert_allclose(s.bottom_uv[1], [22.0, 35.0])
    np.testing.assert_allclose(s.heading_uv[1], [0.0, 1.0])
    np.testing.assert_allclose(s.size_lwh[1], [5, 2, 2])
    np.testing.assert_allclose(s.bottom_uv[2], [60.0, 22.0])
    assert [VEHICLE_TYPES[t] for t in s.vtype] == ["car", "suv_van", "bus", "car"]
    np.testing.assert_array_equal(s.weight, [1, 1, 1, 0])
    empty = refs[1].load()
    assert len(empty) == 0 and empty.box.shape == (0, 4) and empty.image[0, 0] == 30
    half = samples_from_coco(path, scale=0.5)[0].load()
    assert half.shape == (30, 40)
    np.testing.assert_allclose(half.bottom_uv, (s.bottom_uv + 0.5) * 0.5 - 0.5)


def test_coco_round_trip(recording, tmp_path):
    refs = samples_from_recording(recording, scale=0.25)
    extra = Sample(
        image=np.arange(48 * 64, dtype=np.uint8).reshape(48, 64),
        bottom_uv=[[10.25, 20.5]],
        box=[[3.0, 4.5, 17.25, 21.0]],
        heading_uv=[[np.nan, np.nan]],
        size_lwh=[[np.nan, np.nan, np.nan]],
        vtype=[-1],
        weight=[1.0],
    )
    originals = [r.load() for r in refs] + [extra]
    json_path = write_coco([*refs, extra], tmp_path / "out" / "ann.json", tmp_path / "out" / "images")
    back = [r.load() for r in samples_from_coco(json_path, tmp_path / "out" / "images")]
    assert len(back) == len(originals)
    for a, b in zip(originals, back, strict=True):
        np.testing.assert_array_equal(a.image, b.image)
        for key in ("bottom_uv", "box", "size_lwh"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), atol=1e-3, err_msg=key)
        np.testing.assert_allclose(b.heading_uv, a.heading_uv, atol=1e-5)
        np.testing.assert_array_equal(b.vtype, a.vtype)
        np.testing.assert_array_equal(b.weight, a.weight)
        for key in ("camera", "kind", "modality", "t_ns"):
            assert b.meta.get(key) == a.meta.get(key)
        if "principal_point" in a.meta:
            np.testing.assert_allclose(b.meta["principal_point"], a.meta["principal_point"], atol=1e-4)


GOOD = {"id": 5, "image_id": 1, "category_id": 1, "bbox": [10, 20, 30, 25]}


def test_roadside_coco_writes_a_file_train_reads_as_it_is(recording, tmp_path, capsys):
    """`roadside coco`: a recording's labels and images as a COCO-style file that `samples_from_coco` reads with its
    defaults (the images beside the JSON), every vehicle kept, ignore vehicles as iscrowd."""
    from roadside.cli import main
    from training.data import samples_from_recording

    out = tmp_path / "coco" / "annotations.json"
    assert main(["coco", str(recording), "--out", str(out), "--every", "1"]) == 0
    assert "images, " in capsys.readouterr().out
    back = samples_from_coco(out)
    original = samples_from_recording(recording)
    assert len(back) == len(original)
    for a, b in zip(original, back, strict=True):
        a, b = a.load(), b.load()
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_allclose(b.bottom_uv, a.bottom_uv, atol=1e-3)
        np.testing.assert_array_equal(b.weight > 0, a.weight > 0)
    assert main(["coco", str(recording), "--out", str(out), "--cameras", "nowhere"]) == 2
    assert "no camera 'nowhere'" in capsys.readouterr().err
    # a second file in the same folder keeps its own images (they were both 000001.png ...)
    other = tmp_path / "coco" / "thermal.json"
    assert main(["coco", str(recording), "--out", str(other), "--cameras", "T_SW", "--every", "1"]) == 0
    for a, b in zip(original, samples_from_coco(out), strict=True):
        np.testing.assert_array_equal(a.load().image, b.load().image)
    assert main(["coco", str(recording), "--out", str(tmp_path / "coco")]) == 2  # a folder
    assert "must be named *.json" in capsys.readouterr().err



@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"bbox": [10, 20, float("nan"), 5]}, "bbox must be finite"),
        ({"bbox": [10, 20, -3, 5]}, "bbox width and height must be > 0"),
        ({"bbox": [10, 20, 5]}, "bbox must be 4 numbers"),
        ({"bottom_rect": [[1, 2], [3, 4], [5, 6]]}, "bottom_rect must be 4 x 2 numbers"),
        ({"bottom_center": "middle"}, "bottom_center must be 2 numbers"),
        ({"lwh": [4, -1, 2]}, "lwh must be positive"),
        ({"image_id": 99}, "annotation 5: image_id 99 is not in images"),
        ({"category_id": 42}, "category_id 42 is not in categories"),
        ({"bbox": None, "drop": "bbox"}, "annotation 5: missing bbox"),
        ({"bbox": [0.1, 0.2, 0.3, 0.25]}, "every bbox lies within 0-1: COCO boxes are in pixels"),
        ({"bbox": [200, 20, 30, 25]}, r"bbox \[200, 20, 30, 25\] lies outside the 80x60 image"),
        ({"image_id": [1]}, r"image_id must be a number or a string, got \[1\]"),
        ({"category_id": {"a": 1}}, "category_id must be a number or a string"),
    ],
)
def test_coco_bad_annotation_names_the_file(tmp_path, change, message):
    ann = {**GOOD, **{k: v for k, v in change.items() if k != "drop"}}
    ann.pop(change.get("drop", "-"), None)
    path = _coco_folder(tmp_path, [ann])
    with pytest.raises(ValueError, match=message) as err:
        samples_from_coco(path)
    assert str(path) in str(err.value)


def test_coco_duplicate_ids_are_refused_not_merged(tmp_path):
    """A repeated category id would turn cars into trucks, a repeated annotation id count a vehicle twice."""
    path = _coco_folder(tmp_path, [GOOD], categories=[{"id": 1, "name": "car"}, {"id": 1, "name": "truck"}])
    with pytest.raises(ValueError, match="category id 1 appears twice"):
        samples_from_coco(path)
    path = _coco_folder(tmp_path, [GOOD, {**GOOD, "bbox": [40, 20, 30, 25]}])
    with pytest.raises(ValueError, match="annotation id 5 appears twice"):
        samples_from_coco(path)
    doc = json.loads(path.read_text())
    doc["images"][0]["width"] = [80]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="image 1: width must be a whole number of pixels"):
        samples_from_coco(path)


def test_coco_bad_files_name_the_file(tmp_path):
    path = _coco_folder(tmp_path, [GOOD], categories=[{"id": 1, "name": "tractor"}])
    with pytest.raises(ValueError, match="category 'tractor' \\(id 1\\) is not a vehicle type") as err:
        samples_from_coco(path)
    assert str(path) in str(err.value)
    path.write_text('{"images": [}')
    with pytest.raises(ValueError, match="not valid JSON") as err:
        samples_from_coco(path)
    assert str(path) in str(err.value)
    path.write_text(json.dumps({"images": [], "categories": []}))
    with pytest.raises(ValueError, match="'annotations'") as err:
        samples_from_coco(path)
    assert str(path) in str(err.value)
    path = _coco_folder(tmp_path, [GOOD])
    (tmp_path / "b.png").unlink()
    with pytest.raises(ValueError, match="is missing") as err:
        samples_from_coco(path)
    assert str(tmp_path / "b.png") in str(err.value) and str(path) in str(err.value)
    path = _coco_folder(tmp_path, [GOOD])
    (tmp_path / "a.png").write_bytes(b"\x89PNG garbage")
    ref = samples_from_coco(path)[0]
    with pytest.raises(ValueError, match="cannot decode") as err:
        ref.load()
    assert str(tmp_path / "a.png") in str(err.value)
    path = _coco_folder(tmp_path, [GOOD])
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match=r"image is 10x10, .* says 80x60") as err:
        samples_from_coco(path)[0].load()
    assert str(tmp_path / "a.png") in str(err.value)


# ---- augmentation -------------------------------------------------------------------------------


def _dot_sample(rng: np.random.Generator, kind: str) -> Sample:
    """A grey image with Gaussian dots (sigma 1.5 px) at the labelled bottom centres, in pairs: the
    heading of vehicle 2k points at vehicle 2k + 1."""
    h, w = 200, 240
    pts: list[np.ndarray] = []
    while len(pts) < 16:
        p = rng.uniform([8, 8], [w - 9, h - 9])
        if all(np.hypot(*(p - q)) > 22 for q in pts):
            pts.append(p)
    pts_arr = np.array(pts)
    vv, uu = np.mgrid[0:h, 0:w]
    image = np.full((h, w), 128.0)
    for u, v in pts_arr:
        image += 100 * np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * 1.5**2))
    heading = np.empty_like(pts_arr)
    heading[0::2] = pts_arr[1::2] - pts_arr[0::2]
    heading[1::2] = rng.normal(size=(8, 2))
    heading /= np.linalg.norm(heading, axis=1, keepdims=True)
    n = len(pts_arr)
    return Sample(
        image=np.round(image).astype(np.uint8),
        bottom_uv=pts_arr,
        box=np.hstack([pts_arr - np.array([6, 9]), pts_arr + np.array([6, 2])]),
        heading_uv=heading,
        size_lwh=np.tile([4.5, 1.8, 1.5], (n, 1)),
        vtype=np.zeros(n, int),
        weight=np.ones(n),
        source="dots",
        meta={"kind": kind, "principal_point": (121.3, 97.6), "track_id": np.arange(n)},
    )


def _dot_centroid(image: np.ndarray, uv: np.ndarray, radius: int = 5) -> np.ndarray:
    u0, v0 = np.round(uv).astype(int)
    patch = image[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1].astype(float) - 128
    patch = np.clip(patch, 0, None)
    vv, uu = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return np.array([u0 + (patch * uu).sum() / patch.sum(), v0 + (patch * vv).sum() / patch.sum()])


def _check_dots(out: Sample, before: Sample) -> int:
    """Every positive's dot is at its label (0.5 px); headings follow the dots; returns dots checked."""
    h, w = out.shape
    checked = 0
    ids = list(out.meta["track_id"])
    for i, uv in enumerate(out.bottom_uv):
        if out.weight[i] > 0 and 7 <= uv[0] <= w - 8 and 7 <= uv[1] <= h - 8:
            assert np.hypot(*(_dot_centroid(out.image, uv) - uv)) < 0.5, (i, uv)
            checked += 1
        k = ids[i]
        if k % 2 == 0 and k + 1 in ids:  # heading of 2k points at 2k+1 in any affine view
            d = out.bottom_uv[ids.index(k + 1)] - uv
            np.testing.assert_allclose(out.heading_uv[i], d / np.linalg.norm(d), atol=1e-9)
    # everything kept is in the crop, or an ignore whose box still overlaps it
    inside = (out.bottom_uv >= -0.5).all(1) & (out.bottom_uv < [w - 0.5, h - 0.5]).all(1)
    assert (out.weight[~inside] == 0).all()
    assert (out.box[:, 2:] > out.box[:, :2]).all()
    np.testing.assert_allclose(np.linalg.norm(out.heading_uv, axis=1), 1.0)
    assert len(out) <= len(before)
    return checked


@pytest.mark.parametrize("kind", ["pinhole", "fisheye"])
def test_augment_keeps_points_on_their_pixels(kind):
    rng = np.random.default_rng(7)
    sample = _dot_sample(rng, kind)
    before = sample.image.copy()
    checked = 0
    for _ in range(12):
        out = augment(sample, rng, out_hw=(120, 160), config=GEOMETRY_ONLY)
        assert out.shape == (120, 160) and out.image.dtype == np.uint8
        checked += _check_dots(out, sample)
    assert checked >= 40
    np.testing.assert_array_equal(sample.image, before)  # the input is left alone
    assert len(sample) == 16


def test_fisheye_rotation_is_about_the_principal_point():
    rng = np.random.default_rng(3)
    sample = _dot_sample(rng, "fisheye")
    config = AugmentConfig(scale_range=(1.0, 1.0), flip_prob=0.0, focus_prob=0.0, photometric=False)
    angles = []
    for _ in range(8):
        out = augment(sample, rng, out_hw=(200, 240), config=config)
        _check_dots(out, sample)
        pp0, pp1 = np.array(sample.meta["principal_point"]), np.array(out.meta["principal_point"])
        for i, k in enumerate(out.meta["track_id"]):  # distances to the principal point are kept
            np.testing.assert_allclose(
                np.linalg.norm(out.bottom_uv[i] - pp1), np.linalg.norm(sample.bottom_uv[k] - pp0), atol=1e-9
            )
        k = out.meta["track_id"][0]
        a, b = sample.bottom_uv[k] - pp0, out.bottom_uv[0] - pp1
        angles.append(math.atan2(a[0] * b[1] - a[1] * b[0], a @ b))
    assert np.ptp(angles) > 1.0  # really rotated, by different angles
    pinhole = _dot_sample(np.random.default_rng(3), "pinhole")
    out = augment(pinhole, rng, out_hw=(200, 240), config=config)
    np.testing.assert_allclose(out.heading_uv, pinhole.heading_uv[out.meta["track_id"]], atol=1e-12)


def test_quarter_turns_keep_every_box_exact():
    rng = np.random.default_rng(4)
    sample = _dot_sample(rng, "fisheye")
    config = AugmentConfig(scale_range=(1.0, 1.0), flip_prob=0.0, focus_prob=0.0, photometric=False,
                           fisheye_rotation="quarter")
    turns = set()
    for _ in range(12):
        out = augment(sample, rng, out_hw=(400, 400), config=config)
        _check_dots(out, sample)
        src = sample.box[out.meta["track_id"]]
        wh, src_wh = out.box[:, 2:] - out.box[:, :2], src[:, 2:] - src[:, :2]
        inside = (out.box[:, 0] > -0.5) & (out.box[:, 1] > -0.5) & (out.box[:, 2] < 399.5) & (out.box[:, 3] < 399.5)
        turned = np.allclose(wh[inside], src_wh[inside][:, ::-1])
        assert turned or np.allclose(wh[inside], src_wh[inside])  # a box is kept or its sides swap, exactly
        a = sample.heading_uv[out.meta["track_id"][0]]
        b = out.heading_uv[0]
        turns.add(round(math.degrees(math.atan2(a[0] * b[1] - a[1] * b[0], a @ b))) % 360)
    assert turns <= {0, 90, 180, 270} and len(turns) >= 3


def test_flip_crop_and_scale_are_exact():
    sample = _dot_sample(np.random.default_rng(5), "pinhole")
    # flip and shift: u' = c - u, v' = v + 10, with c putting one dot 3 px left of the output
    k = int(np.flatnonzero(sample.bottom_uv[:, 1] < 130)[0])
    c = sample.bottom_uv[k, 0] - 3
    m = np.array([[-1.0, 0.0, c], [0.0, 1.0, 10.0]])
    out = warp_sample(sample, m, (150, 100))
    ids = out.meta["track_id"]
    want_uv = np.column_stack([c - sample.bottom_uv[:, 0], sample.bottom_uv[:, 1] + 10])
    np.testing.assert_allclose(out.bottom_uv, want_uv[ids])
    x1, y1, x2, y2 = sample.box[ids].T
    want_box = np.clip(np.column_stack([c - x2, y1 + 10, c - x1, y2 + 10]), -0.5, [99.5, 149.5, 99.5, 149.5])
    np.testing.assert_allclose(out.box, want_box)
    np.testing.assert_allclose(out.heading_uv, sample.heading_uv[ids] * [-1, 1])
    # kept: box partly inside, with weight 1 when the bottom centre is inside too (else ignore)
    full_box = np.column_stack(
        [c - sample.box[:, 2], sample.box[:, 1] + 10, c - sample.box[:, 0], sample.box[:, 3] + 10]
    )
    clipped = np.clip(full_box, -0.5, [99.5, 149.5, 99.5, 149.5])
    overlap = (clipped[:, 2] > clipped[:, 0]) & (clipped[:, 3] > clipped[:, 1])
    inside = (want_uv >= -0.5).all(1) & (want_uv < [99.5, 149.5]).all(1)
    np.testing.assert_array_equal(ids, np.flatnonzero(overlap))
    np.testing.assert_array_equal(out.weight, inside[ids])
    assert inside.sum() >= 3 and (overlap & ~inside).sum() >= 1 and (~overlap).sum() >= 1
    _check_dots(out, sample)
    for scale in (0.5, 0.37, 1.6):
        small = resize_sample(sample, scale)
        assert small.shape == (round(200 * scale), round(240 * scale))
        if scale >= 0.5:
            _check_dots(small, sample)
        sx = small.shape[1] / 240
        np.testing.assert_allclose(small.bottom_uv[:, 0], (sample.bottom_uv[:, 0] + 0.5) * sx - 0.5)


def test_vehicle_whose_visible_part_is_cropped_away_is_dropped():
    # bottom centres at v = 30, visible parts (boxes) above them: the lower half of each is hidden
    sample = Sample(
        image=np.zeros((40, 40), np.uint8),
        bottom_uv=[[10.0, 30.0], [30.0, 30.0]],
        box=[[0.0, 0.0, 20.0, 20.0], [20.0, 0.0, 39.0, 28.0]],
        heading_uv=[[1.0, 0.0], [1.0, 0.0]],
        size_lwh=np.full((2, 3), np.nan),
        vtype=[0, 1],
        weight=[1.0, 1.0],
    )
    out = warp_sample(sample, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -25.0]]), (20, 40))
    np.testing.assert_array_equal(out.vtype, [1])  # the first one's box ends above the crop
    np.testing.assert_allclose(out.box, [[20.0, -0.5, 39.0, 3.0]])
    np.testing.assert_allclose(out.bottom_uv, [[30.0, 5.0]])
    assert out.weight.tolist() == [1.0]


def test_photometric_jitter_changes_pixels_not_labels():
    rng = np.random.default_rng(11)
    sample = _dot_sample(rng, "pinhole")
    config = AugmentConfig(noise_prob=1.0, blur_prob=1.0)
    a = augment(sample, np.random.default_rng(1), out_hw=(96, 128), config=config)
    b = augment(sample, np.random.default_rng(1), out_hw=(96, 128), config=GEOMETRY_ONLY)
    np.testing.assert_array_equal(a.bottom_uv, b.bottom_uv)
    assert np.abs(a.image.astype(int) - b.image).mean() > 1.0


def test_bad_augment_config_is_named():
    with pytest.raises(ValueError, match=r"scale_range .* got \(1\.3, 0\.7\)"):
        AugmentConfig(scale_range=(1.3, 0.7))
    with pytest.raises(ValueError, match="flip_prob must be in"):
        AugmentConfig(flip_prob=2.0)
    with pytest.raises(ValueError, match="fisheye_rotation must be one of"):
        AugmentConfig(fisheye_rotation=True)


# ---- batches ------------------------------------------------------------------------------------


def test_batcher_yields_augmented_batches(recording):
    refs = samples_from_recording(recording, scale=0.25)
    aug = functools.partial(augment, out_hw=(64, 96))
    batcher = Batcher(refs, aug, batch_size=2, rng=np.random.default_rng(0))
    assert len(batcher) == 2
    for _ in range(2):
        batches = list(batcher)
        assert [len(b) for b in batches] == [2, 2]
        for s in batches[0] + batches[1]:
            assert s.shape == (64, 96) and s.image.dtype == np.uint8
            assert s.box.shape == (len(s), 4) and s.bottom_uv.shape == (len(s), 2)
    assert len(batcher._cache) == 4 and batcher.cached_bytes == 2 * (240 * 320 + 128 * 160)
    np.testing.assert_array_equal(batcher.sample(0).image, refs[0].load().image)  # the cache is untouched
    plain = Batcher(refs, None, batch_size=3, rng=np.random.default_rng(0), shuffle=False, drop_last=False)
    sizes = [[s.shape for s in b] for b in plain]
    assert sizes == [[(240, 320)] * 2 + [(128, 160)], [(128, 160)]]
    again = [[s.bottom_uv for s in b] for b in Batcher(refs, aug, 2, np.random.default_rng(5))]
    same = [[s.bottom_uv for s in b] for b in Batcher(refs, aug, 2, np.random.default_rng(5))]
    for x, y in zip(again, same, strict=True):
        for p, q in zip(x, y, strict=True):
            np.testing.assert_array_equal(p, q)
    with pytest.raises(ValueError, match="batch_size must be"):
        Batcher(refs, aug, batch_size=0, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="no samples"):
        Batcher([], aug, batch_size=1, rng=np.random.default_rng(0))


def test_box_under_rotation_keeps_its_size_not_its_corners():
    """A rotated box becomes the bounds of its rotated inscribed ellipse: a square keeps its size at any
    angle (the corners' bounds would be 1.41 times wider at 45 degrees), a 40 x 20 box turned 90 degrees
    is 20 x 40, and scale, flip and crop stay exact."""
    image = np.zeros((200, 200), np.uint8)

    def one_vehicle(box):
        return Sample(image, [[100.0, 110.0]], [box], [[1.0, 0.0]], [[4.5, 1.8, 1.5]], [0], [1.0])

    sample = one_vehicle([80.0, 80.0, 120.0, 120.0])
    for angle in (0.3, math.pi / 4, 2.0):
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[c, -s, 100 - 100 * c + 100 * s], [s, c, 100 - 100 * s - 100 * c]])  # about (100, 100)
        np.testing.assert_allclose(transform_labels(sample, rot, image).box[0], [80, 80, 120, 120], atol=1e-9)
    wide = one_vehicle([80.0, 90.0, 120.0, 110.0])
    quarter = np.array([[0.0, -1.0, 200.0], [1.0, 0.0, 0.0]])  # 90 degrees about (100, 100)
    np.testing.assert_allclose(transform_labels(wide, quarter, image).box[0], [90, 80, 110, 120], atol=1e-9)
    flip_zoom = np.array([[-2.0, 0.0, 300.0], [0.0, 2.0, -100.0]])
    np.testing.assert_allclose(transform_labels(wide, flip_zoom, image).box[0], [60, 80, 140, 120], atol=1e-9)


def test_focus_by_size_centres_the_crops_on_the_large_vehicles_more_often():
    sample = _dot_sample(np.random.default_rng(8), "pinhole")
    big = 5
    box = sample.box.copy()
    box[big] = np.r_[sample.bottom_uv[big] - [40, 60], sample.bottom_uv[big] + [40, 2]]  # 80x62 among 12x11 boxes
    sample = replace(sample, box=box)
    counts = {}
    for by_size in (False, True):
        config = AugmentConfig(scale_range=(1.0, 1.0), flip_prob=0.0, focus_prob=1.0, photometric=False,
                               focus_by_size=by_size)
        rng = np.random.default_rng(0)
        counts[by_size] = sum(big in augment(sample, rng, (40, 40), config).meta["track_id"] for _ in range(400))
    # uniform: 1 in 16 crops centred on it, more reaching its large box by chance (77 of 400 with this seed); by
    # size about its share of the sizes, 0.29, centred on it (166)
    size = np.sqrt(np.prod(box[:, 2:] - box[:, :2], axis=1))
    assert counts[False] < 400 * 0.25
    assert counts[True] > 400 * 0.8 * size[big] / size.sum() and counts[True] > 1.8 * counts[False]


def test_detections_map_back_from_the_network_as_training_mapped_the_labels_into_it():
    """Training resizes labels with each axis's factor of the whole-pixel size; the detect service mapped back with
    the nominal scale, up to 0.75 px off at the far edge of a 1001x750 image."""
    from shared.decode import Detections
    from shared.inference import input_scale, network_to_image

    for w, h in ((704, 576), (2688, 1520), (1001, 750), (1280, 960)):
        scale = input_scale(w, h, 640)
        uv = np.array([[w - 2.0, h - 2.0], [w / 2, h / 2], [1.0, 1.0]])  # boxes of +-1 px within the image
        sample = Sample(np.zeros((h, w), np.uint8), uv, np.c_[uv - 1, uv + 1], np.tile([1.0, 0.0], (3, 1)),
                        np.ones((3, 3)), [0] * 3, [1.0] * 3)
        net = resize_sample(sample, scale)  # what the network learns to answer
        det = Detections(np.ones(3), net.bottom_uv, net.box, net.heading_uv, np.ones((3, 3)), np.zeros(3, int),
                         np.ones((3, 5)))
        back = network_to_image(det, (h, w), scale)
        np.testing.assert_allclose(back.uv, uv, atol=1e-9, err_msg=f"{w}x{h}")
        np.testing.assert_allclose(back.box, sample.box, atol=1e-9, err_msg=f"{w}x{h}")
