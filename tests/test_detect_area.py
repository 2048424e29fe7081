"""A camera's detect area (`cameras[].detect_area_px`): the detector runs on a rectangle of the image (a fisheye's
image circle) at the whole image's scale and on its 32-pixel grid, and reports detections in the image's pixels."""

from __future__ import annotations

import numpy as np
import pytest
from pipeline_fixtures import REPO, export_tiny_detector

from shared.cameras import Camera, Pose
from shared.inference import OnnxDetector, area_box
from shared.settings import CameraSettings


def test_area_box_moves_out_to_the_grid_and_stays_in_the_image():
    # the simulated roundabout's fisheye circle (90 degrees) on the full 1280 x 960 image, 64-pixel grid
    assert area_box((165, 5, 1115, 955), (960, 1280), 1.0, 64.0) == (128, 0, 1152, 960)
    # the same area on a copy decoded at half size: the grid is 32 pixels of the copy
    assert area_box((165, 5, 1115, 955), (480, 640), 0.5, 32.0) == (64, 0, 576, 480)
    # without a grid: whole pixels, widened outwards
    assert area_box((10.2, 20.7, 30.1, 40.0), (100, 100)) == (10, 20, 31, 40)
    # the grid reaches past the image's edge: clipped
    assert area_box((1200, 900, 1280, 960), (960, 1280), 1.0, 64.0) == (1152, 896, 1280, 960)
    with pytest.raises(ValueError, match="leaves nothing of a 1280x960 image"):
        area_box((1280, 0, 1300, 10), (960, 1280))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> OnnxDetector:
    path = export_tiny_detector(tmp_path_factory.mktemp("model") / "tiny.onnx")
    return OnnxDetector(path, threads=1, score_thr=0.0)


def textured(h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, (h, w), dtype=np.uint8)


def test_detections_inside_the_area_in_the_whole_images_pixels(tiny):
    img = textured(480, 640)  # smaller than the model's 640 px input: scale 1, a 32-pixel grid
    # 32 pixels of context around the area, (68, 38) to (332, 282), then out to the grid
    assert tiny.area_crop(img.shape, 1.0, (100, 70, 300, 250)) == (64, 32, 352, 288)
    part = tiny.detect(img, area_px=(100, 70, 300, 250))
    assert len(part) > 0
    assert part.uv[:, 0].min() >= 64 - 0.5 and part.uv[:, 0].max() <= 352
    assert part.uv[:, 1].min() >= 32 - 0.5 and part.uv[:, 1].max() <= 288
    assert part.uv[:, 0].min() < 100 and part.uv[:, 1].max() > 250  # the context is looked at too
    # the whole image as the area is the whole image
    whole, full = tiny.detect(img), tiny.detect(img, area_px=(0, 0, 640, 480))
    np.testing.assert_array_equal(full.uv, whole.uv)
    np.testing.assert_array_equal(full.score, whole.score)


def matched_share(a, b, tol_px: float = 0.5) -> float:
    """The share of a's detections with one of b's within tol_px and 0.03 in score."""
    d = np.linalg.norm(a.uv[:, None] - b.uv[None], axis=2)
    j = d.argmin(axis=1)
    return float(np.mean((d[np.arange(len(a)), j] <= tol_px) & (np.abs(a.score - b.score[j]) <= 0.03)))


def test_the_shipped_detector_on_a_fisheye_circle_finds_what_it_finds_on_the_whole_image(small_recording):
    """On the grid the network sees the circle and its surroundings as in the whole image; off it (a crop 6 pixels
    over, 3 at the network's input) the same vehicles come out pixels apart: the network is not shift-invariant
    below it."""
    import cv2

    from sim.recording import Recording

    rec = Recording(small_recording)
    cam = rec.cameras["NE"]
    det = OnnxDetector(REPO / "models" / "detector_fp32.onnx", threads=1, score_thr=0.3)
    img = cv2.imread(str(rec.frames("NE")[0][1]), cv2.IMREAD_GRAYSCALE)
    whole = det.detect(img)
    area = cam.image_area_px()
    circle = det.detect(img, area_px=area)
    assert len(whole) >= 5
    assert matched_share(whole, circle) >= 0.9
    x0, _, x1, _ = det.area_crop(img.shape, 1.0, area)
    assert (x0, x1) == (64, 1216)  # the circle, 145 to 1135, with 64 pixels of context, on the 64-pixel grid
    off = det._detect_timed(img[:, x0 + 6:x1 + 6].copy(), 1.0, det.scale_for(*img.shape))[0].scaled(1.0, 1.0, x0 + 6, 0)
    assert matched_share(whole, off) <= 0.5


def test_area_on_a_copy_decoded_smaller(tiny):
    img = textured(480, 640)  # a 1280 x 960 camera decoded at half size
    # in the camera's full-size pixels; the context is 64 of them (32 of the copy, at the network's scale)
    assert tiny.area_crop(img.shape, 0.5, (640, 480, 1280, 960)) == (288, 192, 640, 480)
    det = tiny.detect(img, 0.5, area_px=(640, 480, 1280, 960))
    assert len(det) > 0
    assert det.uv[:, 0].min() >= 288 - 0.5 and det.uv[:, 1].min() >= 192 - 0.5  # the copy's pixels


def test_camera_image_area():
    fisheye = Camera("F", "fisheye", 1280, 960, 300.0, 300.0, 639.5, 479.5, (0.0, 0.0, 0.0, 0.0),
                     Pose.from_angles((0.0, 0.0, 10.0), 0.0, -90.0, 0.0), max_angle_deg=100.0)
    x0, y0, x1, y1 = fisheye.image_area_px()
    r = fisheye.image_circle_radius_px()  # 300 * 100 degrees in radians: 523.6 px, taller than the image
    assert (x0, x1) == (int(np.floor(639.5 - r)), int(np.ceil(639.5 + r)) + 1) and (y0, y1) == (0, 960)
    assert fisheye.image_area_px(90.0) == (168, 8, 1112, 952)  # 300 px * pi / 2 = 471.2 px around the centre
    pinhole = Camera("P", "pinhole", 640, 512, 500.0, 500.0, 319.5, 255.5, (0.0,) * 5,
                     Pose.from_angles((0.0, 0.0, 8.0), 0.0, -20.0, 0.0))
    assert pinhole.image_area_px() == (0, 0, 640, 512)


def test_settings_reject_an_area_outside_the_image():
    ok = CameraSettings(name="NE", kind="fisheye", width=1280, height=960, detect_area_px=(115, 0, 1182, 960))
    assert ok.detect_area_px == (115, 0, 1182, 960)
    for bad in ((0, 0, 1300, 960), (500, 0, 400, 960), (-1, 0, 100, 100)):
        with pytest.raises(ValueError, match=r"camera NE: detect_area_px .* within the 1280x960 image"):
            CameraSettings(name="NE", kind="fisheye", width=1280, height=960, detect_area_px=bad)


def disc_frames(n: int = 3, w: int = 320, h: int = 240, r: int = 100) -> list[tuple[str, np.ndarray]]:
    """Frames of a lit image circle (centre 150, 120, radius r) on black, with noise in the circle only."""
    import cv2

    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        img = np.zeros((h, w), np.uint8)
        cv2.circle(img, (150, 120), r, 90, -1)
        img[img > 0] = np.clip(img[img > 0] + rng.integers(-20, 20, int((img > 0).sum())), 50, 255)
        out.append((f"f{k}.png", img))
    return out


def test_image_area_finds_the_circle_and_names_bad_frames():
    from calibration.area import image_area

    area, size, n = image_area(disc_frames())
    assert size == (320, 240) and n == 3
    # rows 20..220 and columns 50..250 are lit; a column needs more than 2 % of its rows lit (5 of 240)
    x0, y0, x1, y1 = area
    assert 50 <= x0 <= 53 and 247 <= x1 <= 251 and 20 <= y0 <= 23 and 217 <= y1 <= 221
    frames = disc_frames()
    frames.append(("odd.png", np.zeros((100, 100), np.uint8)))
    with pytest.raises(ValueError, match=r"odd.png: 100x100, the frames before it are 320x240"):
        image_area(frames)
    with pytest.raises(ValueError, match="all dark"):
        image_area([("dark.png", np.full((50, 60), 10, np.uint8))])
    with pytest.raises(ValueError, match="no frames"):
        image_area([])


def test_roadside_area_prints_the_site_setting(tmp_path, capsys):
    import json

    import cv2

    from roadside.cli import main

    for name, img in disc_frames():
        cv2.imwrite(str(tmp_path / name), img)
        (tmp_path / f"._{name}").write_bytes(b"\x00\x05\x16\x07")  # macOS's AppleDouble file: not a frame
    assert main(["area", "--frames", str(tmp_path), "--every", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 3 and (out["width"], out["height"]) == (320, 240)
    x0, y0, x1, y1 = out["detect_area_px"]
    assert CameraSettings(name="C", kind="fisheye", width=320, height=240, detect_area_px=(x0, y0, x1, y1))
    assert main(["area", "--frames", str(tmp_path / "missing")]) == 2
    assert "frames folder not found" in capsys.readouterr().err


def test_mirror_average_turns_the_mirrors_maps_back():
    """A mirror's maps that are exactly the image's turned round (columns reversed, the x of the offsets and the
    heading and the axis's sin 2a negated) average back to the image's own maps."""
    from shared.inference import MIRROR_NEGATED, mirror_average

    rng = np.random.default_rng(0)
    shapes = {"heat": 1, "size": 5, "heading": 2, "vtype_prob": 4, "offset": 4, "axis": 2, "vote": 2}
    own = {k: rng.normal(size=(c, 6, 8)).astype(np.float32) for k, c in shapes.items()}
    outputs = {}
    for k, o in own.items():
        turned = o[..., ::-1].copy()
        for c in MIRROR_NEGATED.get(k, ()):
            turned[c] = -turned[c]
        outputs[k] = np.stack([o, turned])
    back = mirror_average(outputs)
    for k in own:
        np.testing.assert_allclose(back[k], own[k], rtol=0, atol=1e-6)
    # a mirror that saw the same thing unturned gives a different average wherever the x channels are not zero
    same = mirror_average({k: np.stack([o, o]) for k, o in own.items()})
    assert not np.allclose(same["offset"][0], own["offset"][0])
    assert np.allclose(same["heat"], 0.5 * (own["heat"] + own["heat"][..., ::-1]))


def test_mirrored_detection_sees_a_mirrored_frame_as_the_mirror_of_the_frame(small_recording):
    """With `mirror`, the detections of a frame turned left to right are those of the frame turned round; the
    network alone is not mirror-symmetric."""
    import cv2

    from sim.recording import Recording

    rec = Recording(small_recording)
    img = cv2.imread(str(rec.frames("NE")[0][1]), cv2.IMREAD_GRAYSCALE)
    w = img.shape[1]
    model = REPO / "models" / "detector_fp32.onnx"

    # the heads' own boxes: the box calibration is fitted on a world whose traffic keeps right, not mirror-symmetric
    mirrored = OnnxDetector(model, threads=1, score_thr=0.3, mirror=True, calibrated_heads=False)
    a, b = mirrored.detect(img), mirrored.detect(np.ascontiguousarray(img[:, ::-1]))
    assert len(a) >= 5 and len(a) == len(b)
    ia, ib = np.argsort(a.uv[:, 1] * 1e4 + a.uv[:, 0]), np.argsort(b.uv[:, 1] * 1e4 + (w - 1 - b.uv[:, 0]))
    np.testing.assert_allclose(a.uv[ia, 0], w - 1 - b.uv[ib, 0], atol=1e-3)
    np.testing.assert_allclose(a.uv[ia, 1], b.uv[ib, 1], atol=1e-3)
    np.testing.assert_allclose(a.score[ia], b.score[ib], atol=1e-5)
    np.testing.assert_allclose(a.heading_uv[ia], b.heading_uv[ib] * [-1, 1], atol=1e-4)
    np.testing.assert_allclose(a.box[ia][:, [0, 2]], w - 1 - b.box[ib][:, [2, 0]], atol=1e-3)
    plain = OnnxDetector(model, threads=1, score_thr=0.3)
    p, q = plain.detect(img), plain.detect(np.ascontiguousarray(img[:, ::-1]))
    d = np.abs(p.uv[:, None, 0] - (w - 1 - q.uv[None, :, 0])) + np.abs(p.uv[:, None, 1] - q.uv[None, :, 1])
    assert len(p) != len(q) or d.min(axis=1).max() > 0.01


def test_the_detect_service_mirrors_when_its_site_says_so(tmp_path):
    import yaml

    from services.detect.__main__ import load_detector
    from shared.settings import load_settings

    site = {"site": "t", "cameras": [{"name": "NE", "kind": "fisheye", "width": 1280, "height": 960}],
            "detect": {"model": str(REPO / "models" / "detector_fp32.onnx"), "providers": ["CPUExecutionProvider"]}}
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(site))
    assert load_detector(load_settings(tmp_path / "site.yaml")).mirror is False
    site["detect"]["mirror"] = True
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(site))
    assert load_detector(load_settings(tmp_path / "site.yaml")).mirror is True


def test_the_network_input_is_the_image_over_255_and_its_padding_one_half(tiny):
    """preprocess writes the scaled image into the padded input in place: the values are those of
    `image.astype(float32) / 255` to the bit, the padding out to the 32-pixel grid 0.5."""
    import cv2

    rng = np.random.default_rng(3)
    for shape in ((480, 640), (470, 630), (100, 90)):
        grey = rng.integers(0, 256, shape, dtype=np.uint8)
        x, scale = tiny.preprocess(grey)
        h, w = round(shape[0] * scale), round(shape[1] * scale)
        small = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        assert x.dtype == np.float32 and x.shape[2] % 32 == 0 and x.shape[3] % 32 == 0
        np.testing.assert_array_equal(x[0, 0, :h, :w], small.astype(np.float32) / 255.0)
        pad = np.ones(x.shape[2:], bool)
        pad[:h, :w] = False
        assert (x[0, 0][pad] == 0.5).all()
