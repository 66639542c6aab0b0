"""Benchmark: shape extraction (decoder field → marching cubes) at 64³ and 128³, dense vs coarse-to-fine.

Two decoders: the trained one of a ``train shape`` run (its real surface decides which cells the
coarse-to-fine pass refines), and an IM-NET-size decoder (gf 128, code 256, the paper's) whose
cost is measured on the *same* refinement pattern: its output is added with weight 0 to the
trained field, so the set of evaluated points is identical while every point pays the large
network. Median of ``--repeats`` extractions of ``--shapes`` sampled latents each.
    .venv/bin/python bench/bench_extract.py [--run outputs/train/shape_cpu] [--device cuda]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import torch
from ngp_mi.models.shape import ShapeModel

from ngp_mi.geometry.extract import extract_mesh
from ngp_mi.models.shape import LEVEL
from ngp_mi.nets.imnet import ImplicitDecoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--run", default="outputs/train/shape_cpu", help="a `train shape` run (default: %(default)s)")
    parser.add_argument("--shapes", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    run = Path(args.run)
    if not run.exists():
        run = Path("outputs/train/shape_tiny")
    model = ShapeModel.from_run(run, args.device)
    big = ImplicitDecoder(256, 128).to(args.device).eval()
    codes = [model.code_of(torch.randn(model.config.z_dim, generator=torch.Generator().manual_seed(s))
                           .to(args.device))[0].detach() for s in range(args.shapes)]
    big_code = torch.rand(1, 256, device=args.device)

    def field(code, paper_size: bool):
        own = model.field(code)
        if not paper_size:
            return own

        def combined(points: torch.Tensor) -> torch.Tensor:
            p = points.to(args.device)
            cost = torch.cat([big(p[None, i:i + 32768], big_code)[0, :, 0] for i in range(0, len(p), 32768)])
            return own(points) + 0.0 * cost.to(points.device)
        return combined

    def sync() -> None:
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    rows = []
    with torch.no_grad():
        for paper_size in (False, True):
            for resolution in (64, 128):
                for coarse in (resolution, 32):
                    times, evaluated, faces = [], [], []
                    for code in codes:
                        for _ in range(args.repeats):
                            sync()
                            start = time.perf_counter()
                            ext = extract_mesh(field(code, paper_size), resolution, LEVEL, coarse=coarse, inside_above=True)
                            sync()
                            times.append(time.perf_counter() - start)
                        evaluated.append(ext.evaluated)
                        faces.append(0 if ext.mesh is None else len(ext.mesh.faces))
                    rows.append((paper_size, resolution, coarse, statistics.median(times), statistics.median(evaluated),
                                 (resolution + 1) ** 3, statistics.median(faces)))
    gf = model.config.gf
    print(f"# bench_extract — {time.strftime('%Y-%m-%d')}, {platform.machine()}, device {args.device}, "
          f"torch {torch.__version__} ({torch.get_num_threads()} threads); run {run}; {args.shapes} latents × "
          f"{args.repeats} repeats\n")
    print("| decoder | grid | pass | median s | field evaluations | of dense | faces |\n|---|---|---|---|---|---|---|")
    for paper_size, resolution, coarse, seconds, evaluated, dense, faces in rows:
        name = "IM-NET size (gf 128)" if paper_size else f"trained (gf {gf})"
        kind = "dense" if coarse == resolution else f"coarse {coarse}³ → fine"
        print(f"| {name} | {resolution}³ | {kind} | {seconds:.3f} | {evaluated:.0f} | {evaluated / dense:.1%} | {faces:.0f} |")


if __name__ == "__main__":
    main()
