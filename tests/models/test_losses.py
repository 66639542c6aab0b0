import pytest
import torch

from ngp_mi.models import losses


def test_lsgan_objective_values():
    assert losses.lsgan(torch.ones(2, 1, 3, 3), True) == 0
    assert losses.lsgan(torch.zeros(4), False) == 0
    assert losses.lsgan([torch.full((5,), 0.5), torch.zeros(5)], True) == pytest.approx((0.25 + 1.0) / 2)
    d = lambda x: x.mean((1, 2, 3))  # noqa: E731  a "discriminator" scoring the mean
    real, fake = torch.ones(2, 1, 4, 4), torch.zeros(2, 1, 4, 4, requires_grad=True)
    assert losses.discriminator_loss(d, real, fake) == 0
    assert losses.adversarial_loss(d, fake) == 1
    assert not losses.discriminator_loss(d, real, fake).requires_grad  # fakes are detached for D
    assert losses.adversarial_loss(d, fake).requires_grad


def test_kl_and_cycles():
    assert losses.kl_loss(torch.zeros(3, 8), torch.zeros(3, 8)) == 0
    mu = torch.full((1, 2), 1.0)
    assert losses.kl_loss(mu, torch.zeros(1, 2)) == pytest.approx(1.0)  # -1/2 sum(1 - 1 - 1) over 2 dims
    a, b = torch.zeros(2, 3, 4, 4), torch.full((2, 3, 4, 4), 0.5)
    for fn in (losses.depth_cycle_loss, losses.noc_cycle_loss, losses.normal_cycle_loss,
               losses.albedo_cycle_loss, losses.diffuse_cycle_loss, losses.latent_cycle_loss):
        assert fn(a, b) == pytest.approx(0.5)


def test_total_loss_uses_the_paper_weights():
    names = ["gan_n", "gan_da", "gan_df", "gan_depth", "gan_noc", "cyc_n", "cyc_da", "cyc_df", "cyc_depth",
             "cyc_noc", "cyc_z", "kl"]
    total = losses.total_2d_loss({k: torch.tensor(1.0) for k in names})
    assert total.item() == pytest.approx(5 + 25 * 3 + 10 * 2 + 1 + 0.001)
    with pytest.raises(ValueError, match="missing terms"):
        losses.total_2d_loss({"gan_n": torch.tensor(1.0)})


def test_the_normal_gan_weight_scales_l_n_gan_alone():
    """[model] lambda_gan_n: 0 drops L_n^GAN from L_2D and leaves every other term's weight."""
    names = ["gan_n", "gan_da", "gan_df", "gan_depth", "gan_noc", "cyc_n", "cyc_da", "cyc_df", "cyc_depth",
             "cyc_noc", "cyc_z", "kl"]
    terms = {k: torch.tensor(float(i + 1)) for i, k in enumerate(names)}
    paper = losses.total_2d_loss(terms)
    assert losses.total_2d_loss(terms, {**losses.LAMBDAS, "gan_n": 0.0}).item() == pytest.approx(paper.item() - 1.0)
    assert losses.total_2d_loss(terms, {**losses.LAMBDAS, "gan_n": 0.25}).item() == pytest.approx(paper.item() - 0.75)
