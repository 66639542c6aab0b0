"""``ngp-mi evaluate shape``: how well a shape prior's autoencoder reconstructs shapes it was not trained on.

The coarse shapes NGP decorates are the prior's (paper Sec. 3.2); the map networks' normals can only
be as right as the surface they are read from. For each shape of a source (by default the held-out
chairs 500–519, which no shipped prior or `cpu` map run trains on):

* **IoU** — decode(encode(voxels)) against the voxels on the encoder's grid (IM-NET's autoencoder IoU);
* **Chamfer-L2** — between ``surface_points`` samples of the reconstruction's marching-cubes surface
  (at ``resolution``) and of the shape's own surface, both ways, squared distances (as IM-NET).

Outputs in ``out``: ``eval.json`` (per shape and the means), ``eval.md``, ``sheet.png`` (each shape
beside its reconstruction, path traced from one camera) and ``data/`` (the shapes' voxels and
surface samples, built once and reused).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ngp_mi.atomic import write_json, write_text
from ngp_mi.camera import Camera
from ngp_mi.data.shapes import ShapeDataConfig, ShapeDataset, build_shape_dataset, shape_refs
from ngp_mi.eval.shape_metrics import chamfer_distance
from ngp_mi.geometry.occupancy import load_solid, surface_samples, voxel_iou
from ngp_mi.models import pretrained
from ngp_mi.render.preview import mesh_preview
from ngp_mi.viz import contact_sheet, save_png


@torch.no_grad()
def evaluate_shape(run_or_model: str | Path, out: str | Path, source: str = "chair", num_shapes: int = 20,
                   seed: int = 500, resolution: int = 64, surface_points: int = 2048, preview_resolution: int = 96,
                   log=print) -> dict[str, Any]:
    """Reconstruct ``num_shapes`` shapes of ``source`` from ``seed`` on; writes and returns the figures."""
    model = pretrained.load_shape_prior(run_or_model).require_encoder()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # Occupancy points are what training reads; here only the voxels and the surface are used.
    config = ShapeDataConfig(source=source, num_shapes=num_shapes, seed=seed,
                             voxel_resolution=model.config.voxel_resolution, resolutions=(16,), points=(64,),
                             surface_points=surface_points)
    summary = build_shape_dataset(config, out / "data", progress=False)
    if not ShapeDataset.index(out / "data"):
        raise ValueError(f"evaluate shape: no shape of {source!r} could be built ({summary['skipped']})")
    data = ShapeDataset(out / "data")
    refs = {ref.id: ref for ref in shape_refs(config)}
    camera = Camera.orbit(20.0, 45.0, preview_resolution)
    rng = np.random.default_rng(seed)
    rows, tiles, labels = [], [], []
    for i in tqdm(range(len(data)), unit="shape", desc="evaluate shape", dynamic_ncols=True):
        shape_id, voxels = data.ids[i], data.voxels(i)
        code = model.encode(data.voxel_tensor(i)[None].to(model.device))[0]
        extraction = model.extract(code, resolution)  # what ShapeModel.reconstruct gives
        row: dict[str, Any] = {"shape": shape_id, "iou": voxel_iou(model.occupancy_grid(code, voxels.shape[0]), voxels)}
        truth = load_solid(refs[shape_id]).mesh
        tiles.append(mesh_preview(truth, camera))
        if extraction.mesh is None:  # an empty reconstruction scores IoU 0 and no distance
            row["chamfer_l2"] = math.inf
            tiles.append(np.full_like(tiles[-1], 32))
        else:
            ours = torch.as_tensor(surface_samples(extraction.mesh, surface_points, rng), dtype=torch.float64)
            row["chamfer_l2"] = float(chamfer_distance(ours, torch.as_tensor(data.surface(i), dtype=torch.float64)))
            tiles.append(mesh_preview(extraction.mesh, camera))
        labels += [shape_id, f"IoU {row['iou']:.2f}"]
        rows.append(row)
    chamfers = [r["chamfer_l2"] for r in rows]
    result = {
        "model": str(run_or_model), "source": source, "seed": seed, "shapes": len(rows),
        "skipped": summary["skipped"], "voxel_resolution": model.config.voxel_resolution,
        "extraction_resolution": resolution,
        "iou": {"mean": float(np.mean([r["iou"] for r in rows])), "median": float(np.median([r["iou"] for r in rows]))},
        "chamfer_l2": {"mean": float(np.mean(chamfers)), "median": float(np.median(chamfers)),
                       "empty": int(sum(math.isinf(c) for c in chamfers))},
        "per_shape": rows,
    }
    write_json(out / "eval.json", result)
    save_png(out / "sheet.png", contact_sheet(tiles, labels, columns=8))
    write_text(out / "eval.md", report(result))
    log(f"evaluate shape: IoU {result['iou']['mean']:.3f}, Chamfer-L2 {result['chamfer_l2']['mean']:.5f} "
        f"over {len(rows)} shapes; wrote {out / 'eval.md'}")
    return result


def report(result: dict[str, Any]) -> str:
    lines = [f"# Shape prior `{result['model']}` on {result['shapes']} shapes of {result['source']} from seed "
             f"{result['seed']}", "",
             f"Autoencoder IoU ({result['voxel_resolution']}³ voxels): mean {result['iou']['mean']:.3f}, median "
             f"{result['iou']['median']:.3f}. Chamfer-L2 of the reconstruction (marching cubes at "
             f"{result['extraction_resolution']}³): mean {result['chamfer_l2']['mean']:.5f}, median "
             f"{result['chamfer_l2']['median']:.5f}; empty reconstructions: {result['chamfer_l2']['empty']}.", "",
             "![each shape beside its reconstruction](sheet.png)", "",
             "| shape | IoU | Chamfer-L2 |", "|---|---|---|"]
    lines += [f"| {r['shape']} | {r['iou']:.3f} | {r['chamfer_l2']:.5f} |" for r in result["per_shape"]]
    if result["skipped"]:
        lines += ["", "Skipped: " + "; ".join(f"{k}: {v}" for k, v in result["skipped"].items())]
    return "\n".join(lines) + "\n"
