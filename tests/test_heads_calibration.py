"""The detector's heads' calibrations: the per-type size map and its fit by least absolute deviations, the 2D box
map and its fit, the ONNX metadata they travel in, and the shipped model carrying both."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.decode import Detections
from shared.heads_calibration import SIZE_CALIBRATION_KEY, BoxCalibration, SizeCalibration, box_features
from shared.inference import OnnxDetector
from training.heads_calibration import (
    box_pairs,
    collect_frames,
    fit_box_calibration,
    fit_size_calibration,
    least_absolute,
    size_pairs,
    write_calibrations,
)

REPO = Path(__file__).resolve().parents[1]


def _calibration(num_types: int = 5, type_: int = 0, gain: tuple[float, float, float] = (2.0, 1.0, 0.5)):
    """Type `type_` multiplies l, w, h by `gain`; the others keep their sizes."""
    calib = SizeCalibration.identity(num_types)
    coef = calib.coef.copy()
    coef[type_, :, 0] = np.log(gain)
    return SizeCalibration(coef, tuple(100 if t == type_ else 0 for t in range(num_types)))


def test_identity_and_a_per_type_map():
    size = np.array([[4.5, 1.8, 1.5], [12.0, 2.5, 3.2], [4.0, 1.7, 1.4]])
    vtype = np.array([0, 3, -1])
    assert np.array_equal(SizeCalibration.identity(5).apply(size, vtype), size)
    out = _calibration().apply(size, vtype)
    assert out[0] == pytest.approx([9.0, 1.8, 0.75])
    assert np.array_equal(out[1:], size[1:])  # another type; an unknown one (-1)
    # an index beyond the calibration keeps its size
    assert np.array_equal(_calibration().apply(size, np.array([0, 3, 7])), np.vstack([out[:2], size[2:]]))
    # a zero from the size head's ReLU is read as 5 cm, not as log 0
    assert np.isfinite(_calibration().apply(np.zeros((1, 3)), np.array([0]))).all()
    assert _calibration().apply(np.zeros((0, 3)), np.zeros(0, int)).shape == (0, 3)


def test_the_calibration_mixes_the_three_sizes():
    coef = SizeCalibration.identity(1).coef.copy()
    coef[0, 2] = [0.1, 0.5, 0.0, 0.5]  # log h' = 0.1 + (log l + log h) / 2
    out = SizeCalibration(coef, (60,)).apply(np.array([[4.0, 2.0, 1.0]]), np.array([0]))
    assert out[0] == pytest.approx([4.0, 2.0, np.exp(0.1) * 2.0])


def test_json_round_trip_and_bad_values():
    calib = _calibration()
    back = SizeCalibration.from_json(calib.to_json())
    assert np.allclose(back.coef, calib.coef, atol=1e-6) and back.pairs == calib.pairs
    with pytest.raises(ValueError, match=r"model\.onnx: metadata: not a size calibration"):
        SizeCalibration.from_json("{not json", "model.onnx: metadata")
    with pytest.raises(ValueError, match="not a size calibration"):
        SizeCalibration.from_json('{"coef": [[[1, 2, 3]]], "pairs": [1]}')
    with pytest.raises(ValueError, match=r"coef must have shape \(C, 3, 4\)"):
        SizeCalibration(np.zeros((2, 3, 3)), (0, 0))
    with pytest.raises(ValueError, match="finite"):
        SizeCalibration(np.full((1, 3, 4), np.nan), (0,))
    with pytest.raises(ValueError, match="pairs must be 1 counts"):
        SizeCalibration(np.zeros((1, 3, 4)), (0, 0))
    with pytest.raises(ValueError, match="3 sizes but 2 types"):
        calib.apply(np.ones((3, 3)), np.zeros(2, int))


def test_least_absolute_ignores_gross_outliers_that_pull_least_squares():
    rng = np.random.default_rng(0)
    x = np.column_stack([np.ones(200), rng.uniform(0, 1, 200)])
    y = 0.5 + 2.0 * x[:, 1] + rng.normal(0, 0.01, 200)
    y[:20] += 5.0  # one in ten badly off
    assert least_absolute(x, y) == pytest.approx([0.5, 2.0], abs=0.02)
    assert abs(np.linalg.lstsq(x, y, rcond=None)[0][0] - 0.5) > 0.2


def test_fit_recovers_a_log_linear_map_per_type_and_keeps_rare_types_as_they_are():
    rng = np.random.default_rng(1)
    pred = np.exp(rng.normal(np.log([4.5, 1.8, 1.5]), 0.1, (300, 3)))
    vtype = np.r_[np.zeros(260, int), np.full(40, 3)]  # type 3: fewer than the 50 pairs a fit needs
    true = pred.copy()
    true[vtype == 0] = 1.1 * pred[vtype == 0] ** [1.0, 0.8, 1.2]  # log-linear in each size
    calib = fit_size_calibration(pred, vtype, true, 5)
    assert calib.pairs == (260, 0, 0, 0, 0)
    assert calib.apply(pred, vtype) == pytest.approx(true, rel=1e-4)
    assert np.array_equal(calib.coef[1:], SizeCalibration.identity(5).coef[1:])


def test_fit_rejects_bad_input():
    ok = np.ones((60, 3))
    with pytest.raises(ValueError, match="60 predicted sizes, 59 true, 60 types"):
        fit_size_calibration(ok, np.zeros(60, int), ok[:59], 5)
    with pytest.raises(ValueError, match="true ones > 0"):
        fit_size_calibration(ok, np.zeros(60, int), np.zeros((60, 3)), 5)
    with pytest.raises(ValueError, match="finite"):
        fit_size_calibration(np.full((60, 3), np.nan), np.zeros(60, int), ok, 5)
    with pytest.raises(ValueError, match="min_pairs must be >= 5"):
        fit_size_calibration(ok, np.zeros(60, int), ok, 5, min_pairs=3)


def _oracle(small_recording, size_gain=(1.0, 1.0, 1.0), box_gain=(1.0, 1.0), box_shift=(0.0, 0.0)):
    """A detector that finds every vehicle to detect of the small recording, reading its sizes times size_gain and
    its 2D box widened by box_gain about a centre moved by box_shift (in box sizes); every vehicle typed car."""
    from tests.pipeline_fixtures import labels_of_image

    labels = labels_of_image(small_recording)

    def detect(grey: np.ndarray) -> Detections:
        s = labels(grey)
        keep = s.weight > 0
        n = int(keep.sum())
        box = s.box[keep]
        wh = box[:, 2:4] - box[:, 0:2]
        centre = (box[:, 0:2] + box[:, 2:4]) / 2 + np.asarray(box_shift) * wh
        wh = wh * np.asarray(box_gain)
        vtype = np.zeros(n, int)
        return Detections(np.linspace(1.0, 0.5, n), s.bottom_uv[keep], np.hstack([centre - wh / 2, centre + wh / 2]),
                          np.tile([1.0, 0.0], (n, 1)), s.size_lwh[keep] * np.asarray(size_gain), vtype,
                          np.eye(5)[vtype])

    return detect


def test_size_pairs_from_a_recording_fit_a_detector_that_reads_sizes_short(small_recording):
    """Sizes read at 0.8, 0.9, 1.1 times the truth: the pairs are the matched detections and the fit undoes it."""
    frames = collect_frames(_oracle(small_recording, size_gain=(0.8, 0.9, 1.1)), [small_recording], every=1)
    assert all(s.image.size == 0 for _, s, _ in frames)  # the pixels are not kept
    pairs = size_pairs(frames)
    assert len(pairs["pred"]) > 5 and np.allclose(pairs["pred"], pairs["true"] * [0.8, 0.9, 1.1])
    calib = fit_size_calibration(pairs["pred"], pairs["vtype"], pairs["true"], 5, min_pairs=5)
    assert calib.apply(pairs["pred"], pairs["vtype"]) == pytest.approx(pairs["true"], rel=1e-3)
    none = [(Detections(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros((0, 3)),
                        np.zeros(0, int), np.zeros((0, 5))), s, wh) for _, s, wh in frames]
    with pytest.raises(ValueError, match="no detection matched a vehicle"):
        size_pairs(none)


def test_box_pairs_from_a_recording_fit_a_detector_whose_boxes_are_off(small_recording):
    """Boxes 1.3 times too wide and 0.8 times too high, their centres a tenth of a box too high: the box map fitted
    on the pairs puts them back, and the boxes then match the labels."""
    frames = collect_frames(_oracle(small_recording, box_gain=(1.3, 0.8), box_shift=(0.0, -0.1)), [small_recording])
    feats, targets = box_pairs(frames)
    assert len(feats) > 5 and feats.shape[1] == 17 + 5
    assert targets[:, 0:2] == pytest.approx(np.tile(-np.log([1.3, 0.8]), (len(targets), 1)))
    calib = fit_box_calibration(feats, targets, min_pairs=5)
    for det, s, (width, height) in frames:
        fixed = calib.apply(det, width, height)
        assert fixed.box == pytest.approx(s.box[s.weight > 0], abs=1e-6)
        assert np.array_equal(fixed.uv, det.uv) and np.array_equal(fixed.size_lwh, det.size_lwh)


def test_box_calibration_map_and_bad_values():
    det = Detections(np.array([0.9, 0.8]), np.array([[100.0, 80.0], [20.0, 30.0]]),
                     np.array([[90.0, 60.0, 110.0, 84.0], [10.0, 20.0, 30.0, 32.0]]),
                     np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([[4.5, 1.8, 1.5], [0.0, 1.0, 1.0]]), np.array([0, 1]),
                     np.eye(5)[[0, 1]])
    feats = box_features(det, 200, 160)
    assert feats.shape == (2, 22) and np.isfinite(feats).all()  # a zero size from the ReLU read as 5 cm
    coef = np.zeros((22, 4))
    assert np.array_equal(BoxCalibration(coef, 10).apply(det, 200, 160).box, det.box)  # no change
    coef[0] = [np.log(2.0), 0.0, 0.25, 0.0]  # twice as wide, the centre a quarter of the old width to the right
    out = BoxCalibration(coef, 10).apply(det, 200, 160)
    assert out.box[0] == pytest.approx([85.0, 60.0, 125.0, 84.0])
    coef[0, 0] = 50.0  # a wild map changes a side by e^2 at most
    wild = BoxCalibration(coef, 10).apply(det, 200, 160).box
    assert wild[:, 2] - wild[:, 0] == pytest.approx(np.exp(2.0) * np.array([20.0, 20.0]))
    back = BoxCalibration.from_json(BoxCalibration(coef, 10).to_json())
    assert np.allclose(back.coef, coef) and back.pairs == 10
    with pytest.raises(ValueError, match=r"coef must have shape \(17 \+ C, 4\)"):
        BoxCalibration(np.zeros((10, 4)), 1)
    with pytest.raises(ValueError, match="finite"):
        BoxCalibration(np.full((22, 4), np.inf), 1)
    with pytest.raises(ValueError, match="fitted for 3 types, the detections have 5"):
        BoxCalibration(np.zeros((20, 4)), 1).apply(det, 200, 160)
    with pytest.raises(ValueError, match="not a box calibration"):
        BoxCalibration.from_json('{"coef": 1}', "m.onnx")
    with pytest.raises(ValueError, match="image size must be > 0"):
        box_features(det, 0, 160)
    with pytest.raises(ValueError, match="fewer than 200"):
        fit_box_calibration(np.ones((10, 22)), np.zeros((10, 4)))
    with pytest.raises(ValueError, match="must be finite"):
        fit_box_calibration(np.full((300, 22), np.nan), np.zeros((300, 4)))


def test_the_calibration_travels_in_the_onnx_metadata(tmp_path):
    from tests.pipeline_fixtures import export_tiny_detector

    path = export_tiny_detector(tmp_path / "tiny.onnx")
    grey = np.random.default_rng(2).integers(0, 255, (96, 128), dtype=np.uint8)
    raw = OnnxDetector(path, threads=1, score_thr=0.0).detect(grey)  # before: no calibration in the file
    assert len(raw) > 0
    write_calibrations([path], sizes=_calibration(type_=int(raw.vtype[0])))
    det = OnnxDetector(path, threads=1, score_thr=0.0)
    assert det.size_calibration is not None and det.box_calibration is None
    assert det.config["stride"] == 4  # the other metadata kept
    got = det.detect(grey)
    mine = raw.vtype == raw.vtype[0]
    assert np.allclose(got.size_lwh[mine], raw.size_lwh[mine] * [2.0, 1.0, 0.5])
    assert np.array_equal(got.size_lwh[~mine], raw.size_lwh[~mine])
    assert np.array_equal(got.uv, raw.uv) and np.array_equal(got.score, raw.score)
    assert np.array_equal(got.box, raw.box)
    coef = np.zeros((22, 4))
    coef[0, 0] = np.log(2.0)  # every box twice as wide about its centre
    write_calibrations([path], boxes=BoxCalibration(coef, 500))
    both = OnnxDetector(path, threads=1, score_thr=0.0).detect(grey)
    assert np.allclose(both.box[:, 2] - both.box[:, 0], 2 * (raw.box[:, 2] - raw.box[:, 0]))
    assert np.allclose(both.size_lwh, got.size_lwh)  # the size calibration kept beside it
    # in the image's own pixels when the network looked at a part of it (a detect area)
    area = OnnxDetector(path, threads=1, score_thr=0.0).detect(grey, area_px=(32, 0, 96, 96))
    assert np.allclose(area.box[:, 2] - area.box[:, 0],
                       2 * np.diff(OnnxDetector(path, threads=1, score_thr=0.0, calibrated_heads=False)
                                   .detect(grey, area_px=(32, 0, 96, 96)).box[:, [0, 2]], axis=1)[:, 0])
    off = OnnxDetector(path, threads=1, score_thr=0.0, calibrated_heads=False)
    assert off.size_calibration is None and off.box_calibration is None
    assert np.array_equal(off.detect(grey).size_lwh, raw.size_lwh) and np.array_equal(off.detect(grey).box, raw.box)


def test_a_broken_calibration_in_a_model_file_is_named(tmp_path):
    import onnx

    from tests.pipeline_fixtures import export_tiny_detector

    path = export_tiny_detector(tmp_path / "tiny.onnx")
    proto = onnx.load(str(path))
    onnx.helper.set_model_props(proto, {**{p.key: p.value for p in proto.metadata_props}, SIZE_CALIBRATION_KEY: "[]"})
    onnx.save(proto, str(path))
    with pytest.raises(ValueError, match=r"tiny\.onnx: metadata: not a size calibration"):
        OnnxDetector(path, threads=1)
    assert OnnxDetector(path, threads=1, calibrated_heads=False).size_calibration is None  # read only when applied
    write_calibrations([path], sizes=SizeCalibration.identity(5), boxes=BoxCalibration(np.zeros((20, 4)), 300))
    with pytest.raises(ValueError, match=r"tiny\.onnx: metadata: the box calibration is for 3 vehicle types, the "
                                         r"model has 5"):
        OnnxDetector(path, threads=1)


def test_the_shipped_detector_carries_both_calibrations_in_both_files():
    fp32 = OnnxDetector(REPO / "models" / "detector_fp32.onnx", threads=1)
    fp16 = OnnxDetector(REPO / "models" / "detector_fp16.onnx", threads=1)
    assert fp32.size_calibration is not None and fp16.size_calibration is not None
    assert np.array_equal(fp32.size_calibration.coef, fp16.size_calibration.coef)
    assert min(fp32.size_calibration.pairs) >= 50  # every type fitted
    assert fp32.box_calibration is not None and np.array_equal(fp32.box_calibration.coef, fp16.box_calibration.coef)


def test_roadside_calibrate_heads_names_a_missing_model(tmp_path, capsys):
    from roadside.cli import main

    assert main(["calibrate-heads", str(tmp_path / "nope.onnx"), "--recording", str(tmp_path)]) != 0
    assert "model not found" in capsys.readouterr().err


def _tiny_checkpoint(path: Path) -> Path:
    import torch

    from training.model import Detector, DetectorConfig, save_detector

    torch.manual_seed(0)
    save_detector(Detector(DetectorConfig(width_mult=0.25, decoder_channels=16, head_channels=8, stride=4)), path)
    return path


def _fake_recording(path: Path) -> Path:
    """A folder the recording reader opens (a camera listed): enough for the checks made before an export."""
    import json

    path.mkdir(parents=True)
    (path / "recording.json").write_text(json.dumps({"format": "roadside-recording", "version": 1,
                                                     "cameras": [{"name": "NE"}]}))
    return path


def test_export_with_a_calibration_that_cannot_be_made_leaves_the_files_at_out_as_they_were(tmp_path, monkeypatch,
                                                                                          capsys):
    """`export --calibration-recording` once wrote the ONNX files first and then failed on the recordings (a typo,
    too few matched detections), leaving uncalibrated files in place of good ones. The recordings are checked
    first, and the files are written under other names and renamed into place only when all succeeded."""
    pytest.importorskip("torch")
    import training.heads_calibration as heads
    from roadside.cli import main

    model = _tiny_checkpoint(tmp_path / "model.pt")
    out = tmp_path / "new" / "sub" / "detector.onnx"  # its folder is made
    assert main(["export", str(model), "--out", str(out)]) == 0
    fp16 = out.with_name("detector_fp16.onnx")
    assert OnnxDetector(out, threads=1).box_calibration is None and fp16.is_file()
    good = {p: p.read_bytes() for p in (out, fp16)}

    def export(*flags: str) -> int:
        return main(["export", str(model), "--out", str(out), *flags])

    assert export("--calibration-recording", str(tmp_path / "typo")) == 2
    assert "not a recording" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        export("--calibration-recording", str(tmp_path / "typo"), "--calibration-every", "0")
    assert "--calibration-every: must be a whole number >= 1" in capsys.readouterr().err

    recording = _fake_recording(tmp_path / "rec")
    seen = []

    def too_few(paths, recordings, every, log=None):
        seen.extend(paths)
        assert all(p.is_file() for p in paths)  # the new export, under other names
        raise ValueError("fit_box_calibration: 12 matched detections, fewer than 200")

    monkeypatch.setattr(heads, "calibrate_files", too_few)
    assert export("--calibration-recording", str(recording)) == 2
    assert "fewer than 200" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in (out, fp16)} == good
    assert len(seen) == 2 and not set(seen) & {out, fp16}
    assert sorted(p.name for p in out.parent.iterdir()) == ["detector.onnx", "detector_fp16.onnx"]  # none left over

    def fitted(paths, recordings, every, log=None):
        heads.write_calibrations(paths, sizes=SizeCalibration.identity(5), boxes=BoxCalibration(np.zeros((22, 4)), 300))
        return {"sizes": SizeCalibration.identity(5), "boxes": BoxCalibration(np.zeros((22, 4)), 300),
                "box_pairs_at_iou50_before": 0.5, "box_pairs_at_iou50_after": 0.6, "size_error_before": 0.4,
                "size_error_after": 0.3}

    monkeypatch.setattr(heads, "calibrate_files", fitted)
    assert export("--calibration-recording", str(recording)) == 0
    assert f"written into {out}, {fp16}:" in capsys.readouterr().out
    assert all(OnnxDetector(p, threads=1).box_calibration is not None for p in (out, fp16))
    assert sorted(p.name for p in out.parent.iterdir()) == ["detector.onnx", "detector_fp16.onnx"]


def test_export_and_calibrate_heads_without_their_packages_say_what_to_install(tmp_path, monkeypatch, capsys):
    import sys

    import onnx

    from roadside.cli import main

    (tmp_path / "m.onnx").write_bytes(b"x")
    # calibrate-heads without onnx: said before the detector is run over the recordings, not after
    monkeypatch.setitem(sys.modules, "onnx", None)  # as if not installed: importing it raises ImportError
    assert main(["calibrate-heads", str(tmp_path / "m.onnx"), "--recording", str(tmp_path / "typo")]) == 2
    assert "calibrating the heads needs onnx" in capsys.readouterr().err
    # export without torch
    monkeypatch.setitem(sys.modules, "onnx", onnx)
    for name in ("training.export", "training.model"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.setitem(sys.modules, "torch", None)
    assert main(["export", str(tmp_path / "model.pt"), "--out", str(tmp_path / "d.onnx")]) == 2
    assert "export needs the train extra (pip install -e '.[train]')" in capsys.readouterr().err
