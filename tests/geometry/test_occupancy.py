"""Inside tests (winding numbers), IM-NET point sampling and the cached shape dataset."""

import json

import numpy as np
import pytest
import trimesh

from ngp_mi.data.shapes import ShapeDataConfig, ShapeDataset, build_shape_dataset
from ngp_mi.geometry.families import generate
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.occupancy import (
    boundary_cells,
    fast_winding_numbers,
    grid_points,
    mesh_occupancy_grid,
    sample_occupancy_points,
    surface_samples,
    voxel_iou,
    winding_numbers,
)


def sphere(radius=0.3, subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return TriangleMesh(s.vertices, s.faces), s


def test_winding_number_is_one_inside_zero_outside_and_half_on_a_hole():
    mesh, _ = sphere()
    w = winding_numbers(mesh.vertices, mesh.faces, np.array([[0, 0, 0], [0.1, -0.05, 0.1], [0.5, 0, 0], [0, 0, -0.9]]))
    np.testing.assert_allclose(w, [1, 1, 0, 0], atol=1e-4)
    # Half a sphere (open, like most ShapeNet meshes): the centre sees half the solid angle.
    s = trimesh.creation.icosphere(4, radius=0.3)
    upper = TriangleMesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0])
    assert abs(winding_numbers(upper.vertices, upper.faces, np.zeros((1, 3)))[0] - 0.5) < 0.02


def test_mesh_grid_equals_the_analytic_sphere_and_survives_holes_where_parity_fails():
    mesh, s = sphere(subdivisions=4)
    truth = np.linalg.norm(grid_points(32), axis=-1) <= 0.3
    occupancy = mesh_occupancy_grid(mesh, 32)
    # Facets sit inside the true sphere: only cells between the polyhedron and the sphere may differ.
    assert voxel_iou(occupancy, truth) > 0.98
    # Punch a hole: remove a cap of triangles. Winding numbers still give the ball.
    keep = s.triangles_center[:, 2] < 0.27  # a hole of radius 0.13
    holed = TriangleMesh(s.vertices, s.faces[keep])
    assert voxel_iou(mesh_occupancy_grid(holed, 32), truth) > 0.95
    # Ray parity along +z through the hole calls the inside "outside" (what we avoid).
    ray_parity = trimesh.Trimesh(holed.vertices, holed.faces).ray.intersects_location(
        [[0, 0, 0]], [[0, 0, 1]])[0]
    assert len(ray_parity) == 0


def _open_and_closed_meshes():
    """Closed: a sphere, a chair, a car. Open: a sphere with a hole, half a sphere, a chair missing 15 % of its faces."""
    rng = np.random.default_rng(3)
    closed_sphere, s = sphere(subdivisions=3)
    chair, car = generate("chair", 5).mesh(), generate("car", 2).mesh()
    holed = TriangleMesh(s.vertices, s.faces[s.triangles_center[:, 2] < 0.27])
    half = TriangleMesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0])
    torn = TriangleMesh(chair.vertices, chair.faces[rng.random(len(chair.faces)) > 0.15])
    return {"sphere": closed_sphere, "chair": chair, "car": car, "holed sphere": holed, "half sphere": half,
            "torn chair": torn}


@pytest.mark.parametrize("name", ["sphere", "chair", "car", "holed sphere", "half sphere", "torn chair"])
def test_fast_winding_numbers_give_the_labels_of_the_exact_ones(name):
    mesh = _open_and_closed_meshes()[name]
    rng = np.random.default_rng(0)
    points = np.concatenate([grid_points(20).reshape(-1, 3), rng.uniform(-0.55, 0.55, (4000, 3)),
                             surface_samples(mesh, 4000, rng) + rng.normal(0, 0.01, (4000, 3))])  # near the surface
    exact = winding_numbers(mesh.vertices, mesh.faces, points)
    fast = fast_winding_numbers(mesh.vertices, mesh.faces, points)
    assert np.mean((fast > 0.5) == (exact > 0.5)) >= 0.999
    far = np.abs(exact - 0.5) > 0.05
    np.testing.assert_allclose(fast[far], exact[far], atol=0.02)
    assert np.array_equal(mesh_occupancy_grid(mesh, 20).ravel(), fast[:20 ** 3] > 0.5)


def test_procedural_mesh_occupancy_matches_its_exact_sdf():
    obj = generate("car", 2)
    exact = obj.solid.occupancy(grid_points(32).reshape(-1, 3)).reshape(32, 32, 32)
    assert voxel_iou(mesh_occupancy_grid(obj.mesh(), 32), exact) > 0.99


def test_point_sampling_prefers_the_surface_and_labels_exactly():
    obj = generate("chair", 1)
    grid = obj.solid.occupancy(grid_points(32).reshape(-1, 3)).reshape(32, 32, 32)
    rng = np.random.default_rng(0)
    points, occ = sample_occupancy_points(obj.solid.occupancy, grid, 4096, rng, near_fraction=0.5)
    assert points.shape == (4096, 3) and occ.shape == (4096,)
    assert np.array_equal(occ.astype(bool), obj.solid.occupancy(points))
    cell = (points + 0.55) / (1.1 / 32)
    boundary = boundary_cells(grid)
    on_surface = boundary[tuple(np.floor(cell).astype(int).T)]
    # Up to half the points are drawn from surface cells (all of them when there are fewer), the
    # rest uniformly: far more surface points than uniform sampling (boundary.mean()) would give.
    assert on_surface.mean() >= min(boundary.sum(), 2048) / 4096
    assert on_surface.mean() > 3 * boundary.mean()
    # All cells once when the count covers the grid (IM-NET's 16³).
    small = grid[::2, ::2, ::2]
    pts, _ = sample_occupancy_points(obj.solid.occupancy, small, 16 ** 3, rng)
    assert len(np.unique(np.floor((pts + 0.55) / (1.1 / 16)).astype(int), axis=0)) == 16 ** 3


def test_shape_dataset_builds_resumes_and_skips_bad_meshes(tmp_path):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    trimesh.creation.box((0.5, 0.3, 0.2)).export(meshes / "box.obj")
    s = trimesh.creation.icosphere(3, radius=0.4)
    trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 1] < 0.3]).export(meshes / "open_sphere.ply")
    (meshes / "broken.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    config = ShapeDataConfig(str(meshes), num_shapes=10, voxel_resolution=32, resolutions=(16, 32), points=(512, 1024),
                             surface_points=256)
    out = tmp_path / "data"
    summary = build_shape_dataset(config, out, progress=False)
    assert summary["built"] == 2 and list(summary["skipped"]) == ["broken"]
    assert "not finite" in summary["skipped"]["broken"]
    again = build_shape_dataset(config, out, progress=False)
    assert again["built"] == 0 and again["present"] == 2

    parallel = build_shape_dataset(config, tmp_path / "parallel", progress=False, workers=2)
    assert parallel["built"] == 2 and list(parallel["skipped"]) == ["broken"]
    for name in ("box.npz", "open_sphere.npz"):  # the same files, whichever process built them
        a, b = np.load(out / "shapes" / name), np.load(tmp_path / "parallel" / "shapes" / name)
        assert all(np.array_equal(a[k], b[k]) for k in a.files)

    data = ShapeDataset(out, 32)
    assert data.ids == ["box", "open_sphere"]
    item = data[1]
    assert item["voxels"].shape == (1, 32, 32, 32) and item["points"].shape == (1024, 3)
    assert item["occ"].shape == (1024, 1) and item["surface"].shape == (256, 3)
    # The open sphere's voxels are a ball (its centre inside) despite the missing cap.
    assert data.voxels(1)[16, 16, 16]
    assert 0.3 < float(item["occ"].mean()) < 0.9

    with pytest.raises(ValueError, match="voxel_resolution"):
        build_shape_dataset(ShapeDataConfig(str(meshes), num_shapes=10, voxel_resolution=64, resolutions=(16, 32),
                                            points=(512, 1024)), out, progress=False)
    assert json.loads((out / "dataset.json").read_text())["voxel_resolution"] == 32
