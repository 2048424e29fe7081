"""Real-data calibration benchmark: readers of the Rope3D and OTVision formats on tiny synthetic files,
the benchmark end to end on synthetic data, and the real-data checks (skipped without ../shared/data)."""

from __future__ import annotations

import bz2
import json
import sqlite3
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from bench.calibration_real import (
    RealBenchSettings,
    decode_gpkg_point,
    default_data_root,
    farthest_point_sample,
    load_rope3d,
    read_gpkg_boxes,
    read_otdet,
    read_otrfpts,
    read_rope3d_calib,
    read_rope3d_denorm,
    read_rope3d_extrinsics,
    real_data_rows,
)
from shared.cameras import Camera, Pose

REPO = Path(__file__).resolve().parents[1]
DATA = default_data_root()
FRAME = "f001"
UTM_OFFSET = np.array([500100.0, 4400200.0])


# ---- synthetic Rope3D ---------------------------------------------------------------------------
def _rope3d_camera() -> Camera:
    pose = Pose.from_angles([UTM_OFFSET[0], UTM_OFFSET[1], 27.0], 30.0, 14.0)
    return Camera("r", "pinhole", 640, 360, 500.0, 500.0, 319.5, 179.5, (0.0,) * 5, pose)


def _write_rope3d(root: Path, n_points: int = 60) -> Path:
    """A Rope3D-layout folder: one frame, a flat ground at z = 20 m seen by `_rope3d_camera`."""
    cam = _rope3d_camera()
    rng = np.random.default_rng(3)
    pts = []
    while len(pts) < n_points:
        p = np.array([*(cam.pose.position_m[:2] + rng.uniform(-60, 60, 2)), 20.0])
        uv, ok = cam.project(p[None])
        if ok[0] and cam.in_image(uv, margin_px=5)[0]:
            pts.append(p)
    r_world_from_cam = cam.pose.r_cam_from_world.T
    qx, qy, qz, qw = Rotation.from_matrix(r_world_from_cam).as_quat()
    t = cam.pose.position_m
    n_cam = cam.pose.r_cam_from_world @ [0.0, 0.0, 1.0]
    d = -float(n_cam @ cam.pose.to_camera(np.array(pts[:1]))[0])  # the ground plane in camera metres
    for sub in ("calib", "denorm", "extrinsics", "image_2"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "demo.txt").write_text(FRAME + "\n")
    (root / "calib" / f"{FRAME}.txt").write_text(
        f"P2: {cam.fx} 0 {cam.cx} 0 0 {cam.fy} {cam.cy} 0 0 0 1 0\n"
    )
    (root / "denorm" / f"{FRAME}.txt").write_text(" ".join(str(v) for v in [*n_cam, d]) + "\n")
    doc = {
        "transform": {
            "translation": dict(zip("xyz", map(float, t), strict=True)),
            "rotation": {"w": float(qw), "x": float(qx), "y": float(qy), "z": float(qz)},
        },
        "points_lane_detection": [float(v) for v in np.ravel(pts)],
    }
    (root / "extrinsics" / f"{FRAME}.yaml").write_text(yaml.safe_dump(doc))
    cv2.imwrite(str(root / "image_2" / f"{FRAME}.jpg"), np.zeros((cam.height, cam.width), np.uint8))
    return root


def test_rope3d_readers_round_trip(tmp_path):
    root = _write_rope3d(tmp_path / "rope3d_demo")
    (frame,) = load_rope3d(root)
    cam = _rope3d_camera()
    assert (frame.width, frame.height) == (640, 360)
    assert frame.ground_points_m.shape == (60, 3)
    np.testing.assert_allclose(frame.t_world_m, cam.pose.position_m)
    np.testing.assert_allclose(frame.r_world_from_cam, cam.pose.r_cam_from_world.T, atol=1e-9)
    uv, ok = frame.project(frame.ground_points_m)
    assert ok.all()
    np.testing.assert_allclose(uv, cam.project(frame.ground_points_m)[0], atol=1e-6)
    off = frame.to_camera(frame.ground_points_m) @ frame.denorm[:3] + frame.denorm[3]
    np.testing.assert_allclose(off, 0.0, atol=1e-6)


def test_rope3d_benchmark_recovers_an_exact_planar_camera(tmp_path):
    _write_rope3d(tmp_path / "rope3d_demo")
    out = real_data_rows(tmp_path, RealBenchSettings(n_fit=10, draws=2))
    assert out["rope3d_heldout_mean_m"] < 0.05
    assert out["rope3d_heldout_mean_m_random_draws"] < 0.2
    assert out["rope3d_true_camera_lsq_plane_mean_m"] < 1e-3
    row = out["rope3d"][0]
    assert row["surveyed_points"] == 60 and row["n_heldout"] == 50 and len(row["fit_points"]) == 10
    assert out["otvision_median_diff_m"] is None and "otvision_skipped" in out


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("calib", "P0: 1 2 3\n", "no 'P2:' line"),
        ("calib", "P2: 1 0 0 0 0 1 0 0 0 0 1\n", "P2 needs 12 finite numbers"),
        ("calib", "P2: 1 0 0 0 0 1 0 0 0 0 x 0\n", "P2 must be numbers"),
        ("denorm", "0 -1 0\n", "needs 4 finite numbers"),
        ("denorm", "0 -3 0 7\n", "unit length"),
    ],
)
def test_rope3d_small_files_reject_bad_input(tmp_path, name, text, match):
    path = tmp_path / f"{name}.txt"
    path.write_text(text)
    reader = read_rope3d_calib if name == "calib" else read_rope3d_denorm
    with pytest.raises(ValueError, match=match) as err:
        reader(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("transform: [1, 2\n", "not valid YAML"),
        ("transform: {translation: {x: 1, y: 2}}\n", "transform.translation"),
        (
            "transform: {translation: {x: 1, y: 2, z: 3}, rotation: {w: 1, x: 0, y: 0, z: 0}}\n",
            "no 'points_lane_detection'",
        ),
        (
            "transform: {translation: {x: 1, y: 2, z: 3}, rotation: {w: 1, x: 0, y: 0, z: 0}}\n"
            "points_lane_detection: [1, 2, 3, 4]\n",
            "x, y, z triples, got 4",
        ),
    ],
)
def test_rope3d_extrinsics_reject_bad_input(tmp_path, doc, match):
    path = tmp_path / "e.yaml"
    path.write_text(doc)
    with pytest.raises(ValueError, match=match) as err:
        read_rope3d_extrinsics(path)
    assert str(path) in str(err.value)


def test_rope3d_missing_image_names_the_file(tmp_path):
    root = _write_rope3d(tmp_path / "r")
    img = root / "image_2" / f"{FRAME}.jpg"
    img.unlink()
    with pytest.raises(ValueError, match="not a readable image") as err:
        load_rope3d(root)
    assert str(img) in str(err.value)


def test_farthest_point_sample_spreads_and_never_repeats():
    uv = np.array([[0, 0], [1, 0], [100, 0], [0, 100], [100, 100], [50, 50], [2, 1]], float)
    idx = farthest_point_sample(uv, 5, 0)
    assert len(set(idx.tolist())) == 5
    assert set(idx[:4].tolist()) == {0, 2, 3, 4}


# ---- synthetic OTVision -----------------------------------------------------------------------
def _gpkg_blob(x: float, y: float, envelope: bool = False, big_endian: bool = False, kind: int = 1) -> bytes:
    flags = 1 | (2 if envelope else 0)
    head = b"GP" + bytes([0, flags]) + struct.pack("<i", 32632)
    env = struct.pack("<4d", x, x, y, y) if envelope else b""
    wkb = struct.pack(">BIdd", 0, kind, x, y) if big_endian else struct.pack("<BIdd", 1, kind, x, y)
    return head + env + wkb


def _write_gpkg(path: Path, rows: list[tuple]) -> None:
    con = sqlite3.connect(path)
    con.execute(
        "CREATE TABLE gpkg_geometry_columns (table_name TEXT, column_name TEXT, geometry_type_name TEXT, "
        "srs_id INTEGER, z TINYINT, m TINYINT)"
    )
    con.execute("INSERT INTO gpkg_geometry_columns VALUES ('clip', 'geom', 'POINT', 32632, 0, 0)")
    con.execute("CREATE TABLE clip (fid INTEGER PRIMARY KEY, geom BLOB, frame TEXT, x REAL, y REAL, w REAL, h REAL)")
    con.executemany("INSERT INTO clip (geom, frame, x, y, w, h) VALUES (?, ?, ?, ?, ?, ?)", rows)
    con.commit()
    con.close()


def _write_otvision(root: Path) -> Path:
    """One clip: 5 reference points, boxes centred on ground pixels, OTVision's homography output."""
    root.mkdir(parents=True)
    cam = Camera("o", "pinhole", 800, 600, 620.0, 620.0, 399.5, 299.5, (0.0,) * 5,
                 Pose.from_angles([0.0, 0.0, 6.0], 40.0, 20.0))
    rng = np.random.default_rng(5)
    ground, uv = [], []
    while len(ground) < 45:
        p = np.array([*rng.uniform(-40, 40, 2), 0.0])
        q, ok = cam.project(p[None])
        if ok[0] and cam.in_image(q, margin_px=30)[0]:
            ground.append(p[:2])
            uv.append(q[0])
    ground, uv = np.array(ground), np.array(uv)
    ref_idx = farthest_point_sample(uv, 5, 0)
    ref = {
        str(k + 1): {"x_px": float(uv[i, 0]), "y_px": float(uv[i, 1]), "hemisphere": "N", "zone_utm": 32,
                     "lon_utm": float(ground[i, 0] + 844000.0), "lat_utm": float(ground[i, 1] + 5673000.0)}
        for k, i in enumerate(ref_idx)
    }
    (root / "clip.otrfpts").write_text(json.dumps(ref))
    xy_ref = ground[ref_idx] + [844000.0, 5673000.0]
    off = xy_ref.mean(axis=0)
    h_mat, _ = cv2.findHomography(uv[ref_idx], xy_ref - off, 0)
    utm = cv2.perspectiveTransform(uv[None], h_mat)[0] + off
    wh = rng.uniform(20, 60, (len(uv), 2))
    frames = np.arange(len(uv)) // 5 + 1
    _write_gpkg(root / "clip.gpkg", [(_gpkg_blob(*utm[i]), str(frames[i]), *uv[i], *wh[i]) for i in range(len(uv))])
    dets: dict = {}
    for i in range(len(uv)):
        x, y = uv[i] - wh[i] / 2  # this detector writes the top-left corner
        dets.setdefault(str(frames[i]), {"detections": []})["detections"].append(
            {"class": "car", "confidence": 0.9, "x": x, "y": y, "w": wh[i, 0], "h": wh[i, 1]}
        )
    meta = {"otdet_version": "1.2", "video": {"width": 800, "height": 600}, "detection": {"normalized_bbox": False}}
    (root / "clip.otdet").write_bytes(bz2.compress(json.dumps({"metadata": meta, "data": dets}).encode()))
    return root


def test_otvision_readers_round_trip(tmp_path):
    root = _write_otvision(tmp_path / "otvision")
    ref = read_otrfpts(root / "clip.otrfpts")
    assert ref.uv.shape == (5, 2) and ref.zone == 32 and ref.hemisphere == "N"
    out, srs = read_gpkg_boxes(root / "clip.gpkg")
    assert srs == 32632 and out.xywh.shape == (45, 4) and out.utm.shape == (45, 2)
    det, meta = read_otdet(root / "clip.otdet")
    assert meta["otdet_version"] == "1.2" and det.xywh.shape == (45, 4)
    np.testing.assert_allclose(det.xywh[:, :2] + det.xywh[:, 2:] / 2, out.xywh[:, :2])


def test_otvision_benchmark_finds_the_mapped_pixel_and_agrees_inside_the_hull(tmp_path):
    _write_otvision(tmp_path / "otvision")
    out = real_data_rows(tmp_path, RealBenchSettings(draws=0))
    (clip,) = out["otvision"]
    assert clip["mapped_pixel"] == "box centre (x, y)"
    assert clip["reproduced_median_m"]["box centre (x, y)"] < 1e-3
    assert clip["otdet_xy"]["anchor"] == "top_left" and clip["otdet_xy"]["matched_share"]["top_left"] == 1.0
    assert clip["n_boxes"] == 45 and clip["valid"] == 1.0
    assert out["otvision_median_diff_m"] < 0.5
    assert out["rope3d_heldout_mean_m"] is None and "rope3d_skipped" in out


def test_gpkg_point_decoding_variants():
    assert decode_gpkg_point(_gpkg_blob(1.5, -2.0)) == (1.5, -2.0)
    assert decode_gpkg_point(_gpkg_blob(3.0, 4.0, envelope=True)) == (3.0, 4.0)
    assert decode_gpkg_point(_gpkg_blob(5.0, 6.0, big_endian=True)) == (5.0, 6.0)
    assert decode_gpkg_point(_gpkg_blob(5.0, 6.0, kind=1001) + struct.pack("<d", 9.0)) == (5.0, 6.0)
    with pytest.raises(ValueError, match="not a point"):
        decode_gpkg_point(_gpkg_blob(1.0, 2.0, kind=2))
    with pytest.raises(ValueError, match="no 'GP' magic"):
        decode_gpkg_point(b"XX" + _gpkg_blob(1.0, 2.0)[2:])
    with pytest.raises(ValueError, match="too short"):
        decode_gpkg_point(_gpkg_blob(1.0, 2.0)[:20])


def test_gpkg_reader_names_the_file_and_row(tmp_path):
    bad = tmp_path / "bad.gpkg"
    _write_gpkg(bad, [(_gpkg_blob(1.0, 2.0), "1", 1.0, 2.0, 3.0, 4.0), (b"junk", "2", 1.0, 2.0, 3.0, 4.0)])
    with pytest.raises(ValueError, match="row 2 of 'clip'") as err:
        read_gpkg_boxes(bad)
    assert str(bad) in str(err.value)
    not_db = tmp_path / "text.gpkg"
    not_db.write_text("hello, not a database " * 20)
    with pytest.raises(ValueError, match="not an OTVision GeoPackage") as err:
        read_gpkg_boxes(not_db)
    assert str(not_db) in str(err.value)
    with pytest.raises(ValueError, match="missing"):
        read_gpkg_boxes(tmp_path / "absent.gpkg")


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("{", "not valid JSON"),
        ("[]", "expected an object"),
        ('{"1": {"x_px": 1, "y_px": 2, "lon_utm": 3}}', "reference point '1' needs"),
        (
            '{"1": {"x_px": 1, "y_px": 2, "lon_utm": 3, "lat_utm": 4, "zone_utm": 32, "hemisphere": "N"},'
            ' "2": {"x_px": 1, "y_px": 2, "lon_utm": 3, "lat_utm": 4, "zone_utm": 33, "hemisphere": "N"}}',
            "mix UTM zones",
        ),
    ],
)
def test_otrfpts_rejects_bad_input(tmp_path, doc, match):
    path = tmp_path / "r.otrfpts"
    path.write_text(doc)
    with pytest.raises(ValueError, match=match) as err:
        read_otrfpts(path)
    assert str(path) in str(err.value)


def test_otdet_reads_plain_json_normalized_boxes_and_rejects_bad_input(tmp_path):
    doc = {"metadata": {"video": {"width": 800, "height": 600}, "detection": {"normalized_bbox": True}},
           "data": {"3": {"detections": [{"x": 0.5, "y": 0.5, "w": 0.1, "h": 0.2}]}}}
    path = tmp_path / "a.otdet"
    path.write_text(json.dumps(doc))
    det, _ = read_otdet(path)
    np.testing.assert_allclose(det.xywh, [[400.0, 300.0, 80.0, 120.0]])
    assert det.frame.tolist() == [3]
    path.write_bytes(bz2.compress(b'{"metadata": {}, "data": {}}'))
    with pytest.raises(ValueError, match=r"needs metadata\.video") as err:
        read_otdet(path)
    assert str(path) in str(err.value)
    path.write_bytes(b"BZh9 truncated")
    with pytest.raises(ValueError, match="not bz2/plain JSON"):
        read_otdet(path)


def test_settings_reject_bad_values():
    with pytest.raises(ValueError, match="n_fit must be >= 4, got 3"):
        RealBenchSettings(n_fit=3)
    with pytest.raises(ValueError, match="draws must be >= 0, got -1"):
        RealBenchSettings(draws=-1)


def test_absent_data_is_skipped_with_a_reason(tmp_path):
    out = real_data_rows(tmp_path / "nowhere")
    assert out["rope3d_heldout_mean_m"] is None and "no Rope3D demo" in out["rope3d_skipped"]
    assert out["otvision_median_diff_m"] is None and "no OTVision data" in out["otvision_skipped"]


def test_cli_prints_one_json_document(tmp_path):
    _write_rope3d(tmp_path / "rope3d_demo")
    _write_otvision(tmp_path / "otvision")
    res = subprocess.run(
        [sys.executable, "-m", "bench.calibration_real", "--data", str(tmp_path), "--draws", "1"],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=True,
    )
    out = json.loads(res.stdout)
    for key in ("rope3d_heldout_mean_m", "rope3d_heldout_mean_m_random_draws", "otvision_median_diff_m"):
        assert isinstance(out[key], float), key


# ---- the real data -----------------------------------------------------------------------------
needs_rope3d = pytest.mark.skipif(not (DATA / "rope3d_demo").is_dir(), reason=f"no Rope3D demo at {DATA}")
needs_otvision = pytest.mark.skipif(not (DATA / "otvision").is_dir(), reason=f"no OTVision data at {DATA}")


@needs_rope3d
def test_real_rope3d_points_are_the_surveyed_ground_in_view():
    (frame,) = load_rope3d(DATA / "rope3d_demo")
    assert len(frame.ground_points_m) == 215
    assert frame.project(frame.ground_points_m)[1].all()
    off = np.abs(frame.to_camera(frame.ground_points_m) @ frame.denorm[:3] + frame.denorm[3])
    assert off.mean() < 0.2  # the pose and the independent ground plane agree


@needs_rope3d
@needs_otvision
def test_real_data_benchmark_gates():
    out = real_data_rows(DATA, RealBenchSettings(draws=2))
    assert out["rope3d_heldout_mean_m"] < 1.5
    assert out["rope3d_heldout_mean_m_random_draws"] < 1.5
    for clip in out["otvision"]:
        assert clip["mapped_pixel"] == "box centre (x, y)"
        assert clip["reproduced_median_m"]["box centre (x, y)"] < 1e-3  # OTVision's output reproduced
    assert out["otvision_median_diff_inside_hull_m"] < 0.5
    assert np.isfinite(out["otvision_median_diff_m"])


@pytest.mark.parametrize("reader", [read_rope3d_calib, read_rope3d_denorm, read_rope3d_extrinsics, read_otrfpts,
                                    read_otdet])
def test_missing_files_are_named(tmp_path, reader):
    path = tmp_path / "absent.file"
    with pytest.raises(ValueError, match="missing") as err:
        reader(path)
    assert str(path) in str(err.value)
