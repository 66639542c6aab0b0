"""Benchmark: R_BP / R_diff shading, Dr.Jit vs torch, against the memory-bandwidth floor.

8 x 256² maps, 4 directional lights (the overhead rig seen from each camera, so every image has
its own light directions), per-pixel view vectors, float32. Forward, and forward + backward with
gradients for normals, albedo and the light parameters. The floor is (bytes read + written) /
copy bandwidth, the bandwidth measured by a large torch copy in the same run.

Method: every call runs after ``--rest-ms`` of idle time, and the calls of all variants are
interleaved within each repetition. Dr.Jit's worker threads spin for a while after each kernel,
which steals a core from whatever runs next; back-to-back blocks of calls would charge that to
torch. Ratios are medians of per-repetition ratios. Prints Markdown tables.

    .venv/bin/python bench/bench_shading.py [--repeats 21] [--rest-ms 30] [--busy] [--res 256] [--device cuda]
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

N = 8


def sync() -> None:
    backend.jit_sync()
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def busy_work(seconds: float) -> None:
    """Stand-in for a training step's other work: small matrix products on torch's threads."""
    a = torch.rand(256, 256)
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        a = torch.tanh(a @ a)


def timed(fn, rest_s: float, busy: bool = False) -> float:
    sync()
    busy_work(rest_s) if busy else time.sleep(rest_s)
    start = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--rest-ms", type=float, default=30.0)
    parser.add_argument("--busy", action="store_true",
                        help="spend the rest in torch matrix products (as between a training step's calls) "
                             "instead of idle")
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--device", default="cpu", help="torch device of the maps (cuda: Dr.Jit's CUDA backend)")
    args = parser.parse_args()
    b = backend.load()
    torch.manual_seed(0)
    res = args.res
    cameras = [Camera.orbit(10.0, -60.0 + 15 * i, res) for i in range(N)]
    # (not torch.set_default_device: its dispatch mode adds Python overhead to every torch call)
    normal = torch.randn(N, 3, res, res, device=args.device)
    normal[:, 2] -= 1.0
    albedo = torch.rand(N, 3, res, res, device=args.device)
    mask = (torch.rand(N, 1, res, res, device=args.device) > 0.3).float()
    lights = CameraLights.from_lights(overhead_rig(), cameras, device=args.device)  # world lights seen by each camera
    src = torch.rand(64 * 2 ** 20 // 4, device=args.device)
    dst = torch.empty_like(src)

    def calls(mode: str, impl: str):
        def forward():
            with torch.no_grad():
                shade(normal, albedo, mask, lights, cameras, mode=mode, backend=impl)

        def forward_backward():
            # fresh leaves sharing the data (a clone would time page faults of 12 MB of new memory)
            n, a = normal.detach().requires_grad_(), albedo.detach().requires_grad_()
            leaves = CameraLights(lights.directions.detach().requires_grad_(), lights.irradiance.detach().requires_grad_(),
                                  lights.positions, lights.intensity)
            shade(n, a, mask, leaves, cameras, mode=mode, backend=impl).sum().backward()

        return forward, forward_backward

    variants = {(mode, impl): calls(mode, impl) for mode in ("blinn_phong", "diffuse") for impl in ("drjit", "torch")}
    for forward, forward_backward in variants.values():  # warm-up: kernel compilation, allocator
        forward(), forward_backward()
    times: dict = {key: ([], []) for key in variants}
    copies = []
    rest = args.rest_ms / 1e3
    for _ in range(args.repeats):
        copies.append(timed(lambda: dst.copy_(src), rest, args.busy))
        for key, (forward, forward_backward) in variants.items():
            times[key][0].append(timed(forward, rest, args.busy))
            times[key][1].append(timed(forward_backward, rest, args.busy))

    bandwidth = 2 * src.numel() * 4 / statistics.median(copies)  # read + write
    pixels = N * res * res
    fwd_bytes = pixels * 4 * (3 + 3 + 1 + 3)  # read normal, albedo, mask; write RGB
    floor = fwd_bytes / bandwidth

    def ms(values):
        return 1e3 * statistics.median(values)

    def ratio(num, den):
        return statistics.median(a / b for a, b in zip(num, den))

    print(f"# bench_shading — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {b.variant}, maps on {args.device}, "
          f"{b.threads} threads, torch {torch.__version__} ({torch.get_num_threads()} threads); {N} x {res}², "
          f"4 lights per camera, {args.repeats} interleaved repetitions, {args.rest_ms:g} ms {'of torch work' if args.busy else 'idle'} before each call\n")
    print(f"copy bandwidth {bandwidth / 1e9:.1f} GB/s; forward traffic {fwd_bytes / 2 ** 20:.1f} MiB "
          f"-> floor {1e3 * floor:.2f} ms\n")
    print("| mode | backend | forward ms | fwd+bwd ms | forward / floor |\n|---|---|---|---|---|")
    for (mode, impl), (fwd, fb) in times.items():
        print(f"| {mode} | {impl} | {ms(fwd):.2f} | {ms(fb):.2f} | {statistics.median(fwd) / floor:.1f}x |")
    print("\n| mode | torch / Dr.Jit forward | torch / Dr.Jit fwd+bwd |\n|---|---|---|")
    for mode in ("blinn_phong", "diffuse"):
        d, t = times[(mode, "drjit")], times[(mode, "torch")]
        print(f"| {mode} | {ratio(t[0], d[0]):.1f}x | {ratio(t[1], d[1]):.1f}x |")


if __name__ == "__main__":
    main()
