"""ingest's main() on a fake bus: a restart while looping goes on in the round fuse_track's tracks reached, capture
times never going back; at the source's end it exits (`roadside up`) or stays up idle (compose)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import ClassVar

import cv2
import numpy as np
import pytest
from test_movements import tracks_message

import services.ingest.__main__ as ingest
from shared.bus import Stopper
from shared.codec import decode, encode
from shared.messages import Frame
from shared.settings import load_settings

T0 = 1_700_000_000_000_000_000
S = 1_000_000_000


class _Bus:
    """What main() asks of a Zenoh session: publishers (frames kept, decoded) and fuse_track's latest tracks."""

    def __init__(self, latest_ns: int | None, stopper: Stopper, stop_after: int) -> None:
        self.frames: list[Frame] = []
        self.latest_ns, self.stopper, self.stop_after = latest_ns, stopper, stop_after

    def declare_publisher(self, key):
        return SimpleNamespace(put=self._put)

    def _put(self, payload: bytes) -> None:
        self.frames.append(decode(payload, Frame))
        if len(self.frames) >= self.stop_after:
            self.stopper.stop()

    def get(self, key, timeout):
        if self.latest_ns is None:
            return iter(())
        payload = encode(tracks_message(self.latest_ns, []))
        return iter([SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload)))])

    def close(self) -> None:
        pass


class _Status:
    """StatusReporter's part main() uses; each one made is kept, to see whether it was closed."""

    made: ClassVar[list[_Status]] = []

    def __init__(self, *args, **kwargs) -> None:
        self.closed = False
        _Status.made.append(self)

    def count(self, *args, **kwargs) -> None:
        pass

    def gauge(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A site of cameras A and B, each 5 frames 1 s apart from T0 in its own folder of a parent; main()'s bus faked."""
    for cam in "AB":
        (tmp_path / "frames" / cam).mkdir(parents=True)
        for i in range(5):
            cv2.imwrite(str(tmp_path / "frames" / cam / f"{T0 + i * S}.jpg"), np.full((48, 64), 90, np.uint8))
    (tmp_path / "site.yaml").write_text(
        "site: se\norigin: {lat_deg: 42.2, lon_deg: -83.7, alt_m: 265.0}\ncameras:\n"
        + "".join(f"  - {{name: {c}, kind: pinhole, width: 64, height: 48, masks: m.npz}}\n" for c in "AB"))
    monkeypatch.setattr(ingest, "declare_alive", lambda *a, **k: [])
    monkeypatch.setattr(ingest, "wait_for_peers", lambda *a, **k: 0)
    monkeypatch.setattr(ingest, "StatusReporter", _Status)
    _Status.made = []
    return tmp_path


def _bus(monkeypatch, latest_ns: int | None = None, stop_after: int = 10**9) -> _Bus:
    bus = _Bus(latest_ns, Stopper(install_signals=False), stop_after)
    monkeypatch.setattr(ingest, "open_session", lambda *a: bus)
    return bus


def _settings(site, **ingest_settings):
    return load_settings(site / "site.yaml", ingest={"source": str(site / "frames"), "pace": "1000", **ingest_settings})


def _play(site, monkeypatch, latest_ns=None, stop_after=10**9, **ingest_settings) -> tuple[int, _Bus]:
    bus = _bus(monkeypatch, latest_ns, stop_after)
    return ingest.main(_settings(site, **ingest_settings), bus.stopper), bus


def _times(bus, camera="A"):
    """Camera's capture times as published, in s after T0."""
    return [(f.t_capture_ns - T0) / S for f in bus.frames if f.camera == camera]


def test_a_restart_while_looping_goes_on_in_the_round_fuse_track_reached(site, monkeypatch):
    """Rounds 4.1 s apart (the source's 4 s and 0.1 s). Restarted at round 0's frame 2: the next round still starts
    4.1 s after the first; restarted in round 2 (fuse_track past the files' own times): after that round's frame."""
    rc, bus = _play(site, monkeypatch, latest_ns=T0 + 2 * S, stop_after=16, loop=True)
    assert rc == ingest.STOPPED and _times(bus) == [3.0, 4.0, 4.1, 5.1, 6.1, 7.1, 8.1, 8.2]
    rc, bus = _play(site, monkeypatch, latest_ns=T0 + 9_700_000_000, stop_after=8, loop=True)
    assert _times(bus) == [10.2, 11.2, 12.2, 12.3]
    source = ingest.open_source(str(site / "frames"), ["A", "B"], {})
    assert ingest.resume_point(bus, "se", source) is None  # not looping: past the files' times is another recording
    rc, bus = _play(site, monkeypatch, latest_ns=T0 + 2 * S)  # not looping: after the tracks, to the end
    assert rc == 0 and _times(bus) == [3.0, 4.0]


def test_looping_rounds_of_max_frames_are_spaced_by_what_they_play(site, monkeypatch):
    """ingest.max_frames with loop: each round plays its first 2 frames and the next starts 0.1 s after them (spaced by
    the whole source, as a restart's resume needs without max_frames, the rounds left most of their time empty: 3 s at
    pace 1 here, 57 s of every minute in a review's 60 s recording)."""
    rc, bus = _play(site, monkeypatch, stop_after=12, loop=True, max_frames=2)
    assert rc == ingest.STOPPED
    assert _times(bus) == [0.0, 1.0, 1.1, 2.1, 2.2, 3.2]


def test_at_the_end_of_its_source_ingest_exits_or_stays_up_idle_until_told_to_stop(site, monkeypatch):
    """`exit` (the default, `roadside up`): status 0; `idle` (compose, which would restart an exit for ever): up,
    reporting and publishing nothing more, until a stop, then at once."""
    rc, bus = _play(site, monkeypatch)
    assert rc == 0 and len(bus.frames) == 10 and _Status.made[-1].closed
    bus = _bus(monkeypatch)
    settings = _settings(site, at_end="idle")
    out = []
    thread = threading.Thread(target=lambda: out.append(ingest.main(settings, bus.stopper)), daemon=True)
    thread.start()
    time.sleep(1.5)
    assert thread.is_alive() and len(bus.frames) == 10 and not _Status.made[-1].closed  # still reporting
    t = time.monotonic()
    bus.stopper.stop()
    thread.join(5.0)
    assert not thread.is_alive() and time.monotonic() - t < 1.5
    assert out == [ingest.STOPPED] and _Status.made[-1].closed


def test_a_played_slice_loops_on_its_own_span_not_the_whole_source():
    """With ingest.play_from / play_until and `loop`, the rounds follow one another by the slice's span (at pace 1 the
    whole source's would leave the rest of it as idle time between rounds)."""
    from types import SimpleNamespace

    from services.ingest.__main__ import LOOP_GAP_NS, loop_period, play_window
    from shared.settings import IngestSettings

    s = 10**9
    t0 = 1_703_001_600 * s  # 2023-12-19 16:00:00 UTC

    def source() -> SimpleNamespace:
        return SimpleNamespace(items=[(t0 + t * s, "NE", f"{t}.jpg") for t in range(60)])

    assert loop_period(source()) == 59 * s + LOOP_GAP_NS
    cut = source()
    play_window(IngestSettings(play_from="16:00:40", play_until="16:00:50"), cut)
    assert loop_period(cut) == 9 * s + LOOP_GAP_NS
    cut = source()
    play_window(IngestSettings(play_from="16:00:40"), cut)
    assert loop_period(cut) == 19 * s + LOOP_GAP_NS
    assert loop_period(SimpleNamespace(items=None)) is None  # a video file: spaced as played


def test_the_played_slice_is_read_in_the_sites_time_zone_and_must_not_be_empty():
    import pytest

    from shared.settings import IngestSettings

    real = IngestSettings(play_from="2023-12-19T11:00:40", timezone="America/Detroit")  # the real minute's held-out
    assert real.window_ns() == (1_703_001_640_000_000_000, None)  # 16:00:40 UTC
    assert IngestSettings(play_from="2023-12-19T16:00:40+00:00", timezone="America/Detroit").window_ns()[0] == \
        1_703_001_640_000_000_000  # an offset given wins
    with pytest.raises(ValueError, match=r"play_until .* is not after play_from"):
        IngestSettings(play_from="2023-12-19T11:00:40", play_until="2023-12-19T11:00:40")
    with pytest.raises(ValueError, match="play_from"):
        IngestSettings(play_from="11:00:40 tomorrow")


def test_a_played_slice_cuts_the_files_read_and_is_refused_for_a_video_or_an_empty_slice():
    """play_window: the recorded files outside the slice are not even read (each part of a merged source cut too); a
    time of day is on the day of the source's first frame, in the site's time zone; a video file or a stream (no
    recorded capture times) and a slice holding no frame are refused, naming what the frames span."""
    from types import SimpleNamespace

    import pytest

    from services.ingest.__main__ import play_window
    from shared.settings import IngestSettings

    s = 10**9
    t0 = 1_703_001_600 * s  # 2023-12-19 11:00:00 in America/Detroit
    a = SimpleNamespace(items=[(t0 + t * s, "NE", f"a{t}") for t in range(0, 60, 2)])
    b = SimpleNamespace(items=[(t0 + t * s, "SW", f"b{t}") for t in range(1, 60, 2)])
    merged = SimpleNamespace(items=sorted(a.items + b.items), parts=[a, b])
    cfg = IngestSettings(play_from="11:00:40", play_until="11:00:50", timezone="America/Detroit")
    assert play_window(cfg, merged) == (t0 + 40 * s, t0 + 50 * s)
    assert [t for t, _, _ in merged.items] == [t0 + t * s for t in range(40, 50)]
    assert [t for t, _, _ in a.items] == [t0 + t * s for t in range(40, 50, 2)] and len(b.items) == 5
    assert play_window(IngestSettings(), SimpleNamespace(items=None)) == (None, None)  # no slice: any source
    with pytest.raises(ValueError, match="apply to recorded files"):
        play_window(cfg, SimpleNamespace(items=None))
    late = IngestSettings(play_from="12:00:00", timezone="America/Detroit")
    with pytest.raises(ValueError, match=r"its frames run 2023-12-19 11:00:00 to 2023-12-19 11:00:58 "
                                         r"\(America/Detroit\)"):
        play_window(late, SimpleNamespace(items=[(t0 + t * s, "NE", f"a{t}") for t in range(0, 60, 2)]))
    with pytest.raises(ValueError, match="is a number"):
        IngestSettings(play_from=39640)  # YAML's reading of 11:00:40 unquoted


def test_a_slice_is_refused_for_a_folder_timed_by_its_frame_rate_and_for_mixed_kinds(tmp_path):
    """A folder whose names carry no time is timed from when it is opened (`fps`): a slice of capture time would cut
    it differently at each opening, so it is refused as for a video. play_from and play_until must be of one kind; a
    time of day with an offset is on the day where that offset tells it."""
    import cv2
    import numpy as np
    import pytest

    from services.ingest.__main__ import play_window
    from services.ingest.sources import ImageFolderSource
    from shared.settings import IngestSettings

    for k in range(3):
        cv2.imwrite(str(tmp_path / f"frame{k}.png"), np.zeros((8, 8), np.uint8))
    source = ImageFolderSource({"NE": tmp_path}, fps=10)
    with pytest.raises(ValueError, match=r"a folder timed by ingest\.fps"):
        play_window(IngestSettings(play_until="23:59:59"), source)
    with pytest.raises(ValueError, match="both as date-times or both as times of day"):
        IngestSettings(play_from="2023-12-19T11:00:40", play_until="11:00:50")
    # 2023-12-20 01:30 UTC is 2023-12-19 20:30 in Detroit: 01:10+00:00 is that UTC day's, not the local one's
    cfg = IngestSettings(play_from="01:10:00+00:00", timezone="America/Detroit")
    assert cfg.window_ns(1_703_035_800 * 10**9)[0] == 1_703_034_600 * 10**9
