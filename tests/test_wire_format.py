"""docs/wire-format.md against the code: what a vehicle written without this project reads off the bus.

The document's Tracks table and its worked example are checked against the Tracks message fuse_track builds
(`tracks_message`, encoded by shared/codec.py), and examples/vehicle_listener.py, which uses only zenoh and
msgpack, decodes real payloads, refuses bad ones with the reason, and listens to a live bus."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import struct
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from pipeline_fixtures import free_port_base

from services.fuse_track.__main__ import tracks_message
from services.fuse_track.tracker import TrackState
from shared.codec import ALLOWED_DTYPES, encode
from shared.geo import GeoFrame
from shared.keys import latest_tracks_key, tracks_key
from shared.messages import PREDICT_ACCEL_STD_MPS2, VEHICLE_TYPES, Tracks, err95_m

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "wire-format.md"
LISTENER = ROOT / "examples" / "vehicle_listener.py"
SITE = "state_ellsworth"
ORIGIN = GeoFrame(42.22939632, -83.73899854, 265.0)


def load_listener():
    spec = importlib.util.spec_from_file_location("vehicle_listener", LISTENER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


listener = load_listener()


def example_message(n: int = 2, seq: int = 42) -> Tracks:
    """A Tracks message as fuse_track builds it: a bus seen by two cameras and a car coasting (no camera)."""
    state = TrackState(
        t_ns=1_764_403_200_000_000_000, tracker="tracker-3f9c2a",
        id=np.array([7, 12])[:n], xy=np.array([[12.25, -3.5], [-20.0, 8.125]])[:n],
        velocity=np.array([[4.5, 1.25], [0.0, -0.5]])[:n], yaw=np.array([0.2705, -1.5708])[:n],
        size_lwh=np.array([[12.5, 2.5, 3.25], [4.5, 1.75, 1.5]])[:n], vtype=np.array([3, 0])[:n],
        score=np.array([0.875, 0.5])[:n], age=np.array([31, 4])[:n], hits=np.array([30, 3])[:n],
        cameras=[["NE", "SE"], []][:n],
        xy_cov=np.array([[[0.125, 0.03125], [0.03125, 0.0625]], [[0.5, -0.125], [-0.125, 0.375]]])[:n],
        velocity_cov=np.array([[[0.25, 0.0625], [0.0625, 0.5]], [[1.0, 0.0], [0.0, 1.0]]])[:n],
        yaw_confirmed=np.array([True, False])[:n], yaw_std=np.array([0.0625, 0.25])[:n])
    msg = tracks_message(SITE, state, state.t_ns, seq, ORIGIN,
                         [("tick_closed", 1_764_403_200_180_000_000), ("fuse_track", 1_764_403_200_183_000_000)],
                         [("NE", 1207, 1_764_403_199_990_000_000, 1_764_403_200_150_000_000)][:n])
    msg.latlon = np.round(msg.latlon, 9)  # the document's bytes must not hang on the geodesy's last bit
    return msg


def render(value) -> str:
    """The msgpack map as the document prints it: JSON, with bytes as h'<hex>'."""
    if isinstance(value, bytes):
        return f"h'{value.hex()}'"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)}: {render(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(render(v) for v in value) + "]"
    return json.dumps(value)


def example_blocks() -> tuple[str, str]:
    """The worked example of the document: the decoded map (one field per line) and the payload in hex."""
    payload = encode(example_message(n=1))
    fields = msgpack.unpackb(payload, raw=False)
    structure = "{\n" + ",\n".join(f"  {json.dumps(k)}: {render(v)}" for k, v in fields.items()) + "\n}"
    hexed = payload.hex()
    return structure, "\n".join(hexed[i:i + 96] for i in range(0, len(hexed), 96))


def doc_tracks_table() -> dict[str, tuple[str, str]]:
    """The document's table of Tracks fields: field -> (msgpack type or dtype, shape)."""
    text = DOC.read_text()
    section = text.split("<!-- tracks-fields -->")[1].split("<!-- /tracks-fields -->")[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
        if len(cells) >= 3 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = (cells[1].strip("`"), cells[2].strip("`"))
    return rows


def test_the_documents_tracks_table_is_what_fuse_track_sends() -> None:
    table = doc_tracks_table()
    msg = example_message()
    assert set(table) == {"kind", *Tracks.model_fields}, "every field of the message is documented, none more"
    fields = msgpack.unpackb(encode(msg), raw=False)
    for name, (typ, shape) in table.items():
        value = fields[name]
        if isinstance(value, dict):  # an array: its dtype and shape as the table says
            assert typ == value["dtype"], name
            expected_shape = ["N"] + ([] if len(value["shape"]) == 1 else value["shape"][1:])
            assert shape == "[" + ", ".join(map(str, expected_shape)) + "]", name
            assert listener.TRACK_COLUMNS[name] == (typ, tuple(value["shape"][1:])), name
        else:
            assert isinstance(value, {"str": str, "int": int, "array": list}[typ.split()[0]]), name
    assert set(listener.TRACK_COLUMNS) == {k for k, (t, _) in table.items() if t.startswith(("<", "|"))}


def test_the_documents_worked_example_is_the_codecs_output() -> None:
    text = DOC.read_text()
    structure, hexed = example_blocks()
    assert structure in text, "docs/wire-format.md's decoded example differs from the codec's; paste:\n" + structure
    assert hexed in text, "docs/wire-format.md's hex example differs from the codec's; paste:\n" + hexed


def test_the_documents_dtype_list_is_the_codecs_allow_list() -> None:
    listed = DOC.read_text().split("from this list only:")[1].split("(")[0]
    assert set(re.findall(r"`([<|][a-z]\d)`", listed)) == ALLOWED_DTYPES
    assert {dtype for dtype, _ in listener.TRACK_COLUMNS.values()} <= set(listener.STRUCT_FORMATS) == ALLOWED_DTYPES


def test_the_vehicle_types_of_the_document_and_the_listener_are_the_contracts() -> None:
    assert listener.VEHICLE_TYPES == VEHICLE_TYPES
    listed = re.search(r"<!-- vehicle-types -->(.*?)<!-- /vehicle-types -->", DOC.read_text(), re.S).group(1)
    assert re.findall(r"`(\d)`: `(\w+)`", listed) == [(str(i), t) for i, t in enumerate(VEHICLE_TYPES)]


def test_the_listener_reads_a_real_payload_as_the_projects_codec_does() -> None:
    msg = example_message()
    got = listener.decode_tracks(encode(msg))
    assert (got["site"], got["seq"], got["t_capture_ns"], got["tracker"]) == (SITE, 42, msg.t_capture_ns,
                                                                               "tracker-3f9c2a")
    assert len(got["tracks"]) == 2
    for row, want in zip(got["tracks"], msg.rows(), strict=True):
        assert row["id"] == want["id"] and row["type"] == want["type"] and row["cameras"] == want["cameras"]
        assert (row["age"], row["hits"]) == (want["age"], want["hits"])
        assert (row["lat"], row["lon"]) == (want["lat"], want["lon"])  # float64 on the wire: exact
        for key in ("x", "y", "vx", "vy", "yaw", "length", "width", "height", "score"):
            assert row[key] == pytest.approx(want[key], abs=1e-3), key
        assert row["xy_cov"] == want["xy_cov"] and row["velocity_cov"] == want["velocity_cov"]  # exact in float32 here
        assert row["yaw_confirmed"] is want["yaw_confirmed"] and row["yaw_std"] == want["yaw_std"]  # exact here
        # the 95 % ellipse's longest half-axis: sqrt(chi2(2 dof, 0.95) x the covariance's larger eigenvalue)
        assert row["err95_m"] == pytest.approx(np.sqrt(5.991 * np.linalg.eigvalsh(want["xy_cov"]).max()))
    assert got["tracks"][0]["type"] == "bus" and got["tracks"][1]["cameras"] == []


def test_the_listener_moves_tracks_on_as_the_contract_does() -> None:
    """The standalone listener's `move_on` (the document's formulas in plain Python) and `Tracks.predicted` agree:
    positions, latitude and longitude, grown covariances, the 95 % half-axis, and the accelerations' sigma."""
    msg = example_message()
    assert listener.ACCEL_STD_MPS2 == PREDICT_ACCEL_STD_MPS2
    moved = listener.move_on(listener.decode_tracks(encode(msg)), 0.4)
    want = msg.predicted(msg.t_capture_ns + 400_000_000)
    assert moved["t_ns"] == want.t_capture_ns and moved["t_capture_ns"] == msg.t_capture_ns
    for row, w in zip(moved["tracks"], want.rows(), strict=True):
        assert (row["x"], row["y"]) == pytest.approx((w["x"], w["y"]), abs=1e-6)
        assert (row["lat"], row["lon"]) == pytest.approx((w["lat"], w["lon"]), abs=1e-10)
        np.testing.assert_allclose(row["xy_cov"], w["xy_cov"], rtol=1e-6)
        np.testing.assert_allclose(row["velocity_cov"], w["velocity_cov"], rtol=1e-6)
        assert row["err95_m"] == pytest.approx(np.sqrt(5.991 * np.linalg.eigvalsh(w["xy_cov"]).max()), rel=1e-6)


def test_the_listener_reads_an_empty_tick() -> None:
    got = listener.decode_tracks(encode(example_message(n=0)))
    assert got["tracks"] == [] and got["seq"] == 42


def tampered(field: str, value) -> bytes:
    fields = msgpack.unpackb(encode(example_message()), raw=False)
    fields[field] = value
    return msgpack.packb(fields, use_bin_type=True)


@pytest.mark.parametrize(("payload", "reason"), [
    (b"\xc1 not msgpack", "not msgpack"),
    (msgpack.packb({"kind": "objects", "v": 1}), "not a Tracks message"),
    (tampered("v", 1), "schema version 1"),
    (tampered("xy", {"dtype": "<f4", "shape": [2, 2], "data": bytes(16)}), "field 'xy': dtype '<f4'"),
    (tampered("yaw", {"dtype": "<f4", "shape": [2], "data": bytes(7)}), "field 'yaw': 7 bytes"),
    (tampered("size_lwh", {"dtype": "<f4", "shape": [2, 2], "data": bytes(16)}), "field 'size_lwh': shape"),
    (tampered("xy_cov", {"dtype": "<f4", "shape": [2, 4], "data": bytes(32)}), "expected [N, 2, 2]"),
    (tampered("id", [7, 12]), "field 'id': expected an array map"),
    (tampered("cameras", [["NE"]]), "fields of different lengths"),
    (tampered("cameras", "NE"), "field 'cameras'"),
    # a message off the contract: reported and skipped, not a ValueError or TypeError that ends the listener
    (tampered("xy_cov", {"dtype": "<f4", "shape": [2, 2, 2], "data": struct.pack("<8f", -1, 0, 0, -1, 1, 0, 0, 1)}),
     "field 'xy_cov': track 0 has [[-1.0, 0.0], [0.0, -1.0]], not a symmetric positive definite covariance"),
    (tampered("xy_cov", {"dtype": "<f4", "shape": [2, 2, 2], "data": struct.pack("<8f", 1, 0, 0, 1, 1, 2, -2, 1)}),
     "field 'xy_cov': track 1 has [[1.0, 2.0], [-2.0, 1.0]], not a symmetric"),
    (tampered("velocity_cov", {"dtype": "<f4", "shape": [2, 2, 2], "data": struct.pack("<8f", 1, 0, 0, 1, 1, 0, 0, 0)}),
     "field 'velocity_cov': track 1 has [[1.0, 0.0], [0.0, 0.0]], not a symmetric"),
    (tampered("xy", {"dtype": "<f8", "shape": [2, 2], "data": struct.pack("<4d", 1, 2, math.nan, 4)}),
     "field 'xy': NaN or infinite values"),
    (tampered("yaw_std", {"dtype": "<f4", "shape": [2], "data": struct.pack("<2f", 0.1, 0.0)}),
     "field 'yaw_std': a value not > 0"),
    (tampered("seq", "42"), "field 'seq': expected an integer >= 0, got '42'"),
    (tampered("seq", True), "field 'seq': expected an integer >= 0, got True"),
    (tampered("t_capture_ns", -5), "field 't_capture_ns': expected an integer >= 0, got -5"),
    (tampered("site", 7), "field 'site': expected a string, got 7"),
    (tampered("tracker", ["t"]), "field 'tracker': expected a string"),
])
def test_the_listener_refuses_a_bad_payload_with_the_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(listener.BadMessage, match=re.escape(reason)):
        listener.decode_tracks(payload)


def run_against_a_cabinet(command: list[str], cwd: str) -> subprocess.CompletedProcess:
    """`command` run while a Zenoh peer on a free loopback port (its endpoint replaces "{endpoint}" in the command)
    serves what fuse_track does: the tracks of seq 5 to a `tracks/latest` query, then a tick every 100 ms (seq 6,
    7, ...), each after a garbage payload."""
    port = free_port_base(span=1)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()
    with zenoh.open(conf) as session:
        latest = encode(example_message(seq=5))  # what fuse_track holds when the vehicle connects
        queryable = session.declare_queryable(latest_tracks_key(SITE), lambda q: q.reply(latest_tracks_key(SITE),
                                                                                       latest))
        pub = session.declare_publisher(tracks_key(SITE))

        def publish() -> None:
            seq = 6
            while not stop.wait(0.1):
                pub.put(b"garbage")
                pub.put(encode(example_message(seq=seq)))
                seq += 1

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        try:
            return subprocess.run([c.replace("{endpoint}", f"tcp/127.0.0.1:{port}") for c in command],
                                  capture_output=True, text=True, timeout=60, cwd=cwd)
        finally:
            stop.set()
            thread.join()
            queryable.undeclare()


@pytest.mark.slow
def test_the_listener_gets_the_current_tracks_then_the_live_ones_and_skips_a_bad_one() -> None:
    done = run_against_a_cabinet([sys.executable, str(LISTENER), "--site", SITE, "--connect", "{endpoint}",
                                  "--count", "3", "--timeout", "10"], cwd="/")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    seqs = [m["seq"] for m in lines]
    assert len(seqs) == 3 and seqs[0] == 5, "the current tracks first"
    assert seqs[0] < seqs[1] < seqs[2]
    assert all(m["tracks"][0]["type"] == "bus" for m in lines)
    assert "skipped a message: not msgpack" in done.stderr


@pytest.mark.slow
def test_roadside_tracks_prints_each_vehicle_with_its_95_percent_error() -> None:
    done = run_against_a_cabinet([sys.executable, "-m", "roadside", "tracks", "--site", SITE, "--connect",
                                  "{endpoint}", "--count", "2", "--timeout", "10"], cwd=str(ROOT))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].endswith("2 tracks") and len(lines) == 6
    want = err95_m(example_message().xy_cov)  # 0.91 m for the bus, 1.86 m for the coasting car
    assert f"+-{want[0]:4.1f} m" in lines[1] and " bus " in lines[1] and "yaw +0.27  speed" in lines[1]
    assert f"+-{want[1]:4.1f} m" in lines[2] and " car " in lines[2]
    assert "yaw -1.57? speed" in lines[2]  # the car was not seen travelling: its heading may be reversed
    assert "heading +- 4 deg" in lines[1] and "heading +-14 deg" in lines[2]  # yaw_std 0.0625 and 0.25 rad


@pytest.mark.slow
def test_roadside_tracks_moves_the_tracks_on_when_asked_and_refuses_a_clock_that_is_not_the_cabinets() -> None:
    done = run_against_a_cabinet([sys.executable, "-m", "roadside", "tracks", "--site", SITE, "--connect",
                                  "{endpoint}", "--count", "1", "--timeout", "10", "--json", "--ahead-ms", "500"],
                                 cwd=str(ROOT))
    assert done.returncode == 0, done.stderr
    msg, sent = json.loads(done.stdout), example_message(seq=5)
    assert msg["t_ns"] == sent.t_capture_ns + 500_000_000
    bus = msg["tracks"][0]
    assert (bus["x"], bus["y"]) == pytest.approx((12.25 + 0.5 * 4.5, -3.5 + 0.5 * 1.25))
    assert bus["xy_cov"][0][0] > sent.xy_cov[0, 0, 0] + 0.25 * sent.velocity_cov[0, 0, 0] - 1e-6
    done = run_against_a_cabinet([sys.executable, "-m", "roadside", "tracks", "--site", SITE, "--connect",
                                  "{endpoint}", "--count", "1", "--timeout", "10", "--now"], cwd=str(ROOT))
    assert done.returncode == 2 and "is the clock the cabinet's?" in done.stderr  # the example is a year old
    assert len(done.stderr.strip().splitlines()) == 1


def test_the_listener_follows_a_recording_played_again_as_the_client_does() -> None:
    """`roadside play` run a second time sends the same tracker with seq from 0 again: the listener (and the document's
    "Order" rule) takes it when its capture time is more than the client's replay margin before the last one's, as
    shared.client.TrackClient does; a duplicate or a straggler a few ticks old is still skipped."""
    from shared.client import REPLAYED_NS

    assert listener.REPLAYED_NS == REPLAYED_NS
    assert f"more than {REPLAYED_NS // 10**9} s before" in " ".join(DOC.read_text().split())

    def decoded(seq: int, t_s: float, tracker: str = "tracker-3f9c2a") -> dict:
        msg = example_message(seq=seq).model_copy(update={"t_capture_ns": round(t_s * 1e9), "tracker": tracker})
        return listener.decode_tracks(encode(msg))

    printed, last = [], None
    for msg in [decoded(68, 66.8), decoded(69, 66.9), decoded(69, 66.9), decoded(66, 66.6),  # a duplicate, a straggler
                decoded(0, 60.0), decoded(1, 60.1),  # the same recording again, from its start
                decoded(0, 70.0, tracker="tracker-b"), decoded(1, 70.1, tracker="tracker-b")]:  # another tracker
        if not listener.seen(msg, last):
            printed.append(msg["seq"])
            last = (msg["tracker"], msg["seq"], msg["t_capture_ns"])
    assert printed == [68, 69, 0, 1, 0, 1]


def run_tracks_against(messages: list[Tracks], *flags: str, monkeypatch, capsys) -> tuple[int, list[str], str, list]:
    """`roadside tracks --site state_ellsworth FLAGS` reading `messages` (the first one the current tracks) from a
    stand-in for TrackClient; returns its status, the lines it printed, its stderr and the `latest` it asked for."""
    import shared.client
    from roadside.cli import main

    asked = []

    class Client:
        def __init__(self, *args, **kw) -> None:
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            pass

        def latest(self, timeout_s: float = 2.0) -> Tracks:
            return messages[0]

        def sites(self, timeout_s: float = 1.0) -> set[str]:
            return {SITE}

        def stream(self, timeout_s=None, poll_s=0.1, stop=None, current=..., latest=True):
            asked.append(latest)
            yield current
            yield from messages[1:]

    monkeypatch.setattr(shared.client, "TrackClient", Client)
    status = main(["tracks", "--site", SITE, *flags])
    out, err = capsys.readouterr()
    return status, out.splitlines(), err, asked


def test_roadside_tracks_now_skips_a_message_too_old_to_move_on_and_goes_on(monkeypatch, capsys) -> None:
    """A message that waited too long (a slow reader, a link that held it) for `Tracks.predicted` to move it on to
    now is skipped with one warning per run of them, not the end of `roadside tracks --now`; the first message still
    says whether this machine shares the cabinet's clock (a recording's or a year-old one is refused, above)."""
    import time

    now = time.time_ns()
    ages = {5: 0.0, 6: 3.0, 7: 2.9, 8: 0.0, 9: 2.5, 10: 0.0}  # seconds since capture
    messages = [example_message(seq=s).model_copy(update={"t_capture_ns": now - round(a * 1e9)})
                for s, a in ages.items()]
    status, lines, err, asked = run_tracks_against(messages, "--now", "--json", monkeypatch=monkeypatch, capsys=capsys)
    assert status == 0, err
    assert [json.loads(line)["seq"] for line in lines] == [5, 8, 10]
    warnings = err.strip().splitlines()
    assert len(warnings) == 2 and all("warning: skipping messages that cannot be moved on to now" in w
                                      for w in warnings), err
    assert asked == [False]  # a JSON line per message is a tracks file: every one
    status, lines, err, asked = run_tracks_against(messages[:1], "--count", "1", monkeypatch=monkeypatch,
                                                   capsys=capsys)
    assert status == 0 and lines[0].endswith("2 tracks") and asked == [True]  # printed for a person: the newest


def test_the_listener_says_in_one_line_when_no_cabinet_answers() -> None:
    port = free_port_base(span=1)
    done = subprocess.run([sys.executable, str(LISTENER), "--site", SITE, "--connect", f"tcp/127.0.0.1:{port}",
                           "--wait", "0.5"], capture_output=True, text=True, timeout=60, cwd="/")
    assert done.returncode == 2
    assert done.stderr.startswith("vehicle_listener: ") and len(done.stderr.strip().splitlines()) == 1
