"""G_shape: the IM-NET autoencoder and the latent WGAN-GP (paper Sec. 3.2, "3D shape network").

Training has two phases (:mod:`ngp_mi.train_shape` runs them):

1. **Autoencoder.** E_voxel encodes a shape's voxels to a code c; the implicit decoder predicts the
   occupancy of points given c. :func:`occupancy_loss` (IM-NET Eq. 2) on point samples of growing
   resolution (16³ → 32³ → 64³).
2. **Latent GAN.** With the autoencoder frozen, G_latent maps z_s ~ N(0, I) to codes and a critic
   D_latent tells them from the training shapes' codes: Wasserstein loss with gradient penalty
   (:func:`critic_loss`, :func:`gradient_penalty`, :func:`generator_loss`; Gulrajani et al. 2017).

At inference ``G_shape(z_s) = extract(decoder(·, G_latent(z_s)))`` (:meth:`ShapeModel.shape`), and
:meth:`ShapeModel.differentiable_surface` returns mesh vertices whose gradient reaches z_s and the
decoder (see :mod:`ngp_mi.geometry.extract`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from ngp_mi.geometry.extract import Extraction, attach_iso_surface_gradient, default_coarse, extract_mesh
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.occupancy import grid_points
from ngp_mi.models.base import BaseModel, config_from_dict
from ngp_mi.nets.imnet import define_shape_nets

LEVEL = 0.5  # the decoder's iso-level: occupancy 1/2


@dataclasses.dataclass(frozen=True)
class ShapeConfig:
    """Sizes and optimiser settings; the defaults are IM-NET's / IM-GAN's."""

    voxel_resolution: int = 64
    ef: int = 32             # encoder base channels
    gf: int = 128            # decoder base width (hidden widths 8gf … gf)
    fourier_levels: int = 0  # positional encoding of the decoder's points (0: IM-NET's plain coordinates)
    code_dim: int = 256
    z_dim: int = 200         # |z_s| (paper)
    gan_hidden: int = 2048   # latent GAN hidden width
    ae_lr: float = 5e-5
    gan_lr: float = 1e-4
    gp_weight: float = 10.0  # λ of the gradient penalty
    critic_steps: int = 5    # critic updates per generator update


# --------------------------------------------------------------------------- losses

def occupancy_loss(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """IM-NET Eq. (2): mean squared error between predicted and true occupancy over the point samples."""
    return (predicted - target).square().mean()


def critic_loss(real_scores: torch.Tensor, fake_scores: torch.Tensor) -> torch.Tensor:
    """WGAN critic objective (Gulrajani et al. 2017, Alg. 1): ``E[D(fake)] − E[D(real)]`` (minimised)."""
    return fake_scores.mean() - real_scores.mean()


def gradient_penalty(critic: nn.Module, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """WGAN-GP penalty ``E[(‖∇D(x̂)‖₂ − 1)²]`` at x̂ = ε·real + (1 − ε)·fake, ε ~ U[0, 1] per sample."""
    eps = torch.rand(real.shape[0], 1, device=real.device, dtype=real.dtype)
    mixed = (eps * real + (1 - eps) * fake).requires_grad_(True)
    grad = torch.autograd.grad(critic(mixed).sum(), mixed, create_graph=True)[0]
    return (grad.norm(dim=1) - 1).square().mean()


def generator_loss(fake_scores: torch.Tensor) -> torch.Tensor:
    """WGAN generator objective: ``−E[D(G(z))]``."""
    return -fake_scores.mean()


# --------------------------------------------------------------------------- model

class ShapeModel(BaseModel):
    """Owns E_voxel, the decoder, G_latent, D_latent and their optimisers."""

    network_names = ("encoder", "decoder", "G_latent", "D_latent")
    optimizer_names = ("opt_ae", "opt_G", "opt_D")
    loss_names = ("ae_mse", "ae_point_accuracy", "gan_wasserstein", "gan_gp", "gan_G")
    config_class, config_key = ShapeConfig, "shape"

    def __init__(self, config: ShapeConfig = ShapeConfig()):
        super().__init__()
        self.config = config
        nets = define_shape_nets(config)
        self.encoder, self.decoder = nets["encoder"], nets["decoder"]
        self.G_latent, self.D_latent = nets["G_latent"], nets["D_latent"]
        self.has_encoder = True  # False: loaded from a model folder that ships no encoder (see encode)
        self.source = "a new model"
        c = config
        self.opt_ae = torch.optim.Adam([*self.encoder.parameters(), *self.decoder.parameters()], lr=c.ae_lr,
                                       betas=(0.5, 0.999))
        self.opt_G = torch.optim.Adam(self.G_latent.parameters(), lr=c.gan_lr, betas=(0.5, 0.9))
        self.opt_D = torch.optim.Adam(self.D_latent.parameters(), lr=c.gan_lr, betas=(0.5, 0.9))

    @classmethod
    def config_from_recipe(cls, recipe: dict[str, Any]) -> ShapeConfig:
        """``[model]``, with the encoder's voxel grid from ``[data]``."""
        voxels = recipe["data"].get("voxel_resolution", ShapeConfig.voxel_resolution)
        return config_from_dict(ShapeConfig, {"voxel_resolution": voxels, **recipe["model"]})

    # ---- phase 1
    def ae_step(self, voxels: torch.Tensor, points: torch.Tensor, occ: torch.Tensor) -> dict[str, float]:
        """One autoencoder update on (B, 1, V³) voxels and (B, N, 3) points with (B, N, 1) occupancy."""
        self.encoder.train()
        self.decoder.train()
        predicted = self.decoder(points, self.encoder(voxels))
        loss = occupancy_loss(predicted, occ)
        self.optimizer_step(self.opt_ae, loss)
        with torch.no_grad():
            accuracy = ((predicted > LEVEL) == (occ > 0.5)).float().mean()
        return {"ae_mse": loss.item(), "ae_point_accuracy": accuracy.item()}

    def require_encoder(self) -> "ShapeModel":
        """Self, or a clear error when the encoder's weights were not loaded (they would be a random
        initialisation, which reconstructs every shape as the same blob)."""
        if not self.has_encoder:
            raise ValueError(f"{self.source}: this shape prior was exported without its encoder, so it cannot "
                             "reconstruct a given shape; re-export it from its `train shape` run, or train an "
                             "encoder for it (`train shape` with [train] encoder_for)")
        return self

    @torch.no_grad()
    def encode(self, voxels: torch.Tensor, batch: int = 32) -> torch.Tensor:
        self.require_encoder().encoder.eval()
        return torch.cat([self.encoder(voxels[i:i + batch]) for i in range(0, len(voxels), batch)])

    # ---- phase 2
    def gan_step(self, real_codes: torch.Tensor) -> dict[str, float]:
        """``critic_steps`` critic updates and one generator update on a batch of training codes."""
        c = self.config
        n = real_codes.shape[0]
        for _ in range(c.critic_steps):
            with torch.no_grad():
                fake = self.G_latent(torch.randn(n, c.z_dim, device=real_codes.device))
            d_wgan = critic_loss(self.D_latent(real_codes), self.D_latent(fake))
            gp = gradient_penalty(self.D_latent, real_codes, fake)
            self.optimizer_step(self.opt_D, d_wgan + c.gp_weight * gp)
        for p in self.D_latent.parameters():
            p.requires_grad_(False)
        g = generator_loss(self.D_latent(self.G_latent(torch.randn(n, c.z_dim, device=real_codes.device))))
        self.optimizer_step(self.opt_G, g)
        for p in self.D_latent.parameters():
            p.requires_grad_(True)
        # -d_wgan estimates the Wasserstein distance between real and generated codes.
        return {"gan_wasserstein": -d_wgan.item(), "gan_gp": gp.item(), "gan_G": g.item()}

    # ---- inference
    def code_of(self, z: torch.Tensor) -> torch.Tensor:
        """Shape code(s) G_latent(z_s); z (z_dim,) or (B, z_dim)."""
        return self.G_latent(z[None] if z.ndim == 1 else z)

    def field(self, code: torch.Tensor, chunk: int = 32768):
        """The occupancy field of one code as a function (P, 3) → (P,), on the model's device."""
        code = code.reshape(1, -1)

        def occupancy(points: torch.Tensor) -> torch.Tensor:
            x = points.to(self.device, code.dtype)
            outs = [self.decoder(x[None, i:i + chunk], code)[0, :, 0] for i in range(0, len(x), chunk)]
            return torch.cat(outs).to(points.device)  # back where the caller's points are
        return occupancy

    @torch.no_grad()
    def occupancy_grid(self, code: torch.Tensor, resolution: int) -> np.ndarray:
        """Decoded occupancy (R, R, R) bool at the cell centres (the voxel grids' convention)."""
        self.decoder.eval()
        points = torch.as_tensor(grid_points(resolution).reshape(-1, 3), dtype=torch.float32)
        return (self.field(code)(points) > LEVEL).reshape((resolution,) * 3).cpu().numpy()

    @torch.no_grad()
    def extract(self, code: torch.Tensor, resolution: int = 128, coarse: int | None = None) -> Extraction:
        """Marching cubes of one code's field, coarse-to-fine: the coarse grid (default: the largest
        divisor of ``resolution`` up to 32 — 24 for 48³, 32 for 64³) finds the cells the surface
        passes through; a grid much coarser than that misses thin parts."""
        self.decoder.eval()
        if coarse is None:
            coarse = default_coarse(resolution)
        return extract_mesh(self.field(code.detach()), resolution, LEVEL, coarse=coarse, inside_above=True)

    def shape(self, z: torch.Tensor, resolution: int = 128, coarse: int | None = None) -> Extraction:
        """G_shape(z_s): the extracted mesh of one latent (z_dim,)."""
        self.G_latent.eval()
        with torch.no_grad():
            code = self.code_of(z.to(self.device))[0]
        return self.extract(code, resolution, coarse)

    def differentiable_surface(self, z: torch.Tensor, resolution: int = 64,
                               coarse: int | None = None) -> tuple[torch.Tensor, np.ndarray] | None:
        """Vertices (V, 3) of G_shape(z) differentiable w.r.t. z and the decoder / G_latent weights, and faces.

        None when the shape is empty. Values equal :meth:`shape`'s vertices.
        """
        code = self.code_of(z.to(self.device))[0]
        extraction = self.extract(code, resolution, coarse)
        if extraction.mesh is None:
            return None
        vertices = torch.as_tensor(extraction.mesh.vertices, device=self.device)
        return attach_iso_surface_gradient(vertices, self.field(code)), extraction.mesh.faces

    @torch.no_grad()
    def reconstruct(self, voxels: torch.Tensor, resolution: int = 64) -> Extraction:
        """decode(encode(voxels)) extracted: the autoencoder's version of a (V, V, V) occupancy grid."""
        code = self.encode(torch.as_tensor(voxels, dtype=torch.float32)[None, None].to(self.device))[0]
        return self.extract(code, resolution)


class CoarseShapes:
    """NGP's coarse shapes: a shape's occupancy grid function → its reconstruction by the shape
    autoencoder of a ``train shape`` run (marching cubes at ``resolution``), None when empty.

    The ``reconstruct`` of :func:`ngp_mi.data.sources.autoencoded_items` and ``render-dataset
    --coarse-shapes``; picklable (worker processes load the model themselves, once).
    """

    def __init__(self, run: str | Path, resolution: int = 64, load: Callable[[str], ShapeModel] | None = None):
        """``load`` reads the model from ``run`` (default: :meth:`ShapeModel.from_run`, a ``train shape``
        run; :func:`ngp_mi.models.pretrained.load_shape_prior` for a run or a model folder); module-level, so picklable."""
        self.run, self.resolution = str(run), int(resolution)
        self.load = load
        self.meta = {"shape_run": self.run, "resolution": self.resolution}
        self._model: ShapeModel | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_model": None}

    def __call__(self, grid: Callable[[int], np.ndarray]) -> TriangleMesh | None:
        if self._model is None:
            self._model = (self.load or ShapeModel.from_run)(self.run)
        return self._model.reconstruct(grid(self._model.config.voxel_resolution), self.resolution).mesh
