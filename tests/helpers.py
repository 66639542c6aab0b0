"""Independent reference computations shared by the tests (no Mitsuba inside)."""

import numpy as np
import trimesh

from ngp_mi.camera import Camera
from ngp_mi.geometry.mesh import TriangleMesh


def trimesh_depth(mesh: TriangleMesh, camera: Camera) -> np.ndarray:
    """z-depth (H, W) at pixel centres by trimesh's ray caster; 0 where the ray misses."""
    rays = camera.pixel_rays().reshape(-1, 3)
    directions = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ camera.R  # camera -> world
    origins = np.broadcast_to(camera.position, directions.shape)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    locations, index_ray, _ = tm.ray.intersects_location(origins, directions, multiple_hits=False)
    depth = np.zeros(len(rays))
    depth[index_ray] = camera.world_to_camera(locations)[:, 2]
    return depth.reshape(camera.height, camera.width)
