"""The unshadowed direct integrator: analytic on a Lambertian sphere, and it ignores occluders."""

import math

import numpy as np

from ngp_mi.camera import Camera
from ngp_mi.lights import DirectionalLight
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render


def test_lambertian_plane_radiance_and_no_shadow(mi):
    camera = Camera.orbit(0.0, 0.0, 32)
    a = math.radians(35.0)
    light = DirectionalLight((math.sin(a), 0.0, math.cos(a)), (1.0, 0.5, 2.0))
    plane = {"plane": {"type": "rectangle", "bsdf": diffuse_bsdf(0.6)}}
    blocker = {"blocker": {"type": "sphere", "center": [0.46, 0.0, 0.655], "radius": 0.15,
                           "bsdf": diffuse_bsdf(0.5)}}  # casts a shadow onto the plane centre
    expected = 0.6 * np.array(light.irradiance) * math.cos(a) / math.pi
    unshadowed = render(build_scene(camera, {**plane, **blocker}, [light], {"type": "direct_unshadowed"}, spp=4))
    shadowed = render(build_scene(camera, {**plane, **blocker}, [light], {"type": "direct"}, spp=4))
    np.testing.assert_allclose(unshadowed[16, 16], expected, rtol=1e-4)
    assert shadowed[16, 16].max() == 0.0  # Mitsuba's direct integrator does see the shadow
    alone = render(build_scene(camera, plane, [light], {"type": "direct"}, spp=4))
    np.testing.assert_allclose(unshadowed[4:8, 4:8], alone[4:8, 4:8], rtol=1e-4)  # unoccluded: equal
