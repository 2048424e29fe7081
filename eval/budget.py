"""Where a simulated run's tracking accuracy goes (`roadside eval budget DEMO_DIR`).

A run of `roadside demo` leaves what localize published (`objects.jsonl`: every camera frame's objects on the
ground), the site it ran (`site/site.yaml` and the lookup masks) and the recording with its ground truth. This
module replays those objects offline through fuse_track's own fusion, tracker and ticks (`services.fuse_track.
__main__.build`), scores the tracks as the demo does, and then replays them again with one source of error taken
away at a time:

- `as_run`: the objects unchanged (at pace `max`, where no frame is dropped, this is the run's own score);
- `exact_lift`: each object lifted through the simulator's exact ground lookup instead of the calibrated masks, at
  the pixel whose mask position is nearest to it (what the calibration costs);
- `true_positions`: every object that is one of the camera's vehicles (Hungarian assignment within `gate_m` of the
  vehicles in its image, however little of them shows) moved to that vehicle's true ground position (what the
  detector's localization costs);
- `no_false_alarms`: the objects that match no such vehicle dropped (what its false alarms cost);
- `true_positions_no_false_alarms`: both; what is left is what the detector misses, and what the fusion and the
  tracker lose of what it finds;
- `true_long_vehicles`: every object lying on a bus's or a truck's footprint (0.5 m around it) in its camera's
  image dropped, and each bus and truck the camera sees given as a `truth` object (below); every other object as
  run (what the long vehicles cost: the detector places a 12 m bus's peak at one end);
- `truth`: every vehicle each camera sees (bottom centre in the image, `min_visible_fraction` visible, as the
  evaluation's rule) at its true pixel, lifted through the masks (fusion, tracking and calibration alone);
- `without_<camera>` (one per camera of the site, asked for by name): that camera's objects dropped, as when it
  fails at the cabinet; scored as the others, over every camera's ROI, and in `lost_camera_roi` over the lost
  camera's own ROI alone, beside the same for the objects as run (what the other cameras' far views keep of it).

A camera "sees" a vehicle as in eval/tracking.py. Objects scoring below the site's `detect.score_thr` are left out
first, so a run detected at a lower threshold can be replayed at any higher one (environment overrides such as
`ROADSIDE_DETECT__SCORE_THR`, `ROADSIDE_FUSE_TRACK__HIGH_SCORE` apply, as for the services). The figures tell
which part of the pipeline to improve next; they are not the run's score (docs/pipeline.md, "Where the MOTA goes").
localize's footprint rule merges a long vehicle's peaks among the objects detect keeps, so what it publishes at one
threshold is not a subset of what it publishes at a lower one: to replay a run at a higher threshold exactly, record
it without the rule (`ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP=0`) and replay with `localize_rule`, which applies the
site's rule (`localize.footprint_overlap`, `footprint_merge`) to the objects left at the replay's threshold.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from shared.messages import VEHICLE_TYPES

SCENARIOS = ("as_run", "exact_lift", "true_positions", "no_false_alarms", "true_positions_no_false_alarms",
             "true_long_vehicles", "truth")
LONG_VEHICLES = ("bus", "truck")
FOOTPRINT_MARGIN_M = 0.5  # an object this close to a long vehicle's footprint is taken to be of it
SCORES = ("mota", "idf1", "id_switches", "precision", "recall", "traj_err_in_roi_m", "yaw_err_in_roi_deg",
          "yaw_err_in_roi_median_deg", "yaw_std_within_95", "yaw_std_loglik", "pos_cov_within_95", "pos_cov_loglik",
          "pos_cov_within_95_truck", "pos_cov_loglik_truck", "pos_cov_within_95_bus", "pos_cov_loglik_bus")
LOST_CAMERA_SCORES = ("mota", "idf1", "recall", "precision", "traj_err_in_roi_m")  # `without_<camera>`, its ROI
OBJECT_KEYS = ("camera", "seq", "t_ns", "xy", "yaw", "size_lwh", "vtype", "score")
TRUTH_SCORE = 0.9  # the score of a `truth` object: above any threshold a site uses


def read_objects(path: str | Path, cameras: Sequence[str] | None = None) -> list[dict]:
    """The rows of an objects file (JSON lines, `roadside demo`'s `objects.jsonl`); ValueError naming the line
    (and a row of a camera not among `cameras`, when given)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"objects file not found: {path}")
    rows = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}:{i}: not JSON ({exc.msg})") from None
        missing = [k for k in OBJECT_KEYS if not isinstance(row, dict) or k not in row]
        if missing:
            raise ValueError(f"{path}:{i}: missing {', '.join(missing)}")
        if not all(isinstance(row[k], list) for k in ("score", "xy", "yaw", "size_lwh", "vtype")):
            raise ValueError(f"{path}:{i}: score, xy, yaw, size_lwh and vtype must be lists")
        n = len(row["score"])
        if any(len(row[k]) != n for k in ("xy", "yaw", "size_lwh", "vtype")):
            raise ValueError(f"{path}:{i}: xy, yaw, size_lwh, vtype and score must have one entry per object")
        if isinstance(row["t_ns"], bool) or not isinstance(row["t_ns"], int) or row["t_ns"] < 0:
            raise ValueError(f"{path}:{i}: t_ns must be a whole number of nanoseconds >= 0, got {row['t_ns']!r}")
        if cameras is not None and row["camera"] not in cameras:
            raise ValueError(f"{path}:{i}: camera {row['camera']!r} is not one of the site's ({', '.join(cameras)})")
        rows.append(row)
    return rows


def replay(rows: Sequence[dict], settings) -> list[dict]:
    """Objects rows -> tracks-file rows: every frame in its event-time tick, fused and tracked as fuse_track does."""
    from services.fuse_track.__main__ import build, fuse_and_track, tracks_message
    from services.fuse_track.fusion import ObjectBatch

    fusion, tracker, ticks, _, geo = build(settings)
    for r in sorted(rows, key=lambda r: r["t_ns"]):
        batch = ObjectBatch.from_frame(
            r["camera"], int(r["t_ns"]), np.asarray(r["xy"], np.float64).reshape(-1, 2),
            np.asarray(r["yaw"], np.float64), np.asarray(r["size_lwh"], np.float64).reshape(-1, 3),
            np.asarray(r["vtype"], np.int64), np.asarray(r["score"], np.float64))
        ticks.add(r["camera"], int(r["t_ns"]), batch, 0.0)
    out = []
    for seq, tick in enumerate(ticks.flush()):
        state = fuse_and_track(fusion, tracker, tick.items(), tick.t_ref_ns, tick.batches.keys())
        msg = tracks_message(settings.site, state, tick.t_ref_ns, seq, geo, [], [])
        out.append({"site": settings.site, "seq": seq, "t_ns": tick.t_ref_ns, "tracker": tracker.id,
                    "tracks": msg.rows()})
    return out


def seen_vehicles(recording, min_visible_fraction: float) -> dict[tuple[str, int], list[dict]]:
    """(camera, capture time) -> the vehicles that camera sees in that frame."""
    out = {}
    for cam in recording.camera_names:
        for frame in recording.ground_truth(cam):
            out[(cam, int(frame["t_ns"]))] = [
                v for v in frame["vehicles"]
                if v.get("in_image") and float(v.get("visible_fraction") or 0.0) >= min_visible_fraction]
    return out


def _select(row: dict, keep: np.ndarray, xy: np.ndarray) -> dict:
    out = dict(row)
    for k in ("yaw", "vtype", "score"):
        out[k] = [v for v, kk in zip(row[k], keep, strict=True) if kk]
    out["size_lwh"] = [v for v, kk in zip(row["size_lwh"], keep, strict=True) if kk]
    out["xy"] = xy[keep].tolist()
    return out


def with_truth(rows: Sequence[dict], seen: dict, gate_m: float = 3.0, move: bool = True,
               drop: bool = False) -> list[dict]:
    """Objects matched to the vehicles of their frame in `seen` (Hungarian, ground distance within `gate_m`) moved
    to the truth (`move`); the unmatched dropped (`drop`)."""
    out = []
    for r in rows:
        xy = np.asarray(r["xy"], np.float64).reshape(-1, 2).copy()
        truth = np.array([v["xyz"][:2] for v in seen.get((r["camera"], int(r["t_ns"])), [])], np.float64)
        matched = np.zeros(len(xy), bool)
        if len(xy) and len(truth):
            d = np.linalg.norm(xy[:, None] - truth[None], axis=2)
            i, j = linear_sum_assignment(np.where(d <= gate_m, d, 1e9))
            ok = d[i, j] <= gate_m
            i, j = i[ok], j[ok]
            matched[i] = True
            if move:
                xy[i] = truth[j]
        out.append(_select(r, matched if drop else np.ones(len(xy), bool), xy))
    return out


def lift_exact(rows: Sequence[dict], masks: dict, exact: dict) -> list[dict]:
    """Objects moved from the calibrated masks' ground position to the exact lookup's at the same pixel (the pixel
    whose mask position is nearest). masks / exact: camera -> ((H, W, 2) metres, (H, W) valid)."""
    index = {}
    for cam, (mxy, mvalid) in masks.items():
        exy, evalid = exact[cam]
        ok = mvalid & evalid
        index[cam] = (cKDTree(mxy[ok].astype(np.float64)), exy[ok][:, :2].astype(np.float64))
    out = []
    for r in rows:
        xy = np.asarray(r["xy"], np.float64).reshape(-1, 2)
        if len(xy):
            tree, exy = index[r["camera"]]
            xy = exy[tree.query(xy)[1]]
        out.append(_select(r, np.ones(len(xy), bool), xy))
    return out


def truth_objects(rows: Sequence[dict], seen: dict, masks: dict) -> list[dict]:
    """For each frame of `rows`: one object per vehicle its camera sees, at its true pixel (`uv`) lifted through
    the masks (camera -> LookupMasks; bilinear, as localize lifts), with its true heading and size."""
    out = []
    for r in rows:
        vehicles = seen.get((r["camera"], int(r["t_ns"])), [])
        uv = np.array([v["uv"] for v in vehicles], np.float64).reshape(-1, 2)
        _, xy, ok = masks[r["camera"]].lookup(uv, geodetic=False)
        kept = [v for v, k in zip(vehicles, ok, strict=True) if k]
        vtype = [VEHICLE_TYPES.index(v["type"]) if v.get("type") in VEHICLE_TYPES else 0 for v in kept]
        out.append({**r, "xy": xy[ok].tolist(), "yaw": [float(v["yaw"]) for v in kept],
                    "size_lwh": [[float(x) for x in v["lwh"]] for v in kept], "vtype": vtype,
                    "score": [TRUTH_SCORE] * len(kept)})
    return out


def on_footprint(xy: np.ndarray, vehicle: dict, margin_m: float = FOOTPRINT_MARGIN_M) -> np.ndarray:
    """(N,) bool: which ground points (N, 2) lie on the vehicle's footprint (its length and width along its yaw)
    grown by `margin_m`."""
    axis = np.array([np.cos(vehicle["yaw"]), np.sin(vehicle["yaw"])])
    d = np.asarray(xy, np.float64).reshape(-1, 2) - np.asarray(vehicle["xyz"][:2], np.float64)
    length, width = float(vehicle["lwh"][0]), float(vehicle["lwh"][1])
    return ((np.abs(d @ axis) <= length / 2 + margin_m)
            & (np.abs(d @ np.array([-axis[1], axis[0]])) <= width / 2 + margin_m))


def true_types(rows: Sequence[dict], in_image: dict, seen: dict, masks: dict,
               types: Sequence[str] = LONG_VEHICLES) -> list[dict]:
    """The objects of `rows` with the vehicles of `types` made right: each object on the footprint of such a vehicle
    in its camera's image (`in_image`) dropped, and each such vehicle the camera sees (`seen`) added as a `truth`
    object (true pixel lifted through the masks, true heading and size); the other objects unchanged."""
    out = []
    for r in rows:
        key = (r["camera"], int(r["t_ns"]))
        xy = np.asarray(r["xy"], np.float64).reshape(-1, 2)
        keep = np.ones(len(xy), bool)
        for v in in_image.get(key, []):
            if v.get("type") in types:
                keep &= ~on_footprint(xy, v)
        kept = _select(r, keep, xy)
        wanted = [v for v in seen.get(key, []) if v.get("type") in types]
        if wanted:
            truth = truth_objects([r], {key: wanted}, masks)[0]
            for k in ("xy", "yaw", "size_lwh", "vtype", "score"):
                kept[k] = kept[k] + truth[k]
        out.append(kept)
    return out


def with_localize_rule(rows: Sequence[dict], localize) -> list[dict]:
    """Objects rows with localize's footprint rule applied to each frame (LocalizeSettings: the overlap scale and
    whether the kept objects merge the peaks they suppress; lift.py `footprint_rule`), as localize does on the
    detections detect keeps."""
    from services.localize.lift import footprint_rule

    out = []
    for r in rows:
        xy = np.asarray(r["xy"], np.float64).reshape(-1, 2)
        kept, xy, size = footprint_rule(xy, np.asarray(r["yaw"], np.float64),
                                        np.asarray(r["size_lwh"], np.float64).reshape(-1, 3),
                                        np.asarray(r["score"], np.float64), localize.footprint_overlap,
                                        localize.footprint_merge)
        keep = np.zeros(len(xy), bool)
        keep[kept] = True
        out.append(_select({**r, "size_lwh": np.asarray(size).tolist()}, keep, xy))
    return out


def budget(demo_dir: str | Path, scenarios: Sequence[str] = SCENARIOS, gate_m: float = 3.0, log=None,
           localize_rule: bool = False) -> dict:
    """Scores of each scenario (module docstring) for a `roadside demo` output folder; `localize_rule`: apply the
    site's footprint rule to the objects at the replay's threshold (a run recorded without it)."""
    from calibration.masks import load_masks
    from eval.tracking import TrackingEvalConfig, evaluate_many
    from shared.settings import load_settings
    from sim.recording import Recording

    demo = Path(demo_dir)
    settings = load_settings(demo / "site" / "site.yaml")
    cams = [c.name for c in settings.cameras]
    lost = {f"without_{c}": c for c in cams}
    unknown = [s for s in scenarios if s not in SCENARIOS and s not in lost]
    if unknown:
        raise ValueError(f"unknown scenario(s) {', '.join(unknown)}; choose from {', '.join((*SCENARIOS, *lost))}")
    summary = demo / "summary.json"
    rec_dir = demo / "recording"
    if summary.is_file():
        try:
            rec = json.loads(summary.read_text())["recording"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise ValueError(f"{summary}: not a demo summary with a 'recording'") from None
        # as the demo wrote it (relative to where it ran), else relative to the demo folder
        rec_dir = next((p for p in (Path(rec), demo / Path(rec).name) if p.is_dir()), Path(rec))
    recording = Recording(rec_dir)
    rows = [_select(r, np.asarray(r["score"], np.float64) >= settings.detect.score_thr,
                    np.asarray(r["xy"], np.float64).reshape(-1, 2)) for r in read_objects(demo / "objects.jsonl", cams)]
    if localize_rule:
        if not settings.localize.footprint_overlap > 0:
            raise ValueError(f"localize_rule: localize.footprint_overlap is {settings.localize.footprint_overlap} "
                             f"in {demo / 'site' / 'site.yaml'} with this environment (is "
                             "ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP=0 still set?): there is no rule to apply")
        rows = with_localize_rule(rows, settings.localize)
    seen = seen_vehicles(recording, TrackingEvalConfig().min_visible_fraction)
    in_image = seen_vehicles(recording, 0.0)  # what an object may be of: any vehicle in its camera's image
    masks = {}
    for c in settings.cameras:
        if c.masks is None:
            raise ValueError(f"camera {c.name} has no masks in {demo / 'site' / 'site.yaml'}")
        masks[c.name] = load_masks(settings.path(c.masks))
    variants = {
        "as_run": lambda: rows,
        "exact_lift": lambda: lift_exact(rows, {c: (m.xy, m.valid) for c, m in masks.items()},
                                         {c: recording.ground_lookup(c) for c in cams}),
        "true_positions": lambda: with_truth(rows, in_image, gate_m, move=True),
        "no_false_alarms": lambda: with_truth(rows, in_image, gate_m, move=False, drop=True),
        "true_positions_no_false_alarms": lambda: with_truth(rows, in_image, gate_m, move=True, drop=True),
        "true_long_vehicles": lambda: true_types(rows, in_image, seen, masks),
        "truth": lambda: truth_objects(rows, seen, masks),
        **{name: (lambda c=c: [r for r in rows if r["camera"] != c]) for name, c in lost.items()},
    }
    out = {"demo": str(demo), "recording": str(rec_dir), "gate_m": gate_m,
           "score_thr": settings.detect.score_thr, "high_score": settings.fuse_track.high_score,
           "localize_rule": {"footprint_overlap": settings.localize.footprint_overlap,
                             "footprint_merge": settings.localize.footprint_merge} if localize_rule else None,
           "scenarios": {}}
    replayed: dict[str, list[dict]] = {}  # each scenario's tracks, as_run's kept for the lost cameras' ROIs
    for name in scenarios:
        tracks = replayed[name] = replay(variants[name](), settings)
        s = evaluate_many(recording, {"fused": tracks}, cameras=cams)["sources"]["fused"]
        for vtype in ("truck", "bus"):  # the long vehicles, whose positions are least sure (docs/pipeline.md)
            of_type = s["pos_cov_by_type"].get(vtype, {})
            for stat in ("within_95", "loglik"):
                s[f"pos_cov_{stat}_{vtype}"] = of_type.get(f"pos_cov_{stat}", math.nan)
        out["scenarios"][name] = {k: round(s[k], 4) if isinstance(s[k], float) else s[k] for k in SCORES}
        if name in lost:
            if "as_run" not in replayed:
                replayed["as_run"] = replay(rows, settings)
            out["scenarios"][name]["lost_camera_roi"] = {
                key: {k: round(v[k], 4) if isinstance(v[k], float) else v[k] for k in LOST_CAMERA_SCORES}
                for key, v in ((key, evaluate_many(recording, {"fused": replayed[run]}, cameras=[lost[name]])[
                    "sources"]["fused"]) for key, run in (("as_run", "as_run"), ("without", name)))}
        if log:
            log(f"{name}: " + ", ".join(f"{k} {out['scenarios'][name][k]}" for k in SCORES))
    return out


def budget_many(demo_dirs: Sequence[str | Path], scenarios: Sequence[str] = SCENARIOS, gate_m: float = 3.0,
                log=None, localize_rule: bool = False) -> dict:
    """`budget` of each run (e.g. several validation recordings), and per scenario the mean of each score over
    them (id switches summed): one recording's figures swing by a few hundredths of MOTA with what happens in it
    (docs/pipeline.md), so choices between settings or models are made on the mean. A score that is undefined
    for a run (NaN, e.g. no tracked position in any ROI) leaves the mean undefined."""
    if not demo_dirs:
        raise ValueError("no demo folder given")
    runs = []
    for d in demo_dirs:
        if log:
            log(f"{d}:")
        runs.append(budget(d, scenarios, gate_m, log, localize_rule))
    mean = {}
    for name in runs[0]["scenarios"]:
        vals = [r["scenarios"][name] for r in runs]
        mean[name] = {k: int(sum(v[k] for v in vals)) if k == "id_switches" else
                      round(float(np.mean([v[k] for v in vals])), 4) for k in SCORES}
        if log:
            log(f"mean {name}: " + ", ".join(f"{k} {mean[name][k]}" for k in SCORES))
    return {"runs": runs, "mean": mean}
