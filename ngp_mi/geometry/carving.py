"""The silhouette of an occupancy field along pixel rays: a loss that can open holes.

Π_v's silhouette gradients move a mesh's *outline*; a pixel inside the projected silhouette has
coverage 1 whatever the surface does there, so no gradient of the mask loss reaches a panel that
covers a gap of the target (the slats of a chair's back, seen from the front). Marching over the
field instead of the mesh gives that pixel a gradient. A pixel's ray r(t) = o + t d sees the object
when the occupancy f reaches the iso-level ℓ somewhere along it:

    s(r) = max_t f(r(t)),       object seen ⟺ s(r) ≥ ℓ                  (visual hull; Laurentini 1994)

and :func:`ray_silhouette_terms` penalises the two ways a field can disagree with a target mask m:

    free = mean over rays with m = 0 of  mean_t relu(f(r(t)) − ℓ + δ)     (the ray must stay empty)
    hit  = mean over rays with m = 1 of  relu(ℓ + δ − s(r))               (the ray must meet the shape)

δ a margin past the level. ``free`` pushes down every sample that is (nearly) occupied, not only
the ray's maximum, so a panel in front of a gap thins from both faces at once and opens (space
carving, Kutulakos and Seitz 2000, as a soft loss). The rays are drawn where the mesh's coverage
disagrees with the target (:func:`disagreement_pixels`): elsewhere both terms are zero or the mesh's
silhouette gradient already acts. Samples are stratified over each ray's segment inside the field's
domain ``[-DOMAIN, DOMAIN]³`` and jittered per step, so a thin part is not skipped between samples.

A network's field answers such a term globally: a decoder pushed to empty a gap erodes the whole
back it belongs to. :class:`OccupancyGrid` is the local alternative — the field's values on the
nodes of a grid, trilinear in between, each node free — started from the network's field, so that
carving one gap moves only the nodes around it.
"""

from __future__ import annotations

import torch

from ngp_mi.camera import Camera
from ngp_mi.geometry.extract import Field, default_coarse, field_grid, grid_mesh
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.occupancy import DOMAIN


class OccupancyGrid(torch.nn.Module):
    """An occupancy field given by its values on the ``(R+1)³`` nodes over ``[-DOMAIN, DOMAIN]³``
    (indexed [i, j, k] ↔ (x, y, z), as :func:`~ngp_mi.geometry.extract.field_grid` writes them),
    trilinear in between: differentiable in the values and the points."""

    def __init__(self, values: torch.Tensor, half: float = DOMAIN):
        super().__init__()
        self.values = torch.nn.Parameter(torch.as_tensor(values, dtype=torch.float32).clone())
        self.half = half

    @classmethod
    def from_field(cls, field: Field, resolution: int, level: float, half: float = DOMAIN) -> "OccupancyGrid":
        """The grid of ``field``'s values (coarse to fine: exact near the level set)."""
        return cls(torch.from_numpy(field_grid(field, resolution, default_coarse(resolution), level, half)[0]), half)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(P, 3) → (P,) trilinear values."""
        volume = self.values.permute(2, 1, 0)[None, None]  # grid_sample reads (D, H, W) = (z, y, x)
        where = (points.to(volume.dtype) / self.half).reshape(1, -1, 1, 1, 3)
        return torch.nn.functional.grid_sample(volume, where, align_corners=True).reshape(-1)

    def mesh(self, level: float) -> TriangleMesh | None:
        """Marching cubes of the node values (inside above ``level``); None when empty."""
        return grid_mesh(self.values.detach().numpy(), level, self.half, inside_above=True, name="occupancy grid")


def pixel_ray_segments(camera: Camera, pixels: torch.Tensor, half: float = DOMAIN
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """World-space unit rays through the centres of ``pixels`` (P,) (flat indices y·W + x) and their
    segment [t0, t1] inside the cube ``[-half, half]³`` (slab test); returns origin (3,), directions
    (P, 3), t0, t1 (P,) with t1 ≤ t0 for a ray that misses the cube."""
    local = torch.from_numpy(camera.pixel_rays().reshape(-1, 3))[pixels]  # camera space, z = 1
    direction = local @ torch.as_tensor(camera.R, dtype=torch.float64)  # Rᵀ · local, camera → world
    direction = direction / direction.norm(dim=-1, keepdim=True)
    origin = torch.as_tensor(camera.position, dtype=torch.float64)
    safe = torch.where(direction.abs() < 1e-12, torch.full_like(direction, 1e-12), direction)
    near, far = (-half - origin) / safe, (half - origin) / safe
    t0 = torch.minimum(near, far).amax(-1).clamp_min(0.0)
    t1 = torch.maximum(near, far).amin(-1)
    return origin, direction, t0, t1


def ray_samples(camera: Camera, pixels: torch.Tensor, samples: int, generator: torch.Generator,
                half: float = DOMAIN) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, S, 3) float32 points stratified over each pixel ray's segment inside the cube, jittered
    by ``generator``; and a (P,) bool: the ray meets the cube (the others' points are meaningless)."""
    origin, direction, t0, t1 = pixel_ray_segments(camera, pixels, half)
    length = (t1 - t0).clamp_min(0.0)
    u = (torch.arange(samples, dtype=torch.float64) + torch.rand(len(pixels), samples, generator=generator,
                                                                  dtype=torch.float64)) / samples
    t = t0[:, None] + u * length[:, None]
    return (origin + t[..., None] * direction[:, None]).float(), t1 > t0


def disagreement_pixels(coverage: torch.Tensor, target: torch.Tensor, count: int,
                        generator: torch.Generator) -> torch.Tensor:
    """Up to ``count`` flat pixel indices of one view, drawn at random where the thresholded coverage
    (H, W) and target mask (H, W) differ."""
    wrong = ((coverage > 0.5) != (target > 0.5)).flatten().nonzero()[:, 0]
    if len(wrong) > count:
        wrong = wrong[torch.randperm(len(wrong), generator=generator)[:count]]
    return wrong


def ray_silhouette_terms(field, cameras: list[Camera], coverage: torch.Tensor, target: torch.Tensor,
                         rays_per_view: int = 128, samples: int = 64, level: float = 0.5, margin: float = 0.05,
                         seed: int = 0) -> dict[str, torch.Tensor]:
    """The ``free`` and ``hit`` terms of the module docstring, summed over the views' rays (each
    term a mean over its rays), for ``field`` (P, 3) → (P,) occupancy, differentiable in its
    parameters. ``coverage`` (N, 1, H, W) is the current mesh's (where to look), ``target`` the
    masks. Zero terms when no pixel disagrees."""
    generator = torch.Generator().manual_seed(seed)
    points, kinds = [], []
    for i, camera in enumerate(cameras):
        pixels = disagreement_pixels(coverage[i, 0].detach(), target[i, 0], rays_per_view, generator)
        if len(pixels) == 0:
            continue
        p, meets = ray_samples(camera, pixels, samples, generator)
        background = target[i, 0].flatten()[pixels] <= 0.5
        points.append(p[meets])
        kinds.append(background[meets])
    if not points:
        return {"free": torch.zeros(()), "hit": torch.zeros(())}
    p, background = torch.cat(points), torch.cat(kinds)
    occupancy = field(p.reshape(-1, 3)).reshape(len(p), samples)
    free = torch.relu(occupancy[background] - level + margin).mean(-1)
    hit = torch.relu(level + margin - occupancy[~background].amax(-1))
    zero = occupancy.sum() * 0.0
    return {"free": free.mean() if len(free) else zero, "hit": hit.mean() if len(hit) else zero}
