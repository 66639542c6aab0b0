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

from typing import Any

from ngp_mi import backend
from ngp_mi.camera import Camera

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
