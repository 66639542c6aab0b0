"""A CPU smoke-train of the map networks on a tiny rendered dataset."""

import dataclasses
import math

import pytest
import torch
from torch.utils.data import DataLoader

from ngp_mi.data.datasets import DepthDataset, ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models import losses
from ngp_mi.models.maps import MapsConfig, MapsModel, cameras_of, depth_to_net, net_to_depth
from ngp_mi.render.from_depth import normals_from_depth

TINY = MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,))


@pytest.fixture(scope="module")
def loaders(tmp_path_factory):
    root = tmp_path_factory.mktemp("maps")
    render_dataset(DatasetConfig(source="chair", num_shapes=3, views=2, resolution=32), root, progress=False)
    g = torch.Generator().manual_seed(0)
    return (DataLoader(DepthDataset(root), batch_size=3, shuffle=True, generator=g),
            DataLoader(ReflectanceMapDataset(root), batch_size=3, shuffle=True, generator=g))


def test_training_steps_are_finite_and_update_every_network(loaders):
    torch.manual_seed(0)
    model = MapsModel(TINY)
    before = {name: [p.detach().clone() for p in getattr(model, name).parameters()]
              for name in ("G_n", "G_da", "G_depth", "E_da", "D_n", "D_da", "D_df", "D_depth", "D_noc")}
    history = []
    for _ in range(3):
        for depth, maps in zip(*loaders):
            history.append(model.optimize(depth, maps))
    assert all(math.isfinite(v) for step in history for v in step.values())
    assert set(history[0]) == set(MapsModel.loss_names)
    for name, params in before.items():
        changed = any(not torch.equal(a, b) for a, b in zip(params, getattr(model, name).parameters()))
        assert changed, f"{name} did not change"
    assert history[-1]["G"] < history[0]["G"]
    assert set(model.visuals) == set(MapsModel.visual_names)


def test_the_diffuse_renderer_passes_gradients_to_the_normal_generator(loaders):
    """G_n receives gradient from L_df^GAN alone, which reaches it only through R_diff."""
    torch.manual_seed(1)
    model = MapsModel(TINY)
    depth, maps = next(zip(*loaders))
    terms = model(depth, maps)
    model.G_n.zero_grad()
    terms["gan_df"].backward()
    grad = sum(p.grad.abs().sum() for p in model.G_n.parameters() if p.grad is not None)
    assert torch.isfinite(grad) and grad > 0


def test_residual_normal_training_is_finite_and_moves_the_correction(loaders):
    torch.manual_seed(2)
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True))
    history = [model.optimize(depth, maps) for depth, maps in zip(*loaders)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    assert model.G_n.output_conv.weight.abs().sum() > 0  # the zero-initialised correction has started to learn


@pytest.mark.parametrize("albedo_cycle_noc", ["generated", "real"])
def test_the_albedo_cycle_reads_the_noc_the_recipe_names(loaders, albedo_cycle_noc):
    """With "real" the albedo cycle no longer depends on G_depth (the paper's form reads the NOC of
    its depth); with "film" the code reaches G_da's output."""
    torch.manual_seed(3)
    model = MapsModel(dataclasses.replace(TINY, albedo_cycle_noc=albedo_cycle_noc, latent_mode="film"))
    depth, maps = next(zip(*loaders))
    terms = model(depth, maps)
    model.zero_grad()
    terms["cyc_da"].backward()
    grad = sum(float(p.grad.abs().sum()) for p in model.G_depth.parameters() if p.grad is not None)
    assert (grad == 0) == (albedo_cycle_noc == "real")
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.G_da.film.parameters())
    with pytest.raises(ValueError, match="albedo_cycle_noc must be"):
        dataclasses.replace(TINY, albedo_cycle_noc="true")


def test_depth_blur_coarsens_the_top_cycles_depth_on_the_object_only(loaders):
    """Each image gets its own σ in [0, depth_blur]: the object's depth changes (edges and detail are
    averaged), the background and the mask do not, and training stays finite; off, the input is the
    data's depth exactly."""
    from ngp_mi.models.maps import coarsen_depth, depth_to_net

    depth, maps = next(zip(*loaders))
    d, m = depth["depth"], depth["mask"]
    torch.manual_seed(4)
    coarse = coarsen_depth(d, m, 3.0)
    assert torch.equal(coarse[m == 0], d[m == 0]) and torch.isfinite(coarse).all()
    changed = [(c - x)[mm > 0].abs().max() > 1e-4 for c, x, mm in zip(coarse, d, m)]
    assert sum(changed) >= 2  # σ ~ U(0, 3): all but a vanishing σ move the depth
    assert coarse[m > 0].min() >= d[m > 0].min() - 1e-6 and coarse[m > 0].max() <= d[m > 0].max() + 1e-6
    assert torch.equal(coarsen_depth(d, m, 0.0), d)
    torch.manual_seed(5)
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True, depth_blur=3.0))
    history = [model.optimize(depth, maps) for depth, maps in zip(*loaders)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    plain = MapsModel(TINY)
    plain(depth, maps)
    assert torch.equal(plain.visuals["depth_r"], depth_to_net(d, m))
    with pytest.raises(ValueError, match="depth_blur must be"):
        dataclasses.replace(TINY, depth_blur=-1.0)


def test_normal_cycle_blur_trains_g_n_on_a_blurred_reconstruction_with_gradient_to_g_depth(loaders):
    torch.manual_seed(6)
    # the paper's G_n: the residual's zero-initialised last layer would block the gradient to G_depth
    model = MapsModel(dataclasses.replace(TINY, normal_cycle_blur=3.0))
    depth, maps = next(zip(*loaders))
    terms = model(depth, maps)
    model.zero_grad()
    terms["cyc_n"].backward()
    for net in (model.G_n, model.G_depth):  # the blur is a convolution: G_depth still learns from the cycle
        grad = sum(float(p.grad.abs().sum()) for p in net.parameters() if p.grad is not None)
        assert math.isfinite(grad) and grad > 0
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True, normal_cycle_blur=3.0))
    history = [model.optimize(depth, maps) for depth, maps in zip(*loaders)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    with pytest.raises(ValueError, match="normal_cycle_blur must be"):
        dataclasses.replace(TINY, normal_cycle_blur=9.0)


@pytest.mark.parametrize("source", ["generated", "real", "coarse"])
def test_the_normal_cycle_reads_the_depth_the_recipe_names(loaders, source):
    """L_n^cyc's G_n reads G_depth's depth (the paper's, with gradient to G_depth), the real maps' own
    depth, or their coarse depth; one training step stays finite, and "coarse" without coarse depth
    in the batch is a clear error."""
    from ngp_mi.models.maps import depth_to_net, smooth_depth

    torch.manual_seed(7)
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True, normal_cycle_depth=source))
    depth, maps = next(zip(*loaders))
    coarse = smooth_depth(maps["depth"], maps["mask"], 2.0)  # any other depth of the same views
    maps = {**maps, "coarse_depth": coarse, "coarse_mask": maps["mask"]}
    generated = torch.rand_like(maps["depth"]) * 2 - 1
    expected = {"generated": generated, "real": depth_to_net(maps["depth"], maps["mask"]),
                "coarse": depth_to_net(coarse, maps["mask"])}[source]
    assert torch.equal(model.normal_cycle_input(generated, maps), expected)
    assert all(math.isfinite(v) for v in model.optimize(depth, maps).values())
    if source == "coarse":
        without = {k: v for k, v in maps.items() if not k.startswith("coarse_")}
        with pytest.raises(ValueError, match=r"needs the real maps' coarse depth: set \[data\] coarse_shapes"):
            model.normal_cycle_input(generated, without)
    with pytest.raises(ValueError, match="normal_cycle_depth must be one of"):
        dataclasses.replace(TINY, normal_cycle_depth="blurred")


def test_the_normal_cycle_agreement_compares_only_the_pixels_where_both_depths_agree(loaders):
    """``normal_cycle_agreement``: L_n^cyc ignores the pixels where G_n's input and the real depth
    disagree (a surface off by more than the tolerance, or an object pixel on one side only) and
    keeps the agreeing ones, background included; a step stays finite."""
    from ngp_mi.models.maps import smooth_depth

    torch.manual_seed(8)
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True, normal_cycle_depth="coarse",
                                          normal_cycle_agreement=0.05))
    depth, maps = next(zip(*loaders))
    mask = maps["mask"].clone()
    coarse = smooth_depth(maps["depth"], mask, 1.0)
    on = torch.nonzero(mask[0, 0] > 0)
    (y0, x0), (y1, x1) = on[0].tolist(), on[len(on) // 2].tolist()
    coarse[0, 0, y0, x0] += 0.2  # a misplaced surface
    coarse_mask = mask.clone()
    coarse_mask[0, 0, y1, x1] = 0  # a missing slat
    maps = {**maps, "coarse_depth": coarse * coarse_mask, "coarse_mask": coarse_mask}
    weight = model.normal_cycle_agreement(model.normal_cycle_input(None, maps), maps)
    assert weight[0, 0, y0, x0] == 0 and weight[0, 0, y1, x1] == 0
    assert weight[0, 0][(mask[0, 0] <= 0)].eq(1).all()  # both off the object
    off = ((coarse - maps["depth"]).abs() > 0.05)[mask * coarse_mask > 0].sum()  # the misplaced one too
    assert weight.sum() == weight.numel() - 1 - off
    normal = torch.nn.functional.normalize(torch.randn_like(maps["normal"]), dim=1)
    loss = losses.normal_cycle_loss(normal, maps["normal"], weight)
    changed = normal.clone()
    changed[0, :, y0, x0] = -changed[0, :, y0, x0]
    assert torch.equal(losses.normal_cycle_loss(changed, maps["normal"], weight), loss)
    assert not torch.equal(losses.normal_cycle_loss(changed, maps["normal"]), losses.normal_cycle_loss(normal, maps["normal"]))
    assert torch.allclose(losses.normal_cycle_loss(normal, maps["normal"], torch.ones_like(weight)),
                          losses.normal_cycle_loss(normal, maps["normal"]))
    assert all(math.isfinite(v) for v in model.optimize(depth, maps).values())
    assert MapsModel(TINY).normal_cycle_agreement(maps["depth"], maps) is None
    with pytest.raises(ValueError, match="normal_cycle_agreement must be"):
        dataclasses.replace(TINY, normal_cycle_agreement=-0.1)


def test_palette_albedo_and_masked_encoder_train_and_read_the_object_masks(loaders):
    """The switches of issue 15's exemplar experiment: G_da as part regions × code colours, E_da
    pooled over the object; E_da receives each domain's mask (a generated albedo's background is
    not exactly −1)."""
    torch.manual_seed(7)
    model = MapsModel(dataclasses.replace(TINY, latent_mode="film", albedo_head="palette", encoder_pool="masked"))
    masks = []
    forward = model.E_da.forward
    model.E_da.forward = lambda x, mask=None: masks.append(mask) or forward(x, mask)
    depth, maps = next(zip(*loaders))
    history = [model.optimize(depth, maps) for _ in range(2)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    assert len(masks) == 4 and all(m is not None for m in masks)
    assert torch.equal(masks[0], depth["mask"]) and torch.equal(masks[1], maps["mask"])
    for field, value in (("albedo_head", "texture"), ("encoder_pool", "max"), ("palette_background", "alpha")):
        with pytest.raises(ValueError, match=f"{field} must be"):
            dataclasses.replace(TINY, **{field: value})


def test_the_palette_background_from_the_mask_and_the_part_encoder_train(loaders):
    """``palette_background = "mask"`` and ``encoder_pool = "parts"`` in the full model: finite steps,
    and G_da's background is exactly −1 off the depth's object in the top cycle."""
    torch.manual_seed(7)
    model = MapsModel(dataclasses.replace(TINY, latent_mode="film", albedo_head="palette", encoder_pool="parts",
                                          palette_background="mask"))
    depth, maps = next(zip(*loaders))
    history = [model.optimize(depth, maps) for _ in range(2)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    off = depth["mask"].expand_as(model.visuals["albedo_g"]) == 0
    assert (model.visuals["albedo_g"][off] == -1).all()


def test_with_ema_the_generators_are_the_moving_averages_of_the_trained_ones(loaders, tmp_path):
    """[model] ema: the optimiser moves G_n_train …; G_n … follow θ̄ ← ema θ̄ + (1 − ema) θ and are what
    eval mode (inference, export) runs; a checkpoint keeps both; without ema one network each."""
    from ngp_mi.models.checkpoint import load_weights
    from ngp_mi.models.maps import GENERATORS

    torch.manual_seed(3)
    model = MapsModel(dataclasses.replace(TINY, ema=0.9, normal_residual=True))
    assert {f"{n}_train" for n in GENERATORS} <= set(model.networks())
    assert not any(n.endswith("_train") for n in MapsModel(TINY).networks())
    averages = {n: [p.detach().clone() for p in getattr(model, n).parameters()] for n in GENERATORS}
    depth, maps = next(zip(*loaders))
    assert all(math.isfinite(v) for v in model.optimize(depth, maps).values())
    for name in GENERATORS:
        trained = list(getattr(model, f"{name}_train").parameters())
        assert any(not torch.equal(a, b) for a, b in zip(averages[name], trained)), f"{name}_train did not move"
        for before, after, now in zip(averages[name], getattr(model, name).parameters(), trained):
            assert torch.allclose(after, 0.9 * before + 0.1 * now, atol=1e-6) and not after.requires_grad
    depth_net = torch.rand(1, 1, 32, 32) * 2 - 1
    with torch.no_grad():
        training = model.G_n_train(depth_net)
        model.eval()
        assert model.generator("G_n") is model.G_n and not torch.allclose(model.G_n(depth_net), training)
    twin = MapsModel(dataclasses.replace(TINY, ema=0.9, normal_residual=True))
    load_weights(twin.networks(), {f"{n}.{k}": v for n, net in model.networks().items()
                                   for k, v in net.state_dict().items()}, tmp_path / "x")
    assert all(torch.equal(a, b) for a, b in zip(twin.G_da_train.parameters(), model.G_da_train.parameters()))
    with pytest.raises(ValueError, match="ema"):
        MapsModel(dataclasses.replace(TINY, ema=1.0))


def test_with_normal_input_g_n_reads_the_depths_own_normals_beside_it(loaders):
    """``normal_input = "depth+normals"``: G_n's first layer reads four channels, its output follows
    the normals it is given, its own are held fixed (the depth's gradient is the one it gets with
    them passed in as constants), and training stays finite; an unknown input is refused by name."""
    torch.manual_seed(3)
    model = MapsModel(dataclasses.replace(TINY, normal_input="depth+normals"))
    assert model.uses_own_normals and not MapsModel(TINY).uses_own_normals
    first = next(m for m in model.G_n.modules() if isinstance(m, torch.nn.Conv2d))
    assert first.in_channels == 4
    depth, maps = next(zip(*loaders))
    cameras = cameras_of(maps)
    depth_net = depth_to_net(maps["depth"], maps["mask"]).requires_grad_(True)
    own = model.generate_normals(depth_net, cameras)
    given = model.generate_normals(depth_net, cameras, from_depth=maps["normal"])
    assert not torch.allclose(own, given)
    given.sum().backward()
    assert torch.isfinite(depth_net.grad).all() and depth_net.grad.abs().sum() > 0
    depth_net.grad = None
    own.sum().backward()  # the same gradient as with its own normals passed in as constants
    through_own = depth_net.grad.clone()
    depth_net.grad = None
    constant = normals_from_depth(*net_to_depth(depth_net.detach()), cameras)
    model.generate_normals(depth_net, cameras, from_depth=constant).sum().backward()
    assert torch.allclose(through_own, depth_net.grad)
    history = [model.optimize(d, m) for d, m in zip(*loaders)]
    assert all(math.isfinite(v) for step in history for v in step.values())
    with pytest.raises(ValueError, match="normal_input"):
        dataclasses.replace(TINY, normal_input="normals")


def test_a_zero_normal_gan_weight_skips_d_n_and_trains_the_generators_as_a_vanishing_one(loaders):
    """[model] lambda_gan_n = 0 computes neither L_n^GAN nor D_n's loss: D_n keeps its weights, and the
    generators take the step a vanishing weight (1e-30) gives, which still trains D_n."""
    depth, maps = next(zip(*loaders))
    models = {}
    for weight in (0.0, 1e-30):
        torch.manual_seed(12)
        models[weight] = MapsModel(dataclasses.replace(TINY, lambda_gan_n=weight))
        d_n = [p.detach().clone() for p in models[weight].D_n.parameters()]
        result = models[weight].optimize(depth, maps)
        trained = any(not torch.equal(a, b) for a, b in zip(d_n, models[weight].D_n.parameters()))
        assert trained == (weight > 0) and math.isfinite(result["G"]) and math.isfinite(result["D"])
    assert result["gan_n"] > 0
    for name in ("G_n", "G_da", "G_depth", "E_da", "D_da", "D_df"):
        for a, b in zip(getattr(models[0.0], name).parameters(), getattr(models[1e-30], name).parameters()):
            assert torch.allclose(a, b, rtol=1e-6, atol=1e-9), name


def test_normal_steps_move_g_n_alone_on_the_paired_normal_cycle(loaders):
    """[model] normal_steps: an extra step trains G_n alone on λ_n L_n^cyc of the paired input (the
    real depth here) — the other generators, the discriminators and their Adam moments untouched —
    and its loss is λ_n times the L1 of G_n's normals against the real ones; "generated" pairing is
    refused, since its input is G_depth's."""
    torch.manual_seed(11)
    model = MapsModel(dataclasses.replace(TINY, normal_residual=True, normal_cycle_depth="real", normal_steps=3))
    depth, maps = next(zip(*loaders))
    model.optimize(depth, maps)  # every parameter has Adam moments now
    others = [p for name in ("G_da", "G_depth", "E_da", "D_n", "D_da") for p in getattr(model, name).parameters()]
    before = [p.detach().clone() for p in others]
    moments = [model.opt_G.state[p]["exp_avg"].clone() for name in ("G_da", "G_depth", "E_da")
               for p in getattr(model, name).parameters()]
    g_n = [p.detach().clone() for p in model.G_n.parameters()]
    with torch.no_grad():
        expected = 25.0 * (model.generate_normals(depth_to_net(maps["depth"], maps["mask"]), cameras_of(maps))
                           - maps["normal"]).abs().mean()
    history = [model.optimize_normals(maps) for _ in range(30)]  # Adam carries the joint step's moments a few steps
    assert history[0] == pytest.approx(expected.item(), rel=1e-5)
    assert all(math.isfinite(v) for v in history) and history[-1] < history[0]
    assert any(not torch.equal(a, b) for a, b in zip(g_n, model.G_n.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(before, others))
    after = [model.opt_G.state[p]["exp_avg"] for name in ("G_da", "G_depth", "E_da")
             for p in getattr(model, name).parameters()]
    assert all(torch.equal(a, b) for a, b in zip(moments, after))
    result = model.optimize(depth, maps, [maps, maps])
    assert set(result) == {*MapsModel.loss_names, "cyc_n_alone"} and math.isfinite(result["cyc_n_alone"])
    with pytest.raises(ValueError, match="normal_steps_depth must be one of"):
        dataclasses.replace(TINY, normal_steps=2, normal_steps_depth="generated")
    with pytest.raises(ValueError, match=r"normal_steps must lie in \[1, 32\]"):
        dataclasses.replace(TINY, normal_steps=0)


def test_normal_steps_on_the_reconstructions_beside_the_papers_cycle(loaders):
    """normal_steps_depth = "coarse" with the paper's normal cycle: G_n's own steps read the real
    views' coarse depth (what ``reads_coarse_pairs`` asks training to load), the joint step G_depth's."""
    from ngp_mi.models.maps import smooth_depth

    torch.manual_seed(12)
    config = dataclasses.replace(TINY, normal_residual=True, normal_steps=2, normal_steps_depth="coarse")
    assert config.reads_coarse_pairs and not dataclasses.replace(config, normal_steps=1).reads_coarse_pairs
    model = MapsModel(config)
    depth, maps = next(zip(*loaders))
    coarse = smooth_depth(maps["depth"], maps["mask"], 2.0)
    paired = {**maps, "coarse_depth": coarse, "coarse_mask": maps["mask"]}
    with torch.no_grad():
        expected = 25.0 * (model.generate_normals(depth_to_net(coarse, maps["mask"]), cameras_of(maps))
                           - maps["normal"]).abs().mean()
    assert model.optimize_normals(paired) == pytest.approx(expected.item(), rel=1e-5)
    assert math.isfinite(model.optimize(depth, maps, [paired])["cyc_n_alone"])
    with pytest.raises(ValueError, match="needs the real maps' coarse depth"):
        model.optimize_normals(maps)


@pytest.mark.parametrize("ema", [0.0, 0.9])
def test_the_encoder_stage_moves_e_da_alone_and_lowers_the_exemplars_l1(loaders, ema):
    """optimize_encoder: E_da (the average that inference runs, with ema) learns the trained G_da's
    inverse — the L1 of G_da(NOC, G_n(d), μ(E_da(I_da))) against I_da falls on the batch it steps on;
    no other weight moves or keeps a gradient, and each network's requires_grad is as before."""
    torch.manual_seed(5)
    config = dataclasses.replace(TINY, ema=ema, albedo_head="palette", palette_background="mask",
                                 encoder_pool="masked", latent_mode="film")
    model = MapsModel(config).eval()
    _, maps = next(zip(*loaders))
    flags = {name: p.requires_grad for name, p in model.named_parameters()}
    before = {name: p.detach().clone() for name, p in model.named_parameters()}
    first = model.encoder_refit_loss(maps).item()
    history = [model.optimize_encoder(maps, lr=3e-3) for _ in range(15)]
    assert all(math.isfinite(h["encoder_l1"]) and h["lr"] == 3e-3 for h in history)
    assert abs(history[0]["encoder_l1"] - first) < 1e-6  # the loss it logs is the one it steps on
    assert model.encoder_refit_loss(maps).item() < 0.8 * first
    for name, p in model.named_parameters():
        moved = not torch.equal(before[name], p)
        # E_da_train (ema) stays too, and E_da's log σ² head: inference reads μ alone
        assert moved == (name.startswith("E_da.") and not name.startswith("E_da.logvar.")), name
        assert p.requires_grad == flags[name] and p.grad is None or name.startswith("E_da."), name
    assert set(model.visuals) == {"albedo_r", "albedo_refit"}
    # G_da's condition computed once per view (the stage's in-memory views) gives the same loss, and
    # it is decorate's: NOC(d) beside G_n(d)
    condition = model.encoder_condition(maps)
    assert torch.equal(model.encoder_refit_loss({**maps, "condition": condition}), model.encoder_refit_loss(maps))
    with torch.no_grad():
        decorated = model.decorate(maps["depth"], maps["mask"], maps, torch.zeros(len(condition), config.latent_dim))
    assert torch.equal(condition, model.albedo_condition(decorated["noc"], decorated["normal"]))
