# make bench: skip (an analysis of a trained model on held-out shapes, minutes per view set)
"""Experiment: what holds NGP's image above the true maps' floor (issue 15), one table.

For ``--shapes`` × ``--views`` held-out views of a model's family (seed ``--seed``, under the overhead
rig, against a ``--spp`` path-traced reference), NGP w/o G_sp^real with each generated map swapped for
the truth (R_diff at the model's k_diff, sRGB PSNR / FLIP on the object):

* the true normals and albedo (the floor); G_n's normals with the true albedo; the true normals with
  G_da's albedo (z_da = μ(E_da(exemplar)), the exemplar the view's true albedo); both generated;
* G_da's colours averaged over each true part (the distinct colours of the true albedo): the true
  regions with G_da's colours, which splits the albedo's error into colours and regions;
* z_da fitted to the exemplar (:func:`ngp_mi.pipeline.fit_appearance`) for each of ``--fit-steps``;
* with ``--coverage``: both images composited over the reference's pixel coverage (the nearest
  object colour times the pixel's alpha), i.e. what edge anti-aliasing would buy.

    .venv/bin/python bench/bench_image_floor.py --model chair --shapes 10 --views 4 --seed 500 --spp 256 \\
        [--fit-steps 10,30] [--coverage]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from scipy import ndimage

from ngp_mi.data.sources import resolve_source
from ngp_mi.data.views import derived_seed, view_cameras
from ngp_mi.eval.metrics import flip, psnr
from ngp_mi.lights import overhead_rig
from ngp_mi.models.pretrained import load_ngp_networks, trained_source
from ngp_mi.pipeline import fit_appearance, ngp_image
from ngp_mi.render.gbuffer import GBufferRenderer, maps_to_tensors
from ngp_mi.render.scene import build_scene, lights_to_mitsuba, render
from ngp_mi.render.shading import shade
from ngp_mi.viz import linear_to_srgb


def part_means(albedo: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``albedo`` (H, W, 3) with each true part (a distinct colour of ``truth`` on ``mask``) set to its mean there."""
    out = np.zeros_like(albedo)
    _, labels = np.unique(np.round(truth[mask], 3), axis=0, return_inverse=True)
    pixels = np.argwhere(mask)
    for part in np.unique(labels):
        rows, cols = pixels[labels.ravel() == part].T
        out[rows, cols] = albedo[rows, cols].mean(0)
    return out


def coverage_composite(image: np.ndarray, mask: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Edge anti-aliasing of a hard-masked image: the nearest object pixel's colour times the coverage."""
    nearest = ndimage.distance_transform_edt(~mask, return_distances=False, return_indices=True)
    return image[nearest[0], nearest[1]] * alpha[..., None]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="chair", help="a shipped name, model folder or `train maps` run")
    parser.add_argument("--shapes", type=int, default=10)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--seed", type=int, default=500)
    parser.add_argument("--spp", type=int, default=256, help="the reference's samples per pixel")
    parser.add_argument("--fit-steps", default="30", help="comma-separated fit_appearance step counts (empty: none)")
    parser.add_argument("--coverage", action="store_true", help="also score edge anti-aliasing by coverage")
    args = parser.parse_args()
    fit_steps = [int(n) for n in args.fit_steps.split(",") if n.strip()]
    model, specular = load_ngp_networks(args.model)
    family = trained_source(args.model)
    k_diff = model.config.constants.diffuse_k_d
    rows: dict[str, list[tuple[float, float, float, float]]] = {}
    rig = overhead_rig()
    for index, item in enumerate(resolve_source(family, args.shapes, args.seed)):
        content = item.load()
        for view, camera in enumerate(view_cameras(args.views, 64, args.seed, index)):
            scene = build_scene(camera, {**content.shapes, **lights_to_mitsuba(rig)}, (),
                                {"type": "path", "max_depth": 6}, spp=args.spp, pixel_format="rgba")
            full = render(scene, seed=derived_seed(args.seed, index, view))
            reference, alpha = full[..., :3], full[..., 3]
            t = maps_to_tensors(GBufferRenderer(content.shapes, content.bounds, camera,
                                                ("depth", "normal", "albedo", "mask")).render(camera))
            mask = t["mask"][0, 0].numpy() > 0.5
            truth = t["albedo"][0].permute(1, 2, 0).numpy()

            def shaded(normal: torch.Tensor, albedo: np.ndarray | torch.Tensor) -> np.ndarray:
                albedo = torch.from_numpy(albedo).permute(2, 0, 1)[None] if isinstance(albedo, np.ndarray) else albedo
                return shade(normal, albedo.float(), t["mask"], rig, camera, mode="diffuse", k_d=k_diff,
                             depth=t["depth"])[0].permute(1, 2, 0).numpy() / math.pi

            def generated(steps: int) -> tuple[dict, float]:
                began = time.perf_counter()
                z_da = fit_appearance(model, t["albedo"], t["depth"], t["mask"], camera, content.bounds, steps)
                with torch.no_grad():
                    out = ngp_image(model, specular, t["depth"], t["mask"], camera, content.bounds, z_da, rig, "no_sp")
                return out, time.perf_counter() - began

            out, _ = generated(0)
            albedo = out["albedo"][0].permute(1, 2, 0).numpy()
            images = {"the true normals and albedo (the floor)": (shaded(t["normal"], truth), truth),
                      "G_n's normals, the true albedo": (shaded(out["normal"], truth), truth),
                      "the true normals, G_da's albedo (μ(E_da))": (shaded(t["normal"], albedo), albedo),
                      "both generated (NGP w/o G_sp^real)": (out["image"][0].permute(1, 2, 0).numpy(), albedo)}
            regions = part_means(albedo, truth, mask)
            images["G_n's normals, G_da's colours averaged over each true part"] = (shaded(out["normal"], regions), regions)
            seconds = {}  # of the rows with a fitted z_da
            for steps in fit_steps:
                name = f"both generated, z_da fitted ({steps} steps)"
                fitted, seconds[name] = generated(steps)
                images[name] = (fitted["image"][0].permute(1, 2, 0).numpy(), fitted["albedo"][0].permute(1, 2, 0).numpy())
            if args.coverage:
                for name in ("the true normals and albedo (the floor)", "both generated (NGP w/o G_sp^real)"):
                    image, colours = images[name]
                    images[f"{name}, coverage anti-aliased"] = (coverage_composite(image, mask, alpha), colours)
            for name, (image, colours) in images.items():
                rows.setdefault(name, []).append((
                    psnr(linear_to_srgb(reference), linear_to_srgb(image), mask),
                    flip(linear_to_srgb(reference), linear_to_srgb(image), mask)[0],
                    float(np.abs(colours - truth)[mask].mean()), seconds.get(name, float("nan"))))
    print(f"# bench_image_floor — {time.strftime('%Y-%m-%d')}, model {args.model} ({family}), {args.shapes} × "
          f"{args.views} views from seed {args.seed}, rig, {args.spp}-spp reference; R_diff at k_d {k_diff:g}\n")
    print("| NGP w/o G_sp^real with | sRGB PSNR / FLIP on the object | albedo L1 | fit s per view |\n|---|---|---|---|")
    for name, values in rows.items():
        psnr_, flip_, l1, sec = np.mean(values, axis=0)
        print(f"| {name} | {psnr_:.2f} / {flip_:.3f} | {l1:.3f} | {'' if math.isnan(sec) else f'{sec:.2f}'} |")


if __name__ == "__main__":
    main()
