# make bench: skip (an experiment over trained runs or data given as arguments)
"""G_n against the depth's own normals on three coarse inputs, per checkpoint (issue 15's G_n rows).

For every checkpoint of each ``train maps`` run: the mean / median angle (°) to the true
normals of held-out shapes (``--held-out``, a ``render-dataset`` folder) of G_n's normals and of the
finite-difference normals of the same depth (NGP w/o G_n), with three depths as input —

* ``recon``: a shape prior's reconstructions of the same shapes and views (``--coarse-data``,
  ``render-dataset --coarse-shapes``), on the pixels both objects cover;
* ``smooth2``: the true depth smoothed by σ = 2 px (``evaluate maps``' default coarse depth);
* ``exact``: the true depth (where the depth's own normals are right but at creases and edges).

Each call appends one line per run and checkpoint not yet there to ``--log`` (JSONL), so calls
during training (checkpoints are pruned to the newest three) build a curve; ``--table`` prints the
log as Markdown; ``--sheets`` writes ``gn_sheet.png`` beside each run (true normals, the
reconstruction's own, G_n's on it and on the exact depth, four views); ``--edges`` prints where the
reconstructions' own normals are wrong (silhouettes against the inside of surfaces). ``evaluate maps`` reports
the same angles for the newest checkpoint with the albedo figures; this script is G_n only, in
seconds per checkpoint.

    .venv/bin/python bench/bench_gn_curve.py --held-out outputs/data/held_out_chair \\
        --coarse-data outputs/data/held_out_chair_coarse_enc --log outputs/bench/gn_curve.jsonl RUN [RUN …]
    .venv/bin/python bench/bench_gn_curve.py --log outputs/bench/gn_curve.jsonl --table
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from ngp_mi.data.datasets import ReflectanceMapDataset, WithCoarseDepth
from ngp_mi.eval.maps_eval import angular_error_deg
from ngp_mi.models.checkpoint import list_checkpoints, load_weights, read_weights
from ngp_mi.models.maps import MapsModel, cameras_of, depth_to_net
from ngp_mi.render.from_depth import normals_from_depth, smooth_depth
from ngp_mi.viz import chw_to_uint8, contact_sheet, save_png

INPUTS = ("recon", "smooth2", "exact")


def coarse_inputs(batch: dict) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """(depth, mask) of each input for a batch of :class:`WithCoarseDepth` views."""
    return {"recon": (batch["coarse_depth"], batch["coarse_mask"]),
            "smooth2": (smooth_depth(batch["depth"], batch["mask"], 2.0), batch["mask"]),
            "exact": (batch["depth"], batch["mask"])}


@torch.no_grad()
def normal_errors(model: MapsModel, batches: list[dict]) -> dict:
    """{input: {"G_n": [mean, median], "own": [mean, median]}} of ``model``'s G_n."""
    errors: dict[str, dict[str, list[torch.Tensor]]] = {k: {"G_n": [], "own": []} for k in INPUTS}
    for batch in batches:
        cameras = cameras_of(batch)
        for name, (depth, mask) in coarse_inputs(batch).items():
            both = batch["mask"] * mask
            errors[name]["G_n"].append(angular_error_deg(model.generate_normals(depth_to_net(depth, mask), cameras),
                                                         batch["normal"], both))
            own = normals_from_depth(depth, mask, cameras)
            errors[name]["own"].append(angular_error_deg(own, batch["normal"], both))
    return {name: {who: [round(torch.cat(e).mean().item(), 2), round(torch.cat(e).median().item(), 2)]
                   for who, e in by.items()} for name, by in errors.items()}


@torch.no_grad()
def normal_sheet(model: MapsModel, batch: dict, rows: int = 4) -> np.ndarray:
    """For the batch's first ``rows`` views: the true normals, the reconstruction's own, G_n's on the
    reconstruction and G_n's on the exact depth (4× nearest-neighbour enlarged)."""
    cameras = cameras_of(batch)
    depth, mask = batch["coarse_depth"], batch["coarse_mask"]
    columns = {"true": batch["normal"], "own (recon)": normals_from_depth(depth, mask, cameras),
               "G_n (recon)": model.generate_normals(depth_to_net(depth, mask), cameras),
               "G_n (exact)": model.generate_normals(depth_to_net(batch["depth"], batch["mask"]), cameras)}
    tiles, labels = [], []
    for i in range(min(rows, len(batch["depth"]))):
        for label, normals in columns.items():
            image = chw_to_uint8((normals[i] + 1) / 2, srgb=False)
            tiles.append(np.kron(image, np.ones((4, 4, 1), np.uint8)))
            labels.append(label)
    return contact_sheet(tiles, labels, columns=len(columns))


@torch.no_grad()
def edge_split(batches: list[dict], agree: float = 0.03) -> str:
    """Where the reconstructions' own normals are wrong: their error (mean, median °) on the pixels
    both objects cover, split into those within one pixel of either object's silhouette and the
    rest, the rest again by whether the two surfaces lie within ``agree``; the exact depth's own
    normals beside them. A Markdown table."""
    parts: dict[str, dict[str, list[torch.Tensor]]] = {}
    def near_off(mask: torch.Tensor) -> torch.Tensor:  # 1 within one pixel of the background
        return torch.nn.functional.max_pool2d(1 - mask, 3, 1, 1)

    for batch in batches:
        cameras = cameras_of(batch)
        both = batch["mask"] * batch["coarse_mask"]
        edge = torch.maximum(near_off(batch["mask"]), near_off(batch["coarse_mask"])) * both
        inside = both - edge
        agrees = ((batch["coarse_depth"] - batch["depth"]).abs() < agree).float()
        own = {"recon": normals_from_depth(batch["coarse_depth"], batch["coarse_mask"], cameras),
               "exact": normals_from_depth(batch["depth"], batch["mask"], cameras)}
        for name, pixels in (("all", both), ("silhouette", edge), ("inside", inside),
                             (f"inside, surfaces within {agree}", inside * agrees),
                             ("inside, surfaces apart", inside * (1 - agrees))):
            for depth, normals in own.items():
                parts.setdefault(name, {}).setdefault(depth, []).append(
                    angular_error_deg(normals, batch["normal"], pixels))
    total = torch.cat(parts["all"]["recon"]).numel()
    lines = ["| pixels | share | own normals, reconstructions (mean, median °) | own normals, exact depth |",
             "|---|---|---|---|"]
    for name, by in parts.items():
        recon, exact = torch.cat(by["recon"]), torch.cat(by["exact"])
        lines.append(f"| {name} | {recon.numel() / total:.0%} | {recon.mean():.1f} ({recon.median():.1f}) | "
                     f"{exact.mean():.1f} ({exact.median():.1f}) |")
    return "\n".join(lines)


def table(log: Path) -> str:
    rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    lines = ["| run | step | " + " | ".join(f"{k}: G_n / own (mean, median °)" for k in INPUTS) + " |",
             "|---|---|" + "---|" * len(INPUTS)]
    for r in sorted(rows, key=lambda r: (r["run"], r["step"])):
        cells = [f"{r[k]['G_n'][0]:.1f} ({r[k]['G_n'][1]:.1f}) / {r[k]['own'][0]:.1f} ({r[k]['own'][1]:.1f})"
                 for k in INPUTS]
        lines.append(f"| {Path(r['run']).parent.name} | {r['step']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", help="train maps runs (each of their checkpoints)")
    parser.add_argument("--held-out", help="render-dataset folder of held-out shapes (depth, normal, mask)")
    parser.add_argument("--coarse-data", help="the same shapes and views, render-dataset --coarse-shapes")
    parser.add_argument("--log", help="JSONL the figures are appended to (needed with runs or --table)")
    parser.add_argument("--table", action="store_true", help="print the log as a Markdown table")
    parser.add_argument("--edges", action="store_true",
                        help="print where the reconstructions' own normals are wrong: silhouettes against inside")
    parser.add_argument("--sheets", action="store_true",
                        help="write RUN/../gn_sheet.png: true, own and G_n's normals of 4 views (newest checkpoint)")
    args = parser.parse_args()
    if (args.runs or args.table) and not args.log:
        parser.error("runs and --table need --log")
    if (args.runs or args.edges) and not (args.held_out and args.coarse_data):
        parser.error("runs and --edges need --held-out and --coarse-data")
    log = Path(args.log) if args.log else None
    batches = list(DataLoader(WithCoarseDepth(ReflectanceMapDataset(args.held_out), args.coarse_data), batch_size=8)) \
        if args.runs or args.edges else []
    if args.edges:
        print(edge_split(batches))
    if args.runs:
        done = {(r["run"], r["step"]) for r in map(json.loads, log.read_text().splitlines())} if log.exists() else set()
        log.parent.mkdir(parents=True, exist_ok=True)
        for run in map(Path, args.runs):
            model = MapsModel.from_run(run)  # the newest checkpoint; each one's weights below
            if args.sheets:
                save_png(run.parent / "gn_sheet.png", normal_sheet(model, batches[0]))
            for checkpoint in list_checkpoints(run):
                step = int(checkpoint.name.split("-")[-1])
                if (str(run), step) in done:
                    continue
                load_weights(model.networks(), read_weights(checkpoint), checkpoint)
                row = {"run": str(run), "step": step, **normal_errors(model, batches)}
                with log.open("a") as f:
                    f.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)
    if args.table:
        print(table(log))


if __name__ == "__main__":
    main()
