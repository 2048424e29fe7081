"""Frame sources for ingest: where images come from and when they were captured.

Every source yields `SourceFrame`s in capture-time order (merged over its cameras):
- `RecordingSource`: a simulator recording (docs/recording-format.md); capture time from the file name.
- `ImageFolderSource`: one folder of images per camera; capture time from each file name — integer
  nanoseconds, microseconds or milliseconds since the epoch (19, 16 or 13 digits: `1718218800000000000.jpg`,
  from 2000 on) or a date and time (`2023-12-19 11-00-00-034395.jpg`, as in the real State/Ellsworth footage;
  in the time zone `ingest.timezone` names, UTC by default) — or, when names carry no time, from a frame rate,
  the files in the order of their names with numbers compared as numbers (`frame2.png` before `frame10.png`).
  Hidden files (a name starting with "."; macOS's `._<name>` AppleDouble files beside each image) are not frames.
- `VideoSource`: a video file or an RTSP/HTTP stream through OpenCV; capture time from the stream's
  position (files) or the wall clock at grab (live streams).

Sources do not decode images they do not have to: a JPEG file is handed on as bytes and decoded (or
passed through) by ingest.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, tzinfo
from pathlib import Path

import cv2
import numpy as np

from shared.messages import T_CAPTURE_END

# a live camera's stream: reopened when it drops (a file:// URL or a finite video over HTTP ends)
STREAM_SCHEMES = ("rtsp", "rtsps", "rtmp", "udp", "tcp", "srt", "http", "https")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
EPOCH_DIGITS = {19: 1, 16: 1_000, 13: 1_000_000}  # a name of so many digits: ns, us or ms since the epoch
T_NAME_MIN = 946_684_800 * 10**9  # 2000-01-01: a number in a name below it is a frame counter, not a time
DATETIME_RE = re.compile(r"(\d{4})-(\d{2})-(\d{2})[ _T](\d{2})[-:_](\d{2})[-:_](\d{2})(?:[-._](\d{1,9}))?")
# cameras played together whose frames lie further apart than this from every other camera's (the gap between
# their spans of capture times) do not share a clock: a video file's frames timed from when it is opened beside dated
# file names, a folder named in another time zone (whole hours off). Footage of one site is recorded together; a
# camera that starts late, or stops early, still overlaps the others and plays (the others alone meanwhile); past
# this the pipeline would play one camera alone for that long at pace 1, or hang for years.
SPANS_APART_MAX_NS = 10 * 60 * 10**9


@dataclass
class SourceFrame:
    """One captured image: `jpeg` bytes (files) or a decoded `image` (video), never both; or `error`, why a file
    could not be read (ingest counts it as bad input and goes on)."""

    camera: str
    t_capture_ns: int
    jpeg: bytes | None = None
    image: np.ndarray | None = None
    origin: str = ""  # file name or stream position, for error messages
    error: str = ""


def capture_time_from_name(name: str, tz: tzinfo = UTC) -> int | None:
    """Capture time (ns since the epoch) from a file name, None when it carries none or one outside the times a
    message may carry (1970 to 2116, `shared.messages.T_CAPTURE_END`; a number of digits since the epoch from 2000
    on: a zero-padded frame counter is no time)."""
    stem = Path(name).stem
    if stem.isdigit():
        t = int(stem) * EPOCH_DIGITS.get(len(stem), 0)
        return t if T_NAME_MIN <= t < T_CAPTURE_END else None
    m = DATETIME_RE.search(stem)
    if m is None:
        return None
    y, mo, d, h, mi, s, frac = m.groups()
    try:
        dt = datetime(int(y), int(mo), int(d), int(h), int(mi), int(s), tzinfo=tz)
    except ValueError:
        return None
    ns = int((frac or "0").ljust(9, "0")[:9])
    t = int(dt.timestamp()) * 1_000_000_000 + ns
    return t if 0 <= t < T_CAPTURE_END else None


def _read(camera: str, t_ns: int, path: Path) -> SourceFrame:
    """A file's frame; one that cannot be read (gone, a dangling link, no permission) carries the reason."""
    try:
        return SourceFrame(camera, t_ns, jpeg=path.read_bytes(), origin=str(path))
    except OSError as exc:
        return SourceFrame(camera, t_ns, origin=str(path), error=f"camera {camera}: cannot read {path}: {exc}")


def image_files(folder: Path) -> list[Path]:
    """The image files of a folder, in no order: not hidden files (a name starting with "."; macOS's `._<name>`
    AppleDouble files copied beside each image), sub-folders or pipes; a dangling link is kept (reported as
    unreadable when it is read)."""
    return [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
            and (p.is_file() or (p.is_symlink() and not p.exists()))]


def check_time_spans(spans: dict[str, tuple[int, int]]) -> None:
    """ValueError naming the camera and the spans when a camera's frames (first, last capture time, ns since the
    epoch, by camera) lie further than `SPANS_APART_MAX_NS` from every other camera's: their clocks differ, and
    fuse_track, putting frames of one time into one tick, would wait for the other cameras for as long."""
    if len(spans) < 2:
        return

    def gap(a: tuple[int, int], b: tuple[int, int]) -> int:
        return max(0, max(a[0], b[0]) - min(a[1], b[1]))

    for cam, span in spans.items():
        apart_ns = min(gap(span, other) for c, other in spans.items() if c != cam)
        if apart_ns <= SPANS_APART_MAX_NS:
            continue
        apart_s = apart_ns / 1e9
        apart = f"{apart_s / 86400:.1f} days" if apart_s >= 86400 else f"{apart_s / 3600:.1f} h" if apart_s >= 3600 \
            else f"{apart_s / 60:.0f} min"

        def when(t: int) -> str:
            return datetime.fromtimestamp(t / 1e9, UTC).isoformat(timespec="seconds")

        each = ", ".join(f"{c} {when(a)} to {when(b)}" for c, (a, b) in sorted(spans.items(), key=lambda kv: kv[1]))
        raise ValueError(f"camera {cam}'s frames lie {apart} from every other camera's ({each}; at most "
                         f"{SPANS_APART_MAX_NS // 60 // 10**9} min): their clocks differ (a video file is timed from "
                         "when it is opened, file names by their own clock and time zone), so fuse_track could not put "
                         "their frames in one tick; play cameras recorded together, with times in one clock")


def _natural(path: Path) -> list:
    """A sort key for file names with numbers compared as numbers: frame2 before frame10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _merge(streams: dict[str, list[tuple[int, Path]]]) -> list[tuple[int, str, Path]]:
    return sorted((t, cam, p) for cam, items in streams.items() for t, p in items)


class RecordingSource:
    """Frames of a simulator recording, all or some of its cameras."""

    def __init__(self, path: str | Path, cameras: list[str] | None = None) -> None:
        from sim.recording import Recording

        self.recording = Recording(path)
        names = cameras or self.recording.camera_names
        streams = {c: self.recording.frames(c) for c in names}
        empty = [c for c, items in streams.items() if not items]
        if empty:
            raise ValueError(f"recording {path} has no frames for camera{'s' * (len(empty) > 1)} {', '.join(empty)}")
        self.items = _merge(streams)

    def __iter__(self) -> Iterator[SourceFrame]:
        for t, cam, p in self.items:
            yield _read(cam, t, p)


class ImageFolderSource:
    """Image sequences, one folder per camera: {camera: folder}."""

    def __init__(self, folders: dict[str, str | Path], fps: float | None = None, tz: tzinfo = UTC,
                 start_ns: int | None = None) -> None:
        self.timed_by_clock = False
        streams: dict[str, list[tuple[int, Path]]] = {}
        for cam, folder in folders.items():
            folder = Path(folder)
            if not folder.is_dir():
                raise ValueError(f"camera {cam}: image folder not found: {folder}")
            files = sorted(image_files(folder))
            if not files:
                raise ValueError(f"camera {cam}: no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
            times = [capture_time_from_name(p.name, tz) for p in files]
            if None in times and any(t is not None for t in times):
                # a frame rate times a folder whose names carry none; with it here, one stray name would replace the
                # others' real times with wall-clock ones, years away from the other cameras'
                bad = files[times.index(None)].name
                raise ValueError(f"camera {cam}: no capture time (or one outside 1970-2116) in file name {bad!r} "
                                 f"while other names in {folder} carry one; move it out of the folder")
            if None in times:
                if fps is None:
                    raise ValueError(f"camera {cam}: no capture time (or one outside 1970-2116) in file name "
                                     f"{files[0].name!r}; give a frame rate (fps)")
                t0 = time.time_ns() if start_ns is None else start_ns
                self.timed_by_clock = True  # from when it is opened (`fps`): no slice of capture time applies
                files = sorted(files, key=_natural)
                times = [t0 + round(i * 1e9 / fps) for i in range(len(files))]
            streams[cam] = sorted(zip(times, files, strict=True))
        check_time_spans({cam: (items[0][0], items[-1][0]) for cam, items in streams.items()})
        self.items = _merge(streams)

    def __iter__(self) -> Iterator[SourceFrame]:
        for t, cam, p in self.items:
            yield _read(cam, t, p)


class VideoSource:
    """A video file or a live stream (rtsp://, http://...) of one camera, through OpenCV. A live stream that drops, or
    that cannot be opened at start (a camera not up yet when the cabinet boots), is opened again, every `RECONNECT_S`
    seconds doubling up to `RECONNECT_MAX_S`, for as long as ingest runs; each failed attempt yields a frame carrying
    the reason (ingest counts and logs it), so a camera that goes down is reported and comes back by itself instead
    of ending the playback. A stream's open and each of its reads give up after `STREAM_TIMEOUT_MS` (OpenCV's own
    wait, for a camera that takes the connection and never answers, is 30 s), and the wait between attempts ends
    when `stop` (ingest's `Stopper.event`) is set, which ends the frames: a stop during a reconnect takes no longer
    than one such timeout."""

    RECONNECT_S = 0.5
    RECONNECT_MAX_S = 5.0
    STREAM_TIMEOUT_MS = 3000

    def __init__(self, url: str, camera: str, fps: float | None = None, stop: threading.Event | None = None) -> None:
        self.url, self.camera, self.stop = url, camera, stop
        self.live = url.split("://")[0].lower() in STREAM_SCHEMES if "://" in url else False
        if "://" not in url and not Path(url).is_file():
            raise ValueError(f"camera {camera}: video file not found: {url}")
        self.cap = self._open()
        if not self.cap.isOpened() and not self.live:  # a live camera that is down is reported as it is read
            raise ValueError(f"camera {camera}: OpenCV cannot open {url}")
        self.fps = fps or self.cap.get(cv2.CAP_PROP_FPS) or 10.0
        if self.live and url.lower().startswith(("http://", "https://")) and self.cap.get(cv2.CAP_PROP_FRAME_COUNT) > 0:
            self.live = False  # a video file served over HTTP: it ends, it is not reopened (one down at start: live)
        self.t0_ns = time.time_ns()

    def _open(self) -> cv2.VideoCapture:
        if not self.live:
            return cv2.VideoCapture(self.url)
        return cv2.VideoCapture(self.url, cv2.CAP_FFMPEG, [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self.STREAM_TIMEOUT_MS,
                                                           cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.STREAM_TIMEOUT_MS])

    def _wait(self, seconds: float) -> bool:
        """Wait before opening a stream again; True when told to stop meanwhile."""
        if self.stop is None:
            time.sleep(seconds)
            return False
        return self.stop.wait(seconds)

    def __iter__(self) -> Iterator[SourceFrame]:
        n = 0
        wait_s = self.RECONNECT_S
        if not self.cap.isOpened() and not self.live:  # played before (ingest.loop): from the start again
            self.cap = self._open()
            if not self.cap.isOpened():
                yield SourceFrame(self.camera, self.t0_ns, origin=self.url,
                                  error=f"camera {self.camera}: OpenCV cannot open {self.url} again")
                return
        while True:
            ok, img = self.cap.read()
            if not ok:
                if not self.live:
                    break
                why = (f"stream {self.url} lost; opening it again" if self.cap.isOpened()
                       else f"cannot open stream {self.url}; trying again")
                yield SourceFrame(self.camera, time.time_ns(), origin=self.url,
                                  error=f"camera {self.camera}: {why} in {wait_s:g} s")
                self.cap.release()
                if self._wait(wait_s):
                    break
                wait_s = min(2 * wait_s, self.RECONNECT_MAX_S)
                self.cap = self._open()  # a failed open fails the next read: the wait doubles
                continue
            wait_s = self.RECONNECT_S
            if self.live:
                t = time.time_ns()
            else:
                t = self.t0_ns + round(n * 1e9 / self.fps)
            yield SourceFrame(self.camera, t, image=img, origin=f"{self.url}#{n}")
            n += 1
        self.cap.release()


def _time_spans(source) -> dict[str, tuple[int, int]]:
    """Each camera's first and last capture time in a source of recorded frames (a video file: from when it was
    opened, for as long as its frames last at its frame rate)."""
    items = getattr(source, "items", None)
    if items is None:
        frames = max(int(source.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 1)
        return {source.camera: (source.t0_ns, source.t0_ns + round((frames - 1) * 1e9 / source.fps))}
    spans: dict[str, tuple[int, int]] = {}
    for t, cam, _ in items:  # in time order
        spans[cam] = (spans.get(cam, (t, t))[0], t)
    return spans


def open_source(source: str, cameras: list[str], camera_sources: dict[str, str | None],
                fps: float | None = None, tz: tzinfo = UTC, stop: threading.Event | None = None
                ) -> RecordingSource | ImageFolderSource | VideoSource | MergedSource:
    """The source a site's settings describe (`tz`: the time zone of date-time file names; `stop`: ingest's
    `Stopper.event`, which ends a live stream's wait to reconnect).

    `source` is a simulator recording, a folder of per-camera image folders (matched to camera names:
    the sub-folder named `<camera>`, in any case, else the one whose name ends with `_<camera>`; sub-folders named
    `.*` or `@*`, a NAS's or a file browser's, are not cameras'), one image folder (one that holds images, for one
    camera, even beside sub-folders), a video file or a stream URL. `camera_sources` (camera -> its own source) take
    precedence; live streams and recorded frames are not mixed, nor recorded cameras whose frames lie more than
    `SPANS_APART_MAX_NS` from every other camera's (their clocks differ: ValueError).
    """
    own = {c: s for c, s in camera_sources.items() if s}
    if own:
        rest = [c for c in cameras if c not in own]
        if rest and not source:
            raise ValueError(f"no source for camera{'s' * (len(rest) > 1)} {', '.join(rest)}: give each camera its "
                             "own source, or ingest.source for the cameras without one")
        parts = [open_source(s, [c], {}, fps, tz, stop) for c, s in own.items()]
        if rest:
            parts.append(open_source(source, rest, {}, fps, tz, stop))
        live = [p for p in parts if getattr(p, "live", False)]
        if live and len(live) < len(parts):
            raise ValueError(f"camera{'s' * (len(live) > 1)} {', '.join(p.camera for p in live)} stream live (the "
                             "wall clock) and the others play recorded frames (their own capture times): the two do "
                             "not share a clock, so fuse_track could not put them in one tick; give every camera a "
                             "live stream, or play them all from recordings")
        if not live:
            check_time_spans({cam: span for p in parts for cam, span in _time_spans(p).items()})
        return parts[0] if len(parts) == 1 else MergedSource(parts, stop)
    if not source:
        raise ValueError("no source: set ingest.source in the site file or pass --source")
    if "://" in source:
        if len(cameras) != 1:
            raise ValueError(f"a stream URL feeds one camera; give each camera its own source ({cameras})")
        return VideoSource(source, cameras[0], fps, stop)
    path = Path(source).expanduser()
    if not path.exists():
        raise ValueError(f"source not found: {path}")
    if path.is_file():
        if len(cameras) != 1:
            raise ValueError(f"a video file feeds one camera; give each camera its own source ({cameras})")
        return VideoSource(str(path), cameras[0], fps, stop)
    if (path / "recording.json").is_file():
        return RecordingSource(path, cameras)
    subdirs = {p.name: p for p in path.iterdir() if p.is_dir() and not p.name.startswith((".", "@"))}

    def matching(cam: str) -> list[Path]:
        return ([p for n, p in subdirs.items() if n == cam]  # NE beside T_NE: NE's folder is NE
                or [p for n, p in subdirs.items() if n.lower() == cam.lower()]
                or [p for n, p in subdirs.items() if n.endswith("_" + cam)])

    # one camera's images, beside other sub-folders (a thumbnails folder): the folder itself, unless a sub-folder is
    # the camera's (a parent of camera folders holding a stray map or preview image at its top)
    if not subdirs or (len(cameras) == 1 and image_files(path) and not matching(cameras[0])):
        if len(cameras) != 1:
            raise ValueError(f"{path} holds images of one camera; the site has {len(cameras)} cameras")
        return ImageFolderSource({cameras[0]: path}, fps, tz)
    folders, wrong = {}, []
    for cam in cameras:
        match = matching(cam)
        if len(match) != 1:
            wrong.append(f"camera {cam}: expected one sub-folder of {path} named {cam} (in any case) or *_{cam}, found "
                         f"{sorted(p.name for p in match) or 'none'}")
        else:
            folders[cam] = match[0]
    if wrong:  # every camera without its folder at once; a camera's own cameras[].source is the other way
        raise ValueError(f"{'; '.join(wrong)} among {sorted(subdirs)} (or give such a camera its own "
                         "cameras[].source)")
    return ImageFolderSource(folders, fps, tz)


class MergedSource:
    """Several sources merged in capture-time order; live streams in the order their frames arrive, each read in
    its own thread, so that one camera that stalls or reconnects does not hold up the others (until `stop` is set).
    `items`, as a single source's, when every part has them (recorded files: a restart resumes after fuse_track's
    latest tracks), else None."""

    def __init__(self, parts: list, stop: threading.Event | None = None) -> None:
        self.parts, self.stop = parts, stop
        items = [getattr(p, "items", None) for p in parts]
        self.items = sorted(i for part in items for i in part) if all(items) else None

    def __iter__(self) -> Iterator[SourceFrame]:
        if all(getattr(p, "live", False) for p in self.parts):
            yield from self._arrivals()
            return
        import heapq

        iters = [iter(p) for p in self.parts]
        heap = []
        for i, it in enumerate(iters):
            f = next(it, None)
            if f is not None:
                heap.append((f.t_capture_ns, i, f))
        heapq.heapify(heap)
        while heap:
            _, i, f = heapq.heappop(heap)
            yield f
            nxt = next(iters[i], None)
            if nxt is not None:
                heapq.heappush(heap, (nxt.t_capture_ns, i, nxt))

    def _arrivals(self) -> Iterator[SourceFrame]:
        import queue

        frames: queue.Queue = queue.Queue(maxsize=8 * len(self.parts))
        ended = object()

        def pump(part) -> None:
            try:
                for f in part:
                    frames.put(f)
            finally:
                frames.put(ended)

        for part in self.parts:  # daemons: ingest stops by leaving this generator, and they end with the process
            threading.Thread(target=pump, args=(part,), daemon=True, name="stream").start()
        running = len(self.parts)
        while running and not (self.stop is not None and self.stop.is_set()):
            try:
                f = frames.get(timeout=0.1)  # not for ever: a stop ends the frames while a camera reconnects
            except queue.Empty:
                continue
            if f is ended:
                running -= 1
                continue
            yield f
