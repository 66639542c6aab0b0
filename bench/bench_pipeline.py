"""Benchmark: NGP latency per handle (issue 16) — what a user waits for after each change of an NGPScene.

The shipped ``chair`` model (``--model``), or a ``--maps-run``, or random models of the shipped size
(the ``cpu`` recipes' architectures: maps ngf 24 / 4 blocks, G_sp^real ngf 24 / 4 blocks; the time
of a forward pass does not depend on the weights). Shapes are procedural chairs given as meshes, so
"new shape" times Π_v and everything after it; with a shape prior, "new z_s" adds G_shape's
extraction (marching cubes at 64³).

For each resolution, the median of ``--repeats`` calls of

* **new z_s** (a model with a shape prior): another latent, then ``render()``;
* **new shape**: another mesh, then ``render()`` (Π_v, G_n, G_da, G_sp^real, shading, blend);
* **new view**: another camera (the same stages; the mesh's Mitsuba scene is kept);
* **new appearance**: another z_da (G_da, G_sp^real, shading, blend);
* **light change**: another light (shading and blend only);

and the process's peak resident memory.

    .venv/bin/python bench/bench_pipeline.py [--res 128,256] [--repeats 15] [--maps-run RUN]
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import statistics
import time
import tomllib
from pathlib import Path

import torch

from ngp_mi import backend
from ngp_mi.geometry.families import generate
from ngp_mi.lights import DirectionalLight
from ngp_mi.models.base import config_from_dict
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.pretrained import available
from ngp_mi.models.specular import SpecularConfig, SpecularModel
from ngp_mi.camera import Camera
from ngp_mi.commands.view import ViewerState, pose_of
from ngp_mi.pipeline import NGP, NGPScene

ROOT = Path(__file__).resolve().parents[1]


def shipped_size_models() -> NGP:
    """Random models of the ``cpu`` recipe's architecture."""
    recipe = tomllib.loads((ROOT / "train" / "maps_cpu.toml").read_text())
    torch.manual_seed(0)
    maps = MapsModel(config_from_dict(MapsConfig, recipe["model"]))
    fields = set(SpecularConfig.__dataclass_fields__)
    specular = SpecularModel(config_from_dict(SpecularConfig, {k: v for k, v in recipe["specular"].items() if k in fields}))
    return NGP.of(maps, specular)


def median_ms(step, repeats: int) -> float:
    times = []
    for k in range(repeats + 1):
        start = time.perf_counter()
        step(k)
        if k:  # the first call compiles kernels
            times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--res", default="128,256")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--model", default="chair" if "chair" in available() else None,
                        help="a shipped model or model folder (default: chair when shipped)")
    parser.add_argument("--maps-run", help="a `train maps` run instead (neither: random weights of the cpu "
                                           "recipe's size)")
    parser.add_argument("--variant", default="ngp")
    args = parser.parse_args()
    ngp = (NGP(args.maps_run) if args.maps_run else NGP.pretrained(args.model) if args.model else
           shipped_size_models())
    weights = (f"weights of {args.maps_run}" if args.maps_run else f"model {args.model}" if args.model else
               "random weights, cpu-recipe size")
    meshes = [generate("chair", s).mesh() for s in range(args.repeats + 1)]
    rows = []
    for res in (int(r) for r in args.res.split(",")):
        scene = NGPScene(ngp, res, args.variant)
        new_latent = (median_ms(lambda k: scene.set_shape(seed=k).render(), args.repeats)
                      if ngp.shape_model is not None else float("nan"))
        scene.set_shape(mesh=meshes[0]).render()
        new_shape = median_ms(lambda k: scene.set_shape(mesh=meshes[k]).render(), args.repeats)
        new_view = median_ms(lambda k: scene.set_camera(theta=10, phi=-40.0 + 5 * k).render(), args.repeats)
        new_look = median_ms(lambda k: scene.set_appearance(seed=100 + k).render(), args.repeats)
        new_light = median_ms(lambda k: scene.set_lights([DirectionalLight((0.1 * k, 1.0, 1.0), (2.0, 2.0, 2.0))])
                              .render(), args.repeats)
        rows.append((res, new_latent, new_shape, new_view, new_look, new_light))
    viewer_rows = []
    for res in (int(r) for r in args.res.split(",")):  # `ngp-mi view`: the same plus the page's uint8 image
        state = ViewerState(ngp, res, mesh=meshes[0])
        camera = state.scene.camera
        light = median_ms(lambda k: state.set_lights([DirectionalLight((0.1 * k, 1.0, 1.0), (2.0, 2.0, 2.0))])
                          or state.render(camera), args.repeats)
        moved = median_ms(lambda k: state.render(state.camera_for(*pose_of(Camera.orbit(10, -40.0 + 5 * k, res)),
                                                                  2 * math.atan(res / 2 / camera.focal_px), 1.0)),
                          args.repeats)
        viewer_rows.append((res, light, moved))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"# bench_pipeline — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), {backend.load().variant}; variant {args.variant}; "
          f"{weights}; "
          f"median of {args.repeats} calls\n")
    print("| resolution | new z_s ms | new shape (mesh) ms | new view ms | new appearance ms | light change ms |\n"
          "|---|---|---|---|---|---|")
    for res, *ms in rows:
        print(f"| {res}² | " + " | ".join(f"{m:.1f}" for m in ms) + " |")
    print("\n`ngp-mi view` (ViewerState: the render and the page's uint8 image)\n")
    print("| resolution | light change ms | camera change ms |\n|---|---|---|")
    for res, light, moved in viewer_rows:
        print(f"| {res}² | {light:.1f} | {moved:.1f} |")
    print(f"\npeak RSS {peak:.0f} MiB")


if __name__ == "__main__":
    main()
