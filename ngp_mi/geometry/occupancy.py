"""Inside / outside of a shape: exact for procedural solids, robust for arbitrary (open) meshes.

Meshes from ShapeNet / PartNet are rarely watertight, so ray parity is unreliable (a ray through a
hole counts one crossing too few). We use the **generalised winding number** (Jacobson, Kavan and
Sorkine-Hornung 2013),

    w(p) = Σ_f Ω_f(p) / 4π,

the signed solid angle Ω_f subtended by each triangle f at p, which is 1 inside and 0 outside a
closed, consistently oriented mesh and degrades gracefully (a smooth value near 1/2 across a hole)
otherwise; ``w > 1/2`` is inside. Ω_f uses Van Oosterom and Strackee's formula (1983):

    tan(Ω/2) = a·(b×c) / (|a||b||c| + (a·b)|c| + (b·c)|a| + (c·a)|b|),   a, b, c = triangle − p.

Evaluated directly (:func:`winding_numbers`) it costs points × triangles: minutes for a 64³ grid
of a 100k-face mesh. Inside tests and grids use libigl's **fast winding number** instead (Barill,
Dickson, Schmidt, Levin and Jacobson 2018; :func:`fast_winding_numbers`): a Barnes–Hut tree whose
far triangles are summarised by dipole expansions, 0.2 s for that grid (bench/RESULTS.md, "Fast
winding numbers"). The exact sum stays as the reference the tests hold the fast one to.

All grids span the cube ``[-DOMAIN, DOMAIN]³`` (meshes are normalised to radius 0.5, so 0.55 leaves
a margin that keeps extracted surfaces closed) and are indexed ``[i, j, k]`` ↔ ``(x, y, z)``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import igl
import numpy as np
import torch
from scipy import ndimage

from ngp_mi.geometry.families import generate
from ngp_mi.geometry.loaders import load_mesh
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.sources import ShapeRef

DOMAIN = 0.55
Inside = Callable[[np.ndarray], np.ndarray]  # (P, 3) points → (P,) bool


def grid_points(resolution: int, half: float = DOMAIN) -> np.ndarray:
    """Cell centres of a ``resolution``³ grid over ``[-half, half]³``, shape (R, R, R, 3), [i, j, k] ↔ (x, y, z)."""
    axis = (np.arange(resolution) + 0.5) / resolution * 2 * half - half
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                    pairs_per_chunk: int = 1 << 22) -> np.ndarray:
    """Generalised winding number of the triangle mesh at each of ``points`` (P, 3) → (P,) float64,
    summed exactly over every triangle (the reference of :func:`fast_winding_numbers`).

    Float32 arithmetic (faster and half the memory of float64); the inside / outside decisions of the
    tests' meshes are the same.
    """
    tri = torch.as_tensor(np.asarray(vertices, np.float32)[np.asarray(faces)])  # (F, 3, 3)
    pts = torch.as_tensor(np.asarray(points, np.float32).reshape(-1, 3))
    out = torch.empty(len(pts), dtype=torch.float32)
    chunk = max(1, pairs_per_chunk // max(1, len(tri)))
    for start in range(0, len(pts), chunk):
        rel = tri[None] - pts[start:start + chunk, None, None]  # (P, F, 3, 3)
        a, b, c = rel.unbind(2)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[start:start + chunk] = torch.atan2(det, den).sum(-1) / (2 * math.pi)
    return out.numpy().astype(np.float64)


def fast_winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The generalised winding number at ``points`` (P, 3) → (P,) float64 by libigl's fast winding
    number (Barill et al. 2018; expansion order 2, Barnes–Hut β = 2): within 1e-3 of
    :func:`winding_numbers` on the tests' meshes, in O((P + F) log F)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(faces) == 0 or len(points) == 0:
        return np.zeros(len(points))
    return igl.fast_winding_number(np.ascontiguousarray(vertices, np.float64),
                                   np.ascontiguousarray(faces, np.int64), np.ascontiguousarray(points))


def mesh_inside(mesh: TriangleMesh) -> Inside:
    """Inside test of a (possibly open) mesh: winding number > 1/2."""
    return lambda points: fast_winding_numbers(mesh.vertices, mesh.faces, points) > 0.5


def triangle_areas(mesh: TriangleMesh) -> np.ndarray:
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def surface_samples(mesh: TriangleMesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniformly (by area) on the mesh, float32."""
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    area = triangle_areas(mesh)
    face = rng.choice(len(tri), count, p=area / area.sum()) if area.sum() > 0 else rng.integers(0, len(tri), count)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[face]
    return (t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])).astype(np.float32)


def mesh_occupancy_grid(mesh: TriangleMesh, resolution: int, half: float = DOMAIN) -> np.ndarray:
    """Occupancy (R, R, R) bool of a (possibly open) mesh at the cell centres: fast winding number > 1/2."""
    points = grid_points(resolution, half).reshape(-1, 3)
    return (fast_winding_numbers(mesh.vertices, mesh.faces, points) > 0.5).reshape((resolution,) * 3)


def boundary_cells(occupancy: np.ndarray) -> np.ndarray:
    """Cells whose occupancy differs from one of their 6 neighbours (the voxel surface), bool."""
    inner = ndimage.binary_erosion(occupancy, border_value=0)
    outer = ndimage.binary_dilation(occupancy)
    return outer & ~inner


def sample_occupancy_points(inside: Inside, grid: np.ndarray, count: int, rng: np.random.Generator,
                            near_fraction: float = 0.5, half: float = DOMAIN) -> tuple[np.ndarray, np.ndarray]:
    """IM-NET style training points at one resolution: (count, 3) float32 and (count,) uint8 occupancy.

    ``grid`` is the shape's occupancy at this resolution. Up to ``near_fraction`` of the points come
    from cells on the voxel surface (where the decoder must be precise), the rest uniformly from all
    cells; each point is jittered uniformly inside its cell and labelled by the exact ``inside``
    test, so that the decoder sees the true surface rather than a staircase. When ``count`` covers
    the whole grid (16³ in IM-NET), every cell is used once.
    """
    resolution = grid.shape[0]
    cells = resolution ** 3
    if count >= cells:
        chosen = np.arange(cells)
    else:
        near = np.flatnonzero(boundary_cells(grid).ravel())
        n_near = min(len(near), int(count * near_fraction))
        picked_near = rng.choice(near, n_near, replace=False) if n_near else np.zeros(0, np.int64)
        rest = rng.choice(cells, count - n_near, replace=False)
        chosen = np.concatenate([picked_near, rest])
    ijk = np.stack(np.unravel_index(chosen, grid.shape), axis=1)
    cell = 2 * half / resolution
    points = (ijk + rng.random(ijk.shape)) * cell - half
    return points.astype(np.float32), inside(points).astype(np.uint8)


def voxel_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean grids (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


@dataclasses.dataclass(frozen=True)
class Solid:
    """A shape as a solid: its surface, an inside test of points, and its occupancy on grids."""

    mesh: TriangleMesh
    inside: Inside
    grid: Callable[[int], np.ndarray]  # resolution R → (R, R, R) bool occupancy at the cell centres


def load_solid(ref: ShapeRef) -> Solid:
    """A procedural object (exact occupancy from its signed distance) or a mesh file (generalised
    winding numbers, so open meshes work); scenes are not solids."""
    if ref.kind == "procedural":
        obj = generate(ref.origin, ref.seed)
        return Solid(obj.mesh(), obj.solid.occupancy,
                     lambda r: obj.solid.occupancy(grid_points(r).reshape(-1, 3)).reshape(r, r, r))
    if ref.kind == "mesh":
        mesh = load_mesh(ref.path)
        return Solid(mesh, mesh_inside(mesh), lambda r: mesh_occupancy_grid(mesh, r))
    raise ValueError(f"{ref.origin}: a {ref.kind} is not a solid (the shape prior needs a family or meshes)")
