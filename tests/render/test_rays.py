"""Pixel-centre rays of many cameras: directions through K⁻¹ [u + ½, v + ½, 1] and the z-depth factor."""

import numpy as np

from ngp_mi.camera import Camera
from ngp_mi.render.rays import camera_table, pixel_centre_rays


def test_rays_go_through_pixel_centres_of_every_view():
    cameras = [Camera.orbit(10.0, -30.0, (8, 6)), Camera.orbit(20.0, 45.0, (8, 6))]
    rays = pixel_centre_rays(camera_table(cameras), 8, 6)
    origin = np.array(rays.ray.o).T.reshape(2, 6, 8, 3)
    direction = np.array(rays.ray.d).T.reshape(2, 6, 8, 3)
    inv_len = np.array(rays.inv_len).reshape(2, 6, 8)
    for n, camera in enumerate(cameras):
        assert np.allclose(origin[n], camera.position, atol=1e-6)
        local = camera.pixel_rays()  # camera-space K⁻¹ [u, v, 1] at pixel centres, from the camera itself
        world = local @ camera.R  # R is world → camera: rows of R.T @ x
        assert np.allclose(direction[n], world / np.linalg.norm(world, axis=-1, keepdims=True), atol=1e-5)
        assert np.allclose(inv_len[n], 1 / np.linalg.norm(local, axis=-1), atol=1e-6)
        # z-depth = t · inv_len: a point at distance t along the ray is t · inv_len in front of the camera
        p = camera.position + 2.0 * direction[n]
        z = (camera.R @ (p - camera.position).reshape(-1, 3).T).T[:, 2].reshape(6, 8)
        assert np.allclose(z, 2.0 * inv_len[n], atol=1e-5)
    assert np.array_equal(np.array(rays.view), np.repeat([0, 1], 48))
    half = pixel_centre_rays(camera_table(cameras), 8, 6, first_view=1, num_views=1)
    assert np.allclose(np.array(half.ray.d).T, direction[1].reshape(-1, 3), atol=1e-6)
