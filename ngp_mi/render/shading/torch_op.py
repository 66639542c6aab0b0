"""The torch backend of :func:`ngp_mi.render.shading.shade`: the shared maths on NCHW tensors, plain autograd.

It is the reference the Dr.Jit kernel is tested against, and the path for inputs that need a
second derivative (Dr.Jit's op is once-differentiable).
"""

from __future__ import annotations

import functools
from typing import Any

import torch

from ngp_mi.render.shading.blinn_phong import (
    TORCH_OPS,
    Vec,
    blinn_phong_radiance,
    point_light_incidence,
    safe_normalize,
)


@functools.lru_cache(maxsize=32)
def intrinsics_tensor(rows: tuple, dtype: torch.dtype, device: str) -> torch.Tensor:
    """The rows as a (B, 3) tensor, made once per camera set (never modified)."""
    return torch.tensor(rows, dtype=dtype, device=device)


def torch_shade(normal, albedo, mask, depth, intr, lights: Any, alpha, spec_albedo, opts) -> torch.Tensor:
    """R_BP / R_diff of NCHW maps; ``intr`` (B, 3) rows (f, cx, cy), ``lights`` a ``CameraLights``."""
    ops = TORCH_OPS
    n, _, h, w = normal.shape

    def comps(x: torch.Tensor) -> Vec:
        return (x[:, 0:1], x[:, 1:2], x[:, 2:3])

    def light_comps(x: torch.Tensor, i: int) -> Vec:
        return tuple(x[:, i, k].reshape(-1, 1, 1, 1) for k in range(3))  # type: ignore[return-value]

    need_rays = opts["view"] == "per_pixel" or lights.positions.shape[1] > 0
    if need_rays:
        v, u = torch.meshgrid(torch.arange(h, dtype=normal.dtype, device=normal.device) + 0.5,
                              torch.arange(w, dtype=normal.dtype, device=normal.device) + 0.5, indexing="ij")
        f, cx, cy = (intr[:, k].reshape(-1, 1, 1, 1) for k in range(3))
        ray = ((u - cx) / f, (v - cy) / f, torch.ones_like(u).expand(intr.shape[0], 1, h, w))
    view = safe_normalize(ops, tuple(-c for c in ray)) if opts["view"] == "per_pixel" else (0.0, 0.0, -1.0)

    directions = torch.stack(safe_normalize(ops, lights.directions.unbind(-1)), dim=-1)  # once per (image, light)
    light_list = [(light_comps(directions, i), light_comps(lights.irradiance, i)) for i in range(directions.shape[1])]
    if lights.positions.shape[1] > 0:
        position = tuple(depth * r for r in ray)
        for i in range(lights.positions.shape[1]):
            light_list.append(point_light_incidence(ops, position, light_comps(lights.positions, i),
                                                    light_comps(lights.intensity, i)))
    spec = None
    if opts["mode"] == "blinn_phong":
        spec = comps(spec_albedo) if isinstance(spec_albedo, torch.Tensor) else (spec_albedo,) * 3
    rgb = blinn_phong_radiance(ops, comps(normal), view, light_list, comps(albedo), opts["k_d"], spec,
                               opts["k_s"], alpha)
    out = torch.cat([c.expand(n, 1, h, w) for c in rgb], dim=1)
    return out * mask if mask is not None else out
