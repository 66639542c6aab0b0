"""The project's own Mitsuba integrators, one per file, registered by name (as Mitsuba's ``python/ad/integrators``).

* ``depth_projective`` (:mod:`.depth_projective`) — pixel-averaged z-depth and coverage with
  primary-visibility (silhouette) derivatives: Π_v's silhouette mode.
* ``direct_unshadowed`` (:mod:`.direct_unshadowed`) — direct light without shadow rays: the
  physically based counterpart of R_diff / R_BP in ``compare``.

:func:`register` makes them known to Mitsuba; it is idempotent, and :func:`ngp_mi.render.scene.build_scene`
calls it, so a scene dictionary may name them.
"""

from __future__ import annotations

from ngp_mi import backend

_registered = False


def register() -> None:
    """Register every integrator of this package with Mitsuba (once per process)."""
    global _registered
    if _registered:
        return
    # Imported here, not at the top: their classes subclass Mitsuba's, so importing them loads Mitsuba.
    from ngp_mi.render.integrators.depth_projective import DepthProjectiveIntegrator
    from ngp_mi.render.integrators.direct_unshadowed import DirectUnshadowedIntegrator

    mi = backend.mitsuba()
    mi.register_integrator("depth_projective", lambda props: DepthProjectiveIntegrator(props))
    mi.register_integrator("direct_unshadowed", lambda props: DirectUnshadowedIntegrator(props))
    _registered = True
