"""Microscopic traffic on the road network: vehicles follow lane routes with the Intelligent
Driver Model, yield at roundabout entries (gap acceptance), stop at red signals, never drive
into a vehicle standing in their path, and enter from every approach as Poisson arrivals.
Parked vehicles stand in parking rows; pedestrians walk the sidewalks (distractors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.roads import AXLE_SPAN, ROUTE_STEP_M, SEGMENT_KINDS, RoadNetwork, body_pose
from sim.site import SiteSpec

VEHICLE_TYPES = ("car", "suv_van", "truck", "bus", "motorcycle")
# type: (share, (length mean, sd), (width mean, sd), (height mean, sd)) in metres.
TYPE_SIZES = {
    "car": (0.52, (4.55, 0.30), (1.80, 0.07), (1.46, 0.07)),
    "suv_van": (0.30, (4.95, 0.30), (1.96, 0.07), (1.80, 0.12)),
    "truck": (0.08, (7.60, 1.20), (2.45, 0.08), (3.10, 0.30)),
    "bus": (0.05, (12.0, 0.60), (2.55, 0.04), (3.20, 0.10)),
    "motorcycle": (0.05, (2.10, 0.15), (0.80, 0.08), (1.45, 0.08)),
}
# Body colours (RGB) of ordinary vehicles, with their shares on US roads.
PALETTE = [
    ((235, 235, 232), 0.23),
    ((22, 22, 25), 0.19),
    ((105, 108, 112), 0.15),
    ((175, 178, 182), 0.13),
    ((30, 60, 125), 0.09),
    ((150, 20, 22), 0.09),
    ((25, 70, 45), 0.03),
    ((200, 185, 150), 0.03),
    ((210, 100, 20), 0.02),
    ((90, 60, 40), 0.02),
    ((225, 190, 40), 0.02),
]
TURN_SHARES = {"right": 0.25, "through": 0.5, "left": 0.2, "uturn": 0.05}
LOOKAHEAD_M = 45
IDM_TIME_HEADWAY_S = 1.3
IDM_MIN_GAP_M = 1.6
IDM_DECEL_MPS2 = 2.2
MAX_DECEL_MPS2 = 9.0
GAP_ACCEPT_S = 3.5
LATERAL_CLEARANCE_M = 0.35
CLOSE_CONFLICT_M = 3.0
SPAWN_CLEARANCE_M = 19.0  # the longest vehicle (13 m) plus a gap


@dataclass(frozen=True)
class VehicleInfo:
    """Static attributes of one vehicle."""

    id: int
    type: str
    length_m: float
    width_m: float
    height_m: float
    color: tuple[int, int, int]
    parked: bool


def check_type_weights(weights: dict[str, float] | None) -> dict[str, float]:
    """The type weights (vehicle type -> factor on its share of the mix), checked; ValueError naming the bad one."""
    out = {}
    for typ, w in (weights or {}).items():
        if typ not in TYPE_SIZES:
            raise ValueError(f"type weight for unknown vehicle type {typ!r}; types: {', '.join(VEHICLE_TYPES)}")
        if not (math.isfinite(w) and w >= 0):
            raise ValueError(f"type weight for {typ} must be a finite number >= 0, got {w}")
        out[typ] = float(w)
    if out and not any(out.get(t, 1.0) > 0 for t in VEHICLE_TYPES):
        raise ValueError("type weights leave no vehicle type with a share above 0")
    return out


def sample_vehicle(rng: np.random.Generator, vid: int = 0, parked: bool = False,
                   allowed: tuple[str, ...] = VEHICLE_TYPES, weights: dict[str, float] | None = None) -> VehicleInfo:
    """A vehicle drawn from the type mix (each type's share times `weights[type]`, default 1), size distributions
    and colour palette."""
    shares = np.array([TYPE_SIZES[t][0] * (weights or {}).get(t, 1.0) for t in allowed])
    if not shares.sum() > 0:  # every allowed type weighted out: draw from them as if unweighted
        shares = np.array([TYPE_SIZES[t][0] for t in allowed])
    typ = allowed[int(rng.choice(len(allowed), p=shares / shares.sum()))]
    _, lm, wm, hm = TYPE_SIZES[typ]
    size = [float(np.clip(rng.normal(m, sd), m - 2.5 * sd, m + 2.5 * sd)) for m, sd in (lm, wm, hm)]
    if typ == "bus":
        color = [(230, 190, 30), (240, 240, 238), (40, 80, 150)][int(rng.integers(3))]
    elif typ == "truck":
        color = [(235, 235, 232), (200, 30, 30), (60, 90, 160), (240, 240, 240)][int(rng.integers(4))]
    else:
        shares = np.array([p for _, p in PALETTE])
        base = PALETTE[int(rng.choice(len(PALETTE), p=shares / shares.sum()))][0]
        color = tuple(int(np.clip(c + rng.normal(0, 8), 0, 255)) for c in base)
    return VehicleInfo(vid, typ, size[0], size[1], size[2], tuple(color), parked)


@dataclass
class SceneState:
    """All vehicles at one instant (struct of arrays, N vehicles).

    ids (N,) int; xy (N, 2) bottom centre, site metres; yaw (N,) rad ENU; lwh (N, 3) metres;
    speed (N,) m/s; velocity (N, 2) m/s; type_idx (N,) index into VEHICLE_TYPES; colors (N, 3)
    uint8 RGB; parked (N,) bool. Pedestrians: ped_xy (P, 2), ped_yaw (P,), ped_color (P, 3).
    """

    t_s: float
    ids: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    lwh: np.ndarray
    speed: np.ndarray
    velocity: np.ndarray
    type_idx: np.ndarray
    colors: np.ndarray
    parked: np.ndarray
    ped_xy: np.ndarray
    ped_yaw: np.ndarray
    ped_color: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class TrafficSim:
    """Steps traffic on a road network. Vehicle ids come from this instance only."""

    def __init__(
        self,
        site: SiteSpec,
        net: RoadNetwork,
        rng: np.random.Generator,
        max_vehicles: int = 100,
        demand_scale: float = 1.0,
        type_weights: dict[str, float] | None = None,
    ) -> None:
        self.type_weights = check_type_weights(type_weights)
        if max_vehicles < 1:
            raise ValueError(f"max_vehicles must be >= 1, got {max_vehicles}")
        if demand_scale < 0 or not math.isfinite(demand_scale):
            raise ValueError(f"demand_scale must be a finite number >= 0, got {demand_scale}")
        self.site, self.net, self.rng = site, net, rng
        self.max_vehicles = max_vehicles
        self.demand_scale = demand_scale
        self._next_id = 1
        self.info: dict[int, VehicleInfo] = {}
        # Concatenated route tables, indexed by offset + round(s / step).
        lens = [len(r.s) for r in net.routes]
        self._off = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
        self._len = np.array(lens, dtype=np.int64)
        self._pts = np.concatenate([r.points for r in net.routes])
        self._head = np.concatenate([r.heading for r in net.routes])
        self._curv = np.concatenate([np.abs(np.gradient(r.heading)) / ROUTE_STEP_M for r in net.routes])
        self._cap = np.concatenate([r.speed_cap for r in net.routes])
        self._pri = np.concatenate([r.seg_priority for r in net.routes])
        self._kind = np.concatenate([r.seg_kind for r in net.routes])
        self._stop_s = np.array([r.stop_s for r in net.routes])
        self._route_len = np.array([r.length for r in net.routes])
        self._merge = np.array([np.nan if r.merge_polar is None else r.merge_polar for r in net.routes])
        # Moving vehicles (struct of arrays).
        self.ids = np.zeros(0, np.int64)
        self.route = np.zeros(0, np.int64)
        self.s = np.zeros(0)
        self.v = np.zeros(0)
        self.length = np.zeros(0)
        self.width = np.zeros(0)
        self.accel = np.zeros(0)
        self.speed_factor = np.zeros(0)
        self.committed = np.zeros(0, bool)
        self._parked = self._place_parked()
        self._pending = [0] * len(site.approaches)  # arrivals waiting for room at the entry
        self._spawn_routes = [self._route_choice(a) for a in range(len(site.approaches))]
        self._peds = self._place_pedestrians()

    # ---- vehicles ---------------------------------------------------------------------------
    def _new_vehicle(self, parked: bool, allowed: tuple[str, ...] = VEHICLE_TYPES) -> VehicleInfo:
        info = sample_vehicle(self.rng, self._next_id, parked, allowed, self.type_weights)
        self.info[info.id] = info
        self._next_id += 1
        return info

    def _place_parked(self) -> list[tuple[int, np.ndarray, float]]:
        out = []
        for xy, yaw, occupancy in self.net.parking_slots:
            if self.rng.random() < occupancy:
                info = self._new_vehicle(True, ("car", "suv_van"))
                yaw = yaw + (math.pi if self.rng.random() < 0.5 else 0.0) + self.rng.normal(0, 0.03)
                jitter = self.rng.normal(0, 0.12, 2)
                out.append((info.id, np.asarray(xy, float) + jitter, float(yaw)))
        return out

    def _place_pedestrians(self) -> dict[str, np.ndarray]:
        n = self.site.pedestrians
        paths = self.net.sidewalk_paths
        path_idx = self.rng.integers(0, len(paths), n) if paths else np.zeros(0, int)
        lens = np.array([np.linalg.norm(paths[i][-1] - paths[i][0]) for i in path_idx])
        shirts = np.array(
            [
                (180, 40, 40),
                (40, 60, 140),
                (30, 30, 30),
                (220, 220, 210),
                (60, 120, 60),
                (200, 160, 60),
                (120, 120, 125),
            ]
        )
        return {
            "path": path_idx,
            "s": self.rng.uniform(0, 1, n) * lens,
            "len": lens,
            "speed": self.rng.uniform(0.9, 1.6, n),
            "dir": np.where(self.rng.random(n) < 0.5, -1.0, 1.0),
            "color": shirts[self.rng.integers(0, len(shirts), n)].astype(np.uint8),
        }

    def _route_choice(self, a: int) -> tuple[list[int], np.ndarray]:
        """Routes starting on approach a and their probabilities (turn share split over lanes)."""
        cands = [i for i, r in enumerate(self.net.routes) if r.origin == a]
        turns = [self.net.routes[i].turn for i in cands]
        w = np.array([TURN_SHARES[t] / turns.count(t) for t in turns])
        return cands, w / w.sum()

    def _spawn(self, dt: float) -> None:
        for a, leg in enumerate(self.site.approaches):
            rate = leg.demand_veh_h * self.demand_scale / 3600.0
            if self.rng.random() < 1 - math.exp(-rate * dt):
                self._pending[a] += 1
            if not self._pending[a] or len(self.ids) >= self.max_vehicles:
                continue
            cands, p = self._spawn_routes[a]
            ri = cands[int(self.rng.choice(len(cands), p=p))]
            start = self._pts[self._off[ri]]
            if len(self.ids):
                pos = self._pts[self._index(self.route, self.s)]
                if np.min(np.linalg.norm(pos - start, axis=1)) < SPAWN_CLEARANCE_M:
                    continue
            info = self._new_vehicle(False)
            self._pending[a] -= 1
            factor = self.rng.normal(1.0, 0.08)
            if self.rng.random() < 0.08:
                factor = self.rng.uniform(0.45, 0.65)  # slow-moving vehicles
            if info.type in ("truck", "bus"):
                factor = min(factor, 0.9)
            self.ids = np.append(self.ids, info.id)
            self.route = np.append(self.route, ri)
            self.s = np.append(self.s, info.length_m / 2)
            self.length = np.append(self.length, info.length_m)
            self.width = np.append(self.width, info.width_m)
            self.speed_factor = np.append(self.speed_factor, float(np.clip(factor, 0.4, 1.25)))
            v0 = self._cap[self._index(np.array([ri]), np.array([info.length_m / 2]))][0] * self.speed_factor[-1]
            self.v = np.append(self.v, min(v0, 10.0))
            self.accel = np.append(self.accel, 1.0 if info.type in ("truck", "bus") else 1.6)
            self.committed = np.append(self.committed, False)

    def _index(self, route: np.ndarray, s: np.ndarray) -> np.ndarray:
        k = np.clip(np.round(s / ROUTE_STEP_M).astype(np.int64), 0, self._len[route] - 1)
        return self._off[route] + k

    def _body(self) -> tuple[np.ndarray, np.ndarray]:
        """Body centres (N, 2) and unit headings (N, 2) of the moving vehicles (Route.pose)."""
        span = AXLE_SPAN * self.length
        pos, yaw = body_pose(
            self._pts[self._index(self.route, self.s + span)], self._pts[self._index(self.route, self.s - span)]
        )
        return pos, np.stack([np.cos(yaw), np.sin(yaw)], 1)

    def _obstacles(self, pos: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Footprint segments (rear, front), half widths and velocities of every vehicle."""
        rear = pos - h * self.length[:, None] / 2
        front = pos + h * self.length[:, None] / 2
        vel = h * self.v[:, None]
        half_w = self.width / 2
        if self._parked:
            p_info = [self.info[i] for i, _, _ in self._parked]
            p_pos = np.array([xy for _, xy, _ in self._parked])
            p_h = np.array([[math.cos(y), math.sin(y)] for _, _, y in self._parked])
            p_len = np.array([i.length_m for i in p_info])
            rear = np.concatenate([rear, p_pos - p_h * p_len[:, None] / 2])
            front = np.concatenate([front, p_pos + p_h * p_len[:, None] / 2])
            vel = np.concatenate([vel, np.zeros((len(p_info), 2))])
            half_w = np.concatenate([half_w, np.array([i.width_m / 2 for i in p_info])])
        return rear, front, half_w, vel

    def _must_wait(self, t_s: float, idx: np.ndarray) -> np.ndarray:
        """(N,) bool: the vehicle must treat its stop line as a wall now."""
        n = len(self.ids)
        wait = np.zeros(n, bool)
        if n == 0:
            return wait
        front_s = self.s + self.length / 2
        before = (front_s < self._stop_s[self.route] + 0.1) & ~self.committed
        near = before & (self._stop_s[self.route] - front_s < LOOKAHEAD_M)
        if not near.any():
            return wait
        if self.net.signal_plan is not None:
            for i in np.nonzero(near)[0]:
                state = self.net.signal_state(self.net.routes[self.route[i]].signal_group, t_s)
                dist = self._stop_s[self.route[i]] - front_s[i]
                can_stop = self.v[i] ** 2 <= 2 * 4.0 * max(dist, 0.01)
                wait[i] = state == "red" or (state == "yellow" and can_stop)
            return wait
        # Roundabout: gap acceptance against vehicles already in the ring or entering it.
        kind = self._kind[idx]
        pos = self._pts[idx]
        circ = (kind == SEGMENT_KINDS.index("entry")) | (kind == SEGMENT_KINDS.index("ring"))
        if not circ.any():
            return wait
        phi = np.arctan2(pos[circ, 1], pos[circ, 0])
        rad = np.linalg.norm(pos[circ], axis=1)
        vc = self.v[circ]
        for i in np.nonzero(near)[0]:
            merge = self._merge[self.route[i]]
            delta = (merge - phi) % (2 * math.pi)
            arc_m = delta * rad
            coming = arc_m < np.maximum(14.0, vc * GAP_ACCEPT_S) + 4.0
            at_merge = delta > 2 * math.pi - 7.0 / np.maximum(rad, 1.0)
            wait[i] = bool(np.any(coming | at_merge))
        return wait

    def step(self, dt: float, t_s: float) -> None:
        self._spawn(dt)
        self._step_pedestrians(dt)
        n = len(self.ids)
        if n == 0:
            return
        # Samples of each vehicle's path from its front bumper to LOOKAHEAD_M ahead; other vehicles
        # are their exact footprints, and the curve margin below covers a long body's sweep.
        ks = np.arange(0.0, LOOKAHEAD_M, 1.0)
        front_s = self.s + self.length / 2
        idx_ahead = self._index(np.repeat(self.route, len(ks)), (front_s[:, None] + ks[None, :]).ravel())
        ahead = self._pts[idx_ahead].reshape(n, len(ks), 2)
        idx_now = self._index(self.route, self.s)
        pos_now, h_now = self._body()
        # On a curve a rigid body's ends stand off its path by (L/2)^2 * curvature / 2.
        kappa = self._curv[idx_ahead].reshape(n, len(ks)).max(axis=1)
        off_tracking = np.minimum(0.5 * (self.length / 2) ** 2 * kappa, 1.5)
        rear, front, half_w, vel = self._obstacles(pos_now, h_now)
        seg = front - rear
        seg_len2 = np.maximum(np.sum(seg**2, 1), 1e-9)
        rel = ahead[:, :, None, :] - rear[None, None, :, :]
        t = np.clip(np.sum(rel * seg[None, None], -1) / seg_len2, 0.0, 1.0)
        closest = rear[None, None] + t[..., None] * seg[None, None]
        dist = np.linalg.norm(ahead[:, :, None, :] - closest, axis=-1)
        reach = self.width / 2 + off_tracking + LATERAL_CLEARANCE_M
        blocked = dist < (reach[:, None, None] + half_w[None, None, :])
        m = blocked.shape[2]
        blocked[np.arange(n), :, np.arange(n)] = False
        hit_any = blocked.any(axis=1)
        first = np.where(hit_any, ks[blocked.argmax(axis=1)], np.inf)  # (n, m) gap in m
        # Mutual blocking: the one behind the other (seen from both headings) yields; otherwise
        # the one with right of way goes, then the one nearer the conflict, then the older one.
        g = first[:, :n]
        pri = self._pri[idx_now].astype(float)
        pri_all = np.concatenate([pri, np.full(m - n, 9.0)])
        mutual = np.isfinite(first[:, :n]) & np.isfinite(first[:, :n].T)
        pos_i, h_i = pos_now, h_now
        rel_ij = pos_i[None, :, :] - pos_i[:, None, :]  # j - i
        ahead_of_i = np.einsum("ijk,ik->ij", rel_ij, h_i) > 0  # j is ahead of i
        behind = ahead_of_i & ~ahead_of_i.T  # i is behind j
        # A close conflict (one already stands in or at the other's path) is not decided by right
        # of way: the one more in the other's way goes first to clear it, the other waits.
        nearer = (g < g.T) | ((g == g.T) & (self.ids[:, None] > self.ids[None, :]))
        close = np.minimum(g, g.T) < CLOSE_CONFLICT_M
        by_right_of_way = (pri[:, None] < pri_all[None, :n]) | ((pri[:, None] == pri_all[None, :n]) & nearer)
        yields = behind | (~behind.T & np.where(close, nearer, by_right_of_way))
        ignore = np.zeros((n, m), bool)
        ignore[:, :n] = mutual & ~yields
        first = np.where(ignore, np.inf, first)
        leader = np.argmin(first, axis=1)
        gap = first[np.arange(n), leader]
        v_lead = np.where(np.isfinite(gap), np.sum(vel[leader] * h_i, 1), 0.0)
        v_lead = np.maximum(v_lead, 0.0)
        # Stop lines.
        wait = self._must_wait(t_s, idx_now)
        stop_gap = np.where(wait, self._stop_s[self.route] - front_s, np.inf)
        use_stop = stop_gap < gap
        gap = np.where(use_stop, np.maximum(stop_gap, 0.0), gap)
        v_lead = np.where(use_stop, 0.0, v_lead)
        self.committed |= front_s >= self._stop_s[self.route]
        # IDM.
        v0 = np.maximum(self._cap[self._index(self.route, front_s)] * self.speed_factor, 0.5)
        dv = self.v - v_lead
        s_star = IDM_MIN_GAP_M + self.v * IDM_TIME_HEADWAY_S + self.v * dv / (2 * np.sqrt(self.accel * IDM_DECEL_MPS2))
        s_star = np.maximum(s_star, IDM_MIN_GAP_M)
        with np.errstate(divide="ignore"):
            interaction = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.05)) ** 2, 0.0)
        acc = self.accel * (1 - (self.v / v0) ** 4 - interaction)
        acc = np.clip(acc, -MAX_DECEL_MPS2, self.accel)
        v_new = np.maximum(self.v + acc * dt, 0.0)
        ds = 0.5 * (self.v + v_new) * dt
        # Hard constraint: never move into the obstacle ahead.
        room = np.where(np.isfinite(gap), np.maximum(gap - 0.3, 0.0), np.inf)
        over = ds > room
        ds = np.where(over, room, ds)
        v_new = np.where(over, np.minimum(v_new, room / dt), v_new)
        self.s = self.s + ds
        self.v = v_new
        keep = self.s + self.length / 2 < self._route_len[self.route] - 0.5
        for name in ("ids", "route", "s", "v", "length", "width", "accel", "speed_factor", "committed"):
            setattr(self, name, getattr(self, name)[keep])

    def _step_pedestrians(self, dt: float) -> None:
        p = self._peds
        if len(p["s"]) == 0:
            return
        p["s"] = p["s"] + p["dir"] * p["speed"] * dt
        flip = (p["s"] < 0) | (p["s"] > p["len"])
        p["dir"] = np.where(flip, -p["dir"], p["dir"])
        p["s"] = np.clip(p["s"], 0, p["len"])

    def snapshot(self) -> dict[str, np.ndarray]:
        """The dynamic state, for TrafficHistory."""
        return {
            "ids": self.ids.copy(),
            "route": self.route.copy(),
            "s": self.s.copy(),
            "v": self.v.copy(),
            "ped_s": self._peds["s"].copy(),
            "ped_dir": self._peds["dir"].copy(),
        }


class TrafficHistory:
    """A simulated clip's traffic, sampled every `dt_s`, queried at any capture time."""

    def __init__(self, sim: TrafficSim, dt_s: float, snaps: list[dict[str, np.ndarray]]) -> None:
        self.sim, self.dt_s, self.snaps = sim, dt_s, snaps
        self.net = sim.net
        self.info = sim.info
        parked = sim._parked
        self._p_ids = np.array([i for i, _, _ in parked], np.int64)
        self._p_xy = np.array([xy for _, xy, _ in parked]).reshape(-1, 2)
        self._p_yaw = np.array([y for _, _, y in parked])

    @property
    def duration_s(self) -> float:
        return (len(self.snaps) - 1) * self.dt_s

    def state_at(self, t_s: float) -> SceneState:
        """Vehicles and pedestrians at clip time t_s (linear interpolation along the routes)."""
        if not 0 <= t_s <= self.duration_s + 1e-9:
            raise ValueError(f"t_s must be within the clip [0, {self.duration_s}], got {t_s}")
        k = min(int(t_s / self.dt_s), len(self.snaps) - 2)
        f = (t_s - k * self.dt_s) / self.dt_s
        a, b = self.snaps[k], self.snaps[k + 1]
        common, ia, ib = np.intersect1d(a["ids"], b["ids"], return_indices=True)
        route = a["route"][ia]
        s = (1 - f) * a["s"][ia] + f * b["s"][ib]
        v = (1 - f) * a["v"][ia] + f * b["v"][ib]
        lengths = np.array([self.info[int(i)].length_m for i in common])
        xy = np.zeros((len(common), 2))
        yaw = np.zeros(len(common))
        for r in np.unique(route):
            m = route == r
            xy[m], yaw[m] = self.net.routes[r].pose(s[m], lengths[m])
        ids = np.concatenate([common, self._p_ids])
        xy = np.concatenate([xy, self._p_xy])
        yaw = np.concatenate([yaw, self._p_yaw])
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        speed = np.concatenate([v, np.zeros(len(self._p_ids))])
        infos = [self.info[int(i)] for i in ids]
        lwh = np.array([[i.length_m, i.width_m, i.height_m] for i in infos]).reshape(-1, 3)
        peds = self.sim._peds
        ped_s = (1 - f) * a["ped_s"] + f * b["ped_s"]
        paths = self.net.sidewalk_paths
        ped_xy = np.zeros((len(ped_s), 2))
        ped_yaw = np.zeros(len(ped_s))
        for j, (pi, sj) in enumerate(zip(peds["path"], ped_s, strict=True)):
            p0, p1 = paths[pi][0], paths[pi][-1]
            d = (p1 - p0) / max(np.linalg.norm(p1 - p0), 1e-9)
            ped_xy[j] = p0 + d * sj
            ped_yaw[j] = math.atan2(d[1], d[0]) + (0.0 if b["ped_dir"][j] > 0 else math.pi)
        return SceneState(
            t_s=t_s,
            ids=ids,
            xy=xy,
            yaw=yaw,
            lwh=lwh,
            speed=speed,
            velocity=np.stack([np.cos(yaw), np.sin(yaw)], 1) * speed[:, None],
            type_idx=np.array([VEHICLE_TYPES.index(i.type) for i in infos], np.int64),
            colors=np.array([i.color for i in infos], np.uint8).reshape(-1, 3),
            parked=np.array([i.parked for i in infos], bool),
            ped_xy=ped_xy,
            ped_yaw=ped_yaw,
            ped_color=peds["color"],
        )


def simulate_traffic(
    site: SiteSpec,
    net: RoadNetwork,
    seconds: float,
    seed: int,
    dt_s: float = 0.1,
    warmup_s: float = 90.0,
    max_vehicles: int = 100,
    demand_scale: float = 1.0,
    type_weights: dict[str, float] | None = None,
) -> TrafficHistory:
    """Run traffic for a warm-up, then record `seconds` of it every dt_s. `type_weights`: vehicle type -> factor
    on its share of the mix (more buses and trucks for training data, say)."""
    if not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    rng = np.random.default_rng([seed, 7])
    sim = TrafficSim(site, net, rng, max_vehicles, demand_scale, type_weights)
    t = -warmup_s
    while t < 0:
        sim.step(dt_s, t)
        t += dt_s
    n = int(math.ceil(seconds / dt_s)) + 1
    snaps = [sim.snapshot()]
    for k in range(1, n):
        sim.step(dt_s, k * dt_s)
        snaps.append(sim.snapshot())
    return TrafficHistory(sim, dt_s, snaps)
