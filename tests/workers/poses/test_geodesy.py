import numpy as np
import pytest

from workers.poses import geodesy

ZURICH = geodesy.Geodetic(47.3769, 8.5417, 408.0)


def test_ecef_of_known_points():
    points = np.array([[0.0, 0.0, 0.0], [90.0, 0.0, 0.0], [0.0, 90.0, 100.0]])
    ecef = geodesy.to_ecef(points)
    b = geodesy.A * (1 - geodesy.F)  # the polar radius
    assert ecef[0] == pytest.approx([geodesy.A, 0, 0], abs=1e-6)
    assert ecef[1] == pytest.approx([0, 0, b], abs=1e-6)
    assert ecef[2] == pytest.approx([0, geodesy.A + 100, 0], abs=1e-6)


def test_geodetic_round_trip_anywhere():
    rng = np.random.default_rng(0)
    points = np.stack(
        [rng.uniform(-89, 89, 200), rng.uniform(-180, 180, 200), rng.uniform(-400, 9000, 200)],
        axis=1,
    )
    back = geodesy.from_ecef(geodesy.to_ecef(points))
    assert np.abs(back[:, :2] - points[:, :2]).max() < 1e-10  # degrees: 0.01 mm
    assert np.abs(back[:, 2] - points[:, 2]).max() < 1e-6


def test_enu_is_metric_and_gravity_up():
    enu = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 250.0, 0.0], [3.0, -4.0, 80.0]])
    places = geodesy.from_enu(enu, ZURICH)
    assert places[0] == pytest.approx([ZURICH.latitude, ZURICH.longitude, ZURICH.altitude])
    assert places[2, 0] > ZURICH.latitude and places[1, 1] > ZURICH.longitude  # north, east
    assert places[3, 2] == pytest.approx(ZURICH.altitude + 80, abs=1e-3)  # up is altitude
    assert geodesy.to_enu(places, ZURICH) == pytest.approx(enu, abs=1e-6)
    # distances in ENU are distances on the Earth
    ecef = geodesy.to_ecef(places)
    assert np.linalg.norm(ecef[3] - ecef[1]) == pytest.approx(np.linalg.norm(enu[3] - enu[1]))


def test_the_centre_of_a_capture_is_its_mean_place():
    enu = np.array([[-50.0, -20.0, 30.0], [50.0, 20.0, 50.0]])
    places = geodesy.from_enu(enu, ZURICH)
    centre = geodesy.centre(places)
    assert geodesy.to_enu(places, centre) == pytest.approx(enu - [0, 0, 40], abs=1e-3)
