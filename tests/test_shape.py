"""G_shape: IM-NET nets and losses, extraction, the differentiable iso-surface link, training and sampling."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from ngp_mi.models.checkpoint import list_checkpoints
from ngp_mi.training.shape import ShapeRecipe, train_shape
from safetensors.torch import load_file

from ngp_mi.cli import main
from ngp_mi.eval.shape_metrics import chamfer_distance, chamfer_matrix, coverage_mmd
from ngp_mi.geometry.extract import attach_iso_surface_gradient, extract_mesh
from ngp_mi.geometry.families import generate
from ngp_mi.models.shape import CoarseShapes, ShapeConfig, ShapeModel, critic_loss, gradient_penalty
from ngp_mi.nets.imnet import ImplicitDecoder, LatentCritic, LatentGenerator, VoxelEncoder, leaky_clamp

TINY = Path(__file__).resolve().parent.parent / "train" / "shape_tiny.toml"


def tiny_config(tmp_path, name, **train):
    text = TINY.read_text().replace('cache_dir = "outputs/data/shape_tiny"', f'cache_dir = "{tmp_path / "data"}"')
    text = text.replace('out = "outputs/train/shape_tiny"', f'out = "{tmp_path / name}"')
    for key, value in train.items():
        text = text.replace(f"\n{key} = ", f"\n{key} = {value}\n# ", 1)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shape")
    return train_shape(tiny_config(tmp, "run"), log=lambda *_: None), tmp


def volume(vertices, faces):
    """Enclosed volume of a closed, outward-oriented mesh (divergence theorem)."""
    t = vertices[torch.as_tensor(np.asarray(faces), dtype=torch.long)]
    return (t[:, 0] * torch.linalg.cross(t[:, 1], t[:, 2])).sum() / 6


# --------------------------------------------------------------------------- networks and losses

def test_network_shapes_and_imnet_output_activation():
    enc, dec = VoxelEncoder(32, ef=4, code_dim=16), ImplicitDecoder(16, gf=4, fourier_levels=2)
    code = enc(torch.rand(2, 1, 32, 32, 32))
    assert code.shape == (2, 16) and bool(((code > 0) & (code < 1)).all())
    assert dec(torch.rand(2, 100, 3) - 0.5, code).shape == (2, 100, 1)
    assert LatentGenerator(8, 32, 16)(torch.randn(5, 8)).shape == (5, 16)
    assert LatentCritic(16, 32)(torch.rand(5, 16)).shape == (5,)
    x = torch.tensor([-1.0, 0.0, 0.3, 1.0, 2.0])
    assert torch.allclose(leaky_clamp(x), torch.tensor([-0.01, 0.0, 0.3, 1.0, 1.01]))
    with pytest.raises(ValueError, match="multiple of 16"):
        VoxelEncoder(16)


def test_wgan_gp_losses_against_closed_forms():
    real, fake = torch.randn(64, 4), torch.randn(64, 4) + 1
    w = torch.tensor([0.5, -2.0, 1.0, 0.25])
    critic = lambda x: x @ w  # noqa: E731 — a linear critic has gradient w everywhere
    assert torch.allclose(gradient_penalty(critic, real, fake), (w.norm() - 1) ** 2)
    assert torch.allclose(critic_loss(critic(real), critic(fake)), (fake @ w).mean() - (real @ w).mean())


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


# --------------------------------------------------------------------------- extraction

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


# --------------------------------------------------------------------------- differentiable link

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


def test_trained_decoder_gradient_wrt_z_and_weights_matches_reextraction(tiny_run):
    """The link vs central finite differences of re-extracted meshes, for the enclosed volume.

    d volume / d z_s along the gradient, three latents, 64³: within 10 % (measured 0.2–7 %).
    d volume / d (decoder output bias), 128³: within 6 % (measured 4.4 %; 15 % at 64³, where the
    tiny decoder's soft field makes marching cubes' linear edge interpolation the larger error —
    the finite differences themselves move from 0.0163 to 0.0149 between 64³ and 128³).
    """
    model = ShapeModel.from_run(tiny_run[0]).double()

    def reextracted(z, resolution):
        mesh = model.shape(z, resolution).mesh
        return float(volume(torch.as_tensor(mesh.vertices, dtype=torch.float64), mesh.faces))

    for seed in range(3):
        z = torch.randn(model.config.z_dim, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        zz = z.clone().requires_grad_(True)
        vertices, faces = model.differentiable_surface(zz, 64)
        volume(vertices, faces).backward()
        direction = zz.grad / zz.grad.norm()
        ad = float(zz.grad @ direction)
        fd = (reextracted(z + 0.1 * direction, 64) - reextracted(z - 0.1 * direction, 64)) / 0.2
        assert abs(ad - fd) < 0.10 * abs(fd), (seed, ad, fd)

    z = torch.randn(model.config.z_dim, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    model.zero_grad()
    vertices, faces = model.differentiable_surface(z, 128)
    volume(vertices, faces).backward()
    ad = float(model.decoder.out.bias.grad[0])
    bias = model.decoder.out.bias
    with torch.no_grad():
        bias += 0.003
        up = reextracted(z, 128)
        bias -= 0.006
        down = reextracted(z, 128)
        bias += 0.003
    fd = (up - down) / 0.006
    assert abs(ad - fd) < 0.06 * abs(fd), (ad, fd)


def test_a_depth_loss_reaches_z_and_the_decoder_through_mitsuba(tiny_run):
    from ngp_mi.camera import Camera
    from ngp_mi.render.depth import project_depth

    model = ShapeModel.from_run(tiny_run[0])
    z = torch.randn(model.config.z_dim, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    vertices, faces = model.differentiable_surface(z, 32)
    maps = project_depth(vertices, faces, Camera.orbit(20.0, 45.0, 32))
    assert maps.mask.sum() > 20
    (maps.depth * maps.mask).sum().backward()
    assert torch.isfinite(z.grad).all() and z.grad.abs().sum() > 0
    grads = [p.grad for p in model.decoder.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and sum(g.abs().sum() for g in grads) > 0


# --------------------------------------------------------------------------- training and sampling

def test_training_outputs_metrics_and_learns(tiny_run):
    run, _ = tiny_run
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    ae = [r for r in records if r.get("phase") == "ae"]
    gan = [r for r in records if r.get("phase") == "gan"]
    assert [r["resolution"] for r in ae][0] == 16 and ae[-1]["resolution"] == 32  # progressive
    assert gan and all(np.isfinite(r["gan_wasserstein"]) for r in gan)
    metrics = json.loads((run / "metrics.json").read_text())
    # The tiny preset (11 s) reaches IoU ~0.65 on its training shapes; an untrained decoder gives 0.
    assert metrics["autoencoder_iou"]["train"] > 0.3 and "held_out" in metrics["autoencoder_iou"]
    samples = metrics["samples"]
    assert samples["samples"] == 4 and {"coverage", "mmd"} <= set(samples) and "held_out_real" in samples


def test_training_resumes_exactly(tmp_path):
    straight = train_shape(tiny_config(tmp_path, "straight", checkpoint_every=40, gan_iterations=10), log=lambda *_: None)
    cut = tiny_config(tmp_path, "resumed", checkpoint_every=40, gan_iterations=10)
    text = cut.read_text().replace("stages = [[16, 100], [32, 150]]", "stages = [[16, 100], [32, 20]]")
    cut.with_name("cut.toml").write_text(text.replace("gan_iterations = 10", "gan_iterations = 0"))
    train_shape(cut.with_name("cut.toml"), log=lambda *_: None)  # stops at step 120 (checkpoint) ...
    resumed = train_shape(cut, log=lambda *_: None)               # ... and continues to the end
    a = load_file(list_checkpoints(straight)[-1] / "weights.safetensors")
    b = load_file(list_checkpoints(resumed)[-1] / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_sample_shapes_cli_writes_meshes_sheet_and_interpolations(tiny_run, tmp_path):
    run, _ = tiny_run
    out = tmp_path / "samples"
    assert main(["sample-shapes", "--run", str(run), "--out", str(out), "--num", "3", "--resolution", "32",
                 "--spp", "4"]) == 0
    summary = json.loads((out / "samples.json").read_text())
    files = [r["file"] for r in summary["shapes"] if r["file"]]
    assert files and all((out / f).stat().st_size > 0 for f in files)
    assert (out / "sheet.png").exists() and "sheet.png" in (out / "report.md").read_text()
    inter = tmp_path / "inter"
    assert main(["sample-shapes", "--run", str(run), "--out", str(inter), "--interpolate", "0", "2", "--steps", "3",
                 "--resolution", "32", "--format", "ply", "--spp", "4"]) == 0
    import trimesh
    # t = 0 and t = 1 are the shapes of seeds 0 and 2.
    for k, seed_file in ((0, "shape-000.obj"), (2, "shape-002.obj")):
        a = trimesh.load(inter / f"shape-{k:03d}.ply", process=False)
        b = trimesh.load(out / seed_file, process=False)
        np.testing.assert_allclose(np.asarray(a.vertices), np.asarray(b.vertices), atol=1e-5)
    assert main(["sample-shapes", "--run", str(tmp_path / "nothing"), "--out", str(out)]) == 1


def test_bad_configs_name_the_field(tmp_path):
    bad = tiny_config(tmp_path, "bad")
    bad.write_text(bad.read_text().replace("gf = 16", "gf = 16\nwidth = 3"))
    with pytest.raises(ValueError, match=r"unknown \[model\] field\(s\) \['width'\]"):
        train_shape(bad)
    bad.write_text(TINY.read_text().replace("stages = [[16, 100], [32, 150]]", "stages = [[64, 10]]"))
    with pytest.raises(ValueError, match="stage resolution 64"):
        train_shape(bad)


def test_shape_model_step_changes_only_its_own_networks():
    model = ShapeModel(ShapeConfig(voxel_resolution=32, ef=4, gf=4, code_dim=8, z_dim=4, gan_hidden=16))
    before = {k: v.clone() for k, v in model.G_latent.state_dict().items()}
    model.ae_step(torch.rand(2, 1, 32, 32, 32).round(), torch.rand(2, 64, 3) - 0.5, torch.rand(2, 64, 1).round())
    assert all(torch.equal(before[k], v) for k, v in model.G_latent.state_dict().items())
    losses = model.gan_step(torch.rand(8, 8))
    assert set(losses) == {"gan_wasserstein", "gan_gp", "gan_G"} and all(np.isfinite(list(losses.values())))


@pytest.mark.parametrize("preset", ["tiny", "cpu", "paper"])
def test_every_preset_config_loads_and_builds(preset):
    recipe = ShapeRecipe.read(TINY.with_name(f"shape_{preset}.toml"))
    data = recipe.data
    model = ShapeModel(recipe.model)
    assert model.encoder(torch.zeros(1, 1, *(data.voxel_resolution,) * 3)).shape == (1, model.config.code_dim)


def test_render_dataset_of_autoencoded_shapes_pairs_with_the_detailed_views(tiny_run, tmp_path):
    """--coarse-shapes: same ids and cameras as the detailed dataset, other geometry (the reconstruction)."""
    from ngp_mi.data.datasets import ReflectanceMapDataset
    from ngp_mi.data.render_dataset import DatasetConfig, render_dataset

    run, _ = tiny_run
    config = DatasetConfig(source="chair", num_shapes=2, views=2, resolution=32, channels=("depth", "mask"))
    render_dataset(config, tmp_path / "detailed", progress=False)
    summary = render_dataset(dataclasses.replace(config, coarse_shapes=str(run), coarse_resolution=32),
                             tmp_path / "coarse", progress=False, reconstruct=CoarseShapes(run, 32))
    detailed, coarse = ReflectanceMapDataset(tmp_path / "detailed"), ReflectanceMapDataset(tmp_path / "coarse")
    rendered = {(r["shape_id"], r["view"]) for r in coarse.records}
    assert len(rendered) + 2 * len(summary["skipped_shapes"]) == 4
    assert all("empty shape" in reason for reason in summary["skipped_shapes"].values())
    for i, record in enumerate(detailed.records):
        if (record["shape_id"], record["view"]) not in rendered:
            continue
        j = next(j for j, r in enumerate(coarse.records) if (r["shape_id"], r["view"]) == (record["shape_id"], record["view"]))
        assert np.allclose(record["K"], coarse.records[j]["K"]) and np.allclose(record["E"], coarse.records[j]["E"])
        a, b = detailed[i], coarse[j]
        assert b["mask"].sum() > 0 and not torch.equal(a["depth"], b["depth"])
    with pytest.raises(ValueError, match="not a scene file"):
        render_dataset(dataclasses.replace(config, source="scenes/table_lamp.xml", coarse_shapes=str(run)), tmp_path / "s",
                       progress=False, reconstruct=CoarseShapes(run))
