"""Benchmark: training speed of the map networks on the CPU (seconds per iteration, peak memory).

The ``cpu`` preset's networks (train/maps_cpu.toml: ngf 24, 4 ResNet blocks, PatchGANs 34 + 70,
albedo 16) at 64² and 128², batch 8; one iteration = both cycles, the generator step and the discriminator step
(and, with ``[model] normal_steps``, G_n's own steps).

``--versus KEY=VALUE,…`` times the preset against the preset with those recipe overrides at 64²,
iteration by iteration in one process (the machines are noisy), and prints both medians and their ratio;
``--base KEY=VALUE,…`` applies its overrides to both sides first.

    .venv/bin/python bench/bench_train_maps.py [--iterations 8]
    .venv/bin/python bench/bench_train_maps.py --versus 'model.normal_cycle_depth="real",model.normal_steps=6'
    .venv/bin/python bench/bench_train_maps.py --base 'model.lambda_gan_n=1e-30' --versus 'model.lambda_gan_n=0'
"""

from __future__ import annotations

import argparse
import platform
import resource
import statistics
import tempfile
import time
from pathlib import Path

import torch

from ngp_mi import backend
from ngp_mi.data.datasets import DepthDataset, ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models.maps import MapsModel
from ngp_mi.training.loop import SeededBatches
from ngp_mi.training.maps import MapsRecipe, normal_step_batches, normal_step_source

ROOT = Path(__file__).resolve().parent.parent


def steps(model: MapsModel, depth: SeededBatches, maps: SeededBatches, extra: SeededBatches, step: int) -> float:
    """Seconds of one training iteration as ``train maps`` runs it (G_n's own steps included)."""
    start = time.perf_counter()
    model.optimize(depth(step), maps(step), normal_step_batches(extra, model.config, step))
    return time.perf_counter() - start


def versus(base: MapsRecipe, other: MapsRecipe, args: argparse.Namespace, b) -> None:
    """The two recipes' iterations at 64², interleaved; medians and ratio."""
    with tempfile.TemporaryDirectory() as tmp:
        render_dataset(DatasetConfig(source="chair", num_shapes=8, views=4, resolution=64), Path(tmp), progress=False)
        maps = SeededBatches(ReflectanceMapDataset(tmp), args.batch, 0)
        depth = SeededBatches(DepthDataset(tmp), args.batch, 1)
        extra = normal_step_source(ReflectanceMapDataset(tmp), args.batch, 0)
        models = []
        for recipe in (base, other):
            torch.manual_seed(0)
            models.append(MapsModel(recipe.model))
        times = [[], []]
        for step in range(args.iterations + 1):
            for model, spent in zip(models, times):
                spent.append(steps(model, depth, maps, extra, step))
    a, c = (statistics.median(t[1:]) for t in times)
    print(f"# bench_train_maps --versus — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), {b.variant}; preset cpu, 64², batch {args.batch}, "
          f"median of {args.iterations} interleaved iterations after one warm-up\n")
    print("| recipe | s / iteration (median) | ratio |\n|---|---|---|")
    base = f"cpu + {args.base}" if args.base else "cpu"
    print(f"| {base} | {a:.2f} | 1.00 |\n| {base} + {args.versus} | {c:.2f} | {c / a:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--versus", metavar="KEY=VALUE,…", help="recipe overrides to time against the preset at 64²")
    parser.add_argument("--base", default="", metavar="KEY=VALUE,…", help="overrides of both sides of --versus")
    args = parser.parse_args()
    b = backend.load()
    base = [o for o in args.base.split(",") if o]
    recipe = MapsRecipe.read(ROOT / "train" / "maps_cpu.toml", base)
    if args.versus:
        versus(recipe, MapsRecipe.read(ROOT / "train" / "maps_cpu.toml", base + [o for o in args.versus.split(",") if o]),
               args, b)
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for res in (64, 128):
            data = Path(tmp) / f"d{res}"
            render_dataset(DatasetConfig(source="chair", num_shapes=8, views=4, resolution=res), data, progress=False)
            torch.manual_seed(0)
            model = MapsModel(recipe.model)
            maps = SeededBatches(ReflectanceMapDataset(data), args.batch, 0)
            depth = SeededBatches(DepthDataset(data), args.batch, 1)
            times = []
            for step in range(args.iterations + 1):
                start = time.perf_counter()
                model.optimize(depth(step), maps(step))
                times.append(time.perf_counter() - start)
            rows.append((res, statistics.median(times[1:]), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
    print(f"# bench_train_maps — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), {b.variant}; preset cpu, batch {args.batch}\n")
    print("| res | s / iteration (median) | iterations / s | peak RSS MiB (process, so far) |\n|---|---|---|---|")
    for res, seconds, rss in rows:
        print(f"| {res}² | {seconds:.2f} | {1 / seconds:.2f} | {rss:.0f} |")


if __name__ == "__main__":
    main()
