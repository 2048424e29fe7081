"""Turning-movement counts of a simulated run against its ground truth (`roadside eval movements`).

The vehicles' true movements are those of their ground-truth trajectories (every sample of the recording,
shared/movements.py's rule); the tracks' those of the tracks file. Over the whole recording:

- `complete_true`, `complete_counted`: the movements with both legs known, by the truth and by the tracks; the
  entry x exit matrices (`matrix_true`, `matrix_counted`, rows entries and columns exits in the legs' order) and
  `count_error`: the sum of the cells' absolute differences over the true total (0 = every movement's count right;
  what a traffic engineer reads off a count board);
- `entering_error`, `leaving_error`: the same for each leg's approach and departure volumes (complete movements and
  those seen on one side only: a count that needs only the approach);
- per vehicle, through the tracking evaluation's matching (eval.tracking: GT objects and tracks matched tick by
  tick within 1.5 m, each track given the vehicle it matched most often): `movement_recall` the share of the true
  complete movements whose vehicle has a track with that movement, `movement_precision` the share of the tracks'
  complete movements whose track's vehicle made that movement (a track matched to no vehicle counts wrong).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from eval.ground_truth import GroundTruth
from eval.tracking import match_tracks
from shared.movements import Counts, Junction, Movement, movement, movements, read_tracks


def true_movements(gt: GroundTruth, junction: Junction) -> list[Movement]:
    """The movement of every ground-truth trajectory that enters the junction (key ("truth", vehicle id))."""
    geo = gt.recording.geo
    out = []
    for vid, traj in gt.trajectories.items():
        ll = geo.to_geodetic(traj.xyz)
        m = movement(("truth", vid), traj.t_ns, junction.zones(ll[:, 0], ll[:, 1]), junction.names)
        if m is not None:
            out.append(m)
    return out


def _error(true: dict, counted: dict) -> float:
    total = sum(true.values())
    diff = sum(abs(true.get(k, 0) - counted.get(k, 0)) for k in set(true) | set(counted))
    return diff / total if total else float("nan")


def evaluate_movements(recording, tracks: str | Path, junction: Junction, cameras: Sequence[str] | None = None) -> dict:
    """The scores of the module doc for one run: its recording (or GroundTruth), its tracks file."""
    gt = recording if isinstance(recording, GroundTruth) else GroundTruth(recording)
    read = read_tracks([Path(tracks)])
    if read.bad_lines:
        raise ValueError(f"{read.bad_lines} bad lines in the tracks: {read.bad[0]}")
    counted = movements(read.positions, junction)
    truth = true_movements(gt, junction)
    legs = junction.names
    true_bin, counted_bin = Counts(0, 0), Counts(0, 0)
    for m in truth:
        true_bin.add(m)
    for m in counted:
        counted_bin.add(m)
    t_json, c_json = true_bin.to_json(junction), counted_bin.to_json(junction)

    # each track's vehicle: the one it matched most often (eval.tracking's matching, every camera's ground)
    res = match_tracks(gt, Path(tracks), cameras=cameras)
    votes: dict[tuple[str, int], Counter] = {}
    for fm in res.frames:
        for vid, key in fm.matched.items():
            votes.setdefault(key, Counter())[vid] += 1
    vehicle_of = {key: c.most_common(1)[0][0] for key, c in votes.items()}
    true_of = {m.key[1]: (m.entry, m.exit) for m in truth if m.entry is not None and m.exit is not None}
    complete = [m for m in counted if m.entry is not None and m.exit is not None]
    right = [m for m in complete if true_of.get(vehicle_of.get(m.key)) == (m.entry, m.exit)]
    recalled = {vehicle_of[m.key] for m in right}
    return {
        "legs": legs,
        "complete_true": t_json["complete_total"], "complete_counted": c_json["complete_total"],
        "matrix_true": t_json["complete"], "matrix_counted": c_json["complete"],
        "count_error": _error(true_bin.complete, counted_bin.complete),
        "entering_error": _error(t_json["entering"], c_json["entering"]),
        "leaving_error": _error(t_json["leaving"], c_json["leaving"]),
        "movement_recall": len(recalled) / len(true_of) if true_of else float("nan"),
        "movement_precision": len(right) / len(complete) if complete else float("nan"),
        "entered_only_counted": sum(c_json["entered_only"].values()),
        "exited_only_counted": sum(c_json["exited_only"].values()),
        "tracks_lines": read.lines,
    }


def as_table(scores: dict) -> str:
    """The two matrices side by side and the scores, as text."""
    legs = scores["legs"]
    width = max(6, *(len(leg) for leg in legs)) + 1
    head = "from \\ to".ljust(width) + "".join(leg.rjust(width) for leg in legs)
    lines = [f"turning movements, counted (true): {scores['complete_counted']} ({scores['complete_true']})", head]
    for i, leg in enumerate(legs):
        lines.append(leg.ljust(width) + "".join(
            f"{c} ({t})".rjust(width) for c, t in zip(scores["matrix_counted"][i], scores["matrix_true"][i],
                                                       strict=True)))
    lines.append(f"count error {scores['count_error']:.3f}, entering {scores['entering_error']:.3f}, leaving "
                 f"{scores['leaving_error']:.3f}; per vehicle: recall {scores['movement_recall']:.3f}, precision "
                 f"{scores['movement_precision']:.3f}")
    return "\n".join(lines)



def demo_junction(demo_dir: str | Path) -> Junction:
    """The junction of a `roadside demo` folder: its site file's `movements:`, else its recording's simulated site
    (a roundabout's is derived: sim.site.SiteSpec.movements)."""
    from shared.settings import load_settings
    from sim.recording import Recording
    from sim.site import SiteSpec

    demo = Path(demo_dir)
    settings = load_settings(demo / "site" / "site.yaml")
    if settings.movements is not None:
        return settings.movements.junction()
    from shared.settings import MovementSettings

    spec = SiteSpec.model_validate(Recording(demo / "recording").meta["site_spec"])
    return MovementSettings.model_validate(spec.movements()).junction()


def evaluate_demo_movements(demo_dir: str | Path) -> dict:
    """`evaluate_movements` of a `roadside demo` folder (its recording, tracks.jsonl and junction)."""
    demo = Path(demo_dir)
    for need in (demo / "recording", demo / "tracks.jsonl"):
        if not need.exists():
            raise ValueError(f"{demo}: not a roadside demo folder ({need.name} missing)")
    return {"demo": str(demo), **evaluate_movements(demo / "recording", demo / "tracks.jsonl", demo_junction(demo))}


MEAN_KEYS = ("count_error", "entering_error", "leaving_error", "movement_recall", "movement_precision")


def evaluate_demos_movements(demo_dirs: Sequence[str | Path]) -> dict:
    """Each demo folder's scores (`evaluate_demo_movements`) and their mean over the runs that have each (a run
    without a true movement has NaN scores: it leaves the others' mean as it is)."""
    runs = [evaluate_demo_movements(d) for d in demo_dirs]
    mean = {}
    for k in MEAN_KEYS:
        vals = [r[k] for r in runs if r[k] == r[k]]
        mean[k] = round(sum(vals) / len(vals), 4) if vals else float("nan")
    return {"runs": runs, "mean": mean}
