"""ngp-mi fit-shape: a sphere fitted to a procedural chair's masks and depths through Π_v; the image
term through NGP's networks (z_da fitted too); resume; bad input; the chains against finite differences."""

import dataclasses
import json

import numpy as np
import pytest
import torch
import trimesh
from safetensors.torch import load_file

from ngp_mi.cli import main
from ngp_mi.commands.fit_shape import FitConfig, fit_losses, fit_shape, load_targets
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset


@pytest.fixture(scope="module")
def chair_views(tmp_path_factory):
    out = tmp_path_factory.mktemp("targets")
    render_dataset(DatasetConfig(source="chair", num_shapes=1, views=6, resolution=32, channels=("depth", "mask")),
                   out, progress=False)
    return out


@pytest.fixture(scope="module")
def chair_images(tmp_path_factory):
    """Two chairs' masks, depths and 16-spp path-traced images under the rig, 32²."""
    out = tmp_path_factory.mktemp("images")
    render_dataset(DatasetConfig(source="chair", num_shapes=1, views=4, resolution=32, channels=("depth", "mask"),
                                 real_spp=16), out, progress=False)
    return out


@pytest.fixture(scope="module")
def tiny_ngp(tiny_maps_run):
    from ngp_mi.pipeline import NGP

    return NGP(tiny_maps_run)


def test_the_image_term_goes_through_the_networks_and_fits_z_da(chair_images, tiny_ngp, tmp_path):
    config = FitConfig(str(chair_images), held_out=1, steps=6, sphere_subdivisions=2, checkpoint_every=3)
    messages = []
    summary = fit_shape(config, tmp_path, ngp=tiny_ngp, log=messages.append)
    history = json.loads((tmp_path / "state" / "state.json").read_text())["history"]
    assert all("image" in h and np.isfinite(h["image"]) and h["image"] > 0 for h in history)
    assert history[-1]["image"] < history[0]["image"]
    saved = load_file(tmp_path / "state" / "u.safetensors")
    assert saved["z_da"].shape == (1, tiny_ngp.maps.config.latent_dim) and saved["z_da"].abs().max() > 0
    assert summary["variant"] == "ngp" and summary["z_da"] == pytest.approx(saved["z_da"][0].tolist())
    for key in ("psnr_fitted_start", "psnr_fitted_end", "psnr_held_out_end", "flip_held_out_end"):
        assert np.isfinite(summary[key]), key
    assert "NGP's image (ngp) on the held-out views: PSNR" in (tmp_path / "report.md").read_text()
    assert all(p.requires_grad is False for p in tiny_ngp.maps.parameters())  # the networks stay as trained
    # without networks or without images the term is off, and says why
    fit_shape(dataclasses.replace(config, steps=1), tmp_path / "none", log=messages.append)
    assert any("no image term (no map networks" in m for m in messages)


def test_the_image_term_at_half_resolution_pools_the_projection(chair_images, tiny_ngp, tmp_path):
    from ngp_mi.commands.fit_shape import pool_views
    from ngp_mi.render.depth import project_depth

    targets = load_targets(chair_images)
    chair = trimesh.creation.box((0.5, 0.8, 0.5))  # the check needs a shape, not the chair itself
    vertices = torch.as_tensor(chair.vertices, dtype=torch.float32)
    fine = project_depth(vertices, chair.faces, targets.cameras[:2], spp=16, silhouette_grad=True)
    coarse = project_depth(vertices, chair.faces, [c.with_resolution(16) for c in targets.cameras[:2]], spp=64,
                           silhouette_grad=True)
    # 2 × 2 pooling of the 32² pixel averages is the 16² pixel average (with 4 × the samples): 0.005
    # here, sampling noise; a max-pool would be 0.03
    assert float((pool_views(fine.mask, 2) - coarse.mask).abs().mean()) < 0.012
    assert float((pool_views(fine.depth, 2) - coarse.depth).abs().mean()) < 0.012 * float(coarse.depth.max())

    config = FitConfig(str(chair_images), held_out=1, steps=3, sphere_subdivisions=2, image_downsample=2)
    summary = fit_shape(config, tmp_path, ngp=tiny_ngp, log=lambda *_: None)
    assert summary["image_resolution"] == [16, 16] and np.isfinite(summary["psnr_held_out_end"])
    history = json.loads((tmp_path / "state" / "state.json").read_text())["history"]
    assert all(np.isfinite(h["image"]) and h["image"] > 0 for h in history)
    with pytest.raises(ValueError, match="--image-downsample 3 does not divide the targets' resolution 32"):
        fit_shape(dataclasses.replace(config, image_downsample=3), tmp_path / "bad", ngp=tiny_ngp, log=lambda *_: None)


def test_the_image_chain_matches_finite_differences(tiny_ngp):
    """Depth and coverage of Π_v → G_n, G_da(z_da) → R_diff (Dr.Jit) → a weighted sum of the image:
    the gradient in the depth, the coverage and z_da against central differences. Smooth directions:
    a per-pixel random one crosses the kinks of the networks' activations in many pixels at once, and
    the differences then converge only as O(h). G_sp^real (``ngp``) adds one more plain torch network
    on top, which needs no check of its own."""
    from ngp_mi.camera import Camera
    from ngp_mi.commands.fit_shape import ImageTerm, fit_images
    from ngp_mi.lights import overhead_rig
    from ngp_mi.render.depth import project_depth

    camera = Camera.orbit(10, -30, 32)
    box = trimesh.creation.box((0.6, 0.5, 0.4))
    with torch.no_grad():
        projected = project_depth(torch.as_tensor(box.vertices, dtype=torch.float32), box.faces, camera)
    mask = projected.mask
    generator = torch.Generator().manual_seed(1)
    weights = torch.rand(1, 3, 32, 32, generator=generator)
    bounds = np.stack([box.vertices.min(0), box.vertices.max(0)])

    def loss(depth, coverage, z_da):
        term = ImageTerm(tiny_ngp, "no_sp", z_da)
        return (weights * fit_images(term, depth * coverage, coverage, [camera], bounds, [overhead_rig()])).sum()

    depth = projected.depth.clone().requires_grad_(True)
    coverage = ((0.7 + 0.3 * torch.rand(mask.shape, generator=generator)) * mask).requires_grad_(True)
    z_da = torch.randn(1, tiny_ngp.maps.config.latent_dim, generator=generator).requires_grad_(True)
    loss(depth, coverage, z_da).backward()
    y, x = torch.meshgrid(torch.linspace(-1, 1, 32), torch.linspace(-1, 1, 32), indexing="ij")
    smooth = (0.3 + x - 0.5 * y)[None, None] * mask
    for value, direction in ((depth, smooth), (coverage, smooth), (z_da, torch.randn(z_da.shape, generator=generator))):
        with torch.no_grad():
            plus, minus = (float(loss(*(v + s * 1e-3 * direction if v is value else v for v in (depth, coverage, z_da))))
                           for s in (1, -1))
        fd, analytic = (plus - minus) / 2e-3, float((value.grad * direction).sum())
        assert abs(analytic - fd) < 0.02 * abs(fd) + 1e-3, (analytic, fd)


def test_a_sphere_becomes_the_chair(chair_views, tmp_path):
    config = FitConfig(str(chair_views), held_out=1, steps=40, sphere_subdivisions=3, frame_every=5)
    summary = fit_shape(config, tmp_path, log=lambda *_: None)
    assert summary["chamfer_end"] < 0.35 * summary["chamfer_start"]
    assert summary["loss_end"] < 0.3 * summary["loss_start"]
    assert summary["mask_iou_fitted"] > max(0.6, summary["mask_iou_start"] + 0.15)
    assert summary["mask_iou_held_out"] > 0.5  # views the fit never saw
    mesh = trimesh.load(tmp_path / "fit.obj", force="mesh")
    assert len(mesh.faces) == 1280 and np.isfinite(mesh.vertices).all()
    for name in ("curves.png", "sheet.png", "progress.gif", "report.md"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "Chamfer-L2 to the true shape" in (tmp_path / "report.md").read_text()


def test_a_killed_fit_resumes_where_its_state_was_saved(chair_views, tmp_path):
    config = FitConfig(str(chair_views), steps=12, checkpoint_every=4, sphere_subdivisions=2)
    fit_shape(config, tmp_path / "straight", log=lambda *_: None)

    def kill_at_step_10(message):
        if "step 10/" in message:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_shape(config, tmp_path / "resumed", log=kill_at_step_10)
    assert json.loads((tmp_path / "resumed" / "state" / "state.json").read_text())["step"] == 8
    messages = []
    fit_shape(config, tmp_path / "resumed", log=messages.append)
    assert any("resumed at step 8" in m for m in messages)
    a, b = (load_file(tmp_path / run / "state" / "u.safetensors")["u"] for run in ("straight", "resumed"))
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="started with other settings"):
        fit_shape(FitConfig(str(chair_views), steps=13, checkpoint_every=4, sphere_subdivisions=2),
                  tmp_path / "resumed")


def test_a_second_fit_into_the_same_folder_is_refused(chair_views, tmp_path):
    from ngp_mi import lock

    with lock.exclusive(tmp_path / "f" / "fit-shape.lock", "a fit"):  # as another process's fit would
        with pytest.raises(lock.Busy, match="fit-shape.lock"):
            fit_shape(FitConfig(str(chair_views), steps=1, sphere_subdivisions=2), tmp_path / "f")
    assert not (tmp_path / "f" / "state").exists()  # nothing of it was written


def test_bad_targets_and_settings_are_named(chair_views, tmp_path, capsys):
    with pytest.raises(ValueError, match="no views of shape 'car/000000'"):
        load_targets(chair_views, "car/000000")
    with pytest.raises(ValueError, match="--held-out 6: the shape has 6 views"):
        fit_shape(FitConfig(str(chair_views), held_out=6), tmp_path)
    with pytest.raises(ValueError, match="needs a loss"):
        FitConfig(str(chair_views), mask_weight=0, depth_weight=0)
    assert main(["fit-shape", "--targets", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 1
    assert "no manifest" in capsys.readouterr().err


def test_the_loss_terms_are_named_and_zero_at_the_target():
    mask = torch.zeros(2, 1, 8, 8)
    mask[:, :, 2:6, 2:6] = 1
    depth = 2.0 * mask
    terms = fit_losses(mask, depth, mask, depth, 1.0, 1.0)
    assert set(terms) == {"mask", "depth", "total"} and float(terms["total"]) == 0.0
    assert float(fit_losses(mask * 0, depth, mask, depth, 1.0, 0.0)["total"]) == pytest.approx(16 / 64)
    # depth where the target has no object costs nothing in the depth term (the mask term sees it)
    spill = torch.ones(2, 1, 8, 8)
    assert float(fit_losses(spill, 2.0 * spill, mask, depth, 0.0, 1.0)["total"]) == 0.0


def test_the_mask_term_fits_the_images_alpha_where_the_targets_have_it(chair_images, chair_views, tmp_path):
    from ngp_mi.commands.fit_shape import mirror_views

    targets = load_targets(chair_images)
    coverage, mask = targets.coverage, targets.mask
    assert coverage is not None and coverage.shape == mask.shape and targets.fit_mask is coverage
    soft = (coverage > 0.05) & (coverage < 0.95)
    assert soft.sum() > 50  # the outline's pixels are partly covered
    assert torch.equal((coverage > 0.5)[~soft], (mask > 0.5)[~soft])  # and the rest agrees with the masks
    assert torch.equal(mirror_views(targets, 3, "x").coverage[3:6], coverage[:3].flip(-1))
    assert load_targets(chair_views).coverage is None  # no images: the binary masks
    summary = fit_shape(FitConfig(str(chair_images), held_out=1, steps=2, sphere_subdivisions=2, image_weight=0),
                        tmp_path / "soft", log=lambda _: None)
    assert summary["mask_target"] == "coverage"
    assert main(["fit-shape", "--targets", str(chair_images), "--out", str(tmp_path / "binary"), "--held-out", "1",
                 "--steps", "2", "--image-weight", "0", "--binary-masks"]) == 0
    assert json.loads((tmp_path / "binary" / "fit.json").read_text())["mask_target"] == "binary"


def test_the_shape_prior_starts_the_fit_and_its_latent_is_fitted_first(chair_views, tiny_run, tmp_path):
    from ngp_mi.models.shape import ShapeModel

    prior = ShapeModel.from_run(tiny_run[0])
    messages = []
    config = FitConfig(str(chair_views), start="zs", zs_candidates=4, zs_steps=6, steps=10, extract_resolution=32)
    summary = fit_shape(config, tmp_path, prior, log=messages.append)
    assert summary["start"] == "zs" and 0 <= summary["zs_seed"] < 4 and summary["chamfer_zs_start"] > 0
    assert any("start z_s of seed" in m for m in messages) and any("z_s fitted" in m for m in messages)
    latent = json.loads((tmp_path / "state" / "latent.json").read_text())
    assert len(latent["zs_history"]) + latent["zs_halvings"] == 6
    assert all(np.isfinite(h["total"]) for h in latent["zs_history"])
    # the phase ends on its lowest-loss latent, not on wherever its last (noisy) step went
    assert latent["zs_end_step"] == min(latent["zs_history"], key=lambda h: h["total"])["step"]
    assert summary["loss_end"] < summary["loss_start"] and np.isfinite(summary["chamfer_end"])
    again = fit_shape(config, tmp_path, prior, log=messages.append)  # done: phase (a) is not repeated
    assert again["zs_seed"] == summary["zs_seed"] and sum("start z_s of seed" in m for m in messages) == 1
    with pytest.raises(ValueError, match="needs a shape prior"):
        fit_shape(config, tmp_path / "none")


def test_the_chain_of_a_latent_fit_matches_finite_differences():
    """Field parameters → extraction with the iso-surface link → Π_v (interior) → a depth loss: the
    gradient of the whole chain against re-extracted, re-projected central differences. The field is
    an ellipsoid of radii θ (so finite differences see the exact surface, not a network's)."""
    from ngp_mi.camera import Camera
    from ngp_mi.geometry.extract import attach_iso_surface_gradient, extract_mesh
    from ngp_mi.render.depth import project_depth

    cams = [Camera.orbit(10, -30, 48), Camera.orbit(15, 40, 48)]

    def field_of(theta):
        return lambda p: (p.double() / theta).norm(dim=-1) - 1.0

    theta = torch.tensor([0.35, 0.25, 0.3], dtype=torch.float64)
    base = extract_mesh(field_of(theta), 64).mesh
    with torch.no_grad():
        mask = project_depth(torch.as_tensor(base.vertices, dtype=torch.float32), base.faces, cams).mask
    interior = torch.nn.functional.max_pool2d(1 - mask, 5, 1, 2) == 0  # away from the silhouette
    weights = torch.rand(mask.shape, generator=torch.Generator().manual_seed(0)).double() * interior

    def loss(vertices, faces):
        return (weights * project_depth(vertices.float(), faces, cams).depth.double()).sum()

    parameters = theta.clone().requires_grad_(True)
    vertices = attach_iso_surface_gradient(torch.as_tensor(base.vertices, dtype=torch.float64), field_of(parameters))
    loss(vertices, base.faces).backward()
    for k in range(3):
        h = torch.zeros(3, dtype=torch.float64)
        h[k] = 2e-3
        plus, minus = (extract_mesh(field_of(theta + s * h), 64).mesh for s in (1, -1))
        fd = (float(loss(torch.as_tensor(plus.vertices), plus.faces))
              - float(loss(torch.as_tensor(minus.vertices), minus.faces))) / (2 * float(h[k]))
        assert abs(float(parameters.grad[k]) - fd) < 0.01 * abs(fd), (k, float(parameters.grad[k]), fd)


# Numerics of long fits (issue 17): each case runs a few steps and ends in a recovered step or a
# clear error, never a non-finite value in the state or the mesh.

def _finite_state(folder):
    return all(torch.isfinite(t).all() for t in load_file(folder / "state" / "u.safetensors").values())


def test_a_start_no_view_sees_is_refused(chair_views, tmp_path, monkeypatch):
    """Mesh files are normalised to the origin, so this happens with cameras that look elsewhere; here
    the start is moved away instead."""
    import ngp_mi.commands.fit_shape as module
    from ngp_mi.geometry.mesh import TriangleMesh

    sphere = trimesh.creation.icosphere(2, radius=0.4)
    far = TriangleMesh(np.asarray(sphere.vertices + [40.0, 0, 0], np.float32), np.asarray(sphere.faces))
    monkeypatch.setattr(module, "_start_mesh", lambda config: far)
    with pytest.raises(ValueError, match="no fitted view .* sees the start shape"):
        fit_shape(FitConfig(str(chair_views), steps=2), tmp_path / "fit", log=lambda *_: None)


def test_a_shape_that_leaves_every_view_is_undone_with_half_the_step(chair_views, tmp_path, monkeypatch):
    import ngp_mi.commands.fit_shape as module

    real, calls = module._step_problem, []

    def leaves_twice(coverage, total):  # steps 3 and 4 (the retry) find the shape gone
        calls.append(1)
        return "the shape left every fitted view" if len(calls) in (4, 5) else real(coverage, total)

    monkeypatch.setattr(module, "_step_problem", leaves_twice)
    messages = []
    config = FitConfig(str(chair_views), steps=6, sphere_subdivisions=2, checkpoint_every=2)
    summary = fit_shape(config, tmp_path, log=messages.append)
    undone = [m for m in messages if "the last step undone, step size halved" in m]
    assert len(undone) == 2 and "step 3: the shape left every fitted view" in undone[0]
    state = torch.load(tmp_path / "state" / "optimizer.pt", weights_only=True)
    assert state["param_groups"][0]["lr"] == pytest.approx(config.lr / 4)
    assert summary["steps"] == 6 and _finite_state(tmp_path)
    assert np.isfinite(trimesh.load(tmp_path / "fit.obj", force="mesh").vertices).all()


def test_non_finite_losses_give_up_with_a_clear_error_and_save_nothing_of_them(chair_views, tmp_path, monkeypatch):
    import ngp_mi.commands.fit_shape as module

    real = module.fit_losses

    def nan_from_step_4(*args, **kwargs):
        terms = real(*args, **kwargs)
        nan_from_step_4.calls += 1
        if nan_from_step_4.calls > 4:
            terms["total"] = terms["total"] * float("nan")
        return terms

    nan_from_step_4.calls = 0
    monkeypatch.setattr(module, "fit_losses", nan_from_step_4)
    config = FitConfig(str(chair_views), steps=10, sphere_subdivisions=2, checkpoint_every=2)
    with pytest.raises(RuntimeError, match="a non-finite loss at step 4, 4 times in a row"):
        fit_shape(config, tmp_path, log=lambda *_: None)
    assert json.loads((tmp_path / "state" / "state.json").read_text())["step"] == 4 and _finite_state(tmp_path)
    assert not (tmp_path / "fit.obj").exists()


def test_a_self_intersecting_start_stays_finite(chair_views, tmp_path):
    a, b = trimesh.creation.box((0.5, 0.3, 0.3)), trimesh.creation.box((0.3, 0.5, 0.3))  # two boxes through each other
    path = tmp_path / "crossed.obj"
    trimesh.util.concatenate([a.subdivide().subdivide(), b.subdivide().subdivide()]).export(path)
    summary = fit_shape(FitConfig(str(chair_views), steps=8, start=str(path)), tmp_path / "fit", log=lambda *_: None)
    assert np.isfinite(summary["loss_end"]) and summary["loss_end"] < summary["loss_start"]
    assert _finite_state(tmp_path / "fit")


def test_empty_extractions_of_z_s_are_undone(chair_views, tiny_run, tmp_path, monkeypatch):
    from ngp_mi.models.shape import ShapeModel

    prior = ShapeModel.from_run(tiny_run[0])
    real, calls = prior.differentiable_surface, []

    def empty_on_the_third(*args, **kwargs):
        calls.append(1)
        return None if len(calls) == 3 else real(*args, **kwargs)

    monkeypatch.setattr(prior, "differentiable_surface", empty_on_the_third)
    messages = []
    config = FitConfig(str(chair_views), start="zs", zs_candidates=2, zs_steps=5, steps=2, extract_resolution=32)
    summary = fit_shape(config, tmp_path, prior, log=messages.append)
    assert summary["zs_halvings"] == 1 and any("z_s step 2 gave an empty shape" in m for m in messages)
    assert np.isfinite(trimesh.load(tmp_path / "fit.obj", force="mesh").vertices).all()


def test_a_point_light_on_the_surface_gives_finite_gradients(tiny_ngp):
    """A point light placed on a visible surface point (distance → 0, irradiance ∝ 1/r²): the image
    term and its gradient in depth, coverage and z_da stay finite, and Adam's steps stay bounded."""
    from ngp_mi.camera import Camera
    from ngp_mi.commands.fit_shape import ImageTerm, fit_images
    from ngp_mi.lights import PointLight
    from ngp_mi.render.depth import project_depth

    camera = Camera.orbit(10, -30, 32)
    box = trimesh.creation.box((0.6, 0.5, 0.4))
    with torch.no_grad():
        projected = project_depth(torch.as_tensor(box.vertices, dtype=torch.float32), box.faces, camera)
    towards = camera.position / np.linalg.norm(camera.position)
    on_surface = tuple(towards * np.min(np.array([0.3, 0.25, 0.2]) / np.abs(towards)))  # where the central ray hits
    lights = [[PointLight(on_surface, (50.0, 50.0, 50.0))]]
    depth = projected.depth.clone().requires_grad_(True)
    coverage = projected.mask.clone().requires_grad_(True)
    z_da = torch.zeros(1, tiny_ngp.maps.config.latent_dim, requires_grad=True)
    optimizer = torch.optim.Adam([depth, coverage, z_da], lr=1e-2)
    bounds = np.stack([box.vertices.min(0), box.vertices.max(0)])
    for _ in range(3):
        image = fit_images(ImageTerm(tiny_ngp, "ngp", z_da), depth * coverage, coverage, [camera], bounds, lights)
        loss = image.abs().mean()
        optimizer.zero_grad()
        loss.backward()
        assert torch.isfinite(loss) and all(torch.isfinite(t.grad).all() for t in (depth, coverage, z_da))
        optimizer.step()
    assert torch.isfinite(depth).all() and float((depth.detach() - projected.depth).abs().max()) < 0.1


def test_phase_b_moves_the_decoder_and_phase_a_fits_z_da_from_images(chair_images, tiny_run, tiny_ngp, tmp_path):
    from ngp_mi.models.shape import ShapeModel

    prior = ShapeModel.from_run(tiny_run[0])
    before = {k: v.clone() for k, v in prior.decoder.state_dict().items()}
    flags = [p.requires_grad for p in prior.parameters()]
    config = FitConfig(str(chair_images), start="zs", zs_candidates=2, zs_steps=4, steps=2, extract_resolution=32,
                       fit_decoder=True, decoder_lr=1e-3)
    summary = fit_shape(config, tmp_path, prior, ngp=tiny_ngp, log=lambda *_: None)
    after = prior.decoder.state_dict()
    latent = json.loads((tmp_path / "state" / "latent.json").read_text())
    assert summary["decoder_fitted"] and latent["decoder_moved_by"] > 0  # a copy moved ...
    assert all(torch.equal(after[k], before[k]) for k in before)  # ... the caller's prior is as trained
    assert [p.requires_grad for p in prior.parameters()] == flags
    assert all("image" in h for h in latent["zs_history"]) and any(abs(x) > 0 for x in latent["z_da"])
    with pytest.raises(ValueError, match="--fit-decoder needs --start zs"):
        FitConfig(str(chair_images), fit_decoder=True)


def test_phase_d_moves_the_field_on_a_grid_and_hands_its_mesh_to_the_vertices(chair_views, tiny_run, tmp_path):
    from ngp_mi.models.shape import ShapeModel

    messages = []
    config = FitConfig(str(chair_views), start="zs", zs_candidates=2, zs_steps=3, steps=2, extract_resolution=32,
                       grid_steps=5, grid_resolution=32)
    summary = fit_shape(config, tmp_path, ShapeModel.from_run(tiny_run[0]), log=messages.append)
    latent = json.loads((tmp_path / "state" / "latent.json").read_text())
    assert len(latent["grid_history"]) == 5 and all("free" in h and np.isfinite(h["total"]) for h in latent["grid_history"])
    assert latent["grid_end_step"] == min(latent["grid_history"], key=lambda h: h["total"])["step"]
    assert any("grid fitted" in m for m in messages) and np.isfinite(summary["chamfer_end"])
    start = load_file(tmp_path / "state" / "start.safetensors")["vertices"].numpy()
    assert np.abs(start).max() <= 0.55 + 1e-6  # the grid's mesh, inside its domain, is the vertex phase's start
    with pytest.raises(ValueError, match="--grid-steps needs --start zs"):
        FitConfig(str(chair_views), grid_steps=3)
    with pytest.raises(ValueError, match="--grid-resolution"):
        FitConfig(str(chair_views), start="zs", grid_steps=3, grid_resolution=4)


def test_zero_vertex_steps_stop_after_the_latent_phase(chair_views, tiny_run, tmp_path):
    from ngp_mi.models.shape import ShapeModel

    config = FitConfig(str(chair_views), start="zs", zs_candidates=2, zs_steps=3, steps=0, extract_resolution=32)
    summary = fit_shape(config, tmp_path, ShapeModel.from_run(tiny_run[0]), log=lambda *_: None)
    assert summary["steps"] == 0 and summary["loss_end"] is None and np.isfinite(summary["chamfer_end"])
    last = fit_shape(dataclasses.replace(config, zs_keep_best=False), tmp_path / "last",
                     ShapeModel.from_run(tiny_run[0]), log=lambda *_: None)
    latent = json.loads((tmp_path / "last" / "state" / "latent.json").read_text())
    assert latent["zs_end_step"] == latent["zs_history"][-1]["step"]  # without zs_keep_best: the last step
    assert np.isfinite(last["chamfer_end"])
    assert (tmp_path / "curves.png").stat().st_size > 0 and "progress.gif" not in (tmp_path / "report.md").read_text()
    with pytest.raises(ValueError, match="--steps must be >= 1"):
        FitConfig(str(chair_views), steps=0)


def _user_folder(chair_images, folder, edit=lambda k, view: view):
    """The render-dataset views as a user would bring them: sRGB PNGs with the mask as alpha, and a
    cameras.json of K and E."""
    from PIL import Image

    from ngp_mi.data.exr import read_exr
    from ngp_mi.data.manifest import load_manifest
    from ngp_mi.viz import to_uint8

    folder.mkdir()
    views = []
    for k, record in enumerate(load_manifest(chair_images)):
        rgb = read_exr(chair_images / record["files"]["real"], ["rgb"])["rgb"]
        mask = read_exr(chair_images / record["files"]["maps"], ["mask"])["mask"]
        rgba = np.concatenate([to_uint8(rgb), (mask[..., None] > 0.5).astype(np.uint8) * 255], -1)
        Image.fromarray(rgba, "RGBA").save(folder / f"view{k}.png")
        views.append(edit(k, {"image": f"view{k}.png", "K": record["K"], "E": record["E"]}))
    (folder / "cameras.json").write_text(json.dumps({"views": views}))
    return folder


def test_the_users_own_images_with_a_cameras_file_are_fitted(chair_images, tiny_ngp, tmp_path):
    folder = _user_folder(chair_images, tmp_path / "mine")
    targets = load_targets(folder)
    assert targets.depth is None and targets.images.shape == (4, 3, 32, 32) and len(targets.lights[0]) == 4
    messages = []
    summary = fit_shape(FitConfig(str(folder), held_out=1, steps=4, sphere_subdivisions=2), tmp_path / "fit",
                        ngp=tiny_ngp, log=messages.append)
    assert any("the depth term is off" in m for m in messages) and summary["chamfer_end"] is None
    history = json.loads((tmp_path / "fit" / "state" / "state.json").read_text())["history"]
    assert all(h["depth"] == 0 and np.isfinite(h["image"]) for h in history)
    assert history[-1]["total"] < history[0]["total"]


@pytest.mark.parametrize("edit, message", [
    (lambda k, v: {key: x for key, x in v.items() if key != "K"} if k == 2 else v, r"view 2 \(view2.png\): no camera field 'K'"),
    (lambda k, v: {**v, "K": [[40, 0, 16], [0, 30, 16], [0, 0, 1]]} if k == 1 else v, "inconsistent camera.*fx == fy"),
    (lambda k, v: {**v, "K": [[40, 0, 90], [0, 40, 16], [0, 0, 1]]} if k == 0 else v, "principal point .* outside"),
    (lambda k, v: {**v, "mask": "nothing.png"} if k == 3 else v, "nothing.png"),
])
def test_a_bad_cameras_file_is_named(chair_images, tmp_path, edit, message):
    folder = _user_folder(chair_images, tmp_path / "bad", edit)
    with pytest.raises((ValueError, OSError), match=message):
        load_targets(folder)


def test_an_image_without_a_mask_is_named(chair_images, tmp_path):
    from PIL import Image

    folder = _user_folder(chair_images, tmp_path / "rgb")
    Image.open(folder / "view1.png").convert("RGB").save(folder / "view1.png")
    with pytest.raises(ValueError, match=r"view 1 \(view1.png\): no mask"):
        load_targets(folder)


def test_the_command_line_fit_writes_a_ply(chair_views, tmp_path):
    from ngp_mi.cli import main

    assert main(["fit-shape", "--targets", str(chair_views), "--out", str(tmp_path / "f"), "--steps", "3",
                 "--format", "ply"]) == 0
    assert len(trimesh.load(tmp_path / "f" / "fit.ply", force="mesh").faces) > 0


def test_the_command_line_runs_phases_b_and_d(chair_views, tiny_run, tmp_path):
    from ngp_mi.cli import main

    assert main(["fit-shape", "--targets", str(chair_views), "--out", str(tmp_path / "f"), "--start", "zs",
                 "--shape-run", str(tiny_run[0]), "--zs-steps", "2", "--fit-decoder", "--grid-steps", "2",
                 "--grid-resolution", "32", "--grid-lr", "0.05", "--ray-weight", "2", "--steps", "1",
                 "--min-component", "0.5"]) == 0
    latent = json.loads((tmp_path / "f" / "state" / "latent.json").read_text())
    assert latent["decoder_fitted"] and len(latent["grid_history"]) == 2
    config = json.loads((tmp_path / "f" / "fit.json").read_text())["config"]
    assert config["ray_weight"] == 2.0 and config["grid_lr"] == 0.05 and config["min_component"] == 0.5
    # every piece but the largest dropped before the vertices: the start is one connected surface
    from ngp_mi.geometry.mesh import TriangleMesh, drop_small_components

    start = load_file(tmp_path / "f" / "state" / "start.safetensors")
    mesh = TriangleMesh(start["vertices"].numpy(), start["faces"].numpy())
    assert "components_dropped" in latent and drop_small_components(mesh, 0.999)[1] == 0
    with pytest.raises(ValueError, match="--min-component"):
        FitConfig(str(chair_views), start="zs", min_component=1.0)


def test_mirrored_views_are_what_the_mirrored_cameras_see_of_a_symmetric_shape(chair_images):
    from ngp_mi.commands.fit_shape import mirror_views
    from ngp_mi.geometry.families import generate
    from ngp_mi.render.depth import project_depth

    targets = load_targets(chair_images)
    mirrored = mirror_views(targets, 3, "x")
    assert len(mirrored.cameras) == 7 and mirrored.cameras[6] is targets.cameras[3]  # the held-out view stays last
    assert torch.equal(mirrored.mask[3:6], targets.mask[:3].flip(-1)) and torch.equal(mirrored.images[6], targets.images[3])
    chair = generate("chair", int(targets.record["shape_id"].rsplit("/", 1)[1])).mesh()  # symmetric about x = 0
    seen = project_depth(torch.as_tensor(chair.vertices, dtype=torch.float32), chair.faces, mirrored.cameras[3:6])
    assert torch.equal(seen.mask > 0.5, mirrored.mask[3:6] > 0.5)
    assert torch.allclose(seen.depth * mirrored.mask[3:6], mirrored.depth[3:6], atol=1e-4)
    light, twin = targets.lights[0][0], mirrored.lights[3][0]
    moved = "direction" if hasattr(light, "direction") else "position"
    assert np.allclose(np.asarray(getattr(twin, moved)), np.asarray(getattr(light, moved)) * [-1, 1, 1])
    # a shape that is not symmetric about x = 0 does not match its mirrored views: the test can fail
    shifted = torch.as_tensor(chair.vertices + np.array([0.15, 0.0, 0.0]), dtype=torch.float32)
    assert not torch.equal(project_depth(shifted, chair.faces, mirrored.cameras[3:6]).mask > 0.5, mirrored.mask[3:6] > 0.5)


def test_the_command_line_fits_mirrored_views(chair_views, tmp_path):
    assert main(["fit-shape", "--targets", str(chair_views), "--out", str(tmp_path / "f"), "--held-out", "2",
                 "--steps", "2", "--mirror", "x"]) == 0
    summary = json.loads((tmp_path / "f" / "fit.json").read_text())
    assert summary["views"] == 10 and summary["fitted_views"] == 8 and summary["config"]["mirror"] == "x"
    with pytest.raises(ValueError, match="--mirror must be one of x, y, z"):
        FitConfig(str(chair_views), mirror="w")


def test_a_users_soft_alpha_is_kept_as_coverage(chair_images, tmp_path):
    from PIL import Image

    folder = tmp_path / "mine"
    _user_folder(chair_images, folder)
    assert load_targets(folder).coverage is None  # a binary alpha is a mask
    rgba = np.asarray(Image.open(folder / "view0.png")).copy()
    rgba[0, :4, 3] = [0, 100, 128, 255]  # a soft matte's edge
    Image.fromarray(rgba, "RGBA").save(folder / "view0.png")
    targets = load_targets(folder)
    assert torch.allclose(targets.coverage[0, 0, 0, :4], torch.tensor([0, 100, 128, 255]) / 255.0)
    assert targets.mask[0, 0, 0, :4].tolist() == [0, 0, 1, 1]
