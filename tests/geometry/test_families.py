"""Procedural families: determinism, variety, labels, materials, and SDF == mesh."""

import numpy as np
import pytest
import trimesh

from ngp_mi.geometry import NORMALIZED_RADIUS
from ngp_mi.geometry.families import FAMILIES, generate
from ngp_mi.geometry.sdf import CYLINDER_SECTIONS, Box, Cylinder, rotation


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_same_seed_same_object_and_variety(family):
    a, b = generate(family, 7), generate(family, 7)
    assert a.params == b.params
    np.testing.assert_array_equal(a.mesh().vertices, b.mesh().vertices)
    samples = [generate(family, seed).params for seed in range(40)]
    varying = [k for k in samples[0] if len({repr(s[k]) for s in samples}) > 1]
    assert len(varying) >= 6, varying
    assert generate(family, 8).params != a.params


@pytest.mark.parametrize("family, required", [("chair", {0, 1, 2}), ("car", {0, 1, 2})])
def test_parts_materials_and_scale(family, required):
    for seed in range(10):
        obj = generate(family, seed)
        mesh = obj.mesh()
        labels = set(np.unique(mesh.part_ids).tolist())
        assert required <= labels <= set(range(len(obj.part_names)))
        assert labels <= set(obj.materials)
        for m in obj.materials.values():
            assert all(0 < c < 1 for c in m.albedo) and 0 <= m.specular <= 1 and 0 <= m.roughness <= 1
        assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(NORMALIZED_RADIUS, rel=1e-5)
        lo, hi = mesh.bounds
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-6)
        assert hi[1] - lo[1] > 0.2  # stands upright (+Y up) with some height


def test_chairs_face_plus_z():
    """The back sits behind the seat (-Z) and above it."""
    for seed in range(10):
        mesh = generate("chair", seed).mesh()
        seat = mesh.vertices[np.unique(mesh.faces[mesh.part_ids == 0])]
        back = mesh.vertices[np.unique(mesh.faces[mesh.part_ids == 2])]
        assert back[:, 2].mean() < seat[:, 2].mean() and back[:, 1].max() > seat[:, 1].max()


def test_primitive_sdfs_are_exact():
    box = Box(np.array([0.1, 0.2, 0.0]), np.array([0.3, 0.2, 0.1]), rotation([1, 1, 0], 25))
    cyl = Cylinder(np.array([0.0, 0.1, 0.0]), 0.2, 0.3, rotation([0, 0, 1], 90))
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (400, 3))
    for prim, tolerance in ((box, 1e-6), (cyl, 0.2 * (1 - np.cos(np.pi / CYLINDER_SECTIONS)) + 1e-6)):
        mesh = prim.mesh()
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        assert tm.is_watertight and tm.volume > 0
        sdf = prim.sdf(points)
        outside = sdf > tolerance
        _, distance, _ = trimesh.proximity.closest_point(tm, points[outside])
        np.testing.assert_allclose(sdf[outside], distance, atol=tolerance)
        inside = tm.contains(points)
        clear = np.abs(sdf) > tolerance
        np.testing.assert_array_equal(inside[clear], sdf[clear] < 0)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_object_sdf_matches_its_mesh(family):
    """Occupancy from the SDF equals inside-any-part of the mesh; outside, SDF = distance to the mesh."""
    obj = generate(family, 3)
    mesh = obj.mesh()
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    rng = np.random.default_rng(1)
    points = np.concatenate([rng.uniform(-0.55, 0.55, (3000, 3)),
                             tm.sample(1000) + rng.normal(0, 0.01, (1000, 3))])  # near the surface
    sdf = obj.solid.sdf(points)
    band = 0.006 * NORMALIZED_RADIUS  # cylinder tessellation
    inside = np.zeros(len(points), bool)
    for prim, _ in obj.solid.parts:
        part = prim.mesh()
        part_tm = trimesh.Trimesh((part.vertices - obj.solid.offset) * obj.solid.scale, part.faces, process=False)
        inside |= part_tm.contains(points)
    clear = np.abs(sdf) > band
    assert (inside[clear] == (sdf[clear] < 0)).mean() == 1.0
    assert inside.sum() > 50
    far = sdf > band
    _, distance, _ = trimesh.proximity.closest_point(tm, points[far])
    np.testing.assert_allclose(sdf[far], distance, atol=band)


def test_unknown_family_is_named():
    with pytest.raises(ValueError, match="unknown shape family 'sofa'"):
        generate("sofa", 0)
