"""The ``ngp-mi`` command. Sub-commands only parse arguments and call library functions."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence


def _doctor(args: argparse.Namespace) -> int:
    from ngp_mi.doctor import run_doctor

    return run_doctor()


def _demo(args: argparse.Namespace) -> int:
    from ngp_mi.demo import run_demo

    run_demo(args.out, resolution=args.res, views=args.views, spp=args.spp, seed=args.seed)
    return 0


def _families(args: argparse.Namespace) -> int:
    from ngp_mi.demo import family_sheet

    path = family_sheet(args.family, args.out or f"outputs/families/{args.family}.png", count=args.count,
                        resolution=args.res, spp=args.spp, first_seed=args.seed)
    print(f"wrote {path}")
    return 0


def _render_dataset(args: argparse.Namespace) -> int:
    import logging

    from ngp_mi.data.render_dataset import DatasetConfig, default_workers, parse_shard, render_dataset

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    config = DatasetConfig(source=args.source, num_shapes=args.num_shapes, views=args.views, resolution=args.res,
                           channels=tuple(c.strip() for c in args.channels.split(",") if c.strip()),
                           real_spp=args.real_spp, lights=args.lights, seed=args.seed, compression=args.compression,
                           full_window=args.full_window, half=args.half, coarse_shapes=args.coarse_shapes,
                           coarse_resolution=args.coarse_resolution)
    summary = render_dataset(config, args.out, shard=parse_shard(args.shard), strict=args.strict,
                             progress=not args.quiet, workers=args.workers or default_workers())
    print(f"render-dataset: {summary['views_rendered']} views rendered ({summary['views_per_second']} views/s), "
          f"{summary['views_before']} already present, {len(summary['skipped_shapes'])} shapes skipped")
    for shape_id, reason in summary["skipped_shapes"].items():
        print(f"  skipped {shape_id}: {reason}")
    return 0


def _compare(args: argparse.Namespace) -> int:
    from ngp_mi.eval.compare import CompareConfig, run_compare

    config = CompareConfig(source=args.source, num_shapes=args.num_shapes, views=args.views, resolution=args.res,
                           light_setups=tuple(args.lights.split(",")),
                           spp_ladder=tuple(int(x) for x in args.spp_ladder.split(",")),
                           reference_spp=args.reference_spp, seed=args.seed, maps_checkpoint=args.maps_checkpoint,
                           inception_weights=args.inception_weights)
    run_compare(config, args.out)
    return 0


def _train(args: argparse.Namespace) -> int:
    if args.stage == "shape":
        from ngp_mi.train_shape import train_shape as run
    else:
        from ngp_mi.train_maps import train_maps as run
    out = run(args.config)
    print(f"train {args.stage}: outputs in {out}")
    return 0


def _sample_shapes(args: argparse.Namespace) -> int:
    from ngp_mi.sample_shapes import sample_shapes

    summary = sample_shapes(args.run, args.out, num=args.num, seed=args.seed, resolution=args.resolution,
                            coarse=args.coarse, fmt=args.format, interpolate=tuple(args.interpolate) if args.interpolate
                            else None, steps=args.steps, spp=args.spp)
    print(f"sample-shapes: {len(summary['shapes'])} shapes ({summary['empty']} empty) in {args.out}; "
          f"median extraction {summary['median_seconds']:.2f} s")
    return 0


def _generate(args: argparse.Namespace) -> int:
    from ngp_mi.lights import load_lights, overhead_rig
    from ngp_mi.pipeline import generate

    views = []
    for text in args.views.split(";"):
        try:
            theta, phi = (float(x) for x in text.split(","))
        except ValueError:
            raise ValueError(f"--views must look like 'THETA,PHI;THETA,PHI' in degrees, got {args.views!r}") from None
        views.append((theta, phi))
    lights = overhead_rig() if args.lights == "rig" else load_lights(args.lights)
    added = load_lights(args.add_lights) if args.add_lights else []
    summary = generate(args.maps_run, args.out, shape_run=args.shape_run, mesh_path=args.mesh, num=args.num,
                       seed=args.seed, views=views, resolution=args.res, lights=lights, added_lights=added,
                       variant=args.variant.replace("-", "_"), exemplar=args.exemplar)
    print(f"generate: {len(summary['images'])} images in {args.out} (sheet.png, report.md)")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from ngp_mi.eval.maps_eval import evaluate_maps

    result = evaluate_maps(args.run, args.data, args.out or f"{args.run}/eval", coarse_sigma=args.coarse_sigma,
                           coarse_data=args.coarse_data)
    print(json.dumps(result, indent=1))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ngp-mi", description="Neural Graphics Pipeline on Mitsuba 3 / Dr.Jit and PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")

    doctor = sub.add_parser("doctor", help="print versions, backend and a timed test render; exit 0 if rendering works",
                            description="Print versions, the Mitsuba variant, libLLVM and a timed test render.")
    doctor.set_defaults(func=_doctor)

    demo = sub.add_parser("demo", help="render the showcase contact sheets under outputs/demo",
                          description="Path trace a procedural chair from the paper's view distribution "
                                      "under the 4-light overhead rig, and 16 samples of each shape family.")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    demo.add_argument("--res", type=int, default=128, help="image size in pixels (default: %(default)s)")
    demo.add_argument("--views", type=int, default=12, help="number of sampled views (default: %(default)s)")
    demo.add_argument("--spp", type=int, default=64, help="samples per pixel (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=0, help="random seed for views and noise (default: %(default)s)")
    demo.set_defaults(func=_demo)

    families = sub.add_parser("families", help="contact sheet of samples of a procedural shape family",
                              description="Path trace consecutive seeds of a procedural family (chair, car) "
                                          "with their part materials into one contact sheet.")
    families.add_argument("family", choices=["chair", "car"], help="shape family")
    families.add_argument("--count", type=int, default=16, help="number of samples (default: %(default)s)")
    families.add_argument("--seed", type=int, default=0, help="first seed (default: %(default)s)")
    families.add_argument("--res", type=int, default=128, help="image size (default: %(default)s)")
    families.add_argument("--spp", type=int, default=32, help="samples per pixel (default: %(default)s)")
    families.add_argument("--out", help="PNG path (default: outputs/families/FAMILY.png)")
    families.set_defaults(func=_families)

    data = sub.add_parser("render-dataset", help="render reference maps (EXR) and path-traced images of many shapes",
                          description="Render G-buffer maps (depth, normal, albedo, NOC, mask) and optionally "
                                      "path-traced 'real' images for shapes x sampled views, with a manifest. "
                                      "Resumable; shardable with --shard K/N.")
    data.add_argument("--source", required=True, help="chair | car | a mesh folder / ShapeNet tree / mesh file | "
                                                      "a Mitsuba scene .xml (or a folder of them)")
    data.add_argument("--out", required=True, help="output folder")
    data.add_argument("--num-shapes", type=int, default=16, help="shapes to take from the source (default: %(default)s)")
    data.add_argument("--views", type=int, default=8, help="views per shape (default: %(default)s)")
    data.add_argument("--res", type=int, default=128, help="image size in pixels (default: %(default)s)")
    data.add_argument("--channels", default="depth,normal,albedo,noc,mask",
                      help="G-buffer channels to write (default: %(default)s)")
    data.add_argument("--real-spp", type=int, default=0, help="samples per pixel of the path-traced 'real' image; "
                                                              "0 = none (default: %(default)s)")
    data.add_argument("--lights", default="rig", choices=["rig", "random", "scene"],
                      help="lights of the real images: the 4-light rig, random, or the scene file's own")
    data.add_argument("--shard", default="0/1", help="K/N: render every N-th shape starting at K (default: 0/1)")
    data.add_argument("--seed", type=int, default=0, help="seed of shapes, views and noise (default: %(default)s)")
    data.add_argument("--compression", default="rle", choices=["rle", "zip", "zstd", "piz", "none"],
                      help="EXR compression, all lossless (default: %(default)s, the fastest to write; zip: ~2x "
                           "smaller); may differ between runs that fill one folder")
    data.add_argument("--full-window", action="store_true", help="store every pixel of the maps, not only the "
                      "object's bounding rectangle (the EXR data window; readers see zeros outside it either way)")
    data.add_argument("--half", action="store_true", help="store all channels but depth as 16-bit floats "
                                                          "(half the size)")
    data.add_argument("--workers", type=int, default=0, help="processes splitting this shard's shapes "
                      "(default: one per core, at most 8; 1 on a GPU)")
    data.add_argument("--coarse-shapes", metavar="RUN", help="a `train shape` run: render each shape as its "
                      "autoencoder reconstructs it (NGP's coarse shapes; ids and views pair with the detailed ones)")
    data.add_argument("--coarse-resolution", type=int, default=64, help="marching-cubes grid of --coarse-shapes "
                                                                        "(default: %(default)s)")
    data.add_argument("--strict", action="store_true", help="exit non-zero if any shape was skipped")
    data.add_argument("--quiet", action="store_true", help="no progress bar")
    data.set_defaults(func=_render_dataset)

    compare = sub.add_parser("compare", help="time and score deferred shading against path-traced references",
                             description="Render, time and score path tracing at a ladder of spp and R_diff / R_BP "
                                         "on ground-truth maps (and NGP on generated maps) against a high-spp "
                                         "path-traced reference; write "
                                         "images, a speed-accuracy plot, results.json and report.html.")
    compare.add_argument("--source", default="chair", help="chair | car | mesh folder / file | scene .xml")
    compare.add_argument("--out", required=True, help="output folder")
    compare.add_argument("--num-shapes", type=int, default=3, help="shapes (default: %(default)s)")
    compare.add_argument("--views", type=int, default=2, help="views per shape (default: %(default)s)")
    compare.add_argument("--res", type=int, default=128, help="image size (default: %(default)s)")
    compare.add_argument("--lights", default="rig,random", help="light setups, from rig,random,rig+random (the rig plus added lights: "
                                                      "NGP-plus) (default: %(default)s)")
    compare.add_argument("--spp-ladder", default="1,4,16,64,256", help="path-tracing spp to compare (default: %(default)s)")
    compare.add_argument("--reference-spp", type=int, default=1024, help="spp of the reference (default: %(default)s)")
    compare.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    compare.add_argument("--maps-checkpoint", help="a `train maps` run folder: adds NGP-BP, NGP, NGP-plus and "
                                                   "the ablations on generated maps")
    compare.add_argument("--inception-weights", help="local inception-2015-12-05.pt (TorchScript): adds FID / KID; "
                                                     "never downloaded")
    compare.set_defaults(func=_compare)

    train = sub.add_parser("train", help="train a stage of NGP from a config (train/*.toml); resumes automatically",
                           description="Train the shape prior (stage 'shape': IM-NET autoencoder + latent WGAN-GP) "
                                       "or the map networks (stage 'maps') from a TOML config; logs, metrics, image "
                                       "grids and checkpoints go to the config's [train].out. Maps: multi-process "
                                       "with torchrun.")
    train.add_argument("stage", choices=["shape", "maps"], help="what to train")
    train.add_argument("--config", required=True, help="TOML config, e.g. train/maps_tiny.toml")
    train.set_defaults(func=_train)

    sample = sub.add_parser("sample-shapes", help="meshes and a rendered contact sheet from a trained shape prior",
                            description="Sample z_s, extract meshes (coarse-to-fine marching cubes), write OBJ/PLY, "
                                        "sheet.png, samples.json and report.md; or interpolate between two seeds.")
    sample.add_argument("--run", required=True, help="a `train shape` output folder (with ckpt-*)")
    sample.add_argument("--out", required=True, help="output folder")
    sample.add_argument("--num", type=int, default=16, help="number of shapes (default: %(default)s)")
    sample.add_argument("--seed", type=int, default=0, help="latent seed of the first shape (default: %(default)s)")
    sample.add_argument("--resolution", type=int, default=128, help="marching-cubes grid (default: %(default)s)")
    sample.add_argument("--coarse", type=int, default=32, help="coarse grid of the coarse-to-fine pass (default: %(default)s)")
    sample.add_argument("--format", choices=["obj", "ply"], default="obj", help="mesh format (default: %(default)s)")
    sample.add_argument("--interpolate", type=int, nargs=2, metavar=("SEED_A", "SEED_B"),
                        help="interpolate (slerp) between the latents of two seeds instead")
    sample.add_argument("--steps", type=int, default=8, help="interpolation steps (default: %(default)s)")
    sample.add_argument("--spp", type=int, default=16, help="samples per pixel of the previews (default: %(default)s)")
    sample.set_defaults(func=_sample_shapes)

    gen = sub.add_parser("generate", help="NGP images: shapes from G_shape (or a mesh), maps, lights, G_sp^real",
                         description="Form NGP images (paper Sec. 3): sample shapes with G_shape (or take --mesh), "
                                     "project them with Mitsuba from the given views, generate normals and albedo, "
                                     "shade under the lights and blend the realistic specular map. Writes images/, "
                                     "sheet.png (every intermediate map), generate.json and report.md.")
    gen.add_argument("--maps-run", required=True, help="a `train maps` output folder (with the [specular] stage for "
                                                       "ngp / ngp-plus)")
    gen.add_argument("--shape-run", help="a `train shape` output folder (shapes from z_s)")
    gen.add_argument("--mesh", help="a user mesh instead of sampled shapes")
    gen.add_argument("--out", required=True, help="output folder")
    gen.add_argument("--num", type=int, default=4, help="shapes to sample (default: %(default)s)")
    gen.add_argument("--seed", type=int, default=0, help="seed of z_s and z_da of the first shape (default: %(default)s)")
    gen.add_argument("--views", default="10,-30;10,30", help="camera views 'THETA,PHI;…' in degrees (default: %(default)s)")
    gen.add_argument("--res", type=int, default=128, help="image size (default: %(default)s)")
    gen.add_argument("--lights", default="rig", help="'rig' (the 4 overhead lights) or a lights JSON file")
    gen.add_argument("--add-lights", help="a lights JSON file of lights added by R_BP (variant ngp-plus)")
    gen.add_argument("--variant", default="ngp", choices=["ngp", "ngp-bp", "ngp-plus", "no-sp", "no-gn", "no-gda"],
                     help="NGP variant or ablation (default: %(default)s)")
    gen.add_argument("--exemplar", help="an albedo image: its appearance code (E_da) instead of a sampled z_da")
    gen.set_defaults(func=_generate)

    evaluate = sub.add_parser("evaluate", help="evaluate trained map networks on held-out maps (normal error, albedo)",
                              description="Normal angular error of G_n from a coarse depth against normals from the "
                                          "same depth (NGP w/o G_n); E_da -> G_da albedo reconstruction and diversity.")
    evaluate.add_argument("stage", choices=["maps"], help="what to evaluate")
    evaluate.add_argument("--run", required=True, help="training output folder (with ckpt-*)")
    evaluate.add_argument("--data", required=True, help="held-out render-dataset folder")
    evaluate.add_argument("--out", help="output folder (default: RUN/eval)")
    evaluate.add_argument("--coarse-sigma", type=float, default=2.0, help="smoothing of the coarse depth, px "
                                                                          "(without --coarse-data)")
    evaluate.add_argument("--coarse-data", help="the same shapes and views rendered with `render-dataset "
                                                "--coarse-shapes SHAPE_RUN`: coarse depth from the shape autoencoder")
    evaluate.set_defaults(func=_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ngp_mi.backend import BackendError

    try:
        return int(args.func(args) or 0)
    except (BackendError, ValueError, RuntimeError) as error:
        print(f"ngp-mi {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
