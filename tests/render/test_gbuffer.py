"""G-buffers (Mitsuba's aov integrator and the batched ray cast) against analytic shapes, Π_v and the depth itself."""

import numpy as np
import pytest
import torch
from helpers import analytic_sphere, compiled_kernels, trimesh_depth

from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.geometry.primitives import box, simple_chair
from ngp_mi.render.depth import project_depth
from ngp_mi.render.gbuffer import GBufferRenderer
from ngp_mi.render.scene import diffuse_bsdf, mesh_parts_to_mitsuba


def render_one(renderer, camera, path):
    """One view through the aov integrator (``render``) or the batched ray cast (``render_views``)."""
    if path == "aov":
        return renderer.render(camera)
    return {name: m[0] for name, m in renderer.render_views([camera]).items()}


@pytest.mark.parametrize("path", ["aov", "views"])
@pytest.mark.parametrize("theta, phi", [(0.0, 0.0), (15.0, 60.0), (20.0, -85.0)])
def test_sphere_depth_normal_albedo_noc_are_exact(theta, phi, path):
    radius, albedo = 0.4, (0.7, 0.2, 0.1)
    camera = Camera.orbit(theta, phi, 48)
    shapes = {"s": {"type": "sphere", "radius": radius, "bsdf": diffuse_bsdf(albedo)}}
    maps = render_one(GBufferRenderer(shapes, np.array([[-radius] * 3, [radius] * 3]), camera), camera, path)
    depth, normal, hit = analytic_sphere(camera, radius)
    np.testing.assert_array_equal(maps["mask"] > 0, hit)  # pixel centres: no blended silhouette
    np.testing.assert_allclose(maps["depth"], depth, atol=2e-5)
    np.testing.assert_allclose(maps["normal"], normal, atol=2e-4)
    np.testing.assert_allclose(maps["albedo"][hit], np.broadcast_to(albedo, (hit.sum(), 3)), atol=1e-6)
    world = (np.where(hit[..., None], camera.pixel_rays() * depth[..., None], 0) - camera.t) @ camera.R
    np.testing.assert_allclose(maps["noc"][hit], (world[hit] + radius) / (2 * radius), atol=1e-4)
    assert set(np.unique(maps["mask"])) == {0.0, 1.0}


def test_box_noc_spans_the_unit_cube():
    mesh = box((0.1, -0.05, 0.0), (0.5, 0.3, 0.4))
    seen = []
    for theta, phi in [(30, 45), (-30, -135), (60, 170), (-60, -10)]:
        camera = Camera.orbit(theta, phi, 64)
        renderer = GBufferRenderer(mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(0.5)), mesh.bounds, camera,
                                   channels=("noc", "mask"))
        maps = renderer.render(camera)
        assert set(maps) == {"noc", "mask"}
        seen.append(maps["noc"][maps["mask"] > 0])
    seen = np.concatenate(seen)
    np.testing.assert_allclose(seen.min(0), 0.0, atol=0.03)
    np.testing.assert_allclose(seen.max(0), 1.0, atol=0.03)
    assert seen.min() >= -1e-5 and seen.max() <= 1 + 1e-5


def test_batched_views_equal_the_aov_integrator_view_by_view():
    """render_views (all views in one kernel) reproduces the aov reference on a multi-material chair."""
    from ngp_mi.data.sources import resolve_source

    content = resolve_source("chair", 3, 0)[2].load()
    assert len(content.shapes) >= 3  # several parts, several BSDFs
    cameras = ViewDistribution().sample(6, seed=4, resolution=64)
    renderer = GBufferRenderer(content.shapes, content.bounds, cameras[0])
    batch = renderer.render_views(cameras)
    assert batch["normal"].shape == (6, 64, 64, 3) and batch["depth"].shape == (6, 64, 64)
    for i, camera in enumerate(cameras):
        reference = renderer.render(camera)
        np.testing.assert_array_equal(batch["mask"][i], reference["mask"])
        np.testing.assert_allclose(batch["depth"][i], reference["depth"], atol=2e-5)
        np.testing.assert_allclose(batch["normal"][i], reference["normal"], atol=1e-4)
        np.testing.assert_allclose(batch["noc"][i], reference["noc"], atol=1e-4)
        # Rays from the near plane (aov) and from the centre may pick the other part on a seam.
        differs = np.abs(batch["albedo"][i] - reference["albedo"]).max(-1) > 1e-6
        assert differs.mean() < 2e-3, differs.sum()
    one = GBufferRenderer(content.shapes, content.bounds, cameras[0], channels=("noc",)).render_views(cameras[:2])
    assert set(one) == {"noc"}
    np.testing.assert_array_equal(one["noc"], batch["noc"][:2])
    with pytest.raises(ValueError, match="64x64"):
        renderer.render_views([cameras[0].with_resolution(32)])


def test_new_shapes_reuse_the_compiled_kernel():
    """Geometry, bounds and materials are kernel inputs: a dataset of new shapes compiles nothing new."""
    camera = Camera.orbit(10.0, 20.0, 16)

    def render(i):
        mesh = box((0.01 * i, -0.02 * i, 0.0), (0.3 + 0.02 * i, 0.25, 0.3 - 0.01 * i))
        shapes = mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf((0.2 + 0.1 * i, 0.5, 0.3)))
        GBufferRenderer(shapes, mesh.bounds, camera).render_views([camera, camera])

    render(0)
    launched, compiled = compiled_kernels(lambda: [render(i) for i in (1, 2, 3)])
    assert len(launched) >= 3 and not compiled, f"{len(compiled)} of {len(launched)} kernels compiled anew"


def test_gbuffer_agrees_with_the_depth_projection():
    """Two Mitsuba paths (aov integrator vs our ray cast) give the same pixel-centre maps."""
    mesh = simple_chair()
    camera = Camera.orbit(12.0, 35.0, 64)
    renderer = GBufferRenderer(mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(0.5)), mesh.bounds, camera)
    maps = renderer.render(camera)
    ours = project_depth(torch.tensor(mesh.vertices), mesh.faces, camera)
    np.testing.assert_array_equal(maps["mask"], ours.mask[0, 0].numpy())
    np.testing.assert_allclose(maps["depth"], ours.depth[0, 0].numpy(), atol=2e-6)
    np.testing.assert_allclose(maps["normal"], ours.normal[0].permute(1, 2, 0).numpy(), atol=1e-5)
    np.testing.assert_allclose(maps["noc"], ours.noc[0].permute(1, 2, 0).numpy(), atol=1e-5)


def test_dataset_depth_agrees_with_trimesh_ray_casting():
    """The dataset renderer's depth against an independent ray cast (trimesh, not Mitsuba)."""
    from ngp_mi.geometry.families import generate

    mesh = generate("chair", 5).mesh()
    camera = Camera.orbit(8.0, 50.0, 48)
    maps = GBufferRenderer(mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(0.5)), mesh.bounds, camera,
                           channels=("depth",)).render(camera)
    reference = trimesh_depth(mesh, camera)
    both = (reference > 0) & (maps["depth"] > 0)
    assert both.sum() > 100 and (both == (reference > 0)).mean() > 0.99
    np.testing.assert_allclose(maps["depth"][both], reference[both], atol=2e-5)


def test_unknown_channel_is_named():
    camera = Camera.orbit(0, 0, 8)
    with pytest.raises(ValueError, match="subset of"):
        GBufferRenderer({}, np.zeros((2, 3)), camera, channels=("depth", "specular"))
