"""fuse_track's tracks recording (services/fuse_track/recorder.py): nothing written is lost, not to a full disk, a
killed process or a rotation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.fuse_track.recorder import Recorder


class Msg:
    """What the recorder reads of a Tracks message."""

    site, tracker = "s", "tracker-1"

    def __init__(self, seq: int) -> None:
        self.seq = self.t_capture_ns = seq

    def rows(self) -> list:
        return [{"id": self.seq}]


def seqs(path: Path) -> list[int]:
    return [json.loads(line)["seq"] for line in path.read_text().splitlines()]


def test_the_recorder_survives_a_failed_write_and_a_half_written_line(tmp_path, caplog):
    """A full disk costs the messages it could not record, not live tracking or the lines before; a file a killed
    process left in half a line gets that half line cut off, so every line parses."""

    path = tmp_path / "tracks.jsonl"
    path.write_bytes(b'{"seq": 0}\n{"seq": 1, "tra')
    rec = Recorder(path)
    assert path.read_bytes() == b'{"seq": 0}\n' and "ended in half a line" in caplog.text
    rec.write(Msg(2))
    real_write = rec.file.write

    def half_then_fail(data: bytes) -> int:
        real_write(data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    rec.file.write = half_then_fail
    rec.write(Msg(3))
    assert rec.failed == 1 and "Tracks seq 3 not recorded (No space left on device" in caplog.text
    for seq in range(1000, 1250):  # a disk that stays full: the first, the 100th and the 200th are logged
        rec.write(Msg(seq))
    assert [r.message.count("not recorded") for r in caplog.records].count(1) == 3 and rec.failed == 251
    assert "Tracks seq 1198 not recorded (No space left on device; 200 lost so far)" in caplog.text
    rec.file.write = real_write
    rec.write(Msg(4))
    assert "recording again from Tracks seq 4 (251 lost so far)" in caplog.text
    rec.close()
    assert seqs(path) == [0, 2, 4]
    Recorder(path).close()  # a complete file is left as it is
    assert seqs(path) == [0, 2, 4]


def test_a_rotated_recording_keeps_every_line_in_order_across_files_and_restarts(tmp_path):
    path = tmp_path / "tracks.jsonl"
    line = len(json.dumps({"site": "s", "seq": 0, "t_ns": 0, "tracker": "tracker-1", "tracks": [{"id": 0}]})) + 1
    rec = Recorder(path, rotate_bytes=3 * line)  # three lines of one digit a file
    for seq in range(8):
        rec.write(Msg(seq))
    rec.close()
    names = [p.name for _, p in rec.rotated()]
    assert names == ["tracks.000001.jsonl", "tracks.000002.jsonl"]
    assert [seqs(tmp_path / n) for n in names] + [seqs(path)] == [[0, 1, 2], [3, 4, 5], [6, 7]]
    rec = Recorder(path, rotate_bytes=3 * line, keep=2)  # a restart numbers on, and keeps the newest two
    for seq in range(8, 12):  # the open file's two lines and these four: two more rotations
        rec.write(Msg(seq))
    rec.close()
    assert [p.name for _, p in rec.rotated()] == ["tracks.000003.jsonl", "tracks.000004.jsonl"]
    assert [seqs(p) for _, p in rec.rotated()] + [seqs(path)] == [[6, 7, 8], [9, 10, 11], []]


def test_a_rotation_that_fails_loses_no_line_and_is_tried_again_later(tmp_path, monkeypatch, caplog):
    path = tmp_path / "tracks.jsonl"
    rec = Recorder(path, rotate_bytes=1000)
    real_rename = Path.rename
    fails = iter([True])

    def rename(self: Path, target: Path) -> Path:
        if next(fails, False):
            raise OSError(13, "Permission denied")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", rename)
    seq = 0
    while path.stat().st_size < 1000:
        rec.write(Msg(seq))
        seq += 1
    assert rec.rotation_failed == 1 and "rotation to tracks.000001.jsonl failed (Permission denied)" in caplog.text
    assert rec.rotated() == [] and seqs(path) == list(range(seq))
    failed_at = path.stat().st_size
    while not rec.rotated():  # again once the file has grown a tenth of the limit more
        rec.write(Msg(seq))
        seq += 1
    rec.write(Msg(seq))
    rec.close()
    (_, first), = rec.rotated()
    assert failed_at + 100 <= first.stat().st_size < failed_at + 100 + 80  # a tenth of 1000 bytes, then one line
    assert seqs(first) + seqs(path) == list(range(seq + 1))



def test_a_recording_whose_file_or_folder_is_removed_goes_on_in_a_new_one(tmp_path, monkeypatch, caplog):
    """An operator clears the recordings folder while fuse_track runs: the next line notices (rotating or not; before,
    every line went into the removed file, unread and uncounted) and starts a new file in the folder made again. A
    rotation that cannot list its folder is counted and logged like a failed rename, not raised out of write (which
    would end fuse_track), and tried again later."""
    import shutil

    folder = tmp_path / "records"
    path = folder / "tracks.jsonl"
    line = len(json.dumps({"site": "s", "seq": 0, "t_ns": 0, "tracker": "tracker-1", "tracks": [{"id": 0}]})) + 1
    rec = Recorder(path, rotate_bytes=3 * line, keep=2)
    rec.write(Msg(0))
    shutil.rmtree(folder)
    for seq in range(1, 9):
        rec.write(Msg(seq))
    rec.close()
    assert rec.rotation_failed == 0 and rec.failed == 0
    assert "the file was removed or renamed away; recording goes on in a new file" in caplog.text
    assert [seqs(p) for _, p in rec.rotated()] + [seqs(path)] == [[1, 2, 3], [4, 5, 6], [7, 8]]
    plain = tmp_path / "plain" / "tracks.jsonl"  # no rotation
    rec = Recorder(plain)
    rec.write(Msg(0))
    shutil.rmtree(plain.parent)
    rec.write(Msg(1))
    plain.unlink()  # the file alone
    rec.write(Msg(2))
    rec.close()
    assert seqs(plain) == [2] and rec.failed == 0

    path = tmp_path / "unreadable" / "tracks.jsonl"
    rec = Recorder(path, rotate_bytes=3 * line)
    real_iterdir = Path.iterdir
    fails = iter([True])

    def iterdir(self: Path):
        if next(fails, False):
            raise PermissionError(13, "Permission denied")
        return real_iterdir(self)

    monkeypatch.setattr(Path, "iterdir", iterdir)
    for seq in range(3):
        rec.write(Msg(seq))
    assert rec.rotation_failed == 1 and rec.rotated() == [] and seqs(path) == [0, 1, 2]
    assert "rotation failed (Permission denied); recording goes on in the same file" in caplog.text
    rec.write(Msg(3))  # a tenth of the size later: rotated
    rec.close()
    assert [seqs(p) for _, p in rec.rotated()] + [seqs(path)] == [[0, 1, 2, 3], []]

def test_the_rotation_settings_are_checked():
    from pydantic import ValidationError

    from shared.settings import FuseTrackSettings

    assert FuseTrackSettings(record_rotate_mb=0.5, record_keep=3).record_keep == 3
    for bad in ({"record_rotate_mb": -1}, {"record_keep": -2}, {"record_rotate_mb": float("nan")}):
        with pytest.raises(ValidationError):
            FuseTrackSettings(**bad)


def test_a_removed_recording_that_cannot_be_made_again_counts_its_lines_and_a_link_count_of_0_alone_is_not_removal(
        tmp_path, monkeypatch, caplog):
    """A folder that cannot be made again (a file now stands in its place): each line counted as not recorded, the
    reason and the first loss logged, not a line each; and a file system that reports no links for a file its path
    still names (some do) is not taken for a removal at every line."""
    import os
    import shutil

    path = tmp_path / "records" / "tracks.jsonl"
    rec = Recorder(path)
    rec.write(Msg(0))
    shutil.rmtree(path.parent)
    path.parent.write_text("not a folder")
    for seq in range(1, 6):
        rec.write(Msg(seq))
    assert rec.failed == 5 and caplog.text.count("cannot be made again") == 2  # why, and the first line lost
    path.parent.unlink()
    rec.write(Msg(6))  # the folder can be made again: recording goes on
    rec.close()
    assert seqs(path) == [6] and rec.failed == 5

    caplog.clear()
    path = tmp_path / "nfs" / "tracks.jsonl"
    rec = Recorder(path)
    real_fstat = os.fstat

    def no_links(fd):
        st = real_fstat(fd)
        return os.stat_result((st.st_mode, st.st_ino, st.st_dev, 0, *tuple(st)[4:]))

    monkeypatch.setattr(os, "fstat", no_links)
    for seq in range(5):
        rec.write(Msg(seq))
    rec.close()
    assert seqs(path) == [0, 1, 2, 3, 4] and "removed" not in caplog.text
