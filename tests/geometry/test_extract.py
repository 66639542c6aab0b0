"""Marching cubes (coarse to fine) and the differentiable iso-surface link on analytic fields."""

import numpy as np
import pytest
import torch
from helpers import volume

from ngp_mi.geometry.extract import attach_iso_surface_gradient, extract_mesh
from ngp_mi.geometry.families import generate


def test_coarse_to_fine_extraction_equals_dense_with_fewer_evaluations():
    solid = generate("chair", 3).solid
    sdf = lambda p: torch.as_tensor(solid.sdf(p.double().numpy()), dtype=torch.float32)  # noqa: E731
    dense, fine = extract_mesh(sdf, 64, coarse=64), extract_mesh(sdf, 64, coarse=32)
    assert fine.evaluated < dense.evaluated / 4
    np.testing.assert_array_equal(dense.mesh.faces, fine.mesh.faces)
    np.testing.assert_allclose(dense.mesh.vertices, fine.mesh.vertices, atol=1e-6)


def test_extraction_of_a_sphere_is_on_the_sphere_outward_and_empty_fields_give_none():
    sdf = lambda p: p.norm(dim=-1) - 0.3  # noqa: E731
    mesh = extract_mesh(sdf, 64).mesh
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3).max() < 2e-3
    v = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    assert abs(float(volume(v, mesh.faces)) - 4 / 3 * np.pi * 0.3 ** 3) < 2e-3 * 0.113
    occupancy = lambda p: (0.3 - p.norm(dim=-1)) * 5 + 0.5  # noqa: E731 — inside above 0.5
    flipped = extract_mesh(occupancy, 64, level=0.5, inside_above=True).mesh
    assert float(volume(torch.as_tensor(flipped.vertices, dtype=torch.float64), flipped.faces)) > 0.1
    assert extract_mesh(lambda p: p.norm(dim=-1) + 1.0, 32).mesh is None


@pytest.mark.parametrize("loss_name", ["mean_squared_radius", "volume"])
def test_iso_surface_gradient_of_a_sphere_radius_matches_finite_differences(loss_name):
    def loss_of(vertices, faces):
        return vertices.square().sum(-1).mean() if loss_name == "mean_squared_radius" else volume(vertices, faces)

    r = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    field = lambda p: p.double().norm(dim=-1) - r  # noqa: E731
    mesh = extract_mesh(field, 64).mesh
    vertices = attach_iso_surface_gradient(torch.as_tensor(mesh.vertices, dtype=torch.float64), field)
    assert torch.equal(vertices.detach(), torch.as_tensor(mesh.vertices, dtype=torch.float64))  # values unchanged
    loss_of(vertices, mesh.faces).backward()

    def reextracted(radius):
        m = extract_mesh(lambda p: p.double().norm(dim=-1) - radius, 64).mesh
        return float(loss_of(torch.as_tensor(m.vertices, dtype=torch.float64), m.faces))

    h = 1e-3
    fd = (reextracted(0.3 + h) - reextracted(0.3 - h)) / (2 * h)
    analytic = 2 * 0.3 if loss_name == "mean_squared_radius" else 4 * np.pi * 0.3 ** 2
    assert abs(float(r.grad) - fd) < 0.01 * abs(fd)
    assert abs(float(r.grad) - analytic) < 0.01 * analytic
