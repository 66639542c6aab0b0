"""Independent reference computations shared by the tests (no Mitsuba inside), and a JIT probe."""

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


def rss_mib() -> float:
    """Resident memory of this process in MiB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


def analytic_sphere(camera: Camera, radius: float):
    """z-depth, camera-space normal and mask of a sphere at the origin, at pixel centres."""
    rays = camera.pixel_rays()
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    c = camera.world_to_camera(np.zeros(3))
    b = unit @ c
    disc = b ** 2 - (c @ c - radius ** 2)
    hit = disc > 0
    t = b - np.sqrt(np.where(hit, disc, 0.0))
    point = t[..., None] * unit
    return np.where(hit, point[..., 2], 0.0), np.where(hit[..., None], (point - c) / radius, 0.0), hit


def compiled_kernels(fn) -> tuple[list[dict], list[dict]]:
    """Run ``fn()`` and return (every JIT kernel it launched, those not found in Dr.Jit's kernel cache)."""
    from ngp_mi import backend

    dr = backend.drjit()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        fn()
        launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return launched, [k for k in launched if not k["cache_hit"]]
