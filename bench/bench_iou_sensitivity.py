# make bench: skip (an experiment over trained runs or data given as arguments)
"""Benchmark: how much held-out mask IoU a sub-pixel error costs (issue 17's IoU ≥ 0.97 goal).

For the held-out views of each procedural shape of a ``render-dataset`` folder (the last
``--held-out`` views, as ``fit-shape --held-out`` scores them), the IoU against the target mask of:

* the true mesh through Π_v — the ceiling (1 when the targets are Π_v's own masks);
* the target mask dilated / eroded by one pixel (3 × 3 cross) — a one-pixel error all round;
* the true mesh with every vertex moved along its (trimesh) vertex normal by ± a fraction of a pixel (the pixel's
  size at the object: camera distance / focal length) — a uniform sub-pixel surface error.

It says what accuracy the goal asks of the surface that no fitted view's outline constrains.

    .venv/bin/python bench/bench_iou_sensitivity.py --targets outputs/bench/fit-goal/targets-real-500
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy import ndimage

from ngp_mi.atomic import write_json
from ngp_mi.commands.fit_shape import load_targets, source_mesh
from ngp_mi.data.manifest import load_manifest
from ngp_mi.geometry.occupancy import voxel_iou
from ngp_mi.render.depth import project_depth

OFFSETS_PX = (-0.5, -0.25, -0.1, 0.1, 0.25, 0.5)


def held_out_ious(vertices: np.ndarray, faces: np.ndarray, cameras: list, masks: torch.Tensor) -> list[float]:
    maps = project_depth(torch.as_tensor(vertices, dtype=torch.float32), faces, cameras)
    return [voxel_iou(maps.mask[i, 0].numpy() > 0.5, masks[i, 0].numpy() > 0.5) for i in range(len(cameras))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", required=True, help="a render-dataset folder of procedural shapes")
    parser.add_argument("--held-out", type=int, default=4)
    parser.add_argument("--out", default="outputs/bench/iou-sensitivity")
    args = parser.parse_args()
    if not (Path(args.targets) / "manifest.jsonl").exists():
        raise SystemExit(f"{args.targets}: no render-dataset folder (bench/bench_fit_shape.py --model chair writes one)")
    shape_ids = sorted({r["shape_id"] for r in load_manifest(args.targets) if r.get("source") == "procedural"})
    if not shape_ids:
        raise SystemExit(f"{args.targets}: no procedural shapes (the true mesh is needed)")
    rows: dict[str, list[float]] = {}
    boundary = []
    for shape_id in shape_ids:
        targets = load_targets(args.targets, shape_id)
        cameras, masks = targets.cameras[-args.held_out:], targets.mask[-args.held_out:]
        truth = source_mesh(targets.record)
        vertices, faces = np.asarray(truth.vertices, np.float64), np.asarray(truth.faces)
        rows.setdefault("the true mesh through Π_v (ceiling)", []).extend(held_out_ious(vertices, faces, cameras, masks))
        for mask in masks[:, 0].numpy() > 0.5:
            eroded = ndimage.binary_erosion(mask)
            rows.setdefault("the target dilated by 1 px", []).append(voxel_iou(ndimage.binary_dilation(mask), mask))
            rows.setdefault("the target eroded by 1 px", []).append(voxel_iou(eroded, mask))
            boundary.append((mask & ~eroded).sum() / mask.sum())
        normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals  # unit, face-angle weighted
        for offset in OFFSETS_PX:
            ious = []
            for camera, mask in zip(cameras, masks):
                pixel = np.linalg.norm(camera.position) / camera.focal_px  # world units per pixel at the object
                ious += held_out_ious(vertices + offset * pixel * normals, faces, [camera], mask[None])
            rows.setdefault(f"the true mesh, surface moved {offset:+.2f} px along its normals", []).extend(ious)
        print(f"iou-sensitivity: {shape_id} done", flush=True)
    table = ["| held-out mask compared with the target | IoU mean | min |", "|---|---|---|"]
    table += [f"| {name} | {np.mean(v):.3f} | {np.min(v):.3f} |" for name, v in rows.items()]
    text = (f"{len(shape_ids)} shapes × {args.held_out} held-out views of {args.targets}; outline pixels (inside, "
            f"next to the background): {100 * np.mean(boundary):.0f} % of the object's\n\n" + "\n".join(table))
    print(text)
    write_json(Path(args.out) / "sensitivity.json", {
        "targets": args.targets, "held_out": args.held_out, "machine": platform.platform(),
        "outline_fraction": float(np.mean(boundary)), "rows": {k: [float(x) for x in v] for k, v in rows.items()}})
    (Path(args.out) / "sensitivity.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
