"""The reflectance-map generation system of NGP (paper Sec. 3.4, Fig. "architecture", App. B).

Networks: G_n (depth → normals), G_da (NOC ⊕ normals, z_da → diffuse albedo), G_depth (diffuse
image → depth), E_da (albedo → μ, log σ² of z_da), and the discriminators D_n, D_da (small, 34-pixel
receptive field), D_df, D_depth, D_noc (mid and large: 70 and 142 pixels).

Two cycles per step, on unpaired batches (paper Fig. "architecture"):

* top — real depth d^r: N^g = G_n(d^r); I_da^g = G_da(NOC(d^r), N^g, z_da); I_df^g = R_diff(N^g, I_da^g, L);
  back to depth through G_depth, and to z_da through E_da;
* bottom — real maps (N^r, I_da^r): I_df^r = R_diff(N^r, I_da^r, L); d^g = G_depth(I_df^r); back to normals
  through G_n, to albedo through G_da(NOC(d^g), N^r, E_da(I_da^r)), and to the diffuse image.

R_diff is the project's differentiable Dr.Jit operator under the 4 overhead lights, in each view's
camera space. Value ranges at the network boundary: depth ``(d − 2) / 0.6`` on the object and −1
on the background (a generated depth's mask is ``M(d) = [net > −0.97]``, the paper's thresholding);
albedo, NOC and diffuse images ``2x − 1``; normals as they are.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Sequence

import torch
from torch import nn

from ngp_mi.camera import Camera
from ngp_mi.lights import overhead_rig
from ngp_mi.models import losses
from ngp_mi.models.base import BaseModel, config_from_dict, update_moving_average
from ngp_mi.nets.networks import ENCODER_POOLS, PaletteGenerator, define_D, define_E, define_G, define_palette_G
from ngp_mi.render.from_depth import noc_from_depth_batch, normals_from_depth, smooth_depth
from ngp_mi.render.shading import DEFAULT, CameraLights, Constants, shade

DEPTH_CENTER, DEPTH_SCALE, MASK_THRESHOLD = 2.0, 0.6, -0.97
NORMAL_CYCLE_DEPTHS = ("generated", "real", "coarse")
PAIRED_DEPTHS = ("real", "coarse")  # depths of the same shape and view as the real normals
NORMAL_INPUTS = ("depth", "depth+normals")
GENERATORS = ("G_n", "G_da", "G_depth", "E_da")


@dataclasses.dataclass(frozen=True)
class MapsConfig:
    ngf: int = 64
    blocks: int = 9
    nef: int = 64
    ndf: int = 64
    latent_dim: int = 8
    lr: float = 1e-4
    beta1: float = 0.5
    # R_BP's constants of this model's family (Constants: chairs 0.8 / 0.2, cars 0.6 / 0.4); NGP-BP
    # shades with all three.
    k_d: float = DEFAULT.k_d
    k_s: float = DEFAULT.k_s
    alpha: float = DEFAULT.alpha
    # R_diff's own k_d (training's diffuse images, NGP's image); None: k_d, the paper's. 1 (the `cpu`
    # recipe) makes R_diff / π the radiance of a Lambertian surface of the albedo map, as the
    # path-traced references are; the paper's k_d < 1 leaves R_diff dark where R_BP's specular term
    # is left out. See Constants.k_diff.
    k_diff: float | None = None
    rf_maps: tuple[int, ...] = (70, 142)
    rf_albedo: tuple[int, ...] = (34,)
    # G_n predicts a correction to the normals of the input depth (finite differences, held fixed)
    # instead of the normals themselves; off in the paper's G_n. See :meth:`MapsModel.generate_normals`.
    normal_residual: bool = False
    # What G_n reads: "depth" (the paper's: the depth map alone) or "depth+normals" (the depth and its
    # finite-difference normals, held fixed, as four channels): G_n then need not learn to
    # differentiate a depth map before it can correct it. See :meth:`MapsModel.generate_normals`.
    normal_input: str = "depth"
    # How z_da enters G_da: "concat" (the paper's, BicycleGAN's) or "film" (per-channel modulation
    # after each instance norm, which otherwise removes a concatenated constant code). See
    # :class:`ngp_mi.nets.networks.ResnetGenerator`.
    latent_mode: str = "concat"
    # Which NOC the albedo cycle conditions G_da on: "generated" (the paper's: NOC of G_depth's depth
    # of the real maps' diffuse image, a blob while G_depth is young) or "real" (NOC of the real maps'
    # own depth: BicycleGAN's conditional-VAE path, a usable geometry from the first step).
    albedo_cycle_noc: str = "generated"
    # Blur the top cycle's input depth by a masked Gaussian of σ ~ U(0, depth_blur) px per image, so
    # G_n and G_da learn on coarse depth as they meet it at inference (the paper gets this from
    # decorating G_shape's coarse shapes, [data] coarse_shapes); 0: off, the paper's. See
    # :func:`coarsen_depth`.
    depth_blur: float = 0.0
    # The same blur on the depth G_n reads inside the normal cycle (G_depth's depth of a real diffuse
    # image): the cycle's L1 against the real normals then asks G_n to restore what a coarse depth
    # lacks — a correctness signal, where depth_blur only adds adversarial pressure. 0: off.
    normal_cycle_blur: float = 0.0
    # The depth G_n reads inside the normal cycle, whose L1 compares its normals with the real ones:
    # "generated" (the paper's: G_depth's depth of the real maps' diffuse image), "real" (the real
    # maps' own depth) or "coarse" (the coarse reconstruction of the real maps' own shape, same view:
    # [data] coarse_shapes). "real" and "coarse" pair G_n's input with the normals of the same shape:
    # supervision the paper's unpaired setting does not use, which any dataset rendered from 3-D
    # models has. See :meth:`MapsModel.normal_cycle_input`.
    normal_cycle_depth: str = "generated"
    # Restrict L_n^cyc to the pixels where G_n's input in the normal cycle and the real depth agree:
    # both on the object within this depth difference (world units), or both off it. A coarse
    # reconstruction misses slats and misplaces surfaces; there the real normal belongs to another
    # surface, or to none G_n can see, and pairing them teaches G_n to invent geometry. 0: off (every
    # pixel, the paper's). See :meth:`MapsModel.normal_cycle_agreement`.
    normal_cycle_agreement: float = 0.0
    # G_da's output: "image" (the paper's: a ResNet generator's tanh image) or "palette" (a soft
    # partition into ``albedo_parts`` regions, one colour of z_da each; the colours bypass the instance
    # norms that remove absolute colour). See :class:`ngp_mi.nets.networks.PaletteGenerator`.
    albedo_head: str = "image"
    albedo_parts: int = 4
    # The palette's background: "slot" (a learned region of colour −1) or "mask" (the NOC's object
    # mask; the softmax runs over the parts only, which keeps every part alive). See
    # :class:`ngp_mi.nets.networks.PaletteGenerator`.
    palette_background: str = "slot"
    # E_da's pooling: "mean" over the image (BicycleGAN's) or "masked" over the object, so a colour is
    # not scaled by the object's size. See :class:`ngp_mi.nets.networks.ResnetEncoder`.
    encoder_pool: str = "mean"
    # Inference uses the average of the generators' trained weights, θ̄ ← ema θ̄ + (1 − ema) θ after
    # each step (Polyak averaging, as G_sp^real's ``ema``; ProGAN, StyleGAN): a GAN generator's
    # weights oscillate from step to step, and G_n's correction with them. 0: off, the paper's.
    ema: float = 0.0
    # L_n^GAN's weight (1 in the paper, as every GAN term). Where the normal cycle pairs G_n's input
    # with the real normals (normal_cycle_depth "real" / "coarse"), its L1 is supervision, and the
    # adversarial term only adds the noise of a young discriminator's opinion. At 0, D_n is not trained.
    lambda_gan_n: float = 1.0
    # G_n's updates per iteration: the joint step, then ``normal_steps`` − 1 steps of G_n alone on
    # λ_n L_n^cyc of further maps batches, G_n reading their own depth ("real") or their shape's
    # reconstruction ("coarse", [data] coarse_shapes) as ``normal_steps_depth`` says — the pairing of
    # normal_cycle_depth "real" / "coarse", which the joint step may or may not use (the number of
    # critic steps per generator step of WGAN, turned round: G_n learns from a paired signal for a
    # fraction of an iteration's cost). 1: the paper's. See :meth:`MapsModel.optimize_normals`.
    normal_steps: int = 1
    normal_steps_depth: str = "real"
    lambdas: tuple[tuple[str, float], ...] = tuple(losses.LAMBDAS.items())

    @property
    def reads_coarse_pairs(self) -> bool:
        """Whether training needs each real view's coarse reconstruction ([data] coarse_shapes)."""
        return self.normal_cycle_depth == "coarse" or (self.normal_steps > 1 and self.normal_steps_depth == "coarse")

    def __post_init__(self) -> None:
        if self.albedo_head not in ("image", "palette"):
            raise ValueError(f"albedo_head must be 'image' or 'palette', got {self.albedo_head!r}")
        if self.albedo_head == "palette" and (self.latent_dim < 1 or self.albedo_parts < 1):
            raise ValueError(f"albedo_head 'palette' needs latent_dim and albedo_parts >= 1, got "
                             f"{self.latent_dim} and {self.albedo_parts}")
        if self.palette_background not in PaletteGenerator.BACKGROUNDS:
            raise ValueError(f"palette_background must be one of {PaletteGenerator.BACKGROUNDS}, got "
                             f"{self.palette_background!r}")
        if self.encoder_pool not in ENCODER_POOLS:
            raise ValueError(f"encoder_pool must be one of {ENCODER_POOLS}, got {self.encoder_pool!r}")
        if self.normal_input not in NORMAL_INPUTS:
            raise ValueError(f"normal_input must be one of {NORMAL_INPUTS}, got {self.normal_input!r}")
        if self.normal_cycle_depth not in NORMAL_CYCLE_DEPTHS:
            raise ValueError(f"normal_cycle_depth must be one of {NORMAL_CYCLE_DEPTHS}, "
                             f"got {self.normal_cycle_depth!r}")
        if not 0 <= self.normal_cycle_agreement <= 1:
            raise ValueError(f"normal_cycle_agreement must be a depth difference within [0, 1] (0: off), "
                             f"got {self.normal_cycle_agreement!r}")
        if not 0 <= self.lambda_gan_n <= 100:
            raise ValueError(f"lambda_gan_n must lie in [0, 100], got {self.lambda_gan_n!r}")
        if not 1 <= self.normal_steps <= 32:
            raise ValueError(f"normal_steps must lie in [1, 32], got {self.normal_steps!r}")
        if self.normal_steps_depth not in PAIRED_DEPTHS:
            raise ValueError(f"normal_steps_depth must be one of {PAIRED_DEPTHS}, got {self.normal_steps_depth!r}")
        if not 0 <= self.ema < 1:
            raise ValueError(f"ema must lie in [0, 1), got {self.ema!r}")
        if self.albedo_cycle_noc not in ("generated", "real"):
            raise ValueError(f"albedo_cycle_noc must be 'generated' or 'real', got {self.albedo_cycle_noc!r}")
        if self.k_diff is not None and not 0 <= self.k_diff <= 10:
            raise ValueError(f"k_diff must lie in [0, 10] (or be absent: R_BP's k_d), got {self.k_diff!r}")
        for name in ("depth_blur", "normal_cycle_blur"):
            if not 0 <= getattr(self, name) <= 8:
                raise ValueError(f"{name} must be a blur radius σ in px within [0, 8], got {getattr(self, name)!r}")

    @property
    def constants(self) -> Constants:
        return Constants(self.k_d, self.k_s, self.alpha, self.k_diff)


def depth_to_net(depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return torch.where(mask > 0, ((depth - DEPTH_CENTER) / DEPTH_SCALE).clamp(-0.95, 1.0), -torch.ones_like(depth))


def net_to_depth(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth, mask) of a network depth map; the mask thresholds the depth (no gradient through it)."""
    mask = (x > MASK_THRESHOLD).to(x.dtype)
    return (DEPTH_CENTER + DEPTH_SCALE * x) * mask, mask


def coarsen_depth(depth: torch.Tensor, mask: torch.Tensor, max_sigma: float) -> torch.Tensor:
    """Each depth map blurred on its object by its own σ ~ U(0, ``max_sigma``) px (the masked Gaussian
    of :func:`smooth_depth`): detailed training depth turned into the coarse depth G_n meets at
    inference, in a range of coarseness rather than one."""
    if max_sigma <= 0:
        return depth
    sigmas = torch.rand(depth.shape[0]) * max_sigma
    return torch.cat([smooth_depth(d[None], m[None], float(s)) for d, m, s in zip(depth, mask, sigmas)])


def cameras_of(batch: dict[str, Any], size: tuple[int, int] | None = None) -> list[Camera]:
    """The cameras of a batch (K, E per view) for images of ``size`` (default: the batch's depth maps)."""
    h, w = size or batch["depth"].shape[-2:]
    return [Camera.from_K_E(K.numpy(), E.numpy(), w, h) for K, E in zip(batch["K"].cpu(), batch["E"].cpu())]


class MapsModel(BaseModel):
    """Owns the map networks, their optimisers and losses; :meth:`optimize` runs one training step."""

    network_names = ("G_n", "G_da", "G_depth", "E_da", "D_n", "D_da", "D_df", "D_depth", "D_noc")
    # opt_E: E_da alone, in the optional encoder stage (``[encoder]``, :meth:`optimize_encoder`)
    optimizer_names = ("opt_G", "opt_D", "opt_E")
    config_class, config_key = MapsConfig, "maps"
    loss_names = ("gan_n", "gan_da", "gan_df", "gan_depth", "gan_noc", "cyc_n", "cyc_da", "cyc_df", "cyc_depth",
                  "cyc_noc", "cyc_z", "kl", "G", "D")
    visual_names = ("depth_r", "normal_g", "albedo_g", "diffuse_g", "depth_cycled", "diffuse_r", "depth_g",
                    "normal_cycled", "albedo_cycled")

    def __init__(self, config: MapsConfig = MapsConfig()):
        super().__init__()
        self.config = config
        c = config
        self.G_n = define_G(1 if c.normal_input == "depth" else 4, 3, c.ngf, c.blocks)
        if c.normal_residual:  # start from the depth's own normals: the correction's last layer is zero
            last = self.G_n.output_conv
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        if c.albedo_head == "palette":
            self.G_da = define_palette_G(6, c.ngf, c.blocks, c.latent_dim, c.albedo_parts, c.palette_background)
        else:
            self.G_da = define_G(6, 3, c.ngf, c.blocks, latent_dim=c.latent_dim, latent_mode=c.latent_mode)
        self.G_depth = define_G(3, 1, c.ngf, c.blocks)
        self.E_da = define_E(3, c.latent_dim, c.nef, pool=c.encoder_pool, parts=c.albedo_parts)
        self.D_n = define_D(3, c.rf_maps, c.ndf)
        self.D_da = define_D(3, c.rf_albedo, c.ndf)
        self.D_df = define_D(3, c.rf_maps, c.ndf)
        self.D_depth = define_D(1, c.rf_maps, c.ndf)
        self.D_noc = define_D(3, c.rf_maps, c.ndf)
        if c.ema:  # G_n … hold the averages (what inference and export use), G_n_train … the trained weights
            for name in GENERATORS:
                setattr(self, f"{name}_train", copy.deepcopy(getattr(self, name)))
                getattr(self, name).requires_grad_(False)
            self.network_names = (*type(self).network_names, *(f"{name}_train" for name in GENERATORS))
        generators = [self.generator(name) for name in GENERATORS]
        self.discriminators = [self.D_n, self.D_da, self.D_df, self.D_depth, self.D_noc]
        betas = (c.beta1, 0.999)
        self.opt_G = torch.optim.Adam([p for m in generators for p in m.parameters()], lr=c.lr, betas=betas)
        self.opt_D = torch.optim.Adam([p for m in self.discriminators for p in m.parameters()], lr=c.lr, betas=betas)
        # the E_da inference runs (the average with ema); its rate is the encoder stage's
        self.opt_E = torch.optim.Adam(self.E_da.parameters(), lr=c.lr, betas=betas)
        self.lights = overhead_rig()

    @classmethod
    def config_from_recipe(cls, recipe: dict[str, Any]) -> MapsConfig:
        return config_from_dict(MapsConfig, recipe["model"])

    def generator(self, name: str) -> nn.Module:
        """The generator ``name`` (one of :data:`GENERATORS`) this mode runs: with ``ema``, in training
        mode the trained copy the optimiser moves, else the average; without, the one network."""
        return getattr(self, f"{name}_train" if self.config.ema and self.training else name)

    def update_average(self) -> None:
        """θ̄ ← ema θ̄ + (1 − ema) θ for each generator's weights (buffers copied); nothing without ``ema``."""
        if not self.config.ema:
            return
        for name in GENERATORS:
            update_moving_average(getattr(self, name), getattr(self, f"{name}_train"), self.config.ema)

    # ------------------------------------------------------------------ pieces
    def render_diffuse(self, normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor,
                       cameras: list[Camera]) -> torch.Tensor:
        """R_diff under the training lights, each view in its own camera space."""
        return shade(normal, albedo, mask, self.training_lights(cameras, normal), cameras,
                     k_d=self.config.constants.diffuse_k_d, mode="diffuse")

    def render_highlight(self, normal: torch.Tensor, mask: torch.Tensor, cameras: list[Camera]) -> torch.Tensor:
        """The specular term of R_BP alone (k_s, α of the constants, white specular albedo) under the
        training lights: (N, 1, H, W), where the Blinn-Phong model puts highlights."""
        c = self.config
        return shade(normal, torch.zeros_like(normal), mask, self.training_lights(cameras, normal), cameras, k_d=0.0,
                     k_s=c.k_s, alpha=c.alpha, mode="blinn_phong")[:, :1]

    def training_lights(self, cameras: list[Camera], like: torch.Tensor) -> CameraLights:
        """The training lights in each view's camera space, in ``like``'s dtype and device."""
        return CameraLights.from_lights(self.lights, cameras, dtype=like.dtype, device=like.device)

    @staticmethod
    def noc(depth: torch.Tensor, mask: torch.Tensor, batch: dict[str, Any]) -> torch.Tensor:
        """NOC(d, K, E) as a network map (2x − 1, background −1)."""
        noc = noc_from_depth_batch(depth, mask, batch["K"], batch["E"], batch["bounds"])
        return torch.where(mask > 0, 2 * noc - 1, -torch.ones_like(noc))

    def generate_normals(self, depth_net: torch.Tensor, cameras: list[Camera],
                         from_depth: torch.Tensor | None = None) -> torch.Tensor:
        """N^g = G_n(d). With ``normal_residual``, N^g = normalise(N_d + G_n(d)) on the object, N_d
        the finite-difference normals of d (no gradient through them: a lone pixel's zero-length
        cross product would send huge gradients into the depth). G_n then starts from the coarse
        shape's normals and learns the detail, instead of learning the differentiation too. With
        ``normal_input`` "depth+normals", G_n reads N_d beside d.
        ``from_depth``: N_d when the caller has it (of the true depth, where ``depth_net`` was moved
        to the training distance)."""
        c = self.config
        if self.uses_own_normals:
            depth, mask = net_to_depth(depth_net.detach())
            if from_depth is None:
                from_depth = normals_from_depth(depth, mask, cameras)
        g_n = self.generator("G_n")
        raw = g_n(depth_net) if c.normal_input == "depth" else g_n(torch.cat([depth_net, from_depth], 1))
        if not c.normal_residual:
            return raw
        return torch.where(mask > 0, torch.nn.functional.normalize(from_depth + raw, dim=1, eps=1e-6), raw)

    @property
    def uses_own_normals(self) -> bool:
        """Whether :meth:`generate_normals` needs the input depth's own normals (and so its cameras)."""
        return self.config.normal_residual or self.config.normal_input != "depth"

    @staticmethod
    def albedo_condition(noc: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        """G_da's condition, the one layout every caller uses: NOC(d) beside N (channels first), as G_da
        reads them in I_da = G_da(NOC(d), N, z_da); z_da enters G_da apart from it (``latent_mode``)."""
        return torch.cat([noc, normal], 1)

    def geometry_maps(self, depth: torch.Tensor, mask: torch.Tensor, views: dict[str, Any],
                      cameras: list[Camera] | None = None) -> dict[str, torch.Tensor]:
        """The part of :meth:`decorate` that does not depend on z_da: network-space ``depth``, its
        ``noc`` and N^g = G_n(d) as ``normal``. ``views`` holds K, E and bounds per image; ``cameras``
        are its cameras when the caller has them (built from ``views`` otherwise)."""
        if cameras is None and self.uses_own_normals:
            cameras = cameras_of(views, depth.shape[-2:])
        depth_net = depth_to_net(depth, mask)
        return {"depth": depth_net, "noc": self.noc(depth, mask, views),
                "normal": self.generate_normals(depth_net, cameras or [])}

    def decorate(self, depth: torch.Tensor, mask: torch.Tensor, views: dict[str, Any], z: torch.Tensor,
                 cameras: list[Camera] | None = None) -> dict[str, torch.Tensor]:
        """The maps NGP generates for a depth map (paper Eq. image formation, inside R_BP):
        N^g = G_n(d), I_da^g = G_da(NOC(d), N^g, z_da) (:meth:`geometry_maps`, then G_da).
        Returns network-space ``depth``, ``noc``, ``albedo`` (2x − 1) and unit-length-ish ``normal``."""
        maps = self.geometry_maps(depth, mask, views, cameras)
        albedo = self.generator("G_da")(self.albedo_condition(maps["noc"], maps["normal"]), z)
        return {**maps, "albedo": albedo}

    # ------------------------------------------------------------------ one step
    def forward(self, depth_batch: dict[str, Any], maps_batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        """Both cycles; returns the generator loss terms (and keeps the visuals)."""
        cams_d, cams_m = cameras_of(depth_batch), cameras_of(maps_batch)
        d_r, m_d = depth_batch["depth"], depth_batch["mask"]
        d_r = coarsen_depth(d_r, m_d, self.config.depth_blur)
        z = torch.randn(d_r.shape[0], self.config.latent_dim, device=d_r.device)
        top = self.decorate(d_r, m_d, depth_batch, z, cams_d)
        d_r_net, noc_r, normal_g, albedo_g_net = top["depth"], top["noc"], top["normal"], top["albedo"]
        diffuse_g = self.render_diffuse(normal_g, (albedo_g_net + 1) / 2, m_d, cams_d)
        diffuse_g_net = 2 * diffuse_g - 1
        G_depth, E_da = self.generator("G_depth"), self.generator("E_da")
        depth_cycled_net = G_depth(diffuse_g_net)
        noc_cycled = self.noc(*net_to_depth(depth_cycled_net), depth_batch)
        z_recovered, _ = E_da(albedo_g_net, m_d)

        normal_r, albedo_r, m_m = maps_batch["normal"], maps_batch["albedo"], maps_batch["mask"]
        albedo_r_net = 2 * albedo_r - 1
        diffuse_r = self.render_diffuse(normal_r, albedo_r, m_m, cams_m).detach()
        diffuse_r_net = 2 * diffuse_r - 1
        depth_g_net = G_depth(diffuse_r_net)
        noc_g = self.noc(*net_to_depth(depth_g_net), maps_batch)
        normal_cycle_depth = self.normal_cycle_input(depth_g_net, maps_batch)
        normal_cycled = self.generate_normals(normal_cycle_depth, cams_m)
        mu, logvar = E_da(albedo_r_net, m_m)
        z_encoded = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        noc_real = self.noc(maps_batch["depth"], m_m, maps_batch)
        noc_for_albedo = noc_real if self.config.albedo_cycle_noc == "real" else noc_g
        albedo_cycled_net = self.generator("G_da")(self.albedo_condition(noc_for_albedo, normal_r), z_encoded)
        diffuse_cycled = self.render_diffuse(normal_cycled, (albedo_cycled_net + 1) / 2, m_m, cams_m)

        self._for_d = {"normal": (normal_r, normal_g), "albedo": (albedo_r_net, albedo_g_net),
                       "diffuse": (diffuse_r_net, diffuse_g_net),
                       "depth": (depth_to_net(maps_batch["depth"], m_m), depth_g_net),
                       "noc": (noc_real, noc_g)}
        self.visuals = {"depth_r": d_r_net, "normal_g": normal_g, "albedo_g": albedo_g_net, "diffuse_g": diffuse_g_net,
                        "depth_cycled": depth_cycled_net, "diffuse_r": diffuse_r_net, "depth_g": depth_g_net,
                        "normal_cycled": normal_cycled, "albedo_cycled": albedo_cycled_net}
        return {
            # at weight 0 neither L_n^GAN nor D_n is computed (D_n, untrained, stays in the checkpoint)
            "gan_n": (losses.normal_gan_loss(self.D_n, normal_g) if self.config.lambda_gan_n
                      else normal_g.new_zeros(())),
            "gan_da": losses.albedo_gan_loss(self.D_da, albedo_g_net),
            "gan_df": losses.diffuse_gan_loss(self.D_df, diffuse_g_net),
            "gan_depth": losses.depth_gan_loss(self.D_depth, depth_g_net),
            "gan_noc": losses.noc_gan_loss(self.D_noc, noc_g),
            "cyc_depth": losses.depth_cycle_loss(depth_cycled_net, d_r_net),
            "cyc_noc": losses.noc_cycle_loss(noc_cycled, noc_r),
            "cyc_n": losses.normal_cycle_loss(normal_cycled, normal_r,
                                              self.normal_cycle_agreement(normal_cycle_depth, maps_batch)),
            "cyc_da": losses.albedo_cycle_loss(albedo_cycled_net, albedo_r_net),
            "cyc_df": losses.diffuse_cycle_loss(2 * diffuse_cycled - 1, diffuse_r_net),
            "cyc_z": losses.latent_cycle_loss(z_recovered, z),
            "kl": losses.kl_loss(mu, logvar),
        }

    def normal_cycle_input(self, depth_g_net: torch.Tensor | None, maps_batch: dict[str, Any],
                           source: str | None = None) -> torch.Tensor:
        """The depth (network range) G_n reads in the normal cycle L_n^cyc: G_depth's depth of the real
        diffuse image ``depth_g_net`` (the paper's), or the real maps' own depth or their shape's
        coarse reconstruction (``source``, default ``normal_cycle_depth``); blurred by ``normal_cycle_blur``."""
        source = source or self.config.normal_cycle_depth
        if source == "generated":
            depth, mask = net_to_depth(depth_g_net)
        elif source == "real":
            depth, mask = maps_batch["depth"], maps_batch["mask"]
        else:
            if "coarse_depth" not in maps_batch:
                raise ValueError("normal_cycle_depth / normal_steps_depth = 'coarse' needs the real maps' coarse "
                                 "depth: set [data] coarse_shapes (a `train shape` run or a model) in the recipe")
            depth, mask = maps_batch["coarse_depth"], maps_batch["coarse_mask"]
        if self.config.normal_cycle_blur > 0:
            depth = coarsen_depth(depth, mask, self.config.normal_cycle_blur)
        elif source == "generated":
            return depth_g_net  # as generated: the gradient reaches G_depth through it
        return depth_to_net(depth, mask)

    def normal_cycle_agreement(self, depth_in_net: torch.Tensor, maps_batch: dict[str, Any]) -> torch.Tensor | None:
        """The pixels L_n^cyc compares (``normal_cycle_agreement``; None: all): G_n's input
        ``depth_in_net`` and the real depth both on the object within the tolerance, or both off it."""
        tolerance = self.config.normal_cycle_agreement
        if tolerance == 0:
            return None
        depth, mask = net_to_depth(depth_in_net.detach())
        real, real_mask = maps_batch["depth"], maps_batch["mask"]
        on_both = (mask > 0) & (real_mask > 0) & ((depth - real).abs() <= tolerance)
        return (on_both | ((mask <= 0) & (real_mask <= 0))).to(depth.dtype)

    def discriminator_terms(self) -> torch.Tensor:
        pairs = [(self.D_da, "albedo"), (self.D_df, "diffuse"), (self.D_depth, "depth"), (self.D_noc, "noc")]
        if self.config.lambda_gan_n:
            pairs.insert(0, (self.D_n, "normal"))
        return sum(losses.discriminator_loss(D, *self._for_d[name]) for D, name in pairs)

    def optimize(self, depth_batch: dict[str, Any], maps_batch: dict[str, Any],
                 normal_batches: Sequence[dict[str, Any]] = ()) -> dict[str, float]:
        """One step: generators and E_da on L_2D (discriminators frozen), then the discriminators;
        then G_n alone on each of ``normal_batches`` (``normal_steps`` − 1 further maps batches,
        :meth:`optimize_normals`), whose mean loss is ``cyc_n_alone``."""
        for D in self.discriminators:
            D.requires_grad_(False)
        terms = self(depth_batch, maps_batch)
        loss_G = losses.total_2d_loss(terms, {**dict(self.config.lambdas), "gan_n": self.config.lambda_gan_n})
        self.optimizer_step(self.opt_G, loss_G)
        self.update_average()
        for D in self.discriminators:
            D.requires_grad_(True)
        loss_D = self.discriminator_terms()
        self.optimizer_step(self.opt_D, loss_D)
        result = {**{k: v.item() for k, v in terms.items()}, "G": loss_G.item(), "D": loss_D.item()}
        if normal_batches:
            result["cyc_n_alone"] = sum(map(self.optimize_normals, normal_batches)) / len(normal_batches)
        return result

    def scale_learning_rates(self, factor: float) -> float:
        """Set both optimisers' learning rates to ``factor`` × ``lr`` (a schedule's step); returns the rate."""
        for optimizer in (self.opt_G, self.opt_D):
            for group in optimizer.param_groups:
                group["lr"] = self.config.lr * factor
        return self.config.lr * factor

    @torch.no_grad()
    def encoder_condition(self, maps_batch: dict[str, Any]) -> torch.Tensor:
        """G_da's condition NOC(d) beside G_n(d) for the views of ``maps_batch`` (depth, mask, K, E,
        bounds), as :meth:`decorate` forms it with the networks inference runs: what the encoder stage
        reads, fixed while only E_da learns (so it can be computed once per view)."""
        maps = self.geometry_maps(maps_batch["depth"], maps_batch["mask"], maps_batch)
        return self.albedo_condition(maps["noc"], maps["normal"])

    def encoder_refit_loss(self, maps_batch: dict[str, Any]) -> torch.Tensor:
        """L_E = Σ_p M |G_da(NOC(d), G_n(d), μ(E_da(I_da))) − I_da| / (3 Σ_p M), colours in [0, 1]: how far
        the exemplar handle's albedo is from the exemplar, with the networks inference runs (the
        averages with ``ema``) and z_da = μ, as inference reads it. G_da's condition is the batch's
        ``condition`` when it carries one (:meth:`encoder_condition`, computed once per view),
        computed here otherwise. :meth:`optimize_encoder` freezes every weight but E_da's around it."""
        mask, albedo = maps_batch["mask"], maps_batch["albedo"]
        condition = maps_batch["condition"] if "condition" in maps_batch else self.encoder_condition(maps_batch)
        mu, _ = self.generator("E_da")(2 * albedo - 1, mask)
        reconstruction = (self.generator("G_da")(condition, mu) + 1) / 2
        self.visuals = {"albedo_r": 2 * albedo - 1, "albedo_refit": 2 * reconstruction - 1}
        return ((reconstruction - albedo).abs() * mask).sum() / (3 * mask.sum()).clamp_min(1.0)

    def optimize_encoder(self, maps_batch: dict[str, Any], lr: float) -> dict[str, float]:
        """One step of the encoder stage (beyond the paper; ``[encoder]`` in a recipe): E_da alone on
        :meth:`encoder_refit_loss` at rate ``lr``, every other network fixed — μ(E_da) trained as an
        amortised inversion of the trained G_da (the per-exemplar fit of
        :func:`ngp_mi.pipeline.fit_appearance`, learned once). In the map stage E_da learns beside a
        G_da that moves, and from z_da sampled around μ; here it learns the G_da that ships."""
        encoder = self.generator("E_da")
        for group in self.opt_E.param_groups:
            group["lr"] = lr
        flags = [(p, p.requires_grad) for p in self.parameters()]
        self.requires_grad_(False)  # G_da's weights would take (and keep) a gradient otherwise
        encoder.requires_grad_(True)
        try:
            loss = self.encoder_refit_loss(maps_batch)
            self.optimizer_step(self.opt_E, loss)
        finally:
            for p, flag in flags:
                p.requires_grad_(flag)
        return {"encoder_l1": loss.item(), "lr": lr}

    def optimize_normals(self, maps_batch: dict[str, Any]) -> float:
        """One of the ``normal_steps`` − 1 extra steps of G_n alone: λ_n L_n^cyc of G_n on the paired
        input of ``normal_steps_depth`` (:meth:`normal_cycle_input`) against the real normals, the
        discriminators and the other generators untouched. Returns the loss."""
        depth_in = self.normal_cycle_input(None, maps_batch, self.config.normal_steps_depth)
        normal = self.generate_normals(depth_in, cameras_of(maps_batch))
        loss = dict(self.config.lambdas)["n"] * losses.normal_cycle_loss(
            normal, maps_batch["normal"], self.normal_cycle_agreement(depth_in, maps_batch))
        # opt_G's other parameters get no gradient (set to None), so Adam leaves them and their moments alone
        self.optimizer_step(self.opt_G, loss)
        return loss.item()
