"""Recording the cameras as ingest plays them (`ingest.record_dir`): a folder that ingest plays back.

Each frame ingest publishes is also written, at the source's full resolution and with the capture time it was
published with, to `<record_dir>/<camera>/<t_capture_ns>.<jpg|png|bmp>` (19 digits: nanoseconds since the epoch, the
image-folder naming `services.ingest.sources.capture_time_from_name` reads). A JPEG file from the source is written
as it is, byte for byte; an image decoded from a video file or a live stream (RTSP, HTTP) is encoded as a JPEG of
`jpeg_quality`. So `roadside up --source <record_dir>` plays a cabinet's cameras again as the pipeline saw them, at
their capture times, and a researcher can take a day's footage home.

The writing never holds up the pipeline: frames wait in a queue bounded in bytes, written by a thread of their own;
when the disk is slower than the cameras the newest frames that do not fit are dropped and counted. Nothing already
recorded is lost: a frame whose file exists (ingest restarted, or the same source recorded into the folder twice) is
not written again; each file is written under a hidden name first (`.<name>.part`, which playback skips) and renamed
when whole, so a crash of the process or a full disk leaves no half image under a name playback reads (files are not
synced to the disk one by one: a power cut may lose the last seconds). Below `min_free_mb` of free space the
recording pauses (frames counted as `no_space`) and goes on by itself once space is freed, camera folders deleted to
free it made again. A frame that cannot be written (no permission, an I/O error) is counted and logged, and the next
is tried. One frame larger than the whole queue is taken when the queue is empty.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import shutil
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger("roadside.ingest.recorder")
NAME_MIN_NS = 10**18  # 2001-09-09: an earlier capture time has fewer than 19 digits, which playback would not read
SPACE_CHECK_S = 1.0  # how often the free space is looked at (a syscall per frame would cost the writer little, but
# nothing is gained by it)
ABANDON_WAIT_S = 5.0  # after close()'s timeout: for the frame being written to end (the rest is dropped at once)
MAGIC = ((b"\xff\xd8", ".jpg"), (b"\x89PNG\r\n\x1a\n", ".png"), (b"BM", ".bmp"))


@dataclass(frozen=True)
class RecorderConfig:
    """`folder`: where the camera folders go; `jpeg_quality`: 1-100, for images decoded from a video or stream;
    `queue_mb`: frames waiting to be written, at most (MB); `min_free_mb`: the free space below which recording
    pauses (MB)."""

    folder: Path
    jpeg_quality: int = 92
    queue_mb: float = 24.0
    min_free_mb: float = 1024.0

    def __post_init__(self) -> None:
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 1-100, got {self.jpeg_quality!r}")
        if not self.queue_mb > 0:
            raise ValueError(f"queue_mb must be > 0, got {self.queue_mb!r}")
        if not self.min_free_mb >= 0:
            raise ValueError(f"min_free_mb must be >= 0, got {self.min_free_mb!r}")


def check_not_the_source(folder: Path, source: str | None) -> None:
    """ValueError when the recording's folder is the folder being played, inside it or holds it: every frame would
    be taken for one recorded before, or the playback would list the files the recording writes."""
    if not source or "://" in source:
        return
    src, rec = Path(source).expanduser().resolve(), folder.expanduser().resolve()
    if src.is_file():  # a video file: the recording's folder may hold it, or lie beside it
        return
    if src == rec or src in rec.parents or rec in src.parents:
        raise ValueError(f"ingest.record_dir {folder} and the source {source} overlap: record the cameras into a "
                         "folder of its own, outside the one being played")


class FrameRecorder:
    """Writes frames to a playable image-sequence folder from a thread of its own (module docstring).

    `put` never blocks; `close` writes what is queued (up to `timeout_s`) and stops the thread. The counters say what
    happened to every frame put: `written` (by camera), `dropped` (the queue was full), `no_space`, `duplicates`
    (its file existed), `errors` (by reason)."""

    def __init__(self, config: RecorderConfig) -> None:
        self.config = config
        self.folder = config.folder.expanduser()
        try:  # at start: a folder that cannot be made stops ingest at once, for good (exit 2, not restarted)
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"ingest.record_dir {self.folder}: cannot be made ({exc.strerror or exc})") from None
        self.written: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.dropped = self.no_space = self.duplicates = 0
        self._queue: queue.Queue = queue.Queue()
        self._queued_bytes = 0
        self._lock = threading.Lock()
        self._paused = False
        self._space_checked = -float("inf")
        self._closed = False
        self._abandon = False  # close() timed out: the writer drops what is left
        self._thread = threading.Thread(target=self._run, name="frame-recorder", daemon=True)
        self._thread.start()

    def put(self, camera: str, t_capture_ns: int, jpeg: bytes | None = None, image: np.ndarray | None = None) -> bool:
        """Queue one frame: the source's image file's bytes (`jpeg`: a JPEG, PNG or BMP file) or a decoded `image`
        (H, W) or (H, W, 3) uint8, BGR. False when it was dropped (the queue is full, or a capture time before
        2001-09-09, which no file name playback reads can carry) or the recorder is closed."""
        if (jpeg is None) == (image is None):
            raise ValueError("give the frame's file bytes or its decoded image, one of the two")
        if self._closed:
            return False
        if t_capture_ns < NAME_MIN_NS:
            self._error(f"capture time {t_capture_ns} ns is before 2001-09-09: no 19-digit file name for it")
            return False
        size = len(jpeg) if jpeg is not None else image.nbytes
        with self._lock:
            # one frame at least, however large (a 4K stream's decoded frame is 25 MB)
            if self._queued_bytes and self._queued_bytes + size > self.config.queue_mb * 1e6:
                self.dropped += 1
                if self.dropped == 1 or self.dropped % 100 == 0:
                    log.warning("recording %s: %d frames dropped so far, the disk is slower than the cameras (the "
                                "queue holds %.0f MB)", self.folder, self.dropped, self.config.queue_mb)
                return False
            self._queued_bytes += size
        self._queue.put((camera, int(t_capture_ns), jpeg, image, size))
        return True

    def counts(self) -> dict[str, float]:
        """A snapshot of the counters, for status reports: `recorded.<camera>`, `record_dropped`, `record_no_space`,
        `record_duplicates`, `record_errors` (read from another thread than the writer's)."""
        with self._lock:
            out = {f"recorded.{camera}": n for camera, n in self.written.items()}
            out.update(record_dropped=self.dropped, record_no_space=self.no_space, record_duplicates=self.duplicates,
                       record_errors=sum(self.errors.values()))
        return out

    @property
    def pending(self) -> int:
        """Frames queued and not yet written."""
        return self._queue.qsize()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued (for at most `timeout_s`), then stop; what is left is counted as dropped. Once."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join(timeout_s)
        if self._thread.is_alive():  # the rest is dropped, counted by the writer (the frame it writes now is written)
            self._abandon = True
            before = self.dropped
            self._thread.join(ABANDON_WAIT_S)
            log.warning("recording %s: %d frames not written within %.0f s of the end", self.folder,
                        self.dropped - before, timeout_s)
        log.info("recording %s: %s", self.folder, self.summary())

    def summary(self) -> str:
        cams = ", ".join(f"{c} {n}" for c, n in sorted(self.written.items())) or "none"
        return (f"{sum(self.written.values())} frames written ({cams}), {self.dropped} dropped, {self.no_space} "
                f"without disk space, {self.duplicates} already there, {sum(self.errors.values())} not writable")

    # --- the writer thread ------------------------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            camera, t_ns, data, image, size = item
            if self._abandon:
                with self._lock:
                    self.dropped += 1
                    self._queued_bytes -= size
                continue
            try:
                self._write(camera, t_ns, data, image)
            except Exception as exc:  # one frame's failure must not end the recording
                self._error(f"camera {camera}: {type(exc).__name__}: {exc}")
            finally:
                with self._lock:
                    self._queued_bytes -= size

    def _write(self, camera: str, t_ns: int, data: bytes | None, image: np.ndarray | None) -> None:
        if not self._space_left():
            with self._lock:
                self.no_space += 1
            return
        if data is not None:
            suffix = next((s for magic, s in MAGIC if data.startswith(magic)), None)
            if suffix is None:
                raise ValueError("not a JPEG, PNG or BMP file")
        else:
            suffix = ".jpg"
            ok, buf = cv2.imencode(suffix, image, [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
            if not ok:
                raise ValueError(f"OpenCV could not encode a {image.shape} {image.dtype} image")
            data = buf.tobytes()
        folder = self.folder / camera
        folder.mkdir(parents=True, exist_ok=True)  # every time: a folder deleted to free space is made again
        path = folder / f"{t_ns}{suffix}"
        if any((folder / f"{t_ns}{s}").exists() for _, s in MAGIC):  # recorded before: never written over
            with self._lock:
                self.duplicates += 1
            return
        part = folder / f".{path.name}.part"
        try:
            part.write_bytes(data)
            os.replace(part, path)
        except OSError:
            part.unlink(missing_ok=True)
            raise
        with self._lock:
            self.written[camera] += 1

    def _space_left(self) -> bool:
        now = time.monotonic()
        if now - self._space_checked < SPACE_CHECK_S:
            return not self._paused
        self._space_checked = now
        where = next(p for p in (self.folder, *self.folder.parents) if p.exists())  # the folder may have been deleted
        free_mb = shutil.disk_usage(where).free / 1e6
        paused = free_mb < self.config.min_free_mb
        if paused != self._paused:
            if paused:
                log.warning("recording %s paused: %.0f MB free, under ingest.record_min_free_mb %.0f MB; it goes on "
                            "when space is freed", self.folder, free_mb, self.config.min_free_mb)
            else:
                log.info("recording %s goes on: %.0f MB free", self.folder, free_mb)
            self._paused = paused
        return not paused

    def _error(self, reason: str) -> None:
        key = re.sub(r"\d+", "#", reason)[:160]  # reasons that differ in their numbers count as one
        with self._lock:
            self.errors[key] += 1
            n = self.errors[key]
        if n == 1 or n % 100 == 0:
            log.warning("recording %s: frame not written (%d so far with this reason): %s", self.folder, n, reason)
