"""calibration.pick: the orthophoto pixel <-> lat/lon mapping and the crop tool's errors (synthetic images only)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calibration.pick import Ortho, main, zoom_crop

# A slightly skewed north-up quad, like the State/Ellsworth orthophoto's corners.
CORNERS = {
    "tl": [42.229958579, -83.739731638],
    "tr": [42.229972311, -83.738218004],
    "bl": [42.228880732, -83.739710566],
    "br": [42.228850768, -83.738217605],
}


def _basemap(tmp_path, width: int = 51, height: int = 37):
    folder = tmp_path / "basemap"
    folder.mkdir()
    img = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "ortho.png"), img)
    (folder / "ortho.json").write_text(json.dumps(CORNERS))
    return folder


def test_ortho_mapping_hits_the_corners_and_round_trips(tmp_path):
    folder = _basemap(tmp_path)
    for name in ("ortho.png", "ortho.json"):  # copied from a Mac: AppleDouble files beside each, not the basemap's
        (folder / f"._{name}").write_bytes(b"\x00\x05\x16\x07")
    ortho = Ortho.load(folder)
    w, h = ortho.size
    outer = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    np.testing.assert_allclose(ortho.to_latlon(outer), [CORNERS[k] for k in ("tl", "tr", "bl", "br")], atol=1e-12)
    np.testing.assert_allclose(ortho.to_px(np.array([CORNERS[k] for k in ("tl", "tr", "bl", "br")])), outer, atol=1e-6)
    px = np.random.default_rng(1).uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (200, 2))
    np.testing.assert_allclose(ortho.to_px(ortho.to_latlon(px)), px, atol=1e-6)
    # the centre of the top-left pixel is (0, 0): half a pixel inside the tl corner, in both directions
    la, lo = ortho.to_latlon(np.array([[0.0, 0.0]]))[0]
    assert CORNERS["bl"][0] < la < CORNERS["tl"][0] and CORNERS["tl"][1] < lo < CORNERS["tr"][1]


def test_crop_outside_the_image_is_a_clear_error(tmp_path, capsys):
    img = np.zeros((40, 60, 3), np.uint8)
    with pytest.raises(ValueError, match=r"--at: point \(75.0, 10.0\) is outside the 60x40 image"):
        zoom_crop(img, (75.0, 10.0), 20, 4, where="--at")
    crop = zoom_crop(img, (0.0, 0.0), 20, 4)  # at the edge: padded, not an error
    assert crop.shape == (80, 80, 3)
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), img)
    assert main(["crop", "--image", str(path), "--at", "75,10", "--out", str(tmp_path / "c.png")]) == 2
    assert "--at: point (75.0, 10.0) is outside" in capsys.readouterr().err
    assert main(["crop", "--image", str(tmp_path / "nope.jpg"), "--at", "5,5", "--out", str(tmp_path / "c.png")]) == 2
    assert "nope.jpg" in capsys.readouterr().err


def test_pair_and_check_write_images(tmp_path):
    folder = _basemap(tmp_path)
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.full((40, 60, 3), 128, np.uint8))
    lat, lon = np.mean([CORNERS[k] for k in CORNERS], axis=0)
    marks = [
        {"id": f"L{i}", "u": 10.0 + 9 * i, "v": 5.0 + 7 * (i % 3), "lat": lat + 1e-5 * i, "lon": lon + 2e-5 * (i % 2)}
        for i in range(4)
    ]
    lm = tmp_path / "lm.json"
    lm.write_text(json.dumps({"camera": "X", "width": 60, "height": 40, "landmarks": marks}))
    out = tmp_path / "pair.png"
    args = ["--image", str(frame), "--basemap", str(folder), "--landmarks", str(lm)]
    assert main(["pair", *args, "--at", "20,20", "--latlon", f"{lat},{lon}", "--out", str(out)]) == 0
    assert cv2.imread(str(out)).shape[0] == 80 * 6
    out = tmp_path / "check.png"
    assert main(["check", *args, "--out", str(out)]) == 0
    assert cv2.imread(str(out)).shape[1] == 60 + 8 + 2 * 51
