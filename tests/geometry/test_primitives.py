"""Built-in test shapes: closed, outward, oriented as the conventions say."""

import numpy as np
import pytest

from ngp_mi.geometry import TriangleMesh
from ngp_mi.geometry.primitives import box, simple_chair


def signed_volume(mesh: TriangleMesh) -> float:
    v = mesh.vertices[mesh.faces].astype(np.float64)
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def test_box_is_closed_with_outward_faces():
    mesh = box((0.1, 0.2, 0.3), (1.0, 2.0, 3.0))
    assert signed_volume(mesh) == pytest.approx(6.0, rel=1e-6)
    np.testing.assert_allclose(mesh.bounds, [[-0.4, -0.8, -1.2], [0.6, 1.2, 1.8]], atol=1e-6)


def test_simple_chair_parts_and_orientation():
    chair = simple_chair()
    assert sorted(np.unique(chair.part_ids)) == [0, 1, 2, 3, 4, 5]
    assert signed_volume(chair) > 0
    back = chair.vertices[np.unique(chair.faces[chair.part_ids == 5])]
    seat = chair.vertices[np.unique(chair.faces[chair.part_ids == 0])]
    assert back[:, 2].mean() < seat[:, 2].mean()  # the back is behind: the chair faces +Z
    assert back[:, 1].max() > seat[:, 1].max()  # and above the seat (+Y up)
