"""Path-traced previews of procedural objects with their physically based part materials."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ngp_mi.camera import Camera
from ngp_mi.geometry.families import ProceduralObject
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.render.scene import build_scene, mesh_parts_to_mitsuba, render, set_sensor_camera
from ngp_mi.viz import contact_sheet, to_uint8


def object_shapes(obj: ProceduralObject) -> dict:
    """Mitsuba shapes of ``obj``, one per part label, each with its ``principled`` BSDF."""
    return mesh_parts_to_mitsuba(obj.mesh(), {label: m.to_mitsuba() for label, m in obj.materials.items()})


def preview_sheet(objects: Sequence[ProceduralObject], camera: Camera, lights: Sequence[Light] | None = None,
                  spp: int = 64, columns: int = 4) -> np.ndarray:
    """A labelled contact sheet (uint8) of ``objects`` seen from ``camera``, path traced."""
    lights = overhead_rig() if lights is None else lights
    tiles = []
    for obj in objects:
        scene = build_scene(camera, object_shapes(obj), lights, {"type": "path", "max_depth": 4}, spp=spp)
        set_sensor_camera(scene.sensors()[0], camera)
        tiles.append(to_uint8(render(scene, seed=obj.seed)))
    return contact_sheet(tiles, [obj.id for obj in objects], columns=columns)
