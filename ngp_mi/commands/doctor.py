"""`ngp-mi doctor`: what the installation runs on, and whether Mitsuba renders."""

from __future__ import annotations

import platform
import statistics
import time

import numpy as np
import torch

from ngp_mi import __version__, backend
from ngp_mi.camera import Camera
from ngp_mi.lights import DirectionalLight
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render


def test_render(resolution: int = 64, repeats: int = 5) -> tuple[float, float]:
    """Render a lit diffuse sphere; return (first-call seconds, median seconds of later calls).

    Raises ``RuntimeError`` when the image is wrong: non-finite, an unlit sphere or a lit background.
    """
    mi = backend.mitsuba()
    camera = Camera.orbit(0.0, 0.0, resolution)
    shapes = {"sphere": {"type": "sphere", "radius": 0.5, "bsdf": mi.load_dict(diffuse_bsdf(0.5))}}
    scene = build_scene(camera, shapes, [DirectionalLight((0, 0, 1), 1.0)], {"type": "direct"}, spp=4)
    times = []
    for i in range(repeats + 1):
        start = time.perf_counter()
        image = render(scene, seed=i)
        times.append(time.perf_counter() - start)
    centre = image[resolution // 2, resolution // 2]
    # Facing the light: radiance = albedo * E * cos(0) / pi.
    if not np.all(np.isfinite(image)) or not np.allclose(centre, 0.5 / np.pi, rtol=0.05) or image[0, 0].any():
        raise RuntimeError(f"test render is wrong: centre {centre.tolist()} (expected {0.5 / np.pi:.4f}), "
                           f"corner {image[0, 0].tolist()} (expected 0)")
    return times[0], statistics.median(times[1:])


def run_doctor(log=print) -> int:
    """Print the report; return the exit code (0 only if rendering works)."""
    log(f"ngp-mi    {__version__}")
    log(f"python    {platform.python_version()} ({platform.machine()}, {platform.system()})")
    log(f"torch     {torch.__version__} (threads {torch.get_num_threads()}, cuda {torch.cuda.is_available()})")
    try:
        b = backend.load()
    except backend.BackendError as error:
        log(f"backend   NOT USABLE: {error}")
        return 1
    log(f"mitsuba   {b.mi.__version__}")
    log(f"drjit     {b.dr.__version__}")
    log(f"variant   {b.variant}")
    log(f"libLLVM   {b.libllvm or '(not used)'}")
    log(f"threads   {b.threads}")
    try:
        first, median = test_render()
    except Exception as error:  # doctor reports every failure rather than raising
        log(f"render    FAILED: {error}")
        return 1
    log(f"render    64x64 ok: first call {first * 1e3:.1f} ms (includes JIT compile), then {median * 1e3:.2f} ms")
    return 0
