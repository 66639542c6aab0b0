"""Benchmark: `fit-shape` from a sphere — masks + depths vs masks only vs interior-only gradients (issue 17).

Targets: ``--shapes`` procedural chairs, 8 fitted + 4 held-out views each at ``--res``² (depth and
mask, rendered by Mitsuba). Start: an icosphere of radius 0.4 (2,562 vertices), I + 20 L, Adam
lr 3e-2, ``--steps`` steps. Per setting: Chamfer-L2 to the true chair (4,096 samples each way),
mask IoU on the held-out views, seconds per step; the convergence curves side by side in
``--out``/curves.png.

    .venv/bin/python bench/bench_fit_shape.py [--shapes 3] [--res 128] [--steps 150] [--out outputs/bench/fit]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from ngp_mi.commands.fit_shape import FitConfig, fit_shape
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset

SETTINGS = {  # name → FitConfig fields
    "masks + depths, silhouette gradients": {},
    "masks only, silhouette gradients": {"depth_weight": 0.0},
    "masks + depths, interior gradients only (fast Π_v)": {"silhouette": False},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--out", default="outputs/bench/fit")
    args = parser.parse_args()
    out = Path(args.out)
    targets = out / "targets"
    render_dataset(DatasetConfig(source="chair", num_shapes=args.shapes, views=12, resolution=args.res,
                                 channels=("depth", "mask"), seed=11), targets, progress=False)
    rows, curves = [], {}
    for name, fields in SETTINGS.items():
        results = []
        for k in range(args.shapes):
            config = FitConfig(str(targets), shape_id=f"chair/{11 + k:06d}", held_out=4, steps=args.steps,
                               checkpoint_every=args.steps, **fields)
            folder = out / f"{list(SETTINGS).index(name)}-{k}"
            start = time.perf_counter()
            summary = fit_shape(config, folder, log=lambda *_: None)
            summary["seconds_per_step"] = (time.perf_counter() - start) / args.steps
            results.append(summary)
            if k == 0:
                curves[name] = json.loads((folder / "state" / "state.json").read_text())["history"]
        rows.append((name, [r["chamfer_start"] for r in results], [r["chamfer_end"] for r in results],
                     [r["mask_iou_held_out"] for r in results], [r["seconds_per_step"] for r in results]))
    _plot(curves, out / "curves.png")
    print(f"# bench_fit_shape — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads); {args.shapes} chairs, 8 + 4 held-out views at {args.res}², "
          f"{args.steps} steps\n")
    print("| setting | Chamfer-L2 start | Chamfer-L2 end (per chair) | held-out mask IoU | s / step |\n|---|---|---|---|---|")
    for name, start, end, iou, seconds in rows:
        print(f"| {name} | {statistics.mean(start):.4f} | {', '.join(f'{e:.4f}' for e in end)} "
              f"(mean {statistics.mean(end):.4f}) | {statistics.mean(iou):.3f} | {statistics.median(seconds):.3f} |")
    print(f"\ncurves: {out / 'curves.png'}")


def _plot(curves: dict[str, list[dict[str, float]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, history in curves.items():
        ax.semilogy([h["step"] for h in history], [h["mask"] for h in history], label=name)
    ax.set_xlabel("step")
    ax.set_ylabel("mask loss (chair 0)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
