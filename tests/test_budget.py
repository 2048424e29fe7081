"""eval/budget.py: the error budget of a simulated run. The pieces on hand-made arrays; the whole on the small
recording (one fisheye camera, two frames) with objects made from its ground truth, moved off and with a false
alarm added, so each scenario's effect is known."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from pipeline_fixtures import CAMERA, write_exact_masks

from eval.budget import (
    SCENARIOS,
    budget,
    budget_many,
    lift_exact,
    on_footprint,
    read_objects,
    seen_vehicles,
    true_types,
    truth_objects,
    with_localize_rule,
    with_truth,
)
from shared.settings import LocalizeSettings


def row(xy, camera="A", t_ns=0, score=None) -> dict:
    xy = np.asarray(xy, float).reshape(-1, 2)
    n = len(xy)
    return {"camera": camera, "seq": 0, "t_ns": t_ns, "xy": xy.tolist(), "yaw": [0.1] * n,
            "size_lwh": [[4.5, 1.8, 1.5]] * n, "vtype": [1] * n, "score": score or [0.8] * n}


def vehicle(x, y, u=0.0, v=0.0) -> dict:
    return {"xyz": [x, y, 0.0], "uv": [u, v], "yaw": 0.5, "lwh": [4.0, 1.7, 1.4], "in_image": True,
            "visible_fraction": 1.0}


def test_with_truth_moves_matched_objects_and_drops_the_rest():
    seen = {("A", 0): [vehicle(0.0, 0.0), vehicle(10.0, 0.0)]}
    r = row([[0.5, 0.5], [10.0, 2.5], [30.0, 0.0]])  # two within the 3 m gate, one false alarm
    moved = with_truth([r], seen)[0]
    assert moved["xy"] == [[0.0, 0.0], [10.0, 0.0], [30.0, 0.0]]
    assert moved["yaw"] == r["yaw"] and moved["score"] == r["score"]
    dropped = with_truth([r], seen, move=False, drop=True)[0]
    assert dropped["xy"] == [[0.5, 0.5], [10.0, 2.5]] and len(dropped["score"]) == 2 and len(dropped["size_lwh"]) == 2
    both = with_truth([r], seen, move=True, drop=True)[0]
    assert both["xy"] == [[0.0, 0.0], [10.0, 0.0]]
    assert with_truth([r], seen, gate_m=1.0, drop=True)[0]["xy"] == [[0.0, 0.0]]  # 2.5 m off is beyond the gate
    assert with_truth([row([[1.0, 1.0]], camera="B")], seen, drop=True)[0]["xy"] == []  # B sees nothing


def test_lift_exact_replaces_the_mask_position_by_the_exact_one_at_that_pixel():
    h, w = 4, 5
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    exact = np.stack([uu * 1.0, vv * 1.0, np.zeros_like(uu, float)], axis=-1)
    masks = exact[..., :2] + [0.3, -0.2]  # the calibration is off by (0.3, -0.2) m everywhere
    valid = np.ones((h, w), bool)
    valid[0, 0] = False
    out = lift_exact([row([[2.3, 1.8], [4.3, 2.8]])], {"A": (masks, valid)}, {"A": (exact, valid)})[0]
    assert np.allclose(out["xy"], [[2.0, 2.0], [4.0, 3.0]])


def test_truth_objects_lift_each_seen_vehicle_at_its_pixel():
    h, w = 10, 10
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    masks = np.stack([uu * 2.0, vv * 3.0], axis=-1)
    valid = np.ones((h, w), bool)
    seen = {("A", 0): [vehicle(4.4, 5.7, u=2.2, v=1.9), vehicle(0.0, 0.0, u=12.0, v=1.0)]}  # the second off the image
    from calibration.masks import LookupMasks

    lookup = LookupMasks(np.zeros((h, w)), np.zeros((h, w)), masks.astype(np.float32), valid, {})
    out = truth_objects([row([[50.0, 50.0]])], seen, {"A": lookup})[0]
    assert np.allclose(out["xy"], [[4.4, 5.7]]) and out["yaw"] == [0.5] and out["size_lwh"] == [[4.0, 1.7, 1.4]]
    assert out["score"][0] >= 0.9


def test_on_footprint_follows_the_vehicles_length_and_heading():
    bus = {**vehicle(10.0, 0.0), "yaw": np.pi / 2, "lwh": [12.0, 2.5, 3.0]}  # pointing north: 12 m along y
    pts = [[10.0, 6.4], [10.0, -6.4], [10.0, 6.6], [11.7, 0.0], [11.8, 0.0], [16.0, 0.0]]
    assert on_footprint(np.array(pts), bus).tolist() == [True, True, False, True, False, False]
    assert on_footprint(np.array([[10.0, 6.6]]), bus, margin_m=1.0).tolist() == [True]


def test_true_types_replaces_the_objects_of_long_vehicles_by_their_truth():
    from calibration.masks import LookupMasks

    h, w = 10, 10
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    lookup = LookupMasks(np.zeros((h, w)), np.zeros((h, w)), np.stack([uu * 2.0, vv * 2.0], -1).astype(np.float32),
                         np.ones((h, w), bool), {})
    bus = {**vehicle(10.0, 4.0, u=5.0, v=2.0), "type": "bus", "yaw": 0.0, "lwh": [12.0, 2.5, 3.0]}
    car = {**vehicle(4.0, 14.0, u=2.0, v=7.0), "type": "car"}
    hidden_truck = {**vehicle(16.0, 16.0, u=8.0, v=8.0), "type": "truck", "visible_fraction": 0.1}
    in_image = {("A", 0): [bus, car, hidden_truck]}
    seen = {("A", 0): [bus, car]}  # the truck shows too little to count as seen
    # one object at the bus's far end (3.5 m along it), one on the car 0.8 m off, one on the hidden truck
    r = row([[13.5, 4.2], [4.8, 14.0], [16.5, 16.0]], score=[0.7, 0.6, 0.5])
    out = true_types([r], in_image, seen, {"A": lookup})[0]
    assert np.allclose(out["xy"], [[4.8, 14.0], [10.0, 4.0]])  # the car's as run, the bus at its truth
    assert out["score"][0] == 0.6 and out["score"][1] >= 0.9
    assert out["size_lwh"][1] == [12.0, 2.5, 3.0] and out["yaw"][1] == 0.0 and out["vtype"] == [1, 3]
    # with cars made right instead, the bus's object stays and the car's object goes to its truth
    cars = true_types([r], in_image, seen, {"A": lookup}, types=("car",))[0]
    assert np.allclose(cars["xy"], [[13.5, 4.2], [16.5, 16.0], [4.0, 14.0]])
    assert true_types([row([[1.0, 1.0]], camera="B")], in_image, seen, {"A": lookup})[0]["xy"] == [[1.0, 1.0]]


def test_read_objects_names_the_bad_line(tmp_path: Path):
    path = tmp_path / "objects.jsonl"
    path.write_text(json.dumps(row([[0.0, 0.0]])) + "\n{not json\n")
    with pytest.raises(ValueError, match=r"objects.jsonl:2: not JSON"):
        read_objects(path)
    bad = row([[0.0, 0.0]])
    del bad["score"]
    path.write_text(json.dumps(bad) + "\n")
    with pytest.raises(ValueError, match=r"objects.jsonl:1: missing score"):
        read_objects(path)
    short = row([[0.0, 0.0], [1.0, 1.0]])
    short["yaw"] = [0.0]
    path.write_text(json.dumps(short) + "\n")
    with pytest.raises(ValueError, match="one entry per object"):
        read_objects(path)
    path.write_text(json.dumps({**row([[0.0, 0.0]]), "score": 0.9}) + "\n")
    with pytest.raises(ValueError, match=r"objects.jsonl:1: score, xy, yaw, size_lwh and vtype must be lists"):
        read_objects(path)
    with pytest.raises(ValueError, match="objects file not found"):
        read_objects(tmp_path / "missing.jsonl")
    path.write_text(json.dumps({**row([[0.0, 0.0]]), "t_ns": "1703001600000000000"}) + "\n")
    with pytest.raises(ValueError, match=r"objects.jsonl:1: t_ns must be a whole number of nanoseconds"):
        read_objects(path)
    path.write_text(json.dumps(row([[0.0, 0.0]], camera="XX")) + "\n")
    assert len(read_objects(path)) == 1  # the site is not known here
    with pytest.raises(ValueError, match=r"objects.jsonl:1: camera 'XX' is not one of the site's \(A, B\)"):
        read_objects(path, ["A", "B"])


@pytest.fixture(scope="module")
def demo(small_recording: Path, tmp_path_factory) -> Path:
    """A demo folder on the small recording: NE alone, exact masks, objects = the seen vehicles' true positions
    moved 2 m east, plus a false alarm 15 m from the camera in every frame."""
    from sim.recording import Recording

    out = tmp_path_factory.mktemp("budget")
    write_exact_masks(small_recording, CAMERA, out / "site" / "masks" / f"{CAMERA}.npz")
    meta = json.loads((small_recording / "recording.json").read_text())
    cam = next(c for c in meta["cameras"] if c["name"] == CAMERA)
    (out / "site" / "site.yaml").write_text(yaml.safe_dump({
        "site": meta["site"]["name"], "origin": meta["site"]["origin"],
        "cameras": [{"name": CAMERA, "kind": cam["kind"], "width": cam["width"], "height": cam["height"],
                     "masks": f"masks/{CAMERA}.npz"}],
        "fuse_track": {"min_hits": 1, "tick_ms": 500.0}}))
    (out / "summary.json").write_text(json.dumps({"recording": str(small_recording)}))
    rec = Recording(small_recording)
    seen = seen_vehicles(rec, 0.3)
    camera_xy = np.asarray(cam["pose"]["position_m"][:2])
    rows = []
    for seq, (t_ns, _) in enumerate(rec.frames(CAMERA)):
        truth = np.array([v["xyz"][:2] for v in seen[(CAMERA, t_ns)]]).reshape(-1, 2)
        xy = np.vstack([truth + np.array([2.0, 0.0]), camera_xy + np.array([0.0, 15.0])])
        rows.append({**row(xy, camera=CAMERA, t_ns=t_ns), "seq": seq})
    assert all(len(r["xy"]) > 2 for r in rows), "the small recording's NE frames should show vehicles"
    (out / "objects.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return out


def test_budget_takes_away_one_error_at_a_time(demo: Path):
    result = budget(demo)
    s = result["scenarios"]
    assert list(s) == list(SCENARIOS)
    # 2 m off: beyond the 1.5 m match gate, every track misses; the false alarm is one more miss
    assert s["as_run"]["recall"] == 0.0 and s["as_run"]["mota"] < 0
    # the masks are the exact lookup: nothing to gain (the unmatched positions' distances to their nearest paths and
    # vehicles, in the trajectory error and the covariance's scores, move by the lookups' last millimetres)
    def scores(r):
        return json.dumps({k: v for k, v in r.items() if not k.startswith(("traj_err_in_roi", "pos_cov"))})

    assert scores(s["exact_lift"]) == scores(s["as_run"])
    assert s["exact_lift"]["traj_err_in_roi_m"] == pytest.approx(s["as_run"]["traj_err_in_roi_m"], abs=0.02)
    assert s["true_positions"]["recall"] == 1.0 and s["true_positions"]["precision"] < 1.0  # the false alarm stays
    assert s["no_false_alarms"]["recall"] == 0.0  # the false alarm goes, the vehicles stay 2 m off
    assert s["true_positions_no_false_alarms"]["mota"] == 1.0
    assert s["truth"]["mota"] == 1.0 and s["truth"]["traj_err_in_roi_m"] < 0.1


def test_budget_finds_the_recording_of_a_demo_folder_run_from_elsewhere(demo: Path, small_recording: Path,
                                                                        tmp_path: Path, monkeypatch):
    """summary.json names the recording as the demo saw it (relative to where it ran): a moved demo folder, or one
    given by an absolute path from another directory, still finds its own recording."""
    moved = tmp_path / "moved"
    moved.mkdir()
    for name in ("site", "objects.jsonl"):
        (moved / name).symlink_to(demo / name)
    (moved / "recording").symlink_to(small_recording)
    (moved / "summary.json").write_text(json.dumps({"recording": "out/demo/recording"}))
    monkeypatch.chdir(tmp_path)
    assert budget(moved, ["as_run"])["scenarios"]["as_run"]["recall"] == 0.0
    (moved / "summary.json").write_text(json.dumps({"mota": 0.5}))
    with pytest.raises(ValueError, match="not a demo summary with a 'recording'"):
        budget(moved, ["as_run"])


def test_budget_rejects_an_unknown_scenario(demo: Path):
    with pytest.raises(ValueError, match="unknown scenario"):
        budget(demo, ["as_run", "perfect"])
    with pytest.raises(ValueError, match=f"unknown scenario.s. without_XX; choose from .*without_{CAMERA}"):
        budget(demo, ["without_XX"])


def test_a_lost_camera_is_scored_over_every_roi_and_its_own(demo: Path):
    """`without_<camera>`: that camera's objects dropped (here the site's only camera: nothing is tracked), scored as
    the other scenarios and, in `lost_camera_roi`, over its own ROI beside the run as it was."""
    out = budget(demo, ["as_run", f"without_{CAMERA}"])["scenarios"]
    lost = out[f"without_{CAMERA}"]
    assert lost["recall"] == 0.0 and lost["lost_camera_roi"]["without"]["recall"] == 0.0
    keys = ("mota", "idf1", "recall", "precision", "traj_err_in_roi_m")
    assert tuple(lost["lost_camera_roi"]["as_run"]) == keys
    # its ROI is the site's: the same figures as the run's own (compared as JSON: NaN where nothing is tracked)
    assert json.dumps(lost["lost_camera_roi"]["as_run"]) == json.dumps({k: out["as_run"][k] for k in keys})


def test_budget_replays_at_the_sites_detect_threshold(demo: Path, monkeypatch):
    monkeypatch.setenv("ROADSIDE_DETECT__SCORE_THR", "0.9")  # above every object's 0.8: none is left
    s = budget(demo, ["true_positions"])["scenarios"]["true_positions"]
    assert s["recall"] == 0.0 and s["mota"] == 0.0  # no tracks at all: no match, no false positive


def test_with_localize_rule_drops_or_merges_at_the_replays_threshold():
    # two peaks 3 m apart along one vehicle heading east (yaw 0), another vehicle 10 m away
    r = row([[0, 0], [3, 0], [13, 0]], score=[0.5, 0.8, 0.6])
    r["yaw"] = [0.0, 0.0, 0.0]
    merged = with_localize_rule([r], LocalizeSettings(footprint_merge=True))[0]
    assert merged["score"] == [0.8, 0.6]
    np.testing.assert_allclose(merged["xy"], [[1.5, 0], [13, 0]])
    assert merged["size_lwh"][0][0] == pytest.approx(7.5) and merged["size_lwh"][1] == [4.5, 1.8, 1.5]
    dropped = with_localize_rule([r], LocalizeSettings(footprint_merge=False))[0]
    np.testing.assert_allclose(dropped["xy"], [[3, 0], [13, 0]])
    assert dropped["size_lwh"][0] == [4.5, 1.8, 1.5]
    assert with_localize_rule([r], LocalizeSettings(footprint_overlap=0))[0]["xy"] == r["xy"]


def test_budget_applies_the_localize_rule_when_asked(demo: Path, monkeypatch):
    plain = budget(demo, ["true_positions"])["scenarios"]["true_positions"]
    ruled = budget(demo, ["true_positions"], localize_rule=True)["scenarios"]["true_positions"]
    assert json.dumps(ruled) == json.dumps(plain)  # the fixture's objects stand apart: the rule changes nothing
    assert plain["recall"] > 0
    monkeypatch.setenv("ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP", "1000")  # every object inside the best one's
    few = budget(demo, ["true_positions"], localize_rule=True)["scenarios"]["true_positions"]
    assert few["recall"] < plain["recall"]
    # only when asked (compared as JSON: the fixture has no bus, and NaN != NaN)
    assert json.dumps(budget(demo, ["true_positions"])["scenarios"]["true_positions"]) == json.dumps(plain)
    out = budget(demo, ["true_positions"], localize_rule=True)
    assert out["localize_rule"] == {"footprint_overlap": 1000.0, "footprint_merge": False}  # said with the scores
    assert budget(demo, ["true_positions"])["localize_rule"] is None
    # the recording's setting left in the environment: no rule to apply, said so rather than a plain replay
    monkeypatch.setenv("ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP", "0")
    with pytest.raises(ValueError, match=r"footprint_overlap is 0\.0.*ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP"):
        budget(demo, ["true_positions"], localize_rule=True)


def test_budget_many_gives_each_run_and_their_mean(demo: Path, tmp_path: Path, monkeypatch, capsys):
    from roadside.cli import main

    one = budget(demo, ["true_positions"])["scenarios"]["true_positions"]
    many = budget_many([demo, demo], ["true_positions"])
    assert json.dumps([r["scenarios"]["true_positions"] for r in many["runs"]]) == json.dumps([one, one])
    mean = many["mean"]["true_positions"]
    assert mean["id_switches"] == 2 * one["id_switches"]
    assert {k: mean[k] for k in ("mota", "idf1", "precision", "recall")} == \
        {k: one[k] for k in ("mota", "idf1", "precision", "recall")}
    # two runs that differ: a copy whose site threshold is above every object, so its replay tracks nothing
    import shutil
    other = tmp_path / "other"
    shutil.copytree(demo, other)
    site = yaml.safe_load((other / "site" / "site.yaml").read_text())
    site["detect"] = {"score_thr": 0.9}
    (other / "site" / "site.yaml").write_text(yaml.safe_dump(site))
    both = budget_many([demo, other], ["true_positions"])["mean"]["true_positions"]
    assert both["recall"] == pytest.approx(one["recall"] / 2, abs=1e-4)
    with pytest.raises(ValueError, match="no demo folder"):
        budget_many([], ["as_run"])
    assert main(["eval", "budget", "--demo", str(demo), "--demo", str(other), "--scenario", "true_positions",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["runs"]) == 2 and out["mean"]["true_positions"]["recall"] == both["recall"]
    assert main(["eval", "budget", "--demo", str(demo), "--scenario", "true_positions", "--json"]) == 0
    as_json = {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in one.items()}  # no bus: null
    assert json.loads(capsys.readouterr().out)["scenarios"]["true_positions"] == as_json  # one run: as before
