"""``ngp-mi generate``: NGP images of sampled shapes or a user mesh, with every intermediate map and a report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ngp_mi.atomic import write_json, write_text
from ngp_mi.camera import Camera
from ngp_mi.data.datasets import read_image
from ngp_mi.geometry.loaders import load_mesh
from ngp_mi.lights import Light, lights_to_json, overhead_rig
from ngp_mi.pipeline import NGP, latent
from ngp_mi.viz import contact_sheet, save_png, to_uint8


def generate(maps_run: str | Path, out: str | Path, shape_run: str | Path | None = None, mesh_path: str | None = None,
             num: int = 4, seed: int = 0, views: Sequence[tuple[float, float]] = ((10.0, -30.0), (10.0, 30.0)),
             resolution: int = 128, lights: Sequence[Light] | None = None, added_lights: Sequence[Light] = (),
             variant: str = "ngp", exemplar: str | None = None, log=print) -> dict[str, Any]:
    """``ngp-mi generate``: ``num`` shapes (z_s of ``seed`` …, or the user's mesh) × ``views`` (θ, φ in
    degrees); writes ``images/*.png``, ``sheet.png`` (depth, normals, albedo, specular, image per
    row), ``generate.json`` and ``report.md``."""
    if not mesh_path and not shape_run:
        raise ValueError("generate: give a `train shape` run (--shape-run) to sample shapes, or a --mesh")
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    lights = list(lights) if lights is not None else overhead_rig()
    ngp = NGP(maps_run, shape_run if mesh_path is None else None)
    exemplar_tensor = None
    if exemplar:
        albedo = torch.from_numpy(np.ascontiguousarray(read_image(Path(exemplar), resolution, linear=True)))
        exemplar_tensor = torch.nn.functional.interpolate(albedo.permute(2, 0, 1)[None], size=(resolution, resolution),
                                                          mode="bilinear", align_corners=False)
    shapes = [("mesh", load_mesh(mesh_path))] if mesh_path else []
    for k in range(0 if mesh_path else num):
        z_s = latent(seed + k, ngp.shape_model.config.z_dim)
        shapes.append((f"z{seed + k}", ngp.shape(z_s)))
    rows, labels, records = [], [], []
    for k, (name, mesh) in enumerate(shapes):
        z_da = ngp.appearance(seed=seed + k, exemplar=exemplar_tensor)
        for theta, phi in views:
            camera = Camera.orbit(theta, phi, resolution)
            result = ngp.render(mesh, camera, z_da, lights, variant, added_lights)
            image = result["image"][0].permute(1, 2, 0).numpy()
            stem = f"{name}_t{theta:g}_p{phi:g}"
            save_png(out / "images" / f"{stem}.png", to_uint8(image))
            records.append({"shape": name, "theta": theta, "phi": phi, "file": f"images/{stem}.png"})
            rows.append(_tiles(result))
            labels.append(stem)
            log(f"generate: {stem}")
    names = ["coarse depth", "normals", "albedo", "specular", "image"]
    sheet = contact_sheet([tile for row in rows for tile in row], [f"{n}" for _ in rows for n in names], columns=len(names))
    save_png(out / "sheet.png", sheet)
    summary = {"maps_run": str(maps_run), "shape_run": str(shape_run) if shape_run else None, "mesh": mesh_path,
               "variant": variant, "resolution": resolution, "lights": json.loads(lights_to_json(lights)),
               "added_lights": json.loads(lights_to_json(added_lights)), "exemplar": exemplar, "images": records}
    write_json(out / "generate.json", summary)
    write_text(out / "report.md", 
        f"# NGP images ({variant})\n\nMaps: `{maps_run}`; shapes: {'`' + mesh_path + '`' if mesh_path else f'G_shape of `{shape_run}`, z_s seeds {seed}…{seed + num - 1}'}; "
        f"appearance: {'E_da of `' + exemplar + '`' if exemplar else 'z_da ~ N(0, I), one per shape'}; {len(lights)} "
        f"light(s){f' + {len(added_lights)} added' if added_lights else ''}; {resolution}².\n\n"
        "Rows: one view each (" + ", ".join(labels) + "); columns: " + ", ".join(names) + ".\n\n![sheet](sheet.png)\n")
    return summary


def _tiles(result: dict[str, torch.Tensor]) -> list[np.ndarray]:
    """One row of the sheet: coarse depth, normals, albedo, specular, image."""
    mask = result["mask"][0, 0].numpy() > 0
    depth = result["depth"][0, 0].numpy()
    shown = np.zeros_like(depth)
    if mask.any():
        lo, hi = depth[mask].min(), depth[mask].max()
        shown[mask] = 1 - 0.8 * (depth[mask] - lo) / max(hi - lo, 1e-6)
    to_rgb = lambda t: t[0].permute(1, 2, 0).clamp(0, 1).numpy()  # noqa: E731
    specular = result.get("specular", torch.zeros_like(result["image"]))
    return [to_uint8(np.repeat(shown[..., None], 3, -1), srgb=False),
            to_uint8(((result["normal"] + 1) / 2 * result["mask"])[0].permute(1, 2, 0).clamp(0, 1).numpy(), srgb=False),
            to_uint8(to_rgb(result["albedo"] * result["mask"])), to_uint8(to_rgb(specular)),
            to_uint8(to_rgb(result["image"]))]
