"""Detector: targets, decode, loss, model (shapes, MACs, a short overfit) and ONNX export parity."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torch.utils.data import default_collate

from shared.decode import BOX_SCALE_PX, Detections, cell_centres, decode, model_stride, peak_mask
from training.loss import LossConfig, detector_loss, focal_heat_loss, heat_loss
from training.model import Detector, DetectorConfig, count_macs, load_detector, save_detector
from training.sample import VEHICLE_TYPES, Sample
from training.targets import MIN_SIGMA_CELLS, build_targets, gaussian_sigma_px

TINY = DetectorConfig(width_mult=0.25, decoder_channels=16, head_channels=8, stride=4)
NAN3 = [np.nan, np.nan, np.nan]


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Tiny models gain nothing from threads, and on a busy 2-core machine thread barriers cost seconds."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_sample(bottom_uv, box, heading_uv=None, size_lwh=None, vtype=None, weight=None, hw=(64, 96),
                image: np.ndarray | None = None) -> Sample:
    n = len(bottom_uv)
    return Sample(image if image is not None else np.zeros(hw, np.uint8), bottom_uv, box,
                  heading_uv if heading_uv is not None else [[1.0, 0.0]] * n,
                  size_lwh if size_lwh is not None else [[4.5, 1.8, 1.5]] * n,
                  vtype if vtype is not None else [0] * n, weight if weight is not None else [1.0] * n, source="test")


def one_hot_prob(vtype: np.ndarray) -> np.ndarray:
    """(C, h, w) probabilities that pick each cell's target type (type 0 where none)."""
    return np.eye(len(VEHICLE_TYPES))[np.maximum(vtype, 0)].transpose(2, 0, 1)


def decode_targets(t: dict[str, np.ndarray], stride: int) -> Detections:
    return decode(t["heat"][None], t["size"], t["heading"], one_hot_prob(t["vtype"]), t["offset"], stride)


# --- targets ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_peak_is_one_at_bottom_centre_cell(stride):
    s = make_sample([[21.3, 41.9]], [[10, 20, 34, 44]])
    t = build_targets(s, stride)
    assert t["heat"].shape == (64 // stride, 96 // stride)
    row, col = np.unravel_index(np.argmax(t["heat"]), t["heat"].shape)
    assert (col, row) == (int((21.3 + 0.5) // stride), int((41.9 + 0.5) // stride))
    assert t["heat"][row, col] == 1.0
    assert np.sum(t["heat"] == 1.0) == 1


def test_tiny_box_still_gets_its_peak():
    t = build_targets(make_sample([[22.9, 41.1]], [[22, 40, 24, 42]]), 4)
    assert t["heat"][10, 5] == 1.0 and t["weight"][10, 5] == 1.0


def test_gaussian_sigma_and_values():
    box = np.array([[10.0, 20.0, 40.0, 60.0]])  # diagonal 50 px
    sigma = 0.5 * np.sqrt(50.0)
    assert gaussian_sigma_px(box)[0] == pytest.approx(sigma)
    t = build_targets(make_sample([[30.0, 40.0]], box), stride=1)
    assert t["heat"][40, 33] == pytest.approx(np.exp(-9 / sigma**2), rel=1e-6)
    assert t["heat"][42, 29] == pytest.approx(np.exp(-5 / sigma**2), rel=1e-6)
    # stride 4: cell (col 8, row 10) has its centre at input pixel (33.5, 41.5); sigma is at least 1.5 cells
    t4 = build_targets(make_sample([[30.0, 40.0]], box), stride=4)
    assert cell_centres(9, 4)[8] == 33.5
    sigma4 = max(sigma, MIN_SIGMA_CELLS * 4)
    assert sigma4 == 6.0
    assert t4["heat"][10, 8] == pytest.approx(np.exp(-(3.5**2 + 1.5**2) / sigma4**2), rel=1e-6)
    assert t4["weight"][10, 8] == t4["heat"][10, 8]


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_offsets_reconstruct_centres(stride):
    s = make_sample([[21.3, 41.9], [70.05, 20.6]], [[10, 22, 34, 44], [58.2, 5.1, 83.9, 24.7]], hw=(64, 96))
    t = build_targets(s, stride)
    h, w = t["heat"].shape
    cu, cv = np.meshgrid(cell_centres(w, stride), cell_centres(h, stride))
    u = cu + t["offset"][0].astype(np.float64) * stride
    v = cv + t["offset"][1].astype(np.float64) * stride
    for k in range(2):
        row, col = int((s.bottom_uv[k, 1] + 0.5) // stride), int((s.bottom_uv[k, 0] + 0.5) // stride)
        assert u[row, col] == pytest.approx(s.bottom_uv[k, 0], abs=1e-5)
        assert v[row, col] == pytest.approx(s.bottom_uv[k, 1], abs=1e-5)
        assert -0.5 <= t["offset"][0, row, col] < 0.5 and -0.5 <= t["offset"][1, row, col] < 0.5
    owned = t["weight"] > 0
    centres = {tuple(np.round(p, 4)) for p in np.stack([u[owned], v[owned]], 1)}
    assert centres == {tuple(np.round(p, 4)) for p in s.bottom_uv}
    box_w = t["size"][3] * BOX_SCALE_PX
    box_cx = u + t["offset"][2] * box_w
    row, col = int((41.9 + 0.5) // stride), int((21.3 + 0.5) // stride)
    assert box_w[row, col] == pytest.approx(24.0, rel=1e-6)
    assert box_cx[row, col] == pytest.approx(22.0, abs=1e-5)


def test_box_centre_mode():
    s = make_sample([[21.3, 41.9]], [[10, 22, 34, 44]])
    t = build_targets(s, 4, center="box")
    row, col = np.unravel_index(np.argmax(t["heat"]), t["heat"].shape)
    assert (col, row) == (int(22.5 // 4), int(33.5 // 4))
    assert np.all(t["offset"][2:, row, col] == 0)
    d = decode_targets(t, 4)
    np.testing.assert_allclose(d.uv, [[22.0, 33.0]], atol=1e-6)
    np.testing.assert_allclose(d.box, s.box, atol=1e-5)
    with pytest.raises(ValueError, match="center"):
        build_targets(s, 4, center="top")


def test_weight_zero_vehicle_is_ignored_not_a_peak():
    s = make_sample([[20.0, 40.0], [70.0, 30.0]], [[10, 20, 30, 44], [60, 10, 80, 34]], weight=[1.0, 0.0])
    t = build_targets(s, 2)
    assert t["heat"][15, 35] == 0.0 and t["ignore"][15, 35]  # its bottom-centre cell
    assert t["ignore"][8, 33] and t["ignore"][5, 39]  # inside its 2D box
    assert not t["ignore"][20, 10] and t["heat"][20, 10] == 1.0  # the other vehicle's peak
    assert not t["ignore"][:, :20].any() and t["ignore"].sum() > 0
    assert t["vtype"][15, 35] == -1 and t["weight"][15, 35] == 0


def test_ignore_does_not_mask_a_vehicle_to_detect():
    s = make_sample([[20.0, 40.0], [22.0, 40.0]], [[10, 20, 30, 44], [12, 20, 32, 44]], weight=[1.0, 0.0])
    t = build_targets(s, 2)
    assert t["heat"][20, 10] == 1.0 and not t["ignore"][20, 10]
    assert not t["ignore"][t["heat"] >= 0.05].any()


def test_unknown_heading_size_and_type_get_no_weight_for_those_terms_only():
    s = make_sample([[20.0, 40.0], [70.0, 30.0]], [[10, 20, 30, 44], [60, 10, 80, 34]],
                    heading_uv=[[np.nan, np.nan], [0.6, 0.8]], size_lwh=[NAN3, [4.0, 1.8, 1.4]], vtype=[-1, 3])
    t = build_targets(s, 4)
    first = t["weight"] > 0
    first[:, 12:] = False
    assert first.any()
    assert not t["heading_mask"][first].any() and np.all(t["heading"][:, first] == 0)
    assert not t["size_mask"][:3, first].any() and t["size_mask"][3:, first].all()
    assert np.all(t["vtype"][first] == -1)
    assert t["heading_mask"][7, 17] and t["vtype"][7, 17] == 3 and t["size_mask"][:, 7, 17].all()
    for value in t.values():
        assert np.isfinite(value).all()


def test_overlapping_vehicles_cell_owned_by_highest_value():
    s = make_sample([[20.0, 40.0], [26.0, 40.0]], [[10, 20, 30, 44], [16, 20, 36, 44]], vtype=[1, 2])
    t = build_targets(s, 1)
    assert t["vtype"][40, 22] == 1 and t["vtype"][40, 24] == 2
    assert t["heat"][40, 23] == pytest.approx(max(np.exp(-9 / gaussian_sigma_px(s.box)[0] ** 2),
                                                  np.exp(-9 / gaussian_sigma_px(s.box)[1] ** 2)))


def test_votes_point_every_box_cell_at_its_centre():
    """A long vehicle (a bus seen from above): every cell of its box, far outside its Gaussian too, points at the
    bottom centre, and decoding there gives it back; cells shared with a second box do not vote, nor do cells
    another vehicle's Gaussian owns; the other targets stay unowned outside the Gaussians."""
    bus, car = [8, 20, 88, 44], [70, 36, 86, 50]
    s = make_sample([[48.0, 40.0], [78.0, 48.0]], [bus, car], hw=(64, 96))
    t = build_targets(s, 4)
    vote = t["vote_weight"] > 0
    cu, cv = cell_centres(24, 4), cell_centres(16, 4)
    row = 5  # cell centre v = 21.5: inside the bus's box only
    for col in (2, 6, 14):  # u = 9.5, 25.5, 57.5: 20-40 px from its centre, outside its Gaussian
        assert vote[row, col] and t["weight"][row, col] == 0
        off = t["offset"][:2, row, col]
        assert cu[col] + 4 * off[0] == pytest.approx(48.0) and cv[row] + 4 * off[1] == pytest.approx(40.0)
    assert vote[10, 12] and t["heat"][10, 12] == 1.0  # its own peak cell votes too (the same offset)
    assert t["vtype"][row, 2] == -1 and not t["size_mask"][:, row, 2].any()  # votes set the offset only
    # a cell in both boxes is ambiguous: no vote; the car's own peak cell is the car's, not the bus's
    both = (cv[:, None] >= 36) & (cv[:, None] <= 44) & (cu[None, :] >= 70) & (cu[None, :] <= 86)
    assert both.any() and not (vote & both).any()
    assert not vote[0, :].any() and not vote[:, 23].any()  # outside every box
    # a weight-0 vehicle's box does not vote
    t0 = build_targets(make_sample([[48.0, 40.0]], [bus], weight=[0.0]), 4)
    assert t0["vote_weight"].sum() == 0


def test_targets_reject_bad_input():
    with pytest.raises(ValueError, match="stride 5"):
        build_targets(make_sample([[20.0, 40.0]], [[10, 20, 30, 44]]), 5)
    with pytest.raises(ValueError, match="empty 2D box"):
        build_targets(make_sample([[20.0, 40.0]], [[10, 20, 10, 44]]), 4)


def test_no_vehicles():
    t = build_targets(make_sample(np.zeros((0, 2)), np.zeros((0, 4)), heading_uv=np.zeros((0, 2)),
                                  size_lwh=np.zeros((0, 3)), vtype=[], weight=[]), 4)
    assert t["heat"].max() == 0 and np.all(t["vtype"] == -1) and not t["ignore"].any()
    assert len(decode_targets(t, 4)) == 0


# --- decode ----------------------------------------------------------------------------------------------------


def hand_maps(h=8, w=10):
    heat = np.zeros((1, h, w), np.float32)
    heat[0, 2, 3], heat[0, 2, 4], heat[0, 1, 3] = 0.9, 0.8, 0.5  # a peak and lower neighbours
    heat[0, 5, 7], heat[0, 6, 7] = 0.7, 0.69
    heat[0, 6, 1] = 0.2  # a peak below the threshold
    size = np.ones((5, h, w), np.float32)
    size[:, 2, 3] = [4.5, 1.8, 1.5, 1.0, 0.5]  # box 32 x 16 px
    offset = np.zeros((4, h, w), np.float32)
    offset[:, 2, 3] = [0.25, -0.5, 0.1, -0.25]
    heading = np.zeros((2, h, w), np.float32)
    heading[:, 2, 3] = [0.3, 0.4]
    heading[:, 5, 7] = [-1.0, 0.0]
    heading[:, 6, 1] = [0.0, 2.0]
    prob = np.full((5, h, w), 0.2, np.float32)
    prob[:, 2, 3] = [0.1, 0.1, 0.6, 0.1, 0.1]
    return heat, size, heading, prob, offset


def test_decode_two_peaks_exact():
    d = decode(*hand_maps(), stride=4)
    assert len(d) == 2
    np.testing.assert_allclose(d.score, [0.9, 0.7], rtol=1e-6)
    # cell (col 3, row 2) centre = (13.5, 9.5); offset (0.25, -0.5) * 4
    np.testing.assert_allclose(d.uv, [[14.5, 7.5], [29.5, 21.5]])
    np.testing.assert_allclose(d.box[0], [14.5 + 3.2 - 16, 7.5 - 4 - 8, 14.5 + 3.2 + 16, 7.5 - 4 + 8], atol=1e-6)
    np.testing.assert_allclose(d.heading_uv, [[0.6, 0.8], [-1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(d.size_lwh[0], [4.5, 1.8, 1.5], rtol=1e-6)
    assert d.vtype[0] == 2 and d.vtype_prob.shape == (2, 5)


def test_decode_threshold_and_top_k():
    maps = hand_maps()
    assert len(decode(*maps, stride=4, score_thr=0.1)) == 3
    assert len(decode(*maps, stride=4, score_thr=0.75)) == 1
    top = decode(*maps, stride=4, score_thr=0.1, top_k=2)
    np.testing.assert_allclose(top.score, [0.9, 0.7], rtol=1e-6)
    assert len(decode(*maps, stride=4, top_k=0)) == 0
    maps[2][:, 6, 1] = 0.0  # a peak with no heading at all: no ground yaw, left out (not a message refused whole)
    assert decode(*maps, stride=4, score_thr=0.1).score.tolist() == pytest.approx([0.9, 0.7])


def test_peak_mask_is_the_3x3_maximum_everywhere():
    rng = np.random.default_rng(0)
    for shape in [(1, 1), (1, 5), (4, 1), (7, 9), (120, 160)]:
        for levels in (None, 4):  # continuous values, and coarse ones with plateaus
            heat = rng.random(shape).astype(np.float32)
            if levels:
                heat = np.round(heat * levels) / levels
            padded = np.pad(heat, 1, constant_values=-np.inf)
            top = heat == np.max([padded[i:i + shape[0], j:j + shape[1]] for i in range(3) for j in range(3)], axis=0)
            want = top.copy()
            for v, u in zip(*np.nonzero(top), strict=True):  # a tie with a peak before it, next to it, is left out
                for dv, du in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
                    if 0 <= v + dv and 0 <= u + du < shape[1] and top[v + dv, u + du] \
                            and heat[v + dv, u + du] == heat[v, u]:
                        want[v, u] = False
            np.testing.assert_array_equal(peak_mask(heat), want, err_msg=f"{shape} {levels}")


def test_peak_mask_plateau_and_border():
    """One peak of a plateau, the first in row-major order; a border cell is a peak as any other."""
    heat = np.array([[0.5, 0.5, 0.1], [0.2, 0.1, 0.0], [0.0, 0.0, 0.3]])
    np.testing.assert_array_equal(peak_mask(heat), [[1, 0, 0], [0, 0, 0], [0, 0, 1]])
    heat = np.array([[0.1, 0.1, 0.7], [0.1, 0.7, 0.1], [0.7, 0.7, 0.1]])  # a diagonal and a row of ties
    np.testing.assert_array_equal(peak_mask(heat), [[0, 0, 1], [0, 0, 0], [0, 0, 0]])


def test_an_fp16_tie_between_two_cells_of_one_vehicle_is_one_detection():
    """fp16 rounds 0.9005 and 0.9002 to one value: the two cells, both pointing at one bottom centre, gave two
    detections one cell apart."""
    h, w = 8, 8
    heat = np.zeros((1, h, w), np.float32)
    heat[0, 3, 3], heat[0, 3, 4] = 0.9005, 0.9002
    maps = [np.ones((5, h, w), np.float32), np.zeros((2, h, w), np.float32), np.full((5, h, w), 0.2, np.float32),
            np.zeros((4, h, w), np.float32)]
    maps[1][0] = 1.0
    maps[3][0, 3, 3], maps[3][0, 3, 4] = 0.45, -0.5
    for hm in (heat, heat.astype(np.float16).astype(np.float32)):
        det = decode(hm, *maps, stride=4, score_thr=0.3)
        assert det.uv[:, 0].tolist() == pytest.approx([15.3])


@pytest.mark.parametrize(("stride", "center"), [(1, "bottom"), (2, "bottom"), (4, "bottom"), (4, "box")])
def test_decode_of_targets_recovers_vehicles(stride, center):
    s = make_sample([[21.3, 41.9], [70.05, 20.6]], [[10, 22, 34, 44], [58.2, 5.1, 83.9, 24.7]],
                    heading_uv=[[0.6, 0.8], [-0.28, 0.96]], size_lwh=[[4.5, 1.8, 1.5], [12.0, 2.5, 3.5]],
                    vtype=[1, 3])
    d = decode_targets(build_targets(s, stride, center), stride)
    order = np.argsort(d.uv[:, 0])
    centre = s.bottom_uv if center == "bottom" else (s.box[:, :2] + s.box[:, 2:]) / 2
    np.testing.assert_allclose(d.uv[order], centre, atol=1e-6)
    np.testing.assert_allclose(d.box[order], s.box, atol=1e-5)
    np.testing.assert_allclose(d.heading_uv[order], s.heading_uv, atol=1e-6)
    np.testing.assert_allclose(d.size_lwh[order], s.size_lwh, rtol=1e-6)
    np.testing.assert_array_equal(d.vtype[order], s.vtype)
    np.testing.assert_array_equal(d.score, [1.0, 1.0])


def test_detections_scaled():
    d = decode(*hand_maps(), stride=4)
    s = d.scaled(2.0, 0.5, dx=10.0, dy=-1.0)
    np.testing.assert_allclose(s.uv, d.uv * [2.0, 0.5] + [10.0, -1.0])
    np.testing.assert_allclose(s.box, d.box * [2.0, 0.5, 2.0, 0.5] + [10.0, -1.0, 10.0, -1.0])
    expected = np.array([0.6 * 2, 0.8 * 0.5]) / np.hypot(1.2, 0.4)
    np.testing.assert_allclose(s.heading_uv[0], expected, atol=1e-6)
    np.testing.assert_array_equal(s.score, d.score)
    with pytest.raises(ValueError, match="sx"):
        d.scaled(0.0, 1.0)


def test_detections_select():
    d = decode(*hand_maps(), stride=4)
    assert len(d) == 2
    back = d.select(np.array([1, 0]))
    np.testing.assert_array_equal(back.uv, d.uv[::-1])
    np.testing.assert_array_equal(back.vtype_prob, d.vtype_prob[::-1])
    assert len(d.select(np.zeros(2, bool))) == 0 and d.select(np.array([True, False])).score.tolist() == [d.score[0]]


def test_decode_and_detections_reject_bad_shapes():
    heat, size, heading, prob, offset = hand_maps()
    with pytest.raises(ValueError, match="size"):
        decode(heat, size[:3], heading, prob, offset, stride=4)
    with pytest.raises(ValueError, match="heat"):
        decode(heat[0], size, heading, prob, offset, stride=4)
    with pytest.raises(ValueError, match="uv"):
        Detections(np.zeros(2), np.zeros((3, 2)), np.zeros((2, 4)), np.zeros((2, 2)), np.zeros((2, 3)),
                   np.zeros(2, np.int64), np.zeros((2, 5)))


# --- loss ------------------------------------------------------------------------------------------------------


def test_topk_picks_exactly_the_top_fraction():
    rng = np.random.default_rng(0)
    target = torch.zeros(2, 20, 25)
    pred = torch.from_numpy(rng.random((2, 20, 25)).astype(np.float32))
    ignore = torch.zeros(2, 20, 25, dtype=torch.bool)
    err = np.sort((pred.numpy() ** 2).ravel())[::-1]
    assert heat_loss(pred, target, ignore, 0.01).item() == pytest.approx(err[:10].mean(), rel=1e-6)
    assert heat_loss(pred, target, ignore, 0.1).item() == pytest.approx(err[:100].mean(), rel=1e-6)
    assert heat_loss(pred, target, ignore, None).item() == pytest.approx(err.mean(), rel=1e-6)
    ignore.view(-1)[torch.argmax(pred)] = True  # the worst pixel is ignored: the next 10 count
    assert heat_loss(pred, target, ignore, 0.01).item() == pytest.approx(err[1:11].mean(), rel=1e-6)


def test_focal_heat_loss_by_hand():
    """CenterNet's focal loss: peaks -(1-p)^2 log p, elsewhere -(1-y)^4 p^2 log(1-p), over the number of peaks;
    ignored cells count neither way."""
    pred = torch.tensor([[[0.9, 0.5, 0.2], [0.1, 0.6, 0.3]]])
    target = torch.tensor([[[1.0, 0.5, 0.0], [0.0, 1.0, 0.2]]])
    ignore = torch.tensor([[[False, False, False], [False, False, True]]])
    p, y = pred.numpy()[0], target.numpy()[0]
    pos = -(1 - p[0, 0]) ** 2 * np.log(p[0, 0]) - (1 - p[1, 1]) ** 2 * np.log(p[1, 1])
    neg = sum(-((1 - y[r, c]) ** 4) * p[r, c] ** 2 * np.log(1 - p[r, c]) for r, c in [(0, 1), (0, 2), (1, 0)])
    assert focal_heat_loss(pred, target, ignore).item() == pytest.approx((pos + neg) / 2, rel=1e-5)
    # a map without peaks is divided by one, not zero; a perfect map costs (almost) nothing
    no_peak = torch.zeros(1, 2, 3)
    assert focal_heat_loss(torch.full((1, 2, 3), 0.5), no_peak, ignore.clone().fill_(False)).item() == pytest.approx(
        6 * -(0.5**2) * np.log(0.5), rel=1e-5)
    assert focal_heat_loss(target.clamp(max=1.0) * (target >= 1), target, ignore).item() < 0.02
    # a confident miss costs far more than a hesitant one (the squared error's sigmoid gradient vanishes there)
    miss, unsure = pred.clone(), pred.clone()
    miss[0, 0, 0], unsure[0, 0, 0] = 0.01, 0.4
    assert focal_heat_loss(miss, target, ignore) > focal_heat_loss(unsure, target, ignore) + 1.0


def test_loss_config_heat_choice():
    torch.manual_seed(0)
    images, targets = batch_of([synthetic_sample()], 4)
    out = Detector(TINY)(images)
    _, mse = detector_loss(out, targets, LossConfig(heat="mse"), 4)
    _, focal = detector_loss(out, targets, LossConfig(heat="focal"), 4)
    assert focal["heat"] == pytest.approx(focal_heat_loss(out["heat"][:, 0], targets["heat"], targets["ignore"]).item())
    assert focal["heat"] != pytest.approx(mse["heat"]) and focal["size"] == mse["size"]
    with pytest.raises(ValueError, match="heat must be one of"):
        LossConfig(heat="l1")


def test_type_weights_weigh_the_cells_of_that_types_vehicles():
    """The synthetic sample holds a car (type 0) and a truck (type 2): weights of 1 change nothing; a weight on the
    truck multiplies its cells' focal terms, and its share of the regression terms, and nothing of the car's."""
    torch.manual_seed(0)
    images, targets = batch_of([synthetic_sample()], 4)
    out = Detector(TINY)(images)
    _, plain = detector_loss(out, targets, LossConfig(heat="focal"), 4)
    _, ones = detector_loss(out, targets, LossConfig(heat="focal", type_weights=[1, 1, 1, 1, 1]), 4)
    assert ones == pytest.approx(plain)
    _, truck3 = detector_loss(out, targets, LossConfig(heat="focal", type_weights=(1, 1, 3, 1, 1)), 4)
    owner = targets["vtype"][0]
    w = torch.where(owner == 2, 3.0, 1.0)[None]
    assert truck3["heat"] == pytest.approx(
        focal_heat_loss(out["heat"][:, 0], targets["heat"], targets["ignore"], w).item())
    assert truck3["heat"] > plain["heat"]
    by_cell = ((out["offset"] - targets["offset"]) ** 2).sum(dim=1)
    weight = targets["weight"] * w
    assert truck3["offset"] == pytest.approx(((weight * by_cell).sum() / weight.sum()).item(), rel=1e-5)
    # a weight on a type the sample does not hold changes nothing
    _, bus9 = detector_loss(out, targets, LossConfig(heat="focal", type_weights=(1, 1, 1, 9, 1)), 4)
    assert bus9 == pytest.approx(plain)
    with pytest.raises(ValueError, match="type_weights must be 5 finite numbers > 0"):
        LossConfig(heat="focal", type_weights=(1, 1, 0, 1, 1))
    with pytest.raises(ValueError, match="type_weights must be 5"):
        LossConfig(heat="focal", type_weights=(1, 2))
    with pytest.raises(ValueError, match="type_weights need the focal heat loss"):
        LossConfig(type_weights=(1, 1, 2, 1, 1))


def test_vote_term_is_the_huber_error_over_vote_cells_and_off_by_default():
    torch.manual_seed(0)
    images, targets = batch_of([synthetic_sample()], 4)
    out = Detector(TINY)(images)
    total, parts = detector_loss(out, targets, LossConfig())
    voting = targets["vote_weight"] > 0
    err = torch.nn.functional.smooth_l1_loss(out["offset"][:, :2], targets["offset"][:, :2], reduction="none")
    assert parts["vote"] == pytest.approx(err.sum(dim=1)[voting].mean().item(), rel=1e-5)
    with_vote, _ = detector_loss(out, targets, LossConfig(beta_vote=2.0))
    assert with_vote.item() == pytest.approx(total.item() + 2.0 * parts["vote"], rel=1e-5)
    perfect = dict(out, offset=targets["offset"].clone())
    assert detector_loss(perfect, targets, LossConfig(beta_vote=1.0))[1]["vote"] == 0.0
    with pytest.raises(ValueError, match="beta_vote must be >= 0"):
        LossConfig(beta_vote=-1.0)


def test_a_vote_head_takes_the_vote_term_and_leaves_the_offset_to_its_own():
    torch.manual_seed(0)
    images, targets = batch_of([synthetic_sample()], 4)
    model = Detector(replace(TINY, vote_head=True))
    out = model(images)
    assert out["vote"].shape == out["offset"][:, :2].shape
    voting = targets["vote_weight"] > 0
    err = torch.nn.functional.smooth_l1_loss(out["vote"], targets["offset"][:, :2], reduction="none")
    total, parts = detector_loss(out, targets, LossConfig(beta_vote=1.0))
    assert parts["vote"] == pytest.approx(err.sum(dim=1)[voting].mean().item(), rel=1e-5)
    # perfect votes: no vote term however wrong the offset head is, and the offset term is the offset head's
    perfect = dict(out, vote=targets["offset"][:, :2].clone())
    perfect_parts = detector_loss(perfect, targets, LossConfig(beta_vote=1.0))[1]
    assert perfect_parts["vote"] == 0.0 and perfect_parts["offset"] == pytest.approx(parts["offset"], rel=1e-6)
    total.backward()
    assert model.heads["vote"].out.weight.grad.abs().sum() > 0


def batch_of(samples: list[Sample], stride: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    images = torch.from_numpy(np.stack([s.image for s in samples])[:, None].astype(np.float32) / 255)
    return images, default_collate([build_targets(s, stride) for s in samples])


def synthetic_sample() -> Sample:
    """Two bright 'vehicles' on a grey 64 x 64 image, bottom centres near their lower edges."""
    image = np.full((64, 64), 90, np.uint8)
    image[20:35, 8:31] = 230
    image[38:55, 38:59] = 200
    return make_sample([[19.0, 32.0], [48.0, 52.0]], [[8, 20, 31, 35], [38, 38, 59, 55]],
                       heading_uv=[[1.0, 0.0], [0.0, 1.0]], size_lwh=[[4.5, 1.8, 1.5], [10.0, 2.5, 3.2]],
                       vtype=[0, 2], image=image)


def test_loss_topk_ablation_changes_value_and_perfect_regression_is_zero():
    torch.manual_seed(0)
    model = Detector(TINY)
    images, targets = batch_of([synthetic_sample()], 4)
    out = model(images)
    total, parts = detector_loss(out, targets)
    _, parts_all = detector_loss(out, targets, LossConfig(topk_fraction=None))
    assert parts["heat"] != pytest.approx(parts_all["heat"], rel=1e-3)
    assert parts["size"] == parts_all["size"]
    assert total.item() == pytest.approx(parts["total"])
    perfect = {"heat": targets["heat"][:, None], "size": targets["size"].clamp(min=1e-3),
               "heading": targets["heading"], "offset": targets["offset"],
               "vtype": 50.0 * nn.functional.one_hot(targets["vtype"].clamp(min=0), 5).permute(0, 3, 1, 2).float()}
    _, parts_perfect = detector_loss(perfect, targets)
    assert all(value == pytest.approx(0.0, abs=1e-6) for value in parts_perfect.values())
    # the extra 2D-box term: off by default, adds beta_box x (box log-size + box-centre offset error)
    assert parts["box"] > 0
    total_box, _ = detector_loss(out, targets, LossConfig(beta_box=0.5))
    assert total_box.item() == pytest.approx(total.item() + 0.5 * parts["box"], rel=1e-5)
    only_box = dict(perfect, size=perfect["size"].clone(), offset=perfect["offset"].clone())
    only_box["size"][:, 3:5] *= 1.5
    _, parts_only_box = detector_loss(only_box, targets)
    assert parts_only_box["box"] > 0 and parts_only_box["offset"] == pytest.approx(0.0, abs=1e-6)
    only_box["offset"][:, 0:2] += 0.3  # the sub-cell offset is not part of the box term
    assert detector_loss(only_box, targets)[1]["box"] == pytest.approx(parts_only_box["box"])
    with pytest.raises(ValueError, match="beta_box"):
        LossConfig(beta_box=-1.0)
    with pytest.raises(ValueError, match="topk_fraction"):
        LossConfig(topk_fraction=0.0)


def test_loss_without_vehicles_is_finite():
    empty = make_sample(np.zeros((0, 2)), np.zeros((0, 4)), heading_uv=np.zeros((0, 2)), size_lwh=np.zeros((0, 3)),
                        vtype=[], weight=[], hw=(64, 64))
    images, targets = batch_of([empty], 4)
    total, parts = detector_loss(Detector(TINY)(images), targets)
    assert np.isfinite(total.item()) and parts["size"] == 0.0


# --- model -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_model_output_shapes(stride):
    model = Detector(DetectorConfig(width_mult=0.25, decoder_channels=8, head_channels=8, stride=stride)).eval()
    with torch.no_grad():
        out = model(torch.rand(2, 1, 64, 96))
    expected = {"heat": 1, "size": 5, "heading": 2, "vtype": len(VEHICLE_TYPES), "offset": 4}
    assert {k: tuple(v.shape) for k, v in out.items()} == {k: (2, c, 64 // stride, 96 // stride)
                                                          for k, c in expected.items()}
    assert out["heat"].min() >= 0 and out["heat"].max() <= 1 and out["size"].min() > 0
    assert out["heading"].abs().max() <= 1


def test_model_rejects_bad_input_and_config():
    with pytest.raises(ValueError, match="multiples of 32"):
        Detector(TINY)(torch.rand(1, 1, 48, 64))
    with pytest.raises(ValueError, match="stride"):
        DetectorConfig(stride=8)
    with pytest.raises(ValueError, match="width_mult"):
        DetectorConfig(width_mult=0.0)


def test_count_macs_exact():
    conv = nn.Conv2d(1, 8, 3, padding=1)
    assert count_macs(conv, 32, 48) == 32 * 48 * 8 * 9
    strided = nn.Sequential(nn.Conv2d(1, 6, 3, stride=2, padding=1), nn.Conv2d(6, 6, 3, padding=1, groups=3),
                            nn.Flatten(), nn.Linear(6 * 16 * 16, 10))
    assert count_macs(strided, 32, 32) == 16 * 16 * 6 * 9 + 16 * 16 * 6 * 2 * 9 + 6 * 16 * 16 * 10


def test_default_model_fits_the_mac_budget():
    macs = count_macs(Detector(), 512, 512)
    assert 0.3e9 < macs < 0.8e9


def test_save_and_load(tmp_path):
    model = Detector(TINY).eval()
    save_detector(model, tmp_path / "d.pt")
    loaded = load_detector(tmp_path / "d.pt")
    assert loaded.config == TINY
    x = torch.rand(1, 1, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(loaded(x)["heat"], model(x)["heat"])


@pytest.fixture(scope="module")
def trained(one_torch_thread):
    """A tiny model overfitted on the synthetic sample (eval mode, batch-norm statistics recomputed on it);
    returns (model, per-step loss parts)."""
    torch.manual_seed(0)
    model = Detector(TINY)
    images, targets = batch_of([synthetic_sample()], 4)
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    losses = []
    for _ in range(40):
        total, parts = detector_loss(model(images), targets)
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(parts)
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None  # a cumulative average: one pass sets the statistics of this batch
    with torch.no_grad():
        model(images.expand(8, -1, -1, -1))  # 8 copies: the unbiased variance is close to the batch one
    return model.eval(), losses


def test_tiny_model_overfits_one_sample(trained):
    model, losses = trained
    assert losses[-1]["total"] < losses[0]["total"] / 4
    assert losses[-1]["heat"] < losses[0]["heat"] / 4
    sample = synthetic_sample()
    with torch.no_grad():
        out = model(torch.from_numpy(sample.image[None, None].astype(np.float32) / 255))
    prob = torch.softmax(out["vtype"], 1)
    d = decode(*(out[k][0].numpy() for k in ("heat", "size", "heading")), prob[0].numpy(), out["offset"][0].numpy(),
               stride=4)
    assert len(d) == 2


@pytest.mark.skipif(importlib.util.find_spec("onnxconverter_common") is None,
                    reason="onnxconverter-common is not installed (needed for the fp16 export)")
def test_export_parity(trained, tmp_path):
    from training.export import export_onnx, parity

    model, _ = trained
    export_onnx(model, tmp_path / "d.onnx", tmp_path / "d16.onnx", (64, 64))
    images = np.stack([synthetic_sample().image, np.fliplr(synthetic_sample().image)])
    report = parity(model, tmp_path / "d.onnx", tmp_path / "d16.onnx", images)
    assert report["detections_torch"] >= 2
    assert report["heat_max_abs_diff_fp32"] < 1e-4
    assert report["detections_match_fp32"] and report["detections_match_fp16"], report
    wide = parity(model, tmp_path / "d.onnx", None, np.tile(images, (1, 1, 2)))  # dynamic width: 64 x 128
    assert wide["detections_match_fp32"] and "detections_fp16" not in wide
    # the service shrinks large frames to the model's input size and never enlarges small ones
    from shared.inference import OnnxDetector

    onnx = OnnxDetector(tmp_path / "d.onnx")
    long_side = model.config.input_long_side
    assert onnx.input_shape(long_side, 2 * long_side) == (0.5, long_side // 2, long_side)
    assert onnx.input_shape(50, 70) == (1.0, 64, 96)
    # a copy decoded at 1/2 or 1/4 (ingest) is brought to the scale of its full-size image
    assert onnx.input_shape(long_side // 2, long_side, 0.5) == (1.0, long_side // 2, long_side)
    assert onnx.input_shape(long_side // 4, long_side // 2, 0.25) == (2.0, long_side // 2, long_side)
    assert onnx.input_shape(long_side, 2 * long_side, 0.5) == (0.5, long_side // 2, long_side)
    with pytest.raises(ValueError, match="source_scale"):
        onnx.input_shape(64, 64, 0.0)


def test_model_stride_needs_the_export_metadata():
    assert model_stride({"detector_config": json.dumps({"stride": 2})}) == 2
    with pytest.raises(ValueError, match="detector_config"):
        model_stride({})


def test_bench_detector_smoke():
    run = subprocess.run([sys.executable, "-m", "bench.detector", "--size", "64", "--height", "96", "--runs", "2",
                          "--warmup", "1"],
                         cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=120,
                         check=True)
    report = json.loads(run.stdout)
    assert report["model"] == "untrained-for-timing-only"
    assert report["input"] == [1, 1, 96, 64]
    assert report["macs"] == count_macs(Detector(), 96, 64)
    assert report["cpu_fp32"]["median_ms"] > 0
    throughput = report["cpu_fp32_throughput"]  # one inference at a time against 2 workers side by side
    one, side = throughput["one_at_a_time_2_threads_fps"], throughput["2_workers_1_thread_fps"]
    assert one > 0 and side > 0 and throughput["ratio"] == pytest.approx(side / one, rel=0.01)


def test_bench_never_reports_a_cpu_fallback_as_a_gpu_time(tmp_path):
    """ONNX Runtime falls back to the CPU when a GPU provider cannot load (TensorRT without its libraries, no
    CUDA here): the benchmark must say so instead of timing the CPU under the GPU's name."""
    from bench.detector import time_gpu
    from training.export import export_onnx

    path = tmp_path / "d.onnx"
    export_onnx(Detector(), path, None, (64, 64))
    image = np.zeros((1, 1, 64, 64), np.float32)
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this machine's ONNX Runtime has CUDA: nothing falls back")
    out = time_gpu(path, "CUDAExecutionProvider", image, runs=1, warmup=0)
    assert set(out) == {"skipped"} and "CUDAExecutionProvider" in out["skipped"]


def test_topk_share_counts_input_pixels_at_any_stride():
    """At output stride s the TopK heat term keeps topk_fraction * s * s of the cells (the paper's share of
    pixels), not topk_fraction of the cells."""
    torch.manual_seed(0)
    b, h, w = 2, 16, 16
    targets = {"heat": torch.zeros(b, h, w), "ignore": torch.zeros(b, h, w, dtype=torch.bool)}
    pred = torch.rand(b, h, w)
    err = (pred**2).flatten()
    for stride in (1, 2, 4):
        k = max(1, round(0.01 * stride * stride * err.numel()))
        expected = torch.topk(err, k).values.mean()
        got = heat_loss(pred, targets["heat"], targets["ignore"], min(1.0, 0.01 * stride * stride))
        assert got.item() == pytest.approx(expected.item(), rel=1e-6)
    # and detector_loss passes the stride through
    out = Detector(TINY)(torch.rand(1, 1, 64, 64))
    s = make_sample([[30.0, 40.0]], [[20.0, 20.0, 40.0, 44.0]], hw=(64, 64))
    tg = {k: torch.from_numpy(v[None]) for k, v in build_targets(s, 4).items()}
    _, p1 = detector_loss(out, tg, LossConfig(), stride=1)
    _, p4 = detector_loss(out, tg, LossConfig(), stride=4)
    mask = ~tg["ignore"][0]
    e = ((out["heat"][0, 0] - tg["heat"][0]) ** 2)[mask].detach()
    assert p4["heat"] == pytest.approx(torch.topk(e, round(0.16 * e.numel())).values.mean().item(), rel=1e-5)
    assert p1["heat"] == pytest.approx(torch.topk(e, max(1, round(0.01 * e.numel()))).values.mean().item(), rel=1e-5)


# --- the axis head ----------------------------------------------------------------------------------------------


def test_axis_targets_are_the_doubled_angle_and_decode_takes_the_sign_from_the_heading():
    s = make_sample([[21.3, 41.9], [70.05, 20.6]], [[10, 22, 34, 44], [58.2, 5.1, 83.9, 24.7]],
                    heading_uv=[[0.6, 0.8], [-0.28, 0.96]], size_lwh=[[4.5, 1.8, 1.5], [12.0, 2.5, 3.5]],
                    vtype=[1, 3])
    t = build_targets(s, 4)
    for uv, (hu, hv) in zip(s.bottom_uv, s.heading_uv, strict=True):
        col, row = int(uv[0] // 4), int(uv[1] // 4)
        np.testing.assert_allclose(t["axis"][:, row, col], [hu * hu - hv * hv, 2 * hu * hv], atol=1e-6)
    # a vehicle and its reverse have the same axis
    rev = build_targets(make_sample(s.bottom_uv, s.box, heading_uv=-s.heading_uv, size_lwh=s.size_lwh,
                                    vtype=s.vtype), 4)
    np.testing.assert_allclose(rev["axis"], t["axis"], atol=1e-7)

    heat, size, heading, prob, offset = hand_maps()
    axis = np.zeros((2, *heat.shape[1:]), np.float32)
    a = np.radians(30.0)
    axis[:, 2, 3] = [np.cos(2 * a), np.sin(2 * a)]  # axis at 30 deg; the heading head says (0.3, 0.4): 53 deg
    axis[:, 5, 7] = [np.cos(2 * a), np.sin(2 * a)]  # same axis; the heading head says (-1, 0): 180 deg
    d = decode(heat, size, heading, prob, offset, stride=4, axis=axis)
    np.testing.assert_allclose(d.heading_uv, [[np.cos(a), np.sin(a)], [-np.cos(a), -np.sin(a)]], atol=1e-6)
    with pytest.raises(ValueError, match="axis"):
        decode(heat, size, heading, prob, offset, stride=4, axis=axis[:1])


def test_a_nan_heading_drops_the_peak_even_where_the_axis_gives_the_direction():
    """The heading head gives the axis its sign: a NaN there leaves the direction's sign unknown, so the peak is
    dropped as one with no heading, as it is without an axis head."""
    heat, size, heading, prob, offset = hand_maps()
    heading[:, 2, 3] = [np.nan, 0.4]
    axis = np.zeros((2, *heat.shape[1:]), np.float32)
    axis[0] = 1.0  # the axis along u everywhere
    for with_axis in (None, axis):
        d = decode(heat, size, heading, prob, offset, stride=4, axis=with_axis)
        np.testing.assert_allclose(d.score, [0.7], rtol=1e-6)  # the peak at (3, 2) is left out
        np.testing.assert_allclose(d.heading_uv, [[-1.0, 0.0]], atol=1e-6)


def test_axis_head_trains_exports_and_loads(tmp_path, one_torch_thread):
    from shared.inference import OnnxDetector
    from training.export import export_onnx

    torch.manual_seed(0)
    model = Detector(replace(TINY, axis_head=True))
    images, targets = batch_of([synthetic_sample()], 4)
    out = model(images)
    assert out["axis"].shape == out["heading"].shape and out["axis"].abs().max() <= 1
    total, parts = detector_loss(out, targets)
    assert parts["axis"] > 0 and torch.isfinite(total)
    total.backward()
    assert model.heads["axis"].out.weight.grad.abs().sum() > 0
    save_detector(model, tmp_path / "m.pt")
    assert load_detector(tmp_path / "m.pt").config.axis_head
    export_onnx(model.eval(), tmp_path / "a.onnx", None, (64, 64))
    det = OnnxDetector(tmp_path / "a.onnx", threads=1, score_thr=0.01)
    assert det.output_names[-1] == "axis"
    assert len(det.detect(synthetic_sample().image)) > 0
    # a model without the head has no axis term in its loss
    plain = Detector(TINY)
    assert detector_loss(plain(images), targets)[1]["axis"] == 0.0


# --- the vote head ----------------------------------------------------------------------------------------------


def bus_end_maps(h=12, w=16):
    """A bus whose heat peaks at its near end, cell (col 3, row 8), with its centre 5 cells up at (3, 3), where
    the maps hold the bus (box 64 x 96 px, type 3) and the peak's own cell a smaller car (type 1); a car elsewhere,
    cell (12, 9), with no vote."""
    heat, size, heading, prob, offset = (np.zeros((1, h, w), np.float32), np.ones((5, h, w), np.float32),
                                         np.zeros((2, h, w), np.float32), np.full((5, h, w), 0.1, np.float32),
                                         np.zeros((4, h, w), np.float32))
    heading[0] = 1.0
    heat[0, 8, 3], heat[0, 9, 12] = 0.8, 0.6
    prob[:, 8, 3] = [0.1, 0.6, 0.1, 0.1, 0.1]
    prob[:, 3, 3] = [0.1, 0.1, 0.1, 0.6, 0.1]
    size[:, 3, 3] = [12.0, 2.5, 3.2, 2.0, 3.0]
    offset[:, 3, 3] = [0.25, -0.25, 0.0, 0.0]
    vote = np.zeros((2, h, w), np.float32)
    vote[:, 8, 3] = [0.2, -5.1]  # rounds to the cell (3, 3)
    vote[:, 9, 12] = [0.5, 0.5]  # a short vote: the car stays where it is
    return heat, size, heading, prob, offset, vote


def test_decode_moves_a_peak_its_vote_points_far_from_to_the_centre_and_reads_the_vehicle_there():
    heat, size, heading, prob, offset, vote = bus_end_maps()
    plain = decode(heat, size, heading, prob, offset, stride=4)
    d = decode(heat, size, heading, prob, offset, stride=4, vote=vote)
    assert len(d) == len(plain) == 2
    np.testing.assert_allclose(d.score, [0.8, 0.6], rtol=1e-6)
    # cell (3, 3) centre (13.5, 13.5) + offset (0.25, -0.25) * 4
    np.testing.assert_allclose(d.uv[0], [14.5, 12.5])
    np.testing.assert_allclose(plain.uv[0], [13.5, 33.5])
    assert d.vtype[0] == 3 and plain.vtype[0] == 1
    np.testing.assert_allclose(d.size_lwh[0], [12.0, 2.5, 3.2])
    np.testing.assert_allclose(d.box[0], [14.5 - 32, 12.5 - 48, 14.5 + 32, 12.5 + 48])
    # the car's short vote leaves it as it was
    np.testing.assert_allclose(d.uv[1], plain.uv[1])
    assert d.vtype[1] == plain.vtype[1]
    # a threshold above the vote's length leaves the bus's end too
    np.testing.assert_allclose(decode(heat, size, heading, prob, offset, stride=4, vote=vote, vote_min_cells=6).uv,
                               plain.uv)
    with pytest.raises(ValueError, match="vote"):
        decode(heat, size, heading, prob, offset, stride=4, vote=vote[:1])


def test_a_moved_peak_that_lands_on_a_detected_vehicle_is_one_detection():
    heat, size, heading, prob, offset, vote = bus_end_maps()
    heat[0, 3, 3] = 0.7  # the bus's centre is a peak of its own too, scoring below its end
    d = decode(heat, size, heading, prob, offset, stride=4, vote=vote)
    assert len(d) == 2 and d.score[0] == pytest.approx(0.8) and d.vtype[0] == 3
    heat[0, 3, 3] = 0.9  # ... or above it
    d = decode(heat, size, heading, prob, offset, stride=4, vote=vote)
    assert len(d) == 2 and d.score[0] == pytest.approx(0.9) and d.vtype[0] == 3
    # two unmoved peaks as close as that are two vehicles, as without votes
    heat, size, heading, prob, offset, vote = bus_end_maps()
    heat[0, 3, 3], heat[0, 3, 5], vote[:] = 0.7, 0.65, 0.0
    size[:, 3, 5] = size[:, 3, 3]
    assert len(decode(heat, size, heading, prob, offset, stride=4, vote=vote)) == 4


def test_vote_head_exports_and_the_detector_uses_it(tmp_path, one_torch_thread):
    from shared.inference import OnnxDetector
    from training.export import export_onnx

    torch.manual_seed(0)
    model = Detector(replace(TINY, axis_head=True, vote_head=True))
    save_detector(model, tmp_path / "m.pt")
    assert load_detector(tmp_path / "m.pt").config.vote_head
    export_onnx(model.eval(), tmp_path / "v.onnx", None, (64, 64))
    det = OnnxDetector(tmp_path / "v.onnx", threads=1, score_thr=0.01)
    assert det.output_names[-2:] == ("axis", "vote")
    assert len(det.detect(synthetic_sample().image)) > 0
    # votes 3 cells to the right everywhere and no sub-cell offsets: every peak is read 3 cells (12 pixels) right of
    # itself when the detector is told to use them (not by default)
    with torch.no_grad():
        for name, bias in (("vote", [3.0, 0.0]), ("offset", [0.0] * 4)):
            model.heads[name].out.weight.zero_()
            model.heads[name].out.bias.copy_(torch.tensor(bias))
    export_onnx(model.eval(), tmp_path / "v3.onnx", None, (64, 64))
    image = synthetic_sample().image
    voted = OnnxDetector(tmp_path / "v3.onnx", threads=1, score_thr=0.01, top_k=1, votes=True).detect(image)
    plain = OnnxDetector(tmp_path / "v3.onnx", threads=1, score_thr=0.01, top_k=1).detect(image)
    assert len(voted) == len(plain) == 1
    assert plain.uv[0, 0] < 64 - 12  # room to move right
    np.testing.assert_allclose(voted.uv[0] - plain.uv[0], [12.0, 0.0], atol=1e-4)
