"""Chamfer distance, coverage and MMD against brute force."""

import numpy as np
import pytest
import torch

from ngp_mi.eval.shape_metrics import chamfer_distance, chamfer_matrix, coverage_mmd


def test_chamfer_and_coverage_against_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.random((50, 3)), rng.random((70, 3))
    d = ((a[:, None] - b[None]) ** 2).sum(-1)
    expected = d.min(1).mean() + d.min(0).mean()
    assert abs(float(chamfer_distance(torch.tensor(a), torch.tensor(b))) - expected) < 1e-9
    clouds = [rng.random((30, 3)) for _ in range(3)]
    matrix = chamfer_matrix(clouds, clouds)
    assert np.allclose(np.diag(matrix), 0, atol=1e-6)
    # generated 0 and 1 both match reference 0; reference 1 is matched by nobody.
    result = coverage_mmd(np.array([[0.1, 0.5], [0.2, 0.9]]))
    assert result == {"coverage": 0.5, "mmd": pytest.approx((0.1 + 0.5) / 2)}
