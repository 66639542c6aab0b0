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


def test_small_pieces_are_dropped_by_their_share_of_the_surface():
    from ngp_mi.geometry.mesh import drop_small_components, face_areas

    big = box((0, 0, 0), (1, 1, 1))  # area 6
    speck = box((2, 0, 0), (0.1, 0.1, 0.1))  # area 0.06: 1 % of 6.06
    strut = box((0, 2, 0), (0.3, 0.3, 0.3))  # area 0.54: 8 %
    mesh = TriangleMesh.concatenate([big, speck, strut])
    assert face_areas(big).sum() == pytest.approx(6.0)
    kept, dropped = drop_small_components(mesh, 0.05)
    assert dropped == 1 and len(kept.faces) == len(big.faces) + len(strut.faces)
    assert len(kept.vertices) == len(big.vertices) + len(strut.vertices)  # the speck's vertices go too
    assert sorted(set(kept.part_ids.tolist())) == [0, 2]  # part ids follow their faces
    assert np.allclose(np.sort(kept.vertices[kept.faces].reshape(-1, 3), 0),
                       np.sort(np.concatenate([big.vertices[big.faces], strut.vertices[strut.faces]]).reshape(-1, 3), 0))
    assert drop_small_components(mesh, 0.005) == (mesh, 0)
    only, dropped = drop_small_components(mesh, 0.99)  # the largest piece stays whatever the threshold
    assert dropped == 2 and len(only.faces) == len(big.faces)
