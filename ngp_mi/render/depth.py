"""Depth projection Π_v (paper Sec. 3.3): a mesh and cameras → z-depth, mask, normal and NOC maps.

``d := K E p`` for every visible surface point p. Two modes, both differentiable w.r.t. the mesh
vertices through Mitsuba / Dr.Jit and wrapped as torch autograd functions:

* ``silhouette_grad=False`` (fast path): one ray per pixel *centre*, all views in one ray cast.
  Interior derivatives come from Mitsuba's differentiable intersection (``si.t``, ``si.p``,
  ``si.n``); the maps are point samples, so moving a silhouette has no derivative.
* ``silhouette_grad=True``: the :class:`DepthProjectiveIntegrator` renders the *pixel-averaged*
  depth ``(1/A) ∫_pixel z(x) 1[hit](x) dx`` and coverage with ``spp`` jittered samples (box
  filter), and adds the primary-visibility boundary term by Mitsuba's projective sampling of
  silhouette edges. Averaged depth blends hit and miss at the silhouette; divide by coverage for
  the mean depth of the covered part.

Conventions (README): z-depth along the optical axis (not ray length), background depth 0 and
mask 0; normals are camera-space geometric (face) normals flipped to face the camera; NOC is the
world-space point normalised by the mesh's bounding box to [0, 1]³.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, Sequence

import numpy as np
import torch

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.render import integrators
from ngp_mi.render.rays import camera_table, pixel_centre_rays
from ngp_mi.render.scene import MESH_POSITIONS, mitsuba_mesh, set_sensor_camera

_MESH_KEY = "mesh"


@dataclasses.dataclass
class DepthMaps:
    """Maps of one projection, NCHW float32 (float tensors keep gradients w.r.t. the vertices)."""

    depth: torch.Tensor   # (N, 1, H, W) z-depth, 0 on background (pixel-averaged with silhouettes)
    mask: torch.Tensor    # (N, 1, H, W) 1 on the object (coverage in [0, 1] with silhouettes)
    normal: torch.Tensor  # (N, 3, H, W) camera-space geometric normals facing the camera, 0 on background
    noc: torch.Tensor     # (N, 3, H, W) normalised object coordinates in [0, 1]³, 0 on background


class MeshProjector:
    """A Mitsuba scene around one mesh topology; vertex positions change between calls.

    Changing only the vertex positions rebuilds the acceleration structure in place and reuses
    the compiled kernels (camera parameters are kernel inputs, not literals).
    """

    def __init__(self, faces: np.ndarray, num_vertices: int):
        mi = backend.mitsuba()
        self.faces = np.ascontiguousarray(faces, np.int32)
        self.num_vertices = int(num_vertices)
        placeholder = np.zeros((self.num_vertices, 3), np.float32)
        self.scene = mi.load_dict({"type": "scene", _MESH_KEY: mitsuba_mesh(placeholder, self.faces, _MESH_KEY)})
        self.params = mi.traverse(self.scene)
        self.key = f"{_MESH_KEY}.{MESH_POSITIONS}"

    def set_vertices(self, vertices: torch.Tensor, requires_grad: bool = False) -> Any:
        """Upload positions (V, 3); returns the Dr.Jit array (grad-enabled when asked)."""
        mi, dr = backend.mitsuba(), backend.drjit()
        if tuple(vertices.shape) != (self.num_vertices, 3):
            raise ValueError(f"vertices must be ({self.num_vertices}, 3) for this mesh, got {tuple(vertices.shape)}")
        positions = mi.Float(vertices.detach().to(torch.float32).contiguous().reshape(-1))
        if requires_grad:
            dr.enable_grad(positions)
        self.params[self.key] = positions
        self.params.update()
        return positions

    def trace(self, table: np.ndarray, width: int, height: int) -> tuple[Any, ...]:
        """Cast one ray per pixel centre of every view; Dr.Jit arrays (z, mask, normal, position).

        Lanes as in :func:`~ngp_mi.render.rays.pixel_centre_rays`; z = t / |K⁻¹ [u, v, 1]|.
        """
        mi, dr = backend.mitsuba(), backend.drjit()
        rays = pixel_centre_rays(table, width, height)
        si = self.scene.ray_intersect(rays.ray, ray_flags=mi.RayFlags.All, coherent=True)
        hit = si.is_valid()
        z = dr.select(hit, si.t * rays.inv_len, 0.0)
        normal = rays.R @ si.n  # world → camera
        normal = dr.select(dr.dot(normal, rays.local) > 0, -normal, normal)  # face the camera
        normal = dr.select(hit, normal, mi.Vector3f(0.0))
        position = dr.select(hit, si.p, mi.Point3f(0.0))
        return z, mi.Float(hit), normal, position


def _to_torch_maps(arrays: Sequence[Any], n: int, height: int, width: int,
                   device: torch.device) -> list[torch.Tensor]:
    """Dr.Jit (lane-major) arrays → NCHW torch tensors on ``device`` (scalars: 1 channel, 3-vectors: 3).

    The Mitsuba variant decides where Dr.Jit computes (CUDA or CPU); results follow the caller's
    ``vertices`` instead, so that the operator composes with torch code on either device.
    """
    dr = backend.drjit()
    out = []
    for a in arrays:
        channels = [a[k] for k in range(3)] if dr.depth_v(a) > 1 else [a]
        out.append(torch.stack([c.torch().reshape(n, height, width) for c in channels], dim=1).to(device))
    return out


class _ProjectFast(torch.autograd.Function):
    """torch autograd around :meth:`MeshProjector.trace`; backward re-traces with AD enabled."""

    @staticmethod
    def forward(ctx, projector: MeshProjector, table: np.ndarray, width: int, height: int,
                vertices: torch.Tensor):  # type: ignore[override]
        dr = backend.drjit()
        projector.set_vertices(vertices)
        arrays = projector.trace(table, width, height)
        dr.eval(*arrays)  # before any later params.update() changes the geometry under lazy rays
        z, hit, normal, position = _to_torch_maps(arrays, len(table), height, width, vertices.device)
        ctx.projector, ctx.table, ctx.size = projector, table, (width, height)
        ctx.save_for_backward(vertices)
        ctx.mark_non_differentiable(hit)
        return z, hit, normal, position

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_z, g_hit, g_normal, g_position):  # type: ignore[override]
        mi, dr = backend.mitsuba(), backend.drjit()
        (vertices,) = ctx.saved_tensors
        width, height = ctx.size
        positions = ctx.projector.set_vertices(vertices, requires_grad=True)
        z, _, normal, position = ctx.projector.trace(ctx.table, width, height)

        def lanes(g: torch.Tensor) -> list[Any]:  # NCHW gradient → per-channel lane arrays
            g = g.detach().to(torch.float32)
            return [mi.Float(g[:, c].contiguous().reshape(-1)) for c in range(g.shape[1])]

        dr.set_grad(z, lanes(g_z)[0])
        dr.set_grad(normal, mi.Vector3f(*lanes(g_normal)))
        dr.set_grad(position, mi.Vector3f(*lanes(g_position)))
        dr.enqueue(dr.ADMode.Backward, z, normal, position)
        dr.traverse(dr.ADMode.Backward)
        grad = dr.grad(positions).torch().reshape(-1, 3).to(vertices.device, vertices.dtype)
        dr.disable_grad(positions)
        return None, None, None, None, grad


_projectors: dict[str, MeshProjector] = {}


def projector_for(faces: np.ndarray | torch.Tensor, num_vertices: int) -> MeshProjector:
    """A cached :class:`MeshProjector` per topology (faces content and vertex count)."""
    faces = np.ascontiguousarray(faces.cpu().numpy() if isinstance(faces, torch.Tensor) else faces, np.int32)
    key = f"{num_vertices}:{faces.shape}:{hashlib.sha1(faces.tobytes()).hexdigest()}"
    if key not in _projectors:
        if len(_projectors) >= 8:
            _projectors.pop(next(iter(_projectors)))
        _projectors[key] = MeshProjector(faces, num_vertices)
    return _projectors[key]


class SilhouetteRenderer:
    """The ``depth_projective`` integrator and one box-filtered sensor of one resolution, moved between views."""

    def __init__(self, camera: Camera, spp: int):
        mi = backend.mitsuba()
        integrators.register()
        self.integrator = mi.load_dict({"type": "depth_projective"})
        sensor = camera.to_mitsuba(spp=spp, rfilter="box")
        sensor["film"]["sample_border"] = True  # shapes entering / leaving the frame
        self.sensor = mi.load_dict(sensor)


_renderers: dict[tuple[int, int, int], SilhouetteRenderer] = {}


def silhouette_renderer(camera: Camera, spp: int) -> SilhouetteRenderer:
    """The cached :class:`SilhouetteRenderer` of a resolution and sample count."""
    key = (camera.width, camera.height, spp)
    if key not in _renderers:
        _renderers[key] = SilhouetteRenderer(camera, spp)
    return _renderers[key]


class _RenderDepthCoverage(torch.autograd.Function):
    """torch autograd around the ``depth_projective`` integrator's render / render_backward, view by view."""

    @staticmethod
    def forward(ctx, projector: Any, cameras: Sequence[Camera], spp: int, boundary_spp: int, seed: int,
                vertices: torch.Tensor):  # type: ignore[override]
        projector.set_vertices(vertices)
        images = []
        for i, camera in enumerate(cameras):
            r = silhouette_renderer(camera, spp)
            set_sensor_camera(r.sensor, camera)
            r.integrator.set_camera(camera)
            image = r.integrator.render(projector.scene, r.sensor, seed=seed + i, spp=spp)
            images.append(image.torch()[..., :2].permute(2, 0, 1))
        ctx.projector, ctx.cameras, ctx.spp, ctx.boundary_spp, ctx.seed = projector, list(cameras), spp, boundary_spp, seed
        ctx.save_for_backward(vertices)
        out = torch.stack(images).to(vertices.device)
        return out[:, :1].contiguous(), out[:, 1:2].contiguous()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_depth, g_mask):  # type: ignore[override]
        mi, dr = backend.mitsuba(), backend.drjit()
        (vertices,) = ctx.saved_tensors
        projector = ctx.projector
        positions = projector.set_vertices(vertices, requires_grad=True)
        zero = torch.zeros_like(g_depth[:, 0])
        for i, camera in enumerate(ctx.cameras):
            r = silhouette_renderer(camera, ctx.spp)
            set_sensor_camera(r.sensor, camera)
            r.integrator.set_camera(camera)
            grad_image = torch.stack([g_depth[i, 0], g_mask[i, 0], zero[i]], dim=-1).to(torch.float32).contiguous()
            # A runtime spp would override both counts; with 0 the integrator's own are used.
            r.integrator.sppc, r.integrator.sppp = ctx.spp, ctx.boundary_spp
            r.integrator.render_backward(projector.scene, projector.params, mi.TensorXf(grad_image),
                                         r.sensor, seed=ctx.seed + i, spp=0)
        grad = dr.grad(projector.params[projector.key]).torch().reshape(-1, 3).to(vertices.device, vertices.dtype)
        dr.disable_grad(positions)
        return None, None, None, None, None, grad


def render_depth_coverage(projector: Any, vertices: torch.Tensor, cameras: Sequence[Camera], spp: int = 8,
                          boundary_spp: int | None = None, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-averaged depth and coverage, (N, 1, H, W) each, differentiable including silhouettes.

    ``spp`` samples per pixel estimate the maps and their interior derivative; ``boundary_spp``
    (default: ``max(1, spp // 4)``) per pixel sample the silhouette edges. The boundary term
    dominates the cost (its samples scale with the image area, not the silhouette length), so a
    small ``boundary_spp`` buys most of the speed. Its variance is high when the loss gradient is a
    small difference of opposite silhouettes (a sideways move); ``bench/bench_depth.py``
    tabulates bias, spread and time per ``boundary_spp``.
    """
    boundary_spp = max(1, spp // 4) if boundary_spp is None else boundary_spp
    if spp < 1 or boundary_spp < 1:
        raise ValueError(f"spp and boundary_spp must be >= 1, got {spp} and {boundary_spp}")
    return _RenderDepthCoverage.apply(projector, list(cameras), int(spp), int(boundary_spp), int(seed), vertices)


def normalized_object_coordinates(position: torch.Tensor, mask: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """NOC: world positions (N, 3, H, W) mapped by the vertices' bounding box to [0, 1]³, 0 off the mask."""
    lo = vertices.min(0).values.reshape(1, 3, 1, 1)
    hi = vertices.max(0).values.reshape(1, 3, 1, 1)
    return (position - lo) / torch.clamp(hi - lo, min=1e-8) * (mask > 0)


def project_depth(vertices: torch.Tensor, faces: np.ndarray | torch.Tensor, cameras: Camera | Sequence[Camera],
                  silhouette_grad: bool = False, spp: int = 8, boundary_spp: int | None = None,
                  seed: int = 0) -> DepthMaps:
    """Π_v: project a triangle mesh into depth, mask, normal and NOC maps for each camera.

    Args:
        vertices: (V, 3) world positions; may require grad.
        faces: (F, 3) vertex indices.
        cameras: one camera or a list (all of one resolution).
        silhouette_grad: add visibility (silhouette) derivatives; depth and mask are then
            pixel-averaged over ``spp`` jittered samples (see the module docstring).
        spp, boundary_spp, seed: samples per pixel for the maps and their interior derivative,
            for the silhouette (boundary) term (default ``max(1, spp // 4)``), and the seed;
            silhouette mode only. The defaults (8, 2) keep a forward + backward pass at 128²
            within 40 ms on 2 CPU cores; ``bench/RESULTS.md`` tabulates time against gradient
            error for other settings.
    """
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if not cameras:
        raise ValueError("project_depth: no cameras given")
    width, height = cameras[0].width, cameras[0].height
    if any((c.width, c.height) != (width, height) for c in cameras):
        raise ValueError("project_depth: all cameras must share one resolution")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"project_depth: vertices must be (V, 3), got {tuple(vertices.shape)}")
    if not torch.isfinite(vertices).all():
        raise ValueError("project_depth: vertices contain non-finite values")
    projector = projector_for(faces, vertices.shape[0])
    z, hit, normal, position = _ProjectFast.apply(projector, camera_table(cameras), width, height, vertices)
    noc = normalized_object_coordinates(position, hit, vertices)
    if silhouette_grad:
        z, hit = render_depth_coverage(projector, vertices, cameras, spp=spp, boundary_spp=boundary_spp, seed=seed)
    return DepthMaps(depth=z, mask=hit, normal=normal, noc=noc)


def depth_of_hits(depth: torch.Tensor, coverage: torch.Tensor, min_coverage: float = 1e-3) -> torch.Tensor:
    """The mean depth of a pixel's covered samples, d̄ / c, from silhouette mode's pixel-averaged
    depth d̄ and coverage c (0 where c < ``min_coverage``: the ratio of two noisy near-zero values is
    noise); what networks trained on depth maps read, with c as the mask."""
    return torch.where(coverage > min_coverage, depth / coverage.clamp_min(min_coverage), torch.zeros_like(depth))


def supersampled_depth_coverage(vertices: torch.Tensor, faces: np.ndarray | torch.Tensor, camera: Camera,
                                factor: int, phase: tuple[float, float] = (0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference pixel-averaged depth and coverage (1, 1, H, W), float64, without any sampling noise.

    Pixel-centre projection at ``factor`` × the resolution, average-pooled. ``phase`` shifts the
    sub-sample grid (in sub-samples, within ±0.5): a fixed grid is a biased reference for edges
    aligned with it (vertical legs, horizontal backs), since a small move crosses a quantised
    number of sub-sample rows; averaging finite differences over random phases removes the bias.
    """
    big = camera.with_resolution(camera.width * factor, camera.height * factor)
    big = dataclasses.replace(big, cx=big.cx + phase[0], cy=big.cy + phase[1])
    with torch.no_grad():
        out = project_depth(vertices.detach().float(), faces, big)
    pool = torch.nn.functional.avg_pool2d
    return pool(out.depth.double(), factor), pool(out.mask.double(), factor)
