"""The tracks recording: one JSON line per Tracks message, appended to `fuse_track.record`.

Each line is flushed as it is written, so a kill loses nothing written before it. A write that fails (disk full,
file too large) is counted (`failed`) and logged (the first, then every 100th, and when writing works again), the
half-written line cut off, and live tracking goes on; a file left ending in half a line (a process killed
mid-write) has that half line cut off when it is opened again, so every line in it parses.

A cabinet records for weeks (the demo's four cameras write about 4 MB a minute), so the file can be rotated
(`fuse_track.record_rotate_mb`): once it reaches that size it is closed and renamed `<stem>.<n>.jsonl` beside
it, numbered up from the highest number there (names sort oldest first), and a new file starts. Every line holds
the whole current Tracks message, so each file reads on its own. With `fuse_track.record_keep` only that many
rotated files are kept: the oldest beyond it are deleted. A listing, rename or delete that fails is logged and
counted, and recording goes on in the file it has (a failed rotation is tried again when the file has grown another
tenth). When the file or its folder has gone (an operator clearing the recordings; checked before each line,
rotating or not), the folder is made again and a new file started in it.
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path

from shared.messages import Tracks

log = logging.getLogger("roadside.fuse_track")


class Recorder:
    """Appends Tracks messages to `path` (nothing when None), rotating it at `rotate_bytes` (0: never) and keeping
    the newest `keep` rotated files (0: all)."""

    def __init__(self, path: Path | None, rotate_bytes: int = 0, keep: int = 0) -> None:
        self.file = None
        self.size = 0  # bytes in the file: where its next line starts
        self.path = path
        self.rotate_bytes = rotate_bytes
        self.keep = keep
        self.next_rotation = rotate_bytes  # the size at which the file is rotated next
        self.failed = 0  # Tracks messages not recorded
        self.failing = False  # the last write failed
        self.rotation_failed = 0  # renames and deletes that failed (the lines stay in the file they were in)
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                self.file = path.open("ab", buffering=0)  # no buffer that a failed write could leave bytes in
                self.size = self._cut_partial_line()
            except OSError as exc:
                raise ValueError(f"cannot write the tracks recording {path}: {exc.strerror or exc}") from None

    def _cut_partial_line(self) -> int:
        """Cut the file back to its last complete line (scanning back from the end a chunk at a time); its size."""
        end = keep = self.file.seek(0, 2)
        with self.path.open("rb") as f:
            while keep > 0:
                start = max(0, keep - 65536)
                f.seek(start)
                nl = f.read(keep - start).rfind(b"\n")
                if nl >= 0:
                    keep = start + nl + 1
                    break
                keep = start
        if keep < end:
            log.warning("%s ended in half a line (%d bytes, a write cut off): removed", self.path, end - keep)
            self.file.truncate(keep)
        return keep

    def write(self, msg: Tracks) -> None:
        if self.file is None:
            return
        line = (json.dumps({"site": msg.site, "seq": msg.seq, "t_ns": msg.t_capture_ns, "tracker": msg.tracker,
                            "tracks": msg.rows()}) + "\n").encode()
        # its lines would go where no one reads them
        if self._removed() and not self._reopen("the file was removed or renamed away"):
            self._lost(msg.seq, "its file was removed and cannot be made again")
            return
        try:
            view = memoryview(line)
            while view:  # a write may take part of the line (a disk filling up), the next one then fails
                view = view[self.file.write(view):]
        except OSError as exc:
            self._lost(msg.seq, exc.strerror or str(exc))
            try:
                self.file.truncate(self.size)  # the part written, cut off: the next line starts a line
            except OSError:
                pass
            return
        self.size += len(line)
        if self.failing:
            self.failing = False
            log.warning("tracks recording %s: recording again from Tracks seq %d (%d lost so far)", self.path,
                        msg.seq, self.failed)
        if self.rotate_bytes and self.size >= self.next_rotation:
            self._rotate()

    def _lost(self, seq: int, why: str) -> None:
        """A Tracks message not recorded: counted, logged the first time and every 100th (a full disk fails every
        line)."""
        self.failed += 1
        self.failing = True
        if self.failed == 1 or self.failed % 100 == 0:
            log.error("tracks recording %s: Tracks seq %d not recorded (%s; %d lost so far); tracking goes on",
                      self.path, seq, why, self.failed)

    def rotated(self) -> list[tuple[int, Path]]:
        """The rotated files beside the recording with their numbers, oldest first."""
        pattern = re.compile(re.escape(self.path.stem) + r"\.(\d+)" + re.escape(self.path.suffix) + "$")
        return sorted((int(m.group(1)), p) for p in self.path.parent.iterdir() if (m := pattern.match(p.name)))

    def _rotate(self) -> None:
        target = None
        try:
            old = self.rotated()  # fails too when the folder has gone or cannot be read
            target = self.path.with_name(f"{self.path.stem}.{old[-1][0] + 1 if old else 1:06d}{self.path.suffix}")
            self.path.rename(target)  # the open file keeps its lines under the new name
            try:
                new = self.path.open("ab", buffering=0)
            except OSError:
                target.rename(self.path)  # back as it was: the lines go on into the file they were in
                raise
        except OSError as exc:
            self.rotation_failed += 1
            self.next_rotation = self.size + self.rotate_bytes // 10  # not again at every line
            # (a folder that has gone is made again at the next line: write's check)
            log.error("tracks recording %s: rotation%s failed (%s); recording goes on in the same file", self.path,
                      f" to {target.name}" if target is not None else "", exc.strerror or exc)
            return
        self.close()
        log.info("tracks recording %s: %s closed at %d bytes", self.path, target.name, self.size)
        self.file, self.size = new, new.seek(0, 2)  # empty: the old one was renamed away
        self.next_rotation = self.rotate_bytes
        if self.keep:
            for _, path in [*old, (0, target)][:-self.keep]:
                try:
                    path.unlink()
                except OSError as exc:
                    self.rotation_failed += 1
                    log.error("tracks recording %s: cannot delete the old %s (%s)", self.path, path.name,
                              exc.strerror or exc)

    def _removed(self) -> bool:
        """Whether the open file has been removed (no name left: an operator cleared the file or its folder). Where a
        file system reports no links for a file that has them, the path still naming the open file says it is not."""
        try:
            here = os.fstat(self.file.fileno())
            if here.st_nlink > 0:
                return False
            there = os.stat(self.path)
        except (FileNotFoundError, NotADirectoryError):  # no such path any more
            return True
        except OSError:
            return False
        return (here.st_dev, here.st_ino) != (there.st_dev, there.st_ino)

    def _reopen(self, why: str) -> bool:
        """The recording's file or folder has gone (its lines with it): the folder made again, a new file started;
        False when that fails (tried again at the next line)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            new = self.path.open("ab", buffering=0)
        except OSError as exc:
            if not self.failing:  # once until a line is recorded again
                log.error("tracks recording %s: %s and cannot be made again (%s); tried again at each line",
                          self.path, why, exc.strerror or exc)
            return False
        self.close()
        self.file, self.size = new, new.seek(0, 2)
        self.next_rotation = self.rotate_bytes
        log.warning("tracks recording %s: %s; recording goes on in a new file", self.path, why)
        return True

    def close(self) -> None:
        if self.file is not None:
            try:
                self.file.close()
            except OSError as exc:
                log.error("tracks recording %s: closing failed (%s)", self.path, exc.strerror or exc)
