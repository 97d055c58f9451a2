"""Geodesy against independent references: the closed-form WGS-84 geodetic→ECEF formula,
GeographicLib's published CartConvert example, and NGA's EGM96 test points."""
import numpy as np
import pytest

from gis import geodesy
from gis.geodesy import (
    LocalFrame,
    ecef_to_geodetic,
    ellipsoid_to_msl,
    geodetic_to_ecef,
    geoid_undulation_m,
    msl_to_ellipsoid,
)

A_M = 6378137.0
F = 1 / 298.257223563
E2 = F * (2 - F)


def textbook_geodetic_to_ecef(lat_deg, lon_deg, h_m):
    """Closed form (e.g. Hofmann-Wellenhof et al., GNSS, Eq. 10.8): independent of PROJ."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = A_M / np.sqrt(1 - E2 * np.sin(lat) ** 2)
    return np.stack(
        [(n + h_m) * np.cos(lat) * np.cos(lon), (n + h_m) * np.cos(lat) * np.sin(lon), (n * (1 - E2) + h_m) * np.sin(lat)], axis=-1
    )


@pytest.fixture(scope="module")
def grid():
    lat, lon, h = np.meshgrid(np.linspace(-89, 89, 37), np.linspace(-180, 179, 19), np.array([-500.0, 0.0, 120.0, 2500.0, 10_000.0]), indexing="ij")
    return lat.ravel(), lon.ravel(), h.ravel()


def test_geodetic_to_ecef_matches_closed_form_submillimetre(grid):
    lat, lon, h = grid
    p = geodetic_to_ecef(lat, lon, h)
    assert p.shape == (lat.size, 3)
    assert np.max(np.abs(p - textbook_geodetic_to_ecef(lat, lon, h))) < 1e-4


def test_geographiclib_cartconvert_example():
    # GeographicLib CartConvert(1) man page: "echo 33.3 44.4 6000 | CartConvert" → 3816209.60 3737108.55 3485109.57
    np.testing.assert_allclose(geodetic_to_ecef(33.3, 44.4, 6000.0), [3816209.60, 3737108.55, 3485109.57], atol=0.01)


def test_round_trip_grid_submillimetre(grid):
    lat, lon, h = grid
    lat2, lon2, h2 = ecef_to_geodetic(textbook_geodetic_to_ecef(lat, lon, h))
    # 1e-9 deg ≈ 0.1 mm on the ground
    assert np.max(np.abs(lat2 - lat)) < 1e-9
    assert np.max(np.abs(((lon2 - lon + 180) % 360) - 180)) < 1e-9
    assert np.max(np.abs(h2 - h)) < 1e-4


def test_enu_and_ned_axes_and_round_trip():
    frame = LocalFrame(47.3977, 8.5456, 488.0)
    # straight up from the origin is +U / −D
    np.testing.assert_allclose(frame.geodetic_to_enu(47.3977, 8.5456, 588.0), [0, 0, 100], atol=1e-6)
    np.testing.assert_allclose(frame.geodetic_to_ned(47.3977, 8.5456, 588.0), [0, 0, -100], atol=1e-6)
    # a point slightly north has positive N, ~zero E
    enu = frame.geodetic_to_enu(47.3987, 8.5456, 488.0)
    assert enu[1] > 100 and abs(enu[0]) < 1e-6
    ned = frame.geodetic_to_ned(47.3977, 8.5466, 488.0)
    assert ned[1] > 70 and abs(ned[0]) < 0.01
    pts = np.random.default_rng(0).uniform(-5000, 5000, size=(200, 3))
    np.testing.assert_allclose(frame.ecef_to_enu(frame.enu_to_ecef(pts)), pts, atol=1e-6)
    np.testing.assert_allclose(frame.ecef_to_ned(frame.ned_to_ecef(pts)), pts, atol=1e-6)
    lat, lon, h = frame.ned_to_geodetic(pts)
    np.testing.assert_allclose(frame.geodetic_to_ned(lat, lon, h), pts, atol=1e-6)


def test_enu_rotation_at_equator_prime_meridian():
    R = geodesy.R_ecef_enu(0.0, 0.0)
    np.testing.assert_allclose(R[:, 0], [0, 1, 0], atol=1e-12)  # east = +Y
    np.testing.assert_allclose(R[:, 1], [0, 0, 1], atol=1e-12)  # north = +Z
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)  # up = +X


# NGA EGM96 test points (outintpt.dat of the EGM96 distribution): lat, lon (0..360), N [m].
NGA_EGM96 = [
    (38.6281550, 269.7791550, -31.628),
    (-14.6212170, 305.0211140, -2.969),
    (46.8743190, 102.4487290, -43.575),
    (-23.6174460, 133.8747120, 15.871),
    (38.6254730, 359.9995000, 50.066),
    (-0.4667440, 0.0023000, 17.329),
]


def test_egm96_against_nga_test_points():
    lat = np.array([p[0] for p in NGA_EGM96])
    lon = np.array([(p[1] + 180) % 360 - 180 for p in NGA_EGM96])
    ref = np.array([p[2] for p in NGA_EGM96])
    n = geoid_undulation_m(lat, lon)
    # NGA interpolates the 15' grid with its own scheme, PROJ bilinearly: a few cm apart.
    assert np.max(np.abs(n - ref)) < 0.07
    assert np.mean(np.abs(n - ref)) < 0.04


def test_msl_ellipsoid_round_trip():
    lat, lon = np.array([47.3977, -33.9, 0.0]), np.array([8.5456, 151.2, -80.0])
    h = np.array([500.0, 20.0, 100.0])
    np.testing.assert_allclose(msl_to_ellipsoid(lat, lon, ellipsoid_to_msl(lat, lon, h)), h, atol=1e-9)
    assert np.all(np.abs(ellipsoid_to_msl(lat, lon, h) - h) > 1.0)  # the geoid really is applied


def test_missing_geoid_grid_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(geodesy, "_EGM96_CANDIDATES", ("/nonexistent/egm96.gtx",))
    geodesy._geoid_transformer.cache_clear()
    try:
        with pytest.raises(geodesy.GeoidUnavailable, match="EGM96"):
            geoid_undulation_m(10.0, 10.0)
    finally:
        geodesy._geoid_transformer.cache_clear()
