"""Shading operators R_diff and R_BP (paper App. A) as differentiable torch ops, on Dr.Jit or torch.

The maths is written once, on 3-component vectors, in :func:`blinn_phong_radiance`; each backend
supplies its arrays and five primitive functions (an "ops" adapter). The Dr.Jit backend evaluates
the whole expression as one fused kernel and is wrapped as a ``torch.autograd.Function``
(:class:`~.drjit_op.DrJitShade`); the torch backend is plain autograd.

Conventions: maps are NCHW, normals in camera space (OpenCV axes: x right, y down, z forward),
lights converted to the same camera space. The direction to the viewer ``V`` is per pixel,
``−normalize(K⁻¹ [u, v, 1])`` at pixel centres, or the paper's single view direction ``(0, 0, −1)``.

Values at the limits (all finite in value and gradient, ``tests/render/shading/test_shade.py`` enumerates them):

* Normals are renormalised, ``n = N / max(|N|, ε)`` with ε = 1e-4 (computed as
  ``N · rsqrt(max(N·N, ε²))``, so there is no square root of 0): exact for |N| ≥ ε, and a
  zero-length normal shades black with a gradient bounded by 1/ε. The half vector and light
  directions use the same rule, so a light exactly opposite the viewer (``L = −V``) or a zero light
  direction gives no highlight.
* ``max(N·H, 0)^α`` is ``exp(α ln max(N·H, 1e-30))`` where ``N·H > 0`` and **0 where N·H ≤ 0 for
  every α, including α = 0** (so ``0^0 := 0`` here: a half vector at or below the surface gives no
  highlight; the term is continuous in α at N·H = 0). Its gradient is finite for α < 1.
* The specular term is gated by ``N·L > 0``, as in the classic fixed-function pipeline: the paper's
  Eq. (1) leaves this implicit, and without it a light behind the surface still makes a highlight.
* Point lights: irradiance at normal incidence ``I / max(r², ε_r²)`` with ε_r = 1e-4.
* Ties: ``max(x, 0)`` passes no gradient to ``x`` where ``x = 0`` exactly, in both backends: N·L = 0
  at a zero normal, a zero light direction or a point light on the surface point.
* float16 / bfloat16 inputs are computed in float32 and the result is float32; float64 stays float64.

Layout: :mod:`.blinn_phong` (the equation, once), :mod:`.torch_op` and :mod:`.drjit_op` (the two
backends), and here :func:`shade` (the public op), :class:`CameraLights` (lights as tensors in
camera space) and :class:`Constants` (the paper's k_d, k_s, α: their one home).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
import torch

from ngp_mi.camera import PAPER_FILM_MM, PAPER_FOCAL_MM, Camera
from ngp_mi.lights import DirectionalLight, Light, PointLight
from ngp_mi.render.shading.drjit_op import DrJitShade, drjit_shade
from ngp_mi.render.shading.torch_op import intrinsics_tensor, torch_shade

MODES = ("diffuse", "blinn_phong")
VIEWS = ("per_pixel", "constant")
BACKENDS = ("drjit", "torch")


@dataclasses.dataclass(frozen=True)
class Constants:
    """R_BP's constants (paper App. "Training details"): k_d, k_s and the Blinn exponent α.

    The one home of these values: :func:`shade`'s defaults, the map networks' training
    (``MapsConfig``), NGP's images and ``compare`` take them from here or from a trained model's
    config. Paper: chairs k_d 0.8 / k_s 0.2, cars 0.6 / 0.4, α = 4 (:data:`PAPER_CONSTANTS`).

    ``k_diff`` is R_diff's k_d where R_diff stands alone (NGP's image, the map networks' diffuse
    images); None: R_BP's ``k_d``, as in the paper, where R_diff is R_BP's diffuse term. 1 makes
    R_diff / π the radiance of a Lambertian surface of the albedo; R_BP keeps its energy split.
    """

    k_d: float = 0.8
    k_s: float = 0.2
    alpha: float = 4.0
    k_diff: float | None = None

    @property
    def diffuse_k_d(self) -> float:
        """The k_d R_diff shades with: ``k_diff``, or R_BP's ``k_d`` when it is None."""
        return self.k_d if self.k_diff is None else self.k_diff

    @classmethod
    def of_family(cls, family: str) -> "Constants":
        """The paper's constants of a shape family; chairs' for any other source."""
        return PAPER_CONSTANTS.get(family, cls())


PAPER_CONSTANTS = {"chair": Constants(0.8, 0.2, 4.0), "car": Constants(0.6, 0.4, 4.0)}
DEFAULT = Constants()


# --------------------------------------------------------------------------- lights in camera space

@dataclasses.dataclass
class CameraLights:
    """Lights in camera space as tensors (they may require grad). Leading dim N or 1 (shared).

    Attributes:
        directions: (B, Ld, 3) directions towards directional lights (normalised in the op).
        irradiance: (B, Ld, 3) their RGB irradiance.
        positions: (B, Lp, 3) point-light positions.
        intensity: (B, Lp, 3) their RGB intensity.
    """

    directions: torch.Tensor
    irradiance: torch.Tensor
    positions: torch.Tensor
    intensity: torch.Tensor

    @classmethod
    def from_lights(cls, lights: Sequence[Light], cameras: Sequence[Camera] | None,
                    dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> "CameraLights":
        """World-space lights seen from each camera (or taken as camera space when ``cameras`` is None).

        Directions and positions get one row per camera; irradiance and intensity do not depend on
        the camera and stay one shared row (the kernel reads them once instead of per pixel).
        """
        rotations = np.stack([c.R for c in cameras]) if cameras else np.eye(3)[None]
        translations = np.stack([c.t for c in cameras]) if cameras else np.zeros((1, 3))
        dirs = [l for l in lights if isinstance(l, DirectionalLight)]
        points = [l for l in lights if isinstance(l, PointLight)]
        d = np.array([l.direction for l in dirs]).reshape(-1, 3)
        p = np.array([l.position for l in points]).reshape(-1, 3)

        def tensor(x: np.ndarray) -> torch.Tensor:
            return torch.tensor(np.array(x), dtype=dtype, device=device)

        return cls(
            directions=tensor(np.einsum("bij,lj->bli", rotations, d)),
            irradiance=tensor(np.array([l.irradiance for l in dirs]).reshape(1, -1, 3)),
            positions=tensor(np.einsum("bij,lj->bli", rotations, p) + translations[:, None]),
            intensity=tensor(np.array([l.intensity for l in points]).reshape(1, -1, 3)),
        )


def _intrinsics(camera: Camera | Sequence[Camera] | None, batch: int, height: int, width: int) -> tuple:
    """Rows (f, cx, cy) in pixels, one per camera or one shared row when every camera has the same (the
    usual case, read once by the kernel); the paper's 50 mm / 36 mm pinhole when no camera is given."""
    cameras = [camera] if isinstance(camera, Camera) else list(camera or [])
    for c in cameras:
        if (c.width, c.height) != (width, height):
            raise ValueError(f"camera is {c.width}x{c.height} but the maps are {width}x{height}")
    rows = tuple((float(c.focal_px), float(c.cx), float(c.cy)) for c in cameras) or (
        (PAPER_FOCAL_MM / PAPER_FILM_MM * width, width / 2, height / 2),)
    if len(rows) not in (1, batch):
        raise ValueError(f"got {len(rows)} cameras for a batch of {batch}")
    return rows[:1] if all(row == rows[0] for row in rows) else rows


# --------------------------------------------------------------------------- public API

def shade(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None = None,
          lights: Sequence[Light] | CameraLights = (), camera: Camera | Sequence[Camera] | None = None, *,
          depth: torch.Tensor | None = None, k_d: float = DEFAULT.k_d, k_s: float = DEFAULT.k_s,
          alpha: float | torch.Tensor = DEFAULT.alpha, spec_albedo: float | torch.Tensor = 1.0,
          mode: str = "blinn_phong", view: str = "per_pixel", backend: str = "drjit") -> torch.Tensor:
    """Shade reflectance maps: R_BP (``mode="blinn_phong"``) or R_diff (``mode="diffuse"``), App. A Eq. (1).

    Args:
        normal: (N, 3, H, W) camera-space normals (renormalised inside, see the module docstring).
        albedo: (N, 3, H, W) diffuse albedo I_d, linear RGB.
        mask: (N, 1, H, W) object mask multiplying the result, or None.
        lights: world-space :mod:`ngp_mi.lights` objects (moved into each camera's space), or
            :class:`CameraLights` tensors already in camera space (these may require grad).
        camera: one camera, one per batch item, or None (paper intrinsics; lights in camera space).
        depth: (N, 1, H, W) z-depth, needed only for point lights.
        k_d, k_s: diffuse and specular constants (:class:`Constants`; paper: 0.8 / 0.2 chairs, 0.6 / 0.4 cars).
        alpha: Blinn exponent α, a number or an (N, 1, H, W) map (paper: 4).
        spec_albedo: specular albedo I_s, a number or an (N, 3, H, W) map (paper: white).
        view: ``"per_pixel"`` view vectors from the camera, or ``"constant"`` (0, 0, −1) as in the paper.
        backend: ``"drjit"`` (one fused kernel) or ``"torch"``; same values and gradients.

    Returns:
        (N, 3, H, W) linear RGB, float32 (float64 if any input is float64).
    """
    if mode not in MODES or view not in VIEWS or backend not in BACKENDS:
        raise ValueError(f"shade: mode must be one of {MODES}, view one of {VIEWS}, backend one of {BACKENDS}; "
                         f"got {mode!r}, {view!r}, {backend!r}")
    if normal.ndim != 4 or normal.shape[1] != 3:
        raise ValueError(f"shade: normal must be (N, 3, H, W), got {tuple(normal.shape)}")
    n, _, h, w = normal.shape
    maps = {"albedo": (albedo, 3), "mask": (mask, 1), "depth": (depth, 1),
            "alpha": (alpha, 1), "spec_albedo": (spec_albedo, 3)}
    for name, (t, channels) in maps.items():
        if isinstance(t, torch.Tensor) and tuple(t.shape) != (n, channels, h, w):
            raise ValueError(f"shade: {name} must be ({n}, {channels}, {h}, {w}), got {tuple(t.shape)}")
    tensors = [t for t in (normal, albedo, mask, depth, alpha, spec_albedo) if isinstance(t, torch.Tensor)]
    dtype = torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32
    device = normal.device
    if not isinstance(lights, CameraLights):
        cameras = [camera] if isinstance(camera, Camera) else (list(camera) if camera is not None else None)
        lights = CameraLights.from_lights(list(lights), cameras, dtype=dtype, device=device)
    if lights.positions.shape[1] and depth is None:
        raise ValueError("shade: point lights need the depth map (depth=...)")
    if lights.directions.shape[1] + lights.positions.shape[1] == 0:
        raise ValueError("shade: no lights given")
    intrinsics = _intrinsics(camera, n, h, w)

    def cast(t: Any) -> Any:
        return t.to(dtype) if isinstance(t, torch.Tensor) and t.dtype != dtype else t

    opts = {"mode": mode, "view": view, "k_d": float(k_d), "k_s": float(k_s),
            "alpha": None if isinstance(alpha, torch.Tensor) else float(alpha),
            "spec_albedo": None if isinstance(spec_albedo, torch.Tensor) else float(spec_albedo)}
    light_tensors = [cast(t) for t in (lights.directions, lights.irradiance, lights.positions, lights.intensity)]
    if backend == "torch":
        intr = intrinsics_tensor(intrinsics, dtype, str(device))
        return torch_shade(cast(normal), cast(albedo), cast(mask), cast(depth), intr, CameraLights(*light_tensors),
                            cast(alpha), cast(spec_albedo), opts)
    inputs = [cast(normal), cast(albedo), cast(mask), cast(depth), *light_tensors,
              cast(alpha) if isinstance(alpha, torch.Tensor) else None,
              cast(spec_albedo) if isinstance(spec_albedo, torch.Tensor) else None]
    if not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs)):
        return drjit_shade(opts, intrinsics, inputs)  # no autograd node needed
    return DrJitShade.apply(opts, intrinsics, *inputs)


def render_diffuse(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None,
                   lights: Sequence[Light] | CameraLights, camera: Camera | Sequence[Camera] | None = None,
                   k_d: float = DEFAULT.k_d, **kwargs: Any) -> torch.Tensor:
    """R_diff: the diffuse part of Eq. (1), ``Σ_l E_l k_d max(N·L_l, 0) I_d`` (paper Sec. 3.4)."""
    return shade(normal, albedo, mask, lights, camera, k_d=k_d, mode="diffuse", **kwargs)


def render_blinn_phong(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None,
                       lights: Sequence[Light] | CameraLights, camera: Camera | Sequence[Camera] | None = None,
                       **kwargs: Any) -> torch.Tensor:
    """R_BP: the full Blinn-Phong rendering function of App. A, Eq. (1)."""
    return shade(normal, albedo, mask, lights, camera, mode="blinn_phong", **kwargs)
