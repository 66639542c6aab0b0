"""Maps derived from a depth map through the camera (torch, differentiable, batched NCHW).

* :func:`backproject` — camera-space points ``z · K⁻¹ [u, v, 1]`` at pixel centres.
* :func:`noc_from_depth` — the paper's ``NOC(d, K, E)`` (Sec. 3.4): world points normalised by a
  bounding box, used as G_da's input and in the NOC adversarial and cycle losses (App. B).
* :func:`normals_from_depth` — camera-space normals by central differences of the back-projected
  points (the paper's "NGP w/o G_n" baseline computes normals from the coarse depth).
* :func:`smooth_depth` — a masked Gaussian blur: a coarse depth made from a detailed one.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from ngp_mi.camera import Camera


def _per_view(cameras: Camera | Sequence[Camera], batch: int) -> list[Camera]:
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if len(cameras) == 1:
        cameras = cameras * batch
    if len(cameras) != batch:
        raise ValueError(f"got {len(cameras)} cameras for a batch of {batch}")
    return cameras


def backproject(depth: torch.Tensor, cameras: Camera | Sequence[Camera]) -> torch.Tensor:
    """(N, 1, H, W) z-depth → (N, 3, H, W) camera-space points (OpenCV axes)."""
    n, _, h, w = depth.shape
    rays = torch.stack([torch.as_tensor(c.pixel_rays(), dtype=depth.dtype, device=depth.device)
                        for c in _per_view(cameras, n)])  # (N, H, W, 3)
    return depth * rays.permute(0, 3, 1, 2)


def noc_from_depth(depth: torch.Tensor, mask: torch.Tensor, cameras: Camera | Sequence[Camera],
                   bounds: np.ndarray | torch.Tensor) -> torch.Tensor:
    """NOC(d, K, E): world points ``Rᵀ (x_cam − t)`` mapped by ``bounds`` (2, 3) to [0, 1]³, 0 off the mask."""
    cams = _per_view(cameras, depth.shape[0])
    as_tensor = lambda a: torch.as_tensor(np.stack(a), dtype=depth.dtype, device=depth.device)  # noqa: E731
    bounds = torch.as_tensor(bounds, dtype=depth.dtype, device=depth.device)
    return noc_from_depth_batch(depth, mask, as_tensor([c.K for c in cams]), as_tensor([c.E for c in cams]),
                                bounds.expand(depth.shape[0], 2, 3))


def noc_from_depth_batch(depth: torch.Tensor, mask: torch.Tensor, K: torch.Tensor, E: torch.Tensor,
                         bounds: torch.Tensor) -> torch.Tensor:
    """:func:`noc_from_depth` with per-sample tensors: K (N, 3, 3), E (N, 3, 4), bounds (N, 2, 3)."""
    n, _, h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5,
                          torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5, indexing="ij")
    f, cx, cy = K[:, 0, 0].reshape(n, 1, 1), K[:, 0, 2].reshape(n, 1, 1), K[:, 1, 2].reshape(n, 1, 1)
    rays = torch.stack([(u - cx) / f, (v - cy) / f, torch.ones_like(u).expand(n, h, w)], dim=1)
    points = depth * rays
    R, t = E[:, :, :3], E[:, :, 3]
    world = torch.einsum("nji,njhw->nihw", R, points - t[:, :, None, None])
    lo, hi = bounds[:, 0].reshape(n, 3, 1, 1), bounds[:, 1].reshape(n, 3, 1, 1)
    return (world - lo) / torch.clamp(hi - lo, min=1e-12) * (mask > 0)


def normals_from_depth(depth: torch.Tensor, mask: torch.Tensor, cameras: Camera | Sequence[Camera]) -> torch.Tensor:
    """Camera-space unit normals from central differences of back-projected points, facing the camera.

    Pixels whose 4-neighbourhood leaves the mask use one-sided differences towards the inside;
    background pixels are 0.
    """
    points = backproject(depth, cameras)
    inside = (mask > 0).to(depth.dtype)

    def derivative(axis: int) -> torch.Tensor:
        # Central difference where both neighbours are on the object, else one-sided.
        fwd = torch.roll(points, -1, axis) - points
        bwd = points - torch.roll(points, 1, axis)
        ok_f = torch.roll(inside, -1, axis) * inside
        ok_b = torch.roll(inside, 1, axis) * inside
        both = ok_f * ok_b
        return both * 0.5 * (fwd + bwd) + (ok_f - both) * fwd + (ok_b - both) * bwd

    du, dv = derivative(3), derivative(2)
    normal = torch.cross(du, dv, dim=1)
    normal = normal / torch.clamp(normal.norm(dim=1, keepdim=True), min=1e-12)
    facing = (normal * points).sum(1, keepdim=True) > 0
    return torch.where(facing, -normal, normal) * inside


def smooth_depth(depth: torch.Tensor, mask: torch.Tensor, sigma: float) -> torch.Tensor:
    """Masked Gaussian smoothing (normalised convolution): background stays 0 and does not bleed in."""
    if sigma <= 0:
        return depth
    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=depth.dtype, device=depth.device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()

    def blur(image: torch.Tensor) -> torch.Tensor:
        image = torch.nn.functional.conv2d(image, kernel.reshape(1, 1, 1, -1), padding=(0, radius))
        return torch.nn.functional.conv2d(image, kernel.reshape(1, 1, -1, 1), padding=(radius, 0))

    weight = blur(mask)
    return torch.where(mask > 0, blur(depth * mask) / weight.clamp_min(1e-8), torch.zeros_like(depth))
