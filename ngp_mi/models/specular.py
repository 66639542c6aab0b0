"""The realistic specular generator G_sp^real (paper Sec. 3.5, "Learning realistic specular generation").

G_sp^real takes the generated detailed normals N^g and the generated diffuse image I_df^g and
produces a realistic specular map I_rs^g; blending it with the diffuse image gives the composite
I_c^g = I_df^g ⊕ I_rs^g that a discriminator D_real compares with real images (the paper's
image-formation equation: I = R(…) ⊕ G_sp^real(Π_v(G_shape(z_s)))). The training data is only a
collection of real images; the paper trains it "with the same adversarial cycle-consistency idea"
as the map generators and gives no further detail, so the cycle is ours:

* generated → real → generated: I_df^g → I_c^g = I_df^g ⊕ G_sp(N^g, I_df^g) → F_sp(I_c^g) ≈ I_df^g;
* real → generated → real: I^r → Î_df = F_sp(I^r) → N̂ = G_n(G_depth(Î_df)) (the frozen map
  networks) → Î_df ⊕ G_sp(N̂, Î_df) ≈ I^r;

with F_sp (real image → diffuse image) the inverse generator, D_real on composites vs real images
and D_dfr on F_sp's diffuse images vs R_diff's. Cycle terms are L1 with weight λ_cyc (10, CycleGAN's
default; the paper gives none for this stage).

Conventions: ⊕ is addition in linear radiance, I = I_df / π + M ⊙ I_rs with I_rs ∈ [0, 1] (a
specular lobe only adds light, only on the object; the ``signed`` switch lets it darken, the sum
clamped at 0). I_df / π is the radiance of R_diff (see
``render.shading``), so composites and path-traced "real" images share one scale. D_real judges
sRGB-encoded images (2 sRGB − 1), as photographs are stored; the map networks keep their own
convention (diffuse network images are 2 R_diff − 1).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any, Callable

import torch

from ngp_mi.camera import Camera
from ngp_mi.models import losses
from ngp_mi.models.base import BaseModel, config_from_dict, update_moving_average
from ngp_mi.models.maps import MapsModel, cameras_of, net_to_depth
from ngp_mi.nets.networks import UPSAMPLES, ResnetGenerator, define_D, define_G


@dataclasses.dataclass(frozen=True)
class SpecularConfig:
    ngf: int = 64
    blocks: int = 9
    ndf: int = 64
    rf_image: tuple[int, ...] = (70, 142)
    lr: float = 1e-4
    beta1: float = 0.5
    lambda_cycle: float = 10.0
    # Beyond the paper (issue 15): start G_sp^real dark. I_rs = (tanh(h) + 1) / 2 starts at 0.5 for
    # h ≈ 0 — more light than the diffuse image's whole range (R_diff / π ≤ 0.32) — and a short
    # second stage leaves a grey-blue veil over the object. dark_start zeroes the last layer's weights
    # and sets its bias so that I_rs starts at DARK_START (a specular map is mostly black).
    dark_start: bool = False
    # Beyond the paper (issue 15): G_sp^real is the exponential moving average of the trained
    # generator's weights, θ̄ ← ema θ̄ + (1 − ema) θ after each step (Polyak averaging, as ProGAN,
    # StyleGAN and BigGAN evaluate their generators): a short adversarial stage ends at a point that
    # varies with the seed; the average is taken over its last ~1 / (1 − ema) steps. 0: off.
    ema: float = 0.0
    # Beyond the paper (issue 15): a grey specular map, I_rs the mean of G_sp^real's three channels.
    # The real images' materials are dielectrics, whose highlights carry the light's colour, not the
    # surface's; an RGB map can instead repaint the diffuse image's colour errors (seen: a blue tint
    # along thin rails where the reference has no highlight).
    grey: bool = False
    # Beyond the paper (issue 15): which diffuse images the generated → real cycle composites.
    # "generated" (the paper): N^g and I_df^g of a depth map with z_da ~ N(0, I). "exemplar": of a
    # real-maps view, with z_da = μ(E_da(its albedo)) and N^g = G_n(its depth) — the inputs NGP gets
    # with the exemplar handle. D_real then sees composites whose colours are already the real
    # distribution's, so what it asks G_sp^real to add is what R_diff lacks (highlights), not the
    # colour statistics of random z_da, which an additive map can only "fix" by adding light.
    diffuse_input: str = "generated"
    # Beyond the paper (issue 15): G_sp^real reads, beside N and I_df, the Blinn-Phong specular term
    # of N under the training lights (R_BP's k_s, α; NGP-BP's highlight, :meth:`MapsModel.render_highlight`).
    # Where a highlight can be is then given by the lights and the normals; the network learns how
    # real highlights look there, instead of finding their places from N alone.
    highlight_input: bool = False
    # Beyond the paper (issue 15): "add" (the paper's ⊕: I_rs ∈ [0, 1] only adds light) or "signed":
    # I_rs ∈ (−1, 1), the composite clamped at 0, so the map can also darken — the shadows and
    # occlusion of real images that R_diff lacks — and starts neutral (tanh(0) = 0) instead of at 0.5.
    blend: str = "add"
    # Beyond the paper (issue 15): weight of an L1 prior on the generated cycle's I_rs over the
    # object (:func:`specular_sparsity_loss`). The adversarial stage otherwise adds light wherever a
    # composite differs from real images, which for rough materials (the chairs' reference has
    # almost no highlight) is mostly the diffuse image's own errors; the prior keeps only the light
    # that pays for itself in L_real^GAN (on chair map networks past 3,000 steps: little, recall
    # ≤ 0.09 of the reference's excess, but it never makes the image worse; bench/RESULTS.md). 0: off.
    lambda_sparse: float = 0.0
    # Beyond the paper (issue 15): G_sp^real's two ×2 upsamplings, "transpose" (CycleGAN's stride-2
    # transposed convolutions, the paper's generators) or "resize" (nearest ×2 + 3×3 convolution,
    # :func:`~ngp_mi.nets.networks.upsampling`): the transposed ones leave a 2-pixel checkerboard in
    # the faint I_rs that ``lambda_sparse`` keeps (``compare``'s ``specular_nyquist``).
    upsample: str = "transpose"


def srgb_encode(linear: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function of linear values clipped to [0, 1], differentiable everywhere
    (the power branch is evaluated only where it is used, so its infinite slope at 0 never appears)."""
    x = linear.clamp(0.0, 1.0)
    power = 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055
    return torch.where(x <= 0.0031308, 12.92 * x, power)


def srgb_decode(encoded: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`srgb_encode` on [0, 1]."""
    x = encoded.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def image_to_net(radiance: torch.Tensor) -> torch.Tensor:
    """Linear radiance → the discriminators' image space, 2 sRGB(I) − 1."""
    return 2 * srgb_encode(radiance) - 1


def diffuse_radiance(diffuse_net: torch.Tensor) -> torch.Tensor:
    """The map networks' diffuse image (2 R_diff − 1) as linear radiance, R_diff / π."""
    return (diffuse_net + 1) / 2 / math.pi


def blend(diffuse_radiance: torch.Tensor, specular: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """⊕ of the paper's image formation (Sec. 3.5): I_c = I_df ⊕ I_rs = max(I_df + M ⊙ I_rs, 0), linear
    radiance (the clamp acts only for a signed I_rs, ``blend = "signed"``: radiance is not negative)."""
    return add_specular(diffuse_radiance, mask * specular)


def add_specular(diffuse_radiance: torch.Tensor, masked_specular: torch.Tensor) -> torch.Tensor:
    """:func:`blend` of an I_rs already zero off the object (what :meth:`SpecularModel.specular` returns)."""
    return (diffuse_radiance + masked_specular).clamp_min(0.0)


DIFFUSE_INPUTS = ("generated", "exemplar")
BLENDS = ("add", "signed")
DARK_START = 0.02  # I_rs everywhere at the start of a dark_start G_sp^real (linear radiance)


def start_dark(generator: ResnetGenerator, value: float = DARK_START) -> None:
    """Make a generator's image (tanh(h) + 1) / 2 start at ``value`` everywhere: its last
    convolution's weights zero, its bias atanh(2 value − 1) (gradients still reach the weights)."""
    last = generator.output_conv
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.constant_(last.bias, math.atanh(2 * value - 1))


def realistic_gan_loss(D_real: Callable, composite_net: torch.Tensor) -> torch.Tensor:
    """L_real^GAN (Sec. 3.5): composites I_c^g = I_df^g ⊕ G_sp^real(N^g, I_df^g) against real images."""
    return losses.adversarial_loss(D_real, composite_net)


def specular_cycle_loss(cycled: torch.Tensor, original: torch.Tensor) -> torch.Tensor:
    """L_sp^cyc (Sec. 3.5, "the same adversarial cycle-consistency idea"): L1 of either cycle above."""
    return (cycled - original).abs().mean()


def specular_sparsity_loss(specular: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_sp^sparse (ours, ``lambda_sparse``): the mean |I_rs| over the object's pixels and channels,
    a specular map is mostly black (the prior intrinsic-image decompositions put on their
    specular layers). ``specular`` is already zero off the object."""
    return specular.abs().sum() / (specular.shape[1] * mask.sum()).clamp_min(1.0)


class SpecularModel(BaseModel):
    """G_sp^real with its inverse F_sp and discriminators; :meth:`optimize` trains them on top of a
    frozen :class:`MapsModel` (the paper's second stage; App. "Training details")."""

    network_names = ("G_sp", "F_sp", "D_real", "D_dfr")
    optimizer_names = ("opt_sp_G", "opt_sp_D")  # beside the map networks' opt_G / opt_D in one checkpoint
    config_class, config_key = SpecularConfig, "specular"
    loss_names = ("gan_real", "gan_dfr", "cyc_generated", "cyc_real", "sparse", "G", "D")
    visual_names = ("diffuse_g", "specular_g", "composite_g", "real", "diffuse_of_real", "real_cycled")

    def __init__(self, config: SpecularConfig = SpecularConfig()):
        super().__init__()
        self.config = c = config
        if not 0 <= c.ema < 1:
            raise ValueError(f"specular.ema must lie in [0, 1), got {c.ema}")
        if c.blend not in BLENDS:
            raise ValueError(f"specular.blend must be one of {BLENDS}, got {c.blend!r}")
        if c.lambda_sparse < 0:
            raise ValueError(f"specular.lambda_sparse must be ≥ 0, got {c.lambda_sparse}")
        if c.diffuse_input not in DIFFUSE_INPUTS:
            raise ValueError(f"specular.diffuse_input must be one of {DIFFUSE_INPUTS}, got {c.diffuse_input!r}")
        if c.upsample not in UPSAMPLES:
            raise ValueError(f"specular.upsample must be one of {UPSAMPLES}, got {c.upsample!r}")
        self.G_sp = define_G(7 if c.highlight_input else 6, 3, c.ngf, c.blocks, upsample=c.upsample)
        if c.dark_start:
            start_dark(self.G_sp)
        if c.ema:  # G_sp holds the average (what inference and export use), G_sp_train the trained weights
            self.G_sp_train = copy.deepcopy(self.G_sp)
            self.G_sp.requires_grad_(False)
            self.network_names = (*type(self).network_names, "G_sp_train")
        self.F_sp = define_G(3, 3, c.ngf, c.blocks)
        self.D_real = define_D(3, c.rf_image, c.ndf)
        self.D_dfr = define_D(3, c.rf_image, c.ndf)
        betas = (c.beta1, 0.999)
        self.opt_sp_G = torch.optim.Adam([*self.trained_G_sp.parameters(), *self.F_sp.parameters()], lr=c.lr,
                                         betas=betas)
        self.opt_sp_D = torch.optim.Adam([*self.D_real.parameters(), *self.D_dfr.parameters()], lr=c.lr, betas=betas)

    @property
    def trained_G_sp(self) -> ResnetGenerator:
        """The generator the optimiser moves: G_sp itself, or with ``ema`` the copy G_sp averages."""
        return self.G_sp_train if self.config.ema else self.G_sp

    def update_average(self) -> None:
        """θ̄ ← ema θ̄ + (1 − ema) θ for G_sp's weights (buffers copied); nothing without ``ema``."""
        if self.config.ema:
            update_moving_average(self.G_sp, self.G_sp_train, self.config.ema)

    @classmethod
    def config_from_recipe(cls, recipe: dict[str, Any]) -> SpecularConfig | None:
        """From the ``[specular]`` table (its data keys aside); None for a run without the stage."""
        if "specular" not in recipe:
            return None
        fields = {f.name for f in dataclasses.fields(SpecularConfig)}
        return config_from_dict(SpecularConfig, {k: v for k, v in recipe["specular"].items() if k in fields})

    def specular(self, normal: torch.Tensor, diffuse_net: torch.Tensor, mask: torch.Tensor,
                 highlight: torch.Tensor | None = None) -> torch.Tensor:
        """I_rs = G_sp^real(N, I_df): linear radiance in [0, 1] (with ``blend = "signed"`` in (−1, 1)),
        zero off the object. ``diffuse_net`` is the map networks' diffuse image, 2 R_diff − 1;
        ``highlight`` (with ``highlight_input``) the Blinn-Phong specular term of N,
        :meth:`MapsModel.render_highlight`. In training mode the trained generator
        (:attr:`trained_G_sp`), else G_sp (with ``ema``, the average)."""
        inputs = [normal, diffuse_net]
        if self.config.highlight_input:
            if highlight is None:
                raise ValueError("specular.highlight_input: G_sp^real needs the Blinn-Phong highlight of its normals")
            inputs.append(2 * highlight.clamp(0.0, 1.0) - 1)
        generator = self.trained_G_sp if self.training else self.G_sp
        raw = generator(torch.cat(inputs, 1))  # tanh: (−1, 1)
        specular = raw if self.config.blend == "signed" else (raw + 1) / 2
        if self.config.grey:
            specular = specular.mean(1, keepdim=True).expand_as(specular)
        return mask * specular

    def compose(self, normal: torch.Tensor, diffuse_net: torch.Tensor, mask: torch.Tensor,
                highlight: torch.Tensor | None = None) -> torch.Tensor:
        """The NGP image of the paper (Sec. 5 "NGP"): R_diff / π ⊕ G_sp^real(N, I_df), linear radiance."""
        return blend(diffuse_radiance(diffuse_net), self.specular(normal, diffuse_net, mask, highlight), mask)

    def highlight(self, maps: MapsModel, normal: torch.Tensor, mask: torch.Tensor,
                  cameras: list[Camera]) -> torch.Tensor | None:
        """G_sp^real's highlight input when it reads one (``highlight_input``), else None."""
        return maps.render_highlight(normal, mask, cameras) if self.config.highlight_input else None

    @staticmethod
    @torch.no_grad()
    def generated_diffuse(maps: MapsModel, depth_batch: dict[str, Any],
                          maps_batch: dict[str, Any] | None = None,
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[Camera]]:
        """(N^g, I_df^g as 2 R_diff − 1, mask, cameras) of the frozen map networks: of ``depth_batch``
        with z_da ~ N(0, I), or with ``maps_batch`` (``diffuse_input = "exemplar"``) of its depth with
        z_da = μ(E_da(its albedo))."""
        batch = depth_batch if maps_batch is None else maps_batch
        depth, mask = batch["depth"], batch["mask"]
        cameras = cameras_of(batch)
        if maps_batch is None:
            z = torch.randn(depth.shape[0], maps.config.latent_dim, device=depth.device)
        else:
            z, _ = maps.E_da(2 * maps_batch["albedo"] - 1, mask)
        generated = maps.decorate(depth, mask, batch, z, cameras)
        normal = generated["normal"]
        diffuse_net = 2 * maps.render_diffuse(normal, (generated["albedo"] + 1) / 2, mask, cameras) - 1
        return normal, diffuse_net, mask, cameras

    def forward(self, maps: MapsModel, depth_batch: dict[str, Any], real: torch.Tensor,
                maps_batch: dict[str, Any] | None = None) -> dict[str, torch.Tensor]:
        """Both cycles on a batch of depth maps (or, with ``diffuse_input = "exemplar"``, of real
        maps: ``maps_batch``) and an unpaired batch of real images (linear radiance)."""
        if self.config.diffuse_input == "exemplar" and maps_batch is None:
            raise ValueError("specular.diffuse_input = 'exemplar' needs a batch of real maps")
        exemplar = maps_batch if self.config.diffuse_input == "exemplar" else None
        normal_g, diffuse_g_net, mask, cameras_g = self.generated_diffuse(maps, depth_batch, exemplar)
        with torch.no_grad():
            highlight_g = self.highlight(maps, normal_g, mask, cameras_g)
        cameras = cameras_of(depth_batch)  # the real cycle's: photographs come without cameras
        specular_g = self.specular(normal_g, diffuse_g_net, mask, highlight_g)
        composite_g = blend(diffuse_radiance(diffuse_g_net), specular_g, mask)
        composite_g_net = image_to_net(composite_g)
        diffuse_cycled_net = self.F_sp(composite_g_net)

        real_net = image_to_net(real)
        diffuse_of_real_net = self.F_sp(real_net)
        depth_of_real_net = maps.G_depth(diffuse_of_real_net)  # frozen weights; gradients reach F_sp
        _, mask_of_real = net_to_depth(depth_of_real_net)
        # Photographs come without cameras; the paper's views share K, all that normals from depth use.
        normal_of_real = maps.generate_normals(depth_of_real_net, cameras)
        highlight_of_real = self.highlight(maps, normal_of_real, mask_of_real, cameras)
        real_cycled_net = image_to_net(self.compose(normal_of_real, diffuse_of_real_net, mask_of_real,
                                                    highlight_of_real))

        self._for_d = {"real": (real_net, composite_g_net), "diffuse": (diffuse_g_net, diffuse_of_real_net)}
        signed = self.config.blend == "signed"
        self.visuals = {"diffuse_g": image_to_net(diffuse_radiance(diffuse_g_net)),
                        "specular_g": specular_g if signed else 2 * specular_g - 1,
                        "composite_g": composite_g_net, "real": real_net,
                        "diffuse_of_real": image_to_net(diffuse_radiance(diffuse_of_real_net)),
                        "real_cycled": real_cycled_net}
        return {
            "gan_real": realistic_gan_loss(self.D_real, composite_g_net),
            "gan_dfr": losses.adversarial_loss(self.D_dfr, diffuse_of_real_net),
            "cyc_generated": specular_cycle_loss(diffuse_cycled_net, diffuse_g_net),
            "cyc_real": specular_cycle_loss(real_cycled_net, real_net),
            "sparse": specular_sparsity_loss(specular_g, mask),
        }

    def optimize(self, maps: MapsModel, depth_batch: dict[str, Any], real: torch.Tensor,
                 maps_batch: dict[str, Any] | None = None) -> dict[str, float]:
        """One step: G_sp and F_sp (discriminators and map networks frozen), then D_real and D_dfr."""
        maps.requires_grad_(False)
        for D in (self.D_real, self.D_dfr):
            D.requires_grad_(False)
        terms = self(maps, depth_batch, real, maps_batch)
        loss_G = (terms["gan_real"] + terms["gan_dfr"]
                  + self.config.lambda_cycle * (terms["cyc_generated"] + terms["cyc_real"])
                  + self.config.lambda_sparse * terms["sparse"])
        self.optimizer_step(self.opt_sp_G, loss_G)
        self.update_average()
        for D in (self.D_real, self.D_dfr):
            D.requires_grad_(True)
        loss_D = (losses.discriminator_loss(self.D_real, *self._for_d["real"])
                  + losses.discriminator_loss(self.D_dfr, *self._for_d["diffuse"]))
        self.optimizer_step(self.opt_sp_D, loss_D)
        maps.requires_grad_(True)
        return {**{k: v.item() for k, v in terms.items()}, "G": loss_G.item(), "D": loss_D.item()}
