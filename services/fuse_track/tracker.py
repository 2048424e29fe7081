"""SORT in site metres (no transport here): a Kalman filter per track, Hungarian assignment on
ground distance, tracks confirmed after `min_hits` consecutive hits and dropped once they have gone
more than `max_age_ticks` ticks without one (SORT's max_age; empty ticks count, so pass them in).
With `high_score` the assignment has ByteTrack's two rounds: objects scoring at least `high_score` first,
then the lower-scoring ones against the confirmed tracks still unmatched; only high-score objects start
tracks (on the validation recording, seed 77, with the shipped detector: tracks from 0.44 and extended down
to 0.35 gave MOTA 0.593, IDF1 0.712, 20 id switches against 0.588, 0.692, 32 for one round at 0.44), unless
`standing_hits` is set: then a low-score object may start a tentative track too, confirmed only after that
many consecutive hits (a parked or queued vehicle the detector is unsure of in every frame but sees at the
same place frame after frame; static clutter that does the same belongs in the site's exclusion zones, which
`roadside static` finds; off by default: on the real State/Ellsworth footage it cost more precision than it
gained recall, deploy/sites/state_ellsworth/README.md).

A vehicle the detector loses for longer than `max_age_ticks` (hidden behind a bus, or scored too low for a
second) comes back as a new track. With `relink_s`, a track confirmed within that many seconds of a confirmed
track's loss takes the lost track's id when the lost track's motion, carried on from where it was lost, brings
it within `relink_gate_m` of the new one (Hungarian on that distance): the vehicle keeps its identity across
the gap. The lost track is not reported in between (max_age still ends it), and an id is never held by two live
tracks. On the three validation recordings (seeds 77-79, docs/pipeline.md "Lost and found") 3 s and 3 m raised
the mean IDF1 0.856 -> 0.865 and cut the id switches 57 -> 49, MOTA and positions unchanged.

State (the paper's): x = [x, y, s, r, vx, vy, vs, vr]; x, y the bottom centre in metres (site ENU
frame), s = l * w the footprint area (m^2), r = l / w the aspect ratio, v* their rates per second.
Constant-velocity model with the TRUE dt between ticks: F = [[I4, dt I4], [0, I4]], and
piecewise-constant white acceleration noise per (value, rate) pair, Q = var * [[dt^4/4, dt^3/2],
[dt^3/2, dt^2]] (filterpy's `Q_discrete_white_noise(dim=2)`, written out here: importing filterpy at run time
pulls in scipy.stats and costs fuse_track about 23 MB of its 150 MB budget; the tests check both equal).

Vehicles accelerate sideways more than along their path: in a bend the centripetal acceleration is v^2 / radius,
3-4 m/s^2 for 7-8 m/s around a roundabout, against the 2 m/s^2 of noise the model allows either way. So a track
moving faster than `turn_speed_mps` gets `turn_accel_std_mps2` across its direction of motion in place of
`accel_std_mps2` (the same white-noise form, rotated onto its motion; `turn_noise`): without it the filter's
positions ran 0.10-0.26 m outside the bends (on the demo's recording, in the ROI, where the objects themselves
are within 0.03 m of the path either way; docs/pipeline.md, "Sideways in the bends").

Capture times: a measurement seen at t_i, off the tick time t by d = t_i - t, is compared with the
track at its own time, x(t_i) = x(t) + d v(t), and updates it through that same relation, H_i =
[I4, d I4] (exact for the constant-velocity model; the process noise over |d| <= tick/2 is
neglected). So the offset between a camera's capture time and the tick adds no error.

The filters of all tracks are stacked and run as one batch of numpy arrays: `kf_predict` and
`kf_update` are exactly filterpy's `KalmanFilter.predict` / `update` (Joseph form) for a batch
(the tests check this), at a few microseconds per track instead of ~90.

What a track reports of its error (`TrackState.xy_cov`, the Tracks message's): the filter weighs measurements
with its own noise (`position_std_m`, the same for every object), which is not what its measurements' errors are,
so its covariance P is not the error of its estimate. Alongside it each track carries E, the covariance of its
estimate's actual error under the gains the filter used ((I - K H) E (I - K H)' + K R_e K' at each update, the
Joseph form, which holds for any gain, and F E F' + Q at each prediction), where R_e is the error of the objects
themselves (`ObjectBatch.xy_cov`: the fusion's, from its cameras' error model). The detector's error for one vehicle
hardly changes from one frame to the next, and a filter cannot average away what persists: so only (1 - bias_share)
of an object's covariance enters E, and the last object's bias_share of it is added to the report unreduced. The
detector places a vehicle's bottom centre somewhere along its body, more so the longer it is (buses and trucks
above all): the report also adds (along_length_share x length)^2 along the track's heading. Then the squared
Mahalanobis distance of the true position is 2 on average when the report is right (chi-square, 2 dof);
The velocity's covariance is E's own (no persisting share: a constant offset does not move). docs/pipeline.md,
"How sure a track is", has the measurements.

Yaw is not in the filter: it is smoothed circularly, and once the track moves faster than
`yaw_from_motion_mps` the direction of motion resolves the detector's 180-degree ambiguity. A road vehicle heads
where it goes: from `yaw_from_motion_mps` up to `yaw_motion_full_mps` the heading is drawn linearly towards the
track's direction of motion, and from there on it is that direction (the filter's velocity, smoothed over many
measurements, is surer than one detection's heading: on the demo's recording its direction is 3.6-5.4 deg off for
tracks faster than 3 m/s (median), the smoothed detections' 8.2-8.5 deg). A vehicle that stops keeps the heading it
had and the detections take over again from there.

Front or back (`TrackState.yaw_confirmed`): a track's heading is confirmed once the track, moving, is
`yaw_confirm_travel_m` from where it was first seen; until then its sign is the detector's guess, which motion turns
round at once. A confirmed heading is turned round only after `yaw_reverse_s` of motion against it without a break:
a standing vehicle's detections jitter by a metre or two, and the filter's velocity with them, which used to
reverse a waiting car's heading for good. docs/pipeline.md, "Front or back", has the measurements.

How sure a heading is (`TrackState.yaw_std`, rad, 1 sigma of the heading's error on its axis: front and back are
`yaw_confirmed`'s). The detector's heading of a vehicle, fused over the cameras that see it, is off by `yaw_std_deg`:
a new track reports that. The detector misplaces a vehicle's heading much the same way from one frame to the next, so
smoothing its detections does not shrink that error: at each hit the track's sigma moves towards `yaw_std_deg` by the
yaw gain, as a standard deviation. Drawn towards the direction of motion by w (0 to 1), the sigma becomes
sqrt((1 - w)^2 sd^2 + w^2 var_motion), where var_motion, the direction's variance, is E's velocity variance across the
motion over the speed squared. docs/pipeline.md, "How sure a heading is", has the measurements.
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from services.fuse_track.fusion import NS_PER_S, ObjectBatch, check_columns, symmetric, wrap_angle

DIM_X, DIM_Z = 8, 4


@dataclass(frozen=True)
class TrackerConfig:
    """gate_m: largest ground distance between a track (at the measurement's capture time) and a
    measurement it takes; max_age_ticks: a track is dropped once it has gone more ticks than this without a
    measurement;
    min_hits: consecutive hits before a track is reported (a tentative track is dropped at its first
    miss); report_coasting_ticks: a confirmed track is still reported this many ticks after its last
    hit (its prediction bridges a missed detection); max_coast_s: dropped anyway after this long
    without a measurement (a gap in the stream); birth_separation_m: no new track this close to an
    existing one (a duplicate the fusion did not merge). Noise: position_std_m and size_std_m of a
    measurement (1 sigma; s and r noise follow from the measured size); accel_std_mps2 the
    acceleration noise of x and y, area_accel_std_m2ps2 of s, aspect_accel_std_ps2 of r; turn_accel_std_mps2 the
    acceleration noise across the direction of motion of a track moving faster than turn_speed_mps (module doc);
    init_speed_std_mps the velocity uncertainty of a new track. Yaw: yaw_gain the weight of a new
    yaw measurement, yaw_from_motion_mps the speed above which motion sets the heading's sign, yaw_motion_full_mps the
    speed from which the heading is the direction of motion (drawn towards it linearly from yaw_from_motion_mps; 0 =
    the detections' heading at any speed, motion only setting its sign); yaw_confirm_travel_m the distance from where
    a track was first seen that confirms its heading's sign, yaw_reverse_s how long a confirmed heading must be moved
    against before it is turned round; yaw_std_deg the detections' heading error, 1 sigma on its axis (module doc).
    high_score: objects scoring at least this are associated first and may start tracks; the others only
    extend confirmed tracks that the first round left unmatched (ByteTrack's second round: a vehicle the
    detector is unsure of in one frame keeps its track and id instead of breaking it); 0 = one round.
    standing_hits: with high_score, a low-score object left unmatched starts a tentative track that needs this
    many consecutive hits (by objects of any score) to be confirmed, instead of min_hits; 0 = low-score objects
    never start tracks. Objects marked extend-only (`ObjectBatch.extend_only`, the fusion's occlusion fallback)
    come last, whatever their score: they may extend a confirmed track that neither round matched, never start
    one. relink_s: a track confirmed within this many seconds of a confirmed track's loss takes its id when the
    lost track's constant-velocity motion since then brings it within relink_gate_m (module doc); 0 = off."""

    gate_m: float = 3.0
    max_age_ticks: int = 3
    min_hits: int = 3
    report_coasting_ticks: int = 1
    max_coast_s: float = 1.0
    # 2.25 m: the middle of the plateau 2.0-2.4 m (run 11, mean validation MOTA 0.772 over seeds 77-79, against 0.756
    # at 2.5 m on the edge of a cliff, 0.753 at 1.0-1.75 m and 0.696 at 3 m; docs/pipeline.md)
    birth_separation_m: float = 2.25
    position_std_m: float = 0.3
    size_std_m: float = 0.3
    accel_std_mps2: float = 2.0
    # 4 m/s^2 across the motion: the middle of a plateau over 3-6 (mean validation trajectory error 0.420 -> 0.416 m,
    # MOTA and IDF1 within 0.001; docs/pipeline.md, "Sideways in the bends"); accel_std_mps2 = the paper's model
    turn_accel_std_mps2: float = 4.0
    turn_speed_mps: float = 3.0
    area_accel_std_m2ps2: float = 0.5
    aspect_accel_std_ps2: float = 0.05
    init_speed_std_mps: float = 10.0
    yaw_gain: float = 0.4
    yaw_from_motion_mps: float = 1.5
    # 4 m/s: the middle of a plateau over 2.5-6 (mean validation yaw error of the tracks in the ROI 47.0 -> 44.5 deg,
    # the demo's recording 16.7 -> 14.3 deg; docs/pipeline.md, "Heading from motion")
    yaw_motion_full_mps: float = 4.0
    # 3 m and 1 s: the middle of plateaus over 2-5 m and 0.5-2 s (docs/pipeline.md, "Front or back")
    yaw_confirm_travel_m: float = 3.0
    yaw_reverse_s: float = 1.0
    # 14 deg: the best mean log-likelihood of the validation recordings' headings, on a plateau over 13-15
    # (docs/pipeline.md, "How sure a heading is")
    yaw_std_deg: float = 14.0
    high_score: float = 0.0
    standing_hits: int = 0
    # 3 s and 3 m: the middle of a plateau over 2-5 s and 3-4 m (mean validation IDF1 0.856 -> 0.865, id switches
    # 57 -> 49; docs/pipeline.md, "Lost and found")
    relink_s: float = 3.0
    relink_gate_m: float = 3.0
    # the reported covariance (module doc): 0.6 and 0.07 gave the best log-likelihood of the true positions on the
    # validation recording (seed 77; docs/pipeline.md, "How sure a track is")
    bias_share: float = 0.6
    along_length_share: float = 0.07

    def __post_init__(self) -> None:
        positive = ("gate_m", "max_coast_s", "position_std_m", "size_std_m", "accel_std_mps2", "area_accel_std_m2ps2",
                    "aspect_accel_std_ps2", "init_speed_std_mps", "turn_accel_std_mps2", "relink_gate_m", "yaw_std_deg")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        for name, low in (("max_age_ticks", 0), ("min_hits", 1), ("report_coasting_ticks", 0), ("standing_hits", 0)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.report_coasting_ticks > self.max_age_ticks:
            raise ValueError(f"report_coasting_ticks ({self.report_coasting_ticks}) must be <= max_age_ticks "
                             f"({self.max_age_ticks})")
        if not (math.isfinite(self.birth_separation_m) and self.birth_separation_m >= 0):
            raise ValueError(f"birth_separation_m must be >= 0, got {self.birth_separation_m!r}")
        if 0 < self.yaw_motion_full_mps <= self.yaw_from_motion_mps:
            raise ValueError(f"yaw_motion_full_mps ({self.yaw_motion_full_mps}) must be 0 or above yaw_from_motion_mps "
                             f"({self.yaw_from_motion_mps})")
        if not 0 < self.yaw_gain <= 1:
            raise ValueError(f"yaw_gain must be within (0, 1], got {self.yaw_gain!r}")
        for name in ("high_score", "bias_share", "along_length_share"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and 0 <= value <= 1):
                raise ValueError(f"{name} must be within [0, 1], got {value!r}")
        for name in ("yaw_from_motion_mps", "turn_speed_mps", "relink_s", "yaw_motion_full_mps", "yaw_confirm_travel_m",
                     "yaw_reverse_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class TrackState:
    """The reported tracks at event time `t_ns` (the tick's reference time), struct of arrays, N rows.

    tracker: the tracker instance's id (track ids are unique per instance); id (N,) int64;
    xy (N, 2) float64 m, site ENU frame; velocity (N, 2) float64 m/s (east, north); yaw (N,) float64
    rad ENU; size_lwh (N, 3) float64 m; vtype (N,) int64 the majority type over the track's history
    (score-weighted); score (N,) float64; age (N,) int64 ticks since the track started (0 at birth);
    hits (N,) int64 ticks with a measurement; cameras: per track, the cameras whose objects updated
    it this tick (empty while it coasts); xy_cov (N, 2, 2) float64 m^2 the covariance of the position's error
    (module doc); velocity_cov (N, 2, 2) float64 (m/s)^2 the velocity's (E's, as propagated); yaw_confirmed (N,)
    bool: whether the track's own travel has confirmed which way it heads (module doc; False: the detector's guess,
    front and back may be swapped); yaw_std (N,) float64 rad: 1 sigma of the heading's error on its axis (module doc).
    """

    t_ns: int
    tracker: str
    id: np.ndarray
    xy: np.ndarray
    velocity: np.ndarray
    yaw: np.ndarray
    size_lwh: np.ndarray
    vtype: np.ndarray
    score: np.ndarray
    age: np.ndarray
    hits: np.ndarray
    cameras: list[list[str]]
    xy_cov: np.ndarray
    velocity_cov: np.ndarray
    yaw_confirmed: np.ndarray
    yaw_std: np.ndarray

    def __post_init__(self) -> None:
        n = check_columns("TrackState", {
            "id": (self.id, ()), "xy": (self.xy, (2,)), "velocity": (self.velocity, (2,)), "yaw": (self.yaw, ()),
            "size_lwh": (self.size_lwh, (3,)), "vtype": (self.vtype, ()), "score": (self.score, ()),
            "age": (self.age, ()), "hits": (self.hits, ()), "xy_cov": (self.xy_cov, (2, 2)),
            "velocity_cov": (self.velocity_cov, (2, 2)), "yaw_confirmed": (self.yaw_confirmed, ()),
            "yaw_std": (self.yaw_std, ())})
        if len(self.cameras) != n:
            raise ValueError(f"TrackState.cameras has {len(self.cameras)} entries, expected {n}")

    def __len__(self) -> int:
        return len(self.id)


def transition(dt_s: float) -> np.ndarray:
    """F (8, 8) of the constant-velocity model over dt_s seconds."""
    f = np.eye(DIM_X)
    f[np.arange(4), np.arange(4) + 4] = dt_s
    return f


def white_noise_block(dt_s: float) -> np.ndarray:
    """(2, 2): piecewise white acceleration noise of unit variance for a (value, rate) pair over dt_s."""
    return np.array([[dt_s**4 / 4, dt_s**3 / 2], [dt_s**3 / 2, dt_s**2]])


def process_noise(dt_s: float, variances: tuple[float, float, float, float]) -> np.ndarray:
    """Q (8, 8): piecewise white acceleration noise of variance var_k for each (value k, rate k) pair."""
    q = np.zeros((DIM_X, DIM_X))
    block = white_noise_block(dt_s)
    for k, var in enumerate(variances):
        q[np.ix_([k, k + 4], [k, k + 4])] = var * block
    return q


def turn_noise(dt_s: float, velocity: np.ndarray, extra_var: float, min_speed: float) -> np.ndarray:
    """(T, 8, 8) to add to Q: for each track moving faster than min_speed (velocity (T, 2) m/s), extra_var (m^2/s^4)
    more acceleration variance across its direction of motion, in the white-noise form of `process_noise`."""
    out = np.zeros((len(velocity), DIM_X, DIM_X))
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    moving = np.flatnonzero(speed > min_speed)
    if extra_var == 0 or len(moving) == 0:
        return out
    across = np.stack([-velocity[moving, 1], velocity[moving, 0]], axis=1) / speed[moving, None]
    outer = extra_var * across[:, :, None] * across[:, None, :]  # (M, 2, 2)
    block = white_noise_block(dt_s)
    for a, i in enumerate((0, 4)):  # positions x, y at 0-1, their rates at 4-5
        for b, j in enumerate((0, 4)):
            out[moving, i:i + 2, j:j + 2] = block[a, b] * outer
    return out


def kf_predict(x: np.ndarray, p: np.ndarray, f: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched Kalman predict: x (T, 8), p (T, 8, 8), f (8, 8) and q (8, 8) or per track (T, 8, 8) -> (x, p) as
    filterpy's predict()."""
    return x @ f.T, f @ p @ f.T + q


def kf_gain(p: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Batched Kalman gain K = P H' (H P H' + R)^-1: p (M, 8, 8), h (M, 4, 8), r (M, 4, 4) -> (M, 8, 4)."""
    pht = p @ h.transpose(0, 2, 1)
    s = h @ pht + r
    return np.linalg.solve(s, pht.transpose(0, 2, 1)).transpose(0, 2, 1)  # P H' S^-1 (S symmetric)


def joseph(p: np.ndarray, k: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(I - K H) P (I - K H)' + K R K': the covariance after an update with gain k, whatever gain that is, of an
    estimate whose error had covariance p, by measurements whose error has covariance r."""
    ikh = np.eye(DIM_X) - k @ h
    return ikh @ p @ ikh.transpose(0, 2, 1) + k @ r @ k.transpose(0, 2, 1)


def kf_update(
    x: np.ndarray, p: np.ndarray, z: np.ndarray, h: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched Kalman update, Joseph form as filterpy's update(z, R, H): x (M, 8), p (M, 8, 8),
    z (M, 4), h (M, 4, 8), r (M, 4, 4) -> (x, p, the gain K (M, 8, 4))."""
    k = kf_gain(p, h, r)
    x = x + np.einsum("mij,mj->mi", k, z - np.einsum("mij,mj->mi", h, x))
    return x, joseph(p, k, h, r), k


class Tracker:
    """SORT on fused ground objects. `update(objects, t_ns)` once per tick, with t_ns not decreasing.

    Track ids count from 1 in each instance; `id` names the instance (given, or `tracker-<random hex>`).
    """

    def __init__(self, config: TrackerConfig | None = None, tracker_id: str | None = None) -> None:
        self.config = config or TrackerConfig()
        self.id = tracker_id if tracker_id is not None else f"tracker-{uuid.uuid4().hex[:12]}"
        if not isinstance(self.id, str) or not self.id:
            raise ValueError(f"tracker_id must be a non-empty string, got {tracker_id!r}")
        c = self.config
        self._q_var = (c.accel_std_mps2**2, c.accel_std_mps2**2, c.area_accel_std_m2ps2**2, c.aspect_accel_std_ps2**2)
        self._next_id = 1
        self._t_ns: int | None = None
        self._fq: tuple[float, np.ndarray, np.ndarray] = (math.nan, np.eye(DIM_X), np.zeros((DIM_X, DIM_X)))  # dt, F, Q
        # Tracks, struct of arrays (T rows).
        self._x = np.zeros((0, DIM_X))
        self._p = np.zeros((0, DIM_X, DIM_X))
        self._e = np.zeros((0, DIM_X, DIM_X))  # the covariance of each state's error, to report (module doc)
        self._b = np.zeros((0, 2, 2))  # and of the part of its position error that persists from frame to frame
        self._ids = np.zeros(0, np.int64)
        self._age = np.zeros(0, np.int64)
        self._hits = np.zeros(0, np.int64)
        self._streak = np.zeros(0, np.int64)
        self._since_hit = np.zeros(0, np.int64)
        self._last_hit_ns = np.zeros(0, np.int64)
        self._confirmed = np.zeros(0, bool)
        self._need = np.zeros(0, np.int64)  # consecutive hits a tentative track needs: min_hits, or standing_hits
        self._yaw = np.zeros(0)
        self._confirmed_yaw = np.zeros(0, bool)  # whether the track's travel has confirmed its heading's sign
        self._origin = np.zeros((0, 2))  # where it was first seen (m)
        self._against = np.zeros(0)  # how long (s) it has moved against its confirmed heading without a break
        self._yaw_std = np.zeros(0)  # the heading's error on its axis, 1 sigma (rad; module doc)
        self._height = np.zeros(0)
        self._score = np.zeros(0)
        self._votes = np.zeros((0, 1))  # score-weighted type votes, (T, types)
        self._cameras: list[list[str]] = []
        self._tick = 0  # updates so far: a track's age is the ticks since the one it was born in
        # Confirmed tracks dropped in the last relink_s, struct of arrays: id, state x at the tick t (ns) they were
        # dropped in, the tick they were born in, their hits and heading
        self._lost = {"id": np.zeros(0, np.int64), "x": np.zeros((0, DIM_X)), "t": np.zeros(0, np.int64),
                      "born": np.zeros(0, np.int64), "hits": np.zeros(0, np.int64), "yaw": np.zeros(0),
                      "confirmed_yaw": np.zeros(0, bool)}

    def __len__(self) -> int:
        """Live tracks, tentative ones included."""
        return len(self._ids)

    def velocity_hints(self, objects: ObjectBatch) -> np.ndarray:
        """(N, 2) m/s per object: the velocity of the nearest track (with a velocity estimate, i.e.
        two hits or more) within gate_m of it at its capture time, zeros where none. For `Fusion.fuse`."""
        hints = np.zeros((len(objects), 2))
        known = np.flatnonzero(self._hits >= 2)
        if len(objects) == 0 or len(known) == 0:
            return hints
        d = self._distances(objects, np.arange(len(objects)), known)
        j = np.argmin(d, axis=1)
        near = d[np.arange(len(objects)), j] <= self.config.gate_m
        hints[near] = self._x[known[j[near]], 4:6]
        return hints

    def update(self, objects: ObjectBatch, t_ns: int) -> TrackState:
        """Fused objects of one tick (each with its own capture time `objects.t_ns`) -> the reported
        tracks at the tick's reference time `t_ns` (ns, not before the previous call's)."""
        if not isinstance(objects, ObjectBatch):
            raise ValueError(f"objects must be an ObjectBatch, got {type(objects).__name__}")
        t_ns = int(t_ns)
        if self._t_ns is not None and t_ns < self._t_ns:
            raise ValueError(f"t_ns must not go back in time: got {t_ns}, the previous tick was {self._t_ns}")
        if len(objects):
            offset_s = float(np.max(np.abs(objects.t_ns - t_ns))) / NS_PER_S
            if offset_s > self.config.max_coast_s:
                raise ValueError(f"objects.t_ns must lie within max_coast_s ({self.config.max_coast_s} s) of t_ns "
                                 f"{t_ns}, one is {offset_s:.3f} s away")
        dt_s = 0.0 if self._t_ns is None else (t_ns - self._t_ns) / NS_PER_S
        self._t_ns = t_ns
        self._tick += 1
        if len(self._ids):
            if self._fq[0] != dt_s:
                self._fq = (dt_s, transition(dt_s), process_noise(dt_s, self._q_var))
            c = self.config
            q = self._fq[2]
            if c.turn_accel_std_mps2 != c.accel_std_mps2:
                q = q + turn_noise(dt_s, self._x[:, 4:6], c.turn_accel_std_mps2**2 - c.accel_std_mps2**2,
                                   c.turn_speed_mps)
            self._x, self._p = kf_predict(self._x, self._p, self._fq[1], q)
            self._e = self._fq[1] @ self._e @ self._fq[1].T + q
            # a shrinking size's rate carries area and aspect below zero on a tick without a measurement: keep them
            # positive here too, not only after an update (their square roots are the reported length and width)
            self._x[:, 2:4] = np.maximum(self._x[:, 2:4], 1e-3)
            self._age += 1
            self._since_hit += 1
        self._cameras = [[] for _ in range(len(self._ids))]
        extend = objects.extend_mask()  # the fusion's occlusion fallback: may extend a confirmed track, never start one
        high = (objects.score >= self.config.high_score) & ~extend
        rows, tracks = self._associate(objects, np.flatnonzero(high), np.arange(len(self._ids)))
        self._need[tracks] = np.minimum(self._need[tracks], self.config.min_hits)  # a high-score hit: as if born high
        if not high.all():  # second round: the low-score objects may only extend tracks the first left unmatched,
            # third: the extend-only objects confirmed tracks that neither round matched
            free = np.ones(len(self._ids), bool)
            free[tracks] = False
            # (with standing_hits, tentative tracks too: those low-score objects started need their hits)
            open_ = self._confirmed | (self.config.standing_hits > 0)
            rows2, tracks2 = self._associate(objects, np.flatnonzero(~high & ~extend), np.flatnonzero(free & open_))
            free[tracks2] = False
            rows3, tracks3 = self._associate(objects, np.flatnonzero(extend), np.flatnonzero(free & self._confirmed))
            rows, tracks = np.concatenate([rows, rows2, rows3]), np.concatenate([tracks, tracks2, tracks3])
        self._correct(objects, rows, tracks)
        missed = np.ones(len(self._ids), bool)
        missed[tracks] = False
        self._streak[missed] = 0
        self._drop(t_ns)
        unmatched = (np.ones(len(objects), bool) if self.config.standing_hits else high.copy()) & ~extend
        unmatched[rows] = False
        born_low = unmatched & ~high
        self._birth(objects, np.flatnonzero(unmatched & high), self.config.min_hits)
        self._birth(objects, np.flatnonzero(born_low), max(self.config.standing_hits, self.config.min_hits))
        newly = ~self._confirmed & (self._streak >= self._need)
        self._confirmed |= newly
        if self.config.relink_s > 0:
            self._relink(np.flatnonzero(newly), t_ns)
        return self._report(t_ns)

    # ---- steps ----------------------------------------------------------------------------------
    def _distances(self, objects: ObjectBatch, rows: np.ndarray, tracks: np.ndarray) -> np.ndarray:
        """(len(rows), len(tracks)) ground distance from each object to each track at the object's capture time."""
        d_s = (objects.t_ns[rows] - self._t_ns) / NS_PER_S
        x = self._x[tracks]
        at = x[None, :, :2] + x[None, :, 4:6] * d_s[:, None, None]
        dx, dy = objects.xy[rows, None, 0] - at[:, :, 0], objects.xy[rows, None, 1] - at[:, :, 1]
        return np.sqrt(dx * dx + dy * dy)  # what np.linalg.norm computes, without its overhead

    def _associate(self, objects: ObjectBatch, rows: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hungarian assignment of the objects at `rows` to the tracks at `tracks` on ground distance with the
        gate -> (object rows, track rows), both indices into the whole batch and track list."""
        empty = np.zeros(0, np.int64)
        if len(rows) == 0 or len(tracks) == 0:
            return empty, empty
        d = self._distances(objects, rows, tracks)
        cost = np.where(d <= self.config.gate_m, d, 1e6)
        r, t = linear_sum_assignment(cost)
        ok = cost[r, t] <= self.config.gate_m
        return rows[r[ok]], tracks[t[ok]]

    def _measurement(self, objects: ObjectBatch, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (M, 4) = [x, y, s, r] and R (M, 4, 4) of the objects at `rows`."""
        lwh = objects.size_lwh[rows]
        length, width = lwh[:, 0], lwh[:, 1]
        sd_p, sd = self.config.position_std_m, self.config.size_std_m
        z = np.column_stack([objects.xy[rows], length * width, length / width])
        r = np.zeros((len(rows), DIM_Z, DIM_Z))
        r[:, 0, 0] = r[:, 1, 1] = sd_p**2
        r[:, 2, 2] = sd**2 * (length**2 + width**2)  # var(l w) to first order
        r[:, 3, 3] = sd**2 * (1 + (length / width) ** 2) / width**2  # var(l / w)
        return z, r

    def _error_r(self, objects: ObjectBatch, rows: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The covariance of the measurements' error, split into the part that changes from frame to frame and the
        part that persists (bias_share of the position's): the filter's R with the objects' own position covariance
        (`ObjectBatch.xy_cov`) where they have one."""
        cov = r[:, :2, :2] if objects.xy_cov is None else objects.xy_cov[rows]
        r = r.copy()
        r[:, :2, :2] = (1 - self.config.bias_share) * cov
        return r, self.config.bias_share * cov

    def _correct(self, objects: ObjectBatch, rows: np.ndarray, tracks: np.ndarray) -> None:
        if len(rows) == 0:
            return
        z, r = self._measurement(objects, rows)
        h = np.zeros((len(rows), DIM_Z, DIM_X))
        h[:, np.arange(4), np.arange(4)] = 1.0
        h[:, np.arange(4), np.arange(4) + 4] = ((objects.t_ns[rows] - self._t_ns) / NS_PER_S)[:, None]
        self._x[tracks], self._p[tracks], k = kf_update(self._x[tracks], self._p[tracks], z, h, r)
        r_e, self._b[tracks] = self._error_r(objects, rows, r)
        self._e[tracks] = joseph(self._e[tracks], k, h, r_e)
        self._x[tracks, 2:4] = np.maximum(self._x[tracks, 2:4], 1e-3)  # area and aspect stay positive
        self._smooth_yaw(tracks, objects.yaw[rows], (objects.t_ns[rows] - self._last_hit_ns[tracks]) / NS_PER_S)
        self._hits[tracks] += 1
        self._streak[tracks] += 1
        self._since_hit[tracks] = 0
        self._last_hit_ns[tracks] = objects.t_ns[rows]
        self._score[tracks] = 0.5 * self._score[tracks] + 0.5 * objects.score[rows]
        self._height[tracks] = 0.7 * self._height[tracks] + 0.3 * objects.size_lwh[rows, 2]
        self._vote(tracks, objects.vtype[rows], objects.score[rows])
        for i, j in zip(rows.tolist(), tracks.tolist(), strict=True):
            self._cameras[j] = objects.sources_of(i)

    def _smooth_yaw(self, tracks: np.ndarray, measured: np.ndarray, dt_s: np.ndarray) -> None:
        """Circular smoothing of the heading (rad) of the tracks at `tracks` with their measured ones, `dt_s` since
        their last hit: the sign from motion once a track moves (at once, or after yaw_reverse_s against a heading
        its travel confirmed), the heading drawn towards the direction of motion (module doc)."""
        c = self.config
        full, low = c.yaw_motion_full_mps, c.yaw_from_motion_mps
        yaw, velocity, sure = self._yaw[tracks], self._x[tracks, 4:6], self._confirmed_yaw[tracks]
        heading = np.arctan2(velocity[:, 1], velocity[:, 0])
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        moving = (speed > low) & (self._hits[tracks] >= 2)
        against = moving & (np.abs(wrap_angle(yaw - heading)) > np.pi / 2)
        held = np.where(against, self._against[tracks] + dt_s, 0.0)
        flip = against & (~sure | (held >= c.yaw_reverse_s))
        yaw = np.where(flip, yaw + np.pi, yaw)
        moving &= ~against | flip  # not drawn towards a motion that has yet to prove itself
        d = wrap_angle(measured - yaw)
        d = wrap_angle(np.where(np.abs(d) > np.pi / 2, d + np.pi, d))  # the detector's heading may be reversed
        yaw = wrap_angle(yaw + c.yaw_gain * d)
        # a detector misplaces a vehicle's heading much the same way from frame to frame: the smoothed heading's
        # error moves towards the detections' own, as a standard deviation (errors that persist add up linearly)
        sd = (1 - c.yaw_gain) * self._yaw_std[tracks] + c.yaw_gain * math.radians(c.yaw_std_deg)
        if full > 0:  # towards the direction of motion, all the way from `full` on
            w = np.where(moving, np.clip((speed - low) / (full - low), 0.0, 1.0), 0.0)
            yaw = wrap_angle(yaw + w * wrap_angle(heading - yaw))
            # the direction of the velocity is as sure as the velocity across it (E's), over the speed
            across = np.column_stack([-np.sin(heading), np.cos(heading)])
            var_across = np.einsum("ti,tij,tj->t", across, self._e[tracks, 4:6, 4:6], across)
            var_motion = var_across / np.maximum(speed, low) ** 2
            sd = np.sqrt((1 - w) ** 2 * sd**2 + w**2 * var_motion)
        self._yaw_std[tracks] = sd
        travelled = np.hypot(*(self._x[tracks, :2] - self._origin[tracks]).T)
        self._yaw[tracks] = yaw
        self._against[tracks] = np.where(flip, 0.0, held)
        self._confirmed_yaw[tracks] = sure | (moving & (travelled >= c.yaw_confirm_travel_m))

    def _vote(self, tracks: np.ndarray, vtype: np.ndarray, score: np.ndarray) -> None:
        need = int(vtype.max()) + 1
        if need > self._votes.shape[1]:
            self._votes = np.pad(self._votes, ((0, 0), (0, need - self._votes.shape[1])))
        np.add.at(self._votes, (tracks, vtype), np.maximum(score, 1e-3))

    def _drop(self, t_ns: int) -> None:
        c = self.config
        stale = (self._since_hit > c.max_age_ticks) | ((self._since_hit > 0) & ~self._confirmed)
        stale |= (t_ns - self._last_hit_ns) / NS_PER_S > c.max_coast_s
        if stale.any():
            if c.relink_s > 0:
                lost = stale & self._confirmed
                add = {"id": self._ids[lost], "x": self._x[lost], "t": np.full(int(lost.sum()), t_ns, np.int64),
                       "born": self._tick - self._age[lost], "hits": self._hits[lost], "yaw": self._yaw[lost],
                       "confirmed_yaw": self._confirmed_yaw[lost]}
                self._lost = {k: np.concatenate([v, add[k]]) for k, v in self._lost.items()}
            self._keep(~stale)

    def _relink(self, tracks: np.ndarray, t_ns: int) -> None:
        """Tracks confirmed this tick take the id of a confirmed track lost within relink_s whose motion,
        carried on from where it was lost, brings it within relink_gate_m of them (Hungarian on that distance), and
        with it the lost track's age (ticks since it was born), hits (added) and heading's sign (and whether travel
        confirmed it)."""
        c = self.config
        lost = self._lost
        recent = (t_ns - lost["t"]) / NS_PER_S <= c.relink_s
        lost = {k: v[recent] for k, v in lost.items()}
        self._lost = lost
        if len(tracks) == 0 or len(lost["id"]) == 0:
            return
        dt = (t_ns - lost["t"]) / NS_PER_S
        at = lost["x"][:, :2] + lost["x"][:, 4:6] * dt[:, None]
        d = np.linalg.norm(self._x[tracks, None, :2] - at[None], axis=2)
        cost = np.where(d <= c.relink_gate_m, d, 1e6)
        r, k = linear_sum_assignment(cost)
        ok = cost[r, k] <= c.relink_gate_m
        new, old = tracks[r[ok]], k[ok]
        self._ids[new] = lost["id"][old]
        self._age[new] = self._tick - lost["born"][old]
        self._hits[new] += lost["hits"][old]
        # the lost track's heading's sign, unless only the new track's travel confirmed its own
        reversed_ = np.abs(wrap_angle(self._yaw[new] - lost["yaw"][old])) > np.pi / 2
        reversed_ &= lost["confirmed_yaw"][old] | ~self._confirmed_yaw[new]
        self._confirmed_yaw[new] |= lost["confirmed_yaw"][old]
        self._yaw[new] = np.where(reversed_, wrap_angle(self._yaw[new] + np.pi), self._yaw[new])
        keep = np.ones(len(lost["id"]), bool)
        keep[old] = False
        self._lost = {k_: v[keep] for k_, v in lost.items()}

    def _keep(self, keep: np.ndarray) -> None:
        for name in ("_x", "_p", "_e", "_b", "_ids", "_age", "_hits", "_streak", "_since_hit", "_last_hit_ns",
                     "_confirmed", "_need", "_yaw", "_confirmed_yaw", "_origin", "_against", "_yaw_std", "_height",
                     "_score", "_votes"):
            setattr(self, name, getattr(self, name)[keep])
        self._cameras = [c for c, k in zip(self._cameras, keep, strict=True) if k]

    def _birth(self, objects: ObjectBatch, rows: np.ndarray, need: int) -> None:
        """New tentative tracks for the unmatched objects, except duplicates of an existing track; each
        needs `need` consecutive hits to be confirmed."""
        if len(rows) == 0:
            return
        sep = self.config.birth_separation_m
        rows = rows[np.argsort(-objects.score[rows], kind="stable")]  # the surest first
        xy = objects.xy[rows]
        if len(self._ids):  # none within sep of a track: all tracks at once
            dx, dy = xy[:, None, 0] - self._x[None, :, 0], xy[:, None, 1] - self._x[None, :, 1]
            keep = np.sqrt(np.min(dx * dx + dy * dy, axis=1)) >= sep
            rows, xy = rows[keep], xy[keep]
        born, placed = [], []  # nor within sep of one born before it in this tick
        for i, (x, y) in zip(rows.tolist(), xy.tolist(), strict=True):
            if all(math.sqrt((x - px) * (x - px) + (y - py) * (y - py)) >= sep for px, py in placed):
                born.append(i)
                placed.append((x, y))
        if not born:
            return
        born = np.array(born)
        n = len(born)
        c = self.config
        z, r = self._measurement(objects, born)
        x = np.zeros((n, DIM_X))
        x[:, :4] = z
        p = np.zeros((n, DIM_X, DIM_X))
        p[:, :4, :4] = r
        p[:, 4, 4] = p[:, 5, 5] = c.init_speed_std_mps**2
        p[:, 6, 6] = c.area_accel_std_m2ps2**2
        p[:, 7, 7] = c.aspect_accel_std_ps2**2
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        votes = np.zeros((n, self._votes.shape[1]))
        self._x = np.concatenate([self._x, x])
        self._p = np.concatenate([self._p, p])
        e = p.copy()
        e[:, :4, :4], b = self._error_r(objects, born, r)
        self._e = np.concatenate([self._e, e])
        self._b = np.concatenate([self._b, b])
        self._ids = np.concatenate([self._ids, ids])
        self._age = np.concatenate([self._age, np.zeros(n, np.int64)])
        self._hits = np.concatenate([self._hits, np.ones(n, np.int64)])
        self._streak = np.concatenate([self._streak, np.ones(n, np.int64)])
        self._since_hit = np.concatenate([self._since_hit, np.zeros(n, np.int64)])
        self._last_hit_ns = np.concatenate([self._last_hit_ns, objects.t_ns[born]])
        self._confirmed = np.concatenate([self._confirmed, np.zeros(n, bool)])
        self._need = np.concatenate([self._need, np.full(n, need, np.int64)])
        self._yaw = np.concatenate([self._yaw, objects.yaw[born]])
        self._confirmed_yaw = np.concatenate([self._confirmed_yaw, np.zeros(n, bool)])
        self._origin = np.concatenate([self._origin, z[:, :2]])
        self._against = np.concatenate([self._against, np.zeros(n)])
        self._yaw_std = np.concatenate([self._yaw_std, np.full(n, math.radians(c.yaw_std_deg))])
        self._height = np.concatenate([self._height, objects.size_lwh[born, 2]])
        self._score = np.concatenate([self._score, objects.score[born]])
        self._votes = np.concatenate([self._votes, votes])
        self._vote(len(self._ids) - n + np.arange(n), objects.vtype[born], objects.score[born])
        self._cameras.extend(objects.sources_of(i) for i in born.tolist())

    def _report(self, t_ns: int) -> TrackState:
        show = np.flatnonzero(self._confirmed & (self._since_hit <= self.config.report_coasting_ticks))
        x = self._x[show]
        s, r = x[:, 2], x[:, 3]
        size = np.column_stack([np.sqrt(s * r), np.sqrt(s / r), self._height[show]])
        along = np.column_stack([np.cos(self._yaw[show]), np.sin(self._yaw[show])])
        cov = self._e[show, :2, :2] + self._b[show] + (
            (self.config.along_length_share * size[:, 0]) ** 2)[:, None, None] * along[:, :, None] * along[:, None, :]
        return TrackState(
            t_ns=t_ns, tracker=self.id, id=self._ids[show].copy(), xy=x[:, :2].copy(), velocity=x[:, 4:6].copy(),
            yaw=self._yaw[show].copy(), size_lwh=size,
            vtype=np.argmax(self._votes[show], axis=1).astype(np.int64) if len(show) else np.zeros(0, np.int64),
            score=self._score[show].copy(), age=self._age[show].copy(), hits=self._hits[show].copy(),
            cameras=[list(self._cameras[j]) for j in show], xy_cov=symmetric(cov),
            velocity_cov=symmetric(self._e[show, 4:6, 4:6]), yaw_confirmed=self._confirmed_yaw[show].copy(),
            yaw_std=self._yaw_std[show].copy())
