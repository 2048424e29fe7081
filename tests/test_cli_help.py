"""Command-line help and messages a user meets first: the benchmarks' usage and descriptions, the defaults in
`--help`, the batch-size message of training, the demo's crossings line, and `viz --frames` keeping only the frames
within the tracks' time span."""

from __future__ import annotations

import importlib
import json
import re

import numpy as np
import pytest

from bench import first_paragraph
from roadside.cli import BENCHMARKS, main
from services.ingest.sources import SourceFrame


def _help(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--help"])
    assert exit_info.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse's line breaks undone


def _flag_help(text: str, flag: str) -> str:
    """The help of `flag` in a --help text (its lines joined), up to the next flag's."""
    options = text.split("options:", 1)[1]
    found = re.search(rf" {re.escape(flag)} [A-Z{{][^ ]* (.*?)(?= --[a-z][a-z-]* [A-Z{{]|$)", options)
    assert found, f"{flag} not in {options[:300]}"
    return found.group(1)


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_bench_help_names_its_command_and_gives_the_whole_first_paragraph(name, capsys):
    text = _help(capsys, "bench", name)
    assert text.startswith(f"usage: roadside bench {name} [-h]")
    paragraph = " ".join(first_paragraph(importlib.import_module(BENCHMARKS[name]).__doc__).split())
    assert paragraph.endswith((".", "?")) and len(paragraph) > 60
    assert paragraph in text


def test_first_paragraph_runs_to_the_blank_line():
    doc = """One: a sentence that goes
on to a second line.

Two."""
    assert first_paragraph(doc) == "One: a sentence that goes on to a second line."


def test_bench_detector_description_is_not_cut_mid_sentence(capsys):
    text = _help(capsys, "bench", "detector")
    assert "fp32 on CPU with a fixed thread count" in text
    assert "untrained-for-timing-only" in text and "(`target`: 25 ms" not in text  # the first paragraph, whole
    assert "frames/s of one inference at a time" in text


def test_a_benchmark_run_as_a_module_names_that_command():
    from bench import bench_parser

    assert bench_parser("sim", "Doc.", None, module="sim_render").prog == "python -m bench.sim_render"
    assert bench_parser("sim", "Doc.", []).prog == "roadside bench sim"


def test_bench_calibration_help_gives_the_stride_and_the_run_time(capsys):
    text = _help(capsys, "bench", "calibration")
    assert "default 2" in text and "README's figures use --stride 3" in text
    assert re.search(r"about 3 with --stride 3 .* on a 2-core machine, 3\.5-5", text)


@pytest.mark.parametrize(("flag", "default"), [
    ("--batch-size", "default 16"), ("--crop", "default 256"), ("--lr", "default 0.002"), ("--every", "default 1"),
    ("--stride", "default 4"), ("--seed", "default 0"), ("--center", "default"), ("--workers", "the default"),
])
def test_train_help_gives_the_defaults(flag, default, capsys):
    assert default in _flag_help(_help(capsys, "train"), flag)


@pytest.mark.parametrize(("flag", "words"), [
    ("--out", "default out/demo"), ("--seconds", "default 60"), ("--hz", "default 10"), ("--seed", "default 2024"),
    ("--port-base", "default 7451"), ("--landmarks", "default 20"),
])
def test_demo_help_explains_every_flag_with_its_default(flag, words, capsys):
    assert words in _flag_help(_help(capsys, "demo"), flag)


def test_viz_help_says_a_basemap_may_be_a_folder_and_frames_keep_the_tracks_span(capsys):
    text = _help(capsys, "viz")
    assert "or a folder holding one such world file and its image" in text
    assert "within the tracks file's time span" in text


def test_a_batch_larger_than_the_data_says_what_to_do():
    from training.data import Batcher

    refs = [object()] * 8  # the check comes before any sample is read
    with pytest.raises(ValueError, match=re.escape(
            "8 samples, fewer than one batch of 16: give --batch-size 8 or less, or more data")):
        Batcher(refs, None, batch_size=16, rng=np.random.default_rng(0))
    assert len(Batcher(refs, None, batch_size=8, rng=np.random.default_rng(0))) == 1


def test_demo_table_writes_crossings_as_counts():
    from roadside.demo import crossings_kept

    assert crossings_kept({"handoff_crossings": 2, "handoff_crossings_kept": 2,
                           "handoff_crossing_kept_fraction": 1.0}) == "2 of 2"
    # a summary written before the count was kept: from the fraction
    assert crossings_kept({"handoff_crossings": 33, "handoff_crossing_kept_fraction": 32 / 33}) == "32 of 33"
    assert crossings_kept({"handoff_crossings": 0, "handoff_crossing_kept_fraction": float("nan")}) == "0 of 0"


def test_tracks_span_is_the_first_and_last_message_time(tmp_path):
    from roadside.cli import _tracks_span

    path = tmp_path / "tracks.jsonl"
    path.write_text("\n".join([
        json.dumps({"site": "s", "t_ns": 5_000_000_000, "tracks": []}),
        "not json",
        json.dumps({"site": "s", "t_capture_ns": 9_000_000_000, "tracks": []}),
        json.dumps({"site": "s", "t_ns": 7_000_000_000, "tracks": []}),
        json.dumps([1, 2]),
        "",
    ]))
    assert _tracks_span(path) == (5_000_000_000, 9_000_000_000)
    (tmp_path / "empty.jsonl").write_text("\n")
    assert _tracks_span(tmp_path / "empty.jsonl") is None
    assert _tracks_span(tmp_path / "missing.jsonl") is None


def _frames(cams, seconds, hz=10):
    step = 10**9 // hz
    return [SourceFrame(cam, k * step, jpeg=b"x") for k in range(seconds * hz) for cam in cams]


def test_viz_frames_keeps_only_those_within_the_tracks_span_and_stops_after_it():
    from roadside.cli import _frames_within

    read: list[int] = []

    def source():
        for sf in _frames(["NE", "SW"], 600):  # ten minutes of footage
            read.append(sf.t_capture_ns)
            yield sf

    counts: dict = {}
    span = (100 * 10**9, 103 * 10**9)  # tracks over 3 s
    kept = list(_frames_within(source(), span, ["NE", "SW"], margin_ns=10**9, counts=counts))
    times = {sf.t_capture_ns for sf in kept}
    assert min(times) == 99 * 10**9 and max(times) == 104 * 10**9
    assert len(kept) == 2 * 51 and counts["kept"] == len(kept)
    assert {sf.camera for sf in kept} == {"NE", "SW"}
    assert max(read) <= 104 * 10**9 + 10**8  # stopped once both cameras passed the end
    assert counts["read"] == len(read) < 2 * 6000
    # without a span (a tracks file without a time): every frame
    assert len(list(_frames_within(iter(_frames(["NE"], 2)), None, ["NE"]))) == 20


def test_viz_frame_rows_run_the_detector_on_kept_frames_only():
    from types import SimpleNamespace

    import cv2

    from roadside.cli import _frames_within, _viz_frame_rows

    jpeg = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes()
    frames = [SourceFrame("NE", k * 10**8, jpeg=jpeg) for k in range(100)]  # 10 s at 10 Hz
    calls: list[int] = []

    class Detector:
        def detect(self, grey, area_px=None):
            calls.append(grey.shape[0])
            return []

    settings = SimpleNamespace(camera=lambda name: SimpleNamespace(detect_area_px=None))
    args = SimpleNamespace(frames_every=5)
    rows = list(_viz_frame_rows(args, settings, Detector(), _frames_within(iter(frames), (2 * 10**9, 3 * 10**9),
                                                                           ["NE"], margin_ns=0)))
    assert [r[1] for r in rows] == [2 * 10**9, int(2.5 * 10**9), 3 * 10**9]  # every 5th of those within the span
    assert len(calls) == 3
