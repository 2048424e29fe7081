"""Build a site's road network from its description: lane routes for traffic, and the paint
(asphalt, islands, markings, text) plus landmark feature points for the ground texture.

Right-hand traffic; roundabouts circulate counter-clockwise seen from above (site ENU frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.geometry import arc, arclength, concat, curvature, hermite, line, rect, resample
from sim.site import ApproachSpec, SiteSpec

ROUTE_STEP_M = 0.5
AXLE_SPAN = 0.35  # front / rear axle positions, as a fraction of the vehicle length from its centre
LATERAL_ACCEL_MPS2 = 2.2
COMFORT_DECEL_MPS2 = 2.0

# Route segment kinds and their right-of-way priority (higher goes first when two vehicles
# each stand in the other's path).
PRIORITY = {"approach": 0, "entry": 1, "box": 2, "ring": 2, "exit": 2, "depart": 3}
SEGMENT_KINDS = tuple(PRIORITY)


@dataclass
class Route:
    """A lane-level path through the junction, sampled every ROUTE_STEP_M metres.

    points (M, 2) site metres; s (M,) arc length; heading (M,) yaw (rad, ENU, from +x);
    speed_cap (M,) m/s: the curvature speed limit with a comfortable braking envelope.
    """

    points: np.ndarray
    origin: int
    dest: int
    lane_in: int
    lane_out: int
    turn: str
    segments: list[tuple[float, float, str]]
    stop_s: float
    signal_group: str | None = None
    merge_polar: float | None = None
    speed_limit_mps: float = 13.4
    s: np.ndarray = field(init=False)
    heading: np.ndarray = field(init=False)
    speed_cap: np.ndarray = field(init=False)
    seg_priority: np.ndarray = field(init=False)
    seg_kind: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.points = resample(self.points, ROUTE_STEP_M)
        self.s = arclength(self.points)
        d = np.gradient(self.points, axis=0)
        self.heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        kappa = np.convolve(curvature(self.points), np.ones(7) / 7, mode="same")
        cap = np.minimum(self.speed_limit_mps, np.sqrt(LATERAL_ACCEL_MPS2 / np.maximum(kappa, 1e-6)))
        # Braking envelope: a vehicle must be able to slow down in time for a curve ahead.
        env = cap.copy()
        ds = ROUTE_STEP_M
        for i in range(len(env) - 2, -1, -1):
            env[i] = min(env[i], math.sqrt(env[i + 1] ** 2 + 2 * COMFORT_DECEL_MPS2 * ds))
        self.speed_cap = env
        pri = np.zeros(len(self.s), dtype=np.int8)
        kinds = np.zeros(len(self.s), dtype=np.int8)
        for s0, s1, kind in self.segments:
            m = (self.s >= s0 - 1e-6) & (self.s <= s1 + 1e-6)
            pri[m] = PRIORITY[kind]
            kinds[m] = SEGMENT_KINDS.index(kind)
        self.seg_priority = pri
        self.seg_kind = kinds

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 2) and yaw (N,) at arc lengths s."""
        s = np.clip(np.asarray(s, float), 0.0, self.s[-1])
        x = np.interp(s, self.s, self.points[:, 0])
        y = np.interp(s, self.s, self.points[:, 1])
        return np.stack([x, y], axis=-1), np.interp(s, self.s, self.heading)

    def pose(self, s: np.ndarray, length_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body centre (N, 2) and yaw (N,) of vehicles whose centre is at arc length s: both axles
        ride on the path, so on a curve the body cuts the inside like a real vehicle instead of
        swinging its ends outside the lane."""
        return body_pose(
            *self.at(np.asarray(s) + AXLE_SPAN * np.asarray(length_m))[:1],
            *self.at(np.asarray(s) - AXLE_SPAN * np.asarray(length_m))[:1],
        )


def body_pose(front_axle: np.ndarray, rear_axle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (N, 2) and yaw (N,) of a body whose axle points (N, 2) are given."""
    d = front_axle - rear_axle
    return (front_axle + rear_axle) / 2, np.arctan2(d[:, 1], d[:, 0])


@dataclass
class Marking:
    """A painted line: polyline (N, 2), width, colour name, optional dash (on_m, off_m)."""

    points: np.ndarray
    width_m: float
    color: str = "white"
    dash: tuple[float, float] | None = None


@dataclass
class Paint:
    """Everything painted on the ground, in site metres."""

    asphalt_polys: list[np.ndarray] = field(default_factory=list)
    asphalt_strokes: list[tuple[np.ndarray, float]] = field(default_factory=list)
    islands: list[tuple[np.ndarray, str]] = field(default_factory=list)  # (polygon, material)
    markings: list[Marking] = field(default_factory=list)
    marking_polys: list[tuple[np.ndarray, str]] = field(default_factory=list)
    texts: list[tuple[str, np.ndarray, float, float]] = field(default_factory=list)  # text, xy, yaw, height
    features: list[tuple[float, float, str]] = field(default_factory=list)  # landmark candidates


@dataclass
class RoadNetwork:
    routes: list[Route]
    paint: Paint
    sidewalk_paths: list[np.ndarray]
    parking_slots: list[tuple[np.ndarray, float, bool]]  # (xy, yaw, occupied-draw-threshold)
    signal_plan: list[tuple[str, float]] | None = None
    yellow_s: float = 3.0
    all_red_s: float = 1.5
    junction_radius_m: float = 0.0

    def signal_state(self, group: str, t_s: float) -> str:
        """'green', 'yellow' or 'red' for a signal group at time t_s (seconds into the clip)."""
        if self.signal_plan is None:
            return "green"
        cycle = sum(g + self.yellow_s + self.all_red_s for _, g in self.signal_plan)
        t = t_s % cycle
        for name, green in self.signal_plan:
            span = green + self.yellow_s + self.all_red_s
            if t < span:
                if name != group:
                    return "red"
                return "green" if t < green else ("yellow" if t < green + self.yellow_s else "red")
            t -= span
        return "red"


def _leg_length(site: SiteSpec, leg: ApproachSpec) -> float:
    u = leg.unit_out
    return site.extent_m / max(abs(u[0]), abs(u[1])) - 1.0


def _lane_point(leg: ApproachSpec, d: float, lane: int, inbound: bool) -> np.ndarray:
    lateral = 0.5 * leg.median_m + (lane + 0.5) * leg.lane_width_m
    side = -leg.unit_right if inbound else leg.unit_right
    return leg.unit_out * d + side * lateral


def _turn_order(site: SiteSpec, a: int) -> list[int]:
    """Other legs ordered counter-clockwise from leg a (first = right turn)."""
    phi = [(90.0 - leg.bearing_deg) % 360.0 for leg in site.approaches]
    others = [b for b in range(len(site.approaches)) if b != a]
    return sorted(others, key=lambda b: (phi[b] - phi[a]) % 360.0)


def _lanes_for(turn: str, n_in: int, n_mid: int, n_out: int) -> list[tuple[int, int, int]]:
    """Allowed (lane_in, middle lane, lane_out) triples for a turn; lane 0 is the leftmost."""
    if turn == "right":
        return [(n_in - 1, n_mid - 1, n_out - 1)]
    if turn in ("left", "uturn"):
        return [(0, 0, 0)]
    out = []
    for k in range(n_in):
        j = round(k * (n_mid - 1) / max(n_in - 1, 1))
        out.append((k, j, round(j * (n_out - 1) / max(n_mid - 1, 1))))
    return out


def dashes(points: np.ndarray, on: float, off: float) -> list[np.ndarray]:
    s = arclength(points)
    out = []
    t = 0.0
    while t + on <= s[-1]:
        seg_s = np.linspace(t, t + on, max(2, int(on / 0.5) + 1))
        out.append(np.stack([np.interp(seg_s, s, points[:, 0]), np.interp(seg_s, s, points[:, 1])], 1))
        t += on + off
    return out


def _add_dashed(paint: Paint, pts: np.ndarray, width: float, on: float, off: float, color="white") -> None:
    paint.markings.append(Marking(pts, width, color, (on, off)))
    for d in dashes(pts, on, off):
        paint.features.append((float(d[0, 0]), float(d[0, 1]), "dash_end"))
        paint.features.append((float(d[-1, 0]), float(d[-1, 1]), "dash_end"))


def _crosswalk(paint: Paint, leg: ApproachSpec, d: float, half_width: float) -> None:
    u, r = leg.unit_out, leg.unit_right
    bar_w, bar_len, gap = 0.6, 3.0, 0.7
    n = int((2 * half_width) // (bar_w + gap))
    start = -0.5 * (n * (bar_w + gap) - gap)
    for i in range(n):
        c = u * d + r * (start + i * (bar_w + gap) + bar_w / 2)
        poly = rect(c, bar_len, bar_w, math.atan2(u[1], u[0]))
        paint.marking_polys.append((poly, "white"))
        for corner in poly:
            paint.features.append((float(corner[0]), float(corner[1]), "crosswalk_corner"))


def _parking(site: SiteSpec, paint: Paint) -> list[tuple[np.ndarray, float, bool]]:
    slots = []
    for row in site.parking:
        b = math.radians(row.bearing_deg)
        along = np.array([math.sin(b), math.cos(b)])
        across = np.array([along[1], -along[0]])
        perpendicular = row.spacing_m < 5.0
        depth = 5.5 if perpendicular else 2.6
        start = np.asarray(row.start_m, float)
        end = start + along * row.spacing_m * row.count
        lot = np.array([start - along, end, end + across * depth, start - along + across * depth])
        paint.asphalt_polys.append(lot)
        for k in range(row.count):
            c = start + along * (row.spacing_m * (k + 0.5)) + across * depth / 2
            yaw = math.atan2(across[1], across[0]) if perpendicular else math.atan2(along[1], along[0])
            slots.append((c, yaw, row.occupancy))
            if perpendicular:
                p0 = start + along * row.spacing_m * k
                paint.markings.append(Marking(np.array([p0, p0 + across * depth]), 0.12))
                paint.features.append((float(p0[0]), float(p0[1]), "stall_line_end"))
    return slots


def _sidewalks(site: SiteSpec, start_d: list[float]) -> list[np.ndarray]:
    paths = []
    for leg, d0 in zip(site.approaches, start_d, strict=True):
        length = _leg_length(site, leg)
        for side in (-1.0, 1.0):
            lat = side * (leg.half_width_m + 3.2)
            paths.append(line(leg.unit_out * d0 + leg.unit_right * lat, leg.unit_out * length + leg.unit_right * lat))
    return paths


def _route(pieces: list[tuple[np.ndarray, str]], ids: tuple[int, int, int, int, str], **kwargs) -> Route:
    """A Route from consecutive (polyline, segment kind) pieces; the stop line ends the first piece.
    `ids` = (origin leg, destination leg, inbound lane, outbound lane, turn)."""
    s = np.cumsum([0.0] + [arclength(p)[-1] for p, _ in pieces])
    segs = [(float(s[i]), float(s[i + 1]), kind) for i, (_, kind) in enumerate(pieces)]
    return Route(concat(*[p for p, _ in pieces]), *ids, segs, stop_s=float(s[1]), **kwargs)


def build_network(site: SiteSpec) -> RoadNetwork:
    if site.layout == "roundabout":
        return _build_roundabout(site)
    return _build_intersection(site)


def _leg_strip(site: SiteSpec, leg: ApproachSpec, d0: float) -> np.ndarray:
    u, r = leg.unit_out, leg.unit_right
    hw = 0.5 * leg.median_m + leg.lanes_out * leg.lane_width_m
    hw_in = 0.5 * leg.median_m + leg.lanes_in * leg.lane_width_m
    d1 = _leg_length(site, leg) + 3.0
    return np.array([u * d0 + r * hw, u * d1 + r * hw, u * d1 - r * hw_in, u * d0 - r * hw_in])


def _leg_lines(paint: Paint, site: SiteSpec, leg: ApproachSpec, d0: float, median_from: float) -> None:
    """Lane dividers, edge lines and the median of one leg, from distance d0 outwards."""
    u, r = leg.unit_out, leg.unit_right
    d1 = _leg_length(site, leg)
    w, m = leg.lane_width_m, 0.5 * leg.median_m
    for inbound, n in ((True, leg.lanes_in), (False, leg.lanes_out)):
        side = -r if inbound else r
        for k in range(1, n):
            a, b = u * d0 + side * (m + k * w), u * d1 + side * (m + k * w)
            _add_dashed(paint, line(a, b), 0.15, 3.0, 9.0)
        edge = m + n * w - 0.3
        paint.markings.append(Marking(line(u * d0 + side * edge, u * d1 + side * edge), 0.15))
        inner = m - 0.2 if m > 0.4 else 0.15
        paint.markings.append(Marking(line(u * median_from + side * inner, u * d1 + side * inner), 0.12, "yellow"))


def _build_roundabout(site: SiteSpec) -> RoadNetwork:
    rb = site.roundabout
    assert rb is not None
    paint = Paint()
    r_in, r_out = rb.inner_radius_m, rb.outer_radius_m
    ring_r = [r_in + (j + 0.5) * rb.lane_width_m for j in range(rb.lanes)]
    d_yield = r_out + 1.2
    legs = site.approaches

    # Ground paint: ring, legs, central island with truck apron.
    paint.asphalt_polys.append(arc((0, 0), r_out + 0.3, 0, 2 * math.pi))
    for leg in legs:
        paint.asphalt_polys.append(_leg_strip(site, leg, r_out - 4.0))
    paint.islands.append((arc((0, 0), r_in, 0, 2 * math.pi), "brick"))
    paint.islands.append((arc((0, 0), rb.island_radius_m, 0, 2 * math.pi), "grass"))
    for j in range(1, rb.lanes):
        _add_dashed(paint, arc((0, 0), r_in + j * rb.lane_width_m, 0, 2 * math.pi), 0.15, 2.0, 4.0)

    routes: list[Route] = []
    for a, leg in enumerate(legs):
        u, r = leg.unit_out, leg.unit_right
        length = _leg_length(site, leg)
        # Splitter island between the inbound and outbound lanes.
        if leg.splitter_length_m > 0 and leg.median_m > 0.8:
            hm = 0.5 * leg.median_m - 0.3
            d0, d1 = r_out + 1.5, r_out + 1.5 + leg.splitter_length_m
            poly = np.array(
                [
                    u * d0 + r * 0.3,
                    u * (d0 + 3) + r * hm,
                    u * d1 + r * hm * 0.6,
                    u * (d1 + 2),
                    u * d1 - r * hm * 0.6,
                    u * (d0 + 3) - r * hm,
                    u * d0 - r * 0.3,
                ]
            )
            paint.islands.append((poly, "brick"))
            paint.features.append(
                (float(poly[0][0] + poly[-1][0]) / 2, float(poly[0][1] + poly[-1][1]) / 2, "island_nose")
            )
            paint.features.append((float(poly[3][0]), float(poly[3][1]), "island_nose"))
        _leg_lines(paint, site, leg, d_yield + 0.6, r_out + 1.5 + leg.splitter_length_m)
        # Yield line (shark teeth) across the inbound lanes, and YIELD text.
        for k in range(leg.lanes_in):
            for t in np.arange(0.35, leg.lane_width_m - 0.3, 0.9):
                base = u * (d_yield + 0.2) - r * (0.5 * leg.median_m + k * leg.lane_width_m + t)
                tip = base + u * 0.9
                tri = np.array([base - r * 0.3, base + r * 0.3, tip])
                paint.marking_polys.append((tri, "white"))
                paint.features.append((float(tip[0]), float(tip[1]), "yield_tooth"))
            c = _lane_point(leg, d_yield + 7.0, k, inbound=True)
            paint.texts.append(("YIELD", c, math.atan2(-u[1], -u[0]), 1.8))
        if leg.crosswalk_m > 0:
            _crosswalk(
                paint, leg, leg.crosswalk_m, 0.5 * leg.median_m + max(leg.lanes_in, leg.lanes_out) * leg.lane_width_m
            )

        order = _turn_order(site, a)
        turns = {order[0]: "right", order[-1]: "left"}
        for b in order[1:-1]:
            turns[b] = "through"
        turns[a] = "uturn"
        for b, turn in turns.items():
            out_leg = legs[b]
            for k, j, kout in _lanes_for(turn, leg.lanes_in, rb.lanes, out_leg.lanes_out):
                start = _lane_point(leg, length, k, True)
                ay = _lane_point(leg, d_yield, k, True)
                approach = line(start, ay, ROUTE_STEP_M)
                phi_a = math.atan2(ay[1], ay[0])
                outer = j == rb.lanes - 1
                phi_b = phi_a + math.radians(rb.entry_angle_deg + (0 if outer else 14))
                rj = ring_r[j]
                pb = rj * np.array([math.cos(phi_b), math.sin(phi_b)])
                tb = np.array([-math.sin(phi_b), math.cos(phi_b)])
                entry = hermite(ay, -u, pb, tb, 0.45)
                pd = _lane_point(out_leg, d_yield, kout, False)
                phi_d = math.atan2(pd[1], pd[0])
                phi_c = phi_d - math.radians(rb.entry_angle_deg - 4 + (0 if outer else 12))
                sweep = (phi_c - phi_b) % (2 * math.pi)
                if turn == "right" and sweep > math.radians(300):
                    # Neighbouring legs: the entry and exit offsets overlap; meet in the middle.
                    mid = phi_b + (sweep - 2 * math.pi) / 2
                    phi_b, phi_c = mid - math.radians(4), mid + math.radians(4)
                    pb = rj * np.array([math.cos(phi_b), math.sin(phi_b)])
                    tb = np.array([-math.sin(phi_b), math.cos(phi_b)])
                    entry = hermite(ay, -u, pb, tb, 0.45)
                else:
                    phi_c = phi_b + max(sweep, math.radians(8))
                ring = arc((0, 0), rj, phi_b, phi_c)
                tc = np.array([-math.sin(phi_c), math.cos(phi_c)])
                exit_ = hermite(ring[-1], tc, pd, out_leg.unit_out, 0.45)
                depart = line(pd, _lane_point(out_leg, _leg_length(site, out_leg), kout, False))
                pieces = [(approach, "approach"), (entry, "entry"), (ring, "ring"), (exit_, "exit"), (depart, "depart")]
                routes.append(
                    _route(
                        pieces,
                        (a, b, k, kout, turn),
                        merge_polar=phi_b,
                        speed_limit_mps=min(leg.speed_limit_mps, out_leg.speed_limit_mps),
                    )
                )
                paint.asphalt_strokes.append((entry, leg.lane_width_m + 1.0))
                paint.asphalt_strokes.append((exit_, out_leg.lane_width_m + 1.0))

    sidewalks = _sidewalks(site, [r_out + 6.0] * len(legs))
    slots = _parking(site, paint)
    return RoadNetwork(routes, paint, sidewalks, slots, junction_radius_m=r_out)


def _build_intersection(site: SiteSpec) -> RoadNetwork:
    ix = site.intersection
    assert ix is not None
    paint = Paint()
    legs = site.approaches
    box_half = max(leg.half_width_m for leg in legs)
    d_stop = box_half + ix.stop_line_gap_m
    # Asphalt: legs from the centre out, plus the box with rounded corners.
    for leg in legs:
        paint.asphalt_polys.append(_leg_strip(site, leg, 0.0))
    rc = ix.corner_radius_m
    paint.asphalt_polys.append(rect((0, 0), 2 * (box_half + rc), 2 * (box_half + rc), 0.0))
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = np.array([sx * (box_half + rc), sy * (box_half + rc)])
            paint.islands.append((arc(c, rc, 0, 2 * math.pi, 0.3), "grass"))

    routes: list[Route] = []
    for a, leg in enumerate(legs):
        u, r = leg.unit_out, leg.unit_right
        length = _leg_length(site, leg)
        _leg_lines(paint, site, leg, d_stop + 0.5, d_stop + 0.5)
        bar = np.array(
            [
                u * (d_stop + 0.3) - r * 0.5 * leg.median_m,
                u * (d_stop + 0.3) - r * (0.5 * leg.median_m + leg.lanes_in * leg.lane_width_m),
            ]
        )
        paint.markings.append(Marking(bar, 0.5))
        for p in bar:
            paint.features.append((float(p[0]), float(p[1]), "stop_line_end"))
        _crosswalk(paint, leg, d_stop - 2.2, leg.half_width_m)
        axis = "NS" if abs(u[1]) > abs(u[0]) else "EW"
        for b, out_leg in enumerate(legs):
            if b == a:
                continue
            rel = (out_leg.bearing_deg - leg.bearing_deg) % 360.0
            turn = "through" if 135 <= rel <= 225 else ("left" if rel < 135 else "right")
            n_through = leg.lanes_in - (1 if leg.left_turn_lane else 0)
            if turn == "left":
                pairs = [(0, 0)]
            elif turn == "right":
                pairs = [(leg.lanes_in - 1, out_leg.lanes_out - 1)]
            else:
                first = 1 if leg.left_turn_lane else 0
                pairs = [
                    (
                        first + i,
                        min(i, out_leg.lanes_out - 1)
                        if n_through <= out_leg.lanes_out
                        else round(i * (out_leg.lanes_out - 1) / max(n_through - 1, 1)),
                    )
                    for i in range(n_through)
                ]
            for k, kout in pairs:
                start = _lane_point(leg, length, k, True)
                pa = _lane_point(leg, d_stop, k, True)
                pd = _lane_point(out_leg, d_stop, kout, False)
                box = hermite(pa, -u, pd, out_leg.unit_out, 0.33 if turn == "through" else 0.5)
                approach = line(start, pa)
                depart = line(pd, _lane_point(out_leg, _leg_length(site, out_leg), kout, False))
                group = f"{axis}_{'left' if turn == 'left' else 'through'}"
                pieces = [(approach, "approach"), (box, "box"), (depart, "depart")]
                routes.append(
                    _route(
                        pieces,
                        (a, b, k, kout, turn),
                        signal_group=group,
                        speed_limit_mps=min(leg.speed_limit_mps, out_leg.speed_limit_mps),
                    )
                )
                paint.asphalt_strokes.append((box, leg.lane_width_m + 0.5))
    plan = [
        ("NS_left", ix.left_green_s),
        ("NS_through", ix.green_s),
        ("EW_left", ix.left_green_s),
        ("EW_through", ix.green_s),
    ]
    sidewalks = _sidewalks(site, [box_half + rc + 1.0] * len(legs))
    slots = _parking(site, paint)
    return RoadNetwork(routes, paint, sidewalks, slots, plan, ix.yellow_s, ix.all_red_s, d_stop)
