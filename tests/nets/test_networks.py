import pytest
import torch

from ngp_mi.nets.networks import (PatchDiscriminator, define_D, define_E, define_G, define_palette_G, object_mask,
                                  patch_receptive_field, upsampling)


def test_generator_shapes_and_latent_conditioning():
    g = define_G(6, 3, ngf=8, blocks=2, latent_dim=8)
    x, z = torch.randn(2, 6, 32, 32), torch.randn(2, 8)
    y = g(x, z)
    assert y.shape == (2, 3, 32, 32) and y.abs().max() <= 1
    assert not torch.allclose(g(x, z), g(x, torch.randn(2, 8)))  # the code changes the output
    with pytest.raises(ValueError, match="latent code"):
        g(x)
    with pytest.raises(ValueError, match="no latent"):
        define_G(1, 3, ngf=8, blocks=1)(torch.randn(1, 1, 16, 16), torch.randn(1, 8))


@pytest.mark.parametrize("size, nearest", [(30, "28 or 32"), (6, "8"), (33, "32 or 36")])
def test_the_generator_names_the_sizes_it_takes(size, nearest):
    g = define_G(1, 3, ngf=8, blocks=1)
    with pytest.raises(ValueError, match=rf"input {size}x32: .*multiples of 4 and at least 8 \(nearest: {nearest}\)"):
        g(torch.randn(1, 1, size, 32))
    assert g(torch.randn(1, 1, 8, 12)).shape == (1, 3, 8, 12)


def test_encoder_outputs_mean_and_log_variance():
    mu, logvar = define_E(3, latent_dim=8, nef=8)(torch.randn(3, 3, 64, 64))
    assert mu.shape == logvar.shape == (3, 8)


@pytest.mark.parametrize("field", [16, 34, 70, 142])
def test_patchgan_receptive_field_is_what_it_says(field):
    """The input region that influences one output score, measured by its gradient.

    Instance normalisation couples every pixel through its statistics; the receptive field of a
    PatchGAN is, by convention, that of its convolutions, so the norms are removed for the measurement.
    """
    assert PatchDiscriminator(3, field).receptive_field == field
    d = PatchDiscriminator(1, field, ndf=4)
    d.model = torch.nn.Sequential(*[m for m in d.model if not isinstance(m, torch.nn.InstanceNorm2d)])
    for m in d.modules():  # positive weights: no accidental zero in the gradient's support
        if isinstance(m, torch.nn.Conv2d):
            torch.nn.init.uniform_(m.weight, 0.1, 0.2)
    size = 2 * field + 32
    x = torch.zeros(1, 1, size, size, requires_grad=True)
    out = d.model(x)
    c = out.shape[-1] // 2
    out[0, 0, c, c].backward()
    rows = torch.nonzero(x.grad[0, 0].abs().sum(1)).flatten()
    assert rows.max() - rows.min() + 1 == field
    assert patch_receptive_field(3) == 70


def test_multi_discriminator_and_size_check():
    d = define_D(3, (34, 70), ndf=8)
    scores = d(torch.randn(2, 3, 64, 64))
    assert len(scores) == 2 and scores[0].shape[-1] > scores[1].shape[-1]
    with pytest.raises(ValueError, match="at least 48x48"):
        define_D(3, (142,), ndf=8)(torch.randn(1, 3, 32, 32))


def _interior_spread(mode: str) -> tuple[float, float]:
    """Std over 6 latent codes of a random-weight generator's output, averaged over the interior of
    a 256² image (64 px from every border), and the output's std over pixels."""
    torch.manual_seed(0)
    G = define_G(6, 3, 16, 2, latent_dim=8, latent_mode=mode).eval()
    x = torch.randn(1, 6, 256, 256)
    with torch.no_grad():
        outs = torch.cat([G(x, torch.randn(1, 8)) for _ in range(6)])
    return float(outs[..., 64:-64, 64:-64].std(0).mean()), float(outs.std())


def test_a_concatenated_code_is_removed_by_the_instance_norms_and_film_keeps_it():
    """Issue 15's "G_da ignores z_da": a constant code concatenated before conv → instance norm adds
    a per-channel constant the norm subtracts, so only the zero-padded borders see it."""
    concat, concat_std = _interior_spread("concat")
    film, film_std = _interior_spread("film")
    assert concat < 0.05 * concat_std  # away from the borders the code changes next to nothing
    assert film > 10 * concat and film > 0.2 * film_std
    with pytest.raises(ValueError, match="latent_mode must be one of"):
        define_G(6, 3, 8, 1, latent_dim=8, latent_mode="add")


def _square(colour: tuple[float, float, float], side: int, size: int = 64) -> torch.Tensor:
    """A network-space albedo map: a flat ``colour`` square of ``side`` px on the background (−1)."""
    image = -torch.ones(1, 3, size, size)
    lo = (size - side) // 2
    image[:, :, lo:lo + side, lo:lo + side] = torch.tensor(colour)[:, None, None]
    return image


def test_masked_pooling_averages_the_features_over_the_object():
    torch.manual_seed(0)
    mean, masked = define_E(3, 8, nef=8, pool="mean"), define_E(3, 8, nef=8, pool="masked")
    masked.load_state_dict(mean.state_dict())  # the same weights: only the pooling differs
    large = _square((0.4, -0.2, 0.1), 24)
    assert not torch.allclose(mean(large)[0], masked(large)[0], atol=1e-4)
    # the heads read the features averaged over the object (its mask at their scale)
    h = masked.features[:-1](large)
    weight = torch.nn.functional.adaptive_avg_pool2d(object_mask(large), h.shape[-2:])
    expected = masked.mu((h * weight).sum((2, 3)) / weight.sum((2, 3)))
    assert torch.allclose(masked(large)[0], expected, atol=1e-6)
    assert torch.allclose(masked(large)[0], masked(large, object_mask(large))[0])
    with pytest.raises(ValueError, match="encoder pool must be one of"):
        define_E(3, 8, nef=8, pool="max")


def test_the_palette_generator_paints_each_region_a_colour_of_the_code():
    torch.manual_seed(0)
    G = define_palette_G(6, ngf=8, blocks=1, latent_dim=8, parts=3)
    x, z = torch.randn(2, 6, 32, 32), torch.randn(2, 8)
    y = G(x, z)
    assert y.shape == (2, 3, 32, 32) and y.abs().max() <= 1
    # every pixel is a convex combination of the background (−1) and the code's part colours
    colours = torch.cat([-torch.ones(2, 1, 3), torch.tanh(G.colours(z)).view(2, 3, 3)], 1)
    assert (y >= colours.amin(1)[:, :, None, None] - 1e-6).all() and (y <= colours.amax(1)[:, :, None, None] + 1e-6).all()
    assert (G(x, torch.randn(2, 8)) - y).abs().mean() > 0.01  # the code changes the colours
    y.mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in G.parameters())


def _two_part_object(size: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """G_da's input (NOC, N) of a square object whose upper half is one part and lower half another
    (the NOC's y tells them apart), and its albedo: red above, blue below, −1 off the object."""
    x = -torch.ones(1, 6, size, size)
    lo, hi = size // 4, 3 * size // 4
    ys = torch.linspace(-0.9, 0.9, hi - lo)
    x[:, 0, lo:hi, lo:hi] = 0.2
    x[:, 1, lo:hi, lo:hi] = ys[:, None]
    x[:, 2, lo:hi, lo:hi] = 0.1
    x[:, 3:, lo:hi, lo:hi] = 0.0
    target = -torch.ones(1, 3, size, size)
    target[:, :, lo:lo + (hi - lo) // 2, lo:hi] = torch.tensor([0.8, -0.6, -0.6])[:, None, None]
    target[:, :, lo + (hi - lo) // 2:hi, lo:hi] = torch.tensor([-0.6, -0.6, 0.8])[:, None, None]
    return x, target


def test_the_palette_background_from_the_mask_keeps_the_parts_apart():
    """With ``background = "mask"`` the background is exactly −1 wherever the NOC is, the parts'
    weights sum to one on the object, and a two-part object is learnt as two colours."""
    torch.manual_seed(0)
    x, target = _two_part_object()
    G = define_palette_G(6, ngf=8, blocks=1, latent_dim=4, parts=3, background="mask")
    z = torch.zeros(1, 4)
    weights = G.weights(x, z)
    mask = object_mask(x[:, :3])
    assert torch.equal(weights[:, 0:1], 1 - mask)
    assert torch.allclose(weights[:, 1:].sum(1, keepdim=True), mask, atol=1e-6)
    optimizer = torch.optim.Adam(G.parameters(), lr=3e-3)
    for _ in range(200):
        loss = (G(x, z) - target).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    y = G(x, z)
    assert torch.equal(y[:, :, mask[0, 0] == 0], target[:, :, mask[0, 0] == 0])  # −1, exactly
    on_object = (y - target).abs().mean(1)[mask[:, 0] > 0].mean()
    assert on_object < 0.05, f"a two-colour object came back with an L1 of {on_object:.3f} on the object"
    with pytest.raises(ValueError, match="palette background must be one of"):
        define_palette_G(6, ngf=8, blocks=1, latent_dim=4, background="alpha")


def test_the_part_encoder_reads_exact_colour_means_of_its_regions():
    """E_da with ``pool = "parts"``: each region's colour is the weighted mean of the object's pixels
    (the background never counts), and the code is a linear function of those colours."""
    torch.manual_seed(0)
    E = define_E(3, 6, nef=8, pool="parts", parts=2)
    image = _square((0.4, -0.2, 0.1), 24)
    image[:, :, 20:32, 20:44] = torch.tensor([-0.5, 0.7, 0.3])[:, None, None]  # a second part: the square's top
    mask = object_mask(image)
    weights = E.region_weights(image, mask)
    assert torch.allclose(weights.sum(1, keepdim=True), mask, atol=1e-6)
    expected = torch.stack([(image * w).sum((2, 3)) / w.sum((2, 3)) for w in weights.split(1, 1)], 1)
    colours = E.part_colours(image)
    assert torch.allclose(colours, expected, atol=1e-5)
    # every region's colour lies between the object's two colours, whatever the partition
    assert (colours[..., 1] >= -0.2 - 1e-5).all() and (colours[..., 1] <= 0.7 + 1e-5).all()
    # uniform regions (a zero last layer) give every region the object's mean colour
    last = E.regions[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    mean = (image * mask).sum((2, 3)) / mask.sum((2, 3))
    assert torch.allclose(E.part_colours(image), mean[:, None].expand(1, 2, 3), atol=1e-5)
    mu, logvar = E(image)
    assert mu.shape == logvar.shape == (1, 6)
    assert torch.allclose(mu, E.mu(E.part_colours(image).flatten(1)), atol=1e-6)


def test_resize_upsampling_weighs_every_pixel_alike_and_the_transposed_one_does_not():
    """A constant feature map through the decoder's ×2 layer: the stride-2 transposed convolution
    (one kernel tap per axis on even pixels, two on odd) comes out 2-periodic inside the image; the
    nearest ×2 + convolution comes out constant there. Both keep the generator's shapes."""
    torch.manual_seed(0)
    flat = torch.ones(1, 4, 8, 8)
    for mode, periodic in (("transpose", True), ("resize", False)):
        layer = upsampling(4, 3, mode)
        with torch.no_grad():
            inner = layer(flat)[..., 2:-2, 2:-2]
        assert inner.shape[-2:] == (12, 12)
        spread = (inner - inner.mean((-2, -1), keepdim=True)).abs().max().item()
        assert (spread > 1e-3) is periodic, mode
        if periodic:  # even and odd pixels differ, pixels two apart do not
            assert torch.allclose(inner[..., ::2, ::2], inner[..., ::2, ::2][..., :1, :1].expand(-1, -1, 6, 6), atol=1e-6)
    generator = define_G(6, 3, ngf=8, blocks=1, upsample="resize")
    assert generator(torch.randn(2, 6, 16, 16)).shape == (2, 3, 16, 16)
    with pytest.raises(ValueError, match="upsample must be one of"):
        define_G(6, 3, ngf=8, blocks=1, upsample="bilinear")
