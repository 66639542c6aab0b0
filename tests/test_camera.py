import math

import numpy as np
import pytest

from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.render.scene import build_scene, render, set_sensor_camera


def test_orbit_camera_geometry():
    cam = Camera.orbit(15.0, -40.0, 128)
    assert np.linalg.norm(cam.position) == pytest.approx(2.0)
    t, p = math.radians(15), math.radians(-40)
    np.testing.assert_allclose(cam.position, 2 * np.array([math.cos(t) * math.sin(p), math.sin(t),
                                                           math.cos(t) * math.cos(p)]), atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cam.forward, -cam.position / 2.0, atol=1e-12)
    np.testing.assert_allclose(cam.E @ np.append(cam.position, 1.0), 0.0, atol=1e-12)
    uv, z = cam.project(np.zeros(3))
    np.testing.assert_allclose(uv, [64.0, 64.0], atol=1e-9)
    assert z == pytest.approx(2.0)
    assert cam.hfov_deg == pytest.approx(39.5978, abs=1e-3)
    # No roll: the world's up direction projects to "up" (negative image y) on the image.
    up_uv, _ = cam.project(np.array([0.0, 0.3, 0.0]))
    assert up_uv[0] == pytest.approx(64.0, abs=1e-9) and up_uv[1] < 64.0


def test_straight_down_view_is_well_defined():
    top = Camera.orbit(90.0, 30.0, 64)
    near = Camera.orbit(89.999, 30.0, 64)
    assert np.all(np.isfinite(top.R))
    np.testing.assert_allclose(top.R, near.R, atol=1e-4)
    np.testing.assert_allclose(top.position, [0, 2, 0], atol=1e-12)


@pytest.mark.parametrize("theta, phi", [(90.5, 0.0), (float("nan"), 0.0), (0.0, float("inf"))])
def test_invalid_angles_are_rejected(theta, phi):
    with pytest.raises(ValueError, match="camera"):
        Camera.orbit(theta, phi, 64)


def _marker_centroid(mi, camera, point, radius=0.02):
    """Coverage-weighted centroid (pixel units) of an emissive marker sphere rendered by Mitsuba."""
    shapes = {"marker": {"type": "sphere", "center": [float(x) for x in point], "radius": radius,
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}}
    scene = build_scene(camera, shapes, integrator={"type": "direct"}, spp=256)
    coverage = render(scene)[..., 0]
    assert coverage.sum() > 1.0, "marker not visible"
    v, u = np.mgrid[:camera.height, :camera.width] + 0.5
    return np.array([(coverage * u).sum(), (coverage * v).sum()]) / coverage.sum()


VIEWS = [(0.0, 0.0), (12.0, 35.0), (20.0, -85.0), (5.0, 60.0), (90.0, 10.0)]
POINTS = [(0.25, 0.15, 0.1), (-0.3, -0.2, 0.25)]


@pytest.mark.parametrize("resolution", [64, 128])
@pytest.mark.parametrize("theta, phi", VIEWS)
def test_mitsuba_renders_points_where_K_E_projects_them(mi, theta, phi, resolution):
    camera = Camera.orbit(theta, phi, resolution)
    for point in POINTS:
        expected, _ = camera.project(np.asarray(point))
        assert np.abs(_marker_centroid(mi, camera, point) - expected).max() < 0.5


def test_off_centre_principal_point_matches_mitsuba(mi):
    base = Camera.orbit(10.0, 20.0, 64)
    K = base.K
    K[0, 2] += 7.0
    K[1, 2] -= 5.0
    camera = Camera.from_K_E(K, base.E, 64, 64)
    expected, _ = camera.project(np.asarray(POINTS[0]))
    assert np.abs(_marker_centroid(mi, camera, POINTS[0]) - expected).max() < 0.5


def test_moving_a_sensor_matches_a_new_sensor(mi):
    cam_a, cam_b = Camera.orbit(5.0, -30.0, 64), Camera.orbit(15.0, 50.0, 64)
    shapes = {"s": {"type": "sphere", "center": [0.1, 0.0, 0.0], "radius": 0.3}}
    aov = {"type": "aov", "aovs": "d:depth"}
    moved = build_scene(cam_a, shapes, integrator=aov)
    set_sensor_camera(moved.sensors()[0], cam_b)
    fresh = build_scene(cam_b, shapes, integrator=aov)
    np.testing.assert_allclose(render(moved, seed=3), render(fresh, seed=3), atol=1e-5)
    with pytest.raises(ValueError, match="new resolution"):
        set_sensor_camera(moved.sensors()[0], Camera.orbit(0.0, 0.0, 32))


def test_K_E_round_trip_and_resolution_change():
    cam = Camera.orbit(7.0, 25.0, 256)
    again = Camera.from_dict(cam.to_dict())
    np.testing.assert_allclose(again.K, cam.K)
    np.testing.assert_allclose(again.E, cam.E)
    assert (again.theta_deg, again.phi_deg) == (7.0, 25.0)
    point = np.array([0.2, -0.1, 0.3])
    small = cam.with_resolution(64)
    np.testing.assert_allclose(small.project(point)[0], cam.project(point)[0] / 4.0, atol=1e-9)
    with pytest.raises(ValueError, match="fx == fy"):
        Camera.from_K_E(np.diag([100.0, 120.0, 1.0]), cam.E, 64, 64)


def test_view_distribution_is_seeded_and_in_range():
    dist = ViewDistribution()
    a, b = dist.sample(50, seed=3), dist.sample(50, seed=3)
    assert [(c.theta_deg, c.phi_deg) for c in a] == [(c.theta_deg, c.phi_deg) for c in b]
    assert [c.theta_deg for c in dist.sample(50, seed=4)] != [c.theta_deg for c in a]
    thetas, phis = np.array([c.theta_deg for c in a]), np.array([c.phi_deg for c in a])
    assert thetas.min() >= 0 and thetas.max() <= 20 and phis.min() >= -90 and phis.max() <= 90
    assert phis.min() < -45 and phis.max() > 45  # spread over the range
    custom = ViewDistribution(theta_range=(30.0, 40.0), phi_range=(0.0, 0.0)).sample(5, seed=0, resolution=32)
    assert all(30 <= c.theta_deg <= 40 and c.phi_deg == 0 and c.width == 32 for c in custom)
    with pytest.raises(ValueError, match="theta_range"):
        ViewDistribution(theta_range=(10.0, 0.0))
    with pytest.raises(ValueError, match="theta_range"):
        ViewDistribution(theta_range=(0.0, 95.0))
