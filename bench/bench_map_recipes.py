# make bench: skip (an experiment over trained runs or data given as arguments)
"""Experiment: map-network recipes at an equal budget (issue 15) — one table, one row per arm.

Each arm trains ``train/maps_cpu.toml`` cut to ``--iterations`` map steps and ``--specular`` G_sp^real
steps, with the arm's ``--set`` overrides (the first arm is usually the paper-faithful recipe), then
measures on held-out chairs (``--held-out``: a ``render-dataset`` folder, e.g. seeds 500–519 × 4
views at 64²):

* ``evaluate maps`` (coarse depth: the truth smoothed by σ = 2 px): G_n's and the coarse depth's own
  normal error, the exemplar reconstruction L1 beside the best single colour per view, the spread
  over z_da, the appearance-diversity ratio;
* ``compare --maps-checkpoint`` on ``--compare-set`` held-out chairs × views under the rig (10 × 4;
  3 × 2, the figure before 2026-12-04, moved FLIP by ±0.03 between neighbouring checkpoints): sRGB
  PSNR / FLIP on the object of NGP without and with G_sp^real against a 1024-spp path-traced
  reference, where G_sp^real puts its light, and how much of it is a 2-pixel checkerboard.

With ``--maps-from RUN`` every arm starts from that run's map networks at ``--iterations`` and
trains only the G_sp^real stage (for switches of that stage; ``train min`` is then the stage's).

Arms run one after the other and resume (a killed experiment continues where it stopped); each
arm's figures are kept in its folder (``result.json``, reused when the arm and budget match), so arms
can also run side by side as separate invocations (one thread each) and a last invocation with all
of them prints the table at once (Markdown, for bench/RESULTS.md).

    .venv/bin/python bench/bench_map_recipes.py --held-out outputs/data/held_out_chairs \\
        --arm "paper-faithful (cpu recipe)=" \\
        --arm "FiLM z_da=model.latent_mode=film" \\
        --arm "FiLM + real-NOC albedo cycle=model.latent_mode=film,model.albedo_cycle_noc=real" \\
        [--iterations 1500 --specular 400 --seed 0 --out outputs/bench/recipes]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from ngp_mi.atomic import write_json
from ngp_mi.eval.compare import NGP_METHOD, NO_SP_METHOD, SPECULAR_METRICS, CompareConfig, run_compare
from ngp_mi.eval.maps_eval import evaluate_maps
from ngp_mi.training.maps import seed_from_maps_run, train_maps

ROOT = Path(__file__).resolve().parents[1]


def score_images(folder: Path, compare_set: tuple[int, int]) -> dict:
    """``compare`` of the arm's last checkpoint on ``compare_set`` (shapes, views): NGP's image without
    and with G_sp^real, and where G_sp^real puts its light (``specular_placement``: precision,
    recall, added)."""
    run = folder / "run"
    shapes, views = compare_set
    source = json.loads((run / "recipe.json").read_text())["tables"]["data"]["source"]  # the arm's family
    summary = run_compare(CompareConfig(source=source, num_shapes=shapes, views=views, resolution=64,
                                        light_setups=("rig",), seed=500, maps_checkpoint=str(run)),
                          folder / "compare", log=lambda *_: None)
    by_method = {row["method"]: row for row in summary}
    images = {label: by_method[method] for label, method in (("without G_sp", NO_SP_METHOD), ("NGP", NGP_METHOD))
              if method in by_method}
    out = {"compare_set": [shapes, views],
           "images": {k: {"psnr": v["psnr_srgb_masked"], "flip": v["flip_masked"]} for k, v in images.items()}}
    if NGP_METHOD in by_method:
        out["specular_placement"] = {k.removeprefix("specular_"): by_method[NGP_METHOD][k] for k in SPECULAR_METRICS}
    return out


def run_arm(name: str, overrides: list[str], args: argparse.Namespace, out: Path) -> dict:
    folder = out / name.replace(" ", "_").replace("/", "-")
    budget = {"iterations": args.iterations, "specular": args.specular, "seed": args.seed, "held_out": args.held_out,
              **({"maps_from": args.maps_from} if args.maps_from else {})}
    saved = folder / "result.json"
    if saved.exists():
        result = json.loads(saved.read_text())
        if result.get("overrides") == overrides and result.get("budget", budget) == budget:
            # an arm scored on another compare set (3 × 2 before the set was recorded) is scored again
            if result.get("compare_set", [3, 2]) != list(args.compare_set):
                result.update(score_images(folder, args.compare_set))
                write_json(saved, result)
            return result
    if args.maps_from:
        seed_from_maps_run(Path(args.maps_from), folder / "run", args.iterations)
    began = time.perf_counter()
    run = train_maps(ROOT / "train" / "maps_cpu.toml", log=lambda *_: None, out=folder / "run",
                     overrides=[f"train.iterations={args.iterations}", f"specular.iterations={args.specular}",
                                f"train.seed={args.seed}", "train.checkpoint_every=250", *overrides])
    minutes = (time.perf_counter() - began) / 60
    maps = evaluate_maps(run, args.held_out, folder / "eval", coarse_sigma=2.0)
    result = {"arm": name, "overrides": overrides, "budget": budget, "train_minutes": minutes, "maps": maps,
              **score_images(folder, args.compare_set)}
    write_json(saved, result)
    return result


def score_reconstructions(result: dict, folder: Path, held_out: str, coarse_data: str) -> dict:
    """``result`` with G_n scored on ``coarse_data`` (the held-out shapes as a shape prior reconstructs
    them: ``render-dataset --coarse-shapes``) as ``maps_recon``, computed once per folder."""
    if result.get("maps_recon", {}).get("coarse") != coarse_data:
        result["maps_recon"] = evaluate_maps(folder / "run", held_out, folder / "eval-recon", coarse_data=coarse_data)
        write_json(folder / "result.json", result)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--held-out", required=True, help="a render-dataset folder of held-out shapes")
    parser.add_argument("--arm", action="append", required=True, metavar="NAME=KEY=VALUE,…",
                        help="an arm: its name and its --set overrides (none: the recipe as it is)")
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--specular", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/bench/recipes")
    parser.add_argument("--maps-from", help="a run whose map networks at --iterations every arm starts from "
                                            "(arms then differ in the G_sp^real stage only)")
    parser.add_argument("--compare-set", type=int, nargs=2, default=(10, 4), metavar=("SHAPES", "VIEWS"),
                        help="held-out shapes × views that compare scores the images on (default 10 × 4)")
    parser.add_argument("--coarse-data", help="also score G_n on these coarse depths of --held-out's shapes and views "
                                              "(render-dataset --coarse-shapes: a shape prior's reconstructions)")
    args = parser.parse_args()
    out = Path(args.out)
    results = []
    for arm in args.arm:
        name, _, overrides = arm.partition("=")
        result = run_arm(name, [o for o in overrides.split(",") if o], args, out)
        if args.coarse_data:
            result = score_reconstructions(result, out / name.replace(" ", "_").replace("/", "-"), args.held_out,
                                           args.coarse_data)
        (out / "results.json").parent.mkdir(parents=True, exist_ok=True)
        results.append(result)
        (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"# bench_map_recipes — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads); train/maps_cpu.toml cut to {args.iterations} + {args.specular} "
          f"steps, seed {args.seed}; held-out {args.held_out}; images: compare on "
          f"{args.compare_set[0]} × {args.compare_set[1]} of them\n")
    print("| arm | diversity ratio | spread over z_da | exemplar L1 (single colour) | G_n / own normals ° (σ 2 px) "
          "| G_n / own normals ° mean (median) on reconstructions | w/o G_sp PSNR / FLIP | NGP PSNR / FLIP "
          "| G_sp^real's light: precision / recall (Nyquist %) | train min |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        m, n = r["maps"], r["maps"]["normal_error_deg"]
        image = {k: f"{v['psnr']:.2f} / {v['flip']:.3f}" for k, v in r["images"].items()}
        place = r.get("specular_placement")
        placement = f"{place['precision']:.2f} / {place['recall']:.2f}" if place else "–"
        if place and "nyquist" in place:
            placement += f" ({100 * place['nyquist']:.2f})"
        r_n = r.get("maps_recon", {}).get("normal_error_deg")
        recon = (f"{r_n['G_n']['mean']:.1f} ({r_n['G_n']['median']:.1f}) / {r_n['from_coarse_depth']['mean']:.1f} "
                 f"({r_n['from_coarse_depth']['median']:.1f})") if r_n else "–"
        print(f"| {r['arm']} | {m['appearance_diversity_ratio']:.3f} | {m['albedo_diversity_l1']:.4f} | "
              f"{m['albedo_reconstruction_l1']:.3f} ({m['albedo_single_colour_l1']:.3f}) | "
              f"{n['G_n']['mean']:.1f} / {n['from_coarse_depth']['mean']:.1f} | {recon} | "
              f"{image.get('without G_sp', '–')} | {image.get('NGP', '–')} | {placement} | "
              f"{r['train_minutes']:.1f} |")


if __name__ == "__main__":
    main()
