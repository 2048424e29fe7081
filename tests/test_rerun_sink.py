"""Rerun sink: tracks file -> .rrd (bad lines counted, not fatal), basemaps, bounded live state."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from services.rerun_sink import Basemap, TrackSink, live, parse_tracks_message, track_color, tracks_file_to_rrd
from services.rerun_sink.sink import ellipses_xy, footprint_strips, heading_fans
from shared.geo import GeoFrame

T0_NS = 1_700_000_000_000_000_000
DT_NS = 100_000_000  # 10 Hz


def _message(k: int, tracker: str = "ft0", ids: tuple[int, ...] = (3, 7)) -> dict:
    """Tick k: track 3 drives east at 10 m/s from (0, 0), track 7 north at 8 m/s from (5, -20)."""
    motion = {3: (0.0, 0.0, 10.0, 0.0), 7: (5.0, -20.0, 0.0, 8.0)}
    rows = []
    for tid in ids:
        x0, y0, vx, vy = motion[tid]
        rows.append(
            {
                "id": tid,
                "x": x0 + vx * k * 0.1,
                "y": y0 + vy * k * 0.1,
                "lat": 42.23,
                "lon": -83.74,
                "vx": vx,
                "vy": vy,
                "yaw": math.atan2(vy, vx),
                "length": 4.5,
                "width": 1.8,
                "height": 1.5,
                "type": "car" if tid == 3 else "truck",
                "score": 0.9,
                "age": k,
                "hits": k,
                "cameras": ["NE"],
                "xy_cov": [[0.09, 0.01], [0.01, 0.04]],
                **({"yaw_std": 0.1, "yaw_confirmed": False} if tid == 3 else {}),  # the other track has neither
            }
        )
    return {"site": "s1", "seq": k, "t_ns": T0_NS + k * DT_NS, "tracker": tracker, "tracks": rows}


@pytest.fixture
def tracks_file(tmp_path: Path) -> Path:
    """20 good lines (2 tracks), a garbage line as line 4 and a line with a NaN x as line 12."""
    lines = [json.dumps(_message(k)) for k in range(20)]
    nan = _message(5)
    nan["tracks"][1]["x"] = float("nan")
    lines.insert(3, "{not json")
    lines.insert(11, json.dumps(nan))  # json.dumps writes NaN, which json.loads reads back
    path = tmp_path / "tracks.jsonl"
    path.write_text("\n".join(lines) + "\n\n")  # a trailing blank line is not a line
    return path


def test_tracks_file_to_rrd_counts_bad_lines_and_writes_the_entities(tracks_file: Path, tmp_path: Path) -> None:
    grey = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))  # (48, 64) grey, row 0 = north
    basemap = Basemap.from_array(grey, (-40.0, 40.0, -30.0, 30.0))
    frame = ("NE", T0_NS, np.zeros((24, 32, 3), np.uint8), [((10.0, 20.0), (5.0, 5.0, 15.0, 20.0))])
    out = tmp_path / "viz" / "tracks.rrd"

    summary = tracks_file_to_rrd(tracks_file, out, basemap=basemap, frames=[frame])

    assert out.is_file() and out.stat().st_size > 0
    assert summary["lines"] == 22
    assert summary["messages"] == 20
    assert summary["bad_lines"] == 2
    assert summary["first_bad_line"] == 4
    assert "JSON" in summary["first_bad_reason"]
    assert summary["rows"] == 40
    assert summary["tracks"] == 2
    assert summary["frames"] == 1
    assert summary["t_first_ns"] == T0_NS and summary["t_last_ns"] == T0_NS + 19 * DT_NS
    assert summary["span_s"] == pytest.approx(1.9)

    chunk = pytest.importorskip("rerun.chunk")  # rerun >= 0.41 reads .rrd files back
    reader = chunk.RrdReader(out)
    assert reader.blueprints(), "the layout (blueprint) is saved with the recording"
    paths = {c.entity_path for c in reader.stream()}
    expected = {
        "/world",
        "/world/basemap",
        "/world/tracks/ft0/trails",
        "/world/tracks/ft0/positions",
        "/world/tracks/ft0/footprints",
        "/world/tracks/ft0/uncertainty",
        "/world/tracks/ft0/heading",
        "/plots/speed/ft0/3",
        "/plots/speed/ft0/7",
        "/plots/tracks/ft0",
        "/cameras/NE/image",
        "/cameras/NE/boxes",
        "/cameras/NE/bottom",
    }
    assert expected <= paths, expected - paths


def test_a_nan_line_is_skipped_with_its_reason(tmp_path: Path) -> None:
    bad = _message(0)
    bad["tracks"][0]["yaw"] = float("nan")
    path = tmp_path / "tracks.jsonl"
    path.write_text(json.dumps(_message(1)) + "\n" + json.dumps(bad) + "\n")
    summary = tracks_file_to_rrd(path, tmp_path / "out.rrd")
    assert (summary["messages"], summary["bad_lines"], summary["first_bad_line"]) == (1, 1, 2)
    assert "track 0" in summary["first_bad_reason"] and "yaw" in summary["first_bad_reason"]


def test_missing_tracks_file_raises_an_error_naming_it(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_tracks.jsonl"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))):
        tracks_file_to_rrd(missing, tmp_path / "out.rrd")
    assert not (tmp_path / "out.rrd").exists()


def test_parse_rejects_missing_keys_and_accepts_a_tracks_message() -> None:
    with pytest.raises(ValueError, match="'t_ns'"):
        parse_tracks_message({"site": "s1", "tracks": []})
    row_without_width = {k: v for k, v in _message(0)["tracks"][0].items() if k != "width"}
    with pytest.raises(ValueError, match="track 0: missing key 'width'"):
        parse_tracks_message({"site": "s1", "t_ns": 1, "tracks": [row_without_width]})

    from shared.messages import Tracks

    msg = Tracks(
        site="s1",
        seq=4,
        t_capture_ns=T0_NS,
        tracker="a",
        id=np.array([9]),
        xy=np.array([[1.0, 2.0]]),
        latlon=np.array([[42.23, -83.74]]),
        velocity=np.array([[3.0, 4.0]], np.float32),
        yaw=np.zeros(1, np.float32),
        size_lwh=np.array([[4.5, 1.8, 1.5]], np.float32),
        vtype=np.array([2], np.int8),
        score=np.ones(1, np.float32),
        age=np.ones(1, np.int32),
        hits=np.ones(1, np.int32),
        cameras=[["NE"]],
        xy_cov=np.array([[[0.1, 0.0], [0.0, 0.1]]], np.float32),
        velocity_cov=np.array([[[0.2, 0.0], [0.0, 0.2]]], np.float32),
        yaw_confirmed=np.array([True]),
        yaw_std=np.array([0.05], np.float32),
    )
    parsed = parse_tracks_message(msg)
    assert (parsed.t_ns, parsed.tracker, parsed.rows[0].id, parsed.rows[0].type) == (T0_NS, "a", 9, "truck")
    assert (parsed.rows[0].x, parsed.rows[0].vy) == (1.0, 4.0)


def test_live_state_is_bounded_and_ended_tracks_are_forgotten(tmp_path: Path) -> None:
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "live.rrd")
    sink = TrackSink(rec, "s1", max_trail_points=5, trail_min_step_m=0.0, forget_after_s=1.0)
    for k in range(10):
        sink.log_tracks(_message(k))
    assert len(sink.trail_of("ft0", 3)) == 5  # bounded: the last 5 positions
    assert sink.trail_of("ft0", 3)[-1] == pytest.approx([9.0, 0.0])
    for k in range(10, 25):  # track 3 ended; after forget_after_s it is no longer held
        sink.log_tracks(_message(k, ids=(7,)))
    assert sink.live_tracks == 1 and sink.trail_of("ft0", 3) is None
    with pytest.raises(ValueError, match="site 'other'"):
        sink.log_tracks({**_message(30), "site": "other"})
    rec.flush()
    rec.disconnect()


def test_a_new_tracker_clears_the_drawings_and_tracks_of_the_one_before(tmp_path: Path) -> None:
    """fuse_track restarted: its old tracker's last tracks do not stay frozen on the map, nor in the sink's state."""
    chunk = pytest.importorskip("rerun.chunk")
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "restart.rrd")
    sink = TrackSink(rec, "s1")
    for k in range(5):
        sink.log_tracks(_message(k, tracker="ft0"))
    for k in range(5, 8):
        sink.log_tracks(_message(k, tracker="ft1"))
    assert {key[0] for key in sink._tracks} == {"ft1"} and sink.trail_of("ft0", 3) is None
    rec.flush()
    rec.disconnect()
    cleared = [c for c in chunk.RrdReader(tmp_path / "restart.rrd").stream()
               if c.entity_path == "/world/tracks/ft0" and "Clear" in str(c.to_record_batch().schema)]
    assert cleared, "no Clear logged on the old tracker's entity"


def test_a_recording_played_again_starts_its_tracks_afresh(tmp_path: Path) -> None:
    """The same tracker back at its start (a tracks file played again): its trails are not joined across the jump
    and the first pass's tracks are not held."""
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "replay.rrd")
    sink = TrackSink(rec, "s1", trail_min_step_m=0.0)
    for k in range(80):  # 8 s: track 3 ends 80 m east
        sink.log_tracks(_message(k))
    sink.log_tracks(_message(0, ids=(3,)))  # played again from the start
    assert np.allclose(sink.trail_of("ft0", 3), [[0.0, 0.0]]) and sink.live_tracks == 1
    sink.log_tracks(_message(30, ids=(3,)))
    sink.log_tracks(_message(10, ids=(3,)))  # 2 s back is a late message, not a replay: the track is held
    assert len(sink.trail_of("ft0", 3)) == 3
    rec.flush()
    rec.disconnect()


def test_live_counts_bad_messages_and_uses_the_first_site(tmp_path: Path) -> None:
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "live.rrd")
    messages = [_message(0), {"site": "s1"}, "junk", _message(1), {**_message(2), "site": "other"}]
    summary = live(iter(messages), rec)
    rec.flush()
    rec.disconnect()
    assert (summary["lines"], summary["messages"], summary["bad_lines"], summary["first_bad_line"]) == (5, 2, 3, 2)
    assert summary["tracks"] == 2


def test_an_uncertainty_ellipse_is_the_95_percent_contour_of_its_covariance() -> None:
    cov = np.array([[[0.09, 0.05], [0.05, 0.16]], [[4.0, 0.0], [0.0, 0.25]]])
    ring = ellipses_xy(np.array([10.0, -5.0]), np.array([2.0, 0.0]), cov, points=16)
    assert ring.shape == (2, 17, 2) and np.allclose(ring[:, 0], ring[:, -1])  # closed
    d = ring - np.array([[10.0, 2.0], [-5.0, 0.0]])[:, None]
    np.testing.assert_allclose(np.einsum("npi,nij,npj->np", d, np.linalg.inv(cov), d), 5.991)  # on the contour
    assert np.abs(d[1, :, 0]).max() == pytest.approx(np.sqrt(5.991) * 2.0)  # 2 m sigma east: 4.9 m half-axis


def test_a_heading_fan_spans_its_95_percent_interval_and_both_ways_when_not_confirmed() -> None:
    """Two tracks: one heading north with a 5 deg sigma, confirmed: one fan, +-9.8 deg, reaching 3 m; one heading
    east with a 60 deg sigma, not confirmed: capped at +-90 deg, drawn ahead and behind."""
    fans, owner = heading_fans(np.array([0.0, 10.0]), np.array([0.0, 5.0]), np.array([math.pi / 2, 0.0]),
                               np.array([3.0, 4.0]), np.radians([5.0, 60.0]), np.array([False, True]), points=5)
    assert owner.tolist() == [0, 1, 1] and all(f.shape == (7, 2) for f in fans)
    for fan, centre in zip(fans, ([0.0, 0.0], [10.0, 5.0], [10.0, 5.0]), strict=True):
        np.testing.assert_allclose(fan[0], centre)
        np.testing.assert_allclose(fan[-1], centre)  # closed at the centre
    arc = fans[0][1:-1]
    np.testing.assert_allclose(np.hypot(*arc.T), 3.0)
    bearings = np.degrees(np.arctan2(arc[:, 1], arc[:, 0]))
    np.testing.assert_allclose(bearings[[0, 2, 4]], [90 - 1.96 * 5, 90, 90 + 1.96 * 5])
    np.testing.assert_allclose(fans[1][1:-1][[0, 4]], [[10.0, 1.0], [10.0, 9.0]], atol=1e-12)  # +-90 deg, 4 m
    np.testing.assert_allclose(fans[2][3], [6.0, 5.0])  # behind: its middle points west


def test_a_track_whose_heading_is_not_confirmed_is_drawn_without_its_front() -> None:
    """Two tracks heading east, the second not confirmed: both rectangles, then the first's nose (centre to front)
    only, each strip with its track's index; a row's yaw_confirmed is read (absent: None), a bad one named."""
    strips, owner = footprint_strips(np.array([0.0, 10.0]), np.array([0.0, 5.0]), np.zeros(2), np.array([4.0, 4.0]),
                                     np.array([2.0, 2.0]), np.array([True, False]))
    assert len(strips) == 3 and owner.tolist() == [0, 1, 0]
    np.testing.assert_allclose(strips[2], [[0.0, 0.0], [2.0, 0.0]])
    row = _message(0)
    row["tracks"][0]["yaw_confirmed"] = False
    parsed = parse_tracks_message(row)
    assert parsed.rows[0].yaw_confirmed is False and parsed.rows[1].yaw_confirmed is None
    row["tracks"][0]["yaw_confirmed"] = "no"
    with pytest.raises(ValueError, match="track 0: yaw_confirmed must be true or false"):
        parse_tracks_message(row)


def test_a_rows_heading_sigma_is_read_and_a_bad_one_named() -> None:
    row = _message(0)
    row["tracks"][0]["yaw_std"] = 0.0625
    parsed = parse_tracks_message(row)
    assert parsed.rows[0].yaw_std == 0.0625 and parsed.rows[1].yaw_std is None
    for bad in (0.0, float("nan"), "0.1", True):
        row["tracks"][0]["yaw_std"] = bad
        with pytest.raises(ValueError, match="track 0: yaw_std must be a finite number > 0"):
            parse_tracks_message(row)


def test_a_bad_position_covariance_is_refused_with_its_reason() -> None:
    row = _message(0)
    row["tracks"][0]["xy_cov"] = [[0.1, 0.2], [0.2, 0.1]]
    with pytest.raises(ValueError, match=r"track 0: xy_cov .* not a symmetric positive definite"):
        parse_tracks_message(row)
    row["tracks"][0]["xy_cov"] = [[0.1, "x"], [0.0, 0.1]]
    with pytest.raises(ValueError, match=r"xy_cov must be \[\[a, b\], \[b, c\]\]"):
        parse_tracks_message(row)


def test_track_colour_is_stable_and_differs_between_tracks() -> None:
    assert track_color("ft0", 3) == track_color("ft0", 3)
    assert track_color("ft0", 3) != track_color("ft0", 4)
    assert track_color("ft0", 3) != track_color("ft1", 3)


def test_basemap_from_array_validates_and_places_corners() -> None:
    bm = Basemap.from_array(np.zeros((10, 20, 3), np.float32), (0.0, 200.0, -50.0, 50.0))
    assert bm.image.dtype == np.uint8
    assert bm.corners_m.tolist() == [[0, 50], [200, 50], [200, -50], [0, -50]]  # TL, TR, BR, BL
    assert bm.extent_m == (0.0, 200.0, -50.0, 50.0)
    with pytest.raises(ValueError, match="extent_m"):
        Basemap.from_array(np.zeros((10, 20), np.uint8), (10.0, 0.0, 0.0, 5.0))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        Basemap.from_array(np.zeros((10, 20, 4), np.uint8), (0.0, 1.0, 0.0, 1.0))
    big = Basemap.from_array(np.zeros((100, 300), np.uint8), (0.0, 3.0, 0.0, 1.0), max_side_px=60)
    assert big.image.shape == (20, 60)


def test_basemap_world_file_with_lat_lon_corners(tmp_path: Path) -> None:
    import cv2

    origin = GeoFrame(42.2294, -83.739, 265.0)
    corners = origin.to_geodetic(np.array([[-100.0, 80.0], [120.0, -60.0]]))  # TL, BR in site metres
    cv2.imwrite(str(tmp_path / "ortho.png"), np.full((30, 40, 3), (255, 0, 0), np.uint8))  # blue in BGR
    world = tmp_path / "ortho.yaml"
    world.write_text(
        json.dumps(
            {
                "image": "ortho.png",
                "top_left": corners[0, :2].tolist(),
                "bottom_right": {"lat": corners[1, 0], "lon": corners[1, 1]},
            }
        )
    )
    bm = Basemap.from_world_file(world, origin)
    assert bm.image[0, 0].tolist() == [0, 0, 255]  # stored RGB
    (tmp_path / "._ortho.yaml").write_bytes(b"\x00\x05\x16\x07")  # copied from a Mac: not a second world file
    assert Basemap.from_world_file(tmp_path, origin).corners_m[0] == pytest.approx([-100.0, 80.0], abs=0.01)
    assert bm.corners_m[0] == pytest.approx([-100.0, 80.0], abs=0.01)
    assert bm.corners_m[2] == pytest.approx([120.0, -60.0], abs=0.01)
    with pytest.raises(ValueError, match="no site origin"):
        Basemap.from_world_file(world)
    with pytest.raises(FileNotFoundError, match=r"nowhere\.yaml"):
        Basemap.from_world_file(tmp_path / "nowhere.yaml")
    world.write_text("image: [unclosed")
    with pytest.raises(ValueError, match=r"ortho\.yaml is not valid YAML or JSON"):
        Basemap.from_world_file(world, origin)
    world.write_text(json.dumps({"image": "ortho.png", "top_left": corners[0, :2].tolist(),
                                 "bottom_right": corners[1, :2].tolist(), "origin": {"lat": 42.2, "lon": -83.7}}))
    with pytest.raises(ValueError, match=r"ortho\.yaml: origin must be \{lat_deg, lon_deg"):
        Basemap.from_world_file(world)


def test_a_failed_conversion_leaves_an_existing_rrd_as_it_was(tracks_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "old.rrd"
    out.write_bytes(b"an earlier recording")

    def frames():
        raise ValueError("the frames' source broke")
        yield

    with pytest.raises(ValueError, match="source broke"):
        tracks_file_to_rrd(tracks_file, out, frames=frames())
    assert out.read_bytes() == b"an earlier recording" and not list(tmp_path.glob("*.partial"))
    with pytest.raises(ValueError, match="is a folder"):
        tracks_file_to_rrd(tracks_file, tmp_path)
    tracks_file_to_rrd(tracks_file, out)
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match="would replace the tracks file"):  # --out naming the input
        tracks_file_to_rrd(tracks_file, tracks_file)
    other = tracks_file_to_rrd(tracks_file, tmp_path / "other.rrd", site="elsewhere")  # --site of another site
    assert other["messages"] == 0 and other["bad_lines"] == other["lines"] > 0
    assert "this sink logs site 'elsewhere'" in other["first_bad_reason"]


def test_basemap_four_corner_file_with_its_image_beside_it_or_a_folder(tmp_path: Path) -> None:
    import cv2

    origin = GeoFrame(42.2294, -83.739, 265.0)
    site = np.array([[-100.0, 80.0], [120.0, 82.0], [-98.0, -60.0], [121.0, -61.0]])  # tl, tr, bl, br (a bit skewed)
    ll = origin.to_geodetic(site)[:, :2]
    folder = tmp_path / "basemap"
    folder.mkdir()
    (folder / "ortho.json").write_text(json.dumps({k: ll[i].tolist() for i, k in enumerate(("tl", "tr", "bl", "br"))}))
    with pytest.raises(FileNotFoundError, match=r"beside .*ortho\.json"):
        Basemap.from_world_file(folder / "ortho.json", origin)
    cv2.imwrite(str(folder / "ortho.jpg"), np.zeros((30, 40, 3), np.uint8))
    for path in (folder / "ortho.json", folder):
        bm = Basemap.from_world_file(path, origin)
        assert bm.corners_m == pytest.approx(site[[0, 1, 3, 2]], abs=0.01)  # stored tl, tr, br, bl
    with pytest.raises(ValueError, match="no site origin"):
        Basemap.from_world_file(folder)
    for change, message in [
        (lambda c: {k: v[::-1] for k, v in c.items()}, "km from the site's origin"),  # [lon, lat]
        (lambda c: {"tl": c["br"], "tr": c["bl"], "bl": c["tr"], "br": c["tl"]}, "top to the north"),  # upside down
        (lambda c: {"tl": c["tr"], "tr": c["tl"], "bl": c["br"], "br": c["bl"]}, "top to the north"),  # mirrored
    ]:
        corners = {k: ll[i].tolist() for i, k in enumerate(("tl", "tr", "bl", "br"))}
        (folder / "ortho.json").write_text(json.dumps(change(corners)))
        with pytest.raises(ValueError, match=message):
            Basemap.from_world_file(folder / "ortho.json", origin)
    (folder / "other.json").write_text("{}")
    with pytest.raises(ValueError, match="exactly one"):
        Basemap.from_world_file(folder, origin)


def test_viz_logs_camera_frames_with_detections_when_asked(tracks_file: Path, small_recording, tmp_path: Path,
                                                           capsys) -> None:
    pytest.importorskip("torch")
    from pipeline_fixtures import export_tiny_detector, site_config, write_site

    from roadside.cli import main

    config = site_config(small_recording)
    site = write_site(tmp_path / "site", config)
    text = tracks_file.read_text().replace('"site": "s1"', f'"site": "{config["site"]}"')
    # the tracks over the recording's first 1.9 s (its frames' capture times), as fuse_track would write them
    t0 = json.loads((small_recording / "recording.json").read_text())["t0_ns"]
    lines = []
    for line in text.splitlines():
        try:
            obj = json.loads(line)
        except ValueError:
            lines.append(line)
            continue
        lines.append(json.dumps({**obj, "t_ns": obj["t_ns"] - T0_NS + t0}))
    tracks_file.write_text("\n".join(lines) + "\n")
    model = export_tiny_detector(tmp_path / "tiny.onnx")
    out = tmp_path / "frames.rrd"
    assert main(["viz", str(tracks_file), "--out", str(out), "--site", str(site), "--frames", str(small_recording),
                 "--model", str(model), "--frames-every", "1"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 2 and out.stat().st_size > 0  # the site's one camera, two frames
    # tracks of another hour: none of the frames lies within their span, and viz says so
    late = tmp_path / "late.jsonl"
    late.write_text("\n".join(json.dumps({**json.loads(line), "t_ns": json.loads(line)["t_ns"] + 3600 * 10**9})
                              for line in lines if line.startswith('{"')) + "\n")
    assert main(["viz", str(late), "--out", str(out), "--site", str(site), "--frames", str(small_recording),
                 "--model", str(model), "--frames-every", "1"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["frames"] == 0
    assert "none of the 2 frames" in captured.err and "within the tracks' time span" in captured.err
    no_model = ["viz", str(tracks_file), "--out", str(out), "--site", str(site), "--frames", str(small_recording)]
    assert main(no_model) == 2
    assert "viz --frames needs --site (camera names) and --model" in capsys.readouterr().err


def test_an_optional_layer_is_drawn_while_rows_carry_it_and_cleared_once_after() -> None:
    """The uncertainty ellipses and heading fans are logged when some rows carry their field, once more (empty) by
    the next message whose rows carry none, so the last drawing does not linger, and then no more."""
    rec = rr.RecordingStream("test-layers")
    sink = TrackSink(rec, "s1")
    path = "world/tracks/t1/heading"
    assert [sink._draws(path, rows) for rows in ([0, 1], [], [], [2], [])] == [True, True, False, True, True]
    assert not sink._draws("world/tracks/t2/heading", [])  # another tracker's layer is its own


def test_the_sites_junction_is_drawn_where_the_counts_take_it_to_be(tracks_file: Path, tmp_path: Path) -> None:
    """With the site's junction and origin the .rrd holds `world/junction`: the inner circle round the junction's
    centre (in the site frame) and each leg's sector between the radii, labelled; without an origin it is left out."""
    from services.rerun_sink.sink import junction_strips
    from shared.movements import Junction

    origin = GeoFrame(42.2294, -83.7390, 265.0)
    centre = origin.to_geodetic(np.array([[10.0, -5.0, 0.0]]))[0]
    junction = Junction(float(centre[0]), float(centre[1]), (("north", 0.0), ("east", 90.0), ("south", 180.0)),
                        inner_radius_m=20.0, outer_radius_m=60.0, half_width_deg=30.0)
    strips, labels = junction_strips(junction, origin)
    assert labels == ["junction", "leg north", "leg east", "leg south"]
    assert np.allclose(np.hypot(strips[0][:, 0] - 10.0, strips[0][:, 1] + 5.0), 20.0, atol=0.01)
    east = strips[2] - [10.0, -5.0]
    r, bearing = np.hypot(east[:, 0], east[:, 1]), np.degrees(np.arctan2(east[:, 0], east[:, 1]))
    assert np.allclose(r[[0, -1]], 20.0, atol=0.01) and np.allclose(r[1:-1], 60.0, atol=0.01)
    assert bearing.min() == pytest.approx(60.0, abs=0.01) and bearing.max() == pytest.approx(120.0, abs=0.01)

    chunk = pytest.importorskip("rerun.chunk")
    for given, drawn in ((origin, True), (None, False)):
        out = tmp_path / f"{drawn}.rrd"
        tracks_file_to_rrd(tracks_file, out, site_origin=given, junction=junction)
        paths = {c.entity_path for c in chunk.RrdReader(out).stream()}
        assert ("/world/junction" in paths) is drawn


def _capture_times(rrd: Path, entity: str, component: str) -> list[int]:
    """The capture times (ns) at which `entity` got `component` (a column name prefix, e.g. "Clear:")."""
    import pyarrow as pa

    chunk = pytest.importorskip("rerun.chunk")
    times = []
    for c in chunk.RrdReader(rrd).stream():
        rb = c.to_record_batch()
        if c.entity_path == entity and "capture" in rb.schema.names and any(
                name.startswith(component) for name in rb.schema.names):
            times += rb.column("capture").cast(pa.int64()).to_pylist()
    return sorted(times)


def test_the_basemap_is_drawn_where_calibration_pick_georeferences_its_pixels(tmp_path: Path) -> None:
    """Four corners that are not a parallelogram (as the State/Ellsworth orthophoto's): a pixel's lat/lon as
    calibration.pick reads it off the orthophoto (bilinear between the corners; the landmarks, so the tracks, are
    placed so) is where the Rerun mesh draws that pixel, to within a centimetre; the image's outer corners are at
    texture coordinates 0 and 1."""
    import cv2

    from calibration.pick import Ortho
    from services.rerun_sink.sink import basemap_mesh

    origin = GeoFrame(42.2294, -83.739, 265.0)
    site = np.array([[-100.0, 80.0], [120.0, 84.0], [-96.0, -60.0], [116.0, -70.0]])  # tl, tr, bl, br: 8 x 14 m skew
    ll = origin.to_geodetic(site)[:, :2]
    folder = tmp_path / "basemap"
    folder.mkdir()
    (folder / "ortho.json").write_text(json.dumps({k: ll[i].tolist() for i, k in enumerate(("tl", "tr", "bl", "br"))}))
    w, h = 50, 40
    cv2.imwrite(str(folder / "ortho.png"), np.zeros((h, w, 3), np.uint8))
    mesh = basemap_mesh(Basemap.from_world_file(folder, origin))
    pos = np.array(mesh.vertex_positions.as_arrow_array().to_pylist())[:, :2]
    uv = np.array(mesh.vertex_texcoords.as_arrow_array().to_pylist())
    tri = np.array(mesh.triangle_indices.as_arrow_array().to_pylist())

    def drawn_at(px: np.ndarray) -> np.ndarray:
        """Where the mesh draws image pixel px (x, y; centre of the top-left pixel (0, 0)): the texture is mapped
        linearly within each triangle."""
        q = (px + 0.5) / [w, h]
        a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
        lam = np.linalg.solve(np.stack([b - a, c - a], axis=2), (q - a)[:, :, None])[:, :, 0]  # (T, 2): b's, c's
        inside = np.flatnonzero((lam >= -1e-9).all(axis=1) & (lam.sum(axis=1) <= 1 + 1e-9))[0]
        pa, pb, pc = pos[tri[inside]]
        return pa + lam[inside, 0] * (pb - pa) + lam[inside, 1] * (pc - pa)

    ortho = Ortho.load(folder)
    inner = [[(w - 1) / 2, (h - 1) / 2], [10.0, 30.0], [37.3, 8.6], [0.0, 0.0]]
    for pixels in (inner, [[-0.5, -0.5], [w - 0.5, h - 0.5]]):  # the image's middle, then its outer corners
        expected = origin.to_enu(*ortho.to_latlon(np.array(pixels)).T)[:, :2]
        drawn = np.array([drawn_at(p) for p in np.array(pixels)])
        assert np.abs(drawn - expected).max() < 0.01
    corner = [int(np.argmin(np.linalg.norm(pos - p, axis=1))) for p in site]
    assert uv[corner].tolist() == [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]


def test_a_new_tracker_on_a_clock_stepped_back_clears_the_old_one_after_its_last_drawing(tmp_path: Path) -> None:
    """fuse_track restarted when the cameras' clock stepped back: the new tracker's times are earlier than the old
    one's. The old tracker's Clear goes 1 ns after its last drawing (at the new tracker's time it would sit before
    them, and its last vehicles would stay drawn), and the new tracker's drawings at their own times."""
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "stepped.rrd")
    sink = TrackSink(rec, "s1")
    for k in range(10):
        sink.log_tracks(_message(k, tracker="ft0"))
    for k in range(20):
        sink.log_tracks(_message(k, tracker="ft1"))
    rec.flush()
    rec.disconnect()
    out = tmp_path / "stepped.rrd"
    assert _capture_times(out, "/world/tracks/ft0", "Clear:") == [T0_NS + 9 * DT_NS + 1]
    assert _capture_times(out, "/world/tracks/ft1/positions", "Points3D:") == [T0_NS + k * DT_NS for k in range(20)]


def test_a_basemap_world_files_origin_does_not_replace_the_sites(tmp_path: Path) -> None:
    """The tracks' frame decides: with the site's origin passed, a world file's own origin within half a metre of it
    is ignored, one further off is an error naming both; without the site's it places the map."""
    import cv2

    origin = GeoFrame(42.2294, -83.739, 265.0)
    site = np.array([[-100.0, 80.0], [120.0, 82.0], [-98.0, -60.0], [121.0, -61.0]])  # tl, tr, bl, br
    ll = origin.to_geodetic(site)[:, :2]
    cv2.imwrite(str(tmp_path / "ortho.jpg"), np.zeros((30, 40, 3), np.uint8))
    spec = {k: ll[i].tolist() for i, k in enumerate(("tl", "tr", "bl", "br"))}
    world = tmp_path / "ortho.json"
    for where, fails in (((0.3, 0.0), False), ((3.0, 3.0), True), ((0.0, 100.0), True)):
        own = origin.to_geodetic(np.array([[*where, 0.0]]))[0]
        world.write_text(json.dumps({**spec, "origin": {"lat_deg": own[0], "lon_deg": own[1], "alt_m": 0.0}}))
        if fails:
            with pytest.raises(ValueError, match=rf"origin \(lat {own[0]}, lon {own[1]}\) is .* m from the site origin "
                                                 rf"\(lat {origin.lat0_deg}, lon {origin.lon0_deg}\)"):
                Basemap.from_world_file(world, origin)
        else:
            bm = Basemap.from_world_file(world, origin)
            assert bm.corners_m == pytest.approx(site[[0, 1, 3, 2]], abs=0.01)
        alone = Basemap.from_world_file(world)  # no site origin: the file's places the map, in its own frame
        assert alone.corners_m == pytest.approx(site[[0, 1, 3, 2]] - where, abs=0.05)
    top_left = {"image": "ortho.jpg", "top_left": ll[0].tolist(), "bottom_right": ll[3].tolist()}
    world.write_text(json.dumps({**top_left, "origin": {"lat_deg": own[0], "lon_deg": own[1]}}))
    with pytest.raises(ValueError, match="m from the site origin"):
        Basemap.from_world_file(world, origin)
    extent = {"image": "ortho.jpg", "extent_m": [-100.0, 120.0, -60.0, 80.0]}  # site metres about its own origin
    world.write_text(json.dumps({**extent, "origin": {"lat_deg": own[0], "lon_deg": own[1]}}))
    with pytest.raises(ValueError, match="m from the site origin"):
        Basemap.from_world_file(world, origin)
    world.write_text(json.dumps(extent))
    assert Basemap.from_world_file(world, origin).corners_m[0] == pytest.approx([-100.0, 80.0])


def test_speeds_keep_flowing_after_a_tracker_restarts_with_the_clock_stepped_back(tmp_path: Path) -> None:
    """Speeds are sent every speed_flush_s of capture time, also once a new tracker's capture time is earlier than
    the last flush (fuse_track restarted on a clock step back), so they are not held until the track ends."""
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "speeds.rrd")
    sink = TrackSink(rec, "s1", speed_flush_s=1.0)
    for k in range(20):  # 2 s
        sink.log_tracks(_message(k, tracker="ft0"))
    for k in range(30):  # 3 s, from the same start
        sink.log_tracks(_message(k, tracker="ft1"))
        assert len(sink._tracks[("ft1", 3)].speed_t_ns) <= 11  # at most 1 s of speeds waits
    rec.flush()
    rec.disconnect()


def test_a_message_the_sink_refuses_logs_nothing_and_live_still_sends_the_layout(tmp_path: Path, monkeypatch) -> None:
    """A message whose position covariance has no Cholesky factor (its uncertainty ellipse cannot be drawn) is
    refused before anything of it is logged or held; live() sends the layout even when its first message is refused."""
    import dataclasses

    from services.rerun_sink import sink as sink_module

    out = tmp_path / "refused.rrd"
    rec = rr.RecordingStream("roadside_test")
    rec.save(out)
    sink = TrackSink(rec, "s1", trail_min_step_m=0.0)
    sink.log_tracks(_message(0))
    good = parse_tracks_message(_message(1))
    singular = ((0.01, 0.21), (0.21, 4.41))  # rank 1; a TracksMessage made by hand is not validated again
    bad = dataclasses.replace(good, rows=(dataclasses.replace(good.rows[0], xy_cov=singular), *good.rows[1:]))
    with pytest.raises(ValueError, match="positive definite"):
        sink.log_tracks(bad)
    assert sink.messages == 1 and len(sink.trail_of("ft0", 3)) == 1
    sink.log_tracks(_message(2))
    rec.flush()
    rec.disconnect()
    for entity in ("trails", "positions", "footprints"):
        assert _capture_times(out, f"/world/tracks/ft0/{entity}", "LineStrips3D:" if entity != "positions"
                              else "Points3D:") == [T0_NS, T0_NS + 2 * DT_NS]

    def refuse(*args, **kwargs):
        raise np.linalg.LinAlgError("Matrix is not positive definite")

    chunk = pytest.importorskip("rerun.chunk")
    monkeypatch.setattr(sink_module, "ellipses_xy", refuse)
    rec = rr.RecordingStream("roadside_test")
    rec.save(tmp_path / "live.rrd")
    summary = live(iter([_message(0)]), rec)
    rec.flush()
    rec.disconnect()
    assert (summary["messages"], summary["bad_lines"]) == (0, 1)
    assert chunk.RrdReader(tmp_path / "live.rrd").blueprints()
