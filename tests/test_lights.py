import math

import numpy as np
import pytest

from ngp_mi.camera import Camera
from ngp_mi.lights import (
    DirectionalLight,
    PointLight,
    light_from_dict,
    lights_from_json,
    lights_to_json,
    load_lights,
    overhead_rig,
    save_lights,
)
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render


def test_json_round_trip(tmp_path):
    lights = [DirectionalLight((0, 2, 0), (1.0, 0.5, 0.25)), PointLight((0.5, 1.0, -2.0), 3.0)]
    assert lights_from_json(lights_to_json(lights)) == lights
    save_lights(tmp_path / "l.json", lights)
    assert load_lights(tmp_path / "l.json") == lights
    assert lights[0].direction == (0.0, 1.0, 0.0)  # stored normalised
    assert lights[1].intensity == (3.0, 3.0, 3.0)  # a number means grey


@pytest.mark.parametrize("data, match", [
    ({"type": "directional", "direction": [0, 0, 0]}, "direction must be non-zero"),
    ({"type": "directional", "direction": [0, 1, 0], "irradiance": [1, -1, 1]}, "irradiance must be non-negative"),
    ({"type": "directional", "direction": [0, 1, 0], "irradiance": [1, float("nan"), 1]}, "irradiance must be finite"),
    ({"type": "point", "position": [0, 1, 0], "intensity": float("inf")}, "intensity must be finite"),
    ({"type": "point", "position": [0, 1]}, "position must be 3 numbers"),
    ({"type": "spot", "position": [0, 1, 0]}, "field 'type' must be one of"),
    ({"type": "point", "position": [0, 1, 0], "power": 2}, r"unknown field\(s\) \['power'\]"),
])
def test_invalid_lights_are_rejected_with_field_named(data, match):
    with pytest.raises(ValueError, match=match) as info:
        light_from_dict(data, where="scene.json[3]")
    assert str(info.value).startswith("scene.json[3]")


def test_unreadable_light_file_names_the_file(tmp_path):
    with pytest.raises(ValueError, match="missing.json"):
        load_lights(tmp_path / "missing.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ValueError, match="broken.json: not valid JSON"):
        load_lights(tmp_path / "broken.json")


def test_overhead_rig_is_four_white_lights_spread_around_overhead():
    rig = overhead_rig()
    assert len(rig) == 4
    dirs = np.array([light.direction for light in rig])
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.all(dirs[:, 1] > 0.5)  # above the horizon
    np.testing.assert_allclose(dirs[:, [0, 2]].sum(0), 0.0, atol=1e-12)  # uniformly around
    assert all(light.irradiance[0] == light.irradiance[1] == light.irradiance[2] for light in rig)
    with pytest.raises(ValueError, match="elevation"):
        overhead_rig(elevation_deg=0.0)


def _plane_radiance(lights, albedo=0.5, resolution=32):
    """Radiance at the image centre of a diffuse plane z = 0 facing +Z, seen from +Z."""
    camera = Camera.orbit(0.0, 0.0, resolution)
    shapes = {"plane": {"type": "rectangle", "bsdf": diffuse_bsdf(albedo)}}
    image = render(build_scene(camera, shapes, lights, integrator={"type": "direct"}, spp=4))
    c = resolution // 2
    return image[c - 1:c + 1, c - 1:c + 1].mean((0, 1))


@pytest.mark.parametrize("angle_deg", [0.0, 40.0, 75.0])
def test_mitsuba_directional_light_radiometry(mi, angle_deg):
    a = math.radians(angle_deg)
    light = DirectionalLight((math.sin(a), 0.0, math.cos(a)), (1.0, 2.0, 0.5))
    expected = 0.5 * np.array(light.irradiance) * math.cos(a) / math.pi  # rho E cos / pi
    np.testing.assert_allclose(_plane_radiance([light]), expected, rtol=1e-3)
    behind = DirectionalLight((0.0, 0.0, -1.0), 1.0)
    assert _plane_radiance([behind]).max() == 0.0


def test_mitsuba_point_light_radiometry(mi):
    light = PointLight((0.0, 0.0, 0.5), 2.0)
    expected = 0.5 * 2.0 / (math.pi * 0.5 ** 2)  # rho I cos / (pi r^2) at the foot point
    np.testing.assert_allclose(_plane_radiance([light], resolution=64), expected, rtol=2e-3)
