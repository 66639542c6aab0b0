"""Benchmark: `train e2e` against its control at an equal budget (issue 17, part 2).

Three states of one family's models: the trained runs the two arms start from (``--base-maps``,
``--base-shape``), the control (``train.link=false``: the same map-network steps on G_shape's depth,
the decoder fixed — training "separately") and the linked run (L_2D through Π_v into the decoder).
Per state: `evaluate maps` on a held-out render-dataset folder (G_n against the coarse depth's own
normals, exemplar L1, appearance-diversity ratio); the shape prior's autoencoder IoU on the held-out
shapes of its cache and COV / MMD of 64 samples against the training shapes (as `train shape`
measures them); and one contact sheet, the same z_s and z_da for every state, NGP w/o G_sp^real under
the rig (the e2e runs do not train G_sp^real).

The runs (the defaults below), after ``scripts/ship-model.sh car 2000 400``, each arm with
``--set train.link=true`` or ``false``:

    ngp-mi train e2e --config train/e2e_cpu.toml --out outputs/train/e2e_car_link \
        --set init.maps_run=outputs/train/maps_car --set init.shape_run=outputs/train/shape_car \
        --set data.source=car --set data.cache_dir=outputs/data/maps_car --set train.iterations=200 \
        --set train.link=true
    .venv/bin/python bench/bench_e2e.py [--family car --base-maps outputs/train/maps_car
        --base-shape outputs/train/shape_car --link outputs/train/e2e_car_link
        --control outputs/train/e2e_car_control --data outputs/data/held_out_car
        --arm "anchored: shape_anchor = 1=outputs/train/e2e_car_anchor" --out outputs/bench/e2e]

Without those folders it says which is missing and skips (``make bench`` runs every benchmark).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from ngp_mi.camera import Camera
from ngp_mi.data.shapes import ShapeDataset
from ngp_mi.eval.maps_eval import evaluate_maps
from ngp_mi.lights import overhead_rig
from ngp_mi.models.maps import MapsModel
from ngp_mi.models.shape import ShapeModel
from ngp_mi.pipeline import NGP, EmptyShape, latent
from ngp_mi.training.shape import autoencoder_iou, run_shape_data, sample_metrics
from ngp_mi.viz import chw_to_uint8, labelled_grid, save_png


def shape_figures(model: ShapeModel, reference: list[np.ndarray], held: ShapeDataset) -> dict[str, float]:
    """Autoencoder IoU on the held-out shapes and COV / MMD of 64 samples against the training shapes'
    surface points ``reference``, as `train shape` reports them."""
    samples = sample_metrics(model, reference, [], 64, 64, seed=1)
    return {"iou_held_out": autoencoder_iou(model, held, model.config.voxel_resolution),
            "coverage": samples.get("coverage", 0.0), "mmd": samples.get("mmd", float("nan")),
            "empty": samples["empty_samples"]}


def sheet_row(ngp: NGP, seeds: range, camera: Camera) -> list[np.ndarray]:
    row = []
    for seed in seeds:
        try:
            mesh = ngp.shape(latent(seed, ngp.shape_model.config.z_dim))
        except EmptyShape:
            row.append(np.zeros((camera.height, camera.width, 3), np.uint8))
            continue
        image = ngp.render(mesh, camera, ngp.appearance(0), overhead_rig(), variant="no_sp")["image"]
        row.append(chw_to_uint8(image.clamp(0, 1)))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    defaults = {"base-maps": "outputs/train/maps_car", "base-shape": "outputs/train/shape_car",
                "link": "outputs/train/e2e_car_link", "control": "outputs/train/e2e_car_control",
                "data": "outputs/data/held_out_car"}
    for name, default in defaults.items():
        parser.add_argument(f"--{name}", default=default)
    parser.add_argument("--family", default="car")
    parser.add_argument("--arm", action="append", default=[], metavar="NAME=FOLDER",
                        help="a further `train e2e` run to compare (e.g. with shape_anchor set)")
    parser.add_argument("--out", default="outputs/bench/e2e")
    args = parser.parse_args()
    given = {name: vars(args)[name.replace("-", "_")] for name in defaults}
    missing = [f"--{name} {folder}" for name, folder in given.items() if not Path(folder).is_dir()]
    if missing:
        print(f"bench_e2e: skipped, no such folder: {', '.join(missing)} (the module docstring says how to make them)")
        return
    out = Path(args.out)
    states = {"trained runs (start)": (args.base_maps, args.base_shape),
              "control: link = false": (args.control, f"{args.control}/shape"),
              "end to end: link = true": (args.link, f"{args.link}/shape")}
    for arm in args.arm:
        name, _, folder = arm.rpartition("=")  # a name may hold "=", a folder does not
        if not Path(folder).is_dir():
            raise SystemExit(f"bench_e2e: --arm {arm}: no such folder {folder}")
        states[name] = (folder, f"{folder}/shape")
    _, train, held = run_shape_data(args.base_shape)  # the shapes and split of the run the arms start from
    if held is None:
        raise SystemExit(f"bench_e2e: {args.base_shape} was trained without held-out shapes; no IoU to compare")
    reference = [train.surface(i) for i in range(len(train))]
    camera = Camera.orbit(20.0, 35.0, 128)
    rows, images = [], []
    for k, (name, (maps_run, shape_run)) in enumerate(states.items()):
        maps_eval = evaluate_maps(maps_run, args.data, out / f"eval-{k}")
        shape_model = ShapeModel.from_run(shape_run)
        shape = shape_figures(shape_model, reference, held)
        ngp = NGP.of(MapsModel.from_run(maps_run), None, shape_model)
        images.append(sheet_row(ngp, range(6), camera))
        rows.append((name, maps_eval, shape))
    e2e_train = json.loads((Path(args.link) / "recipe.json").read_text()).get("tables", {}).get("train", {})
    sheet = save_png(out / "sheet.png", labelled_grid(images, list(states), [f"z_s seed {s}" for s in range(6)],
                                                      row_label_width=150))
    print(f"# bench_e2e — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__}; family "
          f"{args.family}; e2e steps {e2e_train.get('iterations', '?')}, held-out maps data {args.data}\n")
    print("| state | G_n / own normals (mean °) | exemplar L1 | diversity ratio | AE IoU held out | COV / MMD (64 samples) |"
          "\n|---|---|---|---|---|---|")
    for name, m, s in rows:
        n = m["normal_error_deg"]
        empty = f" ({s['empty']} empty)" if s["empty"] else ""
        print(f"| {name} | {n['G_n']['mean']:.1f} / {n['from_coarse_depth']['mean']:.1f} | "
              f"{m['albedo_reconstruction_l1']:.3f} | {m['appearance_diversity_ratio']:.2f} | {s['iou_held_out']:.3f} | "
              f"{s['coverage']:.3f} / {s['mmd']:.5f}{empty} |")
    print(f"\nsheet: {sheet}")


if __name__ == "__main__":
    main()
