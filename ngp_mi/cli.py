"""The ``ngp-mi`` command: one sub-command per job; each parses its flags and calls the library, nothing else.

A flag that sets a field of a config (or a parameter of a function) takes its default from that
dataclass or function, so every default lives in one place. A sub-command's flags are declared
only when it is the one invoked (its module is imported then, as running it would), so that
``ngp-mi --help`` and every other command start without importing torch.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import logging
import sys
from pathlib import Path
from typing import Any, Callable, Sequence


def default(owner: Any, name: str) -> Any:
    """The default of field ``name`` of a dataclass, or of parameter ``name`` of a function."""
    if dataclasses.is_dataclass(owner):
        return next(f.default for f in dataclasses.fields(owner) if f.name == name)
    return inspect.signature(owner).parameters[name].default


def network_size(text: str) -> int:
    """An argparse type: an image size the map networks take (:func:`ngp_mi.nets.networks.check_image_size`)."""
    from ngp_mi.nets.networks import check_image_size

    value = at_least(1)(text)
    try:
        check_image_size(value, value, "size")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return value


def at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer ``>= minimum`` (a sample count of 0 would divide by zero inside Mitsuba)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value
    return parse


def int_list(minimum: int) -> Callable[[str], tuple[int, ...]]:
    """An argparse type: comma-separated integers, each ``>= minimum``."""
    one = at_least(minimum)
    return lambda text: tuple(one(x.strip()) for x in text.split(",") if x.strip())


def _joined(values: Sequence[Any]) -> str:
    return ",".join(str(v) for v in values)


# --------------------------------------------------------------------------- sub-commands: flags, then the call

def doctor_flags(p: argparse.ArgumentParser) -> None:
    pass


def doctor(args: argparse.Namespace) -> int:
    from ngp_mi.commands.doctor import run_doctor

    return run_doctor()


def demo_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.demo import run_demo

    p.add_argument("--out", default=default(run_demo, "out_dir"), help="output folder (default: %(default)s)")
    p.add_argument("--res", type=at_least(8), default=default(run_demo, "resolution"),
                   help="image size in pixels (default: %(default)s)")
    p.add_argument("--views", type=at_least(1), default=default(run_demo, "views"),
                   help="number of sampled views (default: %(default)s)")
    p.add_argument("--spp", type=at_least(1), default=default(run_demo, "spp"),
                   help="samples per pixel (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(run_demo, "seed"),
                   help="random seed for views and noise (default: %(default)s)")
    p.add_argument("--model", action="append", help="a shipped model or a model folder; repeat for several "
                                                   "(default: every shipped model)")
    p.add_argument("--frames", type=at_least(2), default=default(run_demo, "frames"),
                   help="frames of each orbit (default: %(default)s)")
    p.add_argument("--fit-steps", type=at_least(1), default=default(run_demo, "fit_steps"),
                   help="steps of the inverse-rendering fit (default: %(default)s)")


def demo(args: argparse.Namespace) -> int:
    from ngp_mi.commands.demo import run_demo

    run_demo(args.out, models=args.model, resolution=args.res, views=args.views, spp=args.spp, seed=args.seed,
             frames=args.frames, fit_steps=args.fit_steps)
    return 0


def families_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.demo import family_sheet

    p.add_argument("family", choices=["chair", "car"], help="shape family")
    p.add_argument("--count", type=at_least(1), default=default(family_sheet, "count"),
                   help="number of samples (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(family_sheet, "first_seed"),
                   help="first seed (default: %(default)s)")
    p.add_argument("--res", type=at_least(8), default=default(family_sheet, "resolution"),
                   help="image size (default: %(default)s)")
    p.add_argument("--spp", type=at_least(1), default=default(family_sheet, "spp"),
                   help="samples per pixel (default: %(default)s)")
    p.add_argument("--out", help="PNG path (default: outputs/families/FAMILY.png)")


def families(args: argparse.Namespace) -> int:
    from ngp_mi.commands.demo import family_sheet

    path = family_sheet(args.family, args.out or f"outputs/families/{args.family}.png", count=args.count,
                        resolution=args.res, spp=args.spp, first_seed=args.seed)
    print(f"wrote {path}")
    return 0


def render_dataset_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.data.exr import COMPRESSIONS
    from ngp_mi.data.render_dataset import DatasetConfig
    from ngp_mi.data.views import LIGHT_MODES

    p.add_argument("--source", required=True, help="chair | car | a mesh folder / ShapeNet tree / mesh file | "
                                                   "a Mitsuba scene .xml (or a folder of them)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--num-shapes", type=at_least(1), default=default(DatasetConfig, "num_shapes"),
                   help="shapes to take from the source (default: %(default)s)")
    p.add_argument("--views", type=at_least(1), default=default(DatasetConfig, "views"),
                   help="views per shape (default: %(default)s)")
    p.add_argument("--res", type=at_least(1), default=default(DatasetConfig, "resolution"),
                   help="image size in pixels (default: %(default)s)")
    p.add_argument("--channels", default=_joined(default(DatasetConfig, "channels")),
                   help="G-buffer channels to write (default: %(default)s)")
    p.add_argument("--real-spp", type=at_least(0), default=default(DatasetConfig, "real_spp"),
                   help="samples per pixel of the path-traced 'real' image; 0 = none (default: %(default)s)")
    p.add_argument("--lights", default=default(DatasetConfig, "lights"), choices=LIGHT_MODES,
                   help="lights of the real images: the 4-light rig, random, or the scene file's own")
    p.add_argument("--shard", default="0/1", help="K/N: render every N-th shape starting at K (default: 0/1)")
    p.add_argument("--seed", type=int, default=default(DatasetConfig, "seed"),
                   help="seed of shapes, views and noise (default: %(default)s)")
    p.add_argument("--compression", default=default(DatasetConfig, "compression"), choices=sorted(COMPRESSIONS),
                   help="EXR compression, all lossless (default: %(default)s, the fastest to write; zip: ~2x "
                        "smaller); may differ between runs that fill one folder")
    p.add_argument("--full-window", action="store_true", help="store every pixel of the maps, not only the "
                   "object's bounding rectangle (the EXR data window; readers see zeros outside it either way)")
    p.add_argument("--half", action="store_true", help="store all channels but depth as 16-bit floats (half the size)")
    p.add_argument("--workers", type=at_least(0), default=0, help="processes splitting this shard's shapes "
                   "(default: one per core, at most 8; 1 on a GPU)")
    p.add_argument("--coarse-shapes", metavar="RUN", help="a `train shape` run, or a model folder or shipped name "
                   "(chair, car): render each shape as its autoencoder reconstructs it (NGP's coarse shapes; ids and "
                   "views pair with the detailed ones)")
    p.add_argument("--coarse-resolution", type=at_least(8), default=default(DatasetConfig, "coarse_resolution"),
                   help="marching-cubes grid of --coarse-shapes (default: %(default)s)")
    p.add_argument("--strict", action="store_true", help="exit non-zero if any shape was skipped")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def render_dataset(args: argparse.Namespace) -> int:
    from ngp_mi.data.render_dataset import DatasetConfig, default_workers, parse_shard, render_dataset

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    config = DatasetConfig(source=args.source, num_shapes=args.num_shapes, views=args.views, resolution=args.res,
                           channels=tuple(c.strip() for c in args.channels.split(",") if c.strip()),
                           real_spp=args.real_spp, lights=args.lights, seed=args.seed, compression=args.compression,
                           full_window=args.full_window, half=args.half, coarse_shapes=args.coarse_shapes,
                           coarse_resolution=args.coarse_resolution)
    reconstruct = None
    if args.coarse_shapes:
        from ngp_mi.models import pretrained  # imports torch (~3 s): only coarse shapes need it

        reconstruct = pretrained.coarse_shapes(args.coarse_shapes, args.coarse_resolution)
    summary = render_dataset(config, args.out, shard=parse_shard(args.shard), strict=args.strict,
                             progress=not args.quiet, workers=args.workers or default_workers(),
                             reconstruct=reconstruct)
    print(f"render-dataset: {summary['views_rendered']} views rendered ({summary['views_per_second']} views/s), "
          f"{summary['views_before']} already present, {len(summary['skipped_shapes'])} shapes skipped")
    for shape_id, reason in summary["skipped_shapes"].items():
        print(f"  skipped {shape_id}: {reason}")
    return 0


def compare_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.eval.compare import CompareConfig

    p.add_argument("--source", default=default(CompareConfig, "source"), help="chair | car | mesh folder / file | "
                   "scene .xml (default: the family the --maps-checkpoint networks trained on, else chair)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--num-shapes", type=at_least(1), default=default(CompareConfig, "num_shapes"),
                   help="shapes (default: %(default)s)")
    p.add_argument("--views", type=at_least(1), default=default(CompareConfig, "views"),
                   help="views per shape (default: %(default)s)")
    p.add_argument("--res", type=at_least(8), default=default(CompareConfig, "resolution"),
                   help="image size (default: %(default)s)")
    p.add_argument("--lights", default=_joined(default(CompareConfig, "light_setups")),
                   help="light setups, from rig,random,rig+random (the rig plus added lights: NGP-plus) "
                        "(default: %(default)s)")
    p.add_argument("--spp-ladder", type=int_list(1), default=default(CompareConfig, "spp_ladder"),
                   help=f"path-tracing spp to compare (default: {_joined(default(CompareConfig, 'spp_ladder'))})")
    p.add_argument("--reference-spp", type=at_least(1), default=default(CompareConfig, "reference_spp"),
                   help="spp of the reference (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(CompareConfig, "seed"), help="seed (default: %(default)s)")
    p.add_argument("--maps-checkpoint", "--model", dest="maps_checkpoint",
                   help="trained map networks: a `train maps` run folder, a shipped model (chair, car) or a model "
                        "folder; adds NGP-BP, NGP, NGP-plus and the ablations on generated maps")
    p.add_argument("--inception-weights", help="local inception-2015-12-05.pt (TorchScript): adds FID / KID; "
                                               "never downloaded")
    p.add_argument("--exemplar-steps", type=at_least(0), default=default(CompareConfig, "exemplar_steps"),
                   help="also score NGP with z_da refined by this many steps on the exemplar (fit_appearance, "
                        "beyond the paper; 30 in bench/RESULTS.md) beside μ(E_da) (default: %(default)s, off)")


def compare(args: argparse.Namespace) -> int:
    from ngp_mi.eval.compare import CompareConfig, run_compare

    config = CompareConfig(source=args.source, num_shapes=args.num_shapes, views=args.views, resolution=args.res,
                           light_setups=tuple(args.lights.split(",")), spp_ladder=tuple(args.spp_ladder),
                           reference_spp=args.reference_spp, seed=args.seed, maps_checkpoint=args.maps_checkpoint,
                           inception_weights=args.inception_weights, exemplar_steps=args.exemplar_steps)
    run_compare(config, args.out)
    return 0


def train_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("stage", choices=["shape", "maps", "e2e"],
                   help="what to train (e2e: G_shape's decoder with the maps' 2-D losses through Π_v)")
    p.add_argument("--config", required=True, help="TOML recipe, e.g. train/maps_tiny.toml")
    p.add_argument("--out", help="output folder (default: the recipe's [train] out)")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override a recipe value (TOML syntax; bare words are strings), checked like the file; "
                        "repeatable, recorded in OUT/recipe.json. E.g. --set train.iterations=500")
    p.add_argument("--maps-from", metavar="RUN",
                   help="maps only: start from RUN's map networks at step [train] iterations (or from a model "
                        "folder's or shipped model's, with the recipe's [model] as its card's) and train the "
                        "later stages alone (the [encoder] and G_sp^real stages: their switches, or re-trained "
                        "stages, on trained map networks)")


def train(args: argparse.Namespace) -> int:
    if args.stage == "shape":
        from ngp_mi.training.shape import train_shape as run
    elif args.stage == "maps":
        from ngp_mi.training.maps import train_maps as run
    else:
        from ngp_mi.training.e2e import train_e2e as run
    if args.maps_from and args.stage != "maps":
        raise SystemExit(f"train {args.stage}: --maps-from is for `train maps`")
    extra = {"maps_from": args.maps_from} if args.maps_from else {}
    out = run(args.config, out=args.out, overrides=args.set, **extra)
    print(f"train {args.stage}: outputs in {out}")
    return 0


def sample_shapes_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.sample_shapes import sample_shapes

    p.add_argument("--run", required=True, help="a `train shape` output folder (with ckpt-*)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--num", type=at_least(1), default=default(sample_shapes, "num"),
                   help="number of shapes (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(sample_shapes, "seed"),
                   help="latent seed of the first shape (default: %(default)s)")
    p.add_argument("--resolution", type=at_least(8), default=default(sample_shapes, "resolution"),
                   help="marching-cubes grid (default: %(default)s)")
    p.add_argument("--coarse", type=at_least(4), default=default(sample_shapes, "coarse"),
                   help="coarse grid of the coarse-to-fine pass (default: %(default)s)")
    p.add_argument("--format", choices=["obj", "ply"], default=default(sample_shapes, "fmt"),
                   help="mesh format (default: %(default)s)")
    p.add_argument("--interpolate", type=int, nargs=2, metavar=("SEED_A", "SEED_B"),
                   help="interpolate (slerp) between the latents of two seeds instead")
    p.add_argument("--steps", type=at_least(2), default=default(sample_shapes, "steps"),
                   help="interpolation steps (default: %(default)s)")
    p.add_argument("--spp", type=at_least(1), default=default(sample_shapes, "spp"),
                   help="samples per pixel of the previews (default: %(default)s)")


def sample_shapes(args: argparse.Namespace) -> int:
    from ngp_mi.commands.sample_shapes import sample_shapes

    summary = sample_shapes(args.run, args.out, num=args.num, seed=args.seed, resolution=args.resolution,
                            coarse=args.coarse, fmt=args.format, interpolate=tuple(args.interpolate) if args.interpolate
                            else None, steps=args.steps, spp=args.spp)
    print(f"sample-shapes: {len(summary['shapes'])} shapes ({summary['empty']} empty) in {args.out}; "
          f"median extraction {summary['median_seconds']:.2f} s")
    return 0


def generate_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.generate import generate

    views = ";".join(f"{t:g},{f:g}" for t, f in default(generate, "views"))
    p.add_argument("--model", help="a shipped model (chair, car) or a model folder (`ngp-mi export-model`); the "
                                   "default when no --maps-run is given: chair")
    p.add_argument("--maps-run", help="a `train maps` output folder (with the [specular] stage for ngp / ngp-plus) "
                                      "instead of a shipped model")
    p.add_argument("--shape-run", help="a `train shape` output folder (shapes from z_s), with --maps-run")
    p.add_argument("--mesh", help="a user mesh instead of sampled shapes")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--num", type=at_least(1), default=default(generate, "num"),
                   help="shapes to sample (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(generate, "seed"),
                   help="seed of z_s and z_da of the first shape (default: %(default)s)")
    p.add_argument("--views", default=views, help="camera views 'THETA,PHI;…' in degrees (default: %(default)s)")
    p.add_argument("--res", type=network_size, default=default(generate, "resolution"),
                   help="image size, a multiple of 4 (default: %(default)s)")
    p.add_argument("--lights", default="rig", help="'rig' (the 4 overhead lights) or a lights JSON file")
    p.add_argument("--add-lights", help="a lights JSON file of lights added by R_BP (variant ngp-plus)")
    p.add_argument("--variant", default=default(generate, "variant").replace("_", "-"),
                   choices=["ngp", "ngp-bp", "ngp-plus", "no-sp", "no-gn", "no-gda"],
                   help="NGP variant or ablation (default: %(default)s)")
    p.add_argument("--exemplar", help="an albedo image: its appearance code μ(E_da) instead of a sampled z_da")
    p.add_argument("--exemplar-view", metavar="FOLDER",
                   help="a `render-dataset` folder with albedo, depth and mask: z_da fitted to the albedo of one of "
                        "its views on that view's own geometry (closer to the exemplar than --exemplar's code)")
    p.add_argument("--exemplar-item", type=at_least(0), default=default(generate, "exemplar_item"), metavar="N",
                   help="which view of --exemplar-view, in its manifest's order (default: %(default)s)")
    p.add_argument("--fit-steps", type=at_least(0), default=default(generate, "fit_steps"), metavar="N",
                   help="Adam steps of the --exemplar-view fit from μ(E_da); 0 keeps μ (default: %(default)s)")
    sweeps = p.add_argument_group("sweeps (each a labelled sheet in OUT/sweeps/)")
    sweeps.add_argument("--orbit-camera", type=at_least(0), default=0, metavar="N",
                        help="N views from φ -90° to 90° at the first view's elevation")
    sweeps.add_argument("--orbit-light", type=at_least(0), default=0, metavar="N",
                        help="one white light at N positions round the object")
    sweeps.add_argument("--appearance-seeds", type=int_list(0), default=(), metavar="S,S,…", help="z_da seeds")
    sweeps.add_argument("--shape-seeds", type=int_list(0), default=(), metavar="S,S,…", help="z_s seeds (one row)")
    sweeps.add_argument("--light-count", type=int_list(1), default=(), metavar="K,K,…",
                        help="the first K lights of the overhead rig, K in 1..4")
    sweeps.add_argument("--interpolate", type=int, nargs=2, metavar=("A", "B"),
                        help="slerp between the latents of seeds A and B: z_s, or z_da with --mesh")
    sweeps.add_argument("--steps", type=at_least(2), default=5, help="steps of --interpolate (default: %(default)s)")
    sweeps.add_argument("--animate", action="store_true", help="also a looping GIF of each orbit")


def generate(args: argparse.Namespace) -> int:
    from ngp_mi.commands.generate import Sweeps, generate
    from ngp_mi.lights import load_lights, overhead_rig

    views = []
    for text in args.views.split(";"):
        try:
            theta, phi = (float(x) for x in text.split(","))
        except ValueError:
            raise ValueError(f"--views must look like 'THETA,PHI;THETA,PHI' in degrees, got {args.views!r}") from None
        views.append((theta, phi))
    lights = overhead_rig() if args.lights == "rig" else load_lights(args.lights)
    added = load_lights(args.add_lights) if args.add_lights else []
    summary = generate(args.maps_run, args.out, shape_run=args.shape_run, mesh_path=args.mesh, model=args.model,
                       num=args.num,
                       seed=args.seed, views=views, resolution=args.res, lights=lights, added_lights=added,
                       variant=args.variant.replace("-", "_"), exemplar=args.exemplar,
                       exemplar_view=args.exemplar_view, exemplar_item=args.exemplar_item, fit_steps=args.fit_steps,
                       sweeps=Sweeps(orbit_camera=args.orbit_camera, orbit_light=args.orbit_light,
                                     appearance_seeds=tuple(args.appearance_seeds),
                                     shape_seeds=tuple(args.shape_seeds), light_count=tuple(args.light_count),
                                     interpolate=tuple(args.interpolate) if args.interpolate else None,
                                     steps=args.steps, animate=args.animate),
                       command=["ngp-mi", *args.argv])
    print(f"generate: {len(summary['images'])} images and {len(summary['sweep_files'])} sweep files in {args.out} "
          "(sheet.png, sweeps/, report.md)")
    return 0


def fit_shape_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.fit_shape import FitConfig

    p.add_argument("--targets", required=True, help="a render-dataset folder (masks and depths with their cameras), or "
                                                    "a folder of your own images with a cameras.json (README)")
    p.add_argument("--shape-id", help="which shape of it (default: the first)")
    p.add_argument("--out", required=True, help="output folder (a killed fit resumes from it)")
    p.add_argument("--held-out", type=at_least(0), default=default(FitConfig, "held_out"),
                   help="the last K views are scored, not fitted (default: %(default)s)")
    p.add_argument("--steps", type=at_least(0), default=default(FitConfig, "steps"),
                   help="vertex steps; 0 with --start zs stops after the latent phase (default: %(default)s)")
    p.add_argument("--lr", type=float, default=default(FitConfig, "lr"), help="Adam's step (default: %(default)s)")
    p.add_argument("--lam", type=float, default=default(FitConfig, "lam"),
                   help="λ of the preconditioner I + λL (default: %(default)s)")
    p.add_argument("--start", default=default(FitConfig, "start"),
                   help="'sphere', 'zs' (the shape prior's best latent, then z_s fitted) or a mesh file "
                        "(default: %(default)s)")
    p.add_argument("--model", help="a shipped model or model folder: its map networks form the image term (z_da "
                                    "fitted too) and its shape prior starts --start zs")
    p.add_argument("--maps-run", help="a `train maps` output folder for the image term, instead of --model")
    p.add_argument("--shape-run", help="with --start zs: a `train shape` output folder")
    p.add_argument("--zs-steps", type=at_least(0), default=default(FitConfig, "zs_steps"),
                   help="steps of z_s before the vertices (default: %(default)s)")
    p.add_argument("--fit-decoder", action="store_true",
                   help="with --start zs: the decoder's weights move with z_s (phase (b))")
    p.add_argument("--decoder-lr", type=float, default=default(FitConfig, "decoder_lr"),
                   help="Adam's step for the decoder with --fit-decoder (default: %(default)s)")
    p.add_argument("--grid-steps", type=at_least(0), default=default(FitConfig, "grid_steps"),
                   help="with --start zs: steps of phase (d), the field on a grid whose nodes move freely, which can "
                        "open holes (a chair back's slats) before the vertices (default: %(default)s)")
    p.add_argument("--grid-resolution", type=at_least(8), default=default(FitConfig, "grid_resolution"),
                   help="cells per axis of phase (d)'s grid (default: %(default)s)")
    p.add_argument("--grid-lr", type=float, default=default(FitConfig, "grid_lr"),
                   help="Adam's step for phase (d)'s node values (default: %(default)s)")
    p.add_argument("--ray-weight", type=float, default=default(FitConfig, "ray_weight"),
                   help="phase (d): weight of the free-space term along the rays of background pixels "
                        "(default: %(default)s)")
    p.add_argument("--min-component", type=float, default=default(FitConfig, "min_component"),
                   help="with --start zs: drop pieces of the extracted surface under this share of its area before "
                        "the vertices (floaters beside thin parts; 0 keeps all) (default: %(default)s)")
    p.add_argument("--mirror", choices=["x", "y", "z"], default=None,
                   help="the shape is mirror-symmetric about the plane normal to this axis (chairs and cars of "
                        "render-dataset: x): each fitted view's mirror image is fitted too")
    p.add_argument("--mask-weight", type=float, default=default(FitConfig, "mask_weight"), help="(default: %(default)s)")
    p.add_argument("--binary-masks", action="store_true",
                   help="fit the binary masks even where the targets carry each pixel's coverage (the alpha of "
                        "render-dataset's images, a soft matte), which places outlines within a pixel")
    p.add_argument("--depth-weight", type=float, default=default(FitConfig, "depth_weight"),
                   help="0 fits masks only (default: %(default)s)")
    p.add_argument("--image-weight", type=float, default=default(FitConfig, "image_weight"),
                   help="weight of the image L1 (linear radiance) through NGP's networks; needs --model or "
                        "--maps-run and path-traced targets (default: %(default)s)")
    p.add_argument("--image-downsample", type=at_least(1), default=default(FitConfig, "image_downsample"),
                   help="the image term at 1/K of the targets' resolution, e.g. 2 for 128-px targets and "
                        "networks trained at 64 px: 1/4 of their cost (default: %(default)s)")
    p.add_argument("--format", choices=["obj", "ply"], default=default(FitConfig, "mesh_format"),
                   help="of the fitted mesh (default: %(default)s)")
    p.add_argument("--no-silhouette", action="store_true", help="interior gradients only (the fast Π_v)")
    p.add_argument("--spp", type=at_least(1), default=default(FitConfig, "spp"), help="(default: %(default)s)")
    p.add_argument("--boundary-spp", type=at_least(1), default=default(FitConfig, "boundary_spp"),
                   help="samples per pixel of the silhouette term (default: %(default)s)")


def fit_shape(args: argparse.Namespace) -> int:
    from ngp_mi.commands.fit_shape import FitConfig, fit_shape

    config = FitConfig(targets=args.targets, shape_id=args.shape_id, held_out=args.held_out, steps=args.steps,
                       lr=args.lr, lam=args.lam, start=args.start, mask_weight=args.mask_weight,
                       soft_masks=not args.binary_masks,
                       depth_weight=args.depth_weight, silhouette=not args.no_silhouette, spp=args.spp,
                       boundary_spp=args.boundary_spp, zs_steps=args.zs_steps, image_weight=args.image_weight,
                       fit_decoder=args.fit_decoder, decoder_lr=args.decoder_lr, mesh_format=args.format,
                       grid_steps=args.grid_steps, grid_resolution=args.grid_resolution, grid_lr=args.grid_lr,
                       ray_weight=args.ray_weight, mirror=args.mirror or "", min_component=args.min_component,
                       image_downsample=args.image_downsample)
    from ngp_mi.models.shape import ShapeModel
    from ngp_mi.pipeline import NGP

    ngp = (NGP(args.maps_run) if args.maps_run else
           NGP.pretrained(args.model) if args.model else None)
    shape_model = None
    if args.start == "zs":
        shape_model = ShapeModel.from_run(args.shape_run) if args.shape_run else (
            ngp.shape_model if ngp is not None and ngp.shape_model is not None else NGP.pretrained("chair").shape_model)
    summary = fit_shape(config, args.out, shape_model, ngp)
    loss = f"loss {summary['loss_start']:.5f} -> {summary['loss_end']:.5f}, " if summary["loss_end"] is not None else ""
    print(f"fit-shape: {loss}mask IoU "
          f"{summary['mask_iou_fitted']:.3f}" + (f", Chamfer-L2 {summary['chamfer_start']:.5f} -> "
                                                 f"{summary['chamfer_end']:.5f}" if summary["chamfer_end"] else ""))
    return 0


def view_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.commands.view import view

    p.add_argument("--model", help="a shipped model (chair, car) or a model folder (default: chair)")
    p.add_argument("--maps-run", help="a `train maps` output folder instead of a model")
    p.add_argument("--shape-run", help="a `train shape` output folder, with --maps-run")
    p.add_argument("--mesh", help="a mesh to show (needed when the model has no shape prior)")
    p.add_argument("--host", default=default(view, "host"), help="address to serve on (default: %(default)s, this "
                                                                   "machine only)")
    p.add_argument("--port", type=at_least(1), default=default(view, "port"), help="port (default: %(default)s)")
    p.add_argument("--res", type=network_size, default=default(view, "resolution"),
                   help="image height when the camera stops (default: %(default)s)")
    p.add_argument("--out", default=default(view, "out"), help="where 'save image' writes (default: %(default)s)")


def view(args: argparse.Namespace) -> int:
    from ngp_mi.commands.view import view

    view(model=args.model, mesh=args.mesh, maps_run=args.maps_run, shape_run=args.shape_run, host=args.host,
         port=args.port, resolution=args.res, out=args.out)
    return 0


def export_model_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--maps-run", help="a `train maps` output folder (required unless --add-encoder)")
    p.add_argument("--add-encoder", metavar="SHAPE_RUN",
                   help="instead: put this `train shape` run's encoder ([train] encoder_for) into the model folder "
                        "--out, whose G_shape it was trained for; nothing else changes (a model folder with the "
                        "same decoder works too: --out itself re-writes its encoder in float16)")
    p.add_argument("--shape-run", help="a `train shape` output folder (G_shape)")
    p.add_argument("--shape-from", help="instead of --shape-run: keep G_shape (and its card facts) of this model "
                                        "folder or shipped name, when only the maps were re-trained")
    p.add_argument("--specular-from", help="keep G_sp^real of this model folder or shipped name instead of the run's "
                                           "stage (its G_n and G_da must be the run's)")
    p.add_argument("--out", required=True, help="the model folder (ngp_mi/pretrained/NAME to ship it)")
    p.add_argument("--family", default="", help="what the model draws (chair, car, …), for its card")
    p.add_argument("--figures", help="a JSON file of evaluation figures to put on the card")
    p.add_argument("--notes", default="", help="a line for the card (how it was trained, where)")


def export_model(args: argparse.Namespace) -> int:
    from ngp_mi.models.pretrained import export_model

    if args.add_encoder:
        from ngp_mi.models.pretrained import add_encoder

        out = add_encoder(args.out, args.add_encoder)
        print(f"export-model: {out}: G_shape's encoder from {args.add_encoder}")
        return 0
    if not args.maps_run:
        raise ValueError("export-model: --maps-run is required (or --add-encoder SHAPE_RUN)")
    figures = json.loads(open(args.figures).read()) if args.figures else None
    out = export_model(args.out, args.maps_run, args.shape_run, family=args.family, figures=figures, notes=args.notes,
                       shape_from=args.shape_from, specular_from=args.specular_from)
    card = json.loads((out / "card.json").read_text())
    total = sum(f["bytes"] for f in card["files"].values())
    print(f"export-model: {out} ({', '.join(card['files'])}; {total / 2 ** 20:.1f} MiB)")
    return 0


def evaluate_flags(p: argparse.ArgumentParser) -> None:
    from ngp_mi.eval.maps_eval import evaluate_maps
    from ngp_mi.eval.shape_eval import evaluate_shape

    p.add_argument("stage", choices=["maps", "shape"], help="what to evaluate: map networks, or a shape prior")
    p.add_argument("--run", required=True, help="a `train maps` run (maps) or `train shape` run (shape), a shipped "
                                                "model's name (chair, car) or an exported model folder")
    p.add_argument("--data", help="maps: the held-out render-dataset folder (required)")
    p.add_argument("--out", help="output folder (default: RUN/eval or RUN/eval-shape for a run, "
                                 "outputs/eval-maps/NAME or outputs/eval-shape/NAME for a model)")
    p.add_argument("--coarse-sigma", type=float, default=default(evaluate_maps, "coarse_sigma"),
                   help="maps: smoothing of the coarse depth, px (without --coarse-data) (default: %(default)s)")
    p.add_argument("--coarse-data", help="maps: the same shapes and views rendered with `render-dataset --coarse-shapes "
                                         "SHAPE_RUN`: coarse depth from the shape autoencoder")
    p.add_argument("--source", default=default(evaluate_shape, "source"),
                   help="shape: the shapes to reconstruct, a family or meshes (default: %(default)s)")
    p.add_argument("--num-shapes", type=int, default=default(evaluate_shape, "num_shapes"),
                   help="shape: how many (default: %(default)s)")
    p.add_argument("--seed", type=int, default=default(evaluate_shape, "seed"),
                   help="shape: the first shape's seed; 500-519 are held out of every shipped prior (default: %(default)s)")
    p.add_argument("--res", type=int, default=default(evaluate_shape, "resolution"),
                   help="shape: marching-cubes resolution of the reconstructions (default: %(default)s)")


def evaluate(args: argparse.Namespace) -> int:
    from ngp_mi.models.pretrained import is_training_run

    # beside a run's checkpoints; a model's (shipped or a folder) under outputs/
    out = args.out or (f"{args.run}/{'eval-shape' if args.stage == 'shape' else 'eval'}" if is_training_run(args.run)
                       else f"outputs/eval-{args.stage}/{Path(args.run).name}")
    if args.stage == "shape":
        from ngp_mi.eval.shape_eval import evaluate_shape

        evaluate_shape(args.run, out, args.source, args.num_shapes, args.seed, args.res)
        return 0
    from ngp_mi.eval.maps_eval import evaluate_maps

    if not args.data:
        raise ValueError("evaluate maps: --data (a held-out render-dataset folder) is required")
    result = evaluate_maps(args.run, args.data, out, coarse_sigma=args.coarse_sigma,
                           coarse_data=args.coarse_data)
    print(json.dumps(result, indent=1))
    return 0


#: name → (flags, run, one-line help, description)
COMMANDS: dict[str, tuple[Callable, Callable, str, str]] = {
    "doctor": (doctor_flags, doctor, "print versions, backend and a timed test render; exit 0 if rendering works",
               "Print versions, the Mitsuba variant, libLLVM and a timed test render."),
    "demo": (demo_flags, demo, "the demo page outputs/demo/index.html: NGP under every handle, path-traced references",
             "NGP of the shipped models (or --model folders) under every handle — camera and light orbits, "
             "appearance and shape sweeps, an exemplar transfer, the variants, every intermediate map — and a "
             "procedural chair path traced from the paper's view distribution, with 16 samples of each family, in "
             "one HTML page."),
    "families": (families_flags, families, "contact sheet of samples of a procedural shape family",
                 "Path trace consecutive seeds of a procedural family (chair, car) with their part materials into "
                 "one contact sheet."),
    "render-dataset": (render_dataset_flags, render_dataset,
                       "render reference maps (EXR) and path-traced images of many shapes",
                       "Render G-buffer maps (depth, normal, albedo, NOC, mask) and optionally path-traced 'real' "
                       "images for shapes x sampled views, with a manifest. Resumable; shardable with --shard K/N."),
    "compare": (compare_flags, compare, "time and score deferred shading against path-traced references",
                "Render, time and score path tracing at a ladder of spp and R_diff / R_BP on ground-truth maps (and "
                "NGP on generated maps) against a high-spp path-traced reference; write images, a speed-accuracy "
                "plot, results.json and report.html."),
    "train": (train_flags, train, "train a stage of NGP from a recipe (train/*.toml); resumes automatically",
              "Train the shape prior (stage 'shape': IM-NET autoencoder + latent WGAN-GP), the map networks (stage "
              "'maps') or G_shape's decoder through Π_v with the maps' 2-D losses (stage 'e2e') from a TOML recipe, "
              "with values overridden by --set; logs, metrics, image grids and checkpoints go to --out or the "
              "recipe's [train] out. Maps and e2e: multi-process with torchrun."),
    "sample-shapes": (sample_shapes_flags, sample_shapes,
                      "meshes and a rendered contact sheet from a trained shape prior",
                      "Sample z_s, extract meshes (coarse-to-fine marching cubes), write OBJ/PLY, sheet.png, "
                      "samples.json and report.md; or interpolate between two seeds."),
    "generate": (generate_flags, generate, "NGP images: shapes from G_shape (or a mesh), maps, lights, G_sp^real",
                 "Form NGP images (paper Sec. 3): sample shapes with G_shape (or take --mesh), project them with "
                 "Mitsuba from the given views, generate normals and albedo, shade under the lights and blend the "
                 "realistic specular map. Writes images/, sheet.png (every intermediate map), generate.json and "
                 "report.md."),
    "fit-shape": (fit_shape_flags, fit_shape, "recover a shape from images through the differentiable Π_v",
                  "Fit a shape (from a sphere, a mesh file or the shape prior's z_s) to the masks, depths and images "
                  "of one shape of a render-dataset folder, or to your own images with a cameras.json: z_s (and the "
                  "decoder), then vertices through the Laplacian parameterisation (largesteps), Π_v with silhouette "
                  "gradients, the image through NGP's networks with a model; writes the mesh, curves, a "
                  "target-vs-fit sheet, a GIF of the fit and a report; resumable."),
    "view": (view_flags, view, "an interactive NGP viewer in the browser (viser): every handle, live",
             "Serve a page on which you orbit, pan and zoom the NGP image, drag lights as gizmos and set shape, "
             "appearance, variant, constants, the map shown and the resolution; save images with their settings "
             "and write them as generate command lines."),
    "export-model": (export_model_flags, export_model, "a model folder of trained runs' inference networks and a card",
                     "Write the inference networks of a `train maps` run (and a `train shape` run) as safetensors with "
                     "a card.json (configs, recipes, steps, time, machine, figures): what `--model` loads and what "
                     "ngp_mi/pretrained/ ships."),
    "evaluate": (evaluate_flags, evaluate, "evaluate trained map networks on held-out maps (normal error, albedo), "
                 "or a shape prior's reconstructions of held-out shapes",
                 "maps: normal angular error of G_n from a coarse depth against normals from the same depth (NGP w/o "
                 "G_n); E_da -> G_da albedo reconstruction and diversity. shape: the autoencoder's IoU and Chamfer-L2 "
                 "on shapes it was not trained on, with a contact sheet."),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s flags are declared (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="ngp-mi",
                                     description="Neural Graphics Pipeline on Mitsuba 3 / Dr.Jit and PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name, (flags, run, help_text, description) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=description)
        if name == command:
            flags(p)
        p.set_defaults(func=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(next((a for a in argv if a in COMMANDS), None))
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ngp_mi.backend import BackendError

    args.argv = argv  # what a command records to be re-run
    try:
        return int(args.func(args) or 0)
    except (BackendError, ValueError, RuntimeError) as error:
        print(f"ngp-mi {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
