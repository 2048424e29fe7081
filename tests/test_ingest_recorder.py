"""ingest's frame recording (`ingest.record_dir`, services/ingest/recorder.py): what it writes plays back as it was
published, nothing recorded is written over, and a full queue, a full disk or a failing write is counted, not fatal."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from services.ingest import recorder as recorder_module
from services.ingest.recorder import FrameRecorder, RecorderConfig, check_not_the_source
from services.ingest.sources import open_source

T0 = 1_703_001_700_000_000_000


def jpeg(value: int, shape=(48, 64)) -> bytes:
    rng = np.random.default_rng(value)
    img = (rng.integers(0, 40, shape) + value).astype(np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def closed(rec: FrameRecorder) -> FrameRecorder:
    rec.close(timeout_s=30)
    return rec


def test_what_is_recorded_plays_back_as_it_was_published(tmp_path):
    """JPEG files byte for byte, PNG files as PNGs, decoded stream images as JPEGs; at their capture times, each
    camera in its own folder, which `open_source` finds as it finds any cameras' image folders."""
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec"))
    files = {("NE", T0): jpeg(10), ("NE", T0 + 100_000_000): jpeg(20), ("SW", T0 + 30_000_000): jpeg(30)}
    for (cam, t), data in files.items():
        assert rec.put(cam, t, jpeg=data)
    png = cv2.imencode(".png", np.full((48, 64), 7, np.uint8))[1].tobytes()
    assert rec.put("SW", T0 + 130_000_000, jpeg=png)
    stream = np.dstack([np.tile(np.arange(64, dtype=np.uint8) * 3, (48, 1))] * 3)  # BGR, as OpenCV decodes a stream
    assert rec.put("T_NE", T0 + 50_000_000, image=stream)
    closed(rec)
    assert rec.written == {"NE": 2, "SW": 2, "T_NE": 1}
    assert (rec.dropped, rec.no_space, rec.duplicates, sum(rec.errors.values())) == (0, 0, 0, 0)
    assert "5 frames written (NE 2, SW 2, T_NE 1)" in rec.summary()

    played = list(open_source(str(tmp_path / "rec"), ["NE", "SW", "T_NE"], {}))
    assert [(f.camera, f.t_capture_ns) for f in played] == sorted(
        [(c, t) for c, t in files] + [("SW", T0 + 130_000_000), ("T_NE", T0 + 50_000_000)], key=lambda ct: ct[1])
    by_key = {(f.camera, f.t_capture_ns): f.jpeg for f in played}
    for key, data in files.items():
        assert by_key[key] == data
    assert by_key[("SW", T0 + 130_000_000)] == png
    assert (tmp_path / "rec" / "SW" / f"{T0 + 130_000_000}.png").is_file()
    back = cv2.imdecode(np.frombuffer(by_key[("T_NE", T0 + 50_000_000)], np.uint8), cv2.IMREAD_COLOR)
    assert back.shape == stream.shape and np.abs(back.astype(int) - stream).mean() < 2.0
    assert not list((tmp_path / "rec").rglob(".*"))  # no half-written file left


def test_a_frame_recorded_before_is_never_written_over(tmp_path):
    folder = tmp_path / "rec" / "NE"
    folder.mkdir(parents=True)
    (folder / f"{T0}.jpg").write_bytes(b"recorded before")
    (folder / f"{T0 + 1}.png").write_bytes(b"recorded before, as a PNG")
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec"))
    rec.put("NE", T0, jpeg=jpeg(1))
    rec.put("NE", T0 + 1, jpeg=jpeg(2))  # a JPEG now, a PNG then: the same frame
    rec.put("NE", T0 + 2, jpeg=jpeg(3))
    rec.put("NE", T0 + 2, jpeg=jpeg(4))  # twice in one run (a restarted ingest plays frames again)
    closed(rec)
    assert (rec.written["NE"], rec.duplicates) == (1, 3)
    assert (folder / f"{T0}.jpg").read_bytes() == b"recorded before"
    assert (folder / f"{T0 + 2}.jpg").read_bytes() == jpeg(3)
    assert not (folder / f"{T0 + 1}.jpg").exists()


@pytest.fixture
def stalled_disk(monkeypatch) -> threading.Event:
    """Every write waits until the returned event is set (a disk slower than the cameras)."""
    release = threading.Event()
    write = FrameRecorder._write

    def slow_disk(self, *args):
        release.wait(30)
        write(self, *args)

    monkeypatch.setattr(FrameRecorder, "_write", slow_disk)
    return release


def test_frames_that_do_not_fit_in_the_queue_are_dropped_and_counted_never_waited_for(tmp_path, stalled_disk):
    release = stalled_disk
    one = jpeg(5)
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec", queue_mb=2.5 * len(one) / 1e6))
    t = time.monotonic()
    put = [rec.put("NE", T0 + i, jpeg=one) for i in range(4)]
    assert time.monotonic() - t < 5.0  # the disk held up nothing
    assert put == [True, True, False, False] and rec.dropped == 2
    release.set()
    closed(rec)
    assert rec.written["NE"] == 2 and rec.dropped == 2
    assert not rec.put("NE", T0 + 9, jpeg=one)  # closed: no thread to write it
    assert rec.written["NE"] == 2


def test_recording_pauses_below_the_free_space_and_goes_on_when_space_is_freed(tmp_path, monkeypatch):
    free = {"mb": 10.0}

    class Usage:
        @property
        def free(self) -> float:
            return free["mb"] * 1e6

    monkeypatch.setattr(recorder_module.shutil, "disk_usage", lambda path: Usage())
    monkeypatch.setattr(recorder_module, "SPACE_CHECK_S", 0.0)
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec", min_free_mb=100))
    rec.put("NE", T0, jpeg=jpeg(1))
    rec.put("NE", T0 + 1, jpeg=jpeg(2))
    while rec.pending:
        time.sleep(0.01)
    time.sleep(0.05)
    free["mb"] = 5000.0
    rec.put("NE", T0 + 2, jpeg=jpeg(3))
    closed(rec)
    assert (rec.no_space, rec.written["NE"]) == (2, 1)
    assert sorted(p.name for p in (tmp_path / "rec" / "NE").iterdir()) == [f"{T0 + 2}.jpg"]


def test_a_frame_that_cannot_be_written_is_counted_and_the_next_is_written(tmp_path):
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "NE").write_text("a file where camera NE's folder should be")
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec"))
    rec.put("NE", T0, jpeg=jpeg(1))
    rec.put("NE", T0 + 1, jpeg=b"GIF89a not an image format playback reads")
    rec.put("SW", T0 + 2, jpeg=b"GIF89a not an image format playback reads")
    rec.put("SW", T0 + 3, jpeg=jpeg(2))
    assert not rec.put("SW", 999_999_999_999_999_999, jpeg=jpeg(3))  # 2001-09-09: no 19-digit name
    closed(rec)
    assert rec.written == {"SW": 1}
    reasons = " | ".join(rec.errors)
    assert "camera NE: FileExistsError" in reasons or "camera NE: NotADirectoryError" in reasons, reasons
    assert "camera SW: ValueError: not a JPEG, PNG or BMP file" in reasons
    assert "ns is before" in reasons
    assert sum(rec.errors.values()) == 4


def test_the_recording_must_not_overlap_the_folder_being_played(tmp_path):
    src = tmp_path / "footage"
    (src / "NE").mkdir(parents=True)
    for bad in (src, src / "again", tmp_path):
        with pytest.raises(ValueError, match="overlap"):
            check_not_the_source(bad, str(src))
    with pytest.raises(ValueError, match="overlap"):
        check_not_the_source(src, str(src / "NE"))
    check_not_the_source(tmp_path / "recorded", str(src))
    check_not_the_source(src, "rtsp://10.0.0.7/stream1")
    check_not_the_source(src, None)
    video = tmp_path / "cam.mp4"
    video.write_bytes(b"")
    check_not_the_source(tmp_path, str(video))  # a video file in the folder recorded into: nothing to overlap


@pytest.mark.parametrize("field, value", [("jpeg_quality", 0), ("jpeg_quality", 101), ("queue_mb", 0.0),
                                          ("queue_mb", float("nan")), ("min_free_mb", -1.0)])
def test_a_bad_recorder_setting_is_named(tmp_path, field, value):
    with pytest.raises(ValueError, match=field):
        RecorderConfig(tmp_path, **{field: value})


def test_the_site_file_takes_the_recording_settings_and_refuses_bad_ones(tmp_path):
    from shared.settings import IngestSettings

    assert IngestSettings().record_dir is None
    cfg = IngestSettings(record_dir=Path("frames"), record_jpeg_quality=80)
    assert (cfg.record_dir, cfg.record_jpeg_quality) == (Path("frames"), 80)
    for field, value in (("record_jpeg_quality", 0), ("record_queue_mb", 0), ("record_min_free_mb", -5)):
        with pytest.raises(ValueError, match=field):
            IngestSettings(**{field: value})


def test_an_empty_variable_is_not_given_and_an_empty_path_in_the_site_file_is_none(tmp_path, monkeypatch):
    """compose.yaml passes `ROADSIDE_INGEST__RECORD_DIR: ${RECORD_FRAMES:-}`: unset, it is empty, and the site file's
    record_dir stands (pydantic would read "" as Path("."), and the environment would override the file); an empty
    path in the site file is none, not the current folder."""
    from shared.settings import load_settings

    example = Path(__file__).resolve().parents[1] / "deploy" / "sites" / "example" / "site.yaml"
    config = yaml.safe_load(example.read_text())
    config["ingest"] = {**config.get("ingest", {}), "record_dir": "frames"}
    config["fuse_track"] = {**config.get("fuse_track", {}), "record": "out/tracks.jsonl"}
    site = tmp_path / "site.yaml"
    site.write_text(yaml.safe_dump(config))
    for name in ("ROADSIDE_INGEST__RECORD_DIR", "ROADSIDE_FUSE_TRACK__RECORD", "ROADSIDE_DETECT__PROVIDERS"):
        monkeypatch.setenv(name, "")
    s = load_settings(site)
    assert (s.ingest.record_dir, s.fuse_track.record, s.detect.providers) == (Path("frames"), Path("out/tracks.jsonl"),
                                                                              None)
    monkeypatch.setenv("ROADSIDE_INGEST__RECORD_DIR", "/data/frames")
    assert load_settings(site).ingest.record_dir == Path("/data/frames")
    monkeypatch.delenv("ROADSIDE_INGEST__RECORD_DIR")
    config["ingest"]["record_dir"] = ""
    config["fuse_track"]["record"] = ""
    site.write_text(yaml.safe_dump(config))
    s = load_settings(site)
    assert (s.ingest.record_dir, s.fuse_track.record) == (None, None)
    assert load_settings(site, ingest={"record_dir": ""}).ingest.record_dir is None  # --set ingest.record_dir=""


def test_folders_deleted_to_free_space_are_made_again(tmp_path):
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec"))
    rec.put("NE", T0, jpeg=jpeg(1))
    while rec.pending:
        time.sleep(0.01)
    time.sleep(0.05)
    shutil.rmtree(tmp_path / "rec" / "NE")  # an operator frees space
    rec.put("NE", T0 + 1, jpeg=jpeg(2))
    while rec.pending:
        time.sleep(0.01)
    time.sleep(0.05)
    shutil.rmtree(tmp_path / "rec")  # all of it
    rec.put("NE", T0 + 2, jpeg=jpeg(3))
    closed(rec)
    assert rec.written["NE"] == 3 and not rec.errors, rec.errors
    assert [p.name for p in (tmp_path / "rec" / "NE").iterdir()] == [f"{T0 + 2}.jpg"]


def test_a_frame_larger_than_the_queue_is_taken_when_the_queue_is_empty(tmp_path, stalled_disk):
    release = stalled_disk
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec", queue_mb=0.5))
    big = np.zeros((600, 800, 3), np.uint8)  # 1.44 MB decoded, three times the queue
    assert rec.put("NE", T0, image=big)
    assert not rec.put("NE", T0 + 1, image=big)  # the queue holds one already
    release.set()
    closed(rec)
    assert (rec.written["NE"], rec.dropped) == (1, 1)
    assert rec.counts() == {"recorded.NE": 1, "record_dropped": 1, "record_no_space": 0, "record_duplicates": 0,
                            "record_errors": 0}


def test_frames_left_when_close_times_out_are_dropped_and_counted_once(tmp_path, monkeypatch):
    write = FrameRecorder._write

    def slow_disk(self, *args):
        time.sleep(0.2)
        write(self, *args)

    monkeypatch.setattr(FrameRecorder, "_write", slow_disk)
    rec = FrameRecorder(RecorderConfig(tmp_path / "rec"))
    for i in range(10):
        rec.put("NE", T0 + i, jpeg=jpeg(i))
    rec.close(timeout_s=0.3)
    time.sleep(0.5)
    files = len(list((tmp_path / "rec" / "NE").iterdir()))
    assert rec.written["NE"] == files and 1 <= files < 10
    assert rec.written["NE"] + rec.dropped == 10


def test_a_record_dir_that_cannot_be_made_is_named(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(ValueError, match=r"ingest.record_dir .*file/frames: cannot be made"):
        FrameRecorder(RecorderConfig(tmp_path / "file" / "frames"))
