"""``ngp-mi sample-shapes``: meshes from a trained shape prior, a rendered contact sheet, interpolations.

Shape ``k`` of ``--seed s`` uses z_s drawn from N(0, I) by a generator seeded ``s + k``, so any one
shape can be reproduced alone. ``--interpolate A B`` walks from the latent of seed A to that of seed
B in ``--steps`` steps along the great circle (slerp, which keeps |z_s| typical of a Gaussian
sample, where a straight line would pass through low-norm latents the GAN never saw).

Outputs in ``OUT``: ``shape-XXX.obj|ply`` (written atomically), ``sheet.png`` (each mesh path traced
with the project's Mitsuba renderer from the paper's camera), ``samples.json`` (latent seeds, faces,
field evaluations, extraction time) and ``report.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ngp_mi.atomic import atomic_path, write_json, write_text
from ngp_mi.camera import Camera
from ngp_mi.models.shape import ShapeModel
from ngp_mi.pipeline import latent, slerp
from ngp_mi.render.preview import mesh_preview
from ngp_mi.viz import contact_sheet, save_png


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """OBJ or PLY (by suffix) through trimesh, written atomically."""
    import trimesh  # over a second to import: only when a mesh is written

    with atomic_path(path) as tmp:
        trimesh.Trimesh(vertices, faces, process=False).export(str(tmp))


def sample_shapes(run: str | Path, out: str | Path, num: int = 16, seed: int = 0, resolution: int = 128,
                  coarse: int = 32, fmt: str = "obj", interpolate: tuple[int, int] | None = None, steps: int = 8,
                  preview_resolution: int = 128, spp: int = 16, device: str = "cpu") -> dict[str, Any]:
    if fmt not in ("obj", "ply"):
        raise ValueError(f"sample-shapes: --format must be obj or ply, got {fmt!r}")
    model = ShapeModel.from_run(run, device)
    z_dim = model.config.z_dim
    if interpolate is not None:
        a, b = latent(interpolate[0], z_dim), latent(interpolate[1], z_dim)
        ts = np.linspace(0.0, 1.0, steps)
        jobs = [(f"{interpolate[0]}->{interpolate[1]} t={t:.2f}", slerp(a, b, float(t))) for t in ts]
    else:
        jobs = [(f"seed {seed + k}", latent(seed + k, z_dim)) for k in range(num)]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    camera = Camera.orbit(20.0, 45.0, preview_resolution)
    records, tiles = [], []
    for k, (label, z) in enumerate(tqdm(jobs, unit="shape", desc="sample shapes")):
        extraction = model.shape(z, resolution, coarse)
        record = {"index": k, "label": label, "evaluated": extraction.evaluated, "dense": extraction.dense,
                  "seconds": round(extraction.seconds, 3)}
        if extraction.mesh is None:
            record["file"] = None
            tiles.append(np.full((preview_resolution, preview_resolution, 3), 32, np.uint8))
        else:
            path = out / f"shape-{k:03d}.{fmt}"
            write_mesh(path, extraction.mesh.vertices, extraction.mesh.faces)
            record.update(file=path.name, vertices=len(extraction.mesh.vertices), faces=len(extraction.mesh.faces))
            tiles.append(mesh_preview(extraction.mesh, camera, spp=spp, seed=k))
        records.append(record)
    save_png(out / "sheet.png", contact_sheet(tiles, [r["label"] for r in records], columns=min(len(tiles), 8)))
    summary = {"run": str(run), "resolution": resolution, "coarse": coarse, "interpolate": interpolate,
               "shapes": records, "empty": sum(r["file"] is None for r in records),
               "median_seconds": float(np.median([r["seconds"] for r in records]))}
    write_json(out / "samples.json", summary)
    lines = [f"# Shapes sampled from `{run}`", "",
             f"{len(records)} shapes at {resolution}³ (coarse-to-fine from {coarse}³); "
             f"{summary['empty']} empty; median extraction {summary['median_seconds']:.2f} s.", "",
             "![samples](sheet.png)", "", "| # | latent | file | faces | field evaluations (dense) | s |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['index']} | {r['label']} | {r['file'] or '(empty)'} | {r.get('faces', 0)} | "
              f"{r['evaluated']} ({r['dense']}) | {r['seconds']} |" for r in records]
    write_text(out / "report.md", "\n".join(lines) + "\n")
    return summary
