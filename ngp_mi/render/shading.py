"""Shading operators R_diff and R_BP (paper App. A) as differentiable torch ops, on Dr.Jit or torch.

The maths is written once, on 3-component vectors, in :func:`blinn_phong_radiance`; each backend
supplies its arrays and five primitive functions (an "ops" adapter). The Dr.Jit backend evaluates
the whole expression as one fused kernel and is wrapped as a ``torch.autograd.Function``
(:class:`_DrJitShade`); the torch backend is plain autograd.

Conventions: maps are NCHW, normals in camera space (OpenCV axes: x right, y down, z forward),
lights converted to the same camera space. The direction to the viewer ``V`` is per pixel,
``−normalize(K⁻¹ [u, v, 1])`` at pixel centres, or the paper's single view direction ``(0, 0, −1)``.

Values at the limits (all finite in value and gradient, ``tests/test_shading.py`` enumerates them):

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
* float16 / bfloat16 inputs are computed in float32 and the result is float32; float64 stays float64.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import torch

from ngp_mi import backend
from ngp_mi.camera import PAPER_FILM_MM, PAPER_FOCAL_MM, Camera
from ngp_mi.lights import DirectionalLight, Light, PointLight

NORMAL_EPS = 1e-4
POW_FLOOR = 1e-30
POINT_EPS = 1e-4
MODES = ("diffuse", "blinn_phong")
VIEWS = ("per_pixel", "constant")
BACKENDS = ("drjit", "torch")

Vec = tuple[Any, Any, Any]


# --------------------------------------------------------------------------- the maths, written once

@dataclasses.dataclass(frozen=True)
class Ops:
    """The primitive functions the shading maths needs, for one array library."""

    rsqrt: Callable
    exp: Callable
    log: Callable
    maximum: Callable  # maximum(array, float)
    where: Callable    # where(condition, array, float)
    fma: Callable      # fma(a, b, c) = a * b + c (one instruction, one rounding, where the library has it)


TORCH_OPS = Ops(torch.rsqrt, torch.exp, torch.log, lambda a, b: torch.clamp(a, min=b), torch.where,
                lambda a, b, c: a * b + c)


def _drjit_ops() -> Ops:
    dr = backend.drjit()
    return Ops(dr.rsqrt, dr.exp, dr.log, dr.maximum, dr.select, dr.fma)


def dot(ops: Ops, a: Vec, b: Vec) -> Any:
    return ops.fma(a[0], b[0], ops.fma(a[1], b[1], a[2] * b[2]))


def safe_normalize(ops: Ops, v: Vec, eps: float = NORMAL_EPS) -> Vec:
    """``v / max(|v|, ε)``: exact for |v| ≥ ε, 0 at v = 0, gradient bounded by 1/ε (no sqrt of 0)."""
    inv = ops.rsqrt(ops.maximum(dot(ops, v, v), eps * eps))
    return (v[0] * inv, v[1] * inv, v[2] * inv)


def specular_lobe(ops: Ops, cos_nh: Any, alpha: Any) -> Any:
    """Blinn's lobe ``max(N·H, 0)^α`` (paper App. A, Eq. 1), 0 where N·H ≤ 0 for every α ≥ 0.

    A constant integer α in [1, 64] (the paper's α = 4) is evaluated by repeated squaring, which is
    exact and avoids a log and an exp per pixel and light; any other α as ``exp(α ln x)``.
    """
    x = ops.maximum(cos_nh, POW_FLOOR)
    if isinstance(alpha, (int, float)) and float(alpha).is_integer() and 1 <= alpha <= 64:
        power, result, e = x, None, int(alpha)
        while e:
            if e & 1:
                result = power if result is None else result * power
            e >>= 1
            if e:
                power = power * power
        lobe = result
    else:
        lobe = ops.exp(alpha * ops.log(x))
    return ops.where(cos_nh > 0, lobe, 0.0)


def blinn_phong_radiance(ops: Ops, normal: Vec, view: Vec, lights: Sequence[tuple[Vec, Vec]], albedo: Vec,
                         k_d: float, spec_albedo: Vec | None = None, k_s: float = 0.0, alpha: Any = 1.0) -> Vec:
    """The paper's Blinn-Phong rendering function R_BP (App. A, Eq. 1), summed over lights:

        I = Σ_l E_l ⊙ [ k_d max(N·L_l, 0) I_d  +  k_s max(N·H_l, 0)^α I_s ],   H_l = (L_l + V) / |L_l + V|

    with the specular term only where N·L_l > 0 (see the module docstring).

    ``lights`` holds (L_l, E_l): unit direction towards the light and RGB irradiance. With
    ``spec_albedo=None`` only the diffuse term is evaluated: that is R_diff. There is no 1/π: with
    k_d = 1, R_diff is π times the radiance ``I_d E cos θ / π`` of a Lambertian surface of albedo I_d.
    """
    n = safe_normalize(ops, normal)
    out: list | None = None
    for direction, irradiance in lights:
        cos_nl = dot(ops, n, direction)
        diffuse = k_d * ops.maximum(cos_nl, 0.0)
        if spec_albedo is None:
            terms = [diffuse * a for a in albedo]
        else:
            half = safe_normalize(ops, (direction[0] + view[0], direction[1] + view[1], direction[2] + view[2]))
            specular = ops.where(cos_nl > 0, k_s * specular_lobe(ops, dot(ops, n, half), alpha), 0.0)
            terms = [ops.fma(diffuse, a, specular * s) for a, s in zip(albedo, spec_albedo)]
        out = [e * t for e, t in zip(irradiance, terms)] if out is None else \
            [ops.fma(e, t, o) for o, e, t in zip(out, irradiance, terms)]
    return (0.0, 0.0, 0.0) if out is None else (out[0], out[1], out[2])


def point_light_incidence(ops: Ops, position: Vec, light_position: Vec, intensity: Vec) -> tuple[Vec, Vec]:
    """Direction towards a point light and its irradiance at normal incidence, ``I / max(r², ε_r²)``."""
    d = (light_position[0] - position[0], light_position[1] - position[1], light_position[2] - position[2])
    r2 = ops.maximum(dot(ops, d, d), POINT_EPS * POINT_EPS)
    inv_r = ops.rsqrt(r2)
    return (d[0] * inv_r, d[1] * inv_r, d[2] * inv_r), (intensity[0] / r2, intensity[1] / r2, intensity[2] / r2)


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


@functools.lru_cache(maxsize=32)
def _intrinsics_tensor(rows: tuple, dtype: torch.dtype, device: str) -> torch.Tensor:
    """The rows as a (B, 3) tensor, made once per camera set (never modified)."""
    return torch.tensor(rows, dtype=dtype, device=device)


# --------------------------------------------------------------------------- torch backend

def _torch_shade(normal, albedo, mask, depth, intr, lights: CameraLights, alpha, spec_albedo, opts) -> torch.Tensor:
    ops = TORCH_OPS
    n, _, h, w = normal.shape

    def comps(x: torch.Tensor) -> Vec:
        return (x[:, 0:1], x[:, 1:2], x[:, 2:3])

    def light_comps(x: torch.Tensor, i: int) -> Vec:
        return tuple(x[:, i, k].reshape(-1, 1, 1, 1) for k in range(3))  # type: ignore[return-value]

    need_rays = opts["view"] == "per_pixel" or lights.positions.shape[1] > 0
    if need_rays:
        v, u = torch.meshgrid(torch.arange(h, dtype=normal.dtype, device=normal.device) + 0.5,
                              torch.arange(w, dtype=normal.dtype, device=normal.device) + 0.5, indexing="ij")
        f, cx, cy = (intr[:, k].reshape(-1, 1, 1, 1) for k in range(3))
        ray = ((u - cx) / f, (v - cy) / f, torch.ones_like(u).expand(intr.shape[0], 1, h, w))
    view = safe_normalize(ops, tuple(-c for c in ray)) if opts["view"] == "per_pixel" else (0.0, 0.0, -1.0)

    directions = torch.stack(safe_normalize(ops, lights.directions.unbind(-1)), dim=-1)  # once per (image, light)
    light_list = [(light_comps(directions, i), light_comps(lights.irradiance, i)) for i in range(directions.shape[1])]
    if lights.positions.shape[1] > 0:
        position = tuple(depth * r for r in ray)
        for i in range(lights.positions.shape[1]):
            light_list.append(point_light_incidence(ops, position, light_comps(lights.positions, i),
                                                    light_comps(lights.intensity, i)))
    spec = None
    if opts["mode"] == "blinn_phong":
        spec = comps(spec_albedo) if isinstance(spec_albedo, torch.Tensor) else (spec_albedo,) * 3
    rgb = blinn_phong_radiance(ops, comps(normal), view, light_list, comps(albedo), opts["k_d"], spec,
                               opts["k_s"], alpha)
    out = torch.cat([c.expand(n, 1, h, w) for c in rgb], dim=1)
    return out * mask if mask is not None else out


# --------------------------------------------------------------------------- Dr.Jit backend

_INPUTS = ("normal", "albedo", "mask", "depth", "directions", "irradiance", "positions", "intensity",
           "alpha", "spec_albedo")
_PER_IMAGE = ("directions", "irradiance", "positions", "intensity")  # (1 or N, ...) rows


@functools.lru_cache(maxsize=32)
def _drjit_intrinsics(rows: tuple, float_type: type) -> Any:
    """The intrinsics rows as Dr.Jit values, made once per camera set: one opaque scalar per value for
    a shared row (a uniform load in the kernel), else one flat array."""
    dr = backend.drjit()
    values = [v for row in rows for v in row]
    if len(rows) == 1:
        return tuple(dr.opaque(float_type, v) for v in values)
    return dr.opaque(float_type, float_type(values))


def pixels_per_lane(width: int) -> int:
    """How many horizontally adjacent pixels one kernel lane shades: 4 when the row width allows.

    A lane then reads each map channel with one packet load of 4 values instead of 4 gathers, and
    reads the per-image light values once for its 4 pixels; its reverse writes the map gradients
    with packet stores and scatter-adds the light gradients 4x less often. Measured at 8 x 256²
    (bench/RESULTS.md, interleaved A/B against 1 pixel per lane): forward kernel 3.5 -> 1.4 ms diffuse,
    4.9 -> 2.8 ms Blinn-Phong; forward + backward 26 -> 14 ms and 31 -> 22 ms. 8 pixels per lane were
    no faster, and they make the first (traced) call slower: every operation is one JIT variable per pixel.
    """
    return 4 if width % 4 == 0 else 2 if width % 2 == 0 else 1


class _Layout(NamedTuple):
    """Everything the traced Dr.Jit code depends on besides the arrays' contents.

    It is the key of the frozen functions below: a call with another layout traces anew, one with
    the same layout replays the recorded kernel. (A named tuple: it is made on every call.)
    """

    mode: str
    view: str
    k_d: float
    k_s: float
    alpha: float | None        # None: a map
    spec_albedo: float | None  # None: a map
    n: int
    h: int
    w: int
    k: int                             # pixels per lane (pixels_per_lane(w))
    rows: tuple[tuple[str, int], ...]  # per-image inputs: (name, values per row)
    shared: tuple[str, ...]            # per-image inputs given as one row, passed as single values
    wants: tuple[str, ...] = ()        # inputs that need a gradient (backward only)
    grad_scalar: bool = False          # the upstream gradient is one broadcast value (backward only)

    @property
    def lanes_per_image(self) -> int:
        return self.h * self.w // self.k

    def count(self, name: str) -> int:
        """Lights in a per-image input (its values per row / 3)."""
        return next((width // 3 for row_name, width in self.rows if row_name == name), 0)


def _shade_graph(layout: _Layout, arrays: dict) -> tuple[Vec, dict, Any, Any]:
    """Trace the shading of every pixel; each lane shades :func:`pixels_per_lane` adjacent pixels of
    one image (a Dr.Jit ``ArrayXf`` with one component per pixel).

    Returns the RGB expression, the AD leaves of the maps in ``layout.wants`` (the map values as
    read: their gradients are stored with packet stores, every map element belonging to one lane;
    Dr.Jit's own reverse of a packet gather would be a scatter-reduction), the lane index and the
    lane's first element in a 3-channel map.
    """
    dr = backend.drjit()
    ops = _drjit_ops()
    Float = type(arrays["normal"])
    mod = dr.cuda.ad if dr.backend_v(Float) == dr.JitBackend.CUDA else dr.llvm.ad
    Pixels = mod.ArrayXf64 if Float is mod.Float64 else mod.ArrayXf
    UInt = mod.UInt
    n, w, k = layout.n, layout.w, layout.k
    per_image = layout.lanes_per_image
    lanes = n * per_image

    idx = dr.arange(UInt, lanes)
    batch = idx // per_image
    lane = idx - batch * per_image  # lane within its image; it shades pixels k*lane ... k*lane + k-1
    base3 = batch * (3 * per_image) + lane
    leaves: dict[str, tuple] = {}

    def map_channels(name: str, channels: int) -> tuple:
        index = idx if channels == 1 else base3
        values = tuple(dr.gather(Pixels, arrays[name], index + c * per_image, shape=(k, lanes)) for c in range(channels))
        if name in layout.wants:
            dr.enable_grad(*values)
            leaves[name] = values
        return values

    def per_batch(name: str, width: int, offset: int) -> Any:
        """Entry ``[b, offset]`` of a (N, width) array, or of a shared row (passed as single values:
        one scalar load for the whole kernel; a gather inside a frozen function is one per lane)."""
        if name in layout.shared:
            return arrays[name][offset]
        return dr.gather(Float, arrays[name], batch * width + offset)

    def light3(name: str, i: int) -> Vec:
        return tuple(per_batch(name, 3 * layout.count(name), 3 * i + c) for c in range(3))  # type: ignore[return-value]

    n_dir, n_point = layout.count("directions"), layout.count("positions")
    if layout.view == "per_pixel" or n_point:
        f, cx, cy = (per_batch("intr", 3, c) for c in range(3))
        first = lane * k  # the lane's first pixel; its k pixels share a row (k divides the width)
        u = Float(first % w) + Pixels([m + 0.5 for m in range(k)])
        v = Float(first // w) + 0.5
        ray = ((u - cx) / f, (v - cy) / f, Float(1.0))
    view = safe_normalize(ops, (-ray[0], -ray[1], -ray[2])) if layout.view == "per_pixel" else (0.0, 0.0, -1.0)
    # directions normalised per lane (once per pixels_per_lane pixels; a shared one once per kernel)
    lights = [(safe_normalize(ops, light3("directions", i)), light3("irradiance", i)) for i in range(n_dir)]
    if n_point:
        depth = map_channels("depth", 1)[0]
        position = (depth * ray[0], depth * ray[1], depth * ray[2])
        lights += [point_light_incidence(ops, position, light3("positions", i), light3("intensity", i))
                   for i in range(n_point)]
    alpha = map_channels("alpha", 1)[0] if layout.alpha is None else layout.alpha
    spec = None
    if layout.mode == "blinn_phong":
        spec = map_channels("spec_albedo", 3) if layout.spec_albedo is None else (layout.spec_albedo,) * 3
    rgb = blinn_phong_radiance(ops, map_channels("normal", 3), view, lights, map_channels("albedo", 3),
                               layout.k_d, spec, layout.k_s, alpha)
    if "mask" in arrays:
        m = map_channels("mask", 1)[0]
        rgb = (rgb[0] * m, rgb[1] * m, rgb[2] * m)
    return rgb, leaves, idx, base3


def _shade_forward(layout: _Layout, arrays: dict) -> Any:
    """The shaded maps, a flat (N, 3, H, W) array, from one kernel."""
    dr = backend.drjit()
    rgb, _, _, base3 = _shade_graph(layout, arrays)
    Float = type(arrays["normal"])
    per_image = layout.lanes_per_image
    out = dr.empty(Float, layout.n * 3 * layout.h * layout.w)
    for c in range(3):
        # Permute (no two lanes write one element) lets the three packet stores share one kernel;
        # without it each launched its own. One output array: torch.stack of three channels would copy.
        dr.scatter(out, rgb[c], base3 + c * per_image, mode=dr.ReduceMode.Permute)
    return out


def _shade_backward(layout: _Layout, arrays: dict, grad_out: Any) -> dict:
    """Gradients of ``Σ grad_out · shade`` for the inputs in ``layout.wants``, from one kernel.

    ``grad_out`` is the flat upstream gradient, or one value when it is a broadcast scalar (the
    gradient of a sum or a mean: materialising it took 4 ms at 8 x 256²).
    """
    dr = backend.drjit()
    Float = type(arrays["normal"])
    for name in layout.wants:
        if name in _PER_IMAGE:
            dr.enable_grad(arrays[name])
    rgb, leaves, idx, base3 = _shade_graph(layout, arrays)
    Pixels = type(rgb[0])
    k, per_image = layout.k, layout.lanes_per_image
    for c in range(3):
        if layout.grad_scalar:
            dr.set_grad(rgb[c], Pixels([grad_out] * k))
        else:
            dr.set_grad(rgb[c], dr.gather(Pixels, grad_out, base3 + c * per_image, shape=(k, dr.width(idx))))
    dr.enqueue(dr.ADMode.Backward, *rgb)
    dr.traverse(dr.ADMode.Backward)
    grads = {}
    for name, values in leaves.items():
        grads[name] = dr.empty(Float, dr.width(arrays[name]))
        index = idx if len(values) == 1 else base3
        for c, value in enumerate(values):
            dr.scatter(grads[name], dr.grad(value), index + c * per_image, mode=dr.ReduceMode.Permute)
    grads.update({name: dr.grad(arrays[name]) for name in layout.wants if name in _PER_IMAGE})
    return grads


#: Record the Dr.Jit op's kernels once per layout and replay them (``dr.freeze``). Set to False to
#: trace every call instead (same values; for debugging, or should a platform's Dr.Jit misbehave).
FREEZE = True
_FROZEN: dict[str, Callable] = {}


def _frozen(fn: Callable) -> Callable:
    """``dr.freeze(fn)``, made once; ``fn`` itself when :data:`FREEZE` is off.

    A replay skips the Python tracing and the kernel's code generation: at 8 x 256² the forward is
    1.3x faster (diffuse 3.25 -> 2.52 ms, Blinn-Phong 4.74 -> 3.49 ms) and forward + backward 1.15-1.2x
    (interleaved A/B, bench/RESULTS.md). Keyed by the :class:`_Layout` (and Dr.Jit's flags); the 16
    most recent layouts are kept.
    """
    if not FREEZE:
        return fn
    if fn.__name__ not in _FROZEN:
        _FROZEN[fn.__name__] = backend.drjit().freeze(fn, limit=16, warn_after=64)
    return _FROZEN[fn.__name__]


def _packet_aligned(t: torch.Tensor, packet_bytes: int) -> torch.Tensor:
    """``t`` itself (no copy) when its data starts on a packet boundary, else an aligned copy: the
    kernel reads maps with packet loads, which on a GPU must be aligned (a view into a larger
    tensor may start anywhere)."""
    return t if t.data_ptr() % packet_bytes == 0 else t.clone()


def _drjit_run(opts: dict, intrinsics: tuple, inputs: Sequence[torch.Tensor | None],
               grad_out: torch.Tensor | None = None, needs: Sequence[bool] = ()) -> Any:
    """Shade in Dr.Jit; with ``grad_out``, return the input gradients (in :data:`_INPUTS` order) instead.

    Every call builds the Dr.Jit graph anew from the saved inputs (or replays its recording), so any
    number of backward passes over one torch graph is correct (plain ``dr.wrap`` returns a stale
    gradient on the second one).
    """
    dr = backend.drjit()
    x = {name: t for name, t in zip(_INPUTS, inputs) if t is not None}
    normal = x["normal"]
    mod = dr.cuda.ad if normal.is_cuda else dr.llvm.ad
    Float, UInt = (mod.Float64 if normal.dtype == torch.float64 else mod.Float), mod.UInt
    n, _, h, w = normal.shape
    wants = tuple(name for name, need in zip(_INPUTS, needs) if need and name in x) if grad_out is not None else ()
    expanded = set()
    for name in _PER_IMAGE:
        if name in wants and x[name].shape[0] == 1 and n > 1:
            # Dr.Jit's reverse of a gather that every lane reads at one address is a contended
            # reduction, 2.5x slower than one row per image (summed back below).
            x[name] = x[name].expand(n, *x[name].shape[1:])
            expanded.add(name)
    k = pixels_per_lane(w)
    packet = k * normal.element_size()
    arrays = {name: Float(_packet_aligned(t.detach().reshape(-1), packet)) for name, t in x.items() if t.numel()}
    shared = tuple(name for name in _PER_IMAGE if name in arrays and x[name].shape[0] == 1 and name not in wants)
    for name in shared:
        arrays[name] = tuple(dr.gather(Float, arrays[name], UInt(i)) for i in range(x[name].numel()))
    arrays["intr"] = _drjit_intrinsics(intrinsics, Float)
    if len(intrinsics) == 1:
        shared += ("intr",)
    layout = _Layout(opts["mode"], opts["view"], opts["k_d"], opts["k_s"], opts["alpha"], opts["spec_albedo"], n, h, w,
                     k, (("intr", 3),) + tuple((name, x[name][0].numel()) for name in _PER_IMAGE),
                     shared, wants)

    if grad_out is None:
        out = _frozen(_shade_forward)(layout, arrays)
        return out.torch().reshape(n, 3, h, w)

    g = grad_out.detach().to(normal.dtype)
    scalar = all(s == 0 for s in g.stride())
    g = Float(g.as_strided((1,), (1,)) if scalar else _packet_aligned(g.reshape(-1), packet))
    grads = _frozen(_shade_backward)(layout._replace(grad_scalar=scalar), arrays, g)
    result = []
    for name in _INPUTS:
        if name not in grads:
            result.append(None)
            continue
        grad = grads[name].torch()
        result.append(grad.reshape(n, *x[name].shape[1:]).sum(0, keepdim=True) if name in expanded
                      else grad.reshape(x[name].shape))
    return result


class _DrJitShade(torch.autograd.Function):
    """torch autograd around :func:`_drjit_run`; backward recomputes the Dr.Jit graph (see there)."""

    @staticmethod
    def forward(ctx, opts, intrinsics, *inputs):  # type: ignore[override]
        ctx.opts, ctx.intrinsics = opts, intrinsics
        ctx.save_for_backward(*inputs)
        return _drjit_run(opts, intrinsics, inputs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # type: ignore[override]
        grads = _drjit_run(ctx.opts, ctx.intrinsics, ctx.saved_tensors, grad_out=grad_out,
                           needs=ctx.needs_input_grad[2:])
        return (None, None, *grads)


# --------------------------------------------------------------------------- public API

def shade(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None = None,
          lights: Sequence[Light] | CameraLights = (), camera: Camera | Sequence[Camera] | None = None, *,
          depth: torch.Tensor | None = None, k_d: float = 0.8, k_s: float = 0.2,
          alpha: float | torch.Tensor = 4.0, spec_albedo: float | torch.Tensor = 1.0,
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
        k_d, k_s: diffuse and specular constants (paper: 0.8 / 0.2 chairs, 0.6 / 0.4 cars).
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
        intr = _intrinsics_tensor(intrinsics, dtype, str(device))
        return _torch_shade(cast(normal), cast(albedo), cast(mask), cast(depth), intr, CameraLights(*light_tensors),
                            cast(alpha), cast(spec_albedo), opts)
    inputs = [cast(normal), cast(albedo), cast(mask), cast(depth), *light_tensors,
              cast(alpha) if isinstance(alpha, torch.Tensor) else None,
              cast(spec_albedo) if isinstance(spec_albedo, torch.Tensor) else None]
    if not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs)):
        return _drjit_run(opts, intrinsics, inputs)  # no autograd node needed
    return _DrJitShade.apply(opts, intrinsics, *inputs)


def render_diffuse(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None,
                   lights: Sequence[Light] | CameraLights, camera: Camera | Sequence[Camera] | None = None,
                   k_d: float = 0.8, **kwargs: Any) -> torch.Tensor:
    """R_diff: the diffuse part of Eq. (1), ``Σ_l E_l k_d max(N·L_l, 0) I_d`` (paper Sec. 3.4)."""
    return shade(normal, albedo, mask, lights, camera, k_d=k_d, mode="diffuse", **kwargs)


def render_blinn_phong(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor | None,
                       lights: Sequence[Light] | CameraLights, camera: Camera | Sequence[Camera] | None = None,
                       **kwargs: Any) -> torch.Tensor:
    """R_BP: the full Blinn-Phong rendering function of App. A, Eq. (1)."""
    return shade(normal, albedo, mask, lights, camera, mode="blinn_phong", **kwargs)
