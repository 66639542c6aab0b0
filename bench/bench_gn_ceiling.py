# make bench: skip (an experiment over data given as arguments)
"""Experiment: how far G_n can go on a shape prior's reconstructions when it is *taught* (issue 15).

The unpaired recipes leave G_n 1.2–1.5° better than the reconstruction's own normals on held-out
chairs (goal 3°). This script measures the ceiling of the same network at the same budget: G_n of
``--recipe`` (residual or not, as the recipe says) trained alone, with the L1 of L_n^cyc against
the true normals as its only loss (no adversarial term, no cycle through G_depth), Adam with the
recipe's step and β₁, on the training views of the maps cache (``--maps``) with, as its input, one
of:

* ``coarse``: the prior's reconstruction of the same shape and view (``--coarse``: the maps
  cache's ``-coarse`` folder, ``[data] coarse_shapes``), every pixel;
* ``coarse-agree``: the same, the L1 only where both depths agree within 0.03 or both are empty
  (``[model] normal_cycle_agreement``);
* ``real``: the true depth (what ``normal_cycle_depth = "real"`` pairs).

Every ``--every`` steps: ``bench_gn_curve``'s angles (°) to the true normals on held-out shapes
(``--held-out``, ``--coarse-data``), G_n's against the own normals of reconstructions, depth
smoothed by σ = 2 px, and exact depth. One JSON line per arm and step in ``OUT/ceiling.jsonl``
(resumes: arms already finished there are skipped), a Markdown table at the end. ``--model KEY=VALUE``
overrides a ``[model]`` key of the recipe for every arm (``ngf=32``, ``normal_input="depth+normals"``);
the arms are then labelled with it, so one ``--out`` holds both.

    .venv/bin/python bench/bench_gn_ceiling.py --maps outputs/data/maps_cpu --coarse outputs/data/maps_cpu-coarse \\
        --held-out outputs/data/held_out_chair --coarse-data outputs/data/held_out_chair_coarse_enc \\
        [--arms coarse,coarse-agree,real --iterations 1500 --every 250 --out outputs/bench/gn-ceiling]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from bench_gn_curve import normal_errors
from ngp_mi.data.datasets import ReflectanceMapDataset, WithCoarseDepth
from ngp_mi.models import losses
from ngp_mi.models.maps import MapsModel, cameras_of, depth_to_net
from ngp_mi.training.recipe import parse_override, read_tables

ROOT = Path(__file__).resolve().parents[1]
ARMS = {"coarse": ("coarse", 0.0), "coarse-agree": ("coarse", 0.03), "real": ("real", 0.0)}


def train_arm(arm: str, recipe: Path, train_views: WithCoarseDepth, held_out: list[dict], iterations: int,
              every: int, batch_size: int, seed: int, log, model_overrides: tuple[str, ...] = (),
              label: str | None = None) -> None:
    source, agreement = ARMS[arm]
    tables = read_tables(recipe, [f"model.{item}" for item in model_overrides],
                         known=("data", "model", "train", "specular"))
    config = dataclasses.replace(MapsModel.config_from_recipe(tables), normal_cycle_depth=source,
                                 normal_cycle_agreement=agreement, ema=0.0)
    arm = label or arm
    torch.manual_seed(seed)
    model = MapsModel(config)
    optimizer = torch.optim.Adam(model.G_n.parameters(), lr=config.lr, betas=(config.beta1, 0.999))
    loader = DataLoader(train_views, batch_size=batch_size, shuffle=True, drop_last=True,
                        generator=torch.Generator().manual_seed(seed))
    step, start = 0, time.perf_counter()
    while step < iterations:
        for batch in loader:
            model.train()
            depth_in = model.normal_cycle_input(None, batch)
            normal = model.generate_normals(depth_in, cameras_of(batch))
            loss = losses.normal_cycle_loss(normal, batch["normal"], model.normal_cycle_agreement(depth_in, batch))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            if step % every == 0 or step == iterations:
                model.eval()
                row = {"arm": arm, "step": step, "loss": round(loss.item(), 4),
                       "seconds": round(time.perf_counter() - start, 1), **normal_errors(model, held_out)}
                log(row)
            if step == iterations:
                break


def table(rows: list[dict]) -> str:
    steps = sorted({r["step"] for r in rows})
    lines = ["| arm (G_n taught, no GAN) | " + " | ".join(str(s) for s in steps) + " | σ 2 px (last) | exact (last) |",
             "|---" * (len(steps) + 3) + "|"]
    for arm in dict.fromkeys(r["arm"] for r in rows):
        by_step = {r["step"]: r for r in rows if r["arm"] == arm}
        last = by_step[max(by_step)]
        cells = [f"{by_step[s]['recon']['G_n'][0]:.1f}" if s in by_step else "–" for s in steps]
        lines.append(f"| {arm} | " + " | ".join(cells) + f" | {last['smooth2']['G_n'][0]:.1f} | "
                     f"{last['exact']['G_n'][0]:.1f} ({last['exact']['G_n'][1]:.1f}) |")
    own = rows[0]
    lines.append(f"| the depth's own normals | " + " | ".join(f"{own['recon']['own'][0]:.1f}" for _ in steps)
                 + f" | {own['smooth2']['own'][0]:.1f} | {own['exact']['own'][0]:.1f} ({own['exact']['own'][1]:.1f}) |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--maps", required=True, help="render-dataset folder of training maps (depth, normal, mask)")
    parser.add_argument("--coarse", required=True, help="the same views as the prior reconstructs them")
    parser.add_argument("--held-out", required=True, help="render-dataset folder of held-out shapes")
    parser.add_argument("--coarse-data", required=True, help="the held-out views as the prior reconstructs them")
    parser.add_argument("--recipe", default=str(ROOT / "train" / "maps_cpu.toml"), help="whose [model] G_n, lr, β₁")
    parser.add_argument("--arms", default=",".join(ARMS), help=f"from {','.join(ARMS)} (default: all)")
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--every", type=int, default=250)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/bench/gn-ceiling")
    parser.add_argument("--model", action="append", default=[], metavar="KEY=VALUE",
                        help="override a [model] key of the recipe (a TOML value or a bare word, as --set), e.g. ngf=32 or "
                             "normal_input='\"depth+normals\"'; the arms are then logged as ARM KEY=VALUE …")
    args = parser.parse_args()
    for item in args.model:
        try:
            parse_override(f"model.{item}")  # the recipe's --set syntax: a TOML value or a bare word
        except ValueError as error:
            parser.error(f"--model {item!r}: {error}")
    suffix = "".join(f" {item}" for item in args.model)
    arms = args.arms.split(",")
    for arm in arms:
        if arm not in ARMS:
            parser.error(f"--arms: {arm!r} is not one of {', '.join(ARMS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "ceiling.jsonl"
    rows = [json.loads(line) for line in log_path.read_text().splitlines()] if log_path.exists() else []
    finished = {r["arm"] for r in rows if r["step"] == args.iterations}
    labels = {arm: arm + suffix for arm in arms}
    train_views = WithCoarseDepth(ReflectanceMapDataset(args.maps), args.coarse, drop_unpaired=True)
    held_out = list(DataLoader(WithCoarseDepth(ReflectanceMapDataset(args.held_out), args.coarse_data), batch_size=8))

    def log(row: dict) -> None:
        rows.append(row)
        with log_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"{row['arm']} step {row['step']}: G_n on reconstructions {row['recon']['G_n'][0]:.2f}° "
              f"(own {row['recon']['own'][0]:.2f}°), {row['seconds']:.0f} s", flush=True)

    for arm in arms:
        if labels[arm] in finished:
            print(f"{labels[arm]}: done in {log_path}")
            continue
        rows[:] = [r for r in rows if r["arm"] != labels[arm]]  # an unfinished arm starts again
        log_path.write_text("".join(json.dumps(r) + "\n" for r in rows))
        train_arm(arm, Path(args.recipe), train_views, held_out, args.iterations, args.every, args.batch_size,
                  args.seed, log, tuple(args.model), labels[arm])
    print(table(rows))


if __name__ == "__main__":
    main()
