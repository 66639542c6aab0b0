"""`make demo`: the showcase of what works so far.

Now: a built-in chair mesh path traced by Mitsuba from views drawn from the paper's camera
distribution, under the paper's 4-light overhead rig, as a labelled contact sheet.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from ngp_mi.camera import ViewDistribution
from ngp_mi.geometry.primitives import simple_chair
from ngp_mi.lights import lights_to_json, overhead_rig
from ngp_mi.render.scene import build_scene, diffuse_bsdf, mesh_parts_to_mitsuba, render, set_sensor_camera
from ngp_mi.viz import contact_sheet, save_png, to_uint8

# Linear-RGB albedos of the chair's parts: seat, four legs, back.
_CHAIR_ALBEDO = {0: (0.60, 0.22, 0.12), 5: (0.55, 0.20, 0.10)}
_LEG_ALBEDO = (0.25, 0.17, 0.10)


def run_demo(out_dir: str | Path = "outputs/demo", resolution: int = 128, views: int = 12, spp: int = 64,
             seed: int = 0, log=print) -> Path:
    """Render the contact sheet; returns its path. Also writes ``views.json`` (cameras and lights)."""
    out_dir = Path(out_dir)
    mesh = simple_chair()
    lights = overhead_rig()
    cameras = ViewDistribution().sample(views, seed=seed, resolution=resolution)
    bsdfs = {part: diffuse_bsdf(_CHAIR_ALBEDO.get(part, _LEG_ALBEDO)) for part in range(6)}
    scene = build_scene(cameras[0], mesh_parts_to_mitsuba(mesh, bsdfs), lights,
                        integrator={"type": "path", "max_depth": 3}, spp=spp, seed=seed)
    sensor = scene.sensors()[0]

    tiles, labels, start = [], [], time.perf_counter()
    for i, camera in enumerate(cameras):
        set_sensor_camera(sensor, camera)
        tiles.append(to_uint8(render(scene, seed=seed + i)))
        labels.append(f"th={camera.theta_deg:.0f} ph={camera.phi_deg:.0f}")
        done = i + 1
        rate = done / (time.perf_counter() - start)
        log(f"demo: view {done}/{views}  {rate:.1f} views/s  ETA {(views - done) / rate:.1f} s")

    sheet = save_png(out_dir / "contact_sheet.png", contact_sheet(tiles, labels, columns=4))
    (out_dir / "views.json").write_text(json.dumps({
        "mesh": mesh.name, "resolution": resolution, "spp": spp, "seed": seed,
        "cameras": [c.to_dict() for c in cameras], "lights": json.loads(lights_to_json(lights))["lights"],
    }, indent=1))
    log(f"demo: wrote {sheet}")
    return sheet
