"""Subprocess smoke tests of the four live services on real Zenoh sessions over loopback.

Each service runs as `python -m services.<name> --site SITE --set ...` in its own process, on a bus of its
own (a free `bus.port_base` per test), next to a Zenoh peer of the test's own that watches, publishes and
holds liveliness tokens. The site (one fisheye camera of the small recording) has lookup masks from the
recording's exact ground lookup and a tiny untrained detector: these tests check transport, bad input,
start-up errors and restarts, not accuracy.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
import yaml
from pipeline_fixtures import (
    CAMERA,
    REPO,
    Peer,
    ServiceProcess,
    bus_sets,
    export_tiny_detector,
    free_port_base,
    mjpeg_camera,
    service_env,
    site_config,
    wait_until,
    write_exact_masks,
    write_site,
)

from shared.codec import encode
from shared.keys import alive_key, all_alive_key, all_cameras_key, camera_key, tracks_key
from shared.messages import MAX_FRAME_BYTES, SCHEMA_VERSION, Detections, Frame, Objects, Status, Tracks
from shared.status import collect_status

pytestmark = pytest.mark.slow

T0 = 1_703_001_700_000_000_000
TICK_NS = 100_000_000
WAIT_S = 60.0  # generous: the machine may be busy; every wait ends as soon as its condition holds
STATUS_EVERY = "bus.status_period_s=0.2"  # status reports five times a second, so the tests need not wait long


# --- fixtures -------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def site(small_recording: Path, tmp_path_factory) -> Path:
    """site.yaml of camera NE of the small recording: exact lookup masks and a tiny untrained detector."""
    folder = tmp_path_factory.mktemp("site")
    write_exact_masks(small_recording, CAMERA, folder / "masks" / f"{CAMERA}.npz")
    export_tiny_detector(folder / "model.onnx")
    return write_site(folder, site_config(small_recording))


@pytest.fixture(scope="module")
def site_name(site: Path) -> str:
    from shared.settings import load_settings

    return load_settings(site).site


@pytest.fixture
def port_base() -> int:
    return free_port_base()


@pytest.fixture
def launch(tmp_path: Path):
    """start(service, site, *sets) -> ServiceProcess; every process still running at the end is killed."""
    started: list[ServiceProcess] = []

    def start(service: str, site: Path, *sets: str, env: dict | None = None) -> ServiceProcess:
        n = sum(p.service == service for p in started)
        proc = ServiceProcess(service, site, list(sets), tmp_path / f"{service}-{n}.log", env)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.kill()


@pytest.fixture
def peer(port_base: int):
    p = Peer(port_base)
    yield p
    p.close()


# --- message builders -----------------------------------------------------------------------------------------------


def good_frame(site: str, recording: Path, seq: int, reduced: int = 2) -> Frame:
    """The recording's first NE frame as ingest sends it (grey, decoded at 1/2 size, or 1/4)."""
    path = sorted((recording / "frames" / CAMERA).glob("*.jpg"))[0]
    grey = cv2.imread(str(path), {2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4}[reduced])
    return Frame(site=site, camera=CAMERA, seq=seq, t_capture_ns=T0 + seq * TICK_NS, camera_kind="fisheye",
                 encoding="gray8", width=grey.shape[1], height=grey.shape[0], scale=1 / reduced, data=grey.tobytes(),
                 stamps=[("ingest", T0)])


def good_detections(site: str, seq: int, camera: str = CAMERA) -> Detections:
    f4 = np.float32
    return Detections(site=site, camera=camera, seq=seq, t_capture_ns=T0 + seq * TICK_NS, width=1280, height=960,
                      infer_ms=5.0, stamps=[("ingest", T0), ("detect", T0 + 1)],
                      score=np.array([0.9, 0.8], f4), uv=np.array([[640.0, 800.0], [400.0, 600.0]], f4),
                      box=np.array([[600, 760, 680, 800], [360, 560, 440, 600]], f4),
                      heading_uv=np.array([[1.0, 0.0], [0.0, 1.0]], f4),
                      size_lwh=np.array([[4.5, 1.8, 1.5], [4.2, 1.8, 1.5]], f4), vtype=np.array([0, 1], np.int8))


def good_objects(site: str, seq: int, x: float = 5.0, camera: str = CAMERA) -> Objects:
    """One car at (x + 1 m per seq, 5) m, captured at T0 + seq ticks."""
    f4 = np.float32
    return Objects(site=site, camera=camera, seq=seq, t_capture_ns=T0 + seq * TICK_NS, infer_ms=5.0,
                   stamps=[("ingest", T0), ("detect", T0 + 1), ("localize", T0 + 2)],
                   xy=np.array([[x + 1.0 * seq, 5.0]]), latlon=np.array([[42.2294, -83.739]]),
                   yaw=np.zeros(1, f4), size_lwh=np.array([[4.5, 1.8, 1.5]], f4), vtype=np.zeros(1, np.int8),
                   score=np.array([0.9], f4), uv=np.array([[640.0, 800.0]], f4))


def tampered(msg, **fields) -> bytes:
    """The message's msgpack map with fields replaced, packed without validation (bad input on purpose)."""
    return msgpack.packb({**msgpack.unpackb(encode(msg), raw=False), **fields}, use_bin_type=True)


def arr(a: np.ndarray) -> dict:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def send_bad_inputs(proc: ServiceProcess, peer: Peer, cases: list[tuple[str, bytes, str | None]]) -> None:
    """Publish each bad payload and wait until the service's log names its reason (one at a time: a frame
    subscriber keeps only the newest frames, so a burst could be dropped before it is decoded). A reason
    already logged is not logged again (None): the final count of bad messages shows it was seen."""
    for key, payload, reason in cases:
        peer.put(key, payload)
        if reason is None:
            continue
        named = wait_until(lambda r=reason: re.search(r"dropped .* message .*" + r, proc.log()) or not proc.running(),
                           WAIT_S)
        assert proc.running(), f"{proc.service} died on {reason!r}:\n{proc.log()}"
        assert named, f"{proc.service} log does not name {reason!r}:\n{proc.log()}"


def warm_up(peer: Peer, key: str, payload, done, what: str) -> int:
    """Publish a good message every second until the service's answer arrives (the subscription is live); the tries
    made. `payload`: the message, or try number -> message, a new one each try where the same one again would be
    dropped (objects of a tick fuse_track has closed)."""
    for i in range(int(WAIT_S)):
        peer.put(key, payload(i) if callable(payload) else payload)
        if peer.wait_for(done, 1.0):
            return i + 1
    raise AssertionError(f"no answer to {what} within {WAIT_S} s")


def status_report(peer: Peer, site_name: str, service: str, condition) -> Status:
    """The newest Status report of `service`, once `condition(report)` holds (asked for over the bus, as `roadside
    status` does)."""
    found: list[Status] = []

    def check() -> list[Status]:
        reports, errors = collect_status(peer.session, site_name, 1.0)
        assert not errors, errors
        found[:] = [r for r in reports if r.service == service]
        return [r for r in found if condition(r)]

    assert wait_until(check, WAIT_S, 0.1), f"{service} reports {found}"
    return found[0]


def jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def stages(msg) -> list[str]:
    return [s for s, _ in msg.stamps]


def bad_count(proc: ServiceProcess, pattern: str) -> int:
    """The bad-message count of the service's last log line ("stopped: ..., N bad ...")."""
    found = re.findall(pattern, proc.log().strip().splitlines()[-1])
    assert found, proc.log()
    return int(found[-1])


def assert_clean_exit(proc: ServiceProcess, rc: int) -> None:
    assert rc == 0, f"{proc.service} exited {rc}:\n{proc.log()}"
    assert "Traceback" not in proc.log(), proc.log()


# --- a. the whole chain with a frame cap ----------------------------------------------------------------------------


def test_chain_plays_two_frames_through_all_four_services(site, site_name, small_recording, port_base, peer, launch,
                                                          tmp_path):
    record = tmp_path / "tracks.jsonl"
    peer.subscribe("detections", all_cameras_key(site_name, "detections"), Detections)
    peer.subscribe("objects", all_cameras_key(site_name, "objects"), Objects)
    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    sets = [*bus_sets(port_base), f"fuse_track.record={record}", "fuse_track.tick_ms=500", "fuse_track.min_hits=1",
            STATUS_EVERY]
    fuse = launch("fuse_track", site, *sets)
    localize = launch("localize", site, *sets)
    detect = launch("detect", site, *sets)
    assert peer.wait_alive(all_alive_key(site_name), 3, WAIT_S) >= 3, [p.log() for p in (fuse, localize, detect)]
    # every frame must be detected: wait for each frame's detections as long as the test waits (a first inference on
    # a loaded machine took over the default 2 s, and frame 1 then pushed frame 0 out of detect's ring)
    ingest = launch("ingest", site, *sets, "ingest.pace=max", "ingest.max_frames=2", f"ingest.ack_timeout_s={WAIT_S}")
    assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert "done: 2 frames published, 0 bad, 0 ack timeouts" in ingest.log()
    assert "n per camera: {'NE': 2}" in ingest.log()  # 1280x960 decoded at half size for a 640 px model

    def seqs(name: str) -> set[int]:
        return {m.seq for m in peer.got[name]}

    def tracked(seq: int) -> bool:
        return any((CAMERA, seq) in {(c, s) for c, s, _, _ in t.frames} for t in peer.got["tracks"])

    assert peer.wait_for(lambda: seqs("objects") == {0, 1} and tracked(1), WAIT_S), peer.got
    # what each service says it has done (`roadside status`): the two frames in and out of each, nothing bad
    det_status = status_report(peer, site_name, "detect", lambda r: r.counts.get("detections_out") == 2)
    assert det_status.counts == {"frames_in": 2, "detections_out": 2} and det_status.bad == {}, det_status
    assert det_status.last_output_ns > 0 and det_status.gauges["infer_ms_avg"] > 0 and det_status.peak_rss_mb > 0
    loc_status = status_report(peer, site_name, "localize", lambda r: r.counts.get("objects_out") == 2)
    assert loc_status.counts == {"detections_in": 2, "objects_out": 2} and loc_status.bad == {}, loc_status
    fuse_status = status_report(peer, site_name, "fuse_track", lambda r: r.counts.get("objects_in") == 2)
    assert fuse_status.counts["tracks_out"] >= 1 and fuse_status.gauges["not_recorded"] == 0, fuse_status
    assert fuse_status.gauges["cameras_down"] == 0, fuse_status  # its one camera delivers
    for proc in (detect, localize, fuse):  # fuse_track last: it flushes and records what is still open
        assert_clean_exit(proc, proc.terminate())
    peer.poll()

    frame_times = [int(p.stem) for p in sorted((small_recording / "frames" / CAMERA).glob("*.jpg"))][:2]
    dets = sorted(peer.got["detections"], key=lambda m: m.seq)
    assert [d.seq for d in dets] == [0, 1] and [d.t_capture_ns for d in dets] == frame_times
    assert sum(len(d) for d in dets) > 0, "the detector found nothing below its threshold"
    for d in dets:
        assert (d.camera, d.width, d.height) == (CAMERA, 1280, 960)
        assert stages(d) == ["ingest", "detect_in", "detect_start", "detect_done", "detect"]
    objs = sorted(peer.got["objects"], key=lambda m: m.seq)
    assert [o.t_capture_ns for o in objs] == frame_times
    for o in objs:
        assert stages(o) == ["ingest", "detect_in", "detect_start", "detect_done", "detect", "localize"]
        t = [t for _, t in o.stamps]
        assert t == sorted(t), o.stamps
    assert peer.got["tracks"]
    for tr in peer.got["tracks"]:
        assert stages(tr) == ["tick_closed", "fuse_track"] and tr.stamp("tick_closed") <= tr.stamp("fuse_track")
    assert len({tr.tracker for tr in peer.got["tracks"]}) == 1

    lines = jsonl(record)
    assert lines and [r["seq"] for r in lines] == list(range(len(lines)))
    assert {tr.seq for tr in peer.got["tracks"]} <= {r["seq"] for r in lines}
    for r in lines:
        assert r["site"] == site_name and r["tracker"] == peer.got["tracks"][0].tracker
        assert all(math.isfinite(row["lat"]) and row["cameras"] in ([], [CAMERA]) for row in r["tracks"])
    assert "stopped: 2 frames detected, 0 bad" in detect.log()
    assert "stopped: 2 messages localized, 0 bad" in localize.log()


def open_router(port: int, socket: Path, tls: tuple[int, Path, Path] | None = None, enrolled_by: Path | None = None):
    """A Zenoh router on deploy/zenoh/router.json5, as compose.yaml's (its access control included), listening on
    this test's port (the network's way in) and Unix socket (the cabinet services' way in); with `tls` (port,
    certificate, key) also on tls/localhost:port, as deploy/sites/README.md tells a cabinet to add it, and with
    `enrolled_by` (a CA certificate) that listener lets in only clients with a certificate it signed (mutual TLS)."""
    import zenoh

    conf = zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / "router.json5"))
    endpoints = json.loads(conf.get_json("listen/endpoints"))
    assert [e.split("/")[0] for e in endpoints] == ["tcp", "unixsock-stream"], endpoints
    endpoints = [f"tcp/127.0.0.1:{port}", f"unixsock-stream/{socket}"]
    if tls is not None:
        endpoints.append(f"tls/localhost:{tls[0]}")
        conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(tls[1])))
        conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(tls[2])))
    if enrolled_by is not None:
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(enrolled_by)))
    conf.insert_json5("listen/endpoints", json.dumps(endpoints))
    return zenoh.open(conf)


def cabinet_certificates(folder: Path) -> tuple[Path, Path, Path]:
    """A CA and the cabinet's certificate for localhost signed by it, with its key (openssl, as deploy/sites/README.md
    makes them): (ca.pem, cabinet.pem, cabinet.key)."""
    folder.mkdir(parents=True, exist_ok=True)
    ca, ca_key, cert, key, csr = (folder / n for n in ("ca.pem", "ca.key", "cabinet.pem", "cabinet.key", "c.csr"))
    (folder / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for cmd in (["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", ca_key, "-out", ca, "-days", "30",
                 "-subj", "/CN=roadside test CA"],
                ["req", "-newkey", "rsa:2048", "-nodes", "-keyout", key, "-out", csr, "-subj", "/CN=localhost"],
                ["x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial", "-out", cert, "-days",
                 "30", "-extfile", folder / "san.cnf"]):
        subprocess.run(["openssl", *map(str, cmd)], check=True, capture_output=True)
    return ca, cert, key


def enrolled_vehicle(folder: Path, name: str) -> tuple[Path, Path]:
    """A vehicle's certificate signed by the CA that `cabinet_certificates` made in `folder`, with its key (openssl,
    as deploy/sites/README.md enrolls one): (vehicle.pem, vehicle.key)."""
    cert, key, csr, ext = (folder / f"{name}{e}" for e in (".pem", ".key", ".csr", ".cnf"))
    ext.write_text(f"subjectAltName=DNS:{name}\nextendedKeyUsage=clientAuth\n")  # an X.509 v3 client certificate
    for cmd in (["req", "-newkey", "rsa:2048", "-nodes", "-keyout", key, "-out", csr, "-subj", f"/CN={name}"],
                ["x509", "-req", "-in", csr, "-CA", folder / "ca.pem", "-CAkey", folder / "ca.key", "-CAcreateserial",
                 "-out", cert, "-days", "30", "-extfile", ext]):
        subprocess.run(["openssl", *map(str, cmd)], check=True, capture_output=True)
    return cert, key


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl to make the test's certificates")
def test_a_cabinet_with_mutual_tls_lets_only_its_enrolled_vehicles_in(tmp_path, capsys):
    """The router's TLS listener asks for a client certificate signed by the operator's CA: an enrolled vehicle
    (`bus.tls_certificate` and `tls_private_key`, `roadside tracks --cert --key`, the standalone listener's) reads
    the tracks; one without a certificate, or with one another CA signed, is refused; a certificate without its
    key, or a key file that is not there, is named."""
    import zenoh

    from shared.bus import zenoh_config
    from shared.client import TrackClient
    from shared.keys import latest_tracks_key
    from shared.settings import BusSettings

    ca, cert, key = cabinet_certificates(tmp_path / "cabinet")
    vehicle = enrolled_vehicle(tmp_path / "cabinet", "vehicle-17")
    cabinet_certificates(tmp_path / "other")
    stranger = enrolled_vehicle(tmp_path / "other", "vehicle-99")
    port = free_port_base(span=2)
    socket = tmp_path / "cabinet.sock"
    router = open_router(port, socket, (port + 1, cert, key), enrolled_by=ca)
    endpoint = f"tls/localhost:{port + 1}"
    service = zenoh.open(zenoh_config(BusSettings(mode="client", connect=[f"unixsock-stream/{socket}"])))
    try:
        from test_contract import make_tracks
        payload = encode(make_tracks(2, site="s", seq=7))
        queryable = service.declare_queryable(latest_tracks_key("s"),
                                              lambda q: q.reply(latest_tracks_key("s"), payload))
        enrolled = BusSettings(tls_root_ca=ca, tls_certificate=vehicle[0], tls_private_key=vehicle[1])
        with TrackClient("s", connect=[endpoint], bus=enrolled, wait_s=WAIT_S) as client:
            latest = client.latest(timeout_s=5)
            assert latest is not None and latest.seq == 7
        for bus in (BusSettings(tls_root_ca=ca),
                    BusSettings(tls_root_ca=ca, tls_certificate=stranger[0], tls_private_key=stranger[1])):
            with pytest.raises(ConnectionError, match=endpoint):
                TrackClient("s", connect=[endpoint], bus=bus, wait_s=2.0)
        with pytest.raises(ValueError, match=r"bus\.tls_certificate is given without bus\.tls_private_key"):
            BusSettings(tls_certificate=vehicle[0])
        with pytest.raises(ValueError, match=r"bus\.tls_private_key: private key not found: .*nowhere\.key"):
            TrackClient("s", connect=[endpoint], wait_s=2.0, bus=BusSettings(
                tls_root_ca=ca, tls_certificate=vehicle[0], tls_private_key=tmp_path / "nowhere.key"))
        from roadside.cli import main
        assert main(["tracks", "--site", "s", "--connect", endpoint, "--ca", str(ca), "--cert", str(vehicle[0]),
                     "--key", str(vehicle[1]), "--count", "1", "--json", "--wait", "10"]) == 0
        line = json.loads(capsys.readouterr().out)
        from shared.tracks_file import parse_tracks_message  # a tracks-file line: viz, play and counts read it

        assert line["seq"] == 7 and parse_tracks_message(line).site == "s"
        done = subprocess.run([sys.executable, str(REPO / "examples" / "vehicle_listener.py"), "--site", "s",
                               "--connect", endpoint, "--ca", str(ca), "--cert", str(vehicle[0]), "--key",
                               str(vehicle[1]), "--count", "1", "--timeout", "5"],
                              capture_output=True, text=True, timeout=60, cwd="/")
        assert done.returncode == 0 and json.loads(done.stdout)["seq"] == 7, done.stderr
        del queryable
    finally:
        service.close()
        router.close()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl to make the test's certificates")
def test_a_vehicle_over_tls_knows_the_cabinet_and_may_only_read(tmp_path):
    """With a TLS listener on the router, a vehicle given the cabinet's CA (`bus.tls_root_ca`, `roadside tracks
    --ca`) gets the tracks; given another CA it refuses the router; and over TLS, as over TCP, what it puts never
    reaches a service."""
    import zenoh
    from test_contract import make_tracks

    from shared.bus import zenoh_config
    from shared.client import TrackClient
    from shared.codec import encode
    from shared.keys import latest_tracks_key, tracks_key
    from shared.settings import BusSettings

    ca, cert, key = cabinet_certificates(tmp_path / "cabinet")
    impostor_ca, _, _ = cabinet_certificates(tmp_path / "impostor")
    port = free_port_base(span=2)
    tls_port = port + 1
    socket = tmp_path / "cabinet.sock"
    router = open_router(port, socket, (tls_port, cert, key))
    endpoint = f"tls/localhost:{tls_port}"
    inside = BusSettings(mode="client", connect=[f"unixsock-stream/{socket}"])  # a cabinet service's bus
    service = zenoh.open(zenoh_config(inside))
    try:
        latest_payload = encode(make_tracks(2, site="s", seq=7))
        queryable = service.declare_queryable(latest_tracks_key("s"),
                                              lambda q: q.reply(latest_tracks_key("s"), latest_payload))
        heard: list[bytes] = []
        sub = service.declare_subscriber(tracks_key("s"), lambda sample: heard.append(sample.payload.to_bytes()))
        with TrackClient("s", connect=[endpoint], bus=BusSettings(tls_root_ca=ca), wait_s=WAIT_S) as client:
            latest = client.latest(timeout_s=5)
            assert latest is not None and latest.seq == 7
            client.session.put(tracks_key("s"), b"FAKE over TLS")
        with pytest.raises(ConnectionError, match=endpoint):
            TrackClient("s", connect=[endpoint], bus=BusSettings(tls_root_ca=impostor_ca), wait_s=2.0)
        with pytest.raises(ValueError, match="CA certificate not found"):
            TrackClient("s", connect=[endpoint], bus=BusSettings(tls_root_ca=tmp_path / "missing.pem"), wait_s=2.0)
        other = zenoh.open(zenoh_config(inside))
        try:  # a service's put reaches the subscription through the router; the vehicle's did not
            assert wait_until(lambda: other.put(tracks_key("s"), b"real") or b"real" in heard, 10, 0.2)
        finally:
            other.close()
        assert set(heard) == {b"real"}, "a put over TLS reached a service"
        del queryable, sub
    finally:
        service.close()
        router.close()


def test_waiting_for_peers_through_a_router_counts_each_token_once(tmp_path):
    # a client-mode session gets its own token twice (its own answer and the router's): ingest at the cabinet counted
    # one token per camera too many and started before the last services were ready
    import zenoh

    from shared.bus import wait_for_peers, zenoh_config
    from shared.settings import BusSettings

    socket = tmp_path / "cabinet.sock"
    router = open_router(free_port_base(span=1), socket)
    sessions = []
    try:
        for _ in range(2):  # as the services open theirs at the cabinet
            sessions.append(zenoh.open(zenoh_config(BusSettings(mode="client",
                                                                connect=[f"unixsock-stream/{socket}"]))))
        names = ("ingest", "detect")
        tokens = [s.liveliness().declare_token(f"roadside/t/alive/{n}/NE")
                  for s, n in zip(sessions, names, strict=True)]
        assert wait_for_peers(sessions[0], "roadside/t/alive/**", 2, WAIT_S) == 2
        assert wait_for_peers(sessions[0], "roadside/t/alive/**", 3, 1.5) == 2
        del tokens
    finally:
        for s in sessions:
            s.close()
        router.close()


def test_the_cabinet_router_lets_the_network_read_the_tracks_and_inject_nothing(tmp_path):
    """deploy/zenoh/router.json5's access control: a session on the router's Unix socket (a cabinet service) may do
    everything; one over TCP (a vehicle, anyone on the roadside network) gets the tracks, their latest, the liveliness
    tokens and the status reports, but what it puts (fake tracks, a frame for detect) never reaches a service, and
    the camera frames are not sent to it."""
    import zenoh

    from shared.bus import zenoh_config
    from shared.keys import alive_key, camera_key, latest_tracks_key, status_key, tracks_key
    from shared.settings import BusSettings

    port, socket = free_port_base(span=1), tmp_path / "cabinet.sock"
    router = open_router(port, socket)
    sessions = []
    try:
        service, other_service, vehicle = (
            zenoh.open(zenoh_config(BusSettings(mode="client", connect=[e]))) for e in
            (f"unixsock-stream/{socket}", f"unixsock-stream/{socket}", f"tcp/127.0.0.1:{port}"))
        sessions += [service, other_service, vehicle]
        got: dict[str, list[bytes]] = {"service": [], "service_frames": [], "vehicle": [], "vehicle_frames": []}

        def keep(name):
            return lambda sample: got[name].append(sample.payload.to_bytes())

        subs = [other_service.declare_subscriber(tracks_key("s"), keep("service")),
                other_service.declare_subscriber(camera_key("s", "NE", "frame"), keep("service_frames")),
                vehicle.declare_subscriber(tracks_key("s"), keep("vehicle")),
                vehicle.declare_subscriber("roadside/s/cam/**", keep("vehicle_frames"))]
        queryables = [service.declare_queryable(k, lambda q, k=k: q.reply(k, b"answer"))
                      for k in (latest_tracks_key("s"), status_key("s", "fuse_track", "main"))]
        token = service.liveliness().declare_token(alive_key("s", "fuse_track", "t1"))
        assert wait_until(lambda: any(r.ok for r in vehicle.liveliness().get("roadside/s/alive/**", timeout=1)), 10)

        def routed() -> bool:  # every subscription known to the router: a probe of each kind has arrived
            service.put(tracks_key("s"), b"probe")
            service.put(camera_key("s", "NE", "frame"), b"probe")
            return b"probe" in got["service"] and b"probe" in got["vehicle"] and b"probe" in got["service_frames"]

        assert wait_until(routed, 10, 0.1)
        time.sleep(0.3)  # the last probes still on their way
        for values in got.values():
            values.clear()
        for i in range(3):
            service.put(tracks_key("s"), f"real {i}".encode())
            service.put(camera_key("s", "NE", "frame"), f"frame {i}".encode())
            vehicle.put(tracks_key("s"), b"FAKE tracks")
            vehicle.put(camera_key("s", "NE", "frame"), b"FAKE frame")
        assert wait_until(lambda: len(got["vehicle"]) >= 6 and len(got["service"]) >= 3, 10), got
        time.sleep(0.5)  # anything else on its way
        assert got["service"] == [b"real 0", b"real 1", b"real 2"], "a put from the network reached a service"
        assert got["service_frames"] == [b"frame 0", b"frame 1", b"frame 2"]
        assert sorted(got["vehicle"]) == sorted([b"real 0", b"real 1", b"real 2"] + [b"FAKE tracks"] * 3)  # + its own
        assert got["vehicle_frames"] == [b"FAKE frame"] * 3, "camera frames went out to the network"
        for key in (latest_tracks_key("s"), status_key("s", "fuse_track", "main")):
            assert [r.ok.payload.to_bytes() for r in vehicle.get(key, timeout=5) if r.ok] == [b"answer"], key
        del subs, queryables, token
    finally:
        for s in sessions:
            s.close()
        router.close()


def test_the_cabinet_layout_services_in_client_mode_through_the_router(site, site_name, launch, tmp_path):
    """As compose.yaml runs them: a Zenoh router on deploy/zenoh/router.json5 and the four services in client mode
    with compose's bus environment (through the router's Unix socket, this test's), and a vehicle's client that
    reaches the tracks only through the router's TCP port."""
    from shared.client import TrackClient

    router_port = free_port_base(span=1)
    endpoint = f"tcp/127.0.0.1:{router_port}"
    socket = tmp_path / "cabinet.sock"
    router = open_router(router_port, socket)
    try:
        compose_env = yaml.safe_load((REPO / "compose.yaml").read_text())["x-bus-environment"]
        env = {k: v.replace("/run/zenoh/cabinet.sock", str(socket)) for k, v in compose_env.items()}
        assert env["ROADSIDE_BUS__MODE"] == "client"
        assert json.loads(env["ROADSIDE_BUS__CONNECT"]) == [f"unixsock-stream/{socket}"]
        procs = [launch(name, site, "fuse_track.tick_ms=500", "fuse_track.min_hits=1", env=env)
                 for name in ("fuse_track", "localize", "detect")]
        with TrackClient(site_name, connect=[endpoint], wait_s=WAIT_S) as client:
            ingest = launch("ingest", site, "ingest.pace=max", "ingest.max_frames=2", f"ingest.ack_timeout_s={WAIT_S}",
                            env=env)
            assert_clean_exit(ingest, ingest.wait(WAIT_S))
            assert "done: 2 frames published, 0 bad, 0 ack timeouts" in ingest.log()
            tokens = re.search(r"pace max; (\d+) liveliness tokens", ingest.log())
            assert tokens and int(tokens.group(1)) >= 4, ingest.log()  # the other three's, through the router
            seen: set[tuple[str, int]] = set()
            for msg in client.stream(timeout_s=WAIT_S, latest=False):
                seen |= {(c, s) for c, s, _, _ in msg.frames}
                if (CAMERA, 1) in seen:
                    break
            assert {(CAMERA, 0), (CAMERA, 1)} <= seen, seen
            assert client.bad.total == 0
        for proc in procs:
            assert_clean_exit(proc, proc.terminate())
        assert "stopped: 2 frames detected, 0 bad" in procs[2].log()
    finally:
        router.close()


def test_ingest_decodes_each_camera_as_small_as_the_detector_allows():
    from services.ingest.__main__ import decode_scale_for

    assert decode_scale_for(1280, 960, 640) == 2  # fisheye for a 640 px model
    assert decode_scale_for(640, 512, 640) == 1  # thermal: already the model's size
    assert decode_scale_for(1280, 960, 1280) == 1  # a full-resolution model
    assert decode_scale_for(2560, 1920, 640) == 4
    assert decode_scale_for(1280, 960, 2000) == 1  # never larger than the camera's image
    # only a reduction that divides both sides: a JPEG decoded at 1/s rounds an odd side up, and one scale must map
    # the frame back to the camera's size (detect's detections, localize's masks)
    assert decode_scale_for(1281, 960, 640) == 1 and decode_scale_for(1280, 962, 320) == 2


def test_detect_refuses_a_frame_that_is_not_its_cameras_size_before_decoding_it():
    """A header claiming 16384 x 16384 in a few hundred bytes would cost a quarter gigabyte to decode: the frame's
    size (at its scale) is checked against the camera's first."""
    from services.detect.__main__ import frame_image
    from shared.messages import Frame

    def frame(width, height, scale, data):
        return Frame(site="s", camera="NE", seq=3, t_capture_ns=1, encoding="jpeg", width=width, height=height,
                     scale=scale, camera_kind="fisheye", data=data)

    with pytest.raises(ValueError, match=r"camera NE seq 3: a 16384x16384 frame at scale 1 is 16384x16384, the "
                                         r"camera is 1280x960"):
        frame_image(frame(16384, 16384, 1.0, jpeg_claiming(16384, 16384)), (1280, 960))
    assert frame_image(frame(640, 480, 0.5, jpeg_claiming(640, 480)), (1280, 960)).shape == (480, 640)
    assert frame_image(frame(641, 480, 641 / 1281, jpeg_claiming(641, 480)), (1281, 960)).shape == (480, 641)


def test_detect_names_an_unknown_execution_provider_and_drops_one_this_runtime_lacks(caplog):
    import onnxruntime as ort

    from services.detect.__main__ import usable_providers

    with pytest.raises(ValueError, match="CPUExecutionProvidr is not an ONNX Runtime execution provider"):
        usable_providers(["CPUExecutionProvidr"])
    assert usable_providers(["CPUExecutionProvider"]) == ["CPUExecutionProvider"]
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        assert usable_providers(["CUDAExecutionProvider", "CPUExecutionProvider"]) == ["CPUExecutionProvider"]
        assert "CUDAExecutionProvider not in this ONNX Runtime" in caplog.text
        with pytest.raises(ValueError, match="none of CUDAExecutionProvider is in this ONNX Runtime"):
            usable_providers(["CUDAExecutionProvider"])


def test_settings_name_a_bad_log_level_and_an_absurd_frame_rate(tmp_path):
    from shared.settings import load_settings

    site = Path(__file__).resolve().parents[1] / "deploy" / "sites" / "example" / "site.yaml"
    assert load_settings(site, log_level="warning").log_level == "WARNING"
    with pytest.raises(ValueError, match="log_level: Input should be 'DEBUG'"):
        load_settings(site, log_level="verbose")
    with pytest.raises(ValueError, match=r"ingest\.fps"):
        load_settings(site, ingest={"fps": 1e-300})


def jpeg_claiming(width: int, height: int) -> bytes:
    """A small JPEG whose frame header claims another size."""
    data = bytearray(cv2.imencode(".jpg", np.full((48, 64), 128, np.uint8))[1].tobytes())
    i = data.find(b"\xff\xc0")  # SOF0: length, precision, height, width
    data[i + 5:i + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


def test_a_jpeg_header_is_read_before_the_image_is_decoded():
    """OpenCV allocates what a header claims (65535 x 65535 makes it raise): the size is checked first."""
    from shared.jpeg import decode_grey, jpeg_size

    assert jpeg_size(jpeg_claiming(64, 48)) == (64, 48) and jpeg_size(b"\xff\xd8\xff\xe0 cut") is None
    assert jpeg_size(b"not a jpeg") is None and jpeg_size(b"") is None
    assert decode_grey(jpeg_claiming(64, 48), 64, 48).shape == (48, 64)
    for w, h in [(65500, 65500), (30000, 30000), (0, 48)]:
        with pytest.raises(ValueError, match=f"frame 7: JPEG is {w}x{h}, expected 64x48"):
            decode_grey(jpeg_claiming(w, h), 64, 48, what="frame 7")
    with pytest.raises(ValueError, match=r"corrupt JPEG \(5 bytes\): no frame header"):
        decode_grey(b"\xff\xd8abc", 64, 48)


def test_ingest_counts_an_unreadable_or_mislabelled_file_and_goes_on(tmp_path):
    """A dangling link, a header that lies about the size, a JPEG passed through that is not the camera's size:
    each is a reason on its frame (counted by ingest), not an exception that ends playback; file names whose time
    lies outside 1970-2116 carry no capture time."""
    from services.ingest.__main__ import to_frame_fields
    from services.ingest.sources import ImageFolderSource, SourceFrame, capture_time_from_name
    from shared.settings import CameraSettings

    folder = tmp_path / "NE"
    folder.mkdir()
    (folder / "1700000000000000000.jpg").write_bytes(jpeg_claiming(64, 48))
    (folder / "1700000000100000000.jpg").symlink_to(tmp_path / "gone.jpg")
    frames = list(ImageFolderSource({"NE": folder}))
    assert frames[0].error == "" and "cannot read" in frames[1].error and frames[1].jpeg is None
    cam = CameraSettings(name="NE", kind="pinhole", width=64, height=48, masks="m.npz")
    assert to_frame_fields(frames[0], cam, "gray8", 1)["width"] == 64
    # a PNG in the folder with encoding jpeg: decoded and encoded as a JPEG (only a JPEG is passed through)
    png = SourceFrame("NE", 2, jpeg=cv2.imencode(".png", np.full((48, 64), 77, np.uint8))[1].tobytes(), origin="p.png")
    fields = to_frame_fields(png, cam, "jpeg", 1)
    assert fields["encoding"] == "jpeg" and fields["data"][:2] == b"\xff\xd8" and (fields["width"], fields["height"]) \
        == (64, 48) and abs(int(cv2.imdecode(np.frombuffer(fields["data"], np.uint8), 0).mean()) - 77) <= 1
    lying = SourceFrame("NE", 1, jpeg=jpeg_claiming(65500, 65500), origin="x.jpg")
    for encoding in ("gray8", "jpeg"):
        with pytest.raises(ValueError, match=r"x\.jpg: JPEG is 65500x65500"):
            to_frame_fields(lying, cam, encoding, 1)
    assert capture_time_from_name("12345678901234567890.jpg") is None  # past 2116
    assert capture_time_from_name("1969-12-31 23-59-59-000000.jpg") is None
    assert capture_time_from_name("2023-12-19 11-00-41-000000.jpg") == 1702983641000000000


def test_detect_workers_infer_a_burst_side_by_side_and_publish_each_frame_once(site, site_name, small_recording,
                                                                              port_base, peer, launch):
    peer.subscribe("detections", camera_key(site_name, CAMERA, "detections"), Detections)
    detect = launch("detect", site, *bus_sets(port_base), "detect.workers=2", "detect.threads=1", "detect.ring=8")
    assert peer.wait_alive(alive_key(site_name, "detect", CAMERA), 1, WAIT_S), detect.log()
    key = camera_key(site_name, CAMERA, "frame")
    warm_up(peer, key, encode(good_frame(site_name, small_recording, 0)), lambda: peer.got["detections"], "a frame")
    for seq in range(1, 7):
        peer.put(key, encode(good_frame(site_name, small_recording, seq)))
    assert peer.wait_for(lambda: {d.seq for d in peer.got["detections"]} >= set(range(1, 7)), WAIT_S), detect.log()
    seqs = [d.seq for d in peer.got["detections"]]
    assert seqs == sorted(seqs), seqs  # two at a time, and still in capture order: a newer one waits for the older
    assert_clean_exit(detect, detect.terminate())
    seqs = [d.seq for d in peer.got["detections"] if d.seq > 0]
    assert sorted(seqs) == list(range(1, 7))  # every frame once, none lost or doubled by the pool
    assert "2 workers x 1 threads" in detect.log()


def test_a_frame_inferred_before_an_older_one_of_its_camera_waits_for_it():
    from concurrent.futures import Future
    from types import SimpleNamespace

    from services.detect.__main__ import behind

    def item(camera, t, done):
        fut = Future()
        if done:
            fut.set_result(None)
        return (fut, SimpleNamespace(camera=camera, t_capture_ns=t), 0)

    older, newer, other = item("NE", 1, False), item("NE", 2, True), item("SW", 0, False)
    assert behind(newer, [older, newer, other]) and not behind(older, [older, newer, other])
    older[0].set_result(None)  # done a moment ago, not yet published: still first
    assert behind(newer, [older, newer, other]) and not behind(newer, [newer, other])


def test_detect_keeps_the_newest_frames_per_camera_oldest_first():
    from services.detect.__main__ import newest_per_camera

    def frame(cam: str, seq: int) -> tuple[int, Frame]:
        return seq, Frame(site="s", camera=cam, seq=seq, t_capture_ns=T0 + seq * TICK_NS, camera_kind="fisheye",
                          encoding="gray8", width=2, height=1, scale=1.0, data=b"ab", stamps=[])

    waiting = [frame("NE", 3), frame("SW", 1), frame("NE", 1), frame("NE", 2), frame("SW", 4)]
    kept = newest_per_camera(waiting, 2)
    assert [(f.camera, f.seq) for _, f in kept] == [("SW", 1), ("NE", 2), ("NE", 3), ("SW", 4)]
    assert [(f.camera, f.seq) for _, f in newest_per_camera(waiting, 1)] == [("NE", 3), ("SW", 4)]
    assert newest_per_camera([], 2) == []


def test_playback_keeps_no_more_frames_of_a_camera_in_flight_than_detect_keeps():
    from services.ingest.__main__ import Acks
    from shared.bus import Stopper

    class Acknowledger:  # stands in for the detections subscriber: acknowledges NE 0 at its third poll
        def __init__(self) -> None:
            self.polls = 0

        def poll(self) -> list[Detections]:
            self.polls += 1
            return [good_detections("s", 0, "NE")] if self.polls == 3 else []

        def wait(self, timeout_s: float) -> None:
            pass

    rx = Acknowledger()
    acks = Acks(rx, limit=2, stopper=Stopper(install_signals=False), timeout_s=2.0, per_camera=1)
    acks.sent("NE", 0)
    acks.wait_for_room("SW")  # another camera: room at once
    assert rx.polls == 1
    acks.sent("SW", 0)
    acks.wait_for_room("NE")  # full, and NE has one in flight: waits for NE 0's detections
    assert rx.polls == 3 and set(acks.pending) == {("SW", 0)}


# --- b. bad input on the bus at every service -----------------------------------------------------------------------


def test_detect_drops_bad_frames_and_keeps_running(site, site_name, small_recording, port_base, peer, launch):
    peer.subscribe("detections", camera_key(site_name, CAMERA, "detections"), Detections)
    # ring 2: the case sent without waiting for its log line (None below) must not be pushed out by the next one
    detect = launch("detect", site, *bus_sets(port_base), "detect.ring=2", STATUS_EVERY)
    assert peer.wait_alive(alive_key(site_name, "detect", CAMERA), 1, WAIT_S), detect.log()
    key = camera_key(site_name, CAMERA, "frame")
    frame = good_frame(site_name, small_recording, 0)
    warm_up(peer, key, encode(frame), lambda: peer.got["detections"], "a good frame")

    jpeg = frame.model_copy(update={"encoding": "jpeg", "data": b"\xff\xd8\xff\xe0 not really a jpeg"})
    cases = [
        (key, b"\xc1\xc1 this is not msgpack", "not msgpack"),
        (key, tampered(frame, v=99), "schema version 99 is not supported"),
        (key, tampered(frame, data=arr(np.zeros(4, np.complex128))), "field 'data': dtype '<c16' is not allowed"),
        (key, tampered(frame, data=frame.data[:-1]), "gray8 frame 640x480 needs 307200 bytes, got 307199"),
        (key, tampered(frame, scale=float("nan")), "scale: Input should be a finite number"),
        (key, tampered(jpeg, data=b"\xff\xd8" + bytes(MAX_FRAME_BYTES)), f"exceeds the {MAX_FRAME_BYTES}-byte limit"),
        (key, tampered(jpeg, data=b""), r"camera NE seq 0: corrupt JPEG \(0 bytes\)"),
        (key, tampered(jpeg), None),  # the same reason again (only the numbers differ): counted, not logged again
        # a PNG said to be a JPEG: refused before decoding (its header's size is not checked: a decompression bomb)
        (key, tampered(jpeg, data=cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()),
         "encoding 'jpeg' but the data is not a JPEG"),
        (key, tampered(frame, width=4000, height=1, data=bytes(4000)),
         "a 4000x1 frame at scale 0.5 is 8000x2, the camera is 1280x960"),  # not the camera's: refused undecoded
        (key, tampered(frame, camera="SW"), "frame for camera SW on the key of camera NE"),
        (key, encode(good_objects(site_name, 0)), "expected a frame message, got 'objects'"),
    ]
    send_bad_inputs(detect, peer, cases)

    peer.put(key, encode(good_frame(site_name, small_recording, 1)))
    assert peer.wait_for(lambda: any(d.seq == 1 for d in peer.got["detections"]), WAIT_S), detect.log()
    # a frame decoded smaller than the model's input (1/4 of 1280x960 for a 640 px model): detected at the
    # model's scale, with a warning naming the setting, and not counted as bad
    peer.put(key, encode(good_frame(site_name, small_recording, 2, reduced=4)))
    assert peer.wait_for(lambda: any(d.seq == 2 for d in peer.got["detections"]), WAIT_S), detect.log()
    small = next(d for d in peer.got["detections"] if d.seq == 2)
    assert (small.width, small.height) == (1280, 960) and len(small) > 0
    report = status_report(peer, site_name, "detect", lambda r: sum(r.bad.values()) == len(cases)
                           and r.counts.get("detections_out", 0) >= 3)  # reports come every 0.2 s, not at once
    assert any("not msgpack" in reason for reason in report.bad) and report.counts["frames_in"] >= 3, report
    assert_clean_exit(detect, detect.terminate())
    assert "camera NE: frames come at 320x240, smaller than the model's input" in detect.log()
    assert "set ingest.decode_long_side to 640" in detect.log()
    assert bad_count(detect, r"(\d+) bad messages") == len(cases)


def test_detect_looks_only_inside_the_cameras_detect_area(site, site_name, small_recording, port_base, peer, launch):
    """`cameras[].detect_area_px`: the detector runs on that rectangle (widened to the network's 32-pixel grid of the
    whole image) and its detections come back in the whole image's pixels."""
    config = yaml.safe_load(site.read_text())
    config["cameras"][0]["detect_area_px"] = [640, 480, 1280, 960]  # the lower right quarter of 1280 x 960
    area_site = site.parent / "site_area.yaml"
    area_site.write_text(yaml.safe_dump(config, sort_keys=False))
    peer.subscribe("detections", camera_key(site_name, CAMERA, "detections"), Detections)
    detect = launch("detect", area_site, *bus_sets(port_base))
    assert peer.wait_alive(alive_key(site_name, "detect", CAMERA), 1, WAIT_S), detect.log()
    warm_up(peer, camera_key(site_name, CAMERA, "frame"), encode(good_frame(site_name, small_recording, 0)),
            lambda: peer.got["detections"], "a good frame")
    det = peer.got["detections"][0]
    assert (det.width, det.height) == (1280, 960) and len(det) > 10  # the untrained net: top-k everywhere
    # decoded at 1/2 for a 640 px model: 32 pixels of the 640 x 480 copy around the area (64 of the full image),
    # then out to the copy's 32-pixel grid: the crop starts at (576, 384); nothing left of it or above it
    assert det.uv[:, 0].min() >= 576 - 1 and det.uv[:, 1].min() >= 384 - 1, det.uv.min(axis=0)
    assert det.uv[:, 1].min() < 480  # the rows around the area are looked at too
    assert_clean_exit(detect, detect.terminate())


def test_localize_drops_bad_detections_and_keeps_running(site, site_name, port_base, peer, launch):
    peer.subscribe("objects", all_cameras_key(site_name, "objects"), Objects)
    localize = launch("localize", site, *bus_sets(port_base), STATUS_EVERY)
    assert peer.wait_alive(alive_key(site_name, "localize", CAMERA), 1, WAIT_S), localize.log()
    key = camera_key(site_name, CAMERA, "detections")
    det = good_detections(site_name, 0)
    warm_up(peer, key, encode(det), lambda: peer.got["objects"], "good detections")

    uv = det.uv.copy()
    uv[1, 0] = np.nan
    cases = [
        (key, b"\x00\x01garbage", "not msgpack"),
        (key, tampered(det, v=SCHEMA_VERSION + 1), f"schema version {SCHEMA_VERSION + 1} is not supported"),
        (key, tampered(det, uv=arr(det.uv.astype(">f8"))), "field 'uv': dtype '>f8' is not allowed"),
        (key, tampered(det, uv=arr(det.uv.astype(np.complex128))), "dtype '<c16' is not allowed"),
        (key, tampered(det, uv={"dtype": "<f4", "shape": [3, 2], "data": det.uv.tobytes()}),
         r"shape \[3, 2\] <f4 needs 24 bytes, got 16"),
        (key, tampered(det, uv=arr(np.zeros((2, 3), np.float32))), r"Detections.uv must have shape \(N, 2\)"),
        (key, tampered(det, uv=arr(uv)), "Detections.uv contains NaN or infinite values"),
        (key, tampered(det, score=arr(np.ones(3, np.float32))), "Detections.uv has 2 rows, expected 3"),
        (key, tampered(det, width=640, height=480), "detections for a 640x480 image, masks are 1280x960"),
        (camera_key(site_name, "SW", "detections"), encode(good_detections(site_name, 0, camera="SW")),
         "detections from camera 'SW', not at this site"),
        (key, tampered(det, site="other/site"), "site name must be"),
        # off the contract: refused where decoded, not passed on to make fuse_track refuse the whole frame
        (key, tampered(det, score=arr(np.array([0.9, 1.5], np.float32))), r"Detections.score\[1\] = 1.5 is not within"),
        (key, tampered(det, size_lwh=arr(np.array([[4.5, 1.8, 1.5], [0.0, 1.8, 1.5]], np.float32))),
         r"Detections.size_lwh\[1\] = \[0.0, 1.8, 1.5\] is not > 0 m"),
        # misaddressed: another site's detections on this site's key, another camera's on this camera's key
        (key, encode(good_detections("other_site", 0)), f"detections of site 'other_site' on the bus of site "
                                                        f"'{site_name}'"),
        (key, encode(good_detections(site_name, 0, camera="SW")), f"detections of camera 'SW' on the key of camera "
                                                                  f"'{CAMERA}'"),
    ]
    send_bad_inputs(localize, peer, cases)

    peer.put(key, encode(good_detections(site_name, 1)))
    assert peer.wait_for(lambda: any(o.seq == 1 for o in peer.got["objects"]), WAIT_S), localize.log()
    out = next(o for o in peer.got["objects"] if o.seq == 1)
    assert stages(out)[-1] == "localize" and len(out) == 2 and np.isfinite(out.latlon).all()
    report = status_report(peer, site_name, "localize", lambda r: sum(r.bad.values()) == len(cases)
                           and r.counts.get("objects_out", 0) >= 2)
    assert report.bad["detections from camera 'SW', not at this site"] == 1, report.bad
    assert report.rates.keys() == report.counts.keys() and report.last_output_ns > report.started_ns
    assert_clean_exit(localize, localize.terminate())
    assert bad_count(localize, r"(\d+) bad") == len(cases)


def test_fuse_track_drops_bad_objects_and_keeps_running(site, site_name, port_base, peer, launch):
    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    fuse = launch("fuse_track", site, *bus_sets(port_base), "fuse_track.min_hits=1", STATUS_EVERY)
    assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), fuse.log()
    key = camera_key(site_name, CAMERA, "objects")
    seq = iter(range(10_000))
    first = next(seq)
    warm_up(peer, key, encode(good_objects(site_name, first)), lambda: peer.got["tracks"], "good objects")

    obj = good_objects(site_name, next(seq))
    xy = obj.xy.copy()
    xy[0, 1] = np.nan
    cases = [
        (key, b"\xff\xff\xff", "not msgpack"),
        (key, tampered(obj, v=0), "schema version 0 is not supported"),
        (key, tampered(obj, xy=arr(obj.xy.astype(">f8"))), "field 'xy': dtype '>f8' is not allowed"),
        (key, tampered(obj, xy=arr(np.zeros((1, 3)))), r"Objects.xy must have shape \(N, 2\) got \(1, 3\)"),
        (key, tampered(obj, xy=arr(xy)), "Objects.xy contains NaN or infinite values"),
        (key, tampered(obj, latlon=arr(np.array([[np.inf, 0.0]]))), "Objects.latlon contains NaN or infinite values"),
        (key, tampered(obj, score=arr(np.zeros(2, np.float32))), "Objects.score has 2 rows, expected 1"),
        (key, tampered(obj, t_capture_ns=2**64 - 1), "t_capture_ns: Input should be less than"),
        (key, tampered(obj, score=arr(np.array([5.0], np.float32))), r"ObjectBatch.score must be within \[0, 1\]"),
        (key, tampered(obj, xy=arr(np.array([[1e300, 0.0]]))), "beyond 1e\\+06 m of the site"),
        (key, tampered(obj, size_lwh=arr(np.array([[4.0, 1e-300, 1.5]]))), r"size .* m outside"),
        (camera_key(site_name, "SW", "objects"), encode(good_objects(site_name, 0, camera="SW")),
         "objects from camera 'SW', not at this site"),
        (key, encode(good_objects("other_site", next(seq))), f"objects of site 'other_site' on the bus of site "
                                                             f"'{site_name}'"),
        (key, tampered(obj, t_capture_ns=obj.t_capture_ns + 3600 * 10**9), "dropped, ahead: captured 3600"),
        (key, encode(good_objects(site_name, first)), "dropped, late: its tick has closed"),
    ]
    send_bad_inputs(fuse, peer, cases)

    last = next(seq)
    peer.put(key, encode(good_objects(site_name, last)))

    def tracked() -> list[Tracks]:
        return [t for t in peer.got["tracks"] if (CAMERA, last) in {(c, s) for c, s, _, _ in t.frames}]

    assert peer.wait_for(tracked, WAIT_S), fuse.log()
    assert len(tracked()[0]) == 1 and tracked()[0].xy[0, 0] == pytest.approx(5.0 + last, abs=1.0)
    report = status_report(peer, site_name, "fuse_track", lambda r: sum(r.bad.values()) >= len(cases)
                           and r.gauges.get("tracks") == 1)
    assert report.counts["objects_in"] >= 2 and report.counts["tracks_out"] >= 1, report
    assert_clean_exit(fuse, fuse.terminate())
    assert bad_count(fuse, r"(\d+) bad") >= len(cases)  # and any repeats of the warm-up message (late)


def image_folder_with_a_corrupt_jpeg(recording: Path, folder: Path) -> tuple[list[Path], list[int], Path]:
    """`folder` holding the recording's frames of CAMERA and, between the first two, a truncated JPEG: (the good
    files, their capture times, the corrupt file)."""
    folder.mkdir()
    good = sorted((recording / "frames" / CAMERA).glob("*.jpg"))
    for p in good:
        shutil.copy(p, folder / p.name)
    times = [int(p.stem) for p in good]
    corrupt = folder / f"{(times[0] + times[1]) // 2}.jpg"
    corrupt.write_bytes(b"\xff\xd8\xff\xe0 truncated or not a jpeg at all")
    return good, times, corrupt


def stand_in_for_the_pipeline(peer: Peer, site_name: str) -> None:
    """Subscribe to CAMERA's frames and hold the liveliness tokens ingest waits for (detect, localize, fuse_track)."""
    peer.subscribe("frames", camera_key(site_name, CAMERA, "frame"), Frame)
    peer.declare_tokens([alive_key(site_name, "detect", CAMERA), alive_key(site_name, "localize", CAMERA),
                         alive_key(site_name, "fuse_track", "t0")])


def test_ingest_skips_a_corrupt_jpeg_in_an_image_folder(site, site_name, small_recording, port_base, peer, launch,
                                                        tmp_path):
    folder = tmp_path / "images"
    _, times, corrupt = image_folder_with_a_corrupt_jpeg(small_recording, folder)
    (folder / f"{times[-1] + 1}.jpg").write_bytes(b"")  # an empty file
    stand_in_for_the_pipeline(peer, site_name)
    ingest = launch("ingest", site, *bus_sets(port_base), f"ingest.source={folder}", "ingest.pace=100")
    assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 2, 10.0), ingest.log()
    frames = peer.got["frames"]
    assert [f.seq for f in frames] == [0, 1] and [f.t_capture_ns for f in frames] == times
    assert all((f.encoding, f.width, f.height, f.scale) == ("gray8", 640, 480, 0.5) for f in frames)
    assert re.search(rf"dropped {CAMERA} message .*{corrupt.name}: corrupt JPEG", ingest.log()), ingest.log()
    assert "done: 2 frames published, 2 bad" in ingest.log()


def test_ingest_records_what_it_publishes_as_a_folder_it_plays_back(site, site_name, small_recording, port_base, peer,
                                                                    launch, tmp_path):
    """`ingest.record_dir`: each published frame is written under its capture time at full resolution (the JPEG
    files as they are; a corrupt one is not published, so not recorded); played from that folder, ingest publishes the
    same frames; a second recording into the same folder writes nothing over; the folder being played is refused."""
    folder = tmp_path / "images"
    good, times, _ = image_folder_with_a_corrupt_jpeg(small_recording, folder)
    recorded = tmp_path / "recorded"
    stand_in_for_the_pipeline(peer, site_name)
    sets = [*bus_sets(port_base), "ingest.pace=100", "ingest.encoding=jpeg"]
    ingest = launch("ingest", site, *sets, f"ingest.source={folder}", f"ingest.record_dir={recorded}")
    assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert "recording every frame published to" in ingest.log()
    assert f"2 frames written ({CAMERA} 2), 0 dropped" in ingest.log(), ingest.log()
    files = sorted((recorded / CAMERA).iterdir())
    assert [p.name for p in files] == [p.name for p in good]
    assert [p.read_bytes() for p in files] == [p.read_bytes() for p in good]
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 2, 10.0), ingest.log()
    first = [(f.t_capture_ns, f.data) for f in peer.got["frames"]]

    peer.got["frames"].clear()
    again = launch("ingest", site, *sets, f"ingest.source={recorded}", f"ingest.record_dir={tmp_path / 'copy'}")
    assert_clean_exit(again, again.wait(WAIT_S))
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 2, 10.0), again.log()
    assert [(f.t_capture_ns, f.data) for f in peer.got["frames"]] == first
    assert [t for t, _ in first] == times

    twice = launch("ingest", site, *sets, f"ingest.source={folder}", f"ingest.record_dir={recorded}")
    assert_clean_exit(twice, twice.wait(WAIT_S))
    assert "0 frames written (none), 0 dropped, 0 without disk space, 2 already there" in twice.log(), twice.log()
    assert [p.read_bytes() for p in sorted((recorded / CAMERA).iterdir())] == [p.read_bytes() for p in good]

    refused = launch("ingest", site, *sets, f"ingest.source={recorded}", f"ingest.record_dir={recorded}")
    assert refused.wait(WAIT_S) == 2
    assert re.search(r"ingest: error: ingest.record_dir .* overlap", refused.log()), refused.log()


def test_ingest_records_a_live_stream_it_publishes(site, site_name, small_recording, port_base, peer, launch, tmp_path):
    """A live MJPEG-over-HTTP camera: the frames ingest decodes from it are recorded as JPEGs at the camera's full
    size under their capture times (the clock's at grab), and play back as an image folder."""
    from services.ingest.sources import open_source

    jpegs = [p.read_bytes() for p in sorted((small_recording / "frames" / CAMERA).glob("*.jpg"))]
    with mjpeg_camera(lambda k: jpegs[k % len(jpegs)], 40, 0.1) as url:
        stand_in_for_the_pipeline(peer, site_name)
        recorded = tmp_path / "recorded"
        ingest = launch("ingest", site, *bus_sets(port_base), f"ingest.source={url}", "ingest.max_frames=3",
                        f"ingest.record_dir={recorded}")
        assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert f"3 frames written ({CAMERA} 3), 0 dropped" in ingest.log(), ingest.log()
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 3, 10.0), ingest.log()
    published = [f.t_capture_ns for f in peer.got["frames"]]
    files = sorted((recorded / CAMERA).iterdir())
    assert [int(p.stem) for p in files] == published
    source = cv2.imdecode(np.frombuffer(jpegs[0], np.uint8), cv2.IMREAD_COLOR)
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        assert img.shape == (960, 1280, 3)
    assert np.abs(cv2.imread(str(files[0]), cv2.IMREAD_COLOR).astype(int) - source).mean() < 3.0  # quality 92
    assert [f.t_capture_ns for f in open_source(str(recorded), [CAMERA], {})] == published


def test_ingest_plays_only_the_frames_between_play_from_and_play_until(site, site_name, small_recording, port_base,
                                                                       peer, launch):
    """ingest.play_from / play_until (ISO 8601; here with a UTC offset): the held-out slice of a recording; a slice
    holding no frame stops ingest at start, naming the settings."""
    from datetime import UTC, datetime

    times = sorted(int(p.stem) for p in (small_recording / "frames" / CAMERA).glob("*.jpg"))

    def iso(t_ns: int) -> str:
        return datetime.fromtimestamp(t_ns / 1e9, UTC).isoformat()

    stand_in_for_the_pipeline(peer, site_name)
    sets = [*bus_sets(port_base), "ingest.pace=100"]
    ingest = launch("ingest", site, *sets, f"ingest.play_from={iso(times[1] - 500_000)}")
    assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert "done: 1 frames published" in ingest.log(), ingest.log()
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 1, 10.0), ingest.log()
    assert [f.t_capture_ns for f in peer.got["frames"]] == [times[1]]
    peer.got["frames"].clear()
    ingest = launch("ingest", site, *sets, f"ingest.play_until={iso(times[1] - 500_000)}")
    assert_clean_exit(ingest, ingest.wait(WAIT_S))
    assert peer.wait_for(lambda: len(peer.got["frames"]) >= 1, 10.0), ingest.log()
    assert [f.t_capture_ns for f in peer.got["frames"]] == [times[0]]
    empty = launch("ingest", site, *sets, f"ingest.play_from={iso(times[-1] + 10**9)}")
    assert empty.wait(WAIT_S) == 2
    assert "no frame of the source lies within ingest.play_from" in empty.log(), empty.log()


# --- c. a missing file stops a service at start with exit status 2 and one error line -------------------------------


def test_missing_model_masks_or_source_stop_the_service_with_one_error_line(site, small_recording, port_base, launch,
                                                                           tmp_path):
    missing_model = tmp_path / "no" / "model.onnx"
    missing_source = tmp_path / "no" / "recording"
    no_masks = write_site(tmp_path / "site_without_masks", site_config(small_recording, masks="masks/gone.npz"))
    missing_masks = (tmp_path / "site_without_masks").resolve() / "masks" / "gone.npz"
    broken = write_site(tmp_path / "site_broken_masks", site_config(small_recording, masks="masks/cut.npz"))
    cut_masks = (tmp_path / "site_broken_masks").resolve() / "masks" / "cut.npz"
    cut_masks.parent.mkdir(parents=True, exist_ok=True)
    cut_masks.write_bytes(b"PK\x03\x04 a zip cut short")
    sets = bus_sets(port_base)
    runs = [
        (launch("detect", site, *sets, f"detect.model={missing_model}"), missing_model),
        (launch("localize", no_masks, *sets), missing_masks),
        (launch("fuse_track", no_masks, *sets), missing_masks),
        (launch("ingest", site, *sets, f"ingest.source={missing_source}"), missing_source),
        (launch("localize", broken, *sets), cut_masks),
        (launch("fuse_track", broken, *sets), cut_masks),
        (launch("fuse_track", site, *sets, f"fuse_track.record={tmp_path}"), tmp_path),  # a folder, not a file
    ]
    for proc, path in runs:
        rc = proc.wait(WAIT_S)
        err = proc.log().strip().splitlines()
        assert rc == 2, f"{proc.service} exited {rc}:\n{proc.log()}"
        assert len(err) == 1, f"{proc.service} wrote {len(err)} lines:\n{proc.log()}"
        assert err[0].startswith(f"{proc.service}: error: ") and str(path) in err[0], err[0]


# --- c2. a camera that stops delivering: its ground goes to its neighbour, and comes back ------------------------


@pytest.fixture(scope="module")
def two_camera_site(small_recording: Path, tmp_path_factory) -> Path:
    """site.yaml of both cameras of the small recording (NE, T_SW) with exact lookup masks: fuse_track's regions."""
    folder = tmp_path_factory.mktemp("site2")
    config = site_config(small_recording)
    meta = json.loads((small_recording / "recording.json").read_text())
    sw = next(c for c in meta["cameras"] if c["name"] == "T_SW")
    write_exact_masks(small_recording, CAMERA, folder / "masks" / f"{CAMERA}.npz")
    write_exact_masks(small_recording, "T_SW", folder / "masks" / "T_SW.npz")
    config["cameras"].append({"name": "T_SW", "kind": sw["kind"], "width": sw["width"], "height": sw["height"],
                              "masks": "masks/T_SW.npz"})
    return write_site(folder, config)


def cars(site: str, camera: str, seq: int, xy: list[tuple[float, float]], score: float = 0.9) -> Objects:
    """Cars at the given ground positions (m) seen by `camera` at T0 + seq ticks (none: an empty frame)."""
    f4, n = np.float32, len(xy)
    return Objects(site=site, camera=camera, seq=seq, t_capture_ns=T0 + seq * TICK_NS, infer_ms=5.0,
                   stamps=[("ingest", T0), ("detect", T0 + 1), ("localize", T0 + 2)],
                   xy=np.array(xy, float).reshape(n, 2), latlon=np.tile([42.2294, -83.739], (n, 1)),
                   yaw=np.zeros(n, f4), size_lwh=np.tile(np.array([4.5, 1.8, 1.5], f4), (n, 1)),
                   vtype=np.zeros(n, np.int8), score=np.full(n, score, f4), uv=np.zeros((n, 2), f4))


def test_a_silent_camera_hands_its_ground_to_its_neighbour_until_it_delivers_again(two_camera_site, port_base, peer,
                                                                                  launch):
    """NE stops delivering for 3 s of capture time, T_SW going on: after fuse_track.handover_s (1 s) NE is down and
    a car that enters NE's region seen by T_SW alone is tracked (without the handover T_SW's far view of it could
    only extend a track, never start one); when NE delivers again it is up, and the car keeps its track."""
    from services.fuse_track.__main__ import camera_positions
    from shared.settings import load_settings

    settings = load_settings(two_camera_site)
    site_name = settings.site
    positions, _ = camera_positions(settings)
    ne, sw = (np.array(positions[c]) for c in (CAMERA, "T_SW"))
    along = (sw - ne) / np.linalg.norm(sw - ne)
    across = np.array([-along[1], along[0]])
    first = ne + 0.2 * (sw - ne)  # both in NE's region (its Voronoi cell): nearer NE than T_SW
    second = first + 8.0 * across

    def at(start: np.ndarray, seq: int) -> tuple[float, float]:  # 1 m/s along the line between the poles
        return tuple(start + 0.1 * seq * along)

    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    fuse = launch("fuse_track", two_camera_site, *bus_sets(port_base), "fuse_track.min_hits=1", STATUS_EVERY)
    assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), fuse.log()
    keys = {c: camera_key(site_name, c, "objects") for c in (CAMERA, "T_SW")}

    def deliver(seq: int, ne_sees: list | None, sw_sees: list) -> None:
        peer.put(keys["T_SW"], encode(cars(site_name, "T_SW", seq, sw_sees)))
        if ne_sees is not None:
            peer.put(keys[CAMERA], encode(cars(site_name, CAMERA, seq, ne_sees)))
        peer.wait_for(lambda: False, 0.05)

    def down(report: Status) -> float | None:
        return report.gauges.get("cameras_down")

    # both deliver: NE sees the first car, T_SW nothing (its empty frames count as delivered)
    warm_up(peer, keys[CAMERA], lambda i: encode(cars(site_name, CAMERA, i, [at(first, i)])),
            lambda: peer.got["tracks"], "good objects")
    start = 60  # past the warm-up's tries
    for seq in range(start, start + 10):
        deliver(seq, [at(first, seq)], [])
    status_report(peer, site_name, "fuse_track", lambda r: down(r) == 0)

    # NE falls silent; T_SW sees a second car in NE's region (as a far view: it may not start a track there)
    silent = seq + 1
    for seq in range(silent, silent + 30):
        deliver(seq, None, [at(second, seq)])

    def handed_over() -> list[tuple[Tracks, int]]:
        return [(t, i) for t in peer.got["tracks"] for i, cams in enumerate(t.cameras) if cams == ["T_SW"]
                and np.linalg.norm(t.xy[i] - at(second, (t.t_capture_ns - T0) / TICK_NS)) < 1.5]

    assert peer.wait_for(handed_over, WAIT_S), f"no track of T_SW's car in NE's region:\n{fuse.log()}"
    status_report(peer, site_name, "fuse_track", lambda r: down(r) == 1)
    assert re.search(r"cameras down .*: NE; their regions go to the nearest cameras up", fuse.log()), fuse.log()
    car = handed_over()[-1]
    car_id = int(car[0].id[car[1]])

    # NE delivers again, seeing the second car too: it is up, and the car keeps its id
    back = seq + 1
    for seq in range(back, back + 10):
        deliver(seq, [at(second, seq)], [at(second, seq)])
    last = seq

    def newest_of_last() -> list[Tracks]:
        return [t for t in peer.got["tracks"] if (CAMERA, last) in {(c, s) for c, s, _, _ in t.frames}]

    assert peer.wait_for(newest_of_last, WAIT_S), fuse.log()
    status_report(peer, site_name, "fuse_track", lambda r: down(r) == 0)
    assert "cameras up again: NE" in fuse.log()
    final = newest_of_last()[0]
    rows = final.rows()
    near = [r for r in rows if np.hypot(r["x"] - at(second, last)[0], r["y"] - at(second, last)[1]) < 1.5]
    assert len(near) == 1 and near[0]["id"] == car_id and sorted(near[0]["cameras"]) == [CAMERA, "T_SW"], rows
    assert_clean_exit(fuse, fuse.terminate())


# --- d. a vehicle that joins late gets the current tracks at once ---------------------------------------------------


def feed(peer: Peer, key: str, site_name: str, seqs: range, pause_s: float = 0.05) -> None:
    for s in seqs:
        peer.put(key, encode(good_objects(site_name, s)))
        peer.wait_for(lambda: False, pause_s)


def test_a_late_client_gets_the_current_tracks_at_once(site, site_name, port_base, peer, launch):
    from shared.client import TrackClient

    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    fuse = launch("fuse_track", site, *bus_sets(port_base), "fuse_track.min_hits=1")
    assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), fuse.log()
    key = camera_key(site_name, CAMERA, "objects")
    warm_up(peer, key, encode(good_objects(site_name, 0)), lambda: peer.got["tracks"], "good objects")
    feed(peer, key, site_name, range(1, 6))
    assert peer.wait_for(lambda: any(len(t) and (CAMERA, 5) in [f[:2] for f in t.frames] for t in peer.got["tracks"]),
                         WAIT_S), fuse.log()
    newest = max(peer.got["tracks"], key=lambda t: t.seq)

    client = TrackClient(site_name, connect=[f"tcp/127.0.0.1:{port_base + 3}"])
    try:
        latest = client.latest(timeout_s=10.0)
        assert isinstance(latest, Tracks), "fuse_track did not answer the latest-tracks query"
        assert latest.seq >= newest.seq and latest.tracker == newest.tracker and len(latest) == 1
        assert latest.rows()[0]["cameras"] == [CAMERA]
        first = next(client.stream(timeout_s=1.0))
        assert first.seq >= latest.seq and client.bad.total == 0
    finally:
        client.close()
    assert_clean_exit(fuse, fuse.terminate())


def test_a_vehicle_waits_for_the_cabinet_and_rides_through_its_restart(site, site_name, port_base, peer, launch):
    """A vehicle's client started before fuse_track is up connects when it comes, and goes on receiving after
    fuse_track is stopped and started again (the new tracker's messages); one that finds nothing within its wait
    gets a ConnectionError naming the endpoint."""
    import threading

    from shared.client import TrackClient

    endpoint = f"tcp/127.0.0.1:{port_base + 3}"
    with pytest.raises(ConnectionError, match=f"no answer from {endpoint} within 0.5 s"):
        TrackClient(site_name, connect=[endpoint], wait_s=0.5)

    got: list[Tracks] = []
    stop = threading.Event()
    opened: list[TrackClient] = []

    def vehicle() -> None:
        with TrackClient(site_name, connect=[endpoint], wait_s=60.0) as client:
            opened.append(client)
            for msg in client.stream(stop=stop):
                got.append(msg)

    thread = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    key = camera_key(site_name, CAMERA, "objects")
    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    seen: set[str] = set()  # the trackers the vehicle has had tracks from
    try:
        for run in range(2):
            fuse = launch("fuse_track", site, *bus_sets(port_base), "fuse_track.min_hits=1")
            assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), fuse.log()
            start = 100 * run
            before = set(seen)
            # the vehicle's client reconnects on its own back-off (up to 2 s), maybe after the first Tracks message:
            # each try is a new moment (a new tick), as at a cabinet
            tries = warm_up(peer, key, lambda i, s=start: encode(good_objects(site_name, s + i)),
                            lambda b=before: any(m.tracker not in b and len(m) for m in got),
                            "good objects to the vehicle")
            feed(peer, key, site_name, range(start + tries, start + tries + 9), pause_s=0.1)
            seen |= {m.tracker for m in got if len(m)}
            assert len(seen) == run + 1, (run, seen)
            assert_clean_exit(fuse, fuse.terminate())
        assert opened and opened[0].bad.total == 0
    finally:
        stop.set()
        thread.join(10)


def test_viz_live_records_the_live_tracks_until_count_or_sigterm(site, site_name, port_base, peer, launch, tmp_path):
    """`roadside viz --live` subscribes like a vehicle and writes what it receives to an .rrd: it stops after
    --count messages, or on SIGTERM with everything received before it in the file (exit 0); the summary names
    the site and counts the messages and tracks."""
    import threading

    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    fuse = launch("fuse_track", site, *bus_sets(port_base), "fuse_track.min_hits=1")
    assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), fuse.log()
    key = camera_key(site_name, CAMERA, "objects")
    warm_up(peer, key, encode(good_objects(site_name, 0)), lambda: peer.got["tracks"], "good objects")
    done = threading.Event()

    def keep_feeding() -> None:
        s = 1
        while not done.is_set():
            feed(peer, key, site_name, range(s, s + 1), pause_s=0.1)
            s += 1

    feeder = threading.Thread(target=keep_feeding, daemon=True)
    feeder.start()
    base = [sys.executable, "-m", "roadside", "viz", "--live", "--site", str(site),
            "--connect", f"tcp/127.0.0.1:{port_base + 3}", "--timeout", "30"]
    try:
        counted = subprocess.run([*base, "--out", str(tmp_path / "count.rrd"), "--count", "3"], env=service_env(),
                                 capture_output=True, text=True, timeout=120)
        assert counted.returncode == 0, counted.stderr[-2000:]
        summary = json.loads(counted.stdout)
        assert (summary["site"], summary["messages"], summary["bad_lines"]) == (site_name, 3, 0)
        assert summary["tracks"] >= 1 and (tmp_path / "count.rrd").stat().st_size > 1000

        proc = subprocess.Popen([*base, "--out", str(tmp_path / "live.rrd")], env=service_env(),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            partial = tmp_path / "live.rrd.partial"  # the stream's file until it ends, then live.rrd
            assert wait_until(lambda: partial.is_file() and partial.stat().st_size > 1000, 60), \
                "no tracks reached the file"
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, err[-2000:]
        assert (tmp_path / "live.rrd").stat().st_size > 1000 and not partial.exists()
        summary = json.loads(out)
        assert summary["messages"] >= 1 and summary["tracks"] >= 1 and summary["bad_messages"] == 0
    finally:
        done.set()
        feeder.join(10)
    assert_clean_exit(fuse, fuse.terminate())


def test_viz_refuses_mixed_or_missing_sources(tmp_path, capsys):
    from roadside.cli import main

    tracks = tmp_path / "t.jsonl"
    tracks.write_text("")
    for argv, message in [([], "needs a tracks file, or --live"),
                          ([str(tracks), "--count", "3"], "--count goes with --live"),
                          (["--live"], "--live needs --site"),
                          (["--live", str(tracks)], "--live takes no tracks file")]:
        assert main(["viz", *argv, "--out", str(tmp_path / "x.rrd")]) == 2
        assert message in capsys.readouterr().err


# --- e. kill and restart: the recording keeps every line and goes on ------------------------------------------------


def test_fuse_track_killed_and_restarted_keeps_and_appends_its_recording(site, site_name, port_base, peer, launch,
                                                                          tmp_path):
    record = tmp_path / "tracks.jsonl"
    sets = [*bus_sets(port_base), f"fuse_track.record={record}", "fuse_track.min_hits=1"]
    peer.subscribe("tracks", tracks_key(site_name), Tracks)
    key = camera_key(site_name, CAMERA, "objects")
    first = launch("fuse_track", site, *sets)
    assert peer.wait_alive(f"roadside/{site_name}/alive/fuse_track/*", 1, WAIT_S), first.log()
    warm_up(peer, key, encode(good_objects(site_name, 0)), lambda: peer.got["tracks"], "good objects")
    feed(peer, key, site_name, range(1, 8))
    assert peer.wait_for(lambda: any((CAMERA, 7) in [f[:2] for f in t.frames] for t in peer.got["tracks"]), WAIT_S)
    # every tick has closed once nothing new has come for a while (max_wait): the file holds them all
    assert wait_until(lambda: record.is_file() and len(jsonl(record)) == len({t.seq for t in peer.got["tracks"]}),
                      WAIT_S, 0.2), (len(peer.got["tracks"]), record.read_text())
    before = record.read_text()
    old_tracker = peer.got["tracks"][0].tracker

    assert first.kill() == -9
    assert record.read_text() == before, "lines written before the kill were lost"
    rows = jsonl(record)
    assert [r["seq"] for r in rows] == list(range(len(rows))) and {r["tracker"] for r in rows} == {old_tracker}

    second = launch("fuse_track", site, *sets)
    peer.got["tracks"].clear()

    def appended() -> bool:
        peer.poll()
        return record.read_text().startswith(before) and any(r["tracker"] != old_tracker for r in jsonl(record))

    s = 8
    while not appended():  # objects sent before the new process subscribes are lost: keep sending
        assert second.running() and s < 8 + int(WAIT_S / 0.2), second.log()
        peer.put(key, encode(good_objects(site_name, s)))
        s += 1
        peer.wait_for(lambda: False, 0.2)
    new_rows = jsonl(record)[len(rows):]
    assert new_rows[0]["seq"] == 0 and {r["tracker"] for r in new_rows} != {old_tracker}
    assert all(r["site"] == site_name for r in new_rows)
    assert_clean_exit(second, second.terminate())


# --- roadside up (the launcher) ---------------------------------------------------------------------------------------


def _children(pid: int) -> list:
    import psutil

    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def test_roadside_up_refuses_a_bus_whose_ports_another_pipeline_holds(site, port_base, monkeypatch, capsys):
    """A second pipeline on the same ports would see each service die on its port and be restarted ever more slowly
    until the first one stops: `roadside up` says so at once instead, naming the port and the service."""
    import socket

    import roadside.cli
    from roadside.cli import main

    monkeypatch.setattr(roadside.cli, "PORTS_FREE_WAIT_S", 0.3)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:  # as a running localize holds its port
        held.bind(("127.0.0.1", port_base + 2))
        held.listen()
        assert main(["up", "--site", str(site), "--set", f"bus.port_base={port_base}", "--no-restart"]) == 2
    err = capsys.readouterr().err
    assert f"the bus's ports are in use: localize tcp/127.0.0.1:{port_base + 2}; is another pipeline running" in err
    # a host that is no address of this machine: every service would die on it and be restarted for ever
    assert main(["up", "--site", str(site), "--set", f"bus.port_base={port_base}", "--set", "bus.host=192.0.2.7"]) == 2
    assert "bus.host 192.0.2.7 is not an address of this machine" in capsys.readouterr().err


@pytest.mark.slow
def test_roadside_up_plays_a_source_to_the_end_and_stops_every_service(site, small_recording, port_base, tmp_path):
    """`roadside up` starts the four services, ingest ends with its source, the others are drained and
    stopped; the tracks file is written; no service process is left behind."""
    tracks = tmp_path / "tracks.jsonl"
    cmd = [sys.executable, "-m", "roadside", "up", "--site", str(site), "--pace", "max", "--record", str(tracks),
           "--record-frames", str(tmp_path / "frames"), "--log-dir", str(tmp_path / "logs"),
           "--set", f"bus.port_base={port_base}", "--max-frames", "2", "--from", "2001-09-09T01:46:40+00:00",
           "--until", "2100-01-01T00:00:00"]
    proc = subprocess.run(cmd, env=service_env(), capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for s in ("fuse_track", "localize", "detect", "ingest"):
        assert f"started {s}" in proc.stderr
    assert "ingest finished its source" in proc.stderr
    lines = [json.loads(x) for x in tracks.read_text().splitlines()]
    assert lines and all("tracks" in x for x in lines)
    recorded = sorted(p.name for p in (tmp_path / "frames" / CAMERA).iterdir())
    assert recorded == sorted(p.name for p in (small_recording / "frames" / CAMERA).glob("*.jpg"))[:2]


@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGHUP])
def test_roadside_up_stops_cleanly_on_sigterm(site, small_recording, port_base, tmp_path, stop):
    """With a looping source the pipeline runs until told to stop: SIGTERM (or SIGHUP, a closed terminal: the
    services in their own sessions would otherwise keep running and holding the ports) stops all four services
    and `roadside up` exits 0 with no process left."""
    cmd = [sys.executable, "-m", "roadside", "up", "--site", str(site), "--pace", "1", "--loop",
           "--log-dir", str(tmp_path / "logs"), "--set", f"bus.port_base={port_base}"]
    proc = subprocess.Popen(cmd, env=service_env(), stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: len(_children(proc.pid)) >= 4, 60)
        kids = _children(proc.pid)
        assert wait_until(lambda: (tmp_path / "logs" / "ingest.log").is_file()
                          and "source" in (tmp_path / "logs" / "ingest.log").read_text(), 90)
        proc.send_signal(stop)
        assert proc.wait(60) == 0
        assert all(not k.is_running() or k.status() == "zombie" for k in kids)
        assert "[up] stopped" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow
def test_the_soak_bench_samples_every_service_of_a_looping_pipeline(site, small_recording, port_base, tmp_path):
    """`roadside bench soak` (bench/soak.py): a looped source keeps the tracks coming past its end (event time
    goes on), each service's memory is sampled from its process and its counts from its Status reports, and the
    pipeline is stopped cleanly at the end."""
    from bench.soak import run

    doc = run(site, str(small_recording), minutes=0.5, pace="max", sample_s=5.0, warmup_s=0.0, out=tmp_path / "soak",
              sets=[f"bus.port_base={port_base}"], log=lambda m: None)
    assert doc["launcher_exit_code"] == 0 and doc["samples"] >= 4
    for service, summary in doc["services"].items():
        assert (summary["processes"], summary["restarts"]) == (1, 0), service
        assert 20 < summary["rss_mb_end"] <= summary["rss_mb_max"], service
        assert summary["growth_mb_per_hour"] is not None and summary["counts"], service
    assert doc["frames_published"] > 2 * len(list((small_recording / "frames" / CAMERA).glob("*.jpg")))  # looped
    assert doc["tracks_messages"] >= 10 and doc["services"]["fuse_track"]["counts"]["tracks_out"] >= 10
    assert (tmp_path / "soak" / "tracks.jsonl").stat().st_size > 0


def test_a_service_that_keeps_dying_is_restarted_ever_more_slowly(tmp_path):
    """Restarted after restart_delay_s, the delay doubling (to max_restart_delay_s) while it dies soon after its
    start, back to restart_delay_s once it has run stable_s; a stop during the wait starts nothing."""
    from roadside.launcher import Launcher, UpConfig

    (tmp_path / "site.yaml").write_text("site: x\n")
    launcher = Launcher(UpConfig(site=tmp_path, restart_delay_s=1.0, max_restart_delay_s=5.0, stable_s=10.0))
    launcher.started_at["detect"] = time.monotonic()
    assert [launcher.restart_delay("detect") for _ in range(5)] == [1.0, 2.0, 4.0, 5.0, 5.0]
    launcher.started_at["detect"] = time.monotonic() - 60  # it ran a minute before it died
    assert launcher.restart_delay("detect") == 1.0


FAKE_SERVICES = '''
import sys, time
from pathlib import Path
from roadside.launcher import Launcher, UpConfig

class Fake(Launcher):  # stand-ins for the services: detect dies at once, the others run until stopped
    def command(self, service):
        code = {"detect": "import sys; sys.exit(1)",
                "localize": "import sys; print('localize: error: lookup masks not found: m.npz', file=sys.stderr); "
                            "sys.exit(2)"}.get(service, "import time; time.sleep(120)")
        return [sys.executable, "-c", code]
'''


def _fake_launcher(tmp_path, **cfg):
    (tmp_path / "site.yaml").write_text("site: x\n")
    scope: dict = {}
    exec(FAKE_SERVICES, scope)  # the stand-ins, shared with the launcher run in a process of its own below
    return scope["Fake"](scope["UpConfig"](site=tmp_path, **cfg))


def test_a_service_waiting_to_be_restarted_does_not_hold_up_the_others(tmp_path):
    """detect keeps dying (its next start ever later); fuse_track killed meanwhile is restarted at once."""
    import threading

    launcher = _fake_launcher(tmp_path, restart_delay_s=0.2, max_restart_delay_s=30.0, stable_s=10.0,
                              services=("fuse_track", "detect"))
    lines: list[str] = []
    seen: dict[str, float] = {}

    def kill_fuse_track_while_detect_waits() -> None:
        try:
            assert wait_until(lambda: any("next start in 3.2 s" in line for line in lines), 30)
            os.kill(launcher.procs["fuse_track"].pid, signal.SIGKILL)
            t0 = time.monotonic()
            if wait_until(lambda: any("restarted fuse_track" in line for line in lines), 10):
                seen["restart_s"] = time.monotonic() - t0
        finally:
            launcher.stopping = True

    helper = threading.Thread(target=kill_fuse_track_while_detect_waits)
    helper.start()
    assert launcher.run(log=lines.append) == 0
    helper.join()
    assert seen.get("restart_s", 99) < 2.5, lines  # within its own 0.2 s delay, not after detect's 3.2 s


def test_a_configuration_error_ends_the_run_with_its_reason(tmp_path):
    launcher = _fake_launcher(tmp_path, services=("fuse_track", "localize"), log_dir=tmp_path / "logs")
    lines: list[str] = []
    assert launcher.run(log=lines.append) == 2
    assert "[up] localize: a configuration error, not restarted: localize: error: lookup masks not found: m.npz" \
        in lines, lines


def test_a_service_killed_by_a_signal_ends_the_run_as_a_shell_would_say_it(tmp_path):
    """--no-restart, a service killed (the OOM killer's SIGKILL): 128 + 9, not Popen's -9 (247 at the shell)."""
    import threading

    launcher = _fake_launcher(tmp_path, services=("fuse_track",), restart=False, stop_timeout_s=2.0)
    threading.Timer(1.0, lambda: os.kill(launcher.procs["fuse_track"].pid, signal.SIGKILL)).start()
    assert launcher.run(log=lambda _: None) == 128 + signal.SIGKILL
    assert launcher.signalled is None


def test_a_run_stopped_by_a_signal_says_so_and_the_demo_does_not_score_it(tmp_path, monkeypatch):
    """Ctrl-C: `roadside up` stops cleanly (status 0) and says which signal stopped it; `roadside demo` went on to
    score the cut-short run and replaced the last whole run's summary with it."""
    import threading
    from types import SimpleNamespace

    import roadside.demo as demo
    import roadside.launcher
    import shared.settings

    launcher = _fake_launcher(tmp_path, services=("fuse_track",), stop_timeout_s=2.0)
    threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
    assert launcher.run(log=lambda _: None) == 0 and launcher.signalled == "SIGINT"

    class CutShort:  # the demo's launcher, stopped by Ctrl-C
        def __init__(self, cfg):
            self.cpu_s, self.signalled = {}, None

        def run(self, log):
            self.signalled = "SIGINT"
            return 0

    timed: list[str] = []
    settings = SimpleNamespace(cameras=[], detect=None, site="x", path=lambda p: tmp_path / "tracks.jsonl",
                               fuse_track=SimpleNamespace(record="tracks.jsonl"))
    monkeypatch.setattr(demo, "make_recording", lambda cfg, log: tmp_path)
    monkeypatch.setattr(demo, "make_site", lambda cfg, rec, log: (tmp_path, {}))
    monkeypatch.setattr(shared.settings, "load_settings", lambda path: settings)
    monkeypatch.setattr(demo, "DetectorAlone", lambda *a: SimpleNamespace(run=lambda: timed.append("timed") or {}))
    monkeypatch.setattr(demo, "Collector", lambda *a, **k: SimpleNamespace(start=lambda: None, stop=lambda: None))
    monkeypatch.setattr(roadside.launcher, "Launcher", CutShort)
    (tmp_path / "summary.json").write_text("{}")
    lines: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        demo.run_demo(demo.DemoConfig(out=tmp_path), log=lines.append)
    assert timed == ["timed"] and (tmp_path / "summary.json").read_text() == "{}"  # not timed again, not scored
    assert any("stopped by SIGINT: not scored" in line for line in lines), lines


@pytest.mark.skipif(sys.platform != "linux", reason="PR_SET_PDEATHSIG is Linux's")
def test_the_services_stop_when_the_launcher_is_killed(tmp_path):
    """SIGKILL (the OOM killer) gives the launcher no chance to stop its services: they are told by the kernel."""
    import subprocess

    (tmp_path / "site.yaml").write_text("site: x\n")
    script = FAKE_SERVICES + f'''
launcher = Fake(UpConfig(site=Path({str(tmp_path)!r}), services=("fuse_track",)))
launcher.run(log=lambda line: print(line, flush=True))
'''
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # [up] started fuse_track (pid N)
        child = int(line.split("pid ")[1].rstrip(")\n"))
        os.kill(child, 0)  # running
        proc.kill()
        proc.wait(10)

        def gone() -> bool:  # no such process, or a zombie its new parent has not reaped yet
            try:
                return Path(f"/proc/{child}/stat").read_text().split(") ")[1][0] == "Z"
            except (FileNotFoundError, IndexError):
                return True

        assert wait_until(gone, 10), f"service {child} outlived its launcher"
    finally:
        proc.kill()


def test_paths_given_to_roadside_up_are_not_read_as_yaml(tmp_path, monkeypatch):
    """`--record "run #2/tracks.jsonl"`: a YAML comment started at ' #' recorded to 'run'."""
    import roadside.launcher as launcher_mod
    from roadside.cli import main

    got = {}

    class Stub:
        def __init__(self, cfg) -> None:
            got["sets"] = cfg.sets

        def run(self, log=None) -> int:
            return 0

    monkeypatch.setattr(launcher_mod, "Launcher", Stub)
    site = tmp_path / "site"
    site.mkdir()
    (site / "site.yaml").write_text(yaml.safe_dump({"site": "x", "cameras": [
        {"name": "NE", "kind": "fisheye", "width": 64, "height": 48, "masks": "m.npz"}]}))
    record = tmp_path / "run #2" / "tracks: final.jsonl"
    assert main(["up", "--site", str(site), "--record", str(record), "--source", str(tmp_path / "footage #2")]) == 0
    from shared.service import parse_sets

    sets = parse_sets(got["sets"])
    assert sets["fuse_track"]["record"] == str(record) and sets["ingest"]["source"] == str(tmp_path / "footage #2")


def test_exclusion_polygons_take_their_pixels_out_of_the_calibrated_area():
    from calibration.masks import excluded

    valid = np.ones((10, 12), bool)
    valid[0, 0] = False
    out = excluded(valid, [[(2, 2), (5, 2), (5, 5), (2, 5)], [(9.6, 8.6), (11.4, 8.6), (11.4, 9.4)]])
    assert valid[2:6, 2:6].all() and valid.sum() == 119  # the input is not changed
    assert not out[2:6, 2:6].any() and out[2:6, 6].all() and out[1, 2:6].all()  # a 4x4 square of pixels out
    assert not out[0, 0] and (~out).sum() == 1 + 16 + int((~out[8:, 10:]).sum())
    assert not out[9, 11] and out[8, 10]  # the small triangle takes the pixel it covers, not its neighbours
