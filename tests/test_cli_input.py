"""Bad input at the command line and in the files it reads: one clear error naming the flag, field or file, exit 2
(or 1 where the job ran and found nothing), never a traceback. Each case below was once a traceback or a silent
misreading (a review of every `roadside` job with bad input, 2026-11-28)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from roadside.cli import main
from shared.settings import BusSettings, check_endpoint, load_settings

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE_SITE = ROOT / "deploy" / "sites" / "example" / "site.yaml"


@pytest.mark.parametrize(("argv", "message"), [
    (["tracks", "--connect", "garbage"], "argument --connect: not a Zenoh endpoint: 'garbage'"),
    (["tracks", "--connect", "tcp/cabinet"], "tcp needs HOST:PORT"),
    (["status", "--connect", "tcp/cabinet:99999"], "the port 0-65535"),
    (["tracks", "--count", "-3"], "argument --count: must be a whole number >= 1, got -3"),
    (["tracks", "--timeout", "0"], "argument --timeout: must be a finite number > 0"),
    (["tracks", "--port-base", "80"], "argument --port-base: must be a port from 1024 to 65000, got 80"),
    (["tracks", "--wait", "-1"], "argument --wait: must be a finite number >= 0"),
    (["tracks", "--ahead-ms", "2500"], "argument --ahead-ms: must be at most 2000 ms, got 2500"),
    (["tracks", "--ahead-ms", "100", "--now"], "argument --now: not allowed with argument --ahead-ms"),
    (["health", "--site", str(EXAMPLE_SITE), "--service", "detect", "--timeout", "-1"], "argument --timeout"),
    (["viz", "--live", "--site", str(EXAMPLE_SITE), "--out", "x.rrd", "--connect", "garbage"], "not a Zenoh endpoint"),
    (["train", "--steps", "0", "--out", "x"], "argument --steps: must be a whole number >= 1, got 0"),
    (["eval", "real", "--score-thr", "5"], "argument --score-thr: must be a score from 0 to 1, got 5"),
    (["eval", "detector", "--threads", "0"], "argument --threads: must be a whole number >= 1"),
    (["static", "--score-thr", "-1"], "argument --score-thr: must be a score from 0 to 1"),
    (["calibrate", "--landmarks", "l.json", "--kind", "pinhole", "--out", "m.npz", "--width", "0"],
     "argument --width: must be a whole number >= 1, got 0"),
    (["calibrate", "--landmarks", "l.json", "--kind", "pinhole", "--out", "m.npz", "--segments", "-2"],
     "argument --segments: must be a whole number >= 1"),
])
def test_flags_out_of_range_are_refused_by_name(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_bus_jobs_say_when_the_bus_cannot_be_reached_and_live_viz_keeps_the_file_it_would_replace(tmp_path, capsys):
    assert main(["status", "--connect", "tcp/127.0.0.1:9"]) == 2  # nothing listens on port 9
    assert "cannot reach the bus" in capsys.readouterr().err
    out = tmp_path / "earlier.rrd"
    out.write_bytes(b"an earlier recording")
    assert main(["viz", "--live", "--site", str(EXAMPLE_SITE), "--out", str(out), "--basemap",
                 str(tmp_path / "missing.yaml"), "--connect", "tcp/127.0.0.1:9"]) == 2
    assert "basemap world file not found" in capsys.readouterr().err
    assert out.read_bytes() == b"an earlier recording"


def test_viz_refuses_frame_flags_without_frames(tmp_path, capsys):
    tracks = tmp_path / "t.jsonl"
    tracks.write_text("")
    for flags in (["--model", "m.onnx"], ["--frames-every", "2"]):
        assert main(["viz", str(tracks), "--out", str(tmp_path / "o.rrd"), *flags]) == 2
        assert "go with --frames" in capsys.readouterr().err


def test_sim_checks_its_contact_sheet_name_before_the_clip(tmp_path, capsys):
    out = tmp_path / "clip"
    argv = ["sim", "--site", "intersection", "--seconds", "0.1", "--out", str(out)]
    assert main([*argv, "--contact-sheet", str(tmp_path / "sheet.txt")]) == 2
    assert "--contact-sheet" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize(("flag", "message"), [
    (["--landmarks", "3"], "landmarks must be from 5 to 1000 per camera"),
    (["--landmarks", "-1"], "landmarks must be from 5 to 1000 per camera"),
    (["--hz", "0.5"], "hz must be from 1 to 100"),
    (["--pace", "bogus"], "pace must be a speed factor"),
    (["--model", "/nonexistent/detector.onnx"], "detector model not found"),
])
def test_the_demo_checks_its_flags_before_minutes_of_simulation(flag, message, tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), *flag]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists(), "nothing is simulated or written for a demo that cannot run"


@pytest.mark.parametrize("good", ["tcp/zenoh:7447", "tcp/192.168.1.10:7447", "tcp/[::1]:7447",
                                  "tcp/0.0.0.0:7447#iface=eth0", "udp/cabinet:7447", "unixsock-stream//tmp/z.sock"])
def test_zenoh_endpoints_that_are_well_formed_pass(good):
    assert check_endpoint(good) == good
    assert BusSettings(mode="client", connect=[good]).connect == [good]


@pytest.mark.parametrize("bad", ["garbage", "tcp/cabinet", "tcp/cabinet:70000", "http/cabinet:80", "tcp/", ""])
def test_malformed_zenoh_endpoints_are_refused_naming_them(bad):
    with pytest.raises(ValueError, match="not a Zenoh endpoint"):
        check_endpoint(bad)
    with pytest.raises(ValidationError, match="not a Zenoh endpoint"):
        BusSettings(listen=[bad])
        load_settings(EXAMPLE_SITE, bus={"mode": "client", "connect": [bad]})


def test_a_site_file_with_a_number_for_a_key_or_of_binary_bytes_is_named(tmp_path):
    numbered = tmp_path / "numbered.yaml"
    numbered.write_text(EXAMPLE_SITE.read_text() + "\n42: foo\n")
    with pytest.raises(ValueError, match=r"numbered.yaml: top-level keys must be names, got 42"):
        load_settings(numbered)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(bytes(range(128, 256)))
    with pytest.raises(ValueError, match=r"binary.yaml: not a text file"):
        load_settings(binary)


def _line(k: int, t_ns: int | None = None) -> str:
    row = {"id": 3, "x": float(k), "y": 0.0, "yaw": 0.0, "length": 4.5, "width": 1.8, "type": "car"}
    return json.dumps({"site": "s1", "seq": k, "t_ns": 1_700_000_000_000_000_000 + k * 100_000_000 if t_ns is None
                       else t_ns, "tracker": "t0", "tracks": [row]})


def test_viz_skips_a_line_from_beyond_2262_and_fails_on_a_file_with_no_valid_line(tmp_path, capsys):
    mixed = tmp_path / "mixed.jsonl"
    mixed.write_text("\n".join([_line(0), _line(1, t_ns=10**30), _line(2)]) + "\n")
    assert main(["viz", str(mixed), "--out", str(tmp_path / "mixed.rrd")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["messages"], summary["bad_lines"], summary["first_bad_line"]) == (2, 1, 2)
    assert "< 2**63" in summary["first_bad_reason"]

    bad = tmp_path / "bad.jsonl"
    bad.write_text("garbage\n" + _line(0, t_ns=-5) + "\n")
    assert main(["viz", str(bad), "--out", str(tmp_path / "bad.rrd")]) == 1
    assert f"no valid tracks line in {bad} (2 lines; line 1: JSONDecodeError" in capsys.readouterr().err
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    assert main(["viz", str(empty), "--out", str(tmp_path / "empty.rrd")]) == 1
    assert "(0 lines)" in capsys.readouterr().err


def test_eval_names_the_line_of_a_binary_tracks_file(tmp_path):
    from eval.tracking import load_tracks

    binary = tmp_path / "tracks.jsonl"
    binary.write_bytes(bytes(range(128, 256)) + b"\n")
    with pytest.raises(ValueError, match=f"{binary}: line 1: not valid JSON"):
        load_tracks(binary)


def test_bench_detector_names_a_model_it_cannot_load(tmp_path, capsys):
    garbage = tmp_path / "model.onnx"
    garbage.write_bytes(b"not a model")
    assert main(["bench", "detector", "--model", str(garbage), "--runs", "1", "--warmup", "0"]) == 2
    assert f"{garbage}: not a loadable ONNX model" in capsys.readouterr().err
    assert main(["bench", "detector", "--model", str(tmp_path / "missing.onnx")]) == 2
    assert "missing.onnx: not a loadable ONNX model" in capsys.readouterr().err


def test_the_track_client_and_the_detector_refuse_impossible_numbers():
    from shared.client import TrackClient
    from shared.inference import OnnxDetector

    with pytest.raises(ValueError, match="wait_s must be at most"):
        TrackClient("s1", connect=["tcp/127.0.0.1:7454"], wait_s=1e306)
    with pytest.raises(ValueError, match="wait_s must be a finite number"):
        TrackClient("s1", connect=["tcp/127.0.0.1:7454"], wait_s=math.nan)
    with pytest.raises(ValueError, match="not a Zenoh endpoint"):
        TrackClient("s1", connect=["garbage"])
    model = ROOT / "models" / "detector_fp32.onnx"
    for threads in (0, 10**11):
        with pytest.raises(ValueError, match="threads must be a whole number from 1 to 256"):
            OnnxDetector(model, threads=threads)


def test_a_landmark_csv_with_a_header_and_no_rows_is_not_said_to_lack_columns(tmp_path):
    from calibration.landmarks import load_landmarks

    csv = tmp_path / "lm.csv"
    csv.write_text("id,u,v,lat,lon\n")
    landmarks, _ = load_landmarks(csv)  # none: calibrate then says there are fewer than 4
    assert len(landmarks) == 0
    csv.write_text("id,u,v,lat\n")
    with pytest.raises(ValueError, match="CSV header lacks column"):
        load_landmarks(csv)


def test_a_composite_of_less_than_one_image_is_refused():
    from training.composite import CompositeConfig

    with pytest.raises(ValueError, match=r"seconds 0\.5 at hz 1 is not one image"):
        CompositeConfig(seconds=0.5, hz=1.0)


def test_a_bad_value_from_the_environment_or_a_flag_is_not_blamed_on_the_site_file(monkeypatch):
    with pytest.raises(ValueError, match=r"less than 1 \(given on the command line: --set or a flag\)"):
        load_settings(EXAMPLE_SITE, detect={"score_thr": 7})
    assert load_settings(EXAMPLE_SITE).detect.score_thr <= 1  # the file's own values are fine
    monkeypatch.setenv("ROADSIDE_DETECT__SCORE_THR", "nan")
    with pytest.raises(ValueError, match=r"score_thr: .*\(given by the environment: ROADSIDE_DETECT__SCORE_THR\)"):
        load_settings(EXAMPLE_SITE)
    monkeypatch.delenv("ROADSIDE_DETECT__SCORE_THR")
    monkeypatch.setenv("ROADSIDE_BUS", "{not json")
    with pytest.raises(ValueError, match=r"the environment: ROADSIDE_BUS must be JSON \(an object\)"):
        load_settings(EXAMPLE_SITE)


def test_a_flag_wins_over_the_environment_which_wins_over_the_file(monkeypatch):
    """Inside a compose container ROADSIDE_FUSE_TRACK__RECORD is always set: a replay given `--set
    fuse_track.record=...` appended to the cabinet's live recording when the environment won over the flag."""
    monkeypatch.setenv("ROADSIDE_FUSE_TRACK__RECORD", "/data/tracks.jsonl")
    monkeypatch.setenv("ROADSIDE_INGEST__PACE", "1")
    monkeypatch.setenv("ROADSIDE_BUS__PORT_BASE", "31000")
    s = load_settings(EXAMPLE_SITE, fuse_track={"record": "/data/replay.jsonl"}, ingest={"pace": "max"})
    assert str(s.fuse_track.record) == "/data/replay.jsonl" and s.ingest.pace == "max"
    assert s.bus.port_base == 31000  # the environment still wins over the file where no flag names the field
    file = load_settings(EXAMPLE_SITE, detect={"workers": 1})
    assert str(file.fuse_track.record) == "/data/tracks.jsonl" and file.ingest.pace == "1" and file.detect.workers == 1
    monkeypatch.setenv("ROADSIDE_DETECT__SCORE_THR", "0.2")
    with pytest.raises(ValueError, match=r"score_thr: .*\(given on the command line: --set or a flag\)"):
        load_settings(EXAMPLE_SITE, detect={"score_thr": 7})  # the flag's value is the one refused, and named


def test_a_masks_file_that_is_no_archive_and_a_zero_stride_are_named(tmp_path, capsys):
    from calibration.masks import load_masks

    bad = tmp_path / "NE.npz"
    bad.write_text("not an archive")
    with pytest.raises(ValueError) as exc:
        load_masks(bad)
    assert f"{bad}: not a lookup masks file (not an .npz archive" in str(exc.value)
    assert "allow_pickle" not in str(exc.value), "numpy's advice to load it unsafely is not ours to give"
    with pytest.raises(SystemExit) as stop:
        main(["bench", "calibration", "--stride", "0"])
    assert stop.value.code == 2 and "--stride: must be a whole number >= 1" in capsys.readouterr().err


def test_a_site_file_naming_one_camera_twice_says_which_field(tmp_path):
    site = tmp_path / "site.yaml"
    site.write_text("site: t\ncameras:\n" + 2 * "  - {name: A, kind: fisheye, width: 64, height: 48, masks: a.npz}\n")
    with pytest.raises(ValueError, match=r"site.yaml: cameras: .*duplicate camera names \['A'\]$"):
        load_settings(site)  # and not blamed on the command line


def test_mix_names_an_output_that_is_a_folder(tmp_path, capsys):
    pytest.importorskip("torch")
    model = ROOT / "models" / "detector.pt"
    assert main(["mix", str(model), str(model), "--weight", "0.5", "--out", str(tmp_path)]) == 2
    assert f"Is a directory: '{tmp_path}'" in capsys.readouterr().err


def test_a_missing_tls_ca_is_named_before_any_connection(tmp_path, capsys):
    from roadside.cli import main

    missing = tmp_path / "cabinet-ca.pem"
    assert main(["tracks", "--connect", "tls/localhost:7448", "--ca", str(missing), "--wait", "1"]) == 2
    assert f"bus.tls_root_ca: CA certificate not found: {missing}" in capsys.readouterr().err


def test_a_certificate_without_its_key_and_a_roi_radius_without_its_centre_are_one_line_errors(capsys):
    assert main(["tracks", "--cert", "vehicle.pem", "--connect", "tcp/127.0.0.1:7447"]) == 2
    err = capsys.readouterr().err
    assert err == ("roadside tracks: error: bus.tls_certificate is given without bus.tls_private_key: mutual TLS needs "
                   "both\n")
    assert main(["calibrate", "--landmarks", "l.json", "--kind", "fisheye", "--out", "m.npz", "--roi-radius", "5"]) == 2
    assert "--roi-radius goes with --roi-center" in capsys.readouterr().err


def test_output_read_by_a_reader_that_goes_away_ends_quietly(tmp_path):
    """`roadside counts ... | head -1`: no error line when head closes the pipe."""
    import subprocess
    import sys

    tracks = tmp_path / "tracks.jsonl"
    tracks.write_text("".join(json.dumps({"site": "state_ellsworth", "seq": k, "t_ns": 1_703_001_600_000_000_000
                                          + k * 10**8, "tracker": "t", "tracks": []}) + "\n" for k in range(50)))
    site = ROOT / "deploy" / "sites" / "state_ellsworth"
    run = subprocess.run(f"{sys.executable} -m roadside counts {tracks} --site {site} --csv --bin-s 1 | head -1",
                         shell=True, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.stdout == "start,end,observed_s,from,to,turn,vehicles\n", run.stdout
    assert "error" not in run.stderr and "Broken" not in run.stderr, run.stderr


def test_the_demos_simulated_tracks_are_not_scored_as_the_real_sites(tmp_path, capsys):
    """The demo replays a simulated State/Ellsworth at the real footage's UTC minute: under the real site's name its
    tracks were scored against the hand labels of real frames as if they were the real pipeline's."""
    from roadside.demo import DEMO_SITE

    tracks = tmp_path / "tracks.jsonl"
    tracks.write_text("".join(json.dumps({"site": DEMO_SITE, "seq": k, "t_ns": 1_703_001_600_000_000_000 + k * 10**8,
                                          "tracker": "t", "tracks": []}) + "\n" for k in range(5)))
    site = ROOT / "deploy" / "sites" / "state_ellsworth"
    assert DEMO_SITE != load_settings(site).site
    for argv in (["eval", "real", "--tracks", str(tracks), "--site", str(site)],
                 ["counts", str(tracks), "--site", str(site)]):
        assert main(argv) == 2
        assert f"the tracks are of site {DEMO_SITE}" in capsys.readouterr().err


@pytest.mark.parametrize(("host", "why"), [
    ("127.0.0.1:7447", "'127.0.0.1:7447' holds a port: give the address alone"),
    ("cabinet:7447", "'cabinet:7447' holds a port"),
    ("", "'' is empty"),
    ("my host", "'my host' holds a space"),
    ("192.168.1.300", "'192.168.1.300' is not an IP address"),
    ("cabinet..local", "'cabinet..local' is not an IP address or host name"),
])
def test_a_bus_host_with_a_port_a_space_or_no_address_is_refused_naming_the_field(host, why, monkeypatch):
    """Such a host loaded, and every service then died on Zenoh's anonymous lookup error with status 1, restarted for
    ever by `roadside up`."""
    monkeypatch.delenv("ROADSIDE_BUS__HOST", raising=False)
    with pytest.raises(ValueError, match=rf"site.yaml: bus.host: {re.escape(why)}"):
        load_settings(EXAMPLE_SITE, bus={"host": host})
    for good in ("127.0.0.1", "0.0.0.0", "::1", "[::1]", "localhost", "cabinet.local", "roadside_detect"):
        assert BusSettings(host=good).host == good


def test_roadside_up_names_a_bus_host_that_cannot_be_resolved(monkeypatch):
    """The port pre-check of `roadside up` let a name that does not resolve through: four services restarted for
    ever on Zenoh's lookup error."""
    import socket

    from shared.bus import ports_in_use

    def no_such_host(*args, **kwargs):
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_such_host)
    with pytest.raises(ValueError, match=r"^bus.host cabinet.invalid cannot be resolved \(Name or service not known\)"):
        ports_in_use(BusSettings(host="cabinet.invalid", port_base=17921))
    monkeypatch.undo()
    try:  # an IPv6 address is checked as one, where this machine has IPv6 (a container may not)
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
    except OSError:
        pytest.skip("this machine has no IPv6 loopback (the rest of the test ran)")
    assert ports_in_use(BusSettings(host="::1", port_base=17921)) == []


def test_a_key_given_twice_in_the_site_file_is_refused_with_both_lines(tmp_path):
    """PyYAML keeps the last of two equal keys: a `fuse_track:` section appended at the end replaced the whole tuned
    one silently, and a camera's second `masks:` its first."""
    site = tmp_path / "site.yaml"
    text = EXAMPLE_SITE.read_text()
    first = next(i for i, line in enumerate(text.splitlines(), 1) if line.startswith("fuse_track:"))
    site.write_text(text + "\nfuse_track:\n  record: tracks.jsonl\n")
    last = len(text.splitlines()) + 2
    with pytest.raises(ValueError, match=rf"site.yaml: line {last}: fuse_track is given twice \(first at line "
                                         rf"{first}\)$"):
        load_settings(site)
    site.write_text("site: t\ncameras:\n  - name: A\n    kind: fisheye\n    width: 64\n    height: 48\n"
                    "    masks: a.npz\n    masks: b.npz\n")
    with pytest.raises(ValueError, match=r"site.yaml: line 8: masks is given twice \(first at line 7\)$"):
        load_settings(site)
    # a merge's keys may be given again: that is what the merge is for
    site.write_text("site: t\nx-cam: &cam {kind: fisheye, width: 64, height: 48}\ncameras:\n"
                    "  - {<<: *cam, name: A, width: 32}\n")
    with pytest.raises(ValueError, match="x-cam"):  # an unknown top-level key, not a duplicate
        load_settings(site)
    # at any depth: a nested merge (PyYAML rewrites the anchored mapping before it is checked) is no duplicate
    site.write_text("site: t\norigin: &o {<<: &s {lat_deg: 42.0, lon_deg: -83.0}, lat_deg: 42.1}\n"
                    "movements:\n  center: {<<: *o, lon_deg: -83.1}\n"
                    "  legs: [{name: n, bearing_deg: 0}, {name: s, bearing_deg: 180}]\n"
                    "  inner_radius_m: 20\n  outer_radius_m: 60\n"
                    "cameras:\n  - {name: A, kind: fisheye, width: 32, height: 48}\n")
    assert load_settings(site).origin["lat_deg"] == 42.1


def test_two_cameras_with_one_masks_file_are_refused_naming_both(tmp_path):
    """A copied camera entry that kept the other's masks: both cameras got one position and one lookup."""
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "NE.npz").write_bytes(b"")
    (tmp_path / "masks" / "link.npz").symlink_to(tmp_path / "masks" / "NE.npz")
    site = tmp_path / "site.yaml"

    def write(*masks: str) -> None:
        site.write_text("site: t\ncameras:\n" + "".join(
            f"  - {{name: {n}, kind: fisheye, width: 64, height: 48, masks: {m}}}\n"
            for n, m in zip(("NE", "NW", "SE"), masks, strict=True)))

    write("masks/NE.npz", "masks/NW.npz", "masks/NE.npz")
    with pytest.raises(ValueError, match=r"site.yaml: cameras: cameras NE and SE name the same masks file "
                                         r"masks/NE.npz: each camera needs its own"):
        load_settings(site)
    write("masks/NE.npz", "masks/NW.npz", str(tmp_path / "masks" / "link.npz"))  # another name, the same file
    with pytest.raises(ValueError, match=rf"cameras NE and SE name the same masks file \(masks/NE.npz and "
                                         rf"{re.escape(str(tmp_path))}/masks/link.npz\)"):
        load_settings(site)
    write("masks/NE.npz", "masks/NW.npz", "masks/SE.npz")
    assert [c.name for c in load_settings(site).cameras] == ["NE", "NW", "SE"]


@pytest.mark.parametrize(("name", "value", "example"), [
    ("ROADSIDE_BUS__CONNECT", "tcp/router:7447", """ROADSIDE_BUS__CONNECT='["tcp/router:7447"]'"""),
    ("ROADSIDE_MOVEMENTS__LEGS", "x", "ROADSIDE_MOVEMENTS__LEGS='[...]'"),
    ("ROADSIDE_BUS", "mode=client", """ROADSIDE_BUS='{"mode": ...}'"""),
])
def test_a_list_or_section_from_the_environment_that_is_not_json_names_the_variable(name, value, example,
                                                                                     monkeypatch):
    """The error named the section ("bus") and every ROADSIDE_ variable set, not the one at fault, nor that it must
    be JSON."""
    monkeypatch.setenv("ROADSIDE_BUS__MODE", "client")
    monkeypatch.setenv(name, value)
    kind = "an object" if name == "ROADSIDE_BUS" else "a list"
    with pytest.raises(ValueError) as exc:
        load_settings(EXAMPLE_SITE)
    assert str(exc.value) == (f"{EXAMPLE_SITE}: the environment: {name} must be JSON ({kind}), e.g. {example}; got "
                              f"{value!r}")
    monkeypatch.setenv("ROADSIDE_BUS__CONNECT", '["tcp/router:7447"]')
    monkeypatch.delenv("ROADSIDE_BUS", raising=False)
    monkeypatch.delenv("ROADSIDE_MOVEMENTS__LEGS", raising=False)
    assert load_settings(EXAMPLE_SITE).bus.connect == ["tcp/router:7447"]


def _load_error(tmp_path: Path, text: str) -> tuple[Path, str]:
    """A site file of `text` and the error loading it gives."""
    site = tmp_path / "site.yaml"
    site.write_text(text)
    with pytest.raises(ValueError) as exc:
        load_settings(site)
    return site, str(exc.value)


def test_a_yaml_syntax_error_is_one_line_with_the_file_line_and_column(tmp_path, capsys):
    """PyYAML's message spans five lines and names "<unicode string>", not the file."""
    from services.localize.__main__ import main as localize_main
    from shared.service import run

    site, error = _load_error(tmp_path, "site: x\ncameras:\n\t- {name: A, kind: pinhole, width: 10, height: 10}\n")
    assert error == (f"{site}: not valid YAML at line 3, column 1: found character '\\t' that cannot start any token "
                     "(a tab cannot indent YAML: use spaces)")
    assert run("localize", localize_main, ["--site", str(site)]) == 2
    assert capsys.readouterr().err == f"localize: error: {error}\n"
    site.write_text("site: [unclosed\n")
    with pytest.raises(ValueError, match=r"site.yaml: not valid YAML at line 2, column 1: expected ',' or ']', but got "
                                         r"'<stream end>'$"):
        load_settings(site)


def test_a_status_period_is_0_or_at_least_a_tenth_of_a_second():
    """1e-5 s made an idle service publish status reports in a busy loop."""
    with pytest.raises(ValueError, match=r"bus.status_period_s: must be 0 \(no status reports\) or at least 0.1 s, "
                                         r"got 1e-05"):
        load_settings(EXAMPLE_SITE, bus={"status_period_s": 0.00001})
    assert load_settings(EXAMPLE_SITE, bus={"status_period_s": 0}).bus.status_period_s == 0
    assert load_settings(EXAMPLE_SITE, bus={"status_period_s": 0.1}).bus.status_period_s == 0.1


def test_a_refused_name_says_ascii_letters_without_pydantics_prefix(tmp_path):
    """"Value error, " inside the line, and "letters" for a name refused for its 'ü'."""
    site, error = _load_error(tmp_path, "site: x\ncameras:\n  - {name: Süd, kind: pinhole, width: 10, height: 10}\n")
    assert error == (f"{site}: cameras.0.name: camera name must be 1-64 letters, digits, '_' or '-' (ASCII letters "
                     "only: A-Z, a-z), got 'Süd'")


def test_a_folder_given_as_the_model_is_said_to_be_a_folder(tmp_path):
    from services.detect.__main__ import load_detector

    site = tmp_path / "site.yaml"
    (tmp_path / "det.onnx").mkdir()
    site.write_text("site: x\ncameras:\n  - {name: NE, kind: pinhole, width: 10, height: 10}\n"
                    "detect: {model: det.onnx, model_gpu: null, providers: [CPUExecutionProvider]}\n")
    with pytest.raises(ValueError, match=rf"^detector model {re.escape(str(tmp_path / 'det.onnx'))} is a folder, not "
                                         "a model file"):
        load_detector(load_settings(site))
