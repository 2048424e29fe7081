"""Turning-movement counts (shared/movements.py, `roadside counts`, `roadside eval movements`)."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from shared.geo import GeoFrame
from shared.movements import INSIDE, NOWHERE, Junction, Movement, binned, movement, movements, read_tracks

CENTER = (42.22939632, -83.73899854)
LEGS = (("north", -3.0), ("east", 90.0), ("south", 166.0), ("west", 272.0))
GEO = GeoFrame(*CENTER)
T0 = 1_703_001_600_000_000_000  # 2023-12-19T16:00:00Z
S = 1_000_000_000


def junction(**kw) -> Junction:
    return Junction(*CENTER, **{"legs": LEGS, "inner_radius_m": 24.4, "outer_radius_m": 70.0, **kw})


def at(bearing_deg: float, r_m: float) -> np.ndarray:
    b = math.radians(bearing_deg)
    return np.array([r_m * math.sin(b), r_m * math.cos(b)])


def latlon(en: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ll = GEO.to_geodetic(np.column_stack([en, np.zeros(len(en))]))
    return ll[:, 0], ll[:, 1]


def path(*points: np.ndarray, step_m: float = 1.0) -> np.ndarray:
    """A polyline through the points, sampled every step_m."""
    out = []
    for a, b in itertools.pairwise(points):
        n = max(int(np.linalg.norm(b - a) / step_m), 1)
        out += [a + (b - a) * k / n for k in range(n)]
    return np.array([*out, points[-1]])


def through(entry_deg: float, exit_deg: float, r_in: float = 60.0, r_out: float = 60.0,
            step_m: float = 1.0) -> np.ndarray:
    """In along a leg at entry_deg, round the ring counter-clockwise (right-hand traffic: the bearing falls), out
    along exit_deg (the same leg: once round, a U-turn)."""
    ring = 19.0
    sweep = (entry_deg - exit_deg) % 360 or 360
    arc = [at(b, ring) for b in entry_deg - np.linspace(0, sweep, 12)]
    return path(at(entry_deg, r_in), *arc, at(exit_deg, r_out), step_m=step_m)


def positions(key, en: np.ndarray, t0_ns: int = T0, step_ns: int = S // 10) -> list:
    lat, lon = latlon(en)
    return [(key, t0_ns + k * step_ns, la, lo) for k, (la, lo) in enumerate(zip(lat, lon, strict=True))]


# --- the junction --------------------------------------------------------------------------------------------------


def test_positions_fall_on_the_leg_of_nearest_bearing_inside_or_nowhere():
    j = junction()
    en = np.array([at(0, 40), at(88, 30), at(170, 69), at(270, 25), at(0, 10), at(45, 40), at(0, 80), [0.0, 0.0]])
    assert j.zones(*latlon(en)).tolist() == [0, 1, 2, 3, INSIDE, NOWHERE, NOWHERE, INSIDE]


@pytest.mark.parametrize(("kw", "named"), [
    ({"inner_radius_m": 30.0, "outer_radius_m": 20.0}, "0 < inner < outer"),
    ({"legs": (("north", 0.0), ("east", 60.0))}, "legs north and east are 60 deg apart"),
    ({"legs": (("north", 0.0), ("north", 180.0))}, "duplicate leg names"),
    ({"legs": (("north", 0.0),)}, "at least two legs"),
    ({"half_width_deg": 0.0}, "half_width_deg must be in"),
    ({"legs": (("north", 0.0), ("east", math.nan))}, "leg east: bearing must be finite"),
])
def test_a_junction_that_cannot_be_counted_is_named(kw, named):
    with pytest.raises(ValueError, match=named):
        junction(**kw)
    with pytest.raises(ValueError, match="lat0_deg"):
        Junction(95.0, 0.0, LEGS, 20.0, 60.0)


# --- movements -------------------------------------------------------------------------------------------------------


def movement_of(en: np.ndarray, j: Junction | None = None) -> Movement | None:
    j = j or junction()
    found = movements(positions(("t", 1), en), j)
    assert len(found) <= 1
    return found[0] if found else None


@pytest.mark.parametrize(("entry", "exit_", "names"), [
    (-3.0, 166.0, ("north", "south")), (90.0, -3.0, ("east", "north")), (166.0, 90.0, ("south", "east")),
    (272.0, 272.0, ("west", "west")),  # a U-turn
])
def test_a_vehicle_through_the_junction_counts_its_entry_and_exit(entry, exit_, names):
    m = movement_of(through(entry, exit_))
    assert (m.entry, m.exit) == names and m.key == ("t", 1)
    inside = np.flatnonzero(junction().zones(*latlon(through(entry, exit_))) == INSIDE)[0]
    assert m.t_ns == T0 + inside * (S // 10)  # when it first entered


def test_what_a_track_does_between_first_entering_and_last_leaving_does_not_count():
    """Jitter across the inner radius at a leg's mouth (a car on the ring's outer lane) counts once, with the legs
    before the first entry and after the last exit."""
    en = through(-3.0, 166.0)
    jitter = np.array([at(90.0, 24.0), at(90.0, 25.5), at(90.0, 23.8), at(90.0, 26.0), at(92.0, 23.0)])
    k = len(en) // 2
    m = movement_of(np.vstack([en[:k], jitter, en[k:]]))
    assert (m.entry, m.exit) == ("north", "south")


def test_partial_passages_and_tracks_that_never_enter():
    full = through(90.0, 272.0)
    zones = junction().zones(*latlon(full))
    first_in, last_in = np.flatnonzero(zones == INSIDE)[[0, -1]]
    assert (movement_of(full[: last_in + 1]).entry, movement_of(full[: last_in + 1]).exit) == ("east", None)
    assert (movement_of(full[first_in:]).entry, movement_of(full[first_in:]).exit) == (None, "west")
    assert movement_of(path(at(0, 60), at(0, 30))) is None  # stopped on its leg (or turned off before)
    assert movement_of(np.array([at(45, 40)] * 20)) is None  # parked between two legs


def test_a_movements_time_is_its_tracks_own_to_the_nanosecond():
    edge = T0 + 900 * S  # a 15-minute bin's end
    en = through(-3.0, 166.0)
    k = int(np.flatnonzero(junction().zones(*latlon(en)) == INSIDE)[0])  # the step it enters at
    found = movements(positions(("t", 1), en, t0_ns=edge - 1 - k * (S // 10)), junction())
    (m,) = found
    assert m.t_ns == edge - 1 and binned(found, 900)[0].start_ns == T0  # entered 1 ns before the edge: that bin


def test_each_track_of_each_tracker_is_its_own_vehicle_and_positions_may_come_in_any_order():
    a = positions(("tracker-1", 7), through(-3.0, 166.0))
    b = positions(("tracker-2", 7), through(166.0, -3.0), t0_ns=T0 + 5 * S)
    mixed = a + b
    np.random.default_rng(0).shuffle(mixed)
    found = movements(mixed, junction())
    assert [(m.key, m.entry, m.exit) for m in found] == [(("tracker-1", 7), "north", "south"),
                                                          (("tracker-2", 7), "south", "north")]


def test_counts_are_binned_on_the_clock_with_approach_and_departure_volumes():
    t = T0 + 899 * S  # 16:14:59, the first 15-minute bin; then 16:15:00 and 16:31:00
    found = [Movement(("a", 1), "north", "south", t), Movement(("a", 2), "east", None, T0 + 900 * S),
             Movement(("a", 3), None, "west", T0 + 1860 * S), Movement(("a", 4), "north", "south", T0 + 1861 * S)]
    bins = binned(found, 900)
    assert [b.start_ns for b in bins] == [T0, T0 + 900 * S, T0 + 1800 * S]
    last = bins[2].to_json(junction())
    assert last["complete"][0][2] == 1 and last["complete_total"] == 1
    assert last["entering"] == {"north": 1, "east": 0, "south": 0, "west": 0}
    assert last["leaving"] == {"north": 0, "east": 0, "south": 1, "west": 1}
    second = bins[1].to_json(junction())
    assert second["entered_only"]["east"] == 1 and second["entering"]["east"] == 1
    for bad in (0, 0.5, 1e300, math.nan):
        with pytest.raises(ValueError, match="bin_s must be 1 to 604800 seconds"):
            binned(found, bad)


@pytest.mark.parametrize(("entry", "exit_", "turn"), [
    ("north", "south", "T"), ("north", "east", "L"), ("north", "west", "R"), ("north", "north", "U"),
    ("east", "west", "T"), ("east", "south", "L"), ("south", "east", "R"), ("west", "south", "R"),
    ("west", "north", "L"), ("south", "north", "T")])
def test_a_movement_is_a_turn_from_the_legs_bearings(entry, exit_, turn):
    """In from the north (heading south), out to the east is a left turn, whichever side the traffic drives on."""
    assert junction().turn(entry, exit_) == turn


def test_a_skewed_leg_is_through_within_45_degrees_and_a_turn_beyond():
    j = Junction(*CENTER, legs=(("a", 0.0), ("b", 130.0), ("c", 180.0), ("d", 235.0)), inner_radius_m=20,
                 outer_radius_m=60, half_width_deg=25)
    assert [j.turn("a", x) for x in "bcd"] == ["L", "T", "R"]  # 50 deg left of straight on, straight on, 55 right
    j = Junction(*CENTER, legs=(("a", 0.0), ("b", 140.0), ("c", 260.0)), inner_radius_m=20, outer_radius_m=60)
    assert [j.turn("a", x) for x in "bc"] == ["T", "R"]  # 40 deg off straight on is still through


def test_a_bin_says_how_much_of_it_the_tracks_covered():
    """Messages every 0.1 s from 16:14:00 to 16:16:00 with a 5 s hole at 16:15:30 (more than COVER_GAP_S: not
    covered) and a lone message at 16:40: 60 s of the first bin, 55 of the second, none of the third, which is
    left out unless a movement is in it."""
    times = [T0 + 840 * S + k * S // 10 for k in range(1201)]
    times = [t for t in times if not T0 + 930 * S < t < T0 + 935 * S] + [T0 + 2400 * S]
    bins = binned([], 900, times)
    assert [b.start_ns for b in bins] == [T0, T0 + 900 * S]
    assert bins[0].observed_ns == 60 * S and bins[1].observed_ns == pytest.approx(55 * S, abs=S // 5)
    bins = binned([Movement(("a", 1), "north", "south", T0 + 2400 * S)], 900, times)
    assert len(bins) == 3 and bins[2].observed_ns == 0 and bins[2].to_json(junction())["observed_s"] == 0.0


def test_live_counts_cover_what_the_files_count_covers():
    """The same messages, with holes, counted live and from a file: the same coverage per bin."""
    from shared.movements import LiveCounts

    rng = np.random.default_rng(5)
    steps = np.where(rng.random(3000) < 0.01, rng.uniform(2, 8, 3000), 0.1)  # now and then a hole of 2-8 s
    times = (T0 + np.cumsum(steps) * S).astype(np.int64).tolist()
    live = LiveCounts(junction(), bin_s=60, linger_s=2, close_after_s=5)
    out = [c for t in times for c in live.update(tracks_message(t, []))] + live.flush()
    files = binned([], 60, times)
    assert [(c.start_ns, c.observed_ns) for c in out if c.observed_ns] == [(c.start_ns, c.observed_ns) for c in files]
    assert sum(c.observed_ns for c in files) < (times[-1] - times[0]) - 10 * S  # the holes are not covered


def test_read_tracks_counts_and_names_bad_lines(tmp_path):
    good = {"site": "s", "seq": 0, "t_ns": T0, "tracker": "t1", "tracks": [{"id": 3, "lat": CENTER[0],
                                                                             "lon": CENTER[1]}]}
    f = tmp_path / "tracks.jsonl"
    f.write_text("\n".join([json.dumps(good), "{half", json.dumps({**good, "tracks": [{"id": 4, "lat": None,
                                                                                      "lon": 1.0}]}),
                            json.dumps({**good, "t_ns": "soon"}), "", json.dumps({**good, "t_ns": T0 + S}),
                            "[" * 100_000]) + "\n")
    read = read_tracks([f])
    assert read.lines == 6 and read.bad_lines == 4
    assert [p[:2] for p in read.positions] == [(("t1", 3), T0), (("t1", 3), T0 + S)]
    assert read.bad[0].startswith(f"{f}:2: JSONDecodeError") and read.bad[1].startswith(f"{f}:3: ValueError: track 4")
    with pytest.raises(ValueError, match=r"tracks file .*nothing"):
        read_tracks([tmp_path / "nothing.jsonl"])


def test_movement_of_plain_arrays():
    m = movement(("k", 1), np.arange(6) * S, np.array([NOWHERE, 2, INSIDE, 1, INSIDE, 3]), ["a", "b", "c", "d"])
    assert (m.entry, m.exit, m.t_ns) == ("c", "d", 2 * S)


# --- the site file and the command line -----------------------------------------------------------------------------


def write_site(folder: Path, movements_section: dict | None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"site": "se", "cameras": [{"name": "NE", "kind": "fisheye", "width": 1280, "height": 960}]}
    if movements_section is not None:
        doc["movements"] = movements_section
    (folder / "site.yaml").write_text(yaml.safe_dump(doc))
    return folder


SECTION = {"center": {"lat_deg": CENTER[0], "lon_deg": CENTER[1]},
           "legs": [{"name": n, "bearing_deg": b} for n, b in LEGS], "inner_radius_m": 24.4, "outer_radius_m": 70.0}


def test_the_site_files_movements_section_is_checked_naming_the_problem(tmp_path):
    from shared.settings import load_settings

    assert load_settings(write_site(tmp_path / "ok", SECTION)).movements.junction().names == [n for n, _ in LEGS]
    bad = {**SECTION, "legs": [{"name": "north", "bearing_deg": 0.0}, {"name": "east", "bearing_deg": 40.0}]}
    with pytest.raises(ValueError, match="legs north and east are 40 deg apart"):
        load_settings(write_site(tmp_path / "overlap", bad))
    with pytest.raises(ValueError, match=r"movements\.center needs lat_deg and lon_deg"):
        load_settings(write_site(tmp_path / "centre", {**SECTION, "center": {"lat": 1.0}}))


def tracks_file(path: Path, vehicles: list[tuple[int, np.ndarray, int]]) -> Path:
    """A tracks file (one line per 100 ms tick) of vehicles given as (id, positions, first tick)."""
    ticks = max(start + len(en) for _, en, start in vehicles)
    with path.open("w") as f:
        for k in range(ticks):
            rows = []
            for vid, en, start in vehicles:
                if start <= k < start + len(en):
                    lat, lon = latlon(en[k - start: k - start + 1])
                    rows.append({"id": vid, "lat": float(lat[0]), "lon": float(lon[0])})
            f.write(json.dumps({"site": "se", "seq": k, "t_ns": T0 + k * S // 10, "tracker": "t1", "tracks": rows})
                    + "\n")
    return path


def test_roadside_counts_prints_the_movements_per_bin(tmp_path, capsys):
    from roadside.cli import main

    site = write_site(tmp_path / "site", SECTION)
    f = tracks_file(tmp_path / "tracks.jsonl", [(1, through(-3.0, 166.0), 0), (2, through(90.0, 272.0), 5),
                                                (3, through(-3.0, 166.0), 40), (4, path(at(0, 60), at(0, 30)), 0)])
    assert main(["counts", str(f), "--site", str(site), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["legs"] == ["north", "east", "south", "west"] and doc["movements"] == 3 and doc["bad_lines"] == 0
    (b,) = doc["bins"]
    assert b["start"] == "2023-12-19T16:00:00Z" and b["end"] == "2023-12-19T16:15:00Z"
    assert b["complete"] == [[0, 0, 2, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]]
    assert main(["counts", str(f), "--site", str(site)]) == 0
    out = capsys.readouterr().out
    assert "3 vehicles through the junction" in out and "entering" in out
    assert main(["counts", str(f), "--site", str(write_site(tmp_path / "none", None))]) == 2
    assert "has no movements: section" in capsys.readouterr().err


def test_roadside_counts_writes_csv_and_appends_a_cabinets_file(tmp_path, capsys):
    from roadside.cli import main

    site = write_site(tmp_path / "site", SECTION)
    f = tracks_file(tmp_path / "tracks.jsonl", [(1, through(-3.0, 166.0), 0), (2, through(90.0, 166.0), 5)])
    assert main(["counts", str(f), "--site", str(site), "--csv", "--bin-s", "60"]) == 0
    rows = [line.split(",") for line in capsys.readouterr().out.splitlines()]
    assert rows[0] == ["start", "end", "observed_s", "from", "to", "turn", "vehicles"]
    assert len(rows) == 1 + 16 + 4 + 4  # one bin: every pair of legs, then entering only and leaving only
    counted = {(r[3], r[4], r[5]): int(r[6]) for r in rows[1:]}
    assert counted[("north", "south", "T")] == 1 and counted[("east", "south", "L")] == 1 and sum(counted.values()) == 2
    ticks = len(f.read_text().splitlines())  # a line every 0.1 s: the bin covered from the first to the last
    assert rows[1][:3] == ["2023-12-19T16:00:00Z", "2023-12-19T16:01:00Z", str(round((ticks - 1) / 10, 1))]
    out = tmp_path / "counts.csv"
    for _ in range(2):  # appended: one header
        assert main(["counts", str(f), "--site", str(site), "--out", str(out), "--json"]) == 0
    lines = out.read_text().splitlines()
    assert lines[0].startswith("start,end,") and len(lines) == 1 + 2 * 24 and lines.count(lines[0]) == 1
    assert json.loads(capsys.readouterr().out.split("\n}\n")[0] + "\n}")["bins"][0]["turns"]["north"]["T"] == 1
    assert main(["counts", str(f), "--site", str(site), "--csv", "--json"]) == 2
    assert "--csv or --json" in capsys.readouterr().err
    assert main(["counts", str(f), "--site", str(site), "--out", str(tmp_path)]) == 2
    assert "a folder, not a file" in capsys.readouterr().err
    assert main(["counts", str(f), "--site", str(site), "--heartbeat", str(tmp_path / "hb")]) == 2
    assert "--heartbeat goes with --live" in capsys.readouterr().err
    # a file with no tracks line is no count of zero; another site's tracks are not this junction's
    (tmp_path / "junk.jsonl").write_text("not json\n")
    assert main(["counts", str(tmp_path / "junk.jsonl"), "--site", str(site), "--csv"]) == 2
    assert "no tracks line in" in capsys.readouterr().err
    other = tmp_path / "other.jsonl"
    other.write_text(f.read_text().replace('"site": "se"', '"site": "elm"'))
    assert main(["counts", str(other), "--site", str(site)]) == 2
    assert "the tracks are of site elm" in capsys.readouterr().err
    for job in (["eval", "handoff"], ["eval", "real"]):  # nor scored against this site's cameras or labels
        assert main([*job, "--tracks", str(other), "--site", str(site)]) == 2
        assert "the tracks are of site elm" in capsys.readouterr().err


# --- against the truth ----------------------------------------------------------------------------------------------


def test_movements_are_scored_against_the_vehicles_through_the_tracks_matching(tmp_path, monkeypatch):
    """Three vehicles go through; the tracks count one right, one with the wrong exit, and lose the third's exit.
    The matching (eval.tracking's) is stood in for: each track is its vehicle's."""
    import eval.movements as em

    trips = {11: through(-3.0, 166.0), 12: through(90.0, 272.0), 13: through(166.0, -3.0)}
    geo = SimpleNamespace(to_geodetic=lambda xyz: GEO.to_geodetic(xyz))
    gt = SimpleNamespace(recording=SimpleNamespace(geo=geo), trajectories={
        v: SimpleNamespace(t_ns=T0 + np.arange(len(en)) * S // 10, xyz=np.column_stack([en, np.zeros(len(en))]))
        for v, en in trips.items()})
    monkeypatch.setattr(em, "GroundTruth", SimpleNamespace)  # the stand-in is taken as it is
    wrong_exit = through(90.0, 166.0)
    lost = trips[13][: np.flatnonzero(junction().zones(*latlon(trips[13])) == INSIDE)[-1]]
    f = tracks_file(tmp_path / "tracks.jsonl", [(1, trips[11], 0), (2, wrong_exit, 0), (3, lost, 0)])
    frames = [SimpleNamespace(matched={11: ("t1", 1), 12: ("t1", 2), 13: ("t1", 3)})]
    monkeypatch.setattr(em, "match_tracks", lambda *a, **k: SimpleNamespace(frames=frames))
    s = em.evaluate_movements(gt, f, junction())
    assert (s["complete_true"], s["complete_counted"]) == (3, 2)
    # true N->S, E->W, S->N; counted N->S, E->S: |E->W| 1 + |S->N| 1 + |E->S| 1 over 3
    assert s["count_error"] == pytest.approx(1.0)
    assert s["movement_recall"] == pytest.approx(1 / 3) and s["movement_precision"] == pytest.approx(1 / 2)
    assert s["entering_error"] == 0.0  # every vehicle's approach counted (the lost one's as entering only)
    assert s["leaving_error"] == pytest.approx(1.0)  # W 1 and N 1 missed, S 1 too many, over 3
    assert "count error 1.000" in em.as_table(s)


def test_a_simulated_roundabouts_junction_comes_from_its_site_and_an_intersections_is_asked_for():
    from shared.settings import MovementSettings
    from sim.site import load_site

    section = load_site("state_ellsworth").movements()
    j = MovementSettings.model_validate(section).junction()
    assert j.names == ["north", "east", "south", "west"] and j.inner_radius_m == pytest.approx(11 + 3.6 + 8.8 + 1)
    with pytest.raises(ValueError, match="give `movements:` in the site file"):
        load_site("intersection").movements()


# --- live ------------------------------------------------------------------------------------------------------------


def test_a_passage_followed_position_by_position_is_the_same_movement():
    from shared.movements import Passage

    rng = np.random.default_rng(3)
    names = ["a", "b", "c", "d"]
    for _ in range(500):
        zones = rng.choice([NOWHERE, INSIDE, 0, 1, 2, 3], size=int(rng.integers(1, 30)))
        t = np.arange(len(zones)) * S
        p = Passage(("k", 1))
        for ti, z in zip(t.tolist(), zones.tolist(), strict=True):
            p.add(ti, z)
        assert p.movement(names) == movement(("k", 1), t, zones, names), zones


def tracks_message(t_ns: int, rows: list[tuple[int, np.ndarray]], tracker: str = "t1", seq: int = 0):
    """A Tracks message of cars at ground positions (m, the junction's frame)."""
    from shared.messages import Tracks

    n, f4 = len(rows), np.float32
    en = np.array([p for _, p in rows], float).reshape(n, 2)
    lat, lon = latlon(en) if n else (np.zeros(0), np.zeros(0))
    return Tracks(site="se", seq=seq, t_capture_ns=t_ns, tracker=tracker, id=np.array([i for i, _ in rows], np.int64),
                  xy=en, latlon=np.column_stack([lat, lon]).reshape(n, 2), velocity=np.zeros((n, 2), f4),
                  yaw=np.zeros(n, f4), size_lwh=np.tile(np.array([4.5, 1.8, 1.5], f4), (n, 1)),
                  vtype=np.zeros(n, np.int8), score=np.full(n, 0.9, f4), age=np.zeros(n, np.int32),
                  hits=np.zeros(n, np.int32), cameras=[[] for _ in range(n)],
                  xy_cov=np.tile(np.eye(2, dtype=f4), (n, 1, 1)), velocity_cov=np.tile(np.eye(2, dtype=f4), (n, 1, 1)),
                  yaw_confirmed=np.zeros(n, bool), yaw_std=np.full(n, 0.2, f4))


def test_live_counts_close_each_bin_after_its_end_and_count_a_vehicle_once():
    """10 s bins, closed 5 s after their end: car 1 goes north -> south within the first bin; car 2 enters from the
    east at 8 s, slowly, and is still on the ring when the bin closes (counted entering only, and not again when it
    leaves); nothing else enters in the second bin (returned empty); the clock going back returns what is open."""
    from shared.movements import LiveCounts

    live = LiveCounts(junction(), bin_s=10, linger_s=2, close_after_s=5)
    one, two = through(-3.0, 166.0), through(90.0, 272.0, r_in=26.0, step_m=0.5)  # 10 and 5 m/s, a tick 0.1 s
    steps = int(30 / 0.1)
    closed = []
    for k in range(steps):
        rows = [(1, one[k])] if k < len(one) else []
        if 80 <= k < 80 + len(two):
            rows.append((2, two[k - 80]))
        closed += live.update(tracks_message(T0 + k * S // 10, rows))
    legs = [n for n, _ in LEGS]
    assert [(c.start_ns - T0) // S for c in closed] == [0, 10]
    first, second = (c.to_json(junction()) for c in closed)
    assert first["complete"][0][2] == 1 and first["complete_total"] == 1 and first["entered_only"]["east"] == 1
    assert second["complete_total"] == 0 and second["entering"] == dict.fromkeys(legs, 0)
    assert first["observed_s"] == second["observed_s"] == 10.0  # a message every 0.1 s through both
    # back in time: the bin still open (20-30 s, observed to 29.9 s, nobody through) comes out, then nothing
    (rest,) = live.update(tracks_message(T0, []))
    assert (rest.start_ns - T0) // S == 20 and rest.observed_ns == 99 * S // 10 and not rest.complete
    assert live.flush() == []
    with pytest.raises(ValueError, match="linger_s <= close_after_s"):
        LiveCounts(junction(), linger_s=30, close_after_s=10)


@pytest.mark.slow
def test_roadside_counts_live_counts_a_played_recording_as_the_files_are_counted(tmp_path):
    """`roadside counts --live` subscribed before `roadside play` publishes a tracks file: the bins it prints when
    the stream ends are the file's own counts."""
    import subprocess
    import sys

    from pipeline_fixtures import REPO, free_port_base, service_env

    port_base = free_port_base()
    site = write_site(tmp_path / "site", SECTION)
    doc = yaml.safe_load((site / "site.yaml").read_text())
    (site / "site.yaml").write_text(yaml.safe_dump({**doc, "bus": {"port_base": port_base}}))
    from services.fuse_track.recorder import Recorder

    vehicles = [(1, through(-3.0, 166.0), 0), (2, through(90.0, 272.0), 5), (3, through(166.0, 166.0), 60)]
    f = tmp_path / "tracks.jsonl"
    rec = Recorder(f)
    for k in range(max(start + len(en) for _, en, start in vehicles)):
        rec.write(tracks_message(T0 + k * S // 10, [(i, en[k - start]) for i, en, start in vehicles
                                                    if start <= k < start + len(en)], seq=k))
    rec.close()
    counts = subprocess.Popen([sys.executable, "-m", "roadside", "counts", "--live", "--site", str(site), "--json",
                               "--bin-s", "60", "--close-after-s", "120", "--timeout", "10", "--out",
                               str(tmp_path / "live.csv"), "--heartbeat", str(tmp_path / "alive")], cwd=REPO,
                              env=service_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        player = subprocess.run([sys.executable, "-m", "roadside", "play", str(f), "--pace", "10", "--port-base",
                                 str(port_base)], cwd=REPO, env=service_env(), capture_output=True, text=True,
                                timeout=120)
        out, err = counts.communicate(timeout=120)
    finally:
        counts.kill()
    assert player.returncode == 0, player.stdout + player.stderr
    assert counts.returncode == 0, err
    live = [json.loads(line) for line in out.splitlines()]
    from roadside.cli import main

    offline = tmp_path / "offline.json"
    with open(offline, "w") as handle:
        import contextlib

        with contextlib.redirect_stdout(handle):
            assert main(["counts", str(f), "--site", str(site), "--json", "--bin-s", "60"]) == 0
    files = json.loads(offline.read_text())["bins"]
    assert [{k: v for k, v in b.items() if k != "site"} for b in live] == files
    with open(offline, "w") as handle, contextlib.redirect_stdout(handle):
        assert main(["counts", str(f), "--site", str(site), "--csv", "--bin-s", "60"]) == 0
    assert (tmp_path / "live.csv").read_text() == offline.read_text()  # the cabinet's file: the same rows
    assert (tmp_path / "alive").is_file()  # touched as the tracks came
    assert files[0]["complete_total"] == 3 and files[0]["complete"][2][2] == 1  # a U-turn at the south leg


def test_live_counts_take_a_small_step_back_as_it_comes_and_a_jump_forward_at_once():
    from shared.movements import LiveCounts

    one = through(-3.0, 166.0)
    live = LiveCounts(junction(), bin_s=10, linger_s=2, close_after_s=5)
    out = []
    for k in range(len(one)):
        t = T0 + k * S // 10 - (1 if k == 50 else 0) * S // 20  # one tick 50 ms behind the one before it
        out += live.update(tracks_message(t, [(1, one[k])], seq=k))
    out += live.flush()
    assert sum(c.to_json(junction())["complete_total"] for c in out) == 1  # one vehicle, once, north -> south
    assert sum(sum(c.to_json(junction())["entered_only"].values()) for c in out) == 0
    # a clock set forward by years: no stall, no years of empty bins; then a big step back starts again
    live = LiveCounts(junction(), bin_s=1, linger_s=1, close_after_s=2)
    live.update(tracks_message(10**9, [(1, one[0])]))
    jumped = live.update(tracks_message(T0, []))
    assert len(jumped) <= LiveCounts.MAX_EMPTY_BINS + 1 and live.next_start > T0 - 10 * S
    assert live.update(tracks_message(10**9, [])) == [] and live.next_start == 10**9  # back: it started again


def test_the_mean_over_runs_leaves_out_a_run_without_movements(monkeypatch):
    import eval.movements as em

    scores = {"a": dict.fromkeys(em.MEAN_KEYS, 0.5), "b": dict.fromkeys(em.MEAN_KEYS, math.nan),
              "c": dict.fromkeys(em.MEAN_KEYS, 0.25)}
    monkeypatch.setattr(em, "evaluate_demo_movements", lambda d: {"demo": d, **scores[d]})
    out = em.evaluate_demos_movements(["a", "b", "c"])
    assert [r["demo"] for r in out["runs"]] == ["a", "b", "c"] and out["mean"]["count_error"] == 0.375
    assert math.isnan(em.evaluate_demos_movements(["b"])["mean"]["movement_recall"])
