"""The Dr.Jit backend of :func:`ngp_mi.render.shading.shade`: one fused kernel, wrapped as a torch autograd op.

Each lane shades :func:`pixels_per_lane` adjacent pixels with packet loads and stores; the
kernels are recorded once per :class:`Layout` with ``dr.freeze`` and replayed (:data:`FREEZE`).
The backward re-traces the graph from the saved inputs, so any number of backward passes over one
torch graph is correct (plain ``dr.wrap`` returns a stale gradient on the second one).
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple, Sequence

import torch

from ngp_mi import backend
from ngp_mi.render.shading.blinn_phong import Ops, Vec, blinn_phong_radiance, point_light_incidence, safe_normalize

INPUTS = ("normal", "albedo", "mask", "depth", "directions", "irradiance", "positions", "intensity",
           "alpha", "spec_albedo")
PER_IMAGE = ("directions", "irradiance", "positions", "intensity")  # (1 or N, ...) rows


def _drjit_ops() -> Ops:
    """The shared maths' primitives on Dr.Jit arrays."""
    dr = backend.drjit()
    return Ops(dr.rsqrt, dr.exp, dr.log, dr.maximum, dr.select, dr.fma)


@functools.lru_cache(maxsize=32)
def _drjit_intrinsics(rows: tuple, float_type: type) -> Any:
    """The intrinsics rows as Dr.Jit values, made once per camera set: one opaque scalar per value for
    a shared row (a uniform load in the kernel), else one flat array."""
    dr = backend.drjit()
    values = [v for row in rows for v in row]
    if len(rows) == 1:
        return tuple(dr.opaque(float_type, v) for v in values)
    array = float_type(values)  # dr.opaque() refuses an array: make this one opaque in place
    dr.make_opaque(array)
    return array


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


class Layout(NamedTuple):
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


def _shade_graph(layout: Layout, arrays: dict) -> tuple[Vec, dict, Any, Any]:
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


def _shade_forward(layout: Layout, arrays: dict) -> Any:
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


def _shade_backward(layout: Layout, arrays: dict, grad_out: Any) -> dict:
    """Gradients of ``Σ grad_out · shade`` for the inputs in ``layout.wants``, from one kernel.

    ``grad_out`` is the flat upstream gradient, or one value when it is a broadcast scalar (the
    gradient of a sum or a mean: materialising it took 4 ms at 8 x 256²).
    """
    dr = backend.drjit()
    Float = type(arrays["normal"])
    for name in layout.wants:
        if name in PER_IMAGE:
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
    grads.update({name: dr.grad(arrays[name]) for name in layout.wants if name in PER_IMAGE})
    return grads


#: Record the Dr.Jit op's kernels once per layout and replay them (``dr.freeze``). Set to False to
#: trace every call instead (same values; for debugging, or should a platform's Dr.Jit misbehave).
FREEZE = True
#: The frozen functions made so far, by name (their ``n_recordings`` tell how often each traced).
RECORDINGS: dict[str, Callable] = {}


def _frozen(fn: Callable) -> Callable:
    """``dr.freeze(fn)``, made once; ``fn`` itself when :data:`FREEZE` is off.

    A replay skips the Python tracing and the kernel's code generation: at 8 x 256² the forward is
    1.3x faster (diffuse 3.25 -> 2.52 ms, Blinn-Phong 4.74 -> 3.49 ms) and forward + backward 1.15-1.2x
    (interleaved A/B, bench/RESULTS.md). Keyed by the :class:`Layout` (and Dr.Jit's flags); the 16
    most recent layouts are kept.
    """
    if not FREEZE:
        return fn
    if fn.__name__ not in RECORDINGS:
        RECORDINGS[fn.__name__] = backend.drjit().freeze(fn, limit=16, warn_after=64)
    return RECORDINGS[fn.__name__]


def _packet_aligned(t: torch.Tensor, packet_bytes: int) -> torch.Tensor:
    """``t`` itself (no copy) when its data starts on a packet boundary, else an aligned copy: the
    kernel reads maps with packet loads, which on a GPU must be aligned (a view into a larger
    tensor may start anywhere)."""
    return t if t.data_ptr() % packet_bytes == 0 else t.clone()


def drjit_shade(opts: dict, intrinsics: tuple, inputs: Sequence[torch.Tensor | None],
                grad_out: torch.Tensor | None = None, needs: Sequence[bool] = ()) -> Any:
    """Shade in Dr.Jit; with ``grad_out``, return the input gradients (in :data:`INPUTS` order) instead.

    Every call builds the Dr.Jit graph anew from the saved inputs (or replays its recording), so any
    number of backward passes over one torch graph is correct (plain ``dr.wrap`` returns a stale
    gradient on the second one).
    """
    dr = backend.drjit()
    x = {name: t for name, t in zip(INPUTS, inputs) if t is not None}
    normal = x["normal"]
    mod = dr.cuda.ad if normal.is_cuda else dr.llvm.ad
    Float, UInt = (mod.Float64 if normal.dtype == torch.float64 else mod.Float), mod.UInt
    n, _, h, w = normal.shape
    # an empty input (no point lights) has nothing to differentiate, even when it requires grad
    wants = tuple(name for name, need in zip(INPUTS, needs) if need and name in x and x[name].numel()) \
        if grad_out is not None else ()
    expanded = set()
    for name in PER_IMAGE:
        if name in wants and x[name].shape[0] == 1 and n > 1:
            # Dr.Jit's reverse of a gather that every lane reads at one address is a contended
            # reduction, 2.5x slower than one row per image (summed back below).
            x[name] = x[name].expand(n, *x[name].shape[1:])
            expanded.add(name)
    k = pixels_per_lane(w)
    packet = k * normal.element_size()
    arrays = {name: Float(_packet_aligned(t.detach().reshape(-1), packet)) for name, t in x.items() if t.numel()}
    shared = tuple(name for name in PER_IMAGE if name in arrays and x[name].shape[0] == 1 and name not in wants)
    for name in shared:
        arrays[name] = tuple(dr.gather(Float, arrays[name], UInt(i)) for i in range(x[name].numel()))
    arrays["intr"] = _drjit_intrinsics(intrinsics, Float)
    if len(intrinsics) == 1:
        shared += ("intr",)
    layout = Layout(opts["mode"], opts["view"], opts["k_d"], opts["k_s"], opts["alpha"], opts["spec_albedo"], n, h, w,
                     k, (("intr", 3),) + tuple((name, x[name][0].numel()) for name in PER_IMAGE),
                     shared, wants)

    if grad_out is None:
        out = _frozen(_shade_forward)(layout, arrays)
        return out.torch().reshape(n, 3, h, w)

    g = grad_out.detach().to(normal.dtype)
    scalar = all(s == 0 for s in g.stride())
    g = Float(g.as_strided((1,), (1,)) if scalar else _packet_aligned(g.reshape(-1), packet))
    grads = _frozen(_shade_backward)(layout._replace(grad_scalar=scalar), arrays, g)
    result = []
    for name in INPUTS:
        if name not in grads:
            result.append(None)
            continue
        grad = grads[name].torch()
        result.append(grad.reshape(n, *x[name].shape[1:]).sum(0, keepdim=True) if name in expanded
                      else grad.reshape(x[name].shape))
    return result


class DrJitShade(torch.autograd.Function):
    """torch autograd around :func:`drjit_shade`; backward recomputes the Dr.Jit graph (see there)."""

    @staticmethod
    def forward(ctx, opts, intrinsics, *inputs):  # type: ignore[override]
        ctx.opts, ctx.intrinsics = opts, intrinsics
        ctx.save_for_backward(*inputs)
        return drjit_shade(opts, intrinsics, inputs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # type: ignore[override]
        grads = drjit_shade(ctx.opts, ctx.intrinsics, ctx.saved_tensors, grad_out=grad_out,
                            needs=ctx.needs_input_grad[2:])
        return (None, None, *grads)

