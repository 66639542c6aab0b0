"""The 2-D modelling losses of NGP (paper App. B), one function per equation.

Adversarial terms use the least-squares objective (LSGAN, as the paper states): a discriminator
pushes real scores to 1 and fake ones to 0; a generator pushes its fakes' scores to 1. The
paper's equations are written with logs (the original GAN objective); the LSGAN form replaces
``log D(x)`` by ``(D(x) − 1)²`` and ``log(1 − D(G(z)))`` by ``D(G(z))²``. Cycle terms are L1.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch

Scores = torch.Tensor | Sequence[torch.Tensor]

LAMBDAS = {"depth": 10.0, "noc": 10.0, "n": 25.0, "da": 25.0, "df": 25.0, "z": 1.0, "kl": 0.001}  # App. "Training details"


def lsgan(scores: Scores, target_is_real: bool) -> torch.Tensor:
    """Least-squares GAN objective, averaged over patches and over discriminators."""
    scores = [scores] if isinstance(scores, torch.Tensor) else list(scores)
    target = 1.0 if target_is_real else 0.0
    return sum(((s - target) ** 2).mean() for s in scores) / len(scores)


def discriminator_loss(D: Callable[[torch.Tensor], Scores], real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """The discriminator's side of any adversarial term: ½ [(D(real) − 1)² + D(fake)²]; fakes detached."""
    return 0.5 * (lsgan(D(real), True) + lsgan(D(fake.detach()), False))


def adversarial_loss(D: Callable[[torch.Tensor], Scores], fake: torch.Tensor) -> torch.Tensor:
    """The generator's side of any adversarial term: (D(fake) − 1)²."""
    return lsgan(D(fake), True)


# Generator-side adversarial terms, named after the paper's equations.

def normal_gan_loss(D_n: Callable, normal_g: torch.Tensor) -> torch.Tensor:
    """L_n^GAN (App. B, Eq. loss_normal_gan): generated normals N^g = G_n(d^r) against real N^r."""
    return adversarial_loss(D_n, normal_g)


def albedo_gan_loss(D_da: Callable, albedo_g: torch.Tensor) -> torch.Tensor:
    """L_da^GAN (App. B, Eq. loss_diffuse_albedo_gan): I_da^g = G_da(NOC(d^r), G_n(d^r), z_da) against I_da^r."""
    return adversarial_loss(D_da, albedo_g)


def diffuse_gan_loss(D_df: Callable, diffuse_g: torch.Tensor) -> torch.Tensor:
    """L_df^GAN (App. B, Eq. loss_diffuse_gan): R_diff(N^g, I_da^g, L) against real I_df^r."""
    return adversarial_loss(D_df, diffuse_g)


def depth_gan_loss(D_depth: Callable, depth_g: torch.Tensor) -> torch.Tensor:
    """L_depth^GAN (App. B, Eq. loss_depth_gan): d^g = G_depth(I_df^r) against real d^r."""
    return adversarial_loss(D_depth, depth_g)


def noc_gan_loss(D_noc: Callable, noc_g: torch.Tensor) -> torch.Tensor:
    """L_noc^GAN (App. B, Eq. loss_noc_gan): NOC(G_depth(I_df^r)) against NOC(d^r)."""
    return adversarial_loss(D_noc, noc_g)


# Cycle-consistency terms.

def depth_cycle_loss(depth_cycled: torch.Tensor, depth_r: torch.Tensor) -> torch.Tensor:
    """L_depth^cyc (App. B, Eq. loss_depth_cyc): ‖G_depth(R_diff(G_n(d^r), G_da(…), L)) − d^r‖₁."""
    return (depth_cycled - depth_r).abs().mean()


def noc_cycle_loss(noc_cycled: torch.Tensor, noc_r: torch.Tensor) -> torch.Tensor:
    """L_noc^cyc (App. B, Eq. loss_noc_cyc): ‖NOC(d^g) − NOC(d^r)‖₁ along the depth cycle."""
    return (noc_cycled - noc_r).abs().mean()


def normal_cycle_loss(normal_cycled: torch.Tensor, normal_r: torch.Tensor,
                      weight: torch.Tensor | None = None) -> torch.Tensor:
    """L_n^cyc (App. B, Eq. loss_normal_cyc): ‖G_n(G_depth(R_diff(N^r, I_da^r, L))) − N^r‖₁.
    ``weight`` (N, 1, H, W): the mean over the pixels it selects only (all of them: the paper's)."""
    error = (normal_cycled - normal_r).abs()
    if weight is None:
        return error.mean()
    return (error * weight).sum() / (weight.sum() * error.shape[1]).clamp_min(1.0)


def albedo_cycle_loss(albedo_cycled: torch.Tensor, albedo_r: torch.Tensor) -> torch.Tensor:
    """L_da^cyc (App. B, Eq. loss_diffuse_cyc): ‖G_da(NOC(G_depth(I_df^r)), N^r, E_da(I_da^r)) − I_da^r‖₁."""
    return (albedo_cycled - albedo_r).abs().mean()


def diffuse_cycle_loss(diffuse_cycled: torch.Tensor, diffuse_r: torch.Tensor) -> torch.Tensor:
    """L_df^cyc (App. B): ‖R_diff(G_n(G_depth(I_df^r)), G_da(…, N^r, E_da(I_da^r)), L) − I_df^r‖₁."""
    return (diffuse_cycled - diffuse_r).abs().mean()


def latent_cycle_loss(z_recovered: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """L_z^cyc (App. B, Eq. loss_diff_cyc): ‖E_da(G_da(NOC(d^r), G_n(d^r), z_da)) − z_da‖₁ (on μ)."""
    return (z_recovered - z).abs().mean()


def kl_loss(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """L_KL (App. B): KL(N(μ, σ²) ‖ N(0, I)) = −½ Σ (1 + log σ² − μ² − σ²), mean over the batch."""
    return (-0.5 * (1 + logvar - mu ** 2 - logvar.exp()).sum(1)).mean()


def total_2d_loss(terms: dict[str, torch.Tensor], lambdas: dict[str, float] = LAMBDAS) -> torch.Tensor:
    """L_2D (App. B, Eq. 2D_modelling_loss): the five GAN terms plus the weighted cycle and KL terms.

    ``terms`` keys: ``gan_n, gan_da, gan_df, gan_depth, gan_noc`` (weight 1; ``lambdas["gan_n"]``, when
    given, weights L_n^GAN: ours, not the paper's) and ``cyc_n, cyc_da, cyc_df, cyc_depth, cyc_noc, cyc_z,
    kl`` (weights ``lambdas``).
    """
    weights = {"gan_n": lambdas.get("gan_n", 1.0), "gan_da": 1.0, "gan_df": 1.0, "gan_depth": 1.0, "gan_noc": 1.0,
               "cyc_n": lambdas["n"], "cyc_da": lambdas["da"], "cyc_df": lambdas["df"],
               "cyc_depth": lambdas["depth"], "cyc_noc": lambdas["noc"], "cyc_z": lambdas["z"], "kl": lambdas["kl"]}
    missing = set(weights) - set(terms)
    if missing:
        raise ValueError(f"total_2d_loss: missing terms {sorted(missing)}")
    return sum(weights[k] * terms[k] for k in weights)
