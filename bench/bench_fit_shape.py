"""Benchmark: `fit-shape` — from a sphere (masks + depths, masks only, interior-only gradients) and,
with ``--model``, from the model's shape prior (issue 17).

Targets: ``--shapes`` procedural chairs, 8 fitted + 4 held-out views each at ``--res``² (depth, mask
and, with ``--model``, a 64-spp path-traced image under the rig, rendered by Mitsuba). Sphere start:
an icosphere of radius 0.4 (2,562 vertices), I + 20 L, Adam lr 3e-2, ``--steps`` steps. Prior
start: the best of 8 latents by mask loss, z_s fitted for 60 steps ((a)), then the vertices ((c)),
from masks only or from masks and images through the model's networks (z_da fitted too). The mask
term fits the binary masks unless a setting says it fits the images' alpha (each pixel's coverage,
``FitConfig.soft_masks``), so the figures recorded before alpha existed are what the settings give. Per
setting: Chamfer-L2 to the true chair (4,096 samples each way), mask IoU and image PSNR / FLIP on
the held-out views, seconds per step; the convergence curves side by side in ``--out``/curves.png;
with ``--model``, the split of one image-term step (Π_v, networks, shading, backward, optimiser).

``--user-meshes``: instead of procedural chairs, the two meshes of :func:`user_meshes` (a swivel
chair and a stool, shapes the chair family never makes), written as OBJ files and read back through
``render-dataset``'s mesh-folder source, as a user's own meshes would be.

    .venv/bin/python bench/bench_fit_shape.py [--shapes 3] [--seed 500] [--res 128] [--steps 150]
                                              [--model chair] [--only a,b] [--user-meshes]
                                              [--out outputs/bench/fit]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from ngp_mi.atomic import write_json
from ngp_mi.commands.fit_shape import FitConfig, fit_shape
from ngp_mi.data.manifest import load_manifest
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset

SETTINGS = {  # name → FitConfig fields (and whether the model's networks are in the loop)
    "masks + depths, silhouette gradients": ({}, False),
    "masks only, silhouette gradients": ({"depth_weight": 0.0}, False),
    "masks + depths, interior gradients only (fast Π_v)": ({"silhouette": False}, False),
    "masks + depths, boundary spp 1": ({"boundary_spp": 1}, False),
    "masks + depths, boundary spp 8": ({"boundary_spp": 8}, False),
}
PRIOR_SETTINGS = {
    "(a) prior: z_s only, masks + depths": ({"start": "zs", "steps": 0, "image_weight": 0.0}, False),
    "(c) prior then vertices, masks only": ({"start": "zs", "depth_weight": 0.0, "image_weight": 0.0}, False),
    "(c) prior then vertices, masks + images (networks in the loop)": ({"start": "zs", "depth_weight": 0.0}, True),
    "(c) after (b): z_s and the decoder, then vertices, masks only": (
        {"start": "zs", "fit_decoder": True, "depth_weight": 0.0, "image_weight": 0.0}, False),
    "(c) after (b) and (d): the field on a grid, free-space rays, then vertices, masks only": (
        {"start": "zs", "fit_decoder": True, "grid_steps": 60, "lr": 1e-2, "depth_weight": 0.0, "image_weight": 0.0},
        False),
    "(c) after (b) and (d), the 8 views and their mirror images (--mirror x), masks only": (
        {"start": "zs", "fit_decoder": True, "grid_steps": 60, "lr": 1e-2, "depth_weight": 0.0, "image_weight": 0.0,
         "mirror": "x"}, False),
    "(c) after (b) and (d), the 8 views' coverage (the images' alpha), masks only": (
        {"start": "zs", "fit_decoder": True, "grid_steps": 60, "lr": 1e-2, "depth_weight": 0.0, "image_weight": 0.0,
         "soft_masks": True}, False),
    "(c) after (b) and (d), the 8 views' coverage and their mirror images, masks only": (
        {"start": "zs", "fit_decoder": True, "grid_steps": 60, "lr": 1e-2, "depth_weight": 0.0, "image_weight": 0.0,
         "mirror": "x", "soft_masks": True}, False),
    "(c) after (b) and (d), the 8 views' coverage, pieces under 0.3 % of the surface dropped, masks only": (
        {"start": "zs", "fit_decoder": True, "grid_steps": 60, "lr": 1e-2, "depth_weight": 0.0, "image_weight": 0.0,
         "soft_masks": True, "min_component": 0.003}, False),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=500,
                        help="first chair; the shipped prior trained on chairs 0-271, so 500 on are unseen by it")
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--model", help="a shipped model or model folder: adds the fits from its shape prior")
    parser.add_argument("--only", default="", help="comma-separated indices of the settings to run (default: all)")
    parser.add_argument("--image-downsample", type=int, default=1,
                        help="the image term at 1/K of --res (the settings with the networks in the loop)")
    parser.add_argument("--user-meshes", action="store_true",
                        help="fit the two meshes of user_meshes() (a swivel chair, a stool) instead of chairs")
    parser.add_argument("--shard", default="1/1",
                        help="K/N: fit only the K-th of every N targets (run the N shards side by side with the same "
                             "--out, then once more without --shard for the whole table; finished fits are read back)")
    parser.add_argument("--out", default="outputs/bench/fit")
    args = parser.parse_args()
    shard, shards = (int(x) for x in args.shard.split("/"))
    out = Path(args.out)
    source, num_shapes = "chair", args.shapes
    if args.user_meshes:
        source, num_shapes = str(user_meshes(out / "user-meshes")), 2
    targets = out / f"{'targets-real' if args.model else 'targets'}-{'user' if args.user_meshes else args.seed}"
    render_dataset(DatasetConfig(source=source, num_shapes=num_shapes, views=12, resolution=args.res,
                                 channels=("depth", "mask"), seed=args.seed, real_spp=64 if args.model else 0), targets,
                   progress=False)
    shape_ids = list(dict.fromkeys(r["shape_id"] for r in load_manifest(targets)))
    ngp = None
    settings = dict(SETTINGS)
    if args.model:
        from ngp_mi.pipeline import NGP

        ngp = NGP.pretrained(args.model)
        settings.update(PRIOR_SETTINGS)
    chosen = {int(i) for i in args.only.split(",") if i.strip()} or set(range(len(settings)))
    rows, curves = [], {}
    for index, (name, (fields, networks)) in enumerate(settings.items()):
        if index not in chosen:
            continue
        results = []
        for k, shape_id in enumerate(shape_ids):
            folder = out / f"{index}-{k}"
            if (folder / "bench.json").exists():  # a finished fit of this setting and target (another shard's)
                results.append(json.loads((folder / "bench.json").read_text()))
                continue
            if k % shards != shard - 1:
                continue
            config = FitConfig(str(targets), shape_id=shape_id, held_out=4,  # binary masks, all pieces kept, unless said
                               **{"steps": args.steps, "checkpoint_every": max(1, args.steps), "soft_masks": False,
                                  "min_component": 0.0, **fields,
                                  **({"image_downsample": args.image_downsample} if networks else {})})
            start = time.perf_counter()
            summary = fit_shape(config, folder, ngp.shape_model if ngp else None, ngp if networks else None,
                                log=lambda *_: None)
            steps = config.steps + (config.zs_steps + config.grid_steps if config.start == "zs" else 0)
            summary["seconds_per_step"] = (time.perf_counter() - start) / steps
            if networks and "zs_seed" in summary:
                summary.update(prior_start_images(ngp, summary, targets))
            write_json(folder / "bench.json", summary)
            results.append(summary)
        first = out / f"{index}-0" / "state" / "state.json"  # the first target's curve, whichever shard fitted it
        history = json.loads(first.read_text())["history"] if first.exists() else []
        if history:
            curves[name] = history
        if results:
            rows.append((name, results))
    _plot(curves, out / "curves.png")
    print(f"# bench_fit_shape — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads); {', '.join(shape_ids) if args.user_meshes else f'{num_shapes} chairs from seed {args.seed}'}, "
          f"8 + 4 held-out views at {args.res}² (image term at {args.res // args.image_downsample}²), "
          f"{args.steps} vertex steps{f', model {args.model}' if args.model else ''}\n")
    print("| setting | Chamfer-L2 start | Chamfer-L2 end (per chair) | held-out mask IoU | held-out PSNR / FLIP "
          "start → end | s / step |\n|---|---|---|---|---|---|")
    for name, results in rows:
        mean = lambda key: statistics.mean(r[key] for r in results)  # noqa: E731
        image = (f"{mean('psnr_held_out_start'):.2f} / {mean('flip_held_out_start'):.3f} → "
                 f"{mean('psnr_held_out_end'):.2f} / {mean('flip_held_out_end'):.3f}"
                 if "psnr_held_out_end" in results[0] else "–")
        if "psnr_held_out_prior" in results[0]:  # from the prior's best latent, as the goal counts
            image = f"{mean('psnr_held_out_prior'):.2f} / {mean('flip_held_out_prior'):.3f} → (after (a)) " + image
        ends = ", ".join(f"{r['chamfer_end']:.4f}" for r in results)
        start_key = "chamfer_zs_start" if results[0].get("chamfer_zs_start") is not None else "chamfer_start"
        print(f"| {name} | {mean(start_key):.4f} | {ends} "
              f"(mean {mean('chamfer_end'):.4f}) | {mean('mask_iou_held_out'):.3f} | {image} | "
              f"{statistics.median(r['seconds_per_step'] for r in results):.3f} |")
    print(f"\ncurves: {out / 'curves.png'}")
    if ngp is not None and shards == 1:
        print("\n" + step_split(ngp, targets, shape_ids[0], args.image_downsample))


def prior_start_images(ngp, summary: dict, targets: Path) -> dict[str, float]:
    """The image scores of the fit's first shape — the prior's best latent before z_s moved, z_da = 0,
    the start the goal table measures from — on the same views and at the same resolution as the
    fit's own ``psnr_*`` / ``flip_*`` (whose "start" is the vertex phase's, after z_s was fitted)."""
    from ngp_mi.commands.fit_shape import ImageTerm, fit_images, image_scores, load_targets, pool_views
    from ngp_mi.pipeline import latent
    from ngp_mi.render.depth import project_depth

    config = summary["config"]
    data = load_targets(targets, summary["shape_id"])
    shape = ngp.shape_model.shape(latent(summary["zs_seed"], ngp.shape_model.config.z_dim),
                                  resolution=config["extract_resolution"]).mesh
    with torch.no_grad():
        maps = project_depth(torch.as_tensor(shape.vertices, dtype=torch.float32), shape.faces, data.cameras)
        term = ImageTerm(ngp, summary["variant"], torch.zeros(1, ngp.maps.config.latent_dim))
        k = config["image_downsample"]
        image = fit_images(term, maps.depth, maps.mask, data.cameras, shape.bounds, data.lights, k)
    return image_scores({"prior": image}, pool_views(data.images, k), summary["fitted_views"])


def user_meshes(folder: Path) -> Path:
    """Two meshes a user might bring, as OBJ files in ``folder``: a swivel chair (five-star base, a
    pole, a round seat, a tilted back) and a three-legged stool with stretchers — shapes outside the
    procedural chair family (four legs, a flat back). Each is the outer surface of a union of solids
    (marching cubes of its signed distance at 128³), so it is one closed surface, as a scanned or
    modelled mesh would be."""
    import math

    import numpy as np
    import trimesh

    from ngp_mi.geometry.extract import extract_mesh
    from ngp_mi.geometry.sdf import Box, Cylinder, SolidShape, rotation

    up = np.array([0.0, 1.0, 0.0])
    swivel = [(Box(np.array([0.0, 0.05, 0.0]), np.array([0.30, 0.025, 0.035]), rotation(up, 72 * k)), 0)
              for k in range(5)]
    swivel += [(Cylinder(np.array([0.0, 0.28, 0.0]), 0.035, 0.22), 0),
               (Cylinder(np.array([0.0, 0.53, 0.0]), 0.27, 0.035), 1),
               (Box(np.array([0.0, 0.85, -0.24]), np.array([0.24, 0.26, 0.03]), rotation([1, 0, 0], -12)), 2),
               (Box(np.array([0.0, 0.62, -0.22]), np.array([0.04, 0.08, 0.02]), rotation([1, 0, 0], -12)), 2)]
    stool = [(Cylinder(np.array([0.0, 0.70, 0.0]), 0.25, 0.04), 1)]
    for k in range(3):
        angle = 2 * math.pi * k / 3
        outward = np.array([math.cos(angle), 0.0, math.sin(angle)])
        tilt = rotation(np.cross(up, outward), -10)  # legs splayed outwards by 10°
        stool.append((Cylinder(0.19 * outward + [0, 0.34, 0], 0.028, 0.34, tilt), 0))
        side = np.array([math.cos(angle + math.pi / 3), 0.0, math.sin(angle + math.pi / 3)])
        stool.append((Box(0.105 * side + [0, 0.25, 0], np.array([0.02, 0.02, 0.18]),  # a stretcher between legs
                          rotation(up, -math.degrees(angle + math.pi / 3))), 0))
    folder.mkdir(parents=True, exist_ok=True)
    for name, parts in (("swivel_chair", swivel), ("stool", stool)):
        path = folder / f"{name}.obj"
        if path.exists():
            continue
        solid = SolidShape(tuple(parts), name=name).normalized()
        mesh = extract_mesh(lambda p: torch.from_numpy(solid.sdf(p.numpy())), resolution=128).mesh
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    return folder


def step_split(ngp, targets: Path, shape_id: str, downsample: int = 1, repeats: int = 5) -> str:
    """Median seconds per step of the parts of one image-term step of the vertex phase (8 views, each
    network part summed over them; the networks at 1/``downsample`` of the resolution), as a table."""
    import numpy as np

    from ngp_mi.commands.fit_shape import ImageTerm, fit_losses, load_targets, pool_views, source_mesh
    from ngp_mi.render.depth import depth_of_hits, project_depth

    data = load_targets(targets, shape_id)
    cams, fitted = data.cameras[:8], slice(0, 8)
    small = [c.with_resolution(c.width // downsample, c.height // downsample) for c in cams]
    mesh = source_mesh(data.record)
    term = ImageTerm(ngp, "ngp" if ngp.specular is not None else "no_sp",
                     torch.zeros(1, ngp.maps.config.latent_dim, requires_grad=True))
    for module in (ngp.maps, ngp.specular):
        if module is not None:
            module.requires_grad_(False)
    vertices = torch.as_tensor(mesh.vertices, dtype=torch.float32).requires_grad_(True)
    optimizer = torch.optim.Adam([vertices, term.z_da], lr=1e-3)
    parts: dict[str, list[float]] = {}  # part → seconds per step (summed over the step's views)

    def timed(name, fn):
        began = time.perf_counter()
        value = fn()
        times = parts.setdefault(name, [0.0] * (repeats + 1))
        times[step] += time.perf_counter() - began
        return value

    from ngp_mi.pipeline import generate_albedo, generate_normals, realistic_specular, shade_maps

    bounds = np.stack([mesh.vertices.min(0), mesh.vertices.max(0)])
    for step in range(repeats + 1):
        maps = timed("Π_v forward (silhouette, spp 8 / 2)", lambda: project_depth(vertices, mesh.faces, cams,
                                                                                 silhouette_grad=True))
        coverage = pool_views(maps.mask, downsample)
        hits = depth_of_hits(pool_views(maps.depth, downsample), coverage)
        images = []
        for i, camera in enumerate(small):
            d, c = hits[i:i + 1], coverage[i:i + 1]
            normal = timed("G_n forward", lambda: generate_normals(ngp.maps, d, c, camera))
            albedo = timed("G_da forward", lambda: generate_albedo(ngp.maps, d, c, camera, bounds, normal, term.z_da))
            image = timed("R_diff forward (Dr.Jit)", lambda: shade_maps(normal, albedo, c, d, camera, data.lights[i],
                                                                      "ngp", ngp.maps.config.constants))
            if term.variant == "ngp":
                image = image + timed("G_sp^real forward", lambda: realistic_specular(ngp.maps, ngp.specular, normal,
                                                                                    albedo, c, camera))
            images.append(image)
        terms = fit_losses(maps.mask, maps.depth, data.mask[fitted], data.depth[fitted], 1.0, 0.0,
                           torch.cat(images), pool_views(data.images[fitted], downsample), 1.0)
        optimizer.zero_grad()
        timed("backward (networks, shading, Π_v)", lambda: terms["total"].backward())
        timed("optimiser", optimizer.step)
    rows = [(name, statistics.median(times[1:])) for name, times in parts.items()]  # the first is a warm-up
    total = sum(seconds for _, seconds in rows)
    return ("| part of one step (8 views) | median s | share |\n|---|---|---|\n"
            + "\n".join(f"| {name} | {seconds:.3f} | {seconds / total:.0%} |" for name, seconds in rows)
            + f"\n| total | {total:.3f} | |")


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
