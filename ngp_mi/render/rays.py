"""Pixel-centre rays of a batch of cameras as one Dr.Jit array: the ray setup of Π_v and the G-buffers.

Lane ``k = n·H·W + y·W + x`` is the ray through the centre ``(x + ½, y + ½)`` of pixel (x, y) of
view n. In camera space (OpenCV axes) its direction is ``d_c = K⁻¹ [u, v, 1] = ((u − c_x)/f,
(v − c_y)/f, 1)``, so a hit at distance t along the *unit* ray has z-depth ``t / |d_c|``. The
cameras enter as a small table of kernel inputs, never as literals: a new view reuses the kernel.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from ngp_mi import backend
from ngp_mi.camera import Camera

TABLE_WIDTH = 15  # R (9, row-major), camera centre (3), focal_px, cx, cy


def camera_table(cameras: Sequence[Camera]) -> np.ndarray:
    """(N, 15) float32 rows: R (row-major), camera centre, focal_px, cx, cy."""
    return np.stack([np.concatenate([c.R.ravel(), c.position, [c.focal_px, c.cx, c.cy]])
                     for c in cameras]).astype(np.float32)


@dataclasses.dataclass
class PixelRays:
    """Per-lane quantities of :func:`pixel_centre_rays` (Dr.Jit arrays)."""

    view: Any      # UInt32: view index n
    pixel: Any     # UInt32: y·W + x
    R: Any         # Matrix3f: world → camera rotation of the lane's view
    local: Any     # Vector3f: camera-space direction K⁻¹ [u, v, 1] (z = 1, not unit)
    inv_len: Any   # Float: 1 / |local|, so that z-depth = t · inv_len
    ray: Any       # Ray3f: world-space unit ray from the camera centre


def pixel_centre_rays(table: np.ndarray, width: int, height: int, first_view: int = 0,
                      num_views: int | None = None) -> PixelRays:
    """Rays through the pixel centres of views ``first_view … first_view + num_views − 1`` of ``table``."""
    mi, dr = backend.mitsuba(), backend.drjit()
    num_views = len(table) - first_view if num_views is None else num_views
    hw = width * height
    cam = mi.Float(np.ascontiguousarray(table[first_view:first_view + num_views], np.float32).ravel())
    idx = dr.arange(mi.UInt32, num_views * hw)
    view = idx // hw
    pixel = idx - view * hw
    row = [dr.gather(mi.Float, cam, view * TABLE_WIDTH + k) for k in range(TABLE_WIDTH)]
    R = mi.Matrix3f(*row[:9])
    focal, cx, cy = row[12:15]
    local = mi.Vector3f((mi.Float(pixel % width) + 0.5 - cx) / focal,
                        (mi.Float(pixel // width) + 0.5 - cy) / focal, 1.0)
    inv_len = dr.rsqrt(dr.squared_norm(local))
    direction = R.T @ (local * inv_len)  # camera → world
    return PixelRays(view, pixel, R, local, inv_len, mi.Ray3f(mi.Point3f(*row[9:12]), direction))
