"""`roadside play` (services/fuse_track/player.py): a tracks recording published on the bus as fuse_track would."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pipeline_fixtures import REPO, free_port_base, service_env, wait_until

from services.fuse_track.player import play
from services.fuse_track.recorder import Recorder
from shared.bus import BadInput
from shared.messages import Tracks

T0 = 1_703_001_600_050_000_000
STEP_NS = 100_000_000


def message(seq: int, site: str = "se", tracker: str = "tracker-a", n: int = 2) -> Tracks:
    """n tracks at tick seq, moving east 1 m per tick."""
    f4 = np.float32
    return Tracks(site=site, seq=seq, t_capture_ns=T0 + seq * STEP_NS, tracker=tracker,
                  id=np.arange(1, n + 1, dtype=np.int64), xy=np.column_stack([np.arange(n) * 5.0 + seq, np.ones(n)]),
                  latlon=np.tile([42.2294, -83.739], (n, 1)), velocity=np.tile(np.array([10.0, 0.0], f4), (n, 1)),
                  yaw=np.zeros(n, f4), size_lwh=np.tile(np.array([4.5, 1.8, 1.5], f4), (n, 1)),
                  vtype=np.arange(n, dtype=np.int8) % 5, score=np.full(n, 0.8, f4), age=np.full(n, seq, np.int32),
                  hits=np.full(n, seq, np.int32), cameras=[["NE", "SE"][: 1 + i % 2] for i in range(n)],
                  xy_cov=np.tile(np.array([[0.09, 0.02], [0.02, 0.16]], f4), (n, 1, 1)),
                  velocity_cov=np.tile(np.array([[0.25, 0.0], [0.0, 0.25]], f4), (n, 1, 1)),
                  yaw_confirmed=np.arange(n) % 2 == 0, yaw_std=np.full(n, 0.125, f4))


def recording(path: Path, seqs: range, **kw) -> Path:
    """A tracks file as fuse_track's recorder writes it."""
    rec = Recorder(path)
    for s in seqs:
        rec.write(message(s, **kw))
    rec.close()
    return path


def record_of(msg: Tracks) -> dict:
    return {"site": msg.site, "seq": msg.seq, "t_ns": msg.t_capture_ns, "tracker": msg.tracker, "tracks": msg.rows()}


# --- a tracks-file line back to its message ---------------------------------------------------------------------------


def test_a_recorded_line_gives_back_the_message_that_was_recorded(tmp_path):
    path = recording(tmp_path / "tracks.jsonl", range(3), n=3)
    for s, line in enumerate(path.read_text().splitlines()):
        back = Tracks.from_record(json.loads(line))
        sent = message(s, n=3)
        assert (back.site, back.seq, back.t_capture_ns, back.tracker) == (sent.site, s, sent.t_capture_ns, sent.tracker)
        assert back.rows() == sent.rows() and back.stamps == []  # the player stamps what it sends
        assert back.vtype.tolist() == sent.vtype.tolist() and back.cameras == sent.cameras
    assert len(Tracks.from_record({**record_of(message(0)), "tracks": []})) == 0


@pytest.mark.parametrize(("change", "named"), [
    (lambda r: r.pop("t_ns"), "tracks record without t_ns"),
    (lambda r: r.update(tracks={"id": 1}), "'tracks' must be a list of objects"),
    (lambda r: r["tracks"][1].pop("xy_cov"), "track 1 has no xy_cov (a file of an older schema version"),
    (lambda r: r["tracks"][0].update(type="tram"), "track 0 has type 'tram'"),
    (lambda r: r["tracks"][0].update(x="east"), "x/y must be numbers"),
    (lambda r: r["tracks"][0].update(xy_cov=[1.0, 2.0]), "xy_cov must be 2x2 matrices"),
    (lambda r: r["tracks"][0].update(xy_cov=[[1.0, 2.0], [2.0, 1.0]]), "xy_cov[0] is not a symmetric positive"),
    (lambda r: r["tracks"][0].update(yaw_std=0.0), "yaw_std[0] is not > 0"),
    (lambda r: r["tracks"][0].update(cameras="NE"), "cameras must be lists of names"),
    (lambda r: r["tracks"][0].update(yaw_confirmed=1), "yaw_confirmed must be true or false"),
    (lambda r: r["tracks"][0].update(vx=float("nan")), "contains NaN"),
    (lambda r: r.update(seq=-1), "seq"),
    (lambda r: r["tracks"][0].update(id=2**70), "id out of the range of int64"),
    (lambda r: r["tracks"][1].update(age=2**40), "age out of the range of int32"),
    (lambda r: r["tracks"][0].update(id="5"), "id must be integers"),
    (lambda r: r["tracks"][0].update(id=1.5), "id must be integers"),
    (lambda r: r["tracks"][0].update(score=True), "score must be numbers"),
    (lambda r: r["tracks"][0].update(xy_cov=[[1.0, "0"], [0.0, 1.0]]), "xy_cov must be 2x2 matrices of numbers"),
    # an integer too large for a float (1e400 written without its exponent): a ValueError, not an OverflowError
    (lambda r: r["tracks"][0].update(x=10**400), "x/y out of the range of float64"),
    (lambda r: r["tracks"][1].update(yaw_std=10**400), "yaw_std out of the range of float32"),
    (lambda r: r["tracks"][0].update(xy_cov=[[10**400, 0], [0, 1]]), "xy_cov out of the range of float32"),
])
def test_a_broken_record_is_named(change, named):
    record = record_of(message(4))
    change(record)
    with pytest.raises(ValueError, match=re.escape(named)):
        Tracks.from_record(record)
    with pytest.raises(ValueError, match="must be a JSON object, got list"):
        Tracks.from_record([record])


def test_a_line_with_a_number_too_large_for_a_float_is_counted_and_skipped(tmp_path):
    """`roadside play` counts such a line as bad and goes on; the tracks file's other readers (the Rerun sink,
    autolabel's teacher: shared.tracks_file) refuse it with a ValueError naming the field."""
    from services.fuse_track.player import records
    from shared.tracks_file import parse_tracks_message

    huge = record_of(message(1))
    huge["tracks"][0]["x"] = 10**400
    path = tmp_path / "tracks.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in (record_of(message(0)), huge, record_of(message(2)))) + "\n")
    bad: list[tuple[str, str]] = []
    assert [m.seq for _, m in records([path], lambda reason, where: bad.append((where, reason)))] == [0, 2]
    assert bad == [(f"{path}:2", "tracks record: x/y out of the range of float64")]
    for field, value, named in [("x", 10**400, "track 0: 'x' is an integer too large for a float"),
                                ("id", 10**400, "track 0: 'id' is an integer too large for a float"),
                                ("vx", 10**400, "track 0: 'vx' is an integer too large for a float"),
                                ("xy_cov", [[10**400, 0], [0, 1]], "track 0: xy_cov must be [[a, b], [b, c]]"),
                                ("yaw_std", 10**400, "track 0: yaw_std must be a finite number > 0")]:
        line = record_of(message(1))
        line["tracks"][0][field] = value
        with pytest.raises(ValueError, match=re.escape(named)):
            parse_tracks_message(line)
    line = record_of(message(1))
    line["t_ns"] = 10**400
    with pytest.raises(ValueError, match="'t_ns' is an integer too large for a float"):
        parse_tracks_message(line)


# --- the playback ------------------------------------------------------------------------------------------------


class Clock:
    """The waits play asks for, without waiting; stops once `stop_after` messages were published."""

    def __init__(self, got: list, stop_after: int | None = None) -> None:
        self.waits: list[float] = []
        self.got, self.stop_after = got, stop_after

    def __call__(self, wait_s: float) -> bool:
        if wait_s > 0:
            self.waits.append(wait_s)
        return self.stop_after is not None and len(self.got) >= self.stop_after


def test_play_publishes_every_message_in_order_at_the_recorded_pace(tmp_path):
    path = recording(tmp_path / "tracks.jsonl", range(11))
    got: list[Tracks] = []
    clock = Clock(got)
    done = play([path], got.append, 2.0, False, clock, BadInput("play"))
    assert [m.seq for m in got] == list(range(11)) and [m.rows() for m in got] == [message(s).rows() for s in range(11)]
    assert (done.published, done.passes, done.bad, done.site) == (11, 1, 0, "se")
    # 1 s of capture time at 2 x real time, the clock not moving on (the waits are not taken): the k-th message is
    # 0.05 k s after the first, less what the publishing took
    steps = np.diff([0.0, *clock.waits])
    assert len(clock.waits) == 10 and 0.4 < clock.waits[-1] <= 0.5 and np.all((steps > 0.03) & (steps <= 0.05)), steps
    got.clear()
    clock = Clock(got)
    assert play([path], got.append, None, False, clock, BadInput("play")).published == 11 and clock.waits == []


def test_rotated_files_play_in_order_and_a_loop_keeps_time_and_seq_going_on(tmp_path):
    files = [recording(tmp_path / "tracks.1.jsonl", range(0, 4)), recording(tmp_path / "tracks.jsonl", range(4, 6))]
    got: list[Tracks] = []
    done = play(files, got.append, None, True, Clock(got, stop_after=15), BadInput("play"))
    assert done.published == 15 and done.passes == 2
    seqs, times = [m.seq for m in got], [m.t_capture_ns for m in got]
    assert seqs == list(range(15))  # the second pass from 6: the largest seq plus one
    assert times == [T0 + s * STEP_NS for s in range(15)]  # the span (5 steps) plus one step: no gap, no overlap
    assert got[6].rows() == got[0].rows() and got[6].tracker == got[0].tracker


def test_bad_lines_and_other_sites_are_counted_and_skipped(tmp_path, caplog):
    path = recording(tmp_path / "tracks.jsonl", range(3))
    good = path.read_text().splitlines()
    other = json.dumps(record_of(message(3, site="elsewhere")))
    path.write_text("\n".join([good[0], "{not json", good[1], '{"site": "se"}', other, "", good[2]]) + "\n")
    got: list[Tracks] = []
    done = play([path], got.append, None, False, Clock(got), BadInput("play"))
    assert [m.seq for m in got] == [0, 1, 2] and done.bad == 3
    log = caplog.text
    assert f"{path}:2" in log and "not JSON" in log
    assert f"{path}:4" in log and "tracks record without seq, t_ns, tracker, tracks" in log
    assert f"{path}:5" in log and "site 'elsewhere', not the recording's 'se'" in log


def test_a_loop_counts_each_bad_line_once_and_a_deeply_nested_line_is_only_bad(tmp_path):
    path = recording(tmp_path / "tracks.jsonl", range(3))
    path.write_text(path.read_text() + "[" * 100_000 + "\n" + json.dumps({**record_of(message(3)), "tracks": [
        {**message(3).rows()[0], "id": 2**70}]}) + "\n")
    got: list[Tracks] = []
    done = play([path], got.append, None, True, Clock(got, stop_after=9), BadInput("play"))
    assert done.published == 9 and done.passes == 3 and done.bad == 2  # three passes, the two bad lines once


def test_a_capture_time_that_steps_back_restarts_the_pace_there(tmp_path, monkeypatch):
    """A recording whose clock steps back 0.5 s (fuse_track restarted with a new tracker): the messages after the
    step are paced from the step, not sent at once to catch up with the first message's time."""
    import services.fuse_track.player as player

    now = [100.0]
    monkeypatch.setattr(player.time, "monotonic", lambda: now[0])
    path = tmp_path / "tracks.jsonl"
    recording(path, range(10))
    with path.open("a") as f:  # the new tracker's ticks start 0.5 s before the last one's
        for k in range(10):
            f.write(json.dumps(record_of(message(k + 5, tracker="tracker-b"))) + "\n")
    sent: list[float] = []

    def wait(wait_s: float) -> bool:  # the clock moves on as play waits
        now[0] += wait_s
        return False

    play([path], lambda m: sent.append(now[0]), 1.0, False, wait, BadInput("play"))
    assert sent[9] == pytest.approx(100.9) and sent[10] == pytest.approx(100.9)  # the step: at once
    assert np.diff(sent[10:]) == pytest.approx([0.1] * 9)  # then at the recorded pace again



def test_a_loop_over_a_recording_that_steps_back_goes_on_one_interval_after_the_last_message(tmp_path, monkeypatch):
    """A 2 s session, then a 0.5 s one starting at the same capture time (fuse_track restarted after a clock step):
    each loop pass starts one interval after the last message published, not after the 1.5 s the pace would still
    count from the step back, and the capture times still go on increasing from pass to pass."""
    import services.fuse_track.player as player

    now = [100.0]
    monkeypatch.setattr(player.time, "monotonic", lambda: now[0])
    path = tmp_path / "tracks.jsonl"
    recording(path, range(20))
    with path.open("a") as f:
        for k in range(5):
            f.write(json.dumps(record_of(message(k, tracker="tracker-b"))) + "\n")
    sent: list[tuple[float, int]] = []

    def wait(wait_s: float) -> bool:  # the clock moves on as play waits
        now[0] += wait_s
        return len(sent) >= 75

    done = play([path], lambda m: sent.append((now[0], m.t_capture_ns)), 1.0, True, wait, BadInput("play"))
    assert done.passes == 3 and len(sent) == 75
    walls, times = np.array([w for w, _ in sent]), [t for _, t in sent]
    steps_back = [20, 45, 70]  # each pass's second session: published at once
    assert np.diff(walls)[[k - 1 for k in steps_back]] == pytest.approx([0.0] * 3)
    others = [k - 1 for k in range(1, 75) if k not in steps_back]  # the pass boundaries (25, 50) among them
    assert np.diff(walls)[others] == pytest.approx([0.1] * len(others))
    assert times[25] == max(times[:25]) + STEP_NS and times[50] == max(times[:50]) + STEP_NS  # time goes on

def test_a_recording_without_a_good_line_is_refused_naming_it(tmp_path):
    path = tmp_path / "tracks.jsonl"
    path.write_text("half a li")
    with pytest.raises(ValueError, match=f"no tracks message in {re.escape(str(path))} \\(1 bad lines\\)"):
        play([path], lambda m: None, None, True, lambda s: False, BadInput("play"))
    with pytest.raises(ValueError, match=r"tracks file .*missing\.jsonl"):
        play([tmp_path / "missing.jsonl"], lambda m: None, None, False, lambda s: False, BadInput("play"))


def test_roadside_play_refuses_missing_files_and_a_bad_pace(tmp_path, capsys):
    from roadside.cli import main

    assert main(["play", str(tmp_path / "none.jsonl")]) == 2
    assert "tracks file not found" in capsys.readouterr().err
    assert main(["play", str(tmp_path)]) == 2
    assert "not a tracks file (a folder?)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["play", str(tmp_path / "none.jsonl"), "--pace", "0"])
    assert "--pace" in capsys.readouterr().err


# --- on the bus --------------------------------------------------------------------------------------------------


def test_the_latest_tracks_are_answered_only_while_they_are_current():
    """The latest-tracks query (the player's, and fuse_track's with the same `current_payload`) answers with the
    newest message only while it was published within LATEST_MAX_AGE_S: with every camera down nothing is sent, and a
    client that joins then must not get old tracks as the current ones (nor a loop restarting stream() the same old
    message each time)."""
    import zenoh

    from services.fuse_track.player import LATEST_MAX_AGE_S, TracksPublisher, current_payload
    from shared.codec import decode
    from shared.keys import LATEST_ANY_AGE, latest_tracks_key

    assert current_payload([]) is None
    assert current_payload([(time.monotonic(), 0.1, b"new")]) == b"new"
    assert current_payload([(time.monotonic() - LATEST_MAX_AGE_S - 0.1, 0.1, b"old")]) is None
    # a playback slowed down (`--pace 0.05`: 4 s between messages): current for twice the time between them
    assert current_payload([(time.monotonic() - LATEST_MAX_AGE_S - 0.1, 4.0, b"slow")]) == b"slow"
    assert current_payload([(time.monotonic() - 8.1, 4.0, b"slow")]) is None
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    with zenoh.open(conf) as session:
        publish = TracksPublisher(session)
        try:
            publish(message(7))

            def answers() -> list[int]:
                return [decode(r.ok.payload.to_bytes(), Tracks).seq
                        for r in session.get(latest_tracks_key("se"), timeout=1.0) if r.ok is not None]

            assert answers() == [7]
            when, gap, payload = publish.latest[-1]
            publish.latest[:] = [(when - LATEST_MAX_AGE_S - 0.5, gap, payload)]  # as if nothing was sent since
            assert answers() == []
            # a restarted ingest asks where the tracks reached, however long fuse_track has been silent
            assert [decode(r.ok.payload.to_bytes(), Tracks).seq for r in session.get(
                f"{latest_tracks_key('se')}?{LATEST_ANY_AGE}", timeout=1.0) if r.ok is not None] == [7]
            publish(message(8))
            assert answers() == [8]
        finally:
            publish.close()


def looping_player(path: Path, port_base: int) -> subprocess.Popen:
    """`roadside play --loop` of a tracks file at 4 x its pace, as its own process on the embedded ports."""
    return subprocess.Popen([sys.executable, "-m", "roadside", "play", str(path), "--pace", "4", "--loop",
                             "--port-base", str(port_base)], cwd=REPO, env=service_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


@pytest.mark.slow
def test_a_vehicle_reads_a_played_recording_as_it_reads_a_cabinet(tmp_path):
    """`roadside play --loop` as its own process in fuse_track's place: a TrackClient gets the newest message at once
    and then the recorded ones, as recorded; SIGTERM stops the player, which says what it published."""
    from shared.bus import wait_for_peers
    from shared.client import TrackClient

    path = recording(tmp_path / "tracks.jsonl", range(20))
    port_base = free_port_base()
    proc = looping_player(path, port_base)
    try:
        with TrackClient("se", bus=_bus(port_base), wait_s=30.0) as client:
            answers: list[Tracks] = []  # fuse_track's query for a vehicle that joins late, once the player has begun
            assert wait_until(lambda: answers.append(client.latest(timeout_s=1.0)) or answers[-1] is not None, 30)
            assert answers[-1].rows() == message(answers[-1].seq % 20).rows()
            assert wait_for_peers(client.session, "roadside/se/alive/fuse_track/*", 1, 10.0) == 1
            stream = client.stream(timeout_s=30.0)
            got = [next(stream) for _ in range(25)]
            from shared.status import collect_status  # the player reports as fuse_track's "playback" instance

            reports: list = []  # the reports come every 2 s: one after the first messages counts them

            def counted() -> bool:
                reports[:] = collect_status(client.session, "se", 1.0)[0]
                return bool(reports) and reports[0].counts.get("tracks_out", 0) > 0

            assert wait_until(counted, 30)
            assert (reports[0].service, reports[0].instance) == ("fuse_track", "playback")
            assert reports[0].last_output_ns > 0
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "playing 1 file(s) on tcp/127.0.0.1:" in out and "looping" in out
    assert "messages of site se" in out and "0 bad lines" in out
    seqs = [m.seq for m in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), seqs
    for m in got:
        original = message(m.seq % 20)
        assert m.rows() == original.rows() and m.tracker == original.tracker
        assert [name for name, _ in m.stamps] == ["playback"]
        assert m.t_capture_ns == T0 + m.seq * STEP_NS  # a loop's times go on


def _bus(port_base: int):
    from shared.settings import BusSettings

    return BusSettings(port_base=port_base)


@pytest.mark.slow
def test_a_vehicle_asking_for_another_site_is_told_which_sites_the_bus_has(tmp_path):
    """`roadside tracks --site` of a site nobody publishes: no silence for ever, but the sites that are there."""
    path = recording(tmp_path / "tracks.jsonl", range(20))
    port_base = free_port_base()
    proc = looping_player(path, port_base)
    try:
        time.sleep(2.0)
        asked = subprocess.run([sys.executable, "-m", "roadside", "tracks", "--site", "elm", "--port-base",
                                str(port_base), "--timeout", "2", "--wait", "20"], cwd=REPO, env=service_env(),
                               capture_output=True, text=True, timeout=120)
        listener = subprocess.run([sys.executable, str(REPO / "examples" / "vehicle_listener.py"), "--site", "elm",
                                   "--connect", f"tcp/127.0.0.1:{port_base + 3}", "--timeout", "2"], cwd=REPO,
                                  env=service_env(), capture_output=True, text=True, timeout=120)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert asked.returncode == 1 and asked.stdout == ""
    assert "no tracks of site elm on this bus; it has site se (--site)" in asked.stderr, asked.stderr
    assert listener.stdout == "" and "no tracks of site elm on this bus; it has se (--site)" in listener.stderr, \
        listener.stderr


# --- on a site's bus (--site) --------------------------------------------------------------------------------------


def site_file(folder: Path, name: str, port_base: int, **bus) -> Path:
    """A one-camera site.yaml whose bus is on `port_base` (not the embedded default's 7451)."""
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "site.yaml").write_text(yaml.safe_dump({
        "site": name, "cameras": [{"name": "NE", "kind": "fisheye", "width": 64, "height": 64}],
        "bus": {"port_base": port_base, **bus}}))
    return folder


def test_play_takes_its_bus_from_the_site_and_the_flags_over_it(tmp_path):
    import argparse

    import yaml

    from roadside.cli_bus import DEFAULT_PORT_BASE, _play_bus, add_bus_jobs

    parser = argparse.ArgumentParser()
    add_bus_jobs(parser.add_subparsers(dest="job"))

    def bus(*flags: str):
        return _play_bus(parser.parse_args(["play", "tracks.jsonl", *flags]))

    b, name = bus()  # without --site: the embedded default's bus, as before
    assert name is None and (b.mode, b.port_base, b.host, b.connect) == ("peer", DEFAULT_PORT_BASE, "127.0.0.1", [])
    b, _ = bus("--port-base", "20000")
    assert (b.mode, b.port_base) == ("peer", 20000)
    b, _ = bus("--connect", "tcp/10.0.0.2:7447")
    assert (b.mode, b.connect) == ("client", ["tcp/10.0.0.2:7447"])
    site = site_file(tmp_path / "elm", "elm", 31000, host="127.0.0.2", status_period_s=5.0)
    for given in (site, site / "site.yaml"):
        b, name = bus("--site", str(given))
        assert name == "elm" and (b.mode, b.port_base, b.host, b.status_period_s) == ("peer", 31000, "127.0.0.2", 5.0)
    b, _ = bus("--site", str(site), "--port-base", "20000")  # the flag over the file's
    assert (b.mode, b.port_base, b.host) == ("peer", 20000, "127.0.0.2")
    cabinet = site_file(tmp_path / "cab", "cab", 31000, mode="client", connect=["tls/10.0.0.2:7448"],
                        tls_root_ca="/etc/ca.pem")
    b, _ = bus("--site", str(cabinet))  # a cabinet's router, checked by its CA
    assert (b.mode, b.connect, b.tls_root_ca) == ("client", ["tls/10.0.0.2:7448"], Path("/etc/ca.pem"))
    b, _ = bus("--site", str(cabinet), "--connect", "tls/10.0.0.3:7448")  # another router: the file's CA still checks
    assert (b.mode, b.connect, b.tls_root_ca) == ("client", ["tls/10.0.0.3:7448"], Path("/etc/ca.pem"))
    b, name = bus("--site", "example")  # a name: deploy/sites/example
    assert name == yaml.safe_load((REPO / "deploy" / "sites" / "example" / "site.yaml").read_text())["site"]
    with pytest.raises(ValueError, match="site not found"):
        bus("--site", str(tmp_path / "nosuch"))


def test_roadside_play_refuses_a_recording_of_another_site_than_sites(tmp_path, capsys):
    """The recording's tracks are of site se, --site's is elm: a vehicle asking for elm would not see them."""
    from roadside.cli import main

    path = recording(tmp_path / "tracks.jsonl", range(3))
    site = site_file(tmp_path / "elm", "elm", free_port_base())
    assert main(["play", str(path), "--site", str(site)]) == 2
    err = capsys.readouterr().err
    assert "the recording's tracks are of site se, not of site elm" in err and "--site se" in err, err


@pytest.mark.slow
def test_play_on_a_site_reaches_the_vehicles_of_that_site(tmp_path):
    """`roadside play FILE --site SITE` then `roadside tracks --site SITE` (the README's sequence) on a site whose
    bus.port_base is not the default: the tracks arrive, and a TrackClient on the site's bus gets them too."""
    from shared.client import TrackClient
    from shared.settings import load_settings

    path = recording(tmp_path / "tracks.jsonl", range(20))
    port_base = free_port_base()
    site = site_file(tmp_path / "site", "se", port_base)
    proc = subprocess.Popen([sys.executable, "-m", "roadside", "play", str(path), "--pace", "4", "--loop", "--site",
                             str(site)], cwd=REPO, env=service_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        with TrackClient("se", bus=load_settings(site).bus, wait_s=30.0) as client:
            got: list = []
            assert wait_until(lambda: got.append(client.latest(timeout_s=1.0)) or got[-1] is not None, 30)
            assert got[-1].rows() == message(got[-1].seq % 20).rows()
        asked = subprocess.run([sys.executable, "-m", "roadside", "tracks", "--site", str(site), "--json", "--count",
                                "3", "--timeout", "10", "--wait", "20"], cwd=REPO, env=service_env(),
                               capture_output=True, text=True, timeout=120)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert f"playing 1 file(s) on tcp/127.0.0.1:{port_base + 3}," in out, out
    assert asked.returncode == 0, asked.stderr
    lines = [json.loads(line) for line in asked.stdout.splitlines()]
    assert len(lines) == 3 and {r["site"] for r in lines} == {"se"}
    assert all(r["tracks"] == message(r["seq"] % 20).rows() for r in lines)
