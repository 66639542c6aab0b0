"""The ray silhouette of an occupancy field: rays against Mitsuba's masks, gradients, and a hole it opens."""

import numpy as np
import torch

from ngp_mi.camera import Camera
from ngp_mi.geometry.carving import OccupancyGrid, disagreement_pixels, ray_samples, ray_silhouette_terms
from ngp_mi.geometry.extract import attach_iso_surface_gradient, extract_mesh, node_axis
from ngp_mi.geometry.families import generate
from ngp_mi.render.depth import project_depth


def test_rays_marched_through_a_chair_see_what_mitsuba_sees():
    """An independent computation of the mask: marching the procedural chair's SDF along the pixel
    rays agrees with Π_v's (Mitsuba's) pixel-centre coverage on all but a few boundary pixels."""
    chair = generate("chair", 4)
    mesh = chair.mesh()
    camera = Camera.orbit(20, 35, 48)
    with torch.no_grad():
        mask = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, [camera], spp=1).mask
    pixels = torch.arange(48 * 48)
    points, meets = ray_samples(camera, pixels, 512, torch.Generator().manual_seed(0))
    inside = chair.solid.sdf(points.reshape(-1, 3).double().numpy()).reshape(len(pixels), 512) < 0
    marched = inside.any(-1) & meets.numpy()
    truth = mask[0, 0].flatten().numpy() > 0.5
    assert truth.sum() > 200
    assert (marched != truth).mean() < 0.01


def test_disagreement_pixels_are_where_coverage_and_target_differ():
    coverage, target = torch.zeros(8, 8), torch.zeros(8, 8)
    coverage[2:4, 2:4] = 1.0
    target[3:5, 3:5] = 1.0
    wrong = disagreement_pixels(coverage, target, 100, torch.Generator().manual_seed(0))
    expected = ((coverage > 0.5) != (target > 0.5)).flatten().nonzero()[:, 0]
    assert sorted(wrong.tolist()) == expected.tolist()
    assert len(disagreement_pixels(coverage, target, 3, torch.Generator().manual_seed(0))) == 3


def _sphere_field(radius: torch.Tensor, sharpness: float = 20.0):
    return lambda p: torch.sigmoid(sharpness * (radius - p.double().norm(dim=-1)))


def test_free_and_hit_terms_pull_a_sphere_to_the_target_and_match_finite_differences():
    camera = Camera.orbit(10, 20, 32)
    target_small, target_big = (torch.zeros(1, 1, 32, 32) for _ in range(2))
    yy, xx = torch.meshgrid(torch.arange(32) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    distance = ((xx - camera.cx) ** 2 + (yy - camera.cy) ** 2).sqrt()
    target_small[0, 0][distance < 3] = 1.0
    target_big[0, 0][distance < 12] = 1.0
    coverage = torch.zeros(1, 1, 32, 32)
    coverage[0, 0][distance < 7] = 1.0  # a mid-sized sphere's, roughly: both targets disagree with it
    for target, term, sign in ((target_small, "free", 1.0), (target_big, "hit", -1.0)):
        radius = torch.tensor(0.2, dtype=torch.float64, requires_grad=True)
        terms = ray_silhouette_terms(_sphere_field(radius), [camera], coverage, target, rays_per_view=4096, samples=64)
        assert float(terms[term].detach()) > 0
        grad, = torch.autograd.grad(terms[term], radius)
        assert sign * float(grad) > 0  # too big → shrink; too small → grow
        eps = 1e-4
        with torch.no_grad():
            up = ray_silhouette_terms(_sphere_field(radius + eps), [camera], coverage, target, 4096, 64)[term]
            down = ray_silhouette_terms(_sphere_field(radius - eps), [camera], coverage, target, 4096, 64)[term]
        np.testing.assert_allclose(float(grad), float(up - down) / (2 * eps), rtol=0.05)


def test_the_free_term_opens_a_gap_that_the_mask_term_cannot_see():
    """A slab seen face-on covers a target's gap: the gap's pixels lie inside the slab's silhouette,
    so only the field's rays reach them. Descending the free term on an occupancy grid opens the gap
    through the slab and leaves the rest of it."""
    camera = Camera.orbit(0, 0, 32)
    values = torch.zeros(25, 25, 25)
    values[:, :, 10:15] = 1.0  # a slab |z| < 0.09 (node k ↔ z = −0.55 + 0.0458 k)
    grid = OccupancyGrid(values)

    def seen():
        with torch.no_grad():
            points, _ = ray_samples(camera, torch.arange(32 * 32), 256, torch.Generator().manual_seed(1))
            return (grid(points.reshape(-1, 3)).reshape(32 * 32, 256).amax(-1) > 0.5).reshape(32, 32)

    coverage = seen().float()[None, None]
    rows = coverage[0, 0].any(1).nonzero()[:, 0]
    assert coverage.mean() > 0.5 and rows.min() > 0  # the slab fills most of the view, its outline in it
    lo, hi = int(rows.min()), int(rows.max()) + 1  # the slab's rows (and columns: a square)
    target = coverage.clone()
    target[..., :, 14:18] = 0.0  # a vertical gap in the target, inside the slab's silhouette
    optimizer = torch.optim.Adam(grid.parameters(), lr=0.1)
    for step in range(40):
        terms = ray_silhouette_terms(grid, [camera], seen().float()[None, None], target, 512, 64, seed=step)
        loss = terms["free"] + terms["hit"]
        if not loss.requires_grad:  # no pixel disagrees any more
            break
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = seen()
    assert not after[lo:hi, 14:18].any()  # the gap is open
    assert after[lo:hi, lo:14].all() and after[lo:hi, 18:hi].all()  # the slab beside it stays


def test_an_occupancy_grid_is_its_field_at_the_nodes_and_trilinear_between():
    sphere = lambda p: 0.5 + 4 * (0.3 - p.double().norm(dim=-1))  # noqa: E731 — occupancy, inside above 1/2
    grid = OccupancyGrid.from_field(sphere, 32, level=0.5)
    axis = torch.as_tensor(node_axis(32))
    nodes = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    with torch.no_grad():
        np.testing.assert_allclose(grid(nodes).numpy(), sphere(nodes).numpy(), atol=1e-5)
        a, b = nodes[1000], nodes[1000] + torch.tensor([0.0, 0.0, 1.1 / 32])  # neighbours along z
        mid = grid(((a + b) / 2)[None].float())
        np.testing.assert_allclose(float(mid), float((grid(a[None].float()) + grid(b[None].float())) / 2), atol=1e-5)
    mesh = grid.mesh(0.5)
    dense = extract_mesh(sphere, 32, level=0.5, coarse=32, inside_above=True).mesh
    np.testing.assert_allclose(mesh.vertices, dense.vertices, atol=1e-5)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3).max() < 5e-3


def test_the_iso_surface_link_through_a_grid_matches_finite_differences():
    """Raising every node by ε grows the sphere: the link's gradient of its volume along that
    direction against re-extracted central differences."""
    from helpers import volume

    sphere = lambda p: 0.5 + 4 * (0.3 - p.double().norm(dim=-1))  # noqa: E731
    grid = OccupancyGrid.from_field(sphere, 32, level=0.5)
    mesh = grid.mesh(0.5)
    vertices = attach_iso_surface_gradient(torch.as_tensor(mesh.vertices, dtype=torch.float32), grid)
    volume(vertices.double(), mesh.faces).backward()
    analytic = float(grid.values.grad.sum())
    eps, volumes = 1e-2, []
    for sign in (1, -1):
        shifted = OccupancyGrid(grid.values.detach() + sign * eps)
        m = shifted.mesh(0.5)
        volumes.append(float(volume(torch.as_tensor(m.vertices, dtype=torch.float64), m.faces)))
    assert abs(analytic - (volumes[0] - volumes[1]) / (2 * eps)) < 0.03 * abs(analytic)
