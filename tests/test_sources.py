"""ingest's live sources: a stream that drops is reported and opened again; live cameras are read side by side."""

from __future__ import annotations

import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest

from services.ingest.sources import MergedSource, SourceFrame, VideoSource

FRAMES_PER_CONNECTION = 4


class _Camera(BaseHTTPRequestHandler):
    """An MJPEG-over-HTTP camera that sends a few frames, then drops the connection (a reboot, a network blip)."""

    def log_message(self, *args) -> None:
        pass

    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.end_headers()
        for k in range(FRAMES_PER_CONNECTION):
            jpg = cv2.imencode(".jpg", np.full((48, 64, 3), 40 * k, np.uint8))[1].tobytes()
            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpg) + jpg
                             + b"\r\n")
            self.wfile.flush()
            time.sleep(0.05)
        self.close_connection = True


@pytest.fixture
def camera_url():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = ThreadingHTTPServer(("127.0.0.1", port), _Camera)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{port}/stream.mjpg"
    server.shutdown()


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
