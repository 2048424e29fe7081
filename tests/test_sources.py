"""ingest's live sources: a stream that drops is reported and opened again; live cameras are read side by side."""

from __future__ import annotations

import socket
import threading
import time

import cv2
import numpy as np
import pytest
from pipeline_fixtures import free_port_base, mjpeg_camera

from services.ingest.sources import MergedSource, SourceFrame, VideoSource

FRAMES_PER_CONNECTION = 4


def _grey_frame(k: int) -> bytes:
    return cv2.imencode(".jpg", np.full((48, 64, 3), 40 * k, np.uint8))[1].tobytes()


@pytest.fixture
def camera_url():
    """A camera that sends a few frames a connection, then drops it (a reboot, a network blip)."""
    with mjpeg_camera(_grey_frame, FRAMES_PER_CONNECTION, 0.05) as url:
        yield url


def _take(frames, good: int, deadline_s: float = 30.0) -> list[SourceFrame]:
    got, end = [], time.monotonic() + deadline_s
    for f in frames:
        got.append(f)
        if sum(not g.error for g in got) >= good or time.monotonic() > end:
            break
    return got


def test_a_live_stream_that_drops_is_reported_and_opened_again(camera_url):
    source = VideoSource(camera_url, "NE")
    source.RECONNECT_S = 0.05
    got = _take(iter(source), good=3 * FRAMES_PER_CONNECTION)
    images = [f for f in got if not f.error]
    drops = [f for f in got if f.error]
    assert len(images) >= 3 * FRAMES_PER_CONNECTION, f"only {len(images)} frames: the stream was not opened again"
    assert drops and all(f"stream {camera_url} lost; opening it again" in f.error for f in drops)
    assert all(f.image.shape == (48, 64, 3) for f in images)


def test_live_cameras_are_read_side_by_side(camera_url):
    """Two live cameras merged: frames of both come through, in the order they arrive."""
    parts = [VideoSource(camera_url, "NE"), VideoSource(camera_url, "SW")]
    for p in parts:
        p.RECONNECT_S = 0.05
    got = _take(iter(MergedSource(parts)), good=2 * FRAMES_PER_CONNECTION)
    assert {f.camera for f in got if not f.error} == {"NE", "SW"}


def test_a_video_file_given_by_url_ends_and_png_folders_still_play(tmp_path):
    """Only stream schemes are reopened: a file:// video ends like a file; a PNG image folder decodes (the JPEG
    header check does not apply to it)."""
    from services.ingest.__main__ import to_frame_fields
    from services.ingest.sources import ImageFolderSource
    from shared.settings import CameraSettings

    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    source = VideoSource(f"file://{path}", "NE")
    assert not source.live and len(list(source)) == 5
    folder = tmp_path / "NE"
    folder.mkdir()
    cv2.imwrite(str(folder / "1700000000000000000.png"), np.full((48, 64), 90, np.uint8))
    frame = next(iter(ImageFolderSource({"NE": folder})))
    cam = CameraSettings(name="NE", kind="pinhole", width=64, height=48, masks="m.npz")
    assert to_frame_fields(frame, cam, "gray8", 1)["width"] == 64


def _clip(path, frames: int = 5):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(frames):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    return path


def test_a_video_file_plays_again_from_the_start_for_each_loop(tmp_path):
    source = VideoSource(str(_clip(tmp_path / "clip.avi")), "NE")
    first, second = list(source), list(source)
    assert len(first) == len(second) == 5 and [f.t_capture_ns for f in first] == [f.t_capture_ns for f in second]
    assert not any(f.error for f in second)


def test_a_live_stream_beside_recorded_frames_is_refused_naming_the_camera(camera_url, tmp_path):
    """Live frames carry the wall clock, recorded ones their own times: merged, one would wait for the other for
    years. Each camera needs a source, too."""
    from services.ingest.sources import open_source

    folder = tmp_path / "NE"
    folder.mkdir()
    cv2.imwrite(str(folder / "1700000000000000000.png"), np.full((48, 64), 90, np.uint8))
    with pytest.raises(ValueError, match=r"camera SW stream live .* do not share a clock"):
        open_source(str(folder), ["NE", "SW"], {"SW": camera_url})
    with pytest.raises(ValueError, match="no source for camera SW: give each camera its own source"):
        open_source("", ["NE", "SW"], {"NE": str(folder)})
    assert {f.camera for f in open_source("", ["NE"], {"NE": str(folder)})} == {"NE"}


def test_camera_folders_are_matched_exactly_before_by_suffix(tmp_path):
    """NE's folder beside T_NE's is NE's; a suffix (gs_State_Ellsworth_NE) serves when nothing matches exactly."""
    from services.ingest.sources import open_source

    for name in ("NE", "T_NE", "gs_site_SW"):
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "1700000000000000000.png"), np.full((48, 64), 90, np.uint8))
    source = open_source(str(tmp_path), ["NE", "T_NE", "SW"], {})
    assert {f.camera: f.origin.split("/")[-2] for f in source} == {"NE": "NE", "T_NE": "T_NE", "SW": "gs_site_SW"}


def test_capture_times_in_names_and_numbered_frames_in_their_order(tmp_path):
    from services.ingest.sources import ImageFolderSource, capture_time_from_name

    assert capture_time_from_name("1718218800123456789.jpg") == 1718218800123456789  # ns
    assert capture_time_from_name("1718218800123456.jpg") == 1718218800123456000  # us
    assert capture_time_from_name("1718218800123.jpg") == 1718218800123000000  # ms
    assert capture_time_from_name("0000000000000001.jpg") is None  # a zero-padded frame counter: no time
    assert capture_time_from_name("171821880012345.jpg") is None  # 15 digits: no unit
    from zoneinfo import ZoneInfo

    from shared.settings import IngestSettings

    utc = capture_time_from_name("2023-12-19 11-00-00-034395.jpg")
    assert utc == 1702983600034395000  # 11:00 UTC by default
    detroit = IngestSettings(timezone="America/Detroit").tzinfo()  # a camera naming files in its local clock
    assert capture_time_from_name("2023-12-19 11-00-00-034395.jpg", detroit) - utc == 5 * 3600 * 10**9  # EST
    assert capture_time_from_name("2023-07-19 11-00-00.jpg", ZoneInfo("America/Detroit")) == \
        capture_time_from_name("2023-07-19 15-00-00.jpg")  # EDT in summer
    with pytest.raises(ValueError, match="unknown time zone 'Mars/Olympus'"):
        IngestSettings(timezone="Mars/Olympus")
    named = tmp_path / "named"
    named.mkdir()
    cv2.imwrite(str(named / "2023-12-19 11-00-00-034395.png"), np.full((48, 64), 90, np.uint8))
    from services.ingest.sources import open_source

    assert [f.t_capture_ns for f in open_source(str(named), ["c"], {}, tz=detroit)] == [utc + 5 * 3600 * 10**9]
    for n in (1, 2, 10, 11):
        cv2.imwrite(str(tmp_path / f"frame{n}.png"), np.full((48, 64), 90, np.uint8))
    frames = list(ImageFolderSource({"c": tmp_path}, fps=10, start_ns=0))
    assert [f.origin.split("/")[-1] for f in frames] == ["frame1.png", "frame2.png", "frame10.png", "frame11.png"]
    assert [f.t_capture_ns for f in frames] == [0, 100_000_000, 200_000_000, 300_000_000]


def test_a_recording_without_frames_for_a_camera_is_named(tmp_path, small_recording):
    import shutil

    from services.ingest.sources import RecordingSource
    from sim.recording import Recording

    copy = tmp_path / "rec"
    shutil.copytree(small_recording, copy)
    camera = Recording(copy).camera_names[0]
    for f in (copy / "frames" / camera).iterdir():
        f.unlink()
    with pytest.raises(ValueError, match=f"has no frames for camera {camera}"):
        RecordingSource(copy)


def test_a_restarted_ingest_goes_on_after_the_tracks_fuse_track_holds(tmp_path):
    """The latest tracks' capture time inside the files' own times: resumed after it; outside them (another
    recording), nothing answering, or a source without files: from the start."""
    from types import SimpleNamespace

    from test_movements import tracks_message

    from services.ingest.__main__ import resume_point
    from shared.codec import encode

    def session(*t_ns):
        replies = [SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda t=t: encode(
            tracks_message(t, []))))) for t in t_ns]
        return SimpleNamespace(get=lambda key, timeout: iter(replies))

    files = SimpleNamespace(items=[(100, "NE", "a"), (200, "NE", "b"), (300, "NE", "c")])
    assert resume_point(session(250), "se", files) == 250
    assert resume_point(session(50), "se", files) is None and resume_point(session(300), "se", files) is None
    assert resume_point(session(), "se", files) is None
    assert resume_point(session(250), "se", SimpleNamespace()) is None  # a stream: no files to skip


def _still(folder, *names, size=(48, 64)):
    """Tiny grey images named `names` in `folder` (made)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        cv2.imwrite(str(folder / name), np.full(size, 90, np.uint8))
    return folder


def test_a_live_camera_down_at_start_is_reported_and_opened_again(monkeypatch):
    """A camera not up yet when the cabinet boots is no configuration error: its failed opens are frames carrying the
    reason until it comes up; a file or a file:// URL that cannot be opened still stops ingest at start."""
    port = free_port_base(span=1)
    url = f"http://127.0.0.1:{port}/stream.mjpg"
    monkeypatch.setattr(VideoSource, "RECONNECT_S", 0.05)
    source = VideoSource(url, "NE")  # nothing listens yet
    frames = iter(source)
    down = next(frames)
    assert down.error == f"camera NE: cannot open stream {url}; trying again in 0.05 s" and down.image is None
    with mjpeg_camera(_grey_frame, FRAMES_PER_CONNECTION, 0.05, port=port):
        got = _take(frames, good=2)
    assert sum(not f.error for f in got) >= 2, [f.error for f in got]
    with pytest.raises(ValueError, match=r"OpenCV cannot open file:///nowhere/clip\.avi"):
        VideoSource("file:///nowhere/clip.avi", "NE")


def test_a_stop_ends_a_live_camera_s_hung_open_and_its_wait_to_reconnect(monkeypatch):
    """Cameras that take the connection and never answer: each open gives up after `STREAM_TIMEOUT_MS` (OpenCV's own
    wait is 30 s), and a stop ends the wait before the next attempt and the merged cameras' frames at once."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    held = []
    threading.Thread(target=lambda: [held.append(server.accept()) for _ in range(16)], daemon=True).start()
    url = f"http://127.0.0.1:{server.getsockname()[1]}/stream.mjpg"
    monkeypatch.setattr(VideoSource, "STREAM_TIMEOUT_MS", 500)
    monkeypatch.setattr(VideoSource, "RECONNECT_S", 30.0)
    stop = threading.Event()
    t = time.monotonic()
    parts = [VideoSource(url, "NE", stop=stop), VideoSource(url, "SW", stop=stop)]
    assert time.monotonic() - t < 5.0
    frames = iter(MergedSource(parts, stop))
    assert "cannot open stream" in next(frames).error
    stop.set()
    t = time.monotonic()
    rest = list(frames)
    assert time.monotonic() - t < 2.0 and all(f.error for f in rest)
    server.close()


def test_merged_camera_folders_have_items_to_resume_from(tmp_path):
    """Each camera's own image folder (cameras[].source): one source with the files of all, in time order, so a
    restarted ingest asks fuse_track where to go on; with a video file among them, none."""
    from types import SimpleNamespace

    from services.ingest.__main__ import resume_point
    from services.ingest.sources import open_source

    t0 = 1_700_000_000_000_000_000
    _still(tmp_path / "NE", f"{t0}.png", f"{t0 + 200_000_000}.png")
    _still(tmp_path / "SW", f"{t0 + 100_000_000}.png")
    source = open_source("", ["NE", "SW"], {"NE": str(tmp_path / "NE"), "SW": str(tmp_path / "SW")})
    assert isinstance(source, MergedSource)
    assert [(t - t0, cam) for t, cam, _ in source.items] == [(0, "NE"), (100_000_000, "SW"), (200_000_000, "NE")]
    assert [(f.t_capture_ns, f.camera) for f in source] == [(t, cam) for t, cam, _ in source.items]
    asked = []
    resume_point(SimpleNamespace(get=lambda key, timeout: asked.append(key) or iter(())), "se", source)
    assert asked == ["roadside/se/tracks/latest?any_age"]  # whatever its age: fuse_track is silent while ingest is down
    clip = VideoSource(str(_clip(tmp_path / "clip.avi")), "SW")
    assert MergedSource([source, clip]).items is None


def test_hidden_files_in_an_image_folder_are_not_frames(tmp_path):
    """macOS's AppleDouble `._<name>` files beside each image (a copy over SMB or to a FAT drive), other hidden
    files and a sub-folder named like an image are no frames: with epoch names the folder was refused, with date-time
    names every frame had a twin."""
    from services.ingest.sources import ImageFolderSource

    for names in (["1700000000000000000.jpg", "1700000000100000000.jpg"],
                  ["2023-12-19 11-00-00-034395.jpg", "2023-12-19 11-00-01-034395.jpg"]):
        folder = _still(tmp_path / names[0][:4], *names)
        for n in names:
            (folder / f"._{n}").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        " + bytes(100))
        _still(folder, ".hidden.jpg")
        (folder / "dir.jpg").mkdir()
        assert [p.name for _, _, p in ImageFolderSource({"NE": folder}).items] == names


def test_a_camera_folder_holding_sub_folders_is_still_that_camera_s(tmp_path):
    """A one-camera image folder holding a NAS's `@eaDir`, a `.thumbnails` or a `bad/` folder is that camera's; in a
    parent of camera folders, `@*` and `.*` folders are not cameras."""
    from services.ingest.sources import ImageFolderSource, open_source

    folder = _still(tmp_path / "cam", "1700000000000000000.jpg", "1700000000100000000.jpg")
    for sub in ("@eaDir", ".thumbnails", "bad"):
        _still(folder / sub, "1700000000000000000.jpg")
    source = open_source(str(folder), ["NE"], {})
    assert isinstance(source, ImageFolderSource) and [p.parent for _, _, p in source.items] == [folder, folder]
    for cam in ("NE", "SW"):
        _still(tmp_path / "parent" / cam, "1700000000000000000.jpg")
    (tmp_path / "parent" / "@eaDir").mkdir()
    (tmp_path / "parent" / ".thumbnails").mkdir()
    assert {cam for _, cam, _ in open_source(str(tmp_path / "parent"), ["NE", "SW"], {}).items} == {"NE", "SW"}
    with pytest.raises(ValueError, match=r"found none among \['NE', 'SW'\]"):
        open_source(str(tmp_path / "parent"), ["NE", "T_SW"], {})


def test_cameras_whose_clocks_differ_are_refused_naming_them(tmp_path):
    """A frame rate times only folders whose names carry no time (one stray name among dated ones is named, not
    taken for a reason to replace every time by the wall clock); a camera whose frames lie more than 10 min from
    every other camera's (a video file timed from when it is opened beside dated folders, a folder named in another
    time zone) is refused, naming the cameras and their spans; one that starts late while the others record plays."""
    from services.ingest.sources import ImageFolderSource, open_source

    dated = ["2023-12-19 11-00-00-000000.jpg", "2023-12-19 11-00-01-000000.jpg"]
    _still(tmp_path / "gs_NE", *dated)
    _still(tmp_path / "gs_SW", *dated, "preview.jpg")
    with pytest.raises(ValueError, match=r"camera SW: .* file name 'preview.jpg' while other names in .*gs_SW carry"):
        open_source(str(tmp_path), ["NE", "SW"], {}, fps=5.0)
    (tmp_path / "gs_SW" / "preview.jpg").unlink()
    assert len(open_source(str(tmp_path), ["NE", "SW"], {}, fps=5.0).items) == 4  # their own times
    clip = _clip(tmp_path / "SW.avi")
    with pytest.raises(ValueError, match=r"camera .*'s frames lie .* from every other camera's \(NE 2023-12-19T11:00:00"
                                         r"\+00:00 to 2023-12-19T11:00:01\+00:00, SW 20"):
        open_source(str(tmp_path), ["NE", "SW"], {"SW": str(clip)})
    _still(tmp_path / "local" / "SW", "2023-12-19 06-00-05-000000.jpg")  # named in Detroit's clock, read as UTC
    with pytest.raises(ValueError, match=r"camera (NE|SW)'s frames lie 5.0 h from every other camera's \(SW 2023-12"):
        ImageFolderSource({"NE": tmp_path / "gs_NE", "SW": tmp_path / "local" / "SW"})
    _still(tmp_path / "late" / "SW", "2023-12-19 11-09-00-000000.jpg")  # a camera started 9 min later: played
    assert len(ImageFolderSource({"NE": tmp_path / "gs_NE", "SW": tmp_path / "late" / "SW"}).items) == 3
    # a camera that starts 20 min after the others while they still record: their frames overlap, played
    _still(tmp_path / "long" / "NE", "2023-12-19 11-00-00-000000.jpg", "2023-12-19 11-30-00-000000.jpg")
    _still(tmp_path / "long" / "SW", "2023-12-19 11-20-00-000000.jpg", "2023-12-19 11-40-00-000000.jpg")
    assert len(ImageFolderSource({"NE": tmp_path / "long" / "NE", "SW": tmp_path / "long" / "SW"}).items) == 4
    _still(tmp_path / "after" / "SW", "2023-12-19 11-45-00-000000.jpg")  # 15 min after NE's last frame
    with pytest.raises(ValueError, match=r"camera (NE|SW)'s frames lie 15 min from every other camera's"):
        ImageFolderSource({"NE": tmp_path / "long" / "NE", "SW": tmp_path / "after" / "SW"})


@pytest.mark.parametrize("ext", [".png", ".bmp"])
def test_an_oversized_png_or_bmp_is_refused_from_its_header_before_it_is_decoded(ext, monkeypatch):
    """Its header's size is checked as a JPEG's: a 2000x2000 image in a 64x48 camera's folder is not decoded (a
    20000x20000 PNG of 0.4 MB took ingest past its memory limit); the camera's own size still decodes."""
    from shared.jpeg import decode_grey

    big = cv2.imencode(ext, np.zeros((2000, 2000), np.uint8))[1].tobytes()
    own = cv2.imencode(ext, np.full((48, 64, 3), 90, np.uint8))[1].tobytes()
    assert decode_grey(own, 64, 48).shape == (48, 64)
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("decoded"))
    with pytest.raises(ValueError, match=rf"big{ext}: {ext[1:].upper()} is 2000x2000, expected 64x48"):
        decode_grey(big, 64, 48, what=f"big{ext}")


def test_every_camera_without_its_image_folder_is_named_at_once(tmp_path):
    from services.ingest.sources import open_source

    for name in ("cam1", "cam2", "t_sw"):
        (tmp_path / name).mkdir()
    with pytest.raises(ValueError) as err:
        open_source(str(tmp_path), ["NE", "NW", "T_SW"], {})
    msg = str(err.value)
    assert "camera NE: expected one sub-folder" in msg and "camera NW: expected one sub-folder" in msg
    assert "camera T_SW" not in msg  # t_sw is its folder, in any case
    assert "among ['cam1', 'cam2', 't_sw']" in msg and "cameras[].source" in msg
