"""Benchmark: the shape prior's data from real-size meshes — seconds per shape, and agreement with the exact sum.

Builds a folder of ``--shapes`` meshes of at least ``--faces`` faces each (procedural chairs and
cars, subdivided, so their surface is the procedural one; every other one with 5 % of its faces
removed, open like most ShapeNet meshes), written as OBJ files, then times
:func:`ngp_mi.data.shapes.sample_shape` on each — loading the file, the occupancy grids at 16³, 32³,
64³ and the labelled IM-NET points — with the ``cpu`` and ``paper`` recipes' data settings. The
inside / outside labels of ``--check-points`` points near each surface are compared with the exact
winding-number sum (:func:`ngp_mi.geometry.occupancy.winding_numbers`, not timed).

To time another version of the package on the same meshes (the exact band-and-components code
before libigl), run this file with that checkout first on ``PYTHONPATH`` and ``--no-check``.

    .venv/bin/python bench/bench_occupancy.py [--shapes 8] [--faces 100000] [--folder outputs/bench/meshes_100k]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

import ngp_mi
from ngp_mi.data.shapes import ShapeDataConfig, sample_shape, shape_refs
from ngp_mi.geometry.families import generate
from ngp_mi.geometry.loaders import load_mesh

RECIPES = {  # the [data] tables of train/shape_cpu.toml and train/shape_paper.toml
    "cpu": dict(voxel_resolution=32, resolutions=(16, 32, 64), points=(4096, 8192, 16384)),
    "paper": dict(voxel_resolution=64, resolutions=(16, 32, 64), points=(4096, 8192, 32768)),
}


def mesh_folder(folder: Path, shapes: int, faces: int) -> Path:
    """``shapes`` OBJ files of at least ``faces`` faces (made once; the same files on every run)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(shapes):
        path = folder / f"{i:03d}.obj"
        if path.exists():
            continue
        mesh = generate("chair" if i % 2 == 0 else "car", i).mesh()
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        while len(tm.faces) < faces:
            tm = tm.subdivide()
        if i % 4 >= 2:  # open: 5 % of the faces removed
            keep = np.random.default_rng(i).random(len(tm.faces)) >= 0.05
            tm = trimesh.Trimesh(tm.vertices, tm.faces[keep], process=False)
        tm.export(path)
    return folder


def label_agreement(path: Path, count: int) -> float:
    """Share of ``count`` points near the surface whose fast label equals the exact sum's."""
    from ngp_mi.geometry.occupancy import fast_winding_numbers, surface_samples, winding_numbers

    mesh = load_mesh(path)
    rng = np.random.default_rng(1)
    points = surface_samples(mesh, count, rng) + rng.normal(0, 0.01, (count, 3))
    exact = winding_numbers(mesh.vertices, mesh.faces, points) > 0.5
    return float(np.mean((fast_winding_numbers(mesh.vertices, mesh.faces, points) > 0.5) == exact))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=8)
    parser.add_argument("--faces", type=int, default=100_000)
    parser.add_argument("--folder", default="outputs/bench/meshes_100k")
    parser.add_argument("--recipes", default="cpu,paper")
    parser.add_argument("--check-points", type=int, default=500, help="points per shape checked against the exact sum")
    parser.add_argument("--no-check", action="store_true", help="time only (for a checkout without the fast path)")
    args = parser.parse_args()
    folder = mesh_folder(Path(args.folder), args.shapes, args.faces)
    face_counts = [len(load_mesh(p).faces) for p in sorted(folder.glob("*.obj"))[:args.shapes]]
    print(f"# bench_occupancy — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {platform.processor() or ''} "
          f"torch {torch.__version__} ({torch.get_num_threads()} threads); ngp_mi from {Path(ngp_mi.__file__).parent}")
    print(f"# {len(face_counts)} meshes of {min(face_counts):,}–{max(face_counts):,} faces in {folder}\n")
    print("| recipe | shapes | median s / shape | min | max | shapes / s |\n|---|---|---|---|---|---|")
    for recipe in args.recipes.split(","):
        config = ShapeDataConfig(source=str(folder), num_shapes=args.shapes, **RECIPES[recipe])
        times = []
        for index, ref in enumerate(shape_refs(config)):
            start = time.perf_counter()
            sample_shape(config, ref, index)
            times.append(time.perf_counter() - start)
        print(f"| {recipe} | {len(times)} | {statistics.median(times):.2f} | {min(times):.2f} | {max(times):.2f} "
              f"| {len(times) / sum(times):.2f} |", flush=True)
    if not args.no_check:
        agreement = [label_agreement(p, args.check_points) for p in sorted(folder.glob("*.obj"))[:args.shapes]]
        print(f"\nlabels equal to the exact sum's on {args.check_points} points within ~0.01 of each surface: "
              f"min {min(agreement):.4f}, mean {np.mean(agreement):.4f}")


if __name__ == "__main__":
    main()
