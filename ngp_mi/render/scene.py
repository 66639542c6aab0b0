"""Building Mitsuba scenes from project objects (meshes, cameras, lights).

All access to Mitsuba mesh parameters goes through this module: the parameter names differ
between Mitsuba releases (3.9.1: ``vertex_positions``; unreleased master: ``positions``).
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.lights import Light, lights_to_mitsuba
from ngp_mi.render import integrators

MESH_POSITIONS = "vertex_positions"
MESH_FACES = "faces"


def diffuse_bsdf(albedo: Sequence[float] | float) -> dict[str, Any]:
    """A Lambertian BSDF dictionary with a linear-RGB albedo."""
    rgb = [float(albedo)] * 3 if np.isscalar(albedo) else [float(a) for a in albedo]  # type: ignore[arg-type]
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}


def mitsuba_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh",
                 bsdf: Mapping[str, Any] | None = None) -> Any:
    """An ``mi.Mesh`` with the given positions, faces and (optional) BSDF dictionary."""
    mi = backend.mitsuba()
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(dict(bsdf))
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props)
    params = mi.traverse(mesh)
    params[MESH_POSITIONS] = mi.Float(np.ascontiguousarray(vertices, np.float32).ravel())
    params[MESH_FACES] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).ravel())
    params.update()
    return mesh


def mesh_parts_to_mitsuba(mesh: TriangleMesh, bsdfs: Mapping[int, Mapping[str, Any]] | None = None,
                          default_bsdf: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """One ``mi.Mesh`` per part id (so each part can have its own BSDF), keyed ``<name>_part<k>``."""
    bsdfs = bsdfs or {}
    out = {}
    new_index = np.empty(len(mesh.vertices), np.int64)
    for part in np.unique(mesh.part_ids):
        faces = mesh.faces[mesh.part_ids == part]
        used = np.flatnonzero(np.bincount(faces.ravel(), minlength=len(mesh.vertices)))  # sorted, like np.unique
        new_index[used] = np.arange(len(used))
        key = f"{mesh.name}_part{int(part)}"
        out[key] = mitsuba_mesh(mesh.vertices[used], new_index[faces], key, bsdfs.get(int(part), default_bsdf))
    return out


def build_scene(camera: Camera, shapes: Mapping[str, Any], lights: Iterable[Light] = (),
                integrator: Mapping[str, Any] | None = None, spp: int = 1, rfilter: str = "box",
                seed: int = 0, pixel_format: str = "rgb") -> Any:
    """Load a Mitsuba scene: one sensor at ``camera``, the given shapes and emitters.

    The sensor is placed through :func:`set_sensor_camera`, so its pose is a kernel parameter from
    the first render on: moving it to another view of the same resolution reuses the compiled
    kernel. ``integrator`` may name the project's own integrators (:mod:`ngp_mi.render.integrators`).
    ``pixel_format="rgba"`` adds alpha: the filtered fraction of the pixel's samples whose ray hit
    the scene (with the box filter, the pixel's coverage).
    """
    mi = backend.mitsuba()
    integrators.register()
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": dict(integrator or {"type": "path", "max_depth": 3}),
        "sensor": camera.to_mitsuba(spp=spp, rfilter=rfilter, pixel_format=pixel_format, seed=seed),
        **shapes,
        **lights_to_mitsuba(lights),
    }
    loaded = mi.load_dict(scene)
    set_sensor_camera(loaded.sensors()[0], camera)
    return loaded


def set_sensor_camera(sensor: Any, camera: Camera) -> None:
    """Move an existing ``perspective`` sensor to ``camera`` (same resolution).

    Updating through ``mi.traverse`` keeps the pose a kernel parameter, so a new view reuses the
    compiled kernel instead of recompiling (a new resolution is a new kernel: build a new sensor).
    """
    mi = backend.mitsuba()
    params = mi.traverse(sensor)
    size = tuple(int(x) for x in params["film.size"])
    if size != (camera.width, camera.height):
        raise ValueError(f"sensor film is {size[0]}x{size[1]}, camera is {camera.width}x{camera.height}; "
                         "build a new sensor for a new resolution")
    fields = camera.to_mitsuba()
    params["to_world"] = mi.AffineTransform4f(camera.camera_to_world_mitsuba().tolist())
    params["x_fov"] = fields["fov"]
    params["principal_point_offset_x"] = fields["principal_point_offset_x"]
    params["principal_point_offset_y"] = fields["principal_point_offset_y"]
    params.update()


def render(scene: Any, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """Render ``scene`` and return a float32 (H, W, C) numpy array (linear values)."""
    mi = backend.mitsuba()
    image = mi.render(scene, spp=spp or 0, seed=seed)
    return np.array(image, dtype=np.float32)
