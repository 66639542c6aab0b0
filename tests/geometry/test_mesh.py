import numpy as np
import pytest

from ngp_mi.geometry import NORMALIZED_RADIUS, TriangleMesh, normalize_mesh
from ngp_mi.geometry.primitives import box


def test_normalize_mesh_centres_and_scales():
    mesh = normalize_mesh(box((3, -2, 5), (2, 4, 8)))
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-6)
    assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(NORMALIZED_RADIUS, rel=1e-6)


@pytest.mark.parametrize("vertices, faces, match", [
    (np.zeros((0, 3)), np.zeros((0, 3)), "non-empty"),
    ([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], "not finite"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], r"face indices must lie in \[0, 3\)"),
    ([[0, 0], [1, 0]], [[0, 1, 1]], r"\(V, 3\)"),
])
def test_invalid_meshes_are_rejected_with_reason(vertices, faces, match):
    with pytest.raises(ValueError, match=match):
        TriangleMesh(np.asarray(vertices, float), np.asarray(faces), name="bad.obj")
