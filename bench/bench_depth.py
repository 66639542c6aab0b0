"""Benchmark: the depth projection Π_v — speed, and the speed/accuracy trade of silhouette gradients.

1. Forward and forward+backward medians at 128² and 256²: the fast path (pixel centres, interior
   gradients) and the silhouette mode at several (spp, boundary_spp).
2. A ladder of boundary_spp at 128² (interior spp 16): the gradient of a smooth-weighted loss on
   depth and coverage w.r.t. a sideways translation (the hard case: two large boundary terms of
   opposite sign) and a scale of the mesh, against finite differences of a noise-free supersampled
   reference averaged over grid phases. Reported: bias of the mean over seeds, spread (standard
   deviation) over seeds, and time — so a user can pick boundary_spp for their budget.

    .venv/bin/python bench/bench_depth.py [--seeds 8] [--repeats 9]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
import torch

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.geometry.primitives import simple_chair
from ngp_mi.render.depth import project_depth, supersampled_depth_coverage


def timed(fn, repeats: int) -> tuple[float, float]:
    """Median milliseconds of (forward, forward + backward); fn returns (loss, forward seconds)."""
    fwd, total = [], []
    for i in range(repeats + 2):
        start = time.perf_counter()
        loss, t_fwd = fn(i)
        loss.backward()
        if i >= 2:  # warm-up: kernel compilation
            fwd.append(t_fwd)
            total.append(time.perf_counter() - start)
    return 1e3 * statistics.median(fwd), 1e3 * statistics.median(total)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    b = backend.load()
    mesh = simple_chair()
    v0 = torch.tensor(mesh.vertices, dtype=torch.float64)

    print(f"# bench_depth — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {b.variant}, {b.threads} threads, "
          f"mesh simple_chair ({len(mesh.faces)} triangles), one view\n")
    print("| res | mode | spp | boundary spp | forward ms | fwd+bwd ms |\n|---|---|---|---|---|---|")
    for res in (128, 256):
        cam = Camera.orbit(10.0, 30.0, res)
        configs = [("fast", 1, 0), ("silhouette", 16, 16), ("silhouette", 16, 4), ("silhouette", 8, 2),
                   ("silhouette", 16, 1), ("silhouette", 4, 1)]  # (8, 2) is the default
        for mode, spp, bspp in configs:
            def run(i):
                v = v0.clone().float().requires_grad_()
                start = time.perf_counter()
                out = project_depth(v, mesh.faces, cam, silhouette_grad=mode != "fast", spp=spp,
                                    boundary_spp=bspp or None, seed=i)
                t_fwd = time.perf_counter() - start
                return out.depth.sum() + out.mask.sum() + out.normal.sum(), t_fwd

            fwd, total = timed(run, args.repeats)
            print(f"| {res}² | {mode} | {spp if mode != 'fast' else '1 (centre)'} | {bspp or '–'} | "
                  f"{fwd:.1f} | {total:.1f} |")

    res, factor, phases = 128, 16, 8
    cam = Camera.orbit(12.0, 40.0, res)
    y, x = torch.meshgrid(torch.linspace(0, 1, res), torch.linspace(0, 1, res), indexing="ij")
    w = (1.0 + 0.6 * torch.sin(5.0 * x + 1.0) * torch.cos(3.0 * y)).double()[None, None]

    def loss(depth, mask):
        return (depth.double() * w).sum() + 0.5 * (mask.double() * w.flip(-1)).sum()

    sideways = torch.tensor(cam.R[0], dtype=torch.float64)
    motions = {"translate sideways": lambda s: v0 + s * sideways, "scale": lambda s: v0 * (1 + s)}
    print(f"\n## Silhouette-gradient ladder: {res}², interior spp 16, {args.seeds} seeds; "
          f"reference: FD (h = 2e-3) of {factor}x{factor} supersampled maps over {phases} grid phases\n")
    print("| motion | boundary spp | reference ± se | mean AD ± se | bias | spread (sd/seed) | fwd+bwd ms |\n"
          "|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for name, move in motions.items():
        h = 2e-3
        fds = []
        for _ in range(phases):
            phase = tuple(rng.uniform(-0.5, 0.5, 2))
            fds.append((loss(*supersampled_depth_coverage(move(h), mesh.faces, cam, factor, phase))
                        - loss(*supersampled_depth_coverage(move(-h), mesh.faces, cam, factor, phase))).item() / (2 * h))
        reference, reference_se = float(np.mean(fds)), float(np.std(fds) / np.sqrt(len(fds)))
        for bspp in (1, 2, 4, 8, 16, 64):
            grads, times = [], []
            for seed in range(args.seeds + 1):
                s = torch.zeros((), dtype=torch.float64, requires_grad=True)
                start = time.perf_counter()
                out = project_depth(move(s), mesh.faces, cam, silhouette_grad=True, spp=16, boundary_spp=bspp,
                                    seed=seed)
                (g,) = torch.autograd.grad(loss(out.depth, out.mask), s)
                if seed:  # seed 0 warms up
                    times.append(time.perf_counter() - start)
                    grads.append(g.item())
            mean, sd = float(np.mean(grads)), float(np.std(grads))
            print(f"| {name} | {bspp} | {reference:.1f} ± {reference_se:.1f} | {mean:.1f} ± {sd / np.sqrt(len(grads)):.1f} | "
                  f"{100 * (mean / reference - 1):+.2f} % | "
                  f"{100 * sd / abs(reference):.1f} % | {1e3 * statistics.median(times):.1f} |")


if __name__ == "__main__":
    main()
