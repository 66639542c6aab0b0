"""``depth_projective``: pixel-averaged z-depth and coverage with silhouette derivatives.

A Mitsuba projective-sampling integrator (base class ``PSIntegrator``, as ``direct_projective``)
whose "radiance" is the vector ``(z, 1, 0)`` on the object and ``(0, 0, 0)`` elsewhere, where
``z = (p − c)·f`` is the depth of the first hit p along the optical axis f of a camera centred at c.
With a box pixel filter, channel R of the image is the pixel-averaged depth

    D_p = (1/A_p) ∫_{pixel p} z(x) 1[hit](x) dx

and channel G the coverage M_p = (1/A_p) ∫ 1[hit](x) dx. Their derivatives w.r.t. scene
parameters θ have two parts (Reynolds transport):

    ∂D_p/∂θ = (1/A_p) ∫ ∂z/∂θ 1[hit] dx  +  (1/A_p) ∫_{∂Ω ∩ p} (z_fg − z_bg) (∂x_∂Ω/∂θ · n) dl

The interior term is differentiated through ``scene.ray_intersect`` (``radiative_backprop`` is
off). The boundary term is Mitsuba's primary-visibility projective sampling: silhouette points
``ss`` are sampled on mesh edges, :meth:`sample_radiance_difference` returns the jump
``(z_fg − z_bg, 1 − 1[bg hit], 0)`` across the silhouette, and ``PSIntegrator`` multiplies it by
the silhouette's normal motion and the sensor Jacobian. Only primary visibility matters for a
depth map, so indirect silhouettes are disabled (``sppi = 0``).
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.render.scene import set_sensor_camera

mi = backend.mitsuba()
dr = backend.drjit()


class DepthProjectiveIntegrator(mi.ad.integrators.common.PSIntegrator):
    """Pixel-averaged z-depth (R) and coverage (G) with primary-visibility derivatives."""

    def __init__(self, props: Any):
        super().__init__(props)
        self.max_depth = 1
        self.rr_depth = 1
        self.radiative_backprop = False  # the interior derivative is plain AD through the hit point
        self.sppi = 0  # a depth map has no indirect visibility
        # Camera centre and optical axis; opaque so that a new view does not recompile kernels.
        self.camera_center = dr.opaque(mi.Point3f, 0.0)
        self.camera_axis = dr.opaque(mi.Vector3f, [0.0, 0.0, 1.0])

    def set_camera(self, camera: Camera) -> None:
        self.camera_center = dr.opaque(mi.Point3f, [float(x) for x in camera.position])
        self.camera_axis = dr.opaque(mi.Vector3f, [float(x) for x in camera.forward])

    def depth_value(self, p: Any, hit: Any) -> Any:
        """The integrand ``(z, 1, 0)`` at hit points and 0 elsewhere, as a Spectrum."""
        z = dr.dot(p - self.camera_center, self.camera_axis)
        return dr.select(hit, mi.Spectrum(z, 1.0, 0.0), mi.Spectrum(0.0))

    def sample(self, mode: Any, scene: Any, sampler: Any, ray: Any, depth: Any = None, δL: Any = None,
               state_in: Any = None, active: Any = True, project: bool = False, si_shade: Any = None,
               **kwargs: Any) -> tuple[Any, Any, list, Any]:
        primal = mode == dr.ADMode.Primal
        if si_shade is not None:
            si = si_shade
        else:
            with dr.resume_grad(when=not primal):
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
        hit = active & si.is_valid()
        with dr.resume_grad(when=not primal):
            value = self.depth_value(si.p, hit)
        return value, hit, [], None

    def sample_radiance_difference(self, scene: Any, ss: Any, curr_depth: Any, sampler: Any,
                                   wavelengths: Any, active: Any) -> tuple[Any, Any]:
        # Background: continue the camera ray past the silhouette point.
        si_bg = scene.ray_intersect(ss.spawn_ray(wavelengths), active=active)
        background = self.depth_value(si_bg.p, active & si_bg.is_valid())
        # Foreground: the silhouette point itself.
        foreground = self.depth_value(ss.p, active)
        difference = foreground - background
        return difference, active & (dr.max(dr.abs(difference)) > 0)

    def sample_importance(self, *args: Any, **kwargs: Any) -> Any:  # pragma: no cover - sppi = 0
        raise NotImplementedError("depth_projective has no indirect silhouettes")


mi.register_integrator("depth_projective", lambda props: DepthProjectiveIntegrator(props))


class _SilhouetteRenderer:
    """One integrator and one box-filtered sensor per resolution, moved between views."""

    def __init__(self, camera: Camera, spp: int):
        self.integrator = mi.load_dict({"type": "depth_projective"})
        sensor = camera.to_mitsuba(spp=spp, rfilter="box")
        sensor["film"]["sample_border"] = True  # shapes entering / leaving the frame
        self.sensor = mi.load_dict(sensor)


_renderers: dict[tuple[int, int, int], _SilhouetteRenderer] = {}


def _renderer(camera: Camera, spp: int) -> _SilhouetteRenderer:
    key = (camera.width, camera.height, spp)
    if key not in _renderers:
        _renderers[key] = _SilhouetteRenderer(camera, spp)
    return _renderers[key]


class _RenderDepthCoverage(torch.autograd.Function):
    @staticmethod
    def forward(ctx, projector: Any, cameras: Sequence[Camera], spp: int, boundary_spp: int, seed: int,
                vertices: torch.Tensor):  # type: ignore[override]
        projector.set_vertices(vertices)
        images = []
        for i, camera in enumerate(cameras):
            r = _renderer(camera, spp)
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
        (vertices,) = ctx.saved_tensors
        projector = ctx.projector
        positions = projector.set_vertices(vertices, requires_grad=True)
        zero = torch.zeros_like(g_depth[:, 0])
        for i, camera in enumerate(ctx.cameras):
            r = _renderer(camera, ctx.spp)
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

