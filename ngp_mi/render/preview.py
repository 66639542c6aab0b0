"""Path-traced previews: procedural objects with their physically based part materials, plain meshes in grey."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ngp_mi.camera import Camera
from ngp_mi.geometry.families import ProceduralObject
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.render.scene import build_scene, diffuse_bsdf, mesh_parts_to_mitsuba, render
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
        tiles.append(to_uint8(render(scene, seed=obj.seed)))
    return contact_sheet(tiles, [obj.id for obj in objects], columns=columns)


def mesh_preview(mesh: TriangleMesh, camera: Camera, lights: Sequence[Light] | None = None, spp: int = 16,
                 albedo: float = 0.6, seed: int = 0) -> np.ndarray:
    """A uint8 sRGB image of a (grey, Lambertian) mesh path traced under the 4-light rig."""
    lights = overhead_rig() if lights is None else lights
    shapes = mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(albedo))
    scene = build_scene(camera, shapes, lights, {"type": "path", "max_depth": 3}, spp=spp)
    return to_uint8(render(scene, seed=seed))
