"""``direct_unshadowed``: direct illumination from every emitter with no visibility test.

    L(x, ω_o) = Σ_e f(x, ω_e, ω_o) cos θ_e E_e        (no shadow rays, no indirect light)

for delta emitters (directional, point), where ``emitter.sample_direction`` returns the incident
irradiance. It is the physically based counterpart of the deferred renderers R_diff / R_BP, which
see neither shadows nor interreflections: comparing it with Mitsuba's ``direct`` (shadows) and
``path`` (interreflection) integrators measures what each effect contributes to an image.
"""

from __future__ import annotations

from typing import Any

from ngp_mi import backend

mi = backend.mitsuba()
dr = backend.drjit()


class DirectUnshadowedIntegrator(mi.SamplingIntegrator):
    def __init__(self, props: Any):
        super().__init__(props)

    def sample(self, scene: Any, sampler: Any, ray: Any, medium: Any = None, active: Any = True) -> tuple:
        si = scene.ray_intersect(ray, active)
        valid = active & si.is_valid()
        bsdf = si.bsdf(ray)
        context = mi.BSDFContext()
        radiance = mi.Spectrum(0.0)
        for emitter in scene.emitters():
            ds, irradiance = emitter.sample_direction(si, sampler.next_2d(valid), valid)
            value = bsdf.eval(context, si, si.to_local(ds.d), valid)  # includes the cosine
            radiance += dr.select(valid & (ds.pdf > 0), value * irradiance, 0.0)
        return radiance, valid, []

