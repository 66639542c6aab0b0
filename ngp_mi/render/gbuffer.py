"""Reference G-buffers: Mitsuba's ``aov`` integrator sampled exactly at pixel centres.

One render per view gives the requested subset of

* ``depth``  — z-depth along the optical axis, 0 on background,
* ``normal`` — camera-space shading normals (OpenCV axes) facing the camera, 0 on background,
* ``albedo`` — the BSDF's diffuse reflectance (linear RGB), 0 on background,
* ``noc``    — world position normalised by the object's bounding box to [0, 1]³, 0 on background,
* ``mask``   — 1 on the object, 0 elsewhere,

all clean at silhouettes: one sample per pixel at its centre (a ``stratified`` sampler without
jitter and a box filter), so no hit/miss blending and normals consistent with the depth.
Only the AOVs the requested channels need are rendered ("model only what a scene requires").
Mitsuba's ``depth`` AOV is the ray length from the *near plane*; we convert it to z-depth.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.render.scene import render, set_sensor_camera

CHANNELS = ("depth", "normal", "albedo", "noc", "mask")
_AOVS = {"depth": ("depth", 1), "normal": ("sh_normal", 3), "albedo": ("albedo", 3), "noc": ("position", 3)}
_NEAR_CLIP = 1e-3  # Camera.to_mitsuba's near clip: Mitsuba's rays start on the near plane


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
        """The requested maps for ``camera``: (H, W) for depth and mask, (H, W, 3) for the others."""
        set_sensor_camera(self.scene.sensors()[0], camera)
        image = render(self.scene)
        maps, offset = {}, 0
        for name in self._aovs:
            width = _AOVS[name][1]
            maps[name] = image[..., offset] if width == 1 else image[..., offset:offset + width]
            offset += width
        hit = (maps["depth"] > 0).astype(np.float32)
        rays, inv_length = self._rays(camera)
        out: dict[str, np.ndarray] = {}
        if "depth" in self.channels:
            out["depth"] = (maps["depth"] * inv_length + _NEAR_CLIP) * hit
        if "normal" in self.channels:
            n = maps["normal"] @ camera.R.T.astype(np.float32)  # world -> camera
            facing = np.where(np.einsum("hwc,hwc->hw", n, rays) > 0, -hit, hit)  # face the camera; 0 off the object
            out["normal"] = n * facing[..., None]
        if "albedo" in self.channels:
            out["albedo"] = maps["albedo"] * hit[..., None]
        if "noc" in self.channels:
            lo, hi = self.bounds.astype(np.float32)
            out["noc"] = (maps["noc"] - lo) * (1.0 / np.maximum(hi - lo, 1e-12)) * hit[..., None]
        if "mask" in self.channels:
            out["mask"] = hit
        return {name: np.ascontiguousarray(out[name], dtype=np.float32) for name in self.channels}

    def _rays(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre rays (z = 1) and 1 / their length, cached per intrinsics."""
        key = (camera.focal_px, camera.cx, camera.cy, camera.width, camera.height)
        if getattr(self, "_ray_key", None) != key:
            rays = camera.pixel_rays().astype(np.float32)
            self._ray_cache = (rays, 1.0 / np.linalg.norm(rays, axis=-1))
            self._ray_key = key
        return self._ray_cache
