"""G_sp^real (paper Sec. 3.5): the blend, the sRGB encoding it is judged in, and a CPU smoke-train."""

import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from ngp_mi.data.datasets import DepthDataset, ImageFolderDataset, ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel, blend, srgb_decode, srgb_encode
from ngp_mi.viz import linear_to_srgb

TINY_MAPS = MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,))
TINY = SpecularConfig(ngf=8, blocks=1, ndf=8, rf_image=(16, 34))


def test_srgb_encoding_matches_the_standard_and_has_finite_gradients_at_zero():
    x = torch.tensor([0.0, 1e-6, 0.0031308, 0.01, 0.2, 0.5, 1.0, 2.0, -1.0], dtype=torch.float64, requires_grad=True)
    encoded = srgb_encode(x)
    assert np.allclose(encoded.detach().numpy(), linear_to_srgb(np.clip(x.detach().numpy(), 0, 1)), atol=1e-7)
    encoded.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad[0] == pytest.approx(12.92)
    assert torch.allclose(srgb_decode(encoded), x.detach().clamp(0, 1), atol=1e-7)
    # an independent check of the power branch: 0.5 → 1.055 · 0.5^(1/2.4) − 0.055
    assert encoded[5].item() == pytest.approx(1.055 * 0.5 ** (1 / 2.4) - 0.055, abs=1e-12)


def test_blend_adds_specular_light_only_on_the_object():
    diffuse = torch.full((1, 3, 4, 4), 0.2)
    specular = torch.full((1, 3, 4, 4), 0.3)
    mask = torch.zeros(1, 1, 4, 4)
    mask[..., :2, :] = 1
    out = blend(diffuse, specular, mask)
    assert torch.allclose(out[..., :2, :], torch.tensor(0.5)) and torch.allclose(out[..., 2:, :], torch.tensor(0.2))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("spec")
    render_dataset(DatasetConfig(source="chair", num_shapes=2, views=2, resolution=32), root / "maps", progress=False)
    render_dataset(DatasetConfig(source="chair", num_shapes=2, views=2, resolution=32, channels=("mask",), real_spp=4,
                                 seed=1), root / "real", progress=False)
    return (DataLoader(DepthDataset(root / "maps"), batch_size=2),
            DataLoader(ImageFolderDataset(root / "real", size=32, linear=True), batch_size=2))


def test_specular_steps_train_g_sp_and_leave_the_map_networks_alone(data):
    torch.manual_seed(0)
    maps, model = MapsModel(TINY_MAPS), SpecularModel(TINY)
    frozen = [p.detach().clone() for p in maps.parameters()]
    trained = {name: [p.detach().clone() for p in getattr(model, name).parameters()]
               for name in ("G_sp", "F_sp", "D_real", "D_dfr")}
    history = [model.optimize(maps, depth, real) for _ in range(2) for depth, real in zip(*data)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    assert set(history[0]) == set(SpecularModel.loss_names) and set(model.visuals) == set(SpecularModel.visual_names)
    assert all(torch.equal(a, b) for a, b in zip(frozen, maps.parameters()))
    for name, params in trained.items():
        assert any(not torch.equal(a, b) for a, b in zip(params, getattr(model, name).parameters())), name
    assert all(p.requires_grad for p in maps.parameters())  # unfrozen again for a later joint stage


def test_composite_is_diffuse_radiance_plus_a_bounded_specular_on_the_object():
    torch.manual_seed(0)
    model = SpecularModel(TINY)
    normal = torch.nn.functional.normalize(torch.randn(2, 3, 32, 32), dim=1)
    diffuse_net = torch.rand(2, 3, 32, 32) * 2 - 1
    mask = (torch.rand(2, 1, 32, 32) > 0.5).float()
    with torch.no_grad():
        spec = model.specular(normal, diffuse_net, mask)
        image = model.compose(normal, diffuse_net, mask)
    assert (spec >= 0).all() and (spec <= 1).all() and (spec * (1 - mask)).abs().max() == 0
    assert torch.allclose(image - spec, (diffuse_net + 1) / 2 / math.pi, atol=1e-6)


def test_a_dark_start_g_sp_adds_almost_no_light_at_first_and_still_learns():
    """dark_start (issue 15): the default G_sp^real starts near I_rs = 0.5, more than the whole
    diffuse range; the dark one starts at DARK_START everywhere, and gradients reach its last layer."""
    from ngp_mi.models.specular import DARK_START

    torch.manual_seed(0)
    normal, diffuse = torch.randn(2, 3, 16, 16), torch.rand(2, 3, 16, 16) * 2 - 1
    mask = torch.ones(2, 1, 16, 16)
    default = SpecularModel(TINY).specular(normal, diffuse, mask)
    dark_model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "dark_start": True}))
    dark = dark_model.specular(normal, diffuse, mask)
    assert default.mean().item() > 0.3
    assert torch.allclose(dark, torch.tensor(DARK_START), atol=1e-6)
    dark.sum().backward()
    last = dark_model.G_sp.output_conv
    assert last.weight.grad.abs().sum() > 0 and torch.isfinite(last.weight.grad).all()


def test_with_ema_g_sp_is_the_moving_average_of_the_trained_generator(data, tmp_path):
    """ema (issue 15): the optimiser moves G_sp_train; G_sp follows θ̄ ← ema θ̄ + (1 − ema) θ and is
    what eval mode (inference, export) uses; a checkpoint keeps both."""
    from ngp_mi.models.checkpoint import load_weights

    torch.manual_seed(0)
    maps, model = MapsModel(TINY_MAPS), SpecularModel(SpecularConfig(**{**TINY.__dict__, "ema": 0.9}))
    assert "G_sp_train" in model.networks() and "G_sp_train" not in SpecularModel(TINY).networks()
    average = [p.detach().clone() for p in model.G_sp.parameters()]
    depth, real = next(iter(zip(*data)))
    model.optimize(maps, depth, real)
    trained = list(model.G_sp_train.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(average, trained))  # the trained copy moved
    for before, after, now in zip(average, model.G_sp.parameters(), trained):
        assert torch.allclose(after, 0.9 * before + 0.1 * now, atol=1e-6) and not after.requires_grad
    normal = torch.nn.functional.normalize(torch.randn(1, 3, 32, 32), dim=1)
    diffuse, mask = torch.rand(1, 3, 32, 32) * 2 - 1, torch.ones(1, 1, 32, 32)
    with torch.no_grad():
        training = model.specular(normal, diffuse, mask)
        model.eval()
        inference = model.specular(normal, diffuse, mask)
        assert torch.allclose(inference, (model.G_sp(torch.cat([normal, diffuse], 1)) + 1) / 2)
        assert not torch.allclose(training, inference)
    twin = SpecularModel(SpecularConfig(**{**TINY.__dict__, "ema": 0.9}))
    load_weights(twin.networks(), {f"{n}.{k}": v for n, net in model.networks().items()
                                   for k, v in net.state_dict().items()}, tmp_path / "x")
    assert all(torch.equal(a, b) for a, b in zip(twin.G_sp_train.parameters(), trained))
    with pytest.raises(ValueError, match="specular.ema"):
        SpecularModel(SpecularConfig(**{**TINY.__dict__, "ema": 1.0}))


def test_resize_upsampling_builds_g_sp_alone_with_it_and_bad_values_are_refused():
    model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "upsample": "resize"}))
    kinds = lambda net: {type(m).__name__ for m in net.decoder.modules()}
    assert "Upsample" in kinds(model.G_sp) and "ConvTranspose2d" not in kinds(model.G_sp)
    assert "ConvTranspose2d" in kinds(model.F_sp)  # the inverse only serves the cycle
    mask = torch.ones(2, 1, 16, 16)
    assert model.specular(torch.randn(2, 3, 16, 16), torch.rand(2, 3, 16, 16) * 2 - 1, mask).shape == (2, 3, 16, 16)
    with pytest.raises(ValueError, match="specular.upsample must be one of"):
        SpecularModel(SpecularConfig(**{**TINY.__dict__, "upsample": "pixelshuffle"}))


def test_a_grey_g_sp_adds_uncoloured_light_and_still_learns():
    torch.manual_seed(0)
    model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "grey": True}))
    normal, diffuse = torch.randn(2, 3, 16, 16), torch.rand(2, 3, 16, 16) * 2 - 1
    mask = (torch.rand(2, 1, 16, 16) > 0.3).float()
    specular = model.specular(normal, diffuse, mask)
    assert torch.equal(specular[:, 0], specular[:, 1]) and torch.equal(specular[:, 1], specular[:, 2])
    coloured = SpecularModel(TINY)
    coloured.load_state_dict(model.state_dict())
    assert torch.allclose(specular, coloured.specular(normal, diffuse, mask).mean(1, keepdim=True).expand(-1, 3, -1, -1))
    specular.sum().backward()
    assert model.G_sp.output_conv.weight.grad.abs().sum() > 0


@pytest.fixture(scope="module")
def exemplars(tmp_path_factory):
    root = tmp_path_factory.mktemp("exemplars")
    render_dataset(DatasetConfig(source="chair", num_shapes=2, views=2, resolution=32, seed=3), root, progress=False)
    return next(iter(DataLoader(ReflectanceMapDataset(root), batch_size=2)))


def test_exemplar_diffuse_input_shades_the_real_maps_appearance_code(data, exemplars):
    """diffuse_input = "exemplar" (issue 15): the generated → real cycle composites R_diff of
    G_n(d) and G_da(NOC(d), N^g, μ(E_da(albedo))) of real-maps views — what NGP is given with the
    exemplar handle — so the image follows the exemplar's albedo; "generated" ignores the maps."""
    from ngp_mi.models.maps import cameras_of

    torch.manual_seed(0)
    maps = MapsModel(TINY_MAPS)
    depth, real = next(iter(zip(*data)))
    normal, diffuse_net, mask, cameras_g = SpecularModel.generated_diffuse(maps, depth, exemplars)
    with torch.no_grad():
        cameras = cameras_of(exemplars)
        mu, _ = maps.E_da(2 * exemplars["albedo"] - 1, exemplars["mask"])
        expected = maps.decorate(exemplars["depth"], exemplars["mask"], exemplars, mu, cameras)
        shaded = maps.render_diffuse(expected["normal"], (expected["albedo"] + 1) / 2, exemplars["mask"], cameras)
    assert torch.equal(mask, exemplars["mask"]) and torch.allclose(normal, expected["normal"])
    assert [c.E.tolist() for c in cameras_g] == [c.E.tolist() for c in cameras]  # the exemplars' own cameras
    assert torch.allclose(diffuse_net, 2 * shaded - 1, atol=1e-6)
    recoloured = {**exemplars, "albedo": 1 - exemplars["albedo"]}
    assert not torch.allclose(SpecularModel.generated_diffuse(maps, depth, recoloured)[1], diffuse_net)

    model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "diffuse_input": "exemplar"}))
    steps = model.optimize(maps, depth, real, exemplars)
    assert all(math.isfinite(v) for v in steps.values())
    with pytest.raises(ValueError, match="real maps"):
        model.optimize(maps, depth, real)
    with pytest.raises(ValueError, match="specular.diffuse_input"):
        SpecularModel(SpecularConfig(**{**TINY.__dict__, "diffuse_input": "true"}))


def test_highlight_input_gives_g_sp_the_blinn_phong_specular_term(data, exemplars):
    """highlight_input (issue 15): G_sp^real reads a 7th channel, R_BP's specular term of N under the
    training lights — R_BP with a black albedo, checked against R_BP − R_diff — and trains with it."""
    from ngp_mi.models.maps import cameras_of
    from ngp_mi.render.shading import CameraLights, shade

    torch.manual_seed(0)
    maps = MapsModel(TINY_MAPS)
    normal, mask = exemplars["normal"], exemplars["mask"]
    cameras = cameras_of(exemplars)
    highlight = maps.render_highlight(normal, mask, cameras)
    lights = CameraLights.from_lights(maps.lights, cameras)
    c = maps.config
    full = shade(normal, exemplars["albedo"], mask, lights, cameras, k_d=c.k_d, k_s=c.k_s, alpha=c.alpha)
    diffuse = shade(normal, exemplars["albedo"], mask, lights, cameras, k_d=c.k_d, mode="diffuse")
    assert highlight.shape == mask.shape and highlight.max() > 0.05
    assert torch.allclose(highlight.expand(-1, 3, -1, -1), full - diffuse, atol=1e-5)

    model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "highlight_input": True}))
    assert next(model.G_sp.parameters()).shape[1] == 7  # N, I_df and the highlight
    diffuse_net = 2 * maps.render_diffuse(normal, exemplars["albedo"], mask, cameras) - 1
    with pytest.raises(ValueError, match="highlight"):
        model.specular(normal, diffuse_net, mask)
    spec = model.specular(normal, diffuse_net, mask, highlight)
    assert spec.shape == normal.shape and (spec * (1 - mask)).abs().max() == 0
    depth, real = next(iter(zip(*data)))
    steps = model.optimize(maps, depth, real)
    assert all(math.isfinite(v) for v in steps.values())


def test_a_signed_g_sp_starts_neutral_can_darken_and_never_makes_negative_radiance():
    """blend = "signed" (issue 15): I_rs ∈ (−1, 1) starts near 0, the composite may be darker than the
    diffuse image, is clamped at 0 (radiance), and its gradient stays finite at the clamp."""
    torch.manual_seed(0)
    model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "blend": "signed"}))
    normal = torch.nn.functional.normalize(torch.randn(2, 3, 16, 16), dim=1)
    diffuse_net = (torch.rand(2, 3, 16, 16) * 2 - 1).requires_grad_(True)
    mask = torch.ones(2, 1, 16, 16)
    specular = model.specular(normal, diffuse_net, mask)
    assert specular.abs().mean() < 0.3 and (specular < 0).any() and (specular > 0).any()
    assert SpecularModel(TINY).specular(normal, diffuse_net, mask).mean() > 0.3  # the paper's starts at ~0.5
    diffuse = torch.full((1, 3, 2, 2), 0.2)
    darker = blend(diffuse, torch.tensor([-0.1, -0.5]).view(1, 1, 1, 2).expand(1, 3, 2, 2), torch.ones(1, 1, 2, 2))
    assert torch.allclose(darker[..., 0], torch.tensor(0.1)) and torch.equal(darker[..., 1], torch.zeros(1, 3, 2))
    image = model.compose(normal, diffuse_net, mask)
    assert (image >= 0).all()
    image.sum().backward()
    assert torch.isfinite(diffuse_net.grad).all() and model.G_sp.output_conv.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="specular.blend"):
        SpecularModel(SpecularConfig(**{**TINY.__dict__, "blend": "multiply"}))


def test_the_sparsity_prior_is_the_object_mean_of_i_rs_and_darkens_g_sp(data):
    """lambda_sparse (issue 15): L_sp^sparse is |I_rs| averaged over the object's pixels and channels
    (zero off it), and with a large weight a few steps leave less light on the object than the same
    steps without it."""
    from ngp_mi.models.specular import specular_sparsity_loss

    mask = torch.zeros(1, 1, 4, 4)
    mask[..., :2] = 1
    specular = torch.zeros(1, 3, 4, 4)
    specular[:, 0, :, :2] = 0.6
    assert specular_sparsity_loss(specular, mask).item() == pytest.approx(0.6 / 3)
    assert specular_sparsity_loss(torch.zeros_like(specular), torch.zeros_like(mask)).item() == 0.0  # no object, no NaN

    probe = next(iter(data[0]))
    maps_seed_state = MapsModel(TINY_MAPS).state_dict()

    def light_after_steps(weight: float) -> float:
        torch.manual_seed(0)
        maps = MapsModel(TINY_MAPS)
        maps.load_state_dict(maps_seed_state)
        model = SpecularModel(SpecularConfig(**{**TINY.__dict__, "lambda_sparse": weight, "lr": 1e-3}))
        for depth, real in zip(*data):
            torch.manual_seed(1)
            steps = model.optimize(maps, depth, real)
        assert math.isfinite(steps["sparse"]) and steps["sparse"] >= 0
        torch.manual_seed(2)
        normal, diffuse_net, mask, _ = model.generated_diffuse(maps, probe)
        with torch.no_grad():
            return specular_sparsity_loss(model.specular(normal, diffuse_net, mask), mask).item()

    assert light_after_steps(100.0) < 0.9 * light_after_steps(0.0)  # Adam: 2 steps of lr 1e-3 move it so far
    with pytest.raises(ValueError, match="lambda_sparse"):
        SpecularModel(SpecularConfig(**{**TINY.__dict__, "lambda_sparse": -1.0}))
