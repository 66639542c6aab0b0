"""Reference G-buffers sampled exactly at pixel centres, by Mitsuba.

Each view gives the requested subset of

* ``depth``  — z-depth along the optical axis, 0 on background,
* ``normal`` — camera-space shading normals (OpenCV axes) facing the camera, 0 on background,
* ``albedo`` — the BSDF's diffuse reflectance (linear RGB), 0 on background,
* ``noc``    — world position normalised by the object's bounding box to [0, 1]³, 0 on background,
* ``mask``   — 1 on the object, 0 elsewhere,

all clean at silhouettes: one sample per pixel at its centre (a ``stratified`` sampler without
jitter and a box filter), so no hit/miss blending and normals consistent with the depth.
Only what the requested channels need is computed ("model only what a scene requires").

Two paths give the same maps (``tests/test_gbuffer.py`` compares them channel by channel):

* :meth:`GBufferRenderer.render` — one view through Mitsuba's ``aov`` integrator (whose ``depth``
  AOV is the ray length from the *near plane*; we convert it to z-depth). The reference.
* :meth:`GBufferRenderer.render_views` — many views in one kernel: the pixel-centre rays of all
  views are cast together (:mod:`ngp_mi.render.rays`) and the quantities the aov integrator
  reads from the intersection (``si.t``, ``si.sh_frame.n``, the BSDF's diffuse reflectance,
  ``si.p``) are converted and written straight into one array per channel. 7x faster per view at
  128² (``bench/RESULTS.md``); the dataset renderer uses it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.render.rays import camera_table, pixel_centre_rays
from ngp_mi.render.scene import set_sensor_camera

if TYPE_CHECKING:  # torch is imported only when tensors are asked for
    import torch

CHANNELS = ("depth", "normal", "albedo", "noc", "mask")
_AOVS = {"depth": ("depth", 1), "normal": ("sh_normal", 3), "albedo": ("albedo", 3), "noc": ("position", 3)}
_NEAR_CLIP = 1e-3  # Camera.to_mitsuba's near clip: Mitsuba's rays start on the near plane
LANES_PER_LAUNCH = 1 << 22  # bounds the memory of render_views (64 views at 256²)


def maps_to_tensors(maps: Mapping[str, np.ndarray]) -> dict[str, "torch.Tensor"]:
    """G-buffer maps (H, W) / (H, W, 3) as a batch of one NCHW torch tensor each (sharing memory)."""
    import torch  # ~3 s to import: dataset workers, which never ask for tensors, go without it

    return {name: torch.from_numpy(m).permute(2, 0, 1)[None] if m.ndim == 3 else torch.from_numpy(m)[None, None]
            for name, m in maps.items()}


class GBufferRenderer:
    """Renders G-buffers of fixed shapes from any camera of one resolution."""

    def __init__(self, shapes: Mapping[str, Any], bounds: np.ndarray, camera: Camera,
                 channels: Sequence[str] = CHANNELS):
        unknown = [c for c in channels if c not in CHANNELS]
        if unknown or not channels:
            raise ValueError(f"G-buffer channels must be a non-empty subset of {CHANNELS}, got {list(channels)}")
        mi = backend.mitsuba()
        self.channels = tuple(channels)
        self.bounds = np.asarray(bounds, np.float64)
        # depth is always rendered: it also gives the mask and the background of every channel.
        self._aovs = ["depth"] + [c for c in self.channels if c in _AOVS and c != "depth"]
        sensor = camera.to_mitsuba(spp=1, rfilter="box", sampler="stratified")
        sensor["sampler"]["jitter"] = False  # the one sample sits at the pixel centre
        sensor["near_clip"] = _NEAR_CLIP
        aov_string = ",".join(f"{name}:{_AOVS[name][0]}" for name in self._aovs)
        self.scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": aov_string},
                                   "sensor": sensor, **shapes})
        self.resolution = (camera.width, camera.height)

    def render(self, camera: Camera) -> dict[str, np.ndarray]:
        """The requested maps for ``camera``: (H, W) for depth and mask, (H, W, 3) for the others.

        The AOV image is converted in one Dr.Jit kernel: ray length → z-depth, world → camera
        normals (flipped to face the camera), positions → NOC, background → 0. The camera enters
        as a small array, not as literals, so a new view reuses the compiled kernel.
        """
        mi, dr = backend.mitsuba(), backend.drjit()
        set_sensor_camera(self.scene.sensors()[0], camera)
        image = mi.render(self.scene)
        h, w, stride = image.shape
        flat = image.array
        lo, hi = self.bounds
        params = mi.Float(np.concatenate([camera.R.ravel(), [camera.focal_px, camera.cx, camera.cy],
                                          lo, 1.0 / np.maximum(hi - lo, 1e-12)]).astype(np.float32))
        p = [dr.gather(mi.Float, params, k) for k in range(18)]
        idx = dr.arange(mi.UInt32, h * w)
        ray = mi.Vector3f((mi.Float(idx % w) + 0.5 - p[10]) / p[9], (mi.Float(idx // w) + 0.5 - p[11]) / p[9], 1.0)

        def aov(name: str) -> Any:
            offset = sum(_AOVS[n][1] for n in self._aovs[: self._aovs.index(name)])
            values = [dr.gather(mi.Float, flat, idx * stride + offset + k) for k in range(_AOVS[name][1])]
            return values[0] if len(values) == 1 else mi.Vector3f(*values)

        length = aov("depth")
        hit = length > 0
        out: dict[str, Any] = {}
        if "depth" in self.channels:
            out["depth"] = dr.select(hit, length * dr.rsqrt(dr.squared_norm(ray)) + _NEAR_CLIP, 0.0)
        if "normal" in self.channels:
            n = mi.Matrix3f(*p[:9]) @ aov("normal")  # world -> camera
            n = dr.select(dr.dot(n, ray) > 0, -n, n)  # face the camera
            out["normal"] = dr.select(hit, n, 0.0)
        if "albedo" in self.channels:
            out["albedo"] = dr.select(hit, aov("albedo"), 0.0)
        if "noc" in self.channels:
            noc = (aov("noc") - mi.Vector3f(*p[12:15])) * mi.Vector3f(*p[15:18])
            out["noc"] = dr.select(hit, noc, 0.0)
        if "mask" in self.channels:
            out["mask"] = dr.select(hit, mi.Float(1.0), 0.0)
        dr.eval(*out.values())
        maps = {}
        for name in self.channels:
            value = out[name]
            if dr.depth_v(value) > 1:
                maps[name] = np.stack([value[k].numpy() for k in range(3)], axis=-1).reshape(h, w, 3)
            else:
                maps[name] = value.numpy().reshape(h, w)
        return maps

    def render_views(self, cameras: Sequence[Camera]) -> dict[str, np.ndarray]:
        """The requested maps of every camera, stacked: (N, H, W) for depth and mask, (N, H, W, 3) else.

        The same values as :meth:`render` per view (pixel centres, camera-facing shading normals,
        background 0), computed for all views by one ray cast and one kernel per launch of at
        most 4M pixels. 3-vector channels are scattered straight into (N, H, W, 3) order.
        """
        mi, dr = backend.mitsuba(), backend.drjit()
        width, height = self.resolution
        if any((c.width, c.height) != (width, height) for c in cameras):
            raise ValueError(f"render_views: every camera must be {width}x{height}")
        table = camera_table(cameras)
        n, hw = len(cameras), width * height
        # Opaque, not literals: a literal bounding box would make every shape a new kernel to compile.
        lo = dr.opaque(mi.Vector3f, self.bounds[0].tolist())
        inv_extent = dr.opaque(mi.Vector3f, (1.0 / np.maximum(self.bounds[1] - self.bounds[0], 1e-12)).tolist())
        step = max(1, LANES_PER_LAUNCH // hw)
        chunks: dict[str, list[np.ndarray]] = {name: [] for name in self.channels}
        for first in range(0, n, step):
            count = min(step, n - first)
            rays = pixel_centre_rays(table, width, height, first, count)
            si = self.scene.ray_intersect(rays.ray, ray_flags=mi.RayFlags.All, coherent=True)
            hit = si.is_valid()
            out: dict[str, Any] = {}
            if "depth" in self.channels:
                out["depth"] = dr.select(hit, si.t * rays.inv_len, 0.0)
            if "mask" in self.channels:
                out["mask"] = dr.select(hit, mi.Float(1.0), 0.0)
            vectors: dict[str, Any] = {}
            if "normal" in self.channels:
                normal = rays.R @ si.sh_frame.n  # world → camera
                vectors["normal"] = dr.select(dr.dot(normal, rays.local) > 0, -normal, normal)
            if "albedo" in self.channels:
                vectors["albedo"] = mi.Vector3f(si.bsdf().eval_diffuse_reflectance(si, hit))
            if "noc" in self.channels:
                vectors["noc"] = (si.p - lo) * inv_extent
            lanes = dr.arange(mi.UInt32, count * hw)
            for name, value in vectors.items():
                value = dr.select(hit, value, 0.0)
                flat = dr.empty(mi.Float, 3 * count * hw)
                for k in range(3):  # (N, H, W, 3) order; every element written once
                    dr.scatter(flat, value[k], lanes * 3 + k, mode=dr.ReduceMode.Permute)
                out[name] = flat
            dr.eval(*out.values())
            for name, value in out.items():  # numpy views of Dr.Jit's memory: no copy
                shape = (count, height, width, 3) if name in vectors else (count, height, width)
                chunks[name].append(value.numpy().reshape(shape))
        return {name: parts[0] if len(parts) == 1 else np.concatenate(parts) for name, parts in chunks.items()}
