"""Benchmark: the cost of views in the foundation (Mitsuba scene, camera moves, path tracing).

Prints a Markdown table of medians measured in one run. Figures go to bench/RESULTS.md.
    .venv/bin/python bench/bench_render.py [--repeats 15]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

from ngp_mi import backend
from ngp_mi.camera import ViewDistribution
from ngp_mi.geometry.primitives import simple_chair
from ngp_mi.lights import overhead_rig
from ngp_mi.render.scene import build_scene, diffuse_bsdf, mesh_parts_to_mitsuba, render, set_sensor_camera


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        backend.jit_sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    b = backend.load()
    mesh = simple_chair()
    shapes = mesh_parts_to_mitsuba(mesh, default_bsdf=diffuse_bsdf(0.5))
    lights = overhead_rig()
    rows = []
    for res in (128, 256):
        cams = ViewDistribution().sample(args.repeats + 1, seed=1, resolution=res)
        aov = {"type": "aov", "aovs": "d:depth,n:sh_normal"}
        scene = build_scene(cams[0], shapes, lights, integrator=aov)
        sensor = scene.sensors()[0]
        render(scene)  # compile once
        it = iter(cams[1:])
        rows.append(("aov depth+normal, same view, 1 spp", res, median_ms(lambda: render(scene), args.repeats)))
        rows.append(("aov, camera moved via traverse", res,
                     median_ms(lambda: (set_sensor_camera(sensor, next(it)), render(scene)), args.repeats)))
        it2 = iter(cams[1:])
        rows.append(("aov, new scene per view (load_dict)", res,
                     median_ms(lambda: render(build_scene(next(it2), shapes, lights, integrator=aov)), args.repeats)))
        pt = build_scene(cams[0], shapes, lights, integrator={"type": "path", "max_depth": 3}, spp=64)
        render(pt)
        rows.append(("path tracing max_depth 3, 64 spp", res, median_ms(lambda: render(pt), args.repeats)))

    print(f"# bench_render — {time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, "
          f"{b.variant}, {b.threads} threads, mitsuba {b.mi.__version__}, drjit {b.dr.__version__}\n")
    print("| what | res | median ms |\n|---|---|---|")
    for what, res, ms in rows:
        print(f"| {what} | {res}² | {ms:.2f} |")


if __name__ == "__main__":
    main()
