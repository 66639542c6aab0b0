"""Scenes: build_scene places its sensor at the camera (a parameter, so new views reuse the kernel) and
knows the project's own integrators."""

import numpy as np

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.lights import DirectionalLight
from ngp_mi.render import integrators
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render, set_sensor_camera


def test_the_sensor_sits_at_the_camera_and_project_integrators_load():
    mi = backend.mitsuba()
    camera = Camera.orbit(15.0, 40.0, 24)
    shapes = {"sphere": {"type": "sphere", "radius": 0.4, "bsdf": diffuse_bsdf(0.5)}}
    integrators.register()
    integrators.register()  # idempotent
    scene = build_scene(camera, shapes, [DirectionalLight((0, 1, 1), 1.0)], {"type": "direct_unshadowed"}, spp=1)
    to_world = np.array(mi.traverse(scene.sensors()[0])["to_world"].matrix).reshape(4, 4)
    assert np.allclose(to_world, camera.camera_to_world_mitsuba(), atol=1e-5)
    image = render(scene)
    assert image[12, 12].sum() > 0 and not image[0, 0].any()
    other = Camera.orbit(15.0, -40.0, 24)
    set_sensor_camera(scene.sensors()[0], other)
    moved = np.array(mi.traverse(scene.sensors()[0])["to_world"].matrix).reshape(4, 4)
    assert np.allclose(moved, other.camera_to_world_mitsuba(), atol=1e-5)
