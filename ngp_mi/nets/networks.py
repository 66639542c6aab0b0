"""Network building blocks of NGP's map generation (paper Sec. 3.4, "Implementation details").

* :class:`ResnetGenerator` — the CycleGAN / MUNIT ResNet encoder-decoder used for every map
  generator (G_n, G_da, G_depth, G_sp^real), optionally conditioned on a latent code concatenated
  to the input of every encoder layer (as VON / BicycleGAN do for G_da) or modulating its
  normalised features (:class:`FiLM`).
* :class:`PaletteGenerator` — G_da as part regions × part colours of the code (a switch, issue 15).
* :class:`ResnetEncoder` — E_da: albedo map → (μ, log σ²) of the 8-d appearance code;
  :class:`PartEncoder` — E_da from the colours of the exemplar's soft parts (a switch, issue 15).
* :class:`PatchDiscriminator` — PatchGAN with a receptive field of 16, 34, 70 or 142 pixels;
  :class:`MultiPatchDiscriminator` combines several (the paper's "mid (70) and large (140)").
* :func:`define_G`, :func:`define_palette_G`, :func:`define_E`, :func:`define_D` — constructors with CycleGAN's init.
"""

from __future__ import annotations

import torch
from torch import nn


def _norm(channels: int) -> nn.Module:
    return nn.InstanceNorm2d(channels, affine=False, track_running_stats=False)


class ResnetBlock(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.ReflectionPad2d(1), nn.Conv2d(channels, channels, 3), _norm(channels), nn.ReLU(True),
            nn.ReflectionPad2d(1), nn.Conv2d(channels, channels, 3), _norm(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


SIZE_MULTIPLE = 4  # two stride-2 downsamplings, undone by two upsamplings: other sizes come back another size
MIN_SIZE = 8  # at 1/4 scale the residual blocks' reflection padding needs 2 pixels


def check_image_size(height: int, width: int, what: str = "input") -> None:
    """ValueError unless a :class:`ResnetGenerator` takes ``height`` x ``width`` images; it names the nearest sizes."""
    for size in (height, width):
        if size % SIZE_MULTIPLE or size < MIN_SIZE:
            lower = max(MIN_SIZE, size // SIZE_MULTIPLE * SIZE_MULTIPLE)
            upper = max(MIN_SIZE, lower + SIZE_MULTIPLE if size > lower else lower)
            nearest = f"{lower} or {upper}" if lower != upper else f"{lower}"
            raise ValueError(f"{what} {height}x{width}: the map networks take image sizes that are multiples of "
                             f"{SIZE_MULTIPLE} and at least {MIN_SIZE} (nearest: {nearest})")


LATENT_MODES = ("concat", "film")
UPSAMPLES = ("transpose", "resize")


def upsampling(in_channels: int, out_channels: int, mode: str = "transpose") -> nn.Module:
    """×2 upsampling of a :class:`ResnetGenerator`'s decoder. ``transpose`` (CycleGAN's): a stride-2
    3×3 transposed convolution, whose kernel covers even output pixels with one tap per axis and odd
    ones with two, so a trained filter leaves a 2-pixel checkerboard unless its taps balance.
    ``resize`` (Odena et al. 2016, "Deconvolution and checkerboard artifacts"): nearest-neighbour
    ×2, then a 3×3 convolution, which weighs every output pixel alike."""
    if mode == "transpose":
        return nn.ConvTranspose2d(in_channels, out_channels, 3, 2, 1, output_padding=1)
    if mode == "resize":
        return nn.Sequential(nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(in_channels, out_channels, 3, 1, 1))
    raise ValueError(f"upsample must be one of {UPSAMPLES}, got {mode!r}")


class FiLM(nn.Module):
    """Feature-wise modulation by a latent code: x · (1 + γ(z)) + β(z), per channel (Perez et al.
    2018; MUNIT's AdaIN is the same after an instance norm). Placed after an instance norm it is the
    one way a spatially constant code survives it."""

    def __init__(self, latent_dim: int, channels: int):
        super().__init__()
        self.to_scale_shift = nn.Linear(latent_dim, 2 * channels)
        self.reset_parameters()

    def reset_parameters(self, std: float = 0.1) -> None:
        """γ, β of a N(0, I) code start with a std of about 0.1 √latent_dim (0.28 for 8-d codes): the
        code visibly changes the output from the first step (CycleGAN's N(0, 0.02) gives 0.06)."""
        nn.init.normal_(self.to_scale_shift.weight, 0.0, std)
        nn.init.zeros_(self.to_scale_shift.bias)

    def forward(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        scale, shift = self.to_scale_shift(z)[:, :, None, None].chunk(2, dim=1)
        return x * (1 + scale) + shift


class ResnetGenerator(nn.Module):
    """c7s1-ngf, two stride-2 downsamplings, ``blocks`` residual blocks, two upsamplings, c7s1-out, tanh.

    With ``latent_dim > 0`` the generator is conditioned on a latent code, as ``latent_mode`` says:

    * ``concat`` (the paper's G_da, BicycleGAN's "add to all"): the code, broadcast over the image,
      is concatenated to the input of each encoder layer (c7s1 and both downsamplings). Each layer's
      instance norm then subtracts the constant the code adds to every channel, so the code acts
      only through the zero-padded borders (``tests/nets/test_networks.py`` measures it): G_da
      largely ignores z_da (issue 15).
    * ``film``: every instance norm of the encoder and the upsampling decoder is followed by a
      :class:`FiLM` of the code, which the norm cannot undo.

    ``upsample`` picks the decoder's two ×2 layers (:func:`upsampling`).

    Images are ``SIZE_MULTIPLE`` k pixels on a side (:func:`check_image_size`).
    """

    def __init__(self, in_channels: int, out_channels: int, ngf: int = 64, blocks: int = 9, latent_dim: int = 0,
                 latent_mode: str = "concat", upsample: str = "transpose"):
        super().__init__()
        if latent_mode not in LATENT_MODES:
            raise ValueError(f"latent_mode must be one of {LATENT_MODES}, got {latent_mode!r}")
        self.latent_dim = latent_dim
        self.latent_mode = latent_mode if latent_dim else "concat"
        z = latent_dim if self.latent_mode == "concat" else 0
        self.encoder = nn.ModuleList([
            nn.Sequential(nn.ReflectionPad2d(3), nn.Conv2d(in_channels + z, ngf, 7), _norm(ngf), nn.ReLU(True)),
            nn.Sequential(nn.Conv2d(ngf + z, 2 * ngf, 3, 2, 1), _norm(2 * ngf), nn.ReLU(True)),
            nn.Sequential(nn.Conv2d(2 * ngf + z, 4 * ngf, 3, 2, 1), _norm(4 * ngf), nn.ReLU(True)),
        ])
        if self.latent_mode == "film":  # after the norms of the 3 encoder and the 2 upsampling layers
            self.film = nn.ModuleList([FiLM(latent_dim, c) for c in (ngf, 2 * ngf, 4 * ngf, 2 * ngf, ngf)])
        self.blocks = nn.Sequential(*[ResnetBlock(4 * ngf) for _ in range(blocks)])
        self.decoder = nn.Sequential(
            upsampling(4 * ngf, 2 * ngf, upsample), _norm(2 * ngf), nn.ReLU(True),
            upsampling(2 * ngf, ngf, upsample), _norm(ngf), nn.ReLU(True),
            nn.ReflectionPad2d(3), nn.Conv2d(ngf, out_channels, 7), nn.Tanh())

    @property
    def output_conv(self) -> nn.Conv2d:
        """The last convolution, before the tanh: what a chosen starting output is set on."""
        return self.decoder[-2]

    def forward(self, x: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        if (z is None) != (self.latent_dim == 0):
            raise ValueError(f"generator expects a latent code of size {self.latent_dim}" if self.latent_dim
                             else "generator takes no latent code")
        check_image_size(*x.shape[-2:])
        if self.latent_mode == "film":
            return self._forward_film(x, z)
        for layer in self.encoder:
            if z is not None:
                x = torch.cat([x, z[:, :, None, None].expand(-1, -1, *x.shape[-2:])], dim=1)
            x = layer(x)
        return self.decoder(self.blocks(x))

    def _forward_film(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        films = iter(self.film)
        for layer in self.encoder:  # each: [pad,] conv, norm, ReLU — modulated between norm and ReLU
            *conv_norm, relu = layer
            for module in conv_norm:
                x = module(x)
            x = relu(next(films)(x, z))
        x = self.blocks(x)
        for module in self.decoder:
            x = module(x)
            if isinstance(module, nn.InstanceNorm2d):
                x = next(films)(x, z)
        return x


class PaletteGenerator(nn.Module):
    """An albedo map as a soft partition into ``parts`` regions, each of one colour of the code:

        I_da(p) = Σ_k w_k(p) c_k(z),   w(p) = softmax(s · G(x, z)(p)),   c_k(z) = tanh(MLP(z))_k.

    G is a FiLM :class:`ResnetGenerator` (which region a pixel belongs to is a matter of shape, which
    its instance norms keep); the colours come from z through an MLP, which no norm touches: the
    absolute colour a ResNet generator's norms remove (issue 15) is what the code carries. ``s``
    sharpens G's tanh-bounded scores into near-hard parts.

    ``background``: "slot" — a fixed background colour c_0 = −1 is one more region of the softmax,
    so G must learn where the object is; "mask" — the background is the input's (its first three
    channels are the NOC, −1 off the object: m = object mask), I_da = m Σ_k w_k c_k − (1 − m), and the
    softmax runs over the parts alone. With the slot, separating object from background saturates
    the softmax on one part, whose neighbours then get no gradient and never take a pixel: one
    colour per chair (issue 15, RESULTS).
    """

    BACKGROUNDS = ("slot", "mask")

    def __init__(self, in_channels: int, ngf: int, blocks: int, latent_dim: int, parts: int = 4,
                 sharpness: float = 8.0, hidden: int = 64, background: str = "slot"):
        super().__init__()
        if background not in self.BACKGROUNDS:
            raise ValueError(f"palette background must be one of {self.BACKGROUNDS}, got {background!r}")
        self.latent_dim, self.parts, self.sharpness, self.background = latent_dim, parts, sharpness, background
        self.regions = define_G(in_channels, parts + (background == "slot"), ngf, blocks, latent_dim, "film")
        # PyTorch's default (Kaiming-uniform) init: CycleGAN's N(0, 0.02) would start every colour at
        # grey, nearly independent of z
        self.colours = nn.Sequential(nn.Linear(latent_dim, hidden), nn.LeakyReLU(0.2, True),
                                     nn.Linear(hidden, hidden), nn.LeakyReLU(0.2, True), nn.Linear(hidden, 3 * parts))

    def weights(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(B, 1 + parts, H, W): the background's weight, then each part's."""
        scores = self.sharpness * self.regions(x, z)
        if self.background == "slot":
            return torch.softmax(scores, dim=1)
        mask = object_mask(x[:, :3])
        return torch.cat([1 - mask, torch.softmax(scores, dim=1) * mask], 1)

    def forward(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        colours = torch.tanh(self.colours(z)).view(-1, self.parts, 3)
        colours = torch.cat([-torch.ones_like(colours[:, :1]), colours], dim=1)
        return torch.einsum("bkhw,bkc->bchw", self.weights(x, z), colours)


RESNET_POOLS = ("mean", "masked")  # :class:`ResnetEncoder`'s; "parts" is :class:`PartEncoder`
ENCODER_POOLS = (*RESNET_POOLS, "parts")


def object_mask(image: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) mask of the pixels of a network-space map (2x − 1) that are not background (−1)."""
    return (image > -1 + 1e-3).any(1, keepdim=True).to(image.dtype)


class ResnetEncoder(nn.Module):
    """E_da: conv, ``levels`` residual downsampling blocks, average pooling, linear heads μ and log σ².

    ``pool``: ``mean`` (BicycleGAN's) averages the features over the whole image, so a colour
    reaches the linear heads multiplied by the object's share of the image, and recovering it takes
    a division the heads cannot do; ``masked`` averages them over the object only (the mask passed
    to :meth:`forward`, or the non-background pixels of the input)."""

    def __init__(self, in_channels: int, latent_dim: int = 8, nef: int = 64, levels: int = 4, pool: str = "mean"):
        super().__init__()
        if pool not in RESNET_POOLS:
            raise ValueError(f"encoder pool must be one of {RESNET_POOLS}, got {pool!r}")
        self.pool = pool
        layers: list[nn.Module] = [nn.Conv2d(in_channels, nef, 4, 2, 1)]
        channels = nef
        for level in range(1, levels):
            out = nef * min(level + 1, 4)
            layers.append(_BasicDownBlock(channels, out))
            channels = out
        layers += [nn.LeakyReLU(0.2, True), nn.AdaptiveAvgPool2d(1)]
        self.features = nn.Sequential(*layers)
        self.mu = nn.Linear(channels, latent_dim)
        self.logvar = nn.Linear(channels, latent_dim)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        if self.pool == "mean":
            h = self.features(x).flatten(1)
        else:
            h = self.features[:-1](x)  # all but the average pooling
            weight = nn.functional.adaptive_avg_pool2d(object_mask(x) if mask is None else mask, h.shape[-2:])
            h = (h * weight).sum((2, 3)) / weight.sum((2, 3)).clamp_min(1e-3)
        return self.mu(h), self.logvar(h)


class PartEncoder(nn.Module):
    """E_da as the colours of the exemplar's parts (``encoder_pool = "parts"``, issue 15):

        a(p) = softmax(A(x, m, u, v)(p)),   c_k = Σ_p m(p) a_k(p) x(p) / Σ_p m(p) a_k(p),
        (μ, log σ²) = linear heads of (c_1, …, c_K),

    A a full-resolution dilated conv net (receptive field 35 px) over the albedo x, its object mask
    m and the pixel coordinates (u, v), which splits the object into K soft regions. Each region's
    colour is the exact weighted mean of the input's pixels — no norm or pooling of deep features
    sits between a part's colour and the code — so the code holds one colour per region, and the
    palette G_da, trained with it, learns to paint region k where E_da pooled colour k (the parts of
    a chair, from its geometry). Mean pooling instead returns one colour per chair: the average."""

    def __init__(self, in_channels: int, latent_dim: int = 8, nef: int = 64, parts: int = 4,
                 dilations: tuple[int, ...] = (1, 2, 4, 8, 1)):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(in_channels + 3, nef, 3, 1, 1), nn.LeakyReLU(0.2, True)]
        for d in dilations:
            layers += [nn.Conv2d(nef, nef, 3, 1, d, dilation=d), _norm(nef), nn.LeakyReLU(0.2, True)]
        layers.append(nn.Conv2d(nef, parts, 1))
        self.regions = nn.Sequential(*layers)
        self.mu = nn.Linear(in_channels * parts, latent_dim)
        self.logvar = nn.Linear(in_channels * parts, latent_dim)

    def region_weights(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B, K, H, W): each object pixel's soft region, zero off the object."""
        b, _, h, w = x.shape
        v, u = torch.meshgrid(torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype),
                              torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype), indexing="ij")
        coords = torch.stack([u, v]).expand(b, 2, h, w)
        return torch.softmax(self.regions(torch.cat([x, mask, coords], 1)), 1) * mask

    def part_colours(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """(B, K, C): the weighted mean of x over each region (0 for an empty one)."""
        weights = self.region_weights(x, object_mask(x) if mask is None else mask)
        return torch.einsum("bkhw,bchw->bkc", weights, x) / weights.sum((2, 3))[..., None].clamp_min(1e-3)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        colours = self.part_colours(x, mask).flatten(1)
        return self.mu(colours), self.logvar(colours)


class _BasicDownBlock(nn.Module):
    """BicycleGAN's residual block that halves the resolution."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(_norm(cin), nn.LeakyReLU(0.2, True), nn.Conv2d(cin, cin, 3, 1, 1),
                                  _norm(cin), nn.LeakyReLU(0.2, True), nn.Conv2d(cin, cout, 3, 1, 1), nn.AvgPool2d(2))
        self.shortcut = nn.Sequential(nn.AvgPool2d(2), nn.Conv2d(cin, cout, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x) + self.shortcut(x)


PATCH_LAYERS = {16: 1, 34: 2, 70: 3, 142: 4}  # receptive field (pixels) -> stride-2 layers


def patch_receptive_field(n_layers: int) -> int:
    """Receptive field of a PatchGAN with ``n_layers`` stride-2 4×4 convs and two stride-1 4×4 convs."""
    strides = [2] * n_layers + [1, 1]
    field = 1
    for stride in reversed(strides):
        field = (field - 1) * stride + 4
    return field


class PatchDiscriminator(nn.Module):
    """PatchGAN (pix2pix's NLayerDiscriminator): one real/fake score per overlapping patch."""

    def __init__(self, in_channels: int, receptive_field: int = 70, ndf: int = 64):
        super().__init__()
        if receptive_field not in PATCH_LAYERS:
            raise ValueError(f"receptive field must be one of {sorted(PATCH_LAYERS)}, got {receptive_field}")
        n_layers = PATCH_LAYERS[receptive_field]
        layers: list[nn.Module] = [nn.Conv2d(in_channels, ndf, 4, 2, 1), nn.LeakyReLU(0.2, True)]
        channels = ndf
        for i in range(1, n_layers):
            out = ndf * min(2 ** i, 8)
            layers += [nn.Conv2d(channels, out, 4, 2, 1), _norm(out), nn.LeakyReLU(0.2, True)]
            channels = out
        out = ndf * min(2 ** n_layers, 8)
        layers += [nn.Conv2d(channels, out, 4, 1, 1), _norm(out), nn.LeakyReLU(0.2, True), nn.Conv2d(out, 1, 4, 1, 1)]
        self.model = nn.Sequential(*layers)
        self.receptive_field = patch_receptive_field(n_layers)
        self.min_size = 3 * 2 ** n_layers  # the last normalised layer needs more than one element

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if min(x.shape[-2:]) < self.min_size:
            raise ValueError(f"a PatchGAN with a {self.receptive_field}-pixel receptive field needs images of at "
                             f"least {self.min_size}x{self.min_size}, got {tuple(x.shape[-2:])}")
        return self.model(x)


class MultiPatchDiscriminator(nn.Module):
    """Several PatchGANs on the same input; returns the list of their score maps."""

    def __init__(self, in_channels: int, receptive_fields: tuple[int, ...] = (70, 142), ndf: int = 64):
        super().__init__()
        self.discriminators = nn.ModuleList([PatchDiscriminator(in_channels, rf, ndf) for rf in receptive_fields])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [d(x) for d in self.discriminators]


def init_weights(net: nn.Module, gain: float = 0.02) -> nn.Module:
    """CycleGAN's initialisation: N(0, 0.02) convolution and linear weights, zero biases."""
    for module in net.modules():
        if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            nn.init.normal_(module.weight, 0.0, gain)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
    return net


def define_G(in_channels: int, out_channels: int, ngf: int = 64, blocks: int = 9, latent_dim: int = 0,
             latent_mode: str = "concat", upsample: str = "transpose") -> ResnetGenerator:
    net = init_weights(ResnetGenerator(in_channels, out_channels, ngf, blocks, latent_dim, latent_mode, upsample))
    for module in net.modules():
        if isinstance(module, FiLM):
            module.reset_parameters()
    return net


def define_palette_G(in_channels: int, ngf: int, blocks: int, latent_dim: int, parts: int = 4,
                     background: str = "slot") -> PaletteGenerator:
    return PaletteGenerator(in_channels, ngf, blocks, latent_dim, parts, background=background)


def define_E(in_channels: int, latent_dim: int = 8, nef: int = 64, levels: int = 4, pool: str = "mean",
             parts: int = 4) -> ResnetEncoder | PartEncoder:
    if pool != "parts":
        return init_weights(ResnetEncoder(in_channels, latent_dim, nef, levels, pool))
    net = init_weights(PartEncoder(in_channels, latent_dim, nef, parts))
    net.mu.reset_parameters()  # PyTorch's default init: N(0, 0.02) heads would start every code near 0
    net.logvar.reset_parameters()
    return net


def define_D(in_channels: int, receptive_fields: tuple[int, ...] = (70, 142), ndf: int = 64) -> MultiPatchDiscriminator:
    return init_weights(MultiPatchDiscriminator(in_channels, receptive_fields, ndf))
