"""eval.static: places the detector keeps coming back to, the candidates for a camera's exclusion zones."""

from __future__ import annotations

import numpy as np
import pytest

from eval.static import crop, static_detections
from shared.decode import Detections


def _detections(uv: list[list[float]], score: float = 0.4) -> Detections:
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    n = len(uv)
    return Detections(np.full(n, score), uv, np.c_[uv - 5, uv + 5], np.tile([1.0, 0.0], (n, 1)),
                      np.tile([4.5, 1.8, 1.5], (n, 1)), np.zeros(n, np.int64), np.tile([1.0, 0, 0, 0, 0], (n, 1)))


def test_a_place_detected_in_most_frames_is_found_and_passing_vehicles_are_not():
    rng = np.random.default_rng(3)
    frames = []
    for k in range(20):
        passing = rng.uniform(0, 600, size=(3, 2)).tolist()  # vehicles somewhere else every frame
        marking = [[100 + rng.normal(0, 1.0), 200 + rng.normal(0, 1.0)]] if k % 5 else []  # 16 of 20 frames
        frames.append(passing + marking)
    calls = iter(frames)
    r = static_detections(range(20), lambda _img: _detections(next(calls)), min_fraction=0.5)
    assert r["frames"] == 20 and len(r["spots"]) == 1
    spot = r["spots"][0]
    assert spot["frames"] == 16 and spot["fraction"] == 0.8 and spot["score"] == pytest.approx(0.4)
    assert spot["uv"] == pytest.approx([100, 200], abs=1.0)
    (x0, y0), _, (x1, y1), _ = spot["exclude_px"]
    assert x0 < spot["uv"][0] < x1 and y0 < spot["uv"][1] < y1 and x1 - x0 == pytest.approx(15)


def test_two_detections_of_one_frame_never_count_twice_for_one_place():
    calls = iter([[[50, 50], [52, 50]], [[50, 50]], [[300, 300]], [[300, 300]]])
    r = static_detections(range(4), lambda _img: _detections(next(calls)), min_fraction=0.5)
    assert [(s["frames"], s["uv"]) for s in r["spots"]] == [(2, [50.0, 50.0]), (2, [300.0, 300.0])]


def test_bad_arguments_and_no_frames_are_refused():
    with pytest.raises(ValueError, match="no frames"):
        static_detections([], lambda _img: _detections([]))
    with pytest.raises(ValueError, match="min_fraction"):
        static_detections([0], lambda _img: _detections([]), min_fraction=0)
    with pytest.raises(ValueError, match="radius_px"):
        static_detections([0], lambda _img: _detections([]), radius_px=0)


def test_crop_is_clipped_at_the_border_and_enlarged():
    image = np.arange(100 * 80, dtype=np.uint16).reshape(80, 100)
    out = crop(image, (5.0, 70.0), half=10, zoom=2)
    assert out.shape == (2 * (80 - 60), 2 * (15 - 0))
    assert out[0, 0] == image[60, 0]


def test_the_command_runs_the_shipped_model_over_a_folder_and_names_bad_input(tmp_path, capsys):
    import json
    from pathlib import Path

    import cv2

    from roadside.cli import main

    model = Path(__file__).resolve().parent.parent / "models" / "detector_fp32.onnx"
    frames = tmp_path / "cam"
    frames.mkdir()
    for k in range(3):
        cv2.imwrite(str(frames / f"2023-12-19 11-00-0{k}-000000.jpg"), np.full((96, 128), 120, np.uint8))
    assert main(["static", "--model", str(model), "--frames", str(frames), "--every", "1"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames"] == 3 and r["spots"] == []  # a flat grey image has nothing to detect
    assert main(["static", "--model", str(model), "--frames", str(frames), "--until", "11:00:01"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 1
    assert main(["static", "--model", str(model), "--frames", str(tmp_path / "nope")]) == 2
    assert "frames folder not found" in capsys.readouterr().err
    (frames / "2023-12-19 11-00-05-000000.jpg").write_bytes(b"not a jpeg")
    assert main(["static", "--model", str(model), "--frames", str(frames), "--every", "1"]) == 2
    assert "not a readable image" in capsys.readouterr().err
