"""Geometry sources: triangle meshes, their validation and normalisation, simple built-in shapes."""

from ngp_mi.geometry.mesh import NORMALIZED_RADIUS, TriangleMesh, normalize_mesh

__all__ = ["NORMALIZED_RADIUS", "TriangleMesh", "normalize_mesh"]
