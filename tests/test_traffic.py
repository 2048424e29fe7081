"""Road networks and microscopic traffic: no collisions, realistic vehicles, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.geometry import rect
from sim.roads import build_network
from sim.site import load_site
from sim.traffic import VEHICLE_TYPES, TrafficSim, simulate_traffic

SITES = ("state_ellsworth", "intersection")
SECONDS, SEED, WARMUP = 20, 3, 40
SAMPLE_DT = 0.5

# Plausible (min, max) length and width per vehicle type, metres.
SIZE_RANGES = {
    "car": ((3.5, 5.5), (1.5, 2.1)),
    "suv_van": ((4.0, 6.0), (1.7, 2.2)),
    "truck": ((4.5, 11.0), (2.2, 2.7)),
    "bus": ((10.0, 14.0), (2.4, 2.7)),
    "motorcycle": ((1.5, 2.7), (0.5, 1.1)),
}


@pytest.fixture(scope="module")
def runs() -> dict:
    out = {}
    for name in SITES:
        site = load_site(name)
        net = build_network(site)
        hist = simulate_traffic(site, net, seconds=SECONDS, seed=SEED, warmup_s=WARMUP)
        out[name] = (site, net, hist)
    return out


def _sample_times(hist) -> np.ndarray:
    return np.arange(0.0, hist.duration_s + 1e-9, SAMPLE_DT)


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Separating-axis test for two convex polygons: penetration depth (m), 0 if disjoint."""
    depth = math.inf
    for poly in (a, b):
        for i in range(len(poly)):
            e = poly[(i + 1) % len(poly)] - poly[i]
            n = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            pa, pb = a @ n, b @ n
            d = min(pa.max() - pb.min(), pb.max() - pa.min())
            if d <= 0:
                return 0.0
            depth = min(depth, d)
    return depth


def test_overlap_helper() -> None:
    a = rect((0.0, 0.0), 4.0, 2.0, 0.0)
    assert _overlap(a, rect((4.1, 0.0), 4.0, 2.0, 0.0)) == 0.0
    assert _overlap(a, rect((3.5, 0.0), 4.0, 2.0, 0.0)) == pytest.approx(0.5)
    # Diagonal neighbour whose bounding boxes overlap but the rectangles do not.
    sq = rect((0.0, 0.0), 2.0, 2.0, 0.0)
    assert _overlap(sq, rect((1.9, 1.9), 2.0, 2.0, math.radians(45))) == 0.0
    assert _overlap(sq, rect((1.6, 1.6), 2.0, 2.0, math.radians(45))) > 0
    assert _overlap(a, rect((0.0, 0.0), 1.0, 1.0, 0.7)) > 0


# ---- road network ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", SITES)
def test_network_routes_cover_every_approach(name: str) -> None:
    site = load_site(name)
    net = build_network(site)
    n = len(site.approaches)
    assert {r.origin for r in net.routes} == set(range(n))
    assert {r.dest for r in net.routes} >= set(range(n))
    for r in net.routes:
        assert np.all(np.diff(r.s) > 0)
        steps = np.linalg.norm(np.diff(r.points, axis=0), axis=1)
        assert steps.max() < 0.51
        assert np.all(r.speed_cap > 0)
        assert np.all(r.speed_cap <= r.speed_limit_mps + 1e-9)
        assert 0 < r.stop_s < r.length
        # Starts and ends near the edge of the modelled world.
        assert np.max(np.abs(r.points[0])) > 0.8 * site.extent_m
        assert np.max(np.abs(r.points[-1])) > 0.8 * site.extent_m


@pytest.mark.parametrize("name", SITES)
def test_right_turn_is_the_shortest_route_from_each_approach(name: str) -> None:
    """A right turn (next exit; CCW roundabout, right-hand traffic) must not loop the junction."""
    net = build_network(load_site(name))
    for a in {r.origin for r in net.routes}:
        mine = [r for r in net.routes if r.origin == a]
        rights = [r.length for r in mine if r.turn == "right"]
        others = [r.length for r in mine if r.turn in ("through", "left")]
        assert rights and others
        assert max(rights) < min(others), (
            f"{name}: approach {a} right-turn route is {max(rights):.0f} m, "
            f"longer than a through/left route ({min(others):.0f} m)"
        )


# ---- traffic --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SITES)
def test_no_vehicle_footprints_overlap(runs, name: str) -> None:
    _, _, hist = runs[name]
    collisions = _collisions(hist)
    assert not collisions, f"{name}: overlapping vehicles (t, id, id): {collisions}"


def _collisions(hist) -> list[tuple]:
    out = []
    for t in _sample_times(hist):
        st = hist.state_at(float(t))
        polys = [rect(st.xy[i], st.lwh[i, 0], st.lwh[i, 1], st.yaw[i]) for i in range(len(st))]
        radius = 0.5 * np.hypot(st.lwh[:, 0], st.lwh[:, 1])
        for i in range(len(st)):
            for j in range(i + 1, len(st)):
                if np.linalg.norm(st.xy[i] - st.xy[j]) <= radius[i] + radius[j] and _overlap(polys[i], polys[j]) > 0:
                    out.append((round(float(t), 2), int(st.ids[i]), int(st.ids[j])))
    return out


# Seeds that once produced collisions: a bus sweeping into the next lane on an entry curve, and
# entering vehicles stalled in the ring after a gap closed.
@pytest.mark.parametrize("seed", [1, 2, 10])
def test_no_overlap_on_more_roundabout_seeds(seed: int) -> None:
    site = load_site("state_ellsworth")
    hist = simulate_traffic(site, build_network(site), seconds=60.0, seed=seed)
    assert _collisions(hist) == [], f"seed {seed}"


def test_vehicle_types_across_sites() -> None:
    # A 20 s clip holds ~30 moving vehicles and can miss the 5 % types; 200 s holds ~120.
    site = load_site("state_ellsworth")
    hist = simulate_traffic(site, build_network(site), seconds=200.0, seed=SEED, warmup_s=WARMUP)
    seen = {info.type for info in hist.info.values()}
    assert seen <= set(VEHICLE_TYPES)
    assert len(seen) >= 4, seen


@pytest.mark.parametrize("name", SITES)
def test_every_approach_gets_traffic(runs, name: str) -> None:
    site, net, hist = runs[name]
    origins = set()
    for snap in hist.snaps:
        origins |= {net.routes[int(r)].origin for r in snap["route"]}
    assert origins == set(range(len(site.approaches)))


@pytest.mark.parametrize("name", SITES)
def test_speeds_realistic(runs, name: str) -> None:
    _, _, hist = runs[name]
    speeds = []
    for t in _sample_times(hist):
        st = hist.state_at(float(t))
        assert np.all(st.speed >= 0)
        np.testing.assert_allclose(np.linalg.norm(st.velocity, axis=1), st.speed, atol=1e-9)
        speeds.append(st.speed[~st.parked])
    sp = np.concatenate(speeds)
    moving = sp[sp > 0.5]
    assert moving.size > 100
    assert moving.max() < 20.0
    assert 2.0 < moving.mean() < 15.0


@pytest.mark.parametrize("name", SITES)
def test_speed_consistent_with_motion(runs, name: str) -> None:
    """Between two snapshots, a vehicle's path advance lies between min(v)*dt and max(v)*dt."""
    _, _, hist = runs[name]
    dt = hist.dt_s
    checked = 0
    for a, b in zip(hist.snaps[:-1], hist.snaps[1:], strict=True):
        common, ia, ib = np.intersect1d(a["ids"], b["ids"], return_indices=True)
        assert np.array_equal(a["route"][ia], b["route"][ib])  # routes never change
        ds = b["s"][ib] - a["s"][ia]
        lo = np.minimum(a["v"][ia], b["v"][ib]) * dt
        hi = np.maximum(a["v"][ia], b["v"][ib]) * dt
        assert np.all(ds >= lo - 1e-9)
        assert np.all(ds <= hi + 1e-9)
        checked += len(common)
    assert checked > 1000


@pytest.mark.parametrize("name", SITES)
def test_parked_vehicles_exist_and_never_move(runs, name: str) -> None:
    _, _, hist = runs[name]
    ref = hist.state_at(0.0)
    assert ref.parked.sum() > 0
    p_ids = ref.ids[ref.parked]
    p_xy = ref.xy[ref.parked]
    p_yaw = ref.yaw[ref.parked]
    assert set(VEHICLE_TYPES[i] for i in ref.type_idx[ref.parked]) <= {"car", "suv_van"}
    for t in _sample_times(hist)[1:]:
        st = hist.state_at(float(t))
        np.testing.assert_array_equal(st.ids[st.parked], p_ids)
        np.testing.assert_array_equal(st.xy[st.parked], p_xy)
        np.testing.assert_array_equal(st.yaw[st.parked], p_yaw)
        assert np.all(st.speed[st.parked] == 0)
    # Parked vehicles stand off the lane routes (in the parking rows).
    _, net, _ = runs[name]
    lanes = np.concatenate([r.points for r in net.routes])
    d = np.min(np.linalg.norm(p_xy[:, None, :] - lanes[None, :, :], axis=2), axis=1)
    assert d.min() > 2.0


@pytest.mark.parametrize("name", SITES)
def test_sizes_in_realistic_ranges(runs, name: str) -> None:
    _, _, hist = runs[name]
    assert len(hist.info) > 10
    for info in hist.info.values():
        (l0, l1), (w0, w1) = SIZE_RANGES[info.type]
        assert l0 <= info.length_m <= l1, info
        assert w0 <= info.width_m <= w1, info
        assert 0.8 < info.height_m < 4.0, info
    st = hist.state_at(7.3)
    for i, vid in enumerate(st.ids):
        info = hist.info[int(vid)]
        assert VEHICLE_TYPES[st.type_idx[i]] == info.type
        np.testing.assert_array_equal(st.lwh[i], [info.length_m, info.width_m, info.height_m])


def test_sizes_of_many_new_vehicles_including_buses() -> None:
    site = load_site("intersection")
    sim = TrafficSim(site, build_network(site), np.random.default_rng(0))
    infos = [sim._new_vehicle(False) for _ in range(3000)]
    by_type: dict[str, list] = {t: [] for t in VEHICLE_TYPES}
    for info in infos:
        by_type[info.type].append(info)
    for typ, items in by_type.items():
        assert len(items) > 50, typ
        (l0, l1), (w0, w1) = SIZE_RANGES[typ]
        lengths = np.array([i.length_m for i in items])
        widths = np.array([i.width_m for i in items])
        assert l0 <= lengths.min() and lengths.max() <= l1, typ
        assert w0 <= widths.min() and widths.max() <= w1, typ
    assert np.mean([i.length_m for i in by_type["bus"]]) == pytest.approx(12.0, abs=0.3)
    assert np.mean([i.length_m for i in by_type["car"]]) == pytest.approx(4.55, abs=0.1)


def test_type_weights_shift_the_mix_and_parked_vehicles_stay_cars() -> None:
    site = load_site("state_ellsworth")
    net = build_network(site)
    plain = TrafficSim(site, net, np.random.default_rng(0))
    heavy = TrafficSim(site, net, np.random.default_rng(0), type_weights={"bus": 6.0, "truck": 3.0, "motorcycle": 0})
    n = 4000
    share = {}
    for name, sim in (("plain", plain), ("heavy", heavy)):
        types = [sim._new_vehicle(False).type for _ in range(n)]
        share[name] = {t: types.count(t) / n for t in VEHICLE_TYPES}
    assert share["plain"]["bus"] == pytest.approx(0.05, abs=0.015)
    # bus 0.05 * 6 and truck 0.08 * 3 over 0.52 + 0.30 + 0.24 + 0.30 (motorcycles weighted out)
    assert share["heavy"]["bus"] == pytest.approx(0.30 / 1.36, abs=0.025)
    assert share["heavy"]["truck"] == pytest.approx(0.24 / 1.36, abs=0.025)
    assert share["heavy"]["motorcycle"] == 0
    assert {heavy.info[i].type for i, _, _ in heavy._parked} <= {"car", "suv_van"}  # parking is for cars


def test_bad_type_weights_are_named() -> None:
    site = load_site("intersection")
    net = build_network(site)
    for weights, word in [({"plane": 2.0}, "plane"), ({"bus": -1.0}, "bus"), ({"bus": float("nan")}, "bus"),
                          ({t: 0.0 for t in VEHICLE_TYPES}, "no vehicle type")]:
        with pytest.raises(ValueError, match=word):
            TrafficSim(site, net, np.random.default_rng(0), type_weights=weights)


def _state_tuple(hist, t: float) -> tuple:
    st = hist.state_at(t)
    return (st.ids, st.xy, st.yaw, st.lwh, st.speed, st.type_idx, st.colors, st.parked, st.ped_xy)


def test_same_seed_identical_different_seed_differs(runs) -> None:
    site, net, hist = runs["intersection"]
    again = simulate_traffic(site, net, seconds=SECONDS, seed=SEED, warmup_s=WARMUP)
    other = simulate_traffic(site, net, seconds=SECONDS, seed=SEED + 1, warmup_s=WARMUP)
    differs = False
    for t in (0.0, 3.25, 11.0, 19.95):
        for x, y in zip(_state_tuple(hist, t), _state_tuple(again, t), strict=True):
            np.testing.assert_array_equal(x, y)
        a, b = _state_tuple(hist, t), _state_tuple(other, t)
        differs |= any(x.shape != y.shape or not np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert differs


def test_state_at_interpolates_between_snapshots(runs) -> None:
    _, _, hist = runs["intersection"]
    a, b, m = hist.state_at(5.0), hist.state_at(5.1), hist.state_at(5.05)
    moving = [i for i in m.ids if i in a.ids and i in b.ids and not m.parked[list(m.ids).index(i)]]
    assert moving
    for vid in moving:
        ia, ib, im = (list(s.ids).index(vid) for s in (a, b, m))
        # Midway along the route: within a few cm of the chord midpoint.
        assert np.linalg.norm(m.xy[im] - 0.5 * (a.xy[ia] + b.xy[ib])) < 0.05
        assert m.speed[im] == pytest.approx(0.5 * (a.speed[ia] + b.speed[ib]))


def test_state_at_outside_clip_raises(runs) -> None:
    _, _, hist = runs["intersection"]
    assert hist.duration_s == pytest.approx(SECONDS)
    hist.state_at(0.0)
    hist.state_at(hist.duration_s)
    for t in (-0.1, hist.duration_s + 0.5, 1e6):
        with pytest.raises(ValueError, match="t_s"):
            hist.state_at(t)


def test_bad_arguments_raise() -> None:
    site = load_site("intersection")
    net = build_network(site)
    with pytest.raises(ValueError, match="max_vehicles"):
        TrafficSim(site, net, np.random.default_rng(0), max_vehicles=0)
    with pytest.raises(ValueError, match="demand_scale"):
        TrafficSim(site, net, np.random.default_rng(0), demand_scale=-1.0)
    with pytest.raises(ValueError, match="seconds"):
        simulate_traffic(site, net, seconds=0, seed=1)


def test_max_vehicles_respected() -> None:
    site = load_site("state_ellsworth")
    net = build_network(site)
    hist = simulate_traffic(site, net, seconds=2, seed=5, warmup_s=30, max_vehicles=6)
    assert max(len(s["ids"]) for s in hist.snaps) <= 6
