"""`make demo`: the showcase of what works so far, written under ``outputs/demo``.

1. ``views.png`` — a procedural chair path traced from views drawn from the paper's camera
   distribution, under the paper's 4-light overhead rig (``views.json``: cameras and lights).
2. ``chair.png``, ``car.png`` — 16 samples of each procedural family, to show their variety.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from ngp_mi.atomic import write_json
from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.geometry.families import generate
from ngp_mi.lights import lights_to_json, overhead_rig
from ngp_mi.render.preview import object_shapes, preview_sheet
from ngp_mi.render.scene import build_scene, render, set_sensor_camera
from ngp_mi.viz import contact_sheet, save_png, to_uint8

FAMILY_VIEW = (15.0, 35.0)


def family_sheet(family: str, out: str | Path, count: int = 16, resolution: int = 128, spp: int = 32,
                 first_seed: int = 0) -> Path:
    """Contact sheet of ``count`` consecutive seeds of ``family`` from one paper-range view."""
    objects = [generate(family, seed) for seed in range(first_seed, first_seed + count)]
    return save_png(out, preview_sheet(objects, Camera.orbit(*FAMILY_VIEW, resolution), spp=spp))


def run_demo(out_dir: str | Path = "outputs/demo", resolution: int = 128, views: int = 12, spp: int = 64,
             seed: int = 0, family_count: int = 16, log=print) -> Path:
    """Write the demo images; returns the path of ``views.png``."""
    out_dir = Path(out_dir)
    obj = generate("chair", seed)
    lights = overhead_rig()
    cameras = ViewDistribution().sample(views, seed=seed, resolution=resolution)
    scene = build_scene(cameras[0], object_shapes(obj), lights, integrator={"type": "path", "max_depth": 4},
                        spp=spp, seed=seed)
    sensor = scene.sensors()[0]
    tiles, labels, start = [], [], time.perf_counter()
    for i, camera in enumerate(cameras):
        set_sensor_camera(sensor, camera)
        tiles.append(to_uint8(render(scene, seed=seed + i)))
        labels.append(f"th={camera.theta_deg:.0f} ph={camera.phi_deg:.0f}")
        rate = (i + 1) / (time.perf_counter() - start)
        log(f"demo: view {i + 1}/{views}  {rate:.1f} views/s  ETA {(views - i - 1) / rate:.1f} s")
    sheet = save_png(out_dir / "views.png", contact_sheet(tiles, labels, columns=4))
    write_json(out_dir / "views.json", {
        "object": obj.id, "params": obj.params, "resolution": resolution, "spp": spp, "seed": seed,
        "cameras": [c.to_dict() for c in cameras], "lights": json.loads(lights_to_json(lights))["lights"],
    })
    log(f"demo: wrote {sheet}")
    for family in ("chair", "car"):
        path = family_sheet(family, out_dir / f"{family}.png", count=family_count, resolution=resolution,
                            spp=max(1, spp // 2))
        log(f"demo: wrote {path}")
    return sheet
