"""GeoFrame: WGS84 lat/lon/alt <-> site ENU metres."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geo import GeoFrame, in_footprints

LAT0, LON0, ALT0 = 42.2294, -83.739, 265.0


@pytest.fixture
def frame() -> GeoFrame:
    return GeoFrame(LAT0, LON0, ALT0)


def _random_geodetic(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random points within ~1 km of the origin (horizontally), +-50 m in height."""
    r = 1000.0 * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * math.pi, n)
    dlat = r * np.cos(a) / 111_000.0
    dlon = r * np.sin(a) / (111_000.0 * math.cos(math.radians(LAT0)))
    alt = ALT0 + rng.uniform(-50, 50, n)
    return LAT0 + dlat, LON0 + dlon, alt


def test_round_trip_geodetic_enu_geodetic_sub_millimetre(frame: GeoFrame) -> None:
    rng = np.random.default_rng(0)
    lat, lon, alt = _random_geodetic(rng, 500)
    enu = frame.to_enu(lat, lon, alt)
    assert enu.shape == (500, 3)
    assert np.all(np.hypot(enu[:, 0], enu[:, 1]) < 1005.0)
    back = frame.to_geodetic(enu)
    assert back.shape == (500, 3)
    # Convert the angular error to metres (1 deg lat ~ 111 km).
    err_n = (back[:, 0] - lat) * 111_000.0
    err_e = (back[:, 1] - lon) * 111_000.0 * math.cos(math.radians(LAT0))
    err_u = back[:, 2] - alt
    assert np.max(np.abs(err_n)) < 1e-3
    assert np.max(np.abs(err_e)) < 1e-3
    assert np.max(np.abs(err_u)) < 1e-3


def test_round_trip_enu_geodetic_enu_sub_millimetre(frame: GeoFrame) -> None:
    rng = np.random.default_rng(1)
    enu = np.column_stack([rng.uniform(-700, 700, (300, 2)), rng.uniform(-30, 30, 300)])
    geo = frame.to_geodetic(enu)
    back = frame.to_enu(geo[:, 0], geo[:, 1], geo[:, 2])
    assert np.max(np.linalg.norm(back - enu, axis=1)) < 1e-3


def test_origin_maps_to_zero(frame: GeoFrame) -> None:
    enu = frame.to_enu(np.array([LAT0]), np.array([LON0]), ALT0)
    np.testing.assert_allclose(enu, 0.0, atol=1e-6)


def test_known_value_north(frame: GeoFrame) -> None:
    enu = frame.to_enu(np.array([LAT0 + 0.001]), np.array([LON0]), ALT0)[0]
    assert abs(enu[1] - 111.0) < 0.5
    assert abs(enu[0]) < 1e-6
    # The ellipsoid curves away from the tangent plane: ~1 mm drop at 111 m.
    assert abs(enu[2]) < 0.01


def test_known_value_east(frame: GeoFrame) -> None:
    enu = frame.to_enu(np.array([LAT0]), np.array([LON0 + 0.001]), ALT0)[0]
    # One milli-degree of longitude ~ 111.3 km * cos(lat) / 1000 ~ 82.5 m at 42.23 N.
    expected = 111.32 * math.cos(math.radians(LAT0))
    assert abs(enu[0] - expected) < 0.5
    assert enu[0] > 0  # east is +x
    assert abs(enu[1]) < 0.01


def test_to_enu_scalar_altitude_broadcast(frame: GeoFrame) -> None:
    lat = np.array([LAT0, LAT0 + 0.002, LAT0 - 0.001])
    lon = np.array([LON0, LON0 - 0.001, LON0 + 0.003])
    a = frame.to_enu(lat, lon, ALT0 + 5.0)
    b = frame.to_enu(lat, lon, np.full(3, ALT0 + 5.0))
    np.testing.assert_array_equal(a, b)
    assert a.dtype == np.float64


def test_to_geodetic_accepts_n_by_2(frame: GeoFrame) -> None:
    xy = np.array([[10.0, 20.0], [-300.0, 150.0], [0.0, 0.0]])
    out2 = frame.to_geodetic(xy)
    out3 = frame.to_geodetic(np.column_stack([xy, np.zeros(3)]))
    assert out2.shape == (3, 3)
    np.testing.assert_allclose(out2, out3, rtol=0, atol=1e-12)
    # z = 0 is the origin's height.
    assert abs(out2[2, 2] - ALT0) < 1e-6
    assert abs(out2[2, 0] - LAT0) < 1e-12
    assert abs(out2[2, 1] - LON0) < 1e-12


def test_to_geodetic_rejects_wrong_columns(frame: GeoFrame) -> None:
    with pytest.raises(ValueError, match="enu_m"):
        frame.to_geodetic(np.zeros((4, 4)))


@pytest.mark.parametrize(
    ("lat", "lon", "alt", "param"),
    [
        (95.0, LON0, 0.0, "lat0_deg"),
        (-90.5, LON0, 0.0, "lat0_deg"),
        (float("nan"), LON0, 0.0, "lat0_deg"),
        (LAT0, float("nan"), 0.0, "lon0_deg"),
        (LAT0, 181.0, 0.0, "lon0_deg"),
        (LAT0, LON0, float("inf"), "alt0_m"),
    ],
)
def test_invalid_origin_raises(lat: float, lon: float, alt: float, param: str) -> None:
    with pytest.raises(ValueError, match=param):
        GeoFrame(lat, lon, alt)


def test_dict_round_trip(frame: GeoFrame) -> None:
    assert GeoFrame.from_dict(frame.to_dict()) == frame


@pytest.mark.parametrize("origin", [(LAT0, LON0, ALT0), (0.0, 0.0, 0.0), (89.9, 10.0, 100.0), (-60.0, 170.0, 2000.0),
                                    (-89.999, -179.9, 0.0)])
def test_to_geodetic_matches_pymap3d_everywhere(origin: tuple[float, float, float]) -> None:
    """The own ENU -> geodetic closed form agrees with pymap3d's iterative one to far below a millimetre,
    up to 50 km from the origin, at the equator, near the poles and across the antimeridian."""
    pymap3d = pytest.importorskip("pymap3d")
    rng = np.random.default_rng(3)
    enu = np.column_stack([rng.uniform(-50_000, 50_000, (1000, 2)), rng.uniform(-500, 3000, 1000)])
    got = GeoFrame(*origin).to_geodetic(enu)
    want = np.stack(pymap3d.enu2geodetic(enu[:, 0], enu[:, 1], enu[:, 2], *origin), axis=-1)
    dlon = np.abs(got[:, 1] - want[:, 1])
    dlon = np.minimum(dlon, 360 - dlon)
    assert np.max(np.abs(got[:, 0] - want[:, 0])) * 111_000 < 1e-6
    assert np.max(dlon * 111_000 * np.cos(np.radians(want[:, 0]))) < 1e-6
    assert np.max(np.abs(got[:, 2] - want[:, 2])) < 1e-6


def test_reframe_moves_ground_points_between_site_frames(frame: GeoFrame) -> None:
    ll = frame.to_geodetic(np.array([[100.0, -40.0]]))[0]
    other = GeoFrame(ll[0], ll[1], ALT0)  # origin 100 m east, 40 m south of `frame`'s
    np.testing.assert_allclose(frame.reframe(np.array([[100.0, -40.0], [0.0, 0.0]]), other),
                               [[0.0, 0.0], [-100.0, 40.0]], atol=0.01)
    pts = np.random.default_rng(4).uniform(-300, 300, (50, 2))
    np.testing.assert_allclose(other.reframe(frame.reframe(pts, other), frame), pts, atol=1e-6)


def _whole_matrix(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, scale: float) -> np.ndarray:
    """in_footprints as it was, all N x N at once: the reference."""
    half = 0.5 * scale * size_lwh[:, :2]
    d = xy[None, :, :] - xy[:, None, :]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return (np.abs(d[..., 0] * c + d[..., 1] * s) <= half[:, :1]) & (np.abs(d[..., 1] * c - d[..., 0] * s)
                                                                        <= half[:, 1:])


def test_in_footprints_rows_are_the_whole_matrixs_rows() -> None:
    """Rows asked for (in any order, repeated) are the whole matrix's rows, and `either` the rows of it or its
    transpose, bit for bit: what lets the footprint rules take FOOTPRINT_ROWS rows at a time."""
    rng = np.random.default_rng(4)
    n = 300
    xy = np.round(rng.uniform(-20, 20, (n, 2)), 1)  # on a grid: many points on an outline
    yaw = rng.choice([0.0, np.pi / 2, np.pi, 0.3], n)
    size = np.column_stack([rng.choice([4.0, 4.5, 12.0], n), rng.choice([1.8, 2.5], n), np.ones(n)])
    whole = _whole_matrix(xy, yaw, size, 1.4)
    np.testing.assert_array_equal(in_footprints(xy, yaw, size, 1.4), whole)
    rows = np.array([5, 0, 299, 5, 17])
    np.testing.assert_array_equal(in_footprints(xy, yaw, size, 1.4, rows=rows), whole[rows])
    np.testing.assert_array_equal(in_footprints(xy, yaw, size, 1.4, rows=rows, either=True), (whole | whole.T)[rows])
    assert in_footprints(xy, yaw, size, 1.4, rows=np.zeros(0, int)).shape == (0, n)
