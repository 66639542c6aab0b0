"""Benchmark: R_BP / R_diff shading, Dr.Jit vs torch, against the memory-bandwidth floor.

8 x 256² maps, 4 directional lights (the overhead rig), per-pixel view vectors, float32.
Forward, and forward + backward with gradients for normals, albedo and the light parameters.
The floor is (bytes read + written) / copy bandwidth, the bandwidth measured in the same run
by a large torch copy. Prints a Markdown table of medians.
    .venv/bin/python bench/bench_shading.py [--repeats 21] [--device cuda]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.lights import overhead_rig
from ngp_mi.render.shading import CameraLights, shade

N, RES = 8, 256


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up (JIT compile / allocator)
    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def copy_bandwidth(repeats: int, device: str) -> float:
    """Bytes per second of a large out-of-cache copy (read + write counted)."""
    src = torch.rand(64 * 2 ** 20 // 4, device=device)
    dst = torch.empty_like(src)
    ms = median_ms(lambda: dst.copy_(src), repeats)
    return 2 * src.numel() * 4 / (ms * 1e-3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--device", default="cpu", help="torch device of the maps (cuda: Dr.Jit's CUDA backend)")
    args = parser.parse_args()
    torch.set_default_device(args.device)
    b = backend.load()
    torch.manual_seed(0)
    cameras = [Camera.orbit(10.0, -60.0 + 15 * i, RES) for i in range(N)]
    normal = torch.randn(N, 3, RES, RES)
    normal[:, 2] -= 1.0
    albedo = torch.rand(N, 3, RES, RES)
    mask = (torch.rand(N, 1, RES, RES) > 0.3).float()
    per_camera = CameraLights.from_lights(overhead_rig(), cameras, device=args.device)  # world lights seen by each camera
    bandwidth = copy_bandwidth(args.repeats, args.device)

    shared = CameraLights.from_lights(overhead_rig(), None, device=args.device)  # camera-space lights, one set for the batch
    rows = []
    for mode in ("blinn_phong", "diffuse"):
        for name, base in (("drjit", per_camera), ("torch", per_camera), ("drjit, shared lights", shared)):
            impl = name.split(",")[0]

            def forward():
                with torch.no_grad():
                    shade(normal, albedo, mask, base, cameras, mode=mode, backend=impl)

            def forward_backward():
                n, a = normal.clone().requires_grad_(), albedo.clone().requires_grad_()
                lights = CameraLights(base.directions.clone().requires_grad_(),
                                      base.irradiance.clone().requires_grad_(), base.positions, base.intensity)
                shade(n, a, mask, lights, cameras, mode=mode, backend=impl).sum().backward()

            rows.append((mode, name, median_ms(forward, args.repeats), median_ms(forward_backward, args.repeats)))

    pixels = N * RES * RES
    fwd_bytes = pixels * 4 * (3 + 3 + 1 + 3)  # read normal, albedo, mask; write RGB
    floor_ms = 1e3 * fwd_bytes / bandwidth
    print(f"# bench_shading — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {b.variant}, maps on {args.device}, {b.threads} threads, "
          f"torch {torch.__version__} ({torch.get_num_threads()} threads)\n")
    print(f"copy bandwidth {bandwidth / 1e9:.1f} GB/s; forward traffic {fwd_bytes / 2 ** 20:.1f} MiB "
          f"-> floor {floor_ms:.2f} ms\n")
    print("| mode | backend | forward ms | fwd+bwd ms | forward / floor |\n|---|---|---|---|---|")
    for mode, name, fwd, fb in rows:
        print(f"| {mode} | {name} | {fwd:.2f} | {fb:.2f} | {fwd / floor_ms:.1f}x |")
    for mode in ("blinn_phong", "diffuse"):
        d = next(r for r in rows if r[:2] == (mode, "drjit"))
        t = next(r for r in rows if r[:2] == (mode, "torch"))
        print(f"\n{mode}: Dr.Jit speed-up over torch: forward {t[2] / d[2]:.1f}x, forward+backward {t[3] / d[3]:.1f}x")


if __name__ == "__main__":
    main()
