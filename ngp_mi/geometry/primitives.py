"""Small built-in shapes made of boxes: enough for the first demo and for tests."""

from __future__ import annotations

import numpy as np

from ngp_mi.geometry.mesh import TriangleMesh, normalize_mesh

# The 8 corners of [-1, 1]^3 and 12 outward-facing (counter-clockwise) triangles.
_CUBE_VERTICES = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
_CUBE_FACES = np.array([
    [0, 1, 3], [0, 3, 2],  # -x
    [4, 6, 7], [4, 7, 5],  # +x
    [0, 4, 5], [0, 5, 1],  # -y
    [2, 3, 7], [2, 7, 6],  # +y
    [0, 2, 6], [0, 6, 4],  # -z
    [1, 5, 7], [1, 7, 3],  # +z
], np.int32)


def box(center: tuple[float, float, float], size: tuple[float, float, float], name: str = "box") -> TriangleMesh:
    """An axis-aligned box with outward normals."""
    vertices = _CUBE_VERTICES * (np.asarray(size, np.float32) / 2) + np.asarray(center, np.float32)
    return TriangleMesh(vertices, _CUBE_FACES.copy(), name=name)


def simple_chair() -> TriangleMesh:
    """A four-legged chair facing +Z, normalised (:func:`normalize_mesh`). Parts: seat, 4 legs, back."""
    seat_y, leg = 0.45, 0.05
    parts = [box((0, seat_y, 0), (0.5, 0.06, 0.5), "seat")]
    for x in (-0.22, 0.22):
        for z in (-0.22, 0.22):
            parts.append(box((x, seat_y / 2, z), (leg, seat_y, leg), "leg"))
    parts.append(box((0, seat_y + 0.3, -0.23), (0.5, 0.55, 0.04), "back"))
    return normalize_mesh(TriangleMesh.concatenate(parts, name="simple_chair"))
