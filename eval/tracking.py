"""Tracking accuracy of a tracks file (the fuse_track recorder's JSON lines) against a recording's ground truth.

Ground truth and GT objects: eval/ground_truth.py (`GroundTruth`, `TrackingEvalConfig`).

Tracks that are not scored (`ignore_unscored_tracks`, default on): a track position with no GT object within
the match gate is neither a match nor a false positive when it lies outside the evaluation area, or when it is
within the gate of a ground-truth vehicle that is not a GT object at t (mostly hidden, seen by no chosen camera,
outside the area, or out of the field of view of the pinhole camera whose area it is in): a tracker is not
penalised for following a vehicle the evaluation does not ask for.

Matching and metrics
--------------------
Every tracks line (one tick, at its capture time `t_ns`) is one motmetrics frame: the GT objects at `t_ns`
(positions interpolated at `t_ns`) against the line's tracks, on the ground (x, y), squared-distance matrix
with gate `match_gate_m` (max_d2 = gate^2, `motmetrics.distances.norm2squared_matrix`). A track's identity is
(tracker, id): ids are unique per tracker instance, so a restart is an identity change. Lines are taken in
capture-time order; lines outside the recording's time span are skipped. With `fill_silent_ticks` (default),
a frame time of the first chosen camera with no tracks line within half the tracker's own tick (a low, 10th
percentile of the spacing of its lines, at least a frame interval) becomes an empty frame, one per tick it
missed: a silent (or dead, or restarting) tracker misses every GT object then, and an empty tracks file scores
MOTA 0 rather than nothing.

`traj_err_in_roi_m` is the paper's trajectory error: for each tracked position scored inside the ROI, the distance
to the ground-truth trajectory (the polyline of its samples within +-`traj_window_s` of the tick; the projection
distance, so a time lag along the path is not counted) of the vehicle it is matched to, or, for a position matched
to none (a duplicate, a track drifted more than the match gate off, a false track), of the nearest vehicle's;
averaged over all of them (since 2026-11-29 late; before, over the matched positions alone:
`traj_err_in_roi_matched_m`, which leaves out the worst). A matched position is in the ROI when its vehicle is
(`GroundTruth.objects_in_roi`: the test that made the vehicle a GT object, with the ROI radius), wherever the track
puts it, so a track pushed outward across the ROI's edge is scored like one pushed inward; a position matched to
none is in the ROI when it lies within the ROI radius of a chosen camera. `traj_err_out_roi_m`: matched positions
whose vehicle is outside the ROI (in the evaluation area: only with a larger `eval_radius_m`).
`pos_err_m` is the time-synchronised distance (track position vs GT at the same `t_ns`) of all matches.
`yaw_err_in_roi_deg` (mean; `_median_deg`, `_n`) is the tracked heading's error for the same positions, where the
tracks carry a `yaw` (rad, ENU, counter-clockwise from east): the full-circle angle to the vehicle's true heading
at its ground-truth sample nearest the tick (a reversed heading is 180 deg); `yaw_err_in_roi_moving_deg` and
`_standing_deg` split it at `moving_mps` of true speed; `yaw_confirmed_*`, `yaw_reversed_*` and
`yaw_err_(un)confirmed_deg` split it by the tracks' `yaw_confirmed` (`yaw_confirmed_measure`); `yaw_std_*` score
the tracks' `yaw_std` against those errors on the heading's axis (`yaw_std_measure`).
`pos_cov_*`: how well the tracks' own position uncertainty (`xy_cov`, m^2, where the tracks carry one) describes
their error, over the same positions in the ROI (an unmatched one against the nearest vehicle of its tick, where
its tick has one): with d the time-synchronised error and C the covariance,
d' C^-1 d is chi-square with 2 degrees of freedom when C is right, so `pos_cov_nees_mean` should be 2,
`pos_cov_within_1sigma` 0.393 (the 1-sigma ellipse), `pos_cov_within_95` 0.95 (the 95 % ellipse, d' C^-1 d <= 5.991);
`pos_cov_err95_median_m` is the median of the 95 % ellipses' longest half-axes, what a vehicle is told;
`pos_cov_loglik` the mean log-likelihood (nats) of the true positions under the stated Gaussians, a proper score
(higher is better: it rewards a covariance for being right and for being tight); `pos_cov_by_type` the same keys
for each true vehicle type present.
`vel_cov_*` the same for the velocity (`vx`, `vy` and `velocity_cov`) against the vehicle's true velocity (its speed
along its heading at its ground-truth sample nearest the tick).
`ahead_<ms>ms_*` (`prediction_measure`, for each of `predict_horizons_s`): where a vehicle that receives the tracks
that long after their capture finds them, against where their vehicles are by then, for the tracks matched at
their tick in the ROI: as sent (`_stale_err_m`, mean distance; `_stale_cov_*` their covariance as it was) and moved
on at their velocities as `Tracks.predicted` does (`_err_m`; `_cov_*` the grown covariance, with `_cov_loglik`);
`_moving_*` the same distances for the vehicles at least `moving_mps` fast.

Handoff: each GT object's region at t is its nearest chosen camera on the ground. A crossing is a change of
region between two consecutive GT-object samples of a vehicle at most `handoff_window_s` apart; it is tracked
when the vehicle is matched within `handoff_window_s` before the crossing (in the old region's samples) and
after it (in the new region's), and kept when both matches are the same (tracker, id).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import motmetrics as mm
import numpy as np

from eval.ground_truth import GroundTruth, TrackingEvalConfig, _ground_truth
from shared.messages import CHI2_2DOF_95, err95_m, predict_motion
from shared.tracks_file import parse_covariance, parse_yaw_confirmed, parse_yaw_std
from sim.recording import Recording

_MATCH_TYPES = ("MATCH", "SWITCH")
_MM_METRICS = (
    "mota", "idf1", "num_switches", "precision", "recall", "num_frames", "mostly_tracked", "mostly_lost",
    "num_fragmentations", "num_objects", "num_matches", "num_misses", "num_false_positives",
)


# -- tracks input ---------------------------------------------------------------------------------------------


@dataclass
class TrackLine:
    """One tracks line (tick): capture time, tracker instance, track ids and, per track, what the line gives of it
    (NaN where a track has none)."""

    line: int
    t_ns: int
    tracker: str
    ids: list[int]
    xy: np.ndarray  # (N, 2) m, ground positions
    yaw: np.ndarray  # (N,) rad
    cov: np.ndarray  # (N, 2, 2) m^2, the position's error covariance
    vel: np.ndarray  # (N, 2) m/s
    vel_cov: np.ndarray  # (N, 2, 2) (m/s)^2, the velocity's error covariance
    yaw_confirmed: np.ndarray  # (N,) 1.0 where travel confirmed the heading's sign, 0.0 not
    yaw_std: np.ndarray  # (N,) rad, the heading's error on its axis (1 sigma)

    def keys(self) -> list[tuple[str, int]]:
        return [(self.tracker, i) for i in self.ids]

    def subset(self, keep: np.ndarray) -> TrackLine:
        """The tracks where `keep` (N,) bool is set."""
        arrays = {f.name: getattr(self, f.name)[keep] for f in fields(self)
                  if isinstance(getattr(self, f.name), np.ndarray)}
        return replace(self, ids=[i for i, k in zip(self.ids, keep, strict=True) if k], **arrays)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_finite_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _parse_line(obj: Any, where: str) -> TrackLine:
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    for key in ("t_ns", "tracker", "tracks"):
        if key not in obj:
            raise ValueError(f"{where}: missing key {key!r}")
    if not _is_int(obj["t_ns"]) or not 0 <= obj["t_ns"] < 2**63:
        raise ValueError(f"{where}: t_ns must be an integer >= 0 and < 2**63 (ns), got {obj['t_ns']!r}")
    if not isinstance(obj["tracker"], str):
        raise ValueError(f"{where}: tracker must be a string, got {obj['tracker']!r}")
    if not isinstance(obj["tracks"], list):
        raise ValueError(f"{where}: tracks must be a list")
    ids, xy, yaw, cov, vel, vel_cov, sure, yaw_sd = [], [], [], [], [], [], [], []
    for k, tr in enumerate(obj["tracks"]):
        if not isinstance(tr, dict):
            raise ValueError(f"{where}: track {k} is not an object")
        for key in ("id", "x", "y"):
            if key not in tr:
                raise ValueError(f"{where}: track {k} is missing key {key!r}")
        if not _is_int(tr["id"]):
            raise ValueError(f"{where}: track {k} id must be an integer, got {tr['id']!r}")
        if not (_is_finite_number(tr["x"]) and _is_finite_number(tr["y"])):
            raise ValueError(f"{where}: track {k} (id {tr['id']}) has a non-finite or non-numeric position "
                             f"x={tr['x']!r} y={tr['y']!r}")
        ids.append(tr["id"])
        xy.append((float(tr["x"]), float(tr["y"])))
        yaw.append(float(tr["yaw"]) if _is_finite_number(tr.get("yaw")) else math.nan)
        who = f"{where}: track {k} (id {tr['id']})"
        cov.append(_parse_cov(tr.get("xy_cov"), who))
        known = _is_finite_number(tr.get("vx")) and _is_finite_number(tr.get("vy"))
        vel.append((float(tr["vx"]), float(tr["vy"])) if known else (math.nan, math.nan))
        vel_cov.append(_parse_cov(tr.get("velocity_cov"), who, "velocity_cov"))
        confirmed = parse_yaw_confirmed(tr.get("yaw_confirmed"), who)
        sure.append(math.nan if confirmed is None else float(confirmed))
        sd = parse_yaw_std(tr.get("yaw_std"), who)
        yaw_sd.append(math.nan if sd is None else sd)
    if len(set(ids)) != len(ids):
        raise ValueError(f"{where}: duplicate track id in one line")
    return TrackLine(0, obj["t_ns"], obj["tracker"], ids, np.array(xy, float).reshape(-1, 2), np.array(yaw, float),
                     np.array(cov, float).reshape(-1, 2, 2), np.array(vel, float).reshape(-1, 2),
                     np.array(vel_cov, float).reshape(-1, 2, 2), np.array(sure, float), np.array(yaw_sd, float))


def _parse_cov(value: Any, where: str, name: str = "xy_cov") -> np.ndarray:
    """A track's `xy_cov` (or another 2 x 2 covariance, `name`) as a (2, 2) array; NaN when the track has none
    (`parse_covariance`)."""
    cov = parse_covariance(value, where, name)
    return np.full((2, 2), math.nan) if cov is None else np.array(cov, float)


def load_tracks(source: str | Path | Iterable[Mapping | Any]) -> list[TrackLine]:
    """Read and validate tracks: a JSON-lines file path, or an iterable of line dicts ({"t_ns", "tracker",
    "tracks": [{"id", "x", "y", ...}]}) or `shared.messages.Tracks` messages. Blank lines are skipped.
    Raises ValueError naming the (1-based) line of anything malformed (bad JSON, missing key, NaN, ...)."""
    out: list[TrackLine] = []
    if isinstance(source, str | Path):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"tracks file missing: {path}")
        with path.open(encoding="utf-8", errors="replace") as f:  # bytes that are not text fail as bad JSON
            for n, text in enumerate(f, 1):
                if not text.strip():
                    continue
                where = f"{path}: line {n}"
                try:
                    obj = json.loads(text)
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{where}: not valid JSON: {exc}") from None
                line = _parse_line(obj, where)
                line.line = n
                out.append(line)
        return out
    for n, obj in enumerate(source, 1):
        if hasattr(obj, "rows") and hasattr(obj, "t_capture_ns"):  # a Tracks message
            obj = {"t_ns": int(obj.t_capture_ns), "tracker": getattr(obj, "tracker", ""), "tracks": obj.rows()}
        line = _parse_line(obj, f"tracks line {n}")
        line.line = n
        out.append(line)
    return out


# -- matching -------------------------------------------------------------------------------------------------


@dataclass
class FrameMatch:
    """One evaluated tick: GT objects (id -> ground xy), scored tracks ((tracker, id) -> xy), matches."""

    t_ns: int
    gt_xy: dict[Any, np.ndarray]
    track_xy: dict[tuple[str, int], np.ndarray]
    matched: dict[Any, tuple[str, int]]  # GT id -> track identity, for the matched GT objects
    tracks: TrackLine | None = None  # the scored tracks, in track_xy's order: what else the line gives of them
    row: dict[tuple[str, int], int] = field(default_factory=dict)  # track identity -> its row in `tracks`


@dataclass
class MatchResult:
    accumulator: mm.MOTAccumulator
    frames: list[FrameMatch]
    cameras: list[str]
    lines: int = 0
    lines_outside_recording: int = 0
    silent_ticks_filled: int = 0
    ignored_track_positions: int = 0
    track_identities: set = field(default_factory=set)  # every (tracker, id) in the evaluated lines


def match_tracks(ground_truth: GroundTruth, tracks: str | Path | Iterable, cameras: str | Sequence[str] | None = None,
                 config: TrackingEvalConfig | None = None, seen_by: Sequence[str] | None = None) -> MatchResult:
    """Match the tracks to the GT objects of `cameras` (seen by one of `seen_by`, default `cameras`), tick by tick
    (motmetrics accumulator + per-tick matches)."""
    cfg = config or TrackingEvalConfig()
    gt = ground_truth
    cams = gt.check_cameras(cameras)
    lines = load_tracks(tracks)
    iv = gt.frame_interval_ns
    lo_t, hi_t = gt.t_min_ns - iv, gt.t_max_ns + iv
    kept = [ln for ln in lines if lo_t <= ln.t_ns <= hi_t]
    if lines and not kept:
        raise ValueError(f"none of the {len(lines)} tracks lines is within the recording's time span "
                         f"({gt.t_min_ns} to {gt.t_max_ns} ns): the tracks of another run?")
    res = MatchResult(mm.MOTAccumulator(auto_id=False), [], cams, lines=len(lines),
                      lines_outside_recording=len(lines) - len(kept))
    ticks: list[tuple[int, TrackLine | None]] = [(ln.t_ns, ln) for ln in kept]
    if cfg.fill_silent_ticks:
        times = np.sort(np.array([ln.t_ns for ln in kept], np.int64))
        # The tracker's own cadence: a tracker that ticks every 200 ms over 100 ms frames is not silent between its
        # ticks; where it is silent, one empty tick is charged per tick it missed, not per camera frame. Missed ticks
        # only lengthen the gaps between its lines, so its tick is among the shortest of them (a low percentile:
        # not the median, which a tracker missing half its ticks would stretch)
        gaps = np.diff(np.unique(times))
        step = max(iv, int(np.percentile(gaps, 10))) if len(gaps) else iv
        last_filled = None
        for r in gt.cameras[cams[0]].t_ns:
            k = int(np.searchsorted(times, r))
            near = [times[j] for j in (k - 1, k) if 0 <= j < len(times)]
            if near and min(abs(int(x) - int(r)) for x in near) <= step // 2:
                continue
            if last_filled is not None and int(r) - last_filled < step - iv // 2:
                continue
            ticks.append((int(r), None))
            last_filled = int(r)
            res.silent_ticks_filled += 1
    ticks.sort(key=lambda x: (x[0], x[1].line if x[1] is not None else -1))

    gate2 = float(cfg.match_gate_m) ** 2
    gt_index: dict[Any, int] = {}
    hyp_index: dict[tuple[str, int], int] = {}
    for frame_id, (t, line) in enumerate(ticks):
        pos = gt.positions_at(t, cfg)
        objs = gt.gt_objects(t, cams, cfg, pos, seen_by)
        gids = list(objs)
        g_xy = np.array([objs[v][:2] for v in gids], float).reshape(-1, 2)
        if line is None:  # a silent tick: no tracks
            line = _parse_line({"t_ns": t, "tracker": "", "tracks": []}, "silent tick")
        keys = line.keys()
        h_xy = line.xy
        res.track_identities.update(keys)
        if cfg.ignore_unscored_tracks and len(keys):
            d2_gt = np.sum((h_xy[:, None, :] - g_xy[None, :, :]) ** 2, axis=2)
            near_gt = np.any(d2_gt <= gate2, axis=1) if len(gids) else np.zeros(len(keys), bool)
            others = np.array([p[:2] for v, p in pos.items() if v not in objs], float).reshape(-1, 2)
            d2_o = np.sum((h_xy[:, None, :] - others[None, :, :]) ** 2, axis=2)
            near_other = np.any(d2_o <= gate2, axis=1) if len(others) else np.zeros(len(keys), bool)
            outside = ~gt.in_area(h_xy, cams, cfg)
            keep = near_gt | ~(near_other | outside)
            res.ignored_track_positions += int(np.sum(~keep))
            line = line.subset(keep)
            keys, h_xy = line.keys(), line.xy
        oids = [gt_index.setdefault(v, len(gt_index)) for v in gids]
        hids = [hyp_index.setdefault(k, len(hyp_index)) for k in keys]
        if oids and hids:
            dist = mm.distances.norm2squared_matrix(g_xy, h_xy, max_d2=gate2)
        else:
            dist = np.empty((len(oids), len(hids)))
        res.accumulator.update(oids, hids, dist, frameid=frame_id)
        res.frames.append(FrameMatch(t, {v: g_xy[i] for i, v in enumerate(gids)},
                                     {k: h_xy[i] for i, k in enumerate(keys)}, {}, line,
                                     {k: i for i, k in enumerate(keys)}))
    if res.frames:
        ev = res.accumulator.mot_events
        ev = ev[ev.Type.isin(_MATCH_TYPES)]
        gt_of = list(gt_index)
        hyp_of = list(hyp_index)
        for (frame_id, _), o, h in zip(ev.index, ev.OId.to_numpy(), ev.HId.to_numpy(), strict=True):
            res.frames[int(frame_id)].matched[gt_of[int(o)]] = hyp_of[int(h)]
    return res


# -- measures -------------------------------------------------------------------------------------------------


def yaw_confirmed_measure(err_deg: np.ndarray, confirmed: np.ndarray) -> dict:
    """How well a track's `yaw_confirmed` tells a heading's sign: of the headings (errors in deg, full circle) of
    tracks that carry it (1.0 / 0.0; NaN: none), `yaw_confirmed_share` those confirmed, `yaw_reversed_confirmed` /
    `_unconfirmed` the share of each more than 90 deg off (pointing backwards), `yaw_err_confirmed_deg` /
    `_unconfirmed_deg` their mean error. NaN where there are none."""
    known = np.isfinite(confirmed)
    sure = known & (confirmed > 0.5)
    out = {"yaw_confirmed_n": int(known.sum()),
           "yaw_confirmed_share": float(sure.sum() / known.sum()) if known.any() else math.nan}
    for name, part in (("confirmed", sure), ("unconfirmed", known & ~sure)):
        out[f"yaw_reversed_{name}"] = float(np.mean(err_deg[part] > 90)) if part.any() else math.nan
        out[f"yaw_err_{name}_deg"] = float(err_deg[part].mean()) if part.any() else math.nan
    return out


def _mean_std(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    a = np.asarray(values, float)
    return float(a.mean()), float(a.std())


def handoff_measure(frames: Sequence[FrameMatch], camera_xy_m: Mapping[str, Sequence[float]],
                    handoff_window_s: float = 1.0) -> dict:
    """Identity kept across camera regions (region = the nearest camera on the ground).

    Returns: `handoff_crossings` (tracked crossings: matched within the window on both sides),
    `handoff_crossings_kept` (same (tracker, id) on both sides), `handoff_crossing_kept_fraction` (per crossing),
    `handoff_vehicles` (GT vehicles with at least one tracked crossing), `handoff_kept_fraction` (of those, the
    fraction whose every tracked crossing kept the identity), `handoff_crossings_untracked` (crossings without
    a match on one side). Fractions are NaN when there is no tracked crossing."""
    names = list(camera_xy_m)
    cam = np.array([camera_xy_m[c][:2] for c in names], float).reshape(-1, 2)
    window = round(handoff_window_s * 1e9)
    per_vehicle: dict[Any, list[tuple[int, int, tuple | None]]] = {}
    for fm in sorted(frames, key=lambda f: f.t_ns):
        for vid, xy in fm.gt_xy.items():
            region = int(np.argmin(np.linalg.norm(cam - np.asarray(xy)[:2], axis=1))) if len(cam) else 0
            per_vehicle.setdefault(vid, []).append((fm.t_ns, region, fm.matched.get(vid)))
    crossings = kept = untracked = 0
    vehicles_crossed = vehicles_kept = 0
    for seq in per_vehicle.values():
        v_cross = v_kept = 0
        for i in range(1, len(seq)):
            t_prev, r_prev, _ = seq[i - 1]
            t_cur, r_cur, _ = seq[i]
            if r_prev == r_cur or t_cur - t_prev > window:
                continue
            before = next((m for t, r, m in reversed(seq[:i]) if t_prev - t <= window and r == r_prev and m), None)
            after = next((m for t, r, m in seq[i:] if t - t_cur <= window and r == r_cur and m), None)
            if before is None or after is None:
                untracked += 1
                continue
            v_cross += 1
            v_kept += before == after
        crossings += v_cross
        kept += v_kept
        if v_cross:
            vehicles_crossed += 1
            vehicles_kept += v_kept == v_cross
    return {
        "handoff_crossings": crossings,
        "handoff_crossings_kept": kept,
        "handoff_crossing_kept_fraction": kept / crossings if crossings else float("nan"),
        "handoff_vehicles": vehicles_crossed,
        "handoff_kept_fraction": vehicles_kept / vehicles_crossed if vehicles_crossed else float("nan"),
        "handoff_crossings_untracked": untracked,
    }


def yaw_std_measure(err_deg: np.ndarray, std_deg: np.ndarray) -> dict:
    """How well the tracks' `yaw_std` says how far off their heading is, on its axis (front and back are
    `yaw_confirmed`'s): of the headings (errors in deg, full circle) of tracks that carry one (deg; NaN: none), each
    one's axis error (the error, or 180 - it, whichever is less) over its sigma, z: `yaw_std_z2_mean` (1 when right),
    `yaw_std_within_1sigma` (0.683 when right), `yaw_std_within_95` (|z| <= 1.96), `yaw_std_loglik` the mean
    Gaussian log-likelihood per heading (rad: higher is better, for a sigma that is right and small),
    `yaw_std_median_deg` the median sigma. NaN where there are none."""
    known = np.isfinite(std_deg) & (std_deg > 0)
    axis = np.minimum(err_deg[known], 180.0 - err_deg[known])
    sd = std_deg[known]
    z = axis / sd
    n = len(z)
    nan = math.nan
    loglik = -0.5 * z**2 - np.log(np.radians(sd)) - 0.5 * math.log(2 * math.pi)
    return {"yaw_std_n": n, "yaw_std_z2_mean": float(np.mean(z**2)) if n else nan,
            "yaw_std_within_1sigma": float(np.mean(z <= 1.0)) if n else nan,
            "yaw_std_within_95": float(np.mean(z <= 1.96)) if n else nan,
            "yaw_std_loglik": float(np.mean(loglik)) if n else nan,
            "yaw_std_median_deg": float(np.median(sd)) if n else nan}


def covariance_measure(nees: np.ndarray, err95_m: np.ndarray | None = None, prefix: str = "pos_cov",
                       logdet: np.ndarray | None = None) -> dict:
    """`pos_cov_*` (module docstring; `prefix` names them) of the squared Mahalanobis distances `nees` of matched
    positions under their tracks' covariances, with `err95_m` the median of the covariances' 95 % half-axes and with
    `logdet` (the covariances' log-determinants) the mean log-likelihood of the 2D errors; NaN where there are
    none."""
    out = {f"{prefix}_n": len(nees), f"{prefix}_nees_mean": float(nees.mean()) if len(nees) else math.nan,
           f"{prefix}_within_1sigma": float(np.mean(nees <= 1.0)) if len(nees) else math.nan,
           f"{prefix}_within_95": float(np.mean(nees <= CHI2_2DOF_95)) if len(nees) else math.nan}
    if err95_m is not None:
        out[f"{prefix}_err95_median_m"] = float(np.median(err95_m)) if len(err95_m) else math.nan
    if logdet is not None:
        out[f"{prefix}_loglik"] = (float(np.mean(-0.5 * nees - 0.5 * logdet - math.log(2 * math.pi)))
                                   if len(nees) else math.nan)
    return out


def prediction_measure(gt: GroundTruth, cfg: TrackingEvalConfig, matched: Sequence[tuple]) -> dict:
    """`ahead_<ms>ms_*` for each of `cfg.predict_horizons_s` (module docstring) of the tracks matched at their tick
    in the ROI, `matched`: (tick ns, vehicle id, xy, xy_cov, velocity, velocity_cov, whether the vehicle moves at
    least `moving_mps`), each track with a finite velocity and covariances. Against where their vehicles are that
    much later, as they were (`_stale_err_m`, and their stated covariance as it was: `_stale_cov_*`) and moved on by
    `predict_motion` (`_err_m`, `_cov_*`); `_moving_*` the same errors for the moving vehicles."""
    gap, ahead_max = gt.max_gap_ns(cfg), round(cfg.max_extrapolation_s * 1e9)
    when, who, xy, cov, vel, vcov, moving = zip(*matched, strict=True) if matched else ((),) * 7
    xy_a, cov_a = np.array(xy, float).reshape(-1, 2), np.array(cov, float).reshape(-1, 2, 2)
    vel_a, vcov_a = np.array(vel, float).reshape(-1, 2), np.array(vcov, float).reshape(-1, 2, 2)
    moving_a = np.array(moving, bool)
    out: dict[str, Any] = {}
    for horizon in cfg.predict_horizons_s:
        h_ns = round(horizon * 1e9)
        later = [gt.trajectories[v].position_at(t + h_ns, ahead_max, gap) for t, v in zip(when, who, strict=True)]
        known = np.array([p is not None for p in later], bool)
        truth = np.array([p[:2] for p in later if p is not None], float).reshape(-1, 2)
        p_xy, p_cov, _ = predict_motion(xy_a[known], vel_a[known], cov_a[known], vcov_a[known], horizon)
        e_stale, e = truth - xy_a[known], truth - p_xy
        stale, moved, fast = np.hypot(*e_stale.T), np.hypot(*e.T), moving_a[known]
        key = f"ahead_{round(horizon * 1000)}ms"
        out[f"{key}_n"] = len(truth)
        for name, part in (("", np.ones(len(truth), bool)), ("_moving", fast)):
            out[f"{key}{name}_stale_err_m"] = float(stale[part].mean()) if part.any() else math.nan
            out[f"{key}{name}_err_m"] = float(moved[part].mean()) if part.any() else math.nan
        stale_nees = np.einsum("ni,nij,nj->n", e_stale, np.linalg.inv(cov_a[known]), e_stale) if len(e) else np.zeros(0)
        nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(p_cov), e) if len(e) else np.zeros(0)
        logdet = np.linalg.slogdet(p_cov)[1] if len(e) else np.zeros(0)
        out.update({k: v for k, v in covariance_measure(stale_nees, prefix=f"{key}_stale_cov").items()
                    if not k.endswith("_n")})
        out.update({k: v for k, v in covariance_measure(nees, prefix=f"{key}_cov", logdet=logdet).items()
                    if not k.endswith("_n")})
    return out


def evaluate_tracks(recording: Recording | GroundTruth | str | Path, tracks_rows_or_path: str | Path | Iterable,
                    cameras: str | Sequence[str] | None = None, config: TrackingEvalConfig | None = None,
                    seen_by: Sequence[str] | None = None) -> dict:
    """Tracking accuracy of a tracks file (or rows) on a recording, over the GT objects of `cameras` (all by
    default; those any camera of `seen_by` sees, by default `cameras`). Keys (see the module docstring for the
    policy):

    - CLEAR MOT / ID (py-motmetrics): `mota`, `idf1`, `id_switches`, `precision`, `recall`, `num_frames` (ticks
      evaluated), `num_objects` (GT object instances), `num_matches`, `num_misses`, `num_false_positives`,
      `mostly_tracked`, `mostly_lost`, `fragmentations`;
    - trajectory error (m): `traj_err_in_roi_m`, `traj_err_in_roi_std_m`, `traj_err_in_roi_n` (the positions in
      the ROI, matched ones by their vehicle's position, and unmatched ones; `traj_err_in_roi_matched_*` the
      matched ones alone), `traj_err_out_roi_m`, `traj_err_out_roi_std_m`, `traj_err_out_roi_n` (the matched
      positions whose vehicle is outside the ROI: only with a larger `eval_radius_m`); `pos_err_m`,
      `pos_err_std_m` (time-synchronised distance of all matches);
    - counts: `tracks` (scored (tracker, id) identities), `tracks_total` (all identities in the evaluated lines),
      `trackers`, `gt_vehicles` (distinct GT objects), `lines`, `lines_outside_recording`, `silent_ticks_filled`,
      `ignored_track_positions`;
    - handoff (see `handoff_measure`): `handoff_kept_fraction`, `handoff_crossings`, ...;
    - `cameras`, `config`. Undefined ratios are NaN.
    """
    cfg = config or TrackingEvalConfig()
    gt = _ground_truth(recording)
    res = match_tracks(gt, tracks_rows_or_path, cameras, cfg, seen_by)
    cams = res.cameras
    out: dict[str, Any] = {}
    if res.frames:
        summary = mm.metrics.create().compute(res.accumulator, metrics=list(_MM_METRICS), name="tracks")
        s = {k: float(v) for k, v in summary.iloc[0].to_dict().items()}
    else:
        s = {k: float("nan") for k in ("mota", "idf1", "precision", "recall")}
        s.update({k: 0.0 for k in _MM_METRICS if k not in s})
    out.update({
        "mota": s["mota"], "idf1": s["idf1"], "id_switches": int(s["num_switches"]), "precision": s["precision"],
        "recall": s["recall"], "num_frames": len(res.frames), "num_objects": int(s["num_objects"]),
        "num_matches": int(s["num_matches"]), "num_misses": int(s["num_misses"]),
        "num_false_positives": int(s["num_false_positives"]), "mostly_tracked": int(s["mostly_tracked"]),
        "mostly_lost": int(s["mostly_lost"]), "fragmentations": int(s["num_fragmentations"]),
    })
    window = round(cfg.traj_window_s * 1e9)
    gap = gt.max_gap_ns(cfg)
    err_in, err_out, pos_err, err_unmatched = [], [], [], []
    yaw_err, yaw_moving, yaw_sure, yaw_sd = [], [], [], []
    nees, err95, logdet, nees_type, vel_nees, ahead = [], [], [], [], [], []
    for fm in res.frames:
        taken = set(fm.matched.values())
        unmatched = [k for k in fm.track_xy if k not in taken]
        if unmatched:  # scored in the ROI all the same: against the nearest vehicle's path and position
            u_xy = np.array([fm.track_xy[k] for k in unmatched])
            for k, xy, roi in zip(unmatched, u_xy, gt.in_roi(u_xy, cams, cfg), strict=True):
                if not roi:
                    continue
                # against the vehicles there then: a trajectory that ended (or starts) beyond the window is not
                present = (tr for tr in gt.trajectories.values()
                           if tr.t_ns[0] <= fm.t_ns + window and tr.t_ns[-1] >= fm.t_ns - window)
                d = min((tr.distance_to_path(xy, fm.t_ns, window, gap) for tr in present),
                        key=lambda x: x if math.isfinite(x) else math.inf, default=math.nan)
                if math.isfinite(d):
                    err_unmatched.append(d)
                cov = fm.tracks.cov[fm.row[k]] if fm.tracks is not None else np.full((2, 2), np.nan)
                if fm.gt_xy and np.isfinite(cov).all():
                    v = min(fm.gt_xy, key=lambda g: float(np.linalg.norm(xy - fm.gt_xy[g])))
                    e = xy - fm.gt_xy[v]
                    nees.append(float(e @ np.linalg.solve(cov, e)))
                    err95.append(float(err95_m(cov)))
                    logdet.append(float(np.linalg.slogdet(cov)[1]))
                    nees_type.append(gt.trajectories[v].type)
        if not fm.matched:
            continue
        vids = list(fm.matched)
        t_xy = np.array([fm.track_xy[fm.matched[v]] for v in vids])
        # in the ROI by the vehicle's position, as it was chosen a GT object, not by the track's
        in_roi = gt.objects_in_roi(fm.t_ns, {v: fm.gt_xy[v] for v in vids}, cams, cfg)
        for v, xy, roi in zip(vids, t_xy, in_roi, strict=True):
            d = gt.trajectories[v].distance_to_path(xy, fm.t_ns, window, gap)
            (err_in if roi else err_out).append(d)
            pos_err.append(float(np.linalg.norm(xy - fm.gt_xy[v])))
            tr, j = fm.tracks, fm.row[fm.matched[v]]
            cov = tr.cov[j]
            if roi and np.isfinite(cov).all():
                e = xy - fm.gt_xy[v]
                nees.append(float(e @ np.linalg.solve(cov, e)))
                err95.append(float(err95_m(cov)))
                logdet.append(float(np.linalg.slogdet(cov)[1]))
                nees_type.append(gt.trajectories[v].type)
            tracked = float(tr.yaw[j])
            true, speed = gt.trajectories[v].heading_at(fm.t_ns)
            vel, vcov = tr.vel[j], tr.vel_cov[j]
            if roi and np.isfinite(cov).all() and np.isfinite(vel).all() and np.isfinite(vcov).all():
                ahead.append((fm.t_ns, v, xy, cov, vel, vcov, speed >= cfg.moving_mps))  # prediction_measure's
            if (roi and np.isfinite(vel).all() and np.isfinite(vcov).all() and math.isfinite(true)
                    and math.isfinite(speed)):
                e = vel - speed * np.array([math.cos(true), math.sin(true)])
                vel_nees.append(float(e @ np.linalg.solve(vcov, e)))
            if roi and math.isfinite(tracked) and math.isfinite(true):
                yaw_err.append(math.degrees(abs((tracked - true + math.pi) % (2 * math.pi) - math.pi)))
                yaw_moving.append(speed >= cfg.moving_mps)
                yaw_sure.append(float(tr.yaw_confirmed[j]))
                yaw_sd.append(math.degrees(tr.yaw_std[j]))
    for name, vals in (("in_roi", err_in + err_unmatched), ("in_roi_matched", err_in), ("out_roi", err_out)):
        m, sd = _mean_std(vals)
        out[f"traj_err_{name}_m"], out[f"traj_err_{name}_std_m"], out[f"traj_err_{name}_n"] = m, sd, len(vals)
    out["pos_err_m"], out["pos_err_std_m"] = _mean_std(pos_err)
    yaw_err_a, moving = np.array(yaw_err), np.array(yaw_moving, bool)
    out["yaw_err_in_roi_deg"] = float(yaw_err_a.mean()) if len(yaw_err_a) else math.nan
    out["yaw_err_in_roi_median_deg"] = float(np.median(yaw_err_a)) if len(yaw_err_a) else math.nan
    out["yaw_err_in_roi_n"] = len(yaw_err_a)
    for name, part in (("moving", moving), ("standing", ~moving)):
        out[f"yaw_err_in_roi_{name}_deg"] = float(yaw_err_a[part].mean()) if part.any() else math.nan
    out.update(yaw_confirmed_measure(yaw_err_a, np.array(yaw_sure, float)))
    out.update(yaw_std_measure(yaw_err_a, np.array(yaw_sd, float)))
    nees_a, err95_a, logdet_a, nees_type_a = np.array(nees), np.array(err95), np.array(logdet), np.array(nees_type)
    out.update(covariance_measure(nees_a, err95_a, logdet=logdet_a))
    out["pos_cov_by_type"] = {
        name: covariance_measure(nees_a[nees_type_a == name], err95_a[nees_type_a == name],
                                 logdet=logdet_a[nees_type_a == name])
        for name in sorted(set(nees_type))}
    out.update(covariance_measure(np.array(vel_nees), prefix="vel_cov"))
    out.update(prediction_measure(gt, cfg, ahead))
    scored = {k for fm in res.frames for k in fm.track_xy}
    out.update({
        "tracks": len(scored), "tracks_total": len(res.track_identities),
        "trackers": len({k[0] for k in res.track_identities}),
        "gt_vehicles": len({v for fm in res.frames for v in fm.gt_xy}),
        "lines": res.lines, "lines_outside_recording": res.lines_outside_recording,
        "silent_ticks_filled": res.silent_ticks_filled, "ignored_track_positions": res.ignored_track_positions,
    })
    out.update(handoff_measure(res.frames, {c: gt.cameras[c].xy for c in cams}, cfg.handoff_window_s))
    out["cameras"] = cams
    out["config"] = asdict(cfg)
    return out


def evaluate_many(recording: Recording | GroundTruth | str | Path, sources: Mapping[str, str | Path | Iterable],
                  cameras: str | Sequence[str] | None = None,
                  source_cameras: Mapping[str, str | Sequence[str]] | None = None,
                  config: TrackingEvalConfig | None = None) -> dict:
    """Evaluate several track sources on the same ground truth (built once), e.g. fused tracks against each
    camera's own tracks: `evaluate_many(rec, {"fused": rows, "C_NE": rows_ne, ...})`.

    The cameras of a source: `source_cameras[name]` if given, else [name] when `name` is a camera of the
    recording (one camera's tracks are scored in its own area on every vehicle there that any camera sees, as the
    fused tracks are, a pinhole or thermal camera's on those in its image alone; until 2026-11-29 on the vehicles it
    saw itself, which left it the vehicles it misses), else `cameras` (all by default).
    Returns {"sources": {name: evaluate_tracks result},
    "traj_err_best_single_camera_m": the lowest `traj_err_in_roi_m` among the single-camera sources (NaN if none),
    "best_single_camera": its name (None),
    "mota_best_single_camera" / "idf1_best_single_camera": the highest among the single-camera sources}."""
    cfg = config or TrackingEvalConfig()
    gt = _ground_truth(recording)
    results: dict[str, dict] = {}
    for name, src in sources.items():
        if source_cameras and name in source_cameras:
            cams = gt.check_cameras(source_cameras[name])
        elif name in gt.cameras:
            cams = [name]
        else:
            cams = gt.check_cameras(cameras)
        seen = gt.check_cameras(cameras) if len(cams) == 1 else None
        results[name] = evaluate_tracks(gt, src, cams, cfg, seen)
    single = {n: r for n, r in results.items() if len(r["cameras"]) == 1}

    def best(key: str, lowest: bool) -> tuple[str | None, float]:
        vals = [(r[key], n) for n, r in single.items() if not math.isnan(r[key])]
        if not vals:
            return None, float("nan")
        v, n = min(vals) if lowest else max(vals)
        return n, v

    best_name, best_err = best("traj_err_in_roi_m", lowest=True)
    return {
        "sources": results,
        "traj_err_best_single_camera_m": best_err,
        "best_single_camera": best_name,
        "mota_best_single_camera": best("mota", lowest=False)[1],
        "idf1_best_single_camera": best("idf1", lowest=False)[1],
    }


def _settled_crossings(t_ns: list[int], regions: list[int], settle_ns: int) -> int:
    """Region changes of one track (positions at t_ns in `regions`), leaving out stays shorter than settle_ns
    between its first and its last region stay."""
    runs: list[list[int]] = []  # [region, first t, last t]
    for t, r in zip(t_ns, regions, strict=True):
        if runs and runs[-1][0] == r:
            runs[-1][2] = t
        else:
            runs.append([r, t, t])
    if len(runs) > 2:
        inner = [run for run in runs[1:-1] if run[2] - run[1] >= settle_ns]
        runs = [runs[0], *inner, runs[-1]]
    merged = [run[0] for k, run in enumerate(runs) if k == 0 or run[0] != runs[k - 1][0]]
    return len(merged) - 1


def handoff_without_truth(tracks: str | Path | Iterable, camera_xy_m: Mapping[str, Sequence[float]],
                          max_gap_s: float = 1.5, join_m: float = 4.0, settle_s: float = 0.5) -> dict:
    """Identity kept across camera regions in a tracks file with no ground truth (real footage).

    A region is the set of ground points nearest to one camera. A crossing is kept when one track identity
    (tracker, id) moves from one region to another; a stay shorter than `settle_s` between two other regions (a
    track along a region border, flickering across it) is no crossing. It is broken when a track ends in one region
    and, within `max_gap_s`, a new track starts in another region within `join_m` of where the ended track would be at
    that time (its last position extrapolated with its last velocity from two positions): the same vehicle
    under a new id. Ended and started tracks are paired one to one, nearest first.
    Returns crossings kept and broken and `handoff_kept_fraction` (NaN without any crossing)."""
    if not camera_xy_m:
        raise ValueError("handoff needs the cameras' ground positions")
    cam = np.array([camera_xy_m[c][:2] for c in camera_xy_m], float)
    paths: dict[tuple[str, int], list[tuple[int, np.ndarray]]] = {}
    for line in sorted(load_tracks(tracks), key=lambda ln: ln.t_ns):
        for key, xy in zip(line.keys(), line.xy, strict=True):
            paths.setdefault(key, []).append((line.t_ns, np.asarray(xy, float)))

    def region(xy: np.ndarray) -> int:
        return int(np.argmin(np.linalg.norm(cam - xy, axis=1)))

    kept = 0
    ends, starts = [], []
    settle = round(settle_s * 1e9)
    for key, pts in paths.items():
        regions = [region(p) for _, p in pts]
        kept += _settled_crossings([t for t, _ in pts], regions, settle)
        (t0, p0), (t1, p1) = pts[0], pts[-1]
        v = np.zeros(2)
        if len(pts) >= 2 and pts[-1][0] > pts[-2][0]:
            v = (pts[-1][1] - pts[-2][1]) / ((pts[-1][0] - pts[-2][0]) / 1e9)
        ends.append((key, t1, p1, v, regions[-1]))
        starts.append((key, t0, p0, regions[0]))
    pairs = []
    gap = round(max_gap_s * 1e9)
    for ek, t_end, p_end, v, r_end in ends:
        for sk, t_start, p_start, r_start in starts:
            if sk == ek or not 0 < t_start - t_end <= gap or r_start == r_end:
                continue
            d = float(np.linalg.norm(p_end + v * (t_start - t_end) / 1e9 - p_start))
            if d <= join_m:
                pairs.append((d, ek, sk))
    used_e, used_s = set(), set()
    broken = 0
    for _, ek, sk in sorted(pairs):
        if ek not in used_e and sk not in used_s:
            used_e.add(ek)
            used_s.add(sk)
            broken += 1
    total = kept + broken
    if not paths:
        raise ValueError(f"no tracks in {tracks}" if isinstance(tracks, str | Path) else "no tracks to measure")
    return {"tracks": len(paths), "crossings_kept": kept, "crossings_broken": broken,
            "handoff_kept_fraction": kept / total if total else float("nan")}
