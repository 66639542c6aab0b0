"""Evaluation of trained map networks (issue "reflectance-map networks", paper Sec. 4).

* **Normal quality, paired.** For held-out views, a *coarse* depth is fed to G_n and the mean
  angular error of its normals against the detailed mesh's ground-truth normal map is measured,
  next to normals computed from the same coarse depth (the paper's "NGP w/o G_n"). Until the shape
  autoencoder exists, the coarse depth is the ground-truth depth smoothed by a masked Gaussian
  (``coarse_sigma`` pixels), which removes detail the way a coarse reconstruction does.
* **Albedo.** Exemplar fidelity: ``G_da(NOC(d), N, μ(E_da(I_da)))`` against ``I_da`` (masked L1),
  beside the best single colour per view (the per-channel median on the object: what an albedo
  without parts would score); diversity: mean pairwise L1 between G_da outputs for different
  z_da ~ N(0, I) of one view, and the appearance-diversity ratio — the spread (std over images,
  averaged over RGB) of the mean on-object colour of G_da's samples ÷ the same over the real
  albedo maps (1: the samples vary as much as the real objects do).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader

from ngp_mi.atomic import write_json, write_text
from ngp_mi.data.datasets import ReflectanceMapDataset, WithCoarseDepth
from ngp_mi.models import pretrained
from ngp_mi.models.maps import cameras_of, depth_to_net
from ngp_mi.render.from_depth import normals_from_depth, smooth_depth
from ngp_mi.viz import chw_to_uint8, contact_sheet, save_png


def angular_error_deg(predicted: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel angle (degrees) between normal maps (N, 3, H, W), over ``mask`` > 0 (flattened)."""
    p = predicted / predicted.norm(dim=1, keepdim=True).clamp_min(1e-8)
    t = truth / truth.norm(dim=1, keepdim=True).clamp_min(1e-8)
    cosine = (p * t).sum(1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cosine))[mask[:, 0] > 0]


def l1_on_object(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel L1 (mean over channels) between maps (N, C, H, W), over ``mask`` > 0 (flattened)."""
    return (a - b).abs().mean(1)[mask[:, 0] > 0]


def mean_colour(albedo: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(N, 3): each image's mean colour on the object."""
    return (albedo * mask).sum((2, 3)) / mask.sum((2, 3)).clamp_min(1)


def single_colour_l1(albedo: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel L1 (flattened over the objects' pixels) of the best single colour of each view —
    the per-channel median of its object, which minimises L1 — against the albedo."""
    errors = []
    for image, m in zip(albedo, mask[:, 0] > 0):
        if m.any():
            pixels = image[:, m]  # (3, P)
            errors.append((pixels - pixels.median(1, keepdim=True).values).abs().mean(0))
    return torch.cat(errors) if errors else torch.zeros(0)


@torch.no_grad()
def evaluate_maps(run: str | Path, data: str | Path, out: str | Path, coarse_sigma: float = 2.0,
                  latent_samples: int = 4, batch_size: int = 8, seed: int = 0,
                  coarse_data: str | Path | None = None) -> dict[str, Any]:
    """Evaluate a run's newest checkpoint, or a model folder / shipped name (``chair``), on a held-out
    ``render-dataset`` folder; writes ``eval.json`` / ``eval.md``.

    The coarse depth is ``coarse_data`` — a folder of the same shapes and views rendered from their
    autoencoder reconstructions (``render-dataset --coarse-shapes``), paired by (shape id, view) —
    or, without it, the ground-truth depth smoothed by ``coarse_sigma`` pixels. Normal errors count
    the pixels on both the detailed and the coarse object.
    """
    model, checkpoint = pretrained.load_map_networks(run)
    torch.manual_seed(seed)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    errors_gn, errors_depth, fidelity, flat, diversity, overlap = [], [], [], [], [], []
    sample_colours, real_colours = [], []
    views = ReflectanceMapDataset(data)
    sheet = None
    for batch in DataLoader(WithCoarseDepth(views, coarse_data) if coarse_data else views, batch_size=batch_size):
        mask, depth = batch["mask"], batch["depth"]
        if coarse_data is None:
            coarse, coarse_mask = smooth_depth(depth, mask, coarse_sigma), mask
        else:
            coarse, coarse_mask = batch["coarse_depth"], batch["coarse_mask"]
        both = mask * coarse_mask
        overlap.append(both.sum() / mask.sum().clamp_min(1))
        cameras = cameras_of(batch)
        normal_gn = model.generate_normals(depth_to_net(coarse, coarse_mask), cameras)
        normal_depth = normals_from_depth(coarse, coarse_mask, cameras)
        errors_gn.append(angular_error_deg(normal_gn, batch["normal"], both))
        errors_depth.append(angular_error_deg(normal_depth, batch["normal"], both))

        condition = model.albedo_condition(model.noc(depth, mask, batch), batch["normal"])
        mu, _ = model.E_da(2 * batch["albedo"] - 1, mask)
        reconstruction = (model.G_da(condition, mu) + 1) / 2
        fidelity.append(l1_on_object(reconstruction, batch["albedo"], mask))
        flat.append(single_colour_l1(batch["albedo"], mask))
        samples = [(model.G_da(condition, torch.randn_like(mu)) + 1) / 2 for _ in range(latent_samples)]
        real_colours.append(mean_colour(batch["albedo"], mask))
        sample_colours += [mean_colour(sample, mask) for sample in samples]
        pairs = [l1_on_object(a, b, mask).mean() for i, a in enumerate(samples) for b in samples[i + 1:]]
        diversity.append(torch.stack(pairs).mean())
        if sheet is None:
            tiles = [batch["normal"][0], normal_depth[0], normal_gn[0], batch["albedo"][0] * 2 - 1,
                     reconstruction[0] * 2 - 1, samples[0][0] * 2 - 1, samples[-1][0] * 2 - 1]
            images = [chw_to_uint8((t + 1) / 2, srgb=False) for t in tiles]
            sheet = contact_sheet(images, ["N gt", "N from coarse d", "G_n(coarse d)", "albedo gt", "E_da->G_da",
                                           "z sample", "z sample"], columns=len(images))
    gn, from_depth = torch.cat(errors_gn), torch.cat(errors_depth)
    result = {
        "checkpoint": checkpoint, "data": str(data),
        "coarse": str(coarse_data) if coarse_data else f"smoothed, sigma {coarse_sigma} px",
        "coarse_overlap": torch.stack(overlap).mean().item(),
        "normal_error_deg": {"G_n": {"mean": gn.mean().item(), "median": gn.median().item()},
                             "from_coarse_depth": {"mean": from_depth.mean().item(), "median": from_depth.median().item()}},
        "albedo_reconstruction_l1": torch.cat(fidelity).mean().item(),
        "albedo_diversity_l1": torch.stack(diversity).mean().item(),
        "albedo_single_colour_l1": torch.cat(flat).mean().item(),
        "appearance_diversity_ratio": (torch.cat(sample_colours).std(0).mean()
                                       / torch.cat(real_colours).std(0).mean().clamp_min(1e-8)).item(),
    }
    write_json(out / "eval.json", result)
    n = result["normal_error_deg"]
    coarse_text = (f"the shapes' autoencoder reconstructions (`{coarse_data}`)" if coarse_data else
                   f"the ground truth smoothed by a masked Gaussian of σ = {coarse_sigma} px")
    write_text(out / "eval.md", 
        f"# Map networks: {result['checkpoint']}\n\nHeld-out data: `{data}`; coarse depth: {coarse_text} (it covers "
        f"{100 * result['coarse_overlap']:.1f} % of the detailed object's pixels; errors over the pixels of both)."
        f"\n\n| normals from the coarse depth | mean error ° | median ° |\n"
        f"|---|---|---|\n| G_n (NGP) | {n['G_n']['mean']:.2f} | {n['G_n']['median']:.2f} |\n"
        f"| finite differences (NGP w/o G_n) | {n['from_coarse_depth']['mean']:.2f} | {n['from_coarse_depth']['median']:.2f} |\n\n"
        f"Albedo: E_da → G_da reconstruction L1 {result['albedo_reconstruction_l1']:.4f} (the best single colour "
        f"per view: {result['albedo_single_colour_l1']:.4f}); spread over z_da (mean pairwise L1 of {latent_samples} "
        f"samples) {result['albedo_diversity_l1']:.4f}; appearance-diversity ratio "
        f"{result['appearance_diversity_ratio']:.3f}.\n\n![maps](eval.png)\n")
    if sheet is not None:
        save_png(out / "eval.png", sheet)
    return result
