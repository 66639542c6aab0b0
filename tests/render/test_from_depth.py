"""Maps computed from a depth map (NOC, normals) against the G-buffer's own."""

import numpy as np
import torch

from ngp_mi.camera import ViewDistribution
from ngp_mi.geometry.primitives import simple_chair
from ngp_mi.render.from_depth import noc_from_depth, normals_from_depth
from ngp_mi.render.gbuffer import GBufferRenderer
from ngp_mi.render.scene import diffuse_bsdf, mesh_parts_to_mitsuba


def test_normals_and_noc_recomputed_from_depth_are_consistent():
    """Normals from the depth through K agree with the normal channel (median < 1 deg on flat parts)."""
    mesh = simple_chair()
    errors = []
    for camera in ViewDistribution().sample(4, seed=2, resolution=128):
        renderer = GBufferRenderer(mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(0.5)), mesh.bounds, camera)
        maps = renderer.render(camera)
        depth = torch.tensor(maps["depth"])[None, None].double()
        mask = torch.tensor(maps["mask"])[None, None]
        derived = normals_from_depth(depth, mask, camera)[0].permute(1, 2, 0).numpy()
        on = maps["mask"] > 0
        cosine = np.clip(np.sum(derived[on] * maps["normal"][on], axis=-1), -1, 1)
        errors.append(np.degrees(np.arccos(cosine)))
        noc = noc_from_depth(depth, mask, camera, mesh.bounds)[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(noc, maps["noc"], atol=1e-4)
    errors = np.concatenate(errors)
    assert np.median(errors) < 1.0, np.median(errors)
