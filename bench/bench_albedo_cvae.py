# make bench: skip (an experiment over trained runs or data given as arguments)
"""Diagnosis: why an exemplar through E_da → G_da comes back as the wrong colours (issue 15).

The conditional-VAE path of the albedo branch alone — E_da(I_da) = (μ, log σ²), z = μ + σ ε,
Î_da = G_da(NOC, N, z), trained on ``λ_da ‖Î_da − I_da‖₁ + λ_kl KL`` (App. B's weights, 25 and
0.001), no discriminators, no other networks — on the training maps, then the exemplar L1 on the
object of held-out views (``evaluate maps``' figure) at a few checkpoints. Taking the GAN and the
other cycles out shows what the two networks can learn at this budget on their own: if this path
cannot reconstruct part colours, no loss balance of the full model will.

Variants, one change each against the ``cpu`` recipe's G_da (FiLM) and E_da (mean pooling):

* ``masked`` — E_da pools over the object (``encoder_pool = "masked"``);
* ``palette`` — G_da as part regions × colours of z (``albedo_head = "palette"``);
* ``palette+masked`` — both;
* ``palette+parts`` — the palette with E_da from the colours of the exemplar's soft parts
  (``encoder_pool = "parts"``);
* ``palette(mask)+masked``, ``palette(mask)+parts`` — the same with the palette's background taken
  from the NOC's mask (``palette_background = "mask"``) instead of a softmax slot;
* ``deterministic`` — z = μ (no sampling; isolates the KL / noise);
* ``oracle`` — G_da gets the true albedo in place of the normals: the identity is in reach, so its
  error bounds how fast the image head can learn absolute colour at all.

    .venv/bin/python bench/bench_albedo_cvae.py --train outputs/data/maps_cpu \\
        --held-out outputs/data/held_out_chair [--steps 900 --every 300 --out outputs/bench/albedo_cvae]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from ngp_mi.atomic import write_json
from ngp_mi.data.datasets import ReflectanceMapDataset
from ngp_mi.eval.maps_eval import l1_on_object, single_colour_l1
from ngp_mi.models import losses
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.nets.networks import PaletteGenerator, define_E, define_G, define_palette_G
from ngp_mi.viz import chw_to_uint8, labelled_grid, save_png

REGION_COLOURS = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1],
                               [1, 1, 1], [0.5, 0.5, 0.5]])

VARIANTS = {
    "baseline": {},
    "masked": {"pool": "masked"},
    "palette": {"head": "palette"},
    "palette+masked": {"head": "palette", "pool": "masked"},
    "palette+parts": {"head": "palette", "pool": "parts"},
    "palette(mask)+masked": {"head": "palette", "pool": "masked", "background": "mask"},
    "palette(mask)+parts": {"head": "palette", "pool": "parts", "background": "mask"},
    "deterministic": {"deterministic": True},
    "oracle": {"oracle": True},
}


def condition(batch: dict, oracle: bool) -> torch.Tensor:
    """G_da's input: NOC of the true depth and the normals (the oracle: the albedo itself instead)."""
    noc = MapsModel.noc(batch["depth"], batch["mask"], batch)
    return torch.cat([noc, 2 * batch["albedo"] - 1 if oracle else batch["normal"]], 1)


@torch.no_grad()
def exemplar_l1(G, E, held_out: list[dict], oracle: bool) -> float:
    errors = []
    for batch in held_out:
        mask = batch["mask"]
        mu, _ = E(2 * batch["albedo"] - 1, mask)
        reconstruction = (G(condition(batch, oracle), mu) + 1) / 2
        errors.append(l1_on_object(reconstruction, batch["albedo"], mask))
    return torch.cat(errors).mean().item()


@torch.no_grad()
def save_sheet(G, E, batch: dict, oracle: bool, path: Path, views: int = 8) -> None:
    """Exemplars, their reconstructions and (for the palette) each pixel's strongest region
    (black: the background) of the first ``views`` held-out views."""
    mu, _ = E(2 * batch["albedo"] - 1, batch["mask"])
    x = condition(batch, oracle)
    rows = [[chw_to_uint8(a) for a in batch["albedo"][:views]],
            [chw_to_uint8(a) for a in (G(x, mu)[:views] + 1) / 2]]
    labels = ["exemplar", "E_da → G_da"]
    if isinstance(G, PaletteGenerator):
        regions = REGION_COLOURS[G.weights(x, mu).argmax(1) % len(REGION_COLOURS)].permute(0, 3, 1, 2)
        rows.append([chw_to_uint8(r, srgb=False) for r in regions[:views]])
        labels.append("regions")
    save_png(path, labelled_grid(rows, labels, [f"view {k}" for k in range(len(rows[0]))]))


def run_variant(name: str, args: argparse.Namespace, held_out: list[dict]) -> dict:
    spec, config = VARIANTS[name], MapsConfig()
    saved = Path(args.out) / name / "result.json"
    budget = {"steps": args.steps, "every": args.every, "seed": args.seed, "lr": args.lr, "parts": args.parts}
    if saved.exists() and (result := json.loads(saved.read_text())).get("budget") == budget:
        return result
    torch.manual_seed(args.seed)
    if spec.get("head") == "palette":
        G = define_palette_G(6, args.ngf, args.blocks, config.latent_dim, args.parts, spec.get("background", "slot"))
    else:
        G = define_G(6, 3, args.ngf, args.blocks, latent_dim=config.latent_dim, latent_mode="film")
    E = define_E(3, config.latent_dim, args.ngf, pool=spec.get("pool", "mean"), parts=args.parts)
    optimizer = torch.optim.Adam([*G.parameters(), *E.parameters()], lr=args.lr, betas=(0.5, 0.999))
    loader = DataLoader(ReflectanceMapDataset(args.train), batch_size=8, shuffle=True, drop_last=True,
                        generator=torch.Generator().manual_seed(args.seed))
    curve, step, began = [], 0, time.perf_counter()
    while step < args.steps:
        for batch in loader:
            target = 2 * batch["albedo"] - 1
            mu, logvar = E(target, batch["mask"])
            z = mu if spec.get("deterministic") else mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
            loss = (losses.LAMBDAS["da"] * (G(condition(batch, spec.get("oracle", False)), z) - target).abs().mean()
                    + losses.LAMBDAS["kl"] * losses.kl_loss(mu, logvar))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            if step % args.every == 0 or step == args.steps:
                curve.append((step, exemplar_l1(G, E, held_out, spec.get("oracle", False))))
                rate = step / (time.perf_counter() - began)
                print(f"  {name}: step {step}/{args.steps}, exemplar L1 {curve[-1][1]:.3f}, {rate:.1f} it/s, "
                      f"ETA {(args.steps - step) / rate / 60:.1f} min", flush=True)
            if step == args.steps:
                break
    save_sheet(G, E, held_out[0], spec.get("oracle", False), saved.parent / "sheet.png")
    result = {"variant": name, "budget": budget, "curve": curve, "seconds": time.perf_counter() - began}
    write_json(saved, result)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", required=True, help="render-dataset folder to train on")
    parser.add_argument("--held-out", required=True, help="render-dataset folder of held-out shapes")
    parser.add_argument("--variant", action="append", choices=sorted(VARIANTS), help="default: all")
    parser.add_argument("--steps", type=int, default=900)
    parser.add_argument("--every", type=int, default=300)
    parser.add_argument("--lr", type=float, default=4e-4)
    parser.add_argument("--parts", type=int, default=MapsConfig().albedo_parts, help="the palette's regions")
    parser.add_argument("--ngf", type=int, default=24)
    parser.add_argument("--blocks", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/bench/albedo_cvae")
    args = parser.parse_args()
    held_out = list(DataLoader(ReflectanceMapDataset(args.held_out), batch_size=16))
    flat = torch.cat([single_colour_l1(b["albedo"], b["mask"]) for b in held_out]).mean().item()
    results = [run_variant(name, args, held_out) for name in args.variant or VARIANTS]
    steps = [s for s, _ in results[0]["curve"]]
    print(f"\n# bench_albedo_cvae — {time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads); lr {args.lr}, batch 8, seed {args.seed}, {args.parts} palette parts; "
          f"held-out {args.held_out}; "
          f"best single colour per view {flat:.3f}\n")
    print("| variant | " + " | ".join(f"exemplar L1 @{s}" for s in steps) + " | s / step |")
    print("|---|" + "---|" * (len(steps) + 1))
    for r in results:
        print(f"| {r['variant']} | " + " | ".join(f"{l1:.3f}" for _, l1 in r["curve"])
              + f" | {r['seconds'] / r['budget']['steps']:.2f} |")


if __name__ == "__main__":
    main()
