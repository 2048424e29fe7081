"""localize without transport: the footprint overlap rule and the Objects message it shapes, the site frame
of its cameras, exclusion polygons and bad input."""

from __future__ import annotations

import os
import tracemalloc

import cv2
import numpy as np
import pytest
import yaml

from calibration.masks import FORMAT, VERSION, LookupMasks, excluded
from services.fuse_track.__main__ import camera_positions
from services.localize.__main__ import load_all_masks, misaddressed, objects_message
from services.localize.lift import (
    MERGE_MAX_LENGTH_M,
    GroundLookup,
    footprint_groups,
    footprint_rule,
    lift,
    merge_along,
)
from shared.geo import FOOTPRINT_ROWS, GeoFrame
from shared.messages import MAX_ROWS, Detections
from shared.settings import LocalizeSettings, load_settings

CAR = (4.5, 1.8, 1.5)


def _drop(xy, yaw, size, score, scale=1.5):
    n = len(xy)
    kept, _, _ = footprint_rule(np.asarray(xy, float), np.full(n, yaw) if np.ndim(yaw) == 0 else np.asarray(yaw, float),
                                np.asarray(size, float).reshape(-1, 3) if np.ndim(size) > 1 else np.tile(size, (n, 1)),
                                np.asarray(score, float), scale, False)
    drop = np.ones(n, bool)
    drop[kept] = False
    return drop.tolist()


def test_a_second_peak_on_the_same_vehicle_is_dropped_and_the_higher_score_kept():
    # a truck read as two cars, one on each half: 3 m apart along its length (east)
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.4, 0.7]) == [True, False]
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.7, 0.4]) == [False, True]
    # the footprint follows the yaw: the same pair along a north-facing vehicle
    assert _drop([[0, 0], [0, 3]], np.pi / 2, CAR, [0.7, 0.4]) == [False, True]


def test_vehicles_that_only_stand_close_are_all_kept():
    assert _drop([[0, 0], [0, 3.5]], 0.0, CAR, [0.9, 0.5]) == [False, False]  # side by side, two lanes
    assert _drop([[0, 0], [7.0, 0]], 0.0, CAR, [0.9, 0.5]) == [False, False]  # queued, bumper to bumper
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.9, 0.5], scale=0.0) == [False, False]  # the rule switched off
    assert _drop([[0, 0], [3, 0]], 0.0, CAR, [0.9, 0.5], scale=1.2) == [False, False]  # 3 m > 1.2 * 4.5 / 2


def test_either_footprint_counts_and_suppression_is_greedy():
    # a bus (12 m) scored lower than a car-sized peak 4 m along it: the car's footprint does not hold the bus's
    # point, the bus's holds the car's; one vehicle, the higher score kept
    assert _drop([[0, 0], [4, 0]], 0.0, [[4.5, 1.8, 1.5], [12.0, 2.5, 3.2]], [0.8, 0.5]) == [False, True]
    # a chain of peaks 3 m apart: the middle one is dropped by the best, the far one survives the dropped one
    assert _drop([[0, 0], [3, 0], [6, 0]], 0.0, CAR, [0.9, 0.5, 0.4]) == [False, True, False]
    assert _drop([], 0.0, CAR, []) == []


def test_objects_without_a_finite_position_yaw_or_size_are_left_alone():
    xy = [[0, 0], [3, 0], [np.nan, 0]]
    assert _drop(xy, [0.0, np.nan, 0.0], CAR, [0.9, 0.5, 0.4]) == [False, False, False]
    assert _drop([[0, 0], [3, 0]], 0.0, [[np.nan, 1.8, 1.5], CAR], [0.9, 0.5]) == [False, False]


def test_settings_default_and_refuse_a_negative_scale():
    assert LocalizeSettings().footprint_overlap == 1.4
    with pytest.raises(ValueError, match="footprint_overlap"):
        LocalizeSettings(footprint_overlap=-1)


def _lookup_masks(w: int = 64, h: int = 48, m_per_px: float = 0.25) -> LookupMasks:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([u * m_per_px, -v * m_per_px], axis=2)  # east along u, north up the image
    meta = {"geo_origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0}}
    return LookupMasks(42 + xy[..., 1] / 111e3, -83 + xy[..., 0] / 82e3, xy.astype(np.float32), np.ones((h, w), bool),
                       meta)


def _masks(w: int = 64, h: int = 48, m_per_px: float = 0.25) -> GroundLookup:
    return GroundLookup(_lookup_masks(w, h, m_per_px))


def _cars_heading_east(u: list[float], score: list[float]) -> Detections:
    """Car-sized detections heading east at pixel columns u (row 20; 4 px per metre), types 0, 1, 2, ..."""
    f4, n = np.float32, len(u)
    return Detections(site="s", camera="C1", seq=1, t_capture_ns=5, width=64, height=48, infer_ms=1.0,
                      score=np.array(score, f4), uv=np.array([[x, 20] for x in u], f4),
                      box=np.zeros((n, 4), f4), heading_uv=np.tile(np.array([1, 0], f4), (n, 1)),
                      size_lwh=np.tile(np.array(CAR, f4), (n, 1)), vtype=np.arange(n, dtype=np.int8))


def _two_peaks_and_a_car() -> Detections:
    """Three car-sized detections heading east: two 12 px = 3 m apart on one vehicle (x 2.5 and 5.5 m), one 40 px
    = 10 m further."""
    return _cars_heading_east([10, 22, 50], [0.5, 0.8, 0.6])


def test_objects_message_drops_the_overlapping_detection_and_keeps_the_columns_aligned():
    det, masks = _two_peaks_and_a_car(), _masks()
    kept = objects_message(det, masks, 6.0, 1.5, False)
    assert kept.score.tolist() == pytest.approx([0.8, 0.6])
    assert kept.vtype.tolist() == [1, 2]
    np.testing.assert_allclose(kept.xy, [[5.5, -5.0], [12.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.uv, [[22, 20], [50, 20]])
    assert len(objects_message(det, masks, 6.0, 0.0, False)) == 3
    assert len(objects_message(det, masks, 6.0, 0.0, True)) == 3  # no rule, nothing to merge


def test_objects_message_merges_the_peaks_of_one_vehicle_along_its_axis():
    det, masks = _two_peaks_and_a_car(), _masks()  # a long vehicle read as two car-sized peaks, and a car
    kept = objects_message(det, masks, 6.0, 1.5, True)
    assert kept.score.tolist() == pytest.approx([0.8, 0.6])
    # the span of both peaks: 0.25 to 7.75 m east, its middle 4.0 m, 7.5 m long; the car untouched
    np.testing.assert_allclose(kept.xy, [[4.0, -5.0], [12.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.size_lwh, [[7.5, 1.8, 1.5], CAR], atol=1e-6)
    np.testing.assert_allclose(kept.uv, [[22, 20], [50, 20]])  # the pixel stays the detection's
    # latitude/longitude follow the moved point (1.5 m west of the kept peak)
    dropped = objects_message(det, masks, 6.0, 1.5, False)
    assert kept.latlon[1].tolist() == dropped.latlon[1].tolist()
    assert kept.latlon[0, 0] == pytest.approx(dropped.latlon[0, 0], abs=1e-9)
    assert kept.latlon[0, 1] < dropped.latlon[0, 1]
    assert (dropped.latlon[0, 1] - kept.latlon[0, 1]) * 111320 * np.cos(np.radians(42)) == pytest.approx(1.5, rel=1e-2)


def _merge(xy, yaw, size, score, scale=1.5):
    n = len(xy)
    xy, yaw = np.asarray(xy, float), np.full(n, yaw) if np.ndim(yaw) == 0 else np.asarray(yaw, float)
    size = np.asarray(size, float).reshape(-1, 3) if np.ndim(size) > 1 else np.tile(size, (n, 1))
    groups = footprint_groups(xy, yaw, size, np.asarray(score, float), scale)
    mxy, msize = merge_along(xy, yaw, size, np.asarray(score, float), groups)
    return sorted(groups), mxy, msize


def test_merge_spans_the_aligned_peaks_and_leaves_the_rest():
    # three peaks along a bus (east), 3 m apart: the best (middle) takes in both, 10.5 m long centred on it
    kept, xy, size = _merge([[3, 0], [0, 0], [-3, 0]], 0.0, CAR, [0.4, 0.9, 0.5], scale=2.0)
    assert kept == [1]
    np.testing.assert_allclose(xy[1], [0.0, 0.0], atol=1e-12)
    assert size[1, 0] == pytest.approx(10.5)
    assert size[1, 1:].tolist() == list(CAR[1:])
    # a peak off the axis (1.5 m across) or turned (45 deg) is dropped but not taken in
    for xy2, yaw2 in (([[0, 0], [2, 1.5]], [0.0, 0.0]), ([[0, 0], [3, 0]], [0.0, np.pi / 4])):
        kept, xy, size = _merge(xy2, yaw2, CAR, [0.9, 0.5], scale=2.0)
        assert kept == [0]
        np.testing.assert_allclose(xy[0], [0, 0])
        assert size[0, 0] == pytest.approx(CAR[0])
    # a reversed heading is the same axis: merged
    kept, xy, size = _merge([[0, 0], [3, 0]], [0.0, np.pi], CAR, [0.9, 0.5])
    np.testing.assert_allclose(xy[0], [1.5, 0])
    assert size[0, 0] == pytest.approx(7.5)


def test_merge_never_grows_past_a_long_bus_and_changes_nothing_alone():
    big = (14.0, 2.5, 3.2)
    kept, xy, size = _merge([[0, 0], [6, 0]], 0.0, big, [0.9, 0.5])  # the union would be 20 m
    assert kept == [0] and size[0, 0] == pytest.approx(14.0) and xy[0].tolist() == [0, 0]
    assert 20.0 > MERGE_MAX_LENGTH_M
    kept, xy, size = _merge([[0, 0], [0, 3.5]], 0.0, CAR, [0.9, 0.5])  # two lanes: both kept, both as they were
    assert kept == [0, 1]
    np.testing.assert_allclose(xy, [[0, 0], [0, 3.5]])
    np.testing.assert_allclose(size, [CAR, CAR])


def test_merge_takes_in_a_peak_the_grown_span_reaches_and_is_stable():
    # a bus (east) read as peaks at 0, 3 and 6 m, the best at one end: the first round spans 0 and 3 (7.5 m long,
    # centred at 1.5 m), whose footprint then holds the peak at 6 m; it joins in the second round
    xy, yaw, size = np.array([[0.0, 0], [3, 0], [6, 0]]), np.zeros(3), np.tile(CAR, (3, 1))
    score = np.array([0.9, 0.6, 0.5])
    kept, mxy, msize = footprint_rule(xy, yaw, size, score, 1.5, True)
    assert kept.tolist() == [0]
    np.testing.assert_allclose(mxy[0], [3.0, 0.0], atol=1e-12)
    assert msize[0, 0] == pytest.approx(6 + CAR[0])
    again, xy2, size2 = footprint_rule(mxy[kept], yaw[kept], msize[kept], score[kept], 1.5, True)
    assert again.tolist() == [0]
    np.testing.assert_allclose(xy2, mxy[kept])
    np.testing.assert_allclose(size2, msize[kept])
    # without merging the first round's drop stands: the peak at 6 m is outside the best one's own footprint
    kept, mxy, _ = footprint_rule(xy, yaw, size, score, 1.5, False)
    assert kept.tolist() == [0, 2]
    np.testing.assert_allclose(mxy, xy)


def test_settings_drop_without_merging_by_default():
    assert LocalizeSettings().footprint_merge is False
    assert LocalizeSettings(footprint_merge=True).footprint_merge is True


def test_objects_message_grows_a_vehicle_merged_on_both_sides_without_moving_it():
    # peaks 12 px = 3 m either side of the best one, all heading east: the span grows, its middle stays
    kept = objects_message(_cars_heading_east([10, 22, 34], [0.5, 0.8, 0.6]), _masks(), 6.0, 2.0, True)
    np.testing.assert_allclose(kept.xy, [[5.5, -5.0]], atol=1e-6)
    np.testing.assert_allclose(kept.size_lwh, [[10.5, 1.8, 1.5]], atol=1e-6)


# --- one site frame for every camera -----------------------------------------------------------------------------


def _save_masks(path, geo: GeoFrame, site: GeoFrame, w: int = 64, h: int = 48) -> None:
    """Masks of one ground patch (east along u, north up the image, 4 px per metre from the point 10 m east and
    5 m north of `site`'s origin) expressed around `geo`, with the camera's foot at the patch's top-left corner."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy_site = np.stack([10 + u / 4, 5 - v / 4], axis=2).reshape(-1, 2)
    xy = site.reframe(xy_site, geo).reshape(h, w, 2)
    ll = site.to_geodetic(xy_site)
    meta = {"format": FORMAT, "version": VERSION, "geo_origin": geo.to_dict(),
            "camera": {"pose": {"position_m": [*site.reframe(np.array([[10.0, 5.0]]), geo)[0].tolist(), 8.0]}}}
    LookupMasks(ll[:, 0].reshape(h, w), ll[:, 1].reshape(h, w), xy.astype(np.float32), np.ones((h, w), bool),
                meta).save(path)


def test_without_an_origin_every_camera_is_lifted_in_the_first_masks_frame_as_fuse_track_takes_it(tmp_path,
                                                                                                   monkeypatch):
    """Two cameras seeing the same ground, their masks made around origins 112 m apart and a site file without
    `origin`: localize lifts both in the first masks file's frame, the one fuse_track takes for the site, so the same
    ground point has the same metres from either camera (before, B's were in its own masks' frame, 112 m off)."""
    for k in [k for k in os.environ if k.startswith("ROADSIDE_")]:
        monkeypatch.delenv(k)
    a = GeoFrame(42.2294, -83.739, 265.0)
    ll = a.to_geodetic(np.array([[50.0, 100.0]]))[0]
    b = GeoFrame(float(ll[0]), float(ll[1]), 262.0)
    (tmp_path / "masks").mkdir()
    _save_masks(tmp_path / "masks" / "A.npz", a, a)
    _save_masks(tmp_path / "masks" / "B.npz", b, a)
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({"site": "s2", "cameras": [
        {"name": n, "kind": "fisheye", "width": 64, "height": 48, "masks": f"masks/{n}.npz"} for n in ("A", "B")]}))
    settings = load_settings(tmp_path / "site.yaml")
    assert settings.origin is None
    lookups = load_all_masks(settings)
    positions, site_geo = camera_positions(settings)
    assert site_geo == a and lookups["A"].site_geo == a and lookups["B"].site_geo == a
    uv = np.array([[0.0, 0.0], [20.0, 12.0], [63.0, 47.0]])
    latlon_a, xy_a, _ = lookups["A"].lookup(uv)
    latlon_b, xy_b, _ = lookups["B"].lookup(uv)
    np.testing.assert_allclose(xy_a, [[10.0, 5.0], [15.0, 2.0], [25.75, -6.75]], atol=1e-4)
    np.testing.assert_allclose(xy_b, xy_a, atol=1e-4)  # float32 masks: a tenth of a millimetre
    np.testing.assert_allclose(latlon_b, latlon_a, atol=1e-9)
    np.testing.assert_allclose([positions["A"], positions["B"]], [[10.0, 5.0], [10.0, 5.0]], atol=1e-6)
    # the site's origin, where the file gives one, is every camera's frame
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({**yaml.safe_load((tmp_path / "site.yaml").read_text()),
                                                        "origin": b.to_dict()}))
    lookups = load_all_masks(load_settings(tmp_path / "site.yaml"))
    np.testing.assert_allclose(lookups["A"].lookup(uv)[1], lookups["B"].lookup(uv)[1], atol=1e-4)
    np.testing.assert_allclose(lookups["A"].lookup(uv)[1], a.reframe(xy_a, b), atol=1e-4)


# --- bad input ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", ["empty", "npy", "folder"])
def test_an_empty_npy_or_folder_masks_file_stops_localize_and_fuse_track_with_one_line_and_status_2(tmp_path, bad,
                                                                                                  monkeypatch, capsys):
    """A failed copy (0 bytes), a single .npy array or a folder as a camera's masks: numpy's EOFError or TypeError
    went out as a traceback with status 1, which `roadside up` restarts for ever; a folder was said to be missing."""
    from services.fuse_track.__main__ import main as fuse_track_main
    from services.localize.__main__ import main as localize_main
    from shared.service import run

    for k in [k for k in os.environ if k.startswith("ROADSIDE_")]:
        monkeypatch.delenv(k)
    a = GeoFrame(42.2294, -83.739, 265.0)
    (tmp_path / "masks").mkdir()
    _save_masks(tmp_path / "masks" / "A.npz", a, a)
    path = tmp_path / "masks" / "B.npz"
    if bad == "empty":
        path.write_bytes(b"")
    elif bad == "npy":
        with path.open("wb") as f:
            np.save(f, np.zeros((48, 64), np.float32))
    else:
        path.mkdir()
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({"site": "s2", "bus": {"port_base": 17911}, "cameras": [
        {"name": n, "kind": "fisheye", "width": 64, "height": 48, "masks": f"masks/{n}.npz"} for n in ("A", "B")]}))
    why = {"empty": f"{path}: not a lookup masks file (an empty file;",
           "npy": f"{path}: not a lookup masks file (not an .npz archive;",
           "folder": f"lookup masks {path} is a folder, not a masks file"}[bad]
    settings = load_settings(tmp_path / "site.yaml")
    for load in (load_all_masks, camera_positions):
        with pytest.raises(ValueError) as exc:
            load(settings)
        assert why in str(exc.value)
    for service, service_main in (("localize", localize_main), ("fuse_track", fuse_track_main)):
        capsys.readouterr()
        assert run(service, service_main, ["--site", str(tmp_path / "site.yaml")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"{service}: error: ") and why in err[0], err


def test_every_cameras_queue_is_localized_in_capture_order_across_the_cameras():
    """After a stall each camera's queue holds several frames: taken camera by camera, NE's backlog would be
    published before NW's, and fuse_track would close the ticks NW still needs."""
    from services.localize.__main__ import in_capture_order

    det = _cars_heading_east([10], [0.9])
    queues = {c: [det.model_copy(update={"camera": c, "t_capture_ns": t}) for t in (100, 200, 300)]
              for c in ("NE", "NW")}
    merged = in_capture_order([(c, d) for c, q in queues.items() for d in q])
    assert [(c, d.t_capture_ns) for c, d in merged] == [("NE", 100), ("NW", 100), ("NE", 200), ("NW", 200),
                                                         ("NE", 300), ("NW", 300)]


def test_detections_of_another_site_or_of_another_camera_than_their_keys_are_misaddressed():
    det = _cars_heading_east([10], [0.9])
    assert misaddressed(det, "s", "C1") is None
    assert misaddressed(det, "other", "C1") == "detections of site 's' on the bus of site 'other'"
    assert misaddressed(det, "s", "C2") == "detections of camera 'C1' on the key of camera 'C2'"


# --- many objects ---------------------------------------------------------------------------------------------------


def _dense_footprint_groups(xy, yaw, size_lwh, score, scale):
    """footprint_groups as it was, on the whole N x N matrix (geo.in_footprints as it was): the reference."""
    from services.localize.lift import footprint_inputs  # the inputs as the rule reads them; the matrix as it was

    xy, yaw, size, score, order, ok = footprint_inputs(xy, yaw, size_lwh, score)
    n = len(xy)
    if n < 2 or scale <= 0:
        return {int(a): np.zeros(0, np.int64) for a in order}
    half = 0.5 * scale * size[:, :2]
    d = xy[None, :, :] - xy[:, None, :]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    inside = (np.abs(d[..., 0] * c + d[..., 1] * s) <= half[:, :1]) & (np.abs(d[..., 1] * c - d[..., 0] * s)
                                                                          <= half[:, 1:])
    inside = (inside | inside.T) & ok[:, None] & ok[None, :]
    np.fill_diagonal(inside, False)
    drop = np.zeros(n, bool)
    groups = {}
    for a in order:
        if not drop[a]:
            groups[int(a)] = np.flatnonzero(inside[a] & ~drop)
            drop |= inside[a]
    return groups


def test_the_footprint_rule_in_blocks_is_the_whole_matrix_rule():
    """Random frames of up to three blocks of FOOTPRINT_ROWS objects, crowded (most overlap something), with ties in
    score and non-finite rows: the same groups, in the same order, as the N x N rule."""
    rng = np.random.default_rng(7)
    for trial in range(40):
        n = int(rng.integers(0, 3 * FOOTPRINT_ROWS + 5))
        xy = rng.uniform(-25, 25, (n, 2))
        yaw = rng.uniform(-np.pi, np.pi, n)
        size = np.column_stack([rng.uniform(2, 14, n), rng.uniform(1.5, 2.6, n), rng.uniform(1, 3, n)])
        score = np.round(rng.uniform(0, 1, n), 1)
        if n > 2:
            xy[rng.integers(0, n), 0], yaw[rng.integers(0, n)], size[rng.integers(0, n), 1] = np.nan, np.nan, np.inf
        want = _dense_footprint_groups(xy, yaw, size, score, 1.4)
        got = footprint_groups(xy, yaw, size, score, 1.4)
        assert list(got) == list(want), trial
        assert all(got[a].tolist() == want[a].tolist() for a in want), trial


def test_a_frame_of_max_rows_detections_is_localized_in_bounded_memory():
    """MAX_ROWS detections, every one on the same few metres (each overlaps all the others): the footprint rule takes
    blocks of rows, not an N x N matrix (that took ~650 MB and 2 s; localize has 512 MB)."""
    f4, n = np.float32, MAX_ROWS
    rng = np.random.default_rng(3)
    det = Detections(site="s", camera="C1", seq=1, t_capture_ns=5, width=64, height=48, infer_ms=1.0,
                     score=rng.uniform(0.3, 1, n).astype(f4), uv=rng.uniform(20, 30, (n, 2)).astype(f4),
                     box=np.zeros((n, 4), f4), heading_uv=np.tile(np.array([1, 0], f4), (n, 1)),
                     size_lwh=np.tile(np.array(CAR, f4), (n, 1)), vtype=np.zeros(n, np.int8))
    tracemalloc.start()
    try:
        out = objects_message(det, _masks(), 6.0, 1.4, False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert 1 <= len(out) < 10 and peak < 64e6, (len(out), peak)


# --- merging --------------------------------------------------------------------------------------------------------


def test_merging_rounds_take_in_only_what_lines_up_and_keep_the_rest():
    """After the first round a grown footprint suppresses only the peaks the grown object takes in: a car crossing
    1.5 m in front of a 12 m bus read as two 6 m peaks stays (before, the bus's 10 m span held its point and it was
    dropped), and so does a 12 m vehicle lined up behind the span that would make it longer than MERGE_MAX_LENGTH_M."""
    bus = [[6.0, 2.5, 3.2], [6.0, 2.5, 3.2]]
    kept, xy, size = footprint_rule(np.array([[0.0, 0], [4, 0], [8.5, 0]]), np.array([0, 0, np.pi / 2]),
                                    np.array([*bus, CAR]), np.array([0.9, 0.8, 0.7]), 1.4, True)
    assert kept.tolist() == [0, 2]
    np.testing.assert_allclose(xy[kept], [[2.0, 0.0], [8.5, 0.0]])
    np.testing.assert_allclose(size[kept, 0], [10.0, CAR[0]])
    # lined up, inside the 10 m span's footprint (7.4 m from its middle, reach 7.5 m), but 17.5 + 1 m together
    kept, xy, size = footprint_rule(np.array([[0.0, 0], [4, 0], [9.4, 0]]), np.zeros(3),
                                    np.array([*bus, [12.0, 2.5, 3.2]]), np.array([0.9, 0.8, 0.7]), 1.5, True)
    assert kept.tolist() == [0, 2]
    np.testing.assert_allclose(size[kept, 0], [10.0, 12.0])
    np.testing.assert_allclose(xy[kept], [[2.0, 0.0], [9.4, 0.0]])


# --- exclusion polygons ---------------------------------------------------------------------------------------------


def test_an_exclusion_polygon_takes_exactly_the_pixels_whose_centres_it_holds():
    """Pixel centres inside or on the outline, as cv2.pointPolygonTest says, and no others (cv2.fillPoly also took
    outline pixels whose centres lie outside, up to a pixel beyond the polygon)."""
    valid = np.ones((60, 70), bool)
    square = excluded(valid, [[(10.5, 10.5), (19.5, 10.5), (19.5, 19.5), (10.5, 19.5)]])
    vv, uu = np.nonzero(~square)
    assert (uu.min(), uu.max(), vv.min(), vv.max(), len(uu)) == (11, 19, 11, 19, 81)
    on_outline = excluded(valid, [[(2, 3), (6, 3), (6, 5), (2, 5)]])  # integer corners: the outline's pixels count
    assert (~on_outline).sum() == 15 and not on_outline[3:6, 2:7].any()
    rng = np.random.default_rng(5)
    vv, uu = np.mgrid[0:60, 0:70]
    for _ in range(12):
        k = int(rng.integers(3, 9))
        poly = np.round(rng.uniform(-5, 75, (k, 2)) * 8) / 8  # eighths: float32 holds them, as pointPolygonTest does
        out = excluded(valid, [poly])
        test = np.array([cv2.pointPolygonTest(poly.astype(np.float32), (float(u), float(v)), False)
                         for u, v in zip(uu.ravel(), vv.ravel(), strict=True)]).reshape(60, 70)
        np.testing.assert_array_equal(~out, test >= 0)
    # several polygons take their union; pixels already invalid stay so; nothing in the image: nothing taken
    two = excluded(valid, [[(0, 0), (3, 0), (3, 3), (0, 3)], [(2, 2), (5, 2), (5, 5), (2, 5)]])
    assert (~two).sum() == 16 + 16 - 4
    assert excluded(np.zeros((4, 4), bool), [[(0, 0), (2, 0), (2, 2)]]).sum() == 0
    assert excluded(valid, [[(-9, -9), (-2, -9), (-2, -2)]]).all()


# --- latitude/longitude of the bottom centres only ------------------------------------------------------------------


def test_lift_converts_only_the_bottom_centres_to_latitude_longitude(monkeypatch):
    """The ends of the heading step need metres only: the ellipsoid conversion takes N points, not 3N, and the
    latitudes and longitudes are those of the lookup of the bottom centres alone."""
    masks = _masks()
    uv = np.array([[10.0, 20.0], [30.5, 12.25], [50.0, 40.0], [200.0, 5.0]])  # the last outside the image
    heading = np.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8], [1.0, 0.0]])
    want, _, _ = masks.lookup(uv)
    converted = []
    to_geodetic = GeoFrame.to_geodetic
    monkeypatch.setattr(GeoFrame, "to_geodetic", lambda self, p: converted.append(len(p)) or to_geodetic(self, p))
    out = lift(masks, uv, heading)
    assert converted == [3]
    np.testing.assert_array_equal(out.latlon, want)
    for lookup in (masks, _lookup_masks()):  # masks with latitude/longitude arrays (eval.real lifts through them)
        latlon, xy, _ = lookup.lookup(np.concatenate([uv, uv + 1]), latlon_rows=4)
        assert np.isnan(latlon[4:]).all() and np.isfinite(xy[4:7]).all()
        np.testing.assert_array_equal(latlon[:4], lookup.lookup(uv)[0])


def test_a_heading_of_any_length_but_zero_is_lifted_as_its_direction():
    """The contract accepts any non-zero heading: a tiny one stepped onto the bottom centre itself and a raw pixel
    vector stepped off the calibrated ground; both dropped the detection as if it lay outside."""
    h, w = 48, 64
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([u * 0.25, -v * 0.25], axis=2).astype(np.float32)  # 4 px per metre, east along u, v down = south
    masks = GroundLookup(LookupMasks(np.zeros((0, 0)), np.zeros((0, 0)), xy, np.ones((h, w), bool),
                                     {"geo_origin": {"lat_deg": 42.0, "lon_deg": -83.0, "alt_m": 0.0}}))
    for heading, yaw_deg in (([1.0, 0.0], 0.0), ([1e-30, 0.0], 0.0), ([0.0, 20.0], -90.0), ([12.0, 5.0], -22.62)):
        out = lift(masks, np.array([[32.0, 24.0]]), np.array([heading]))
        assert out.valid.tolist() == [True], heading
        assert np.degrees(out.yaw[0]) == pytest.approx(yaw_deg, abs=0.01), heading


def test_latitude_longitude_astride_the_antimeridian_is_not_half_the_earth_away():
    """Pixel centres at 179.99999 and -179.99999 deg averaged to about 0 deg of longitude."""
    geo = GeoFrame(-16.8, 179.99997)  # Taveuni, Fiji: the 180th meridian crosses it
    h, w = 48, 64
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([u * 0.25 - 8.0, -v * 0.25], axis=2)  # x from -8 to +7.75 m, the meridian at about 3.2 m
    ll = geo.to_geodetic(xy.reshape(-1, 2))
    masks = LookupMasks(ll[:, 0].reshape(h, w), ll[:, 1].reshape(h, w), xy.astype(np.float32),
                        np.ones((h, w), bool), {"geo_origin": geo.to_dict()})
    u180 = (geo.to_enu(np.array([-16.8]), np.array([180.0]))[0, 0] + 8.0) / 0.25
    uv = np.array([[np.floor(u180) + 0.5, 20.0], [10.25, 7.5]])  # between the centres astride it; one west of it
    latlon, pts, ok = masks.lookup(uv)
    exact = geo.to_geodetic(pts)[:, :2]
    assert ok.all() and abs(latlon[0, 1]) > 179.99
    np.testing.assert_allclose(np.cos(np.radians(latlon - exact)), 1.0, atol=1e-15)
    np.testing.assert_allclose((latlon[:, 1] - exact[:, 1] + 180.0) % 360.0 - 180.0, 0.0, atol=1e-9)  # blended
    np.testing.assert_allclose(latlon[:, 0], exact[:, 0], atol=1e-9)
