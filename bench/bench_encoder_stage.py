# make bench: skip (times a trained model's encoder stage on a folder given as an argument)
"""Benchmark: one step of the ``[encoder]`` stage (E_da refitted to the fixed G_da), its views read
from the folder per batch against held in memory with G_da's condition (``[encoder] cache_mib``).

The two sides step the same model alternately, batch by batch, in one process (the machines are
noisy), from the same weights; reported are the median seconds per step, their ratio, the time to
build the in-memory views and what they take.

    .venv/bin/python bench/bench_encoder_stage.py --model chair --views outputs/data/maps_cpu-encoder [--steps 40]
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics
import time

import torch

from ngp_mi.data.datasets import ReflectanceMapDataset
from ngp_mi.models import pretrained
from ngp_mi.models.maps import MapsModel
from ngp_mi.training.loop import SeededBatches
from ngp_mi.training.maps import EncoderStage, EncoderViews


def timed_step(model: MapsModel, batches: SeededBatches, step: int, lr: float) -> float:
    start = time.perf_counter()
    model.optimize_encoder(batches(step), lr)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="chair", help="a shipped model or a model folder")
    parser.add_argument("--views", required=True, help="a render-dataset folder with depth, albedo and mask")
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    stage = EncoderStage(iterations=args.steps)
    maps = pretrained.load_model(args.model)[0].eval()
    views = ReflectanceMapDataset(args.views)
    start = time.perf_counter()
    cached = EncoderViews(views, maps, torch.device("cpu"))
    build = time.perf_counter() - start
    sides = {"per batch": (copy.deepcopy(maps), SeededBatches(views, stage.batch_size, 0)),
             "in memory": (copy.deepcopy(maps), SeededBatches(cached, stage.batch_size, 0))}
    times: dict[str, list[float]] = {name: [] for name in sides}
    for step in range(args.steps):
        for name, (model, batches) in sides.items():
            times[name].append(timed_step(model, batches, step, stage.lr))
    median = {name: statistics.median(t[2:]) for name, t in times.items()}  # the first steps warm up
    print(f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, torch {torch.__version__}; "
          f"{len(views)} views at {views[0]['mask'].shape[-1]}², batch {stage.batch_size}, {args.steps} steps per side")
    print("| views | s per step (median) | 6,000 steps |")
    print("|---|---|---|")
    for name, seconds in median.items():
        print(f"| {name} | {seconds:.3f} | {seconds * 6000 / 60:.0f} min |")
    print(f"in memory / per batch: {median['in memory'] / median['per batch']:.2f}; building the views: "
          f"{build:.0f} s, {EncoderViews.mebibytes(views):.0f} MiB")


if __name__ == "__main__":
    main()
