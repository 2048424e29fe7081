"""`roadside check`: a site's pre-flight runs every service's start-up checks and reports every problem at once."""

from __future__ import annotations

import copy
import json
import shutil
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from pipeline_fixtures import CAMERA, export_tiny_detector, free_port_base, site_config, write_exact_masks, write_site

from roadside.cli import main


@pytest.fixture(scope="module")
def good_site(small_recording, tmp_path_factory):
    folder = tmp_path_factory.mktemp("site")
    write_exact_masks(small_recording, CAMERA, folder / "masks" / f"{CAMERA}.npz")
    export_tiny_detector(folder / "model.onnx")
    config = site_config(small_recording)
    config["fuse_track"]["record"] = "out/tracks.jsonl"
    return folder, config


def checked(capsys, site, *flags: str) -> tuple[int, dict]:
    rc = main(["check", "--site", str(site), "--json", *flags])
    return rc, json.loads(capsys.readouterr().out)


def by_name(doc: dict) -> dict[str, dict]:
    return {c["name"]: c for c in doc["checks"]}


def test_a_good_site_passes_every_check_and_says_what_it_found(good_site, capsys):
    folder, config = good_site
    site = write_site(folder, config)
    port_base = free_port_base()
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={port_base}")
    assert rc == 0 and doc["ok"], doc
    checks = by_name(doc)
    assert set(checks) == {f"masks {CAMERA}", "detector", f"source {CAMERA}", "fusion", "tracks recording", "bus"}
    assert "1280x960, ground lookup for" in checks[f"masks {CAMERA}"]["detail"]
    assert "CPUExecutionProvider" in checks["detector"]["detail"] and f"{CAMERA} " in checks["detector"]["detail"]
    assert "2 frames over 0.5 s" in checks[f"source {CAMERA}"]["detail"]
    assert "published at 640x480" in checks[f"source {CAMERA}"]["detail"]
    assert f"fuse_track.record: {folder / 'out' / 'tracks.jsonl'}: to be made in {folder}" in \
        checks["tracks recording"]["detail"]
    assert not (folder / "out").exists()  # the check makes nothing
    assert f"ports {port_base}-{port_base + 3} free" in checks["bus"]["detail"]
    assert main(["check", "--site", str(site), "--set", f"bus.port_base={port_base}"]) == 0
    assert "all 6 checks passed" in capsys.readouterr().out


def test_every_problem_is_reported_at_once_each_naming_what_is_wrong(good_site, capsys, tmp_path):
    folder, config = good_site
    bad = copy.deepcopy(config)
    bad["cameras"][0]["masks"] = "masks/missing.npz"
    bad["detect"]["model"] = "no-such-model.onnx"
    small = tmp_path / "frames"
    small.mkdir()
    cv2.imwrite(str(small / "1703001700000000000.jpg"), np.zeros((100, 100), np.uint8))
    bad["ingest"]["source"] = str(small)
    bad["ingest"]["record_dir"] = str(small / "rec")  # inside the folder played
    (tmp_path / "a-file").write_text("")
    bad["fuse_track"]["record"] = str(tmp_path / "a-file" / "tracks.jsonl")
    site = write_site(folder / "bad", bad)
    port_base = free_port_base()
    with socket.socket() as held:  # another pipeline's detect
        held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        held.bind(("127.0.0.1", port_base + 1))
        held.listen()
        rc, doc = checked(capsys, site, "--set", f"bus.port_base={port_base}")
    assert rc == 2 and not doc["ok"]
    checks = by_name(doc)
    failed = {n for n, c in checks.items() if not c["ok"]}
    assert failed == {f"masks {CAMERA}", "detector", f"source {CAMERA}", "fusion", "tracks recording",
                      "frames recording", "bus"}, doc
    assert "missing.npz" in checks[f"masks {CAMERA}"]["detail"]
    assert "detector model not found" in checks["detector"]["detail"]
    assert "no-such-model.onnx" in checks["detector"]["detail"]
    assert "1703001700000000000.jpg: JPEG is 100x100, expected 1280x960" in checks[f"source {CAMERA}"]["detail"]
    assert "missing.npz" in checks["fusion"]["detail"]
    assert "ingest.record_dir" in checks["frames recording"]["detail"] and "overlap" in checks["frames recording"][
        "detail"]
    assert not (small / "rec").exists()
    assert checks["tracks recording"]["detail"] == (f"fuse_track.record: {tmp_path / 'a-file'} cannot be made: "
                                                     f"{tmp_path / 'a-file'} is a file, not a folder")
    assert "ports in use" in checks["bus"]["detail"] and "detect" in checks["bus"]["detail"]
    assert checks["bus"]["detail"].startswith("ports in use")  # the checks after a failure still run

    assert main(["check", "--site", str(site), "--set", f"bus.port_base={port_base}"]) == 2
    out = capsys.readouterr().out
    assert "FAIL  detector" in out and "6 of 7 checks failed" in out  # the port is free again


def test_masks_of_another_size_and_a_source_not_found_are_named(good_site, capsys, tmp_path):
    folder, config = good_site
    other = copy.deepcopy(config)
    other["cameras"][0].update(width=640, height=480, masks=f"../masks/{CAMERA}.npz")
    other["detect"]["model"] = "../model.onnx"
    other["ingest"]["source"] = str(tmp_path / "nowhere")
    site = write_site(folder / "other", other)
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    checks = by_name(doc)
    assert rc == 2
    masks = checks[f"masks {CAMERA}"]["detail"]
    assert "are 1280x960, the camera is 640x480: set the camera's width and height" in masks
    assert checks["detector"]["ok"]
    assert "source not found" in checks["source"]["detail"] and "nowhere" in checks["source"]["detail"]


def test_the_masks_of_two_cameras_swapped_in_the_site_file_are_refused(good_site, capsys, tmp_path):
    """Masks of the same size given to the wrong camera would place every vehicle through the other camera's lookup:
    the camera the landmarks named (kept in the masks since 2026-11-30; before, the landmark file's name) must not
    be another camera of the site."""
    from calibration.masks import load_masks

    folder, config = good_site
    exact = load_masks(folder / "masks" / f"{CAMERA}.npz")
    for own, named in (("A", {"landmarks_camera": "B"}), ("B", {"landmarks_file": "landmarks/A.json"}),
                       ("C", {"landmarks_camera": "elsewhere"})):
        exact.meta = {**load_masks(folder / "masks" / f"{CAMERA}.npz").meta, **named}
        exact.save(tmp_path / "masks" / f"{own}.npz")
    swapped = copy.deepcopy(config)
    base = swapped["cameras"][0]
    swapped["cameras"] = [{**base, "name": n, "masks": str(tmp_path / "masks" / f"{n}.npz")} for n in "ABC"]
    swapped["ingest"]["source"] = None
    site = write_site(tmp_path / "site", swapped)
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    checks = by_name(doc)
    assert rc == 2
    assert "camera A: masks" in checks["masks A"]["detail"]
    assert "were calibrated from camera B's landmarks" in checks["masks A"]["detail"]
    assert "swapped in the site file?" in checks["masks A"]["detail"]
    assert "from camera A's landmarks (landmarks/A.json)" in checks["masks B"]["detail"]
    assert checks["masks C"]["ok"]  # a name that is no camera of the site: landmarks named otherwise, not a swap


def test_the_gpu_model_is_opened_on_the_cpu_where_no_gpu_would_load_it(good_site, capsys, tmp_path):
    folder, config = good_site
    site_cfg = copy.deepcopy(config)
    site_cfg["cameras"][0]["masks"] = str(folder / "masks" / f"{CAMERA}.npz")
    site_cfg["detect"].update(model=str(folder / "model.onnx"), model_gpu=str(tmp_path / "model_fp16.onnx"))
    (tmp_path / "model_fp16.onnx").write_bytes(b"not a model")
    site = write_site(tmp_path / "site", site_cfg)
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    checks = by_name(doc)
    assert rc == 2 and checks["detector"]["ok"]
    assert not checks["detector (GPU)"]["ok"] and "model_fp16.onnx" in checks["detector (GPU)"]["detail"]
    shutil.copy(folder / "model.onnx", tmp_path / "model_fp16.onnx")
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    assert rc == 0 and "opens and runs" in by_name(doc)["detector (GPU)"]["detail"]
    (tmp_path / "model_fp16.onnx").unlink()  # missing: detect would run the CPU model on a GPU, so a warning
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    gpu = by_name(doc)["detector (GPU)"]
    assert rc == 0 and gpu["ok"] and gpu["warning"] and "a GPU would run detect.model instead" in gpu["detail"]


def test_a_site_file_that_does_not_load_is_one_error_line(tmp_path, capsys):
    site = write_site(tmp_path, {"site": "x", "cameras": [{"name": "NE", "kind": "fisheye", "width": 0}]})
    assert main(["check", "--site", str(site)]) == 2
    err = capsys.readouterr().err
    assert "width" in err and "Traceback" not in err
    rc, doc = checked(capsys, site)  # --json: a JSON document all the same
    assert rc == 2 and doc["ok"] is False and "width" in doc["error"] and doc["checks"] == []


def test_what_the_services_work_around_passes_with_a_warning(good_site, capsys, tmp_path):
    """A bad first frame (ingest skips it and plays the next) and little disk space for the frames' recording (it
    pauses) pass with a warning; a recording file that is a folder, the bus's missing TLS file and extra listen
    endpoints every service would take fail; live streams are not even opened with --no-live."""
    folder, config = good_site
    site_cfg = copy.deepcopy(config)
    src = tmp_path / "images"
    src.mkdir()
    good = sorted((Path(config["ingest"]["source"]) / "frames" / CAMERA).glob("*.jpg"))
    for p in good:
        shutil.copy(p, src / p.name)
    (src / f"{int(good[0].stem) - 100_000_000}.jpg").write_bytes(b"\xff\xd8 truncated")  # the first frame, corrupt
    site_cfg["ingest"].update(source=str(src), record_dir=str(tmp_path / "recorded"), record_min_free_mb=1e9)
    (tmp_path / "tracks-folder").mkdir()
    site_cfg["fuse_track"]["record"] = str(tmp_path / "tracks-folder")
    site_cfg["bus"] = {"mode": "peer", "listen": ["tcp/127.0.0.1:45999"], "tls_root_ca": str(tmp_path / "no-ca.pem")}
    site = write_site(tmp_path / "site", {**site_cfg, "detect": {**site_cfg["detect"], "model": str(folder /
                                                                                                 "model.onnx")},
                                          "cameras": [{**site_cfg["cameras"][0],
                                                       "masks": str(folder / "masks" / f"{CAMERA}.npz")}]})
    rc, doc = checked(capsys, site, "--set", f"bus.port_base={free_port_base()}")
    checks = by_name(doc)
    assert rc == 2
    source = checks[f"source {CAMERA}"]
    assert source["ok"] and source["warning"] and "1 before it refused (ingest skips them)" in source["detail"]
    assert "3 frames over" in source["detail"] and "the first good one" in source["detail"]
    recording = checks["frames recording"]
    assert recording["ok"] and recording["warning"] and "below which recording pauses" in recording["detail"]
    assert not checks["tracks recording"]["ok"] and "is a folder" in checks["tracks recording"]["detail"]
    assert not checks["bus"]["ok"] and "no-ca.pem" in checks["bus"]["detail"]
    site_cfg["bus"].pop("tls_root_ca")
    site = write_site(tmp_path / "site", {**site_cfg, "detect": {**site_cfg["detect"], "model": str(folder /
                                                                                                 "model.onnx")},
                                          "cameras": [{**site_cfg["cameras"][0], "source": "rtsp://10.255.255.1/x",
                                                       "masks": str(folder / "masks" / f"{CAMERA}.npz")}]})
    t = time.monotonic()
    rc, doc = checked(capsys, site, "--no-live", "--set", f"bus.port_base={free_port_base()}")
    assert time.monotonic() - t < 30  # nothing connects to the stream
    checks = by_name(doc)
    assert checks["source"]["ok"] and "live streams not read (--no-live): rtsp://10.255.255.1/x" in checks["source"][
        "detail"]
    assert not checks["bus"]["ok"] and "in peer mode on one machine every service would listen there" in checks[
        "bus"]["detail"]
    rc, doc = checked(capsys, site, "--no-live", "--set", 'ingest.play_from="11:00:40"')  # refused by ingest too
    assert not by_name(doc)["source"]["ok"] and "not to live streams" in by_name(doc)["source"]["detail"]
    main(["check", "--site", str(site), "--no-live", "--set", f"bus.port_base={free_port_base()}"])
    assert "WARN  frames recording" in capsys.readouterr().out
