"""``ngp-mi train e2e --config train/e2e_<preset>.toml``: G_shape's decoder fine-tuned with the map
networks' 2-D losses through the differentiable depth projection Π_v.

The paper trains G_shape on its own and notes that NGP "can be linked to a differentiable depth
rendering layer and trained end-to-end" (Sec. 3.2); this is that link. Each step draws
``batch_size`` latents z_s ~ N(0, I), extracts G_shape(z_s) with the iso-surface link (vertices
differentiable in the decoder's weights, :meth:`ngp_mi.models.shape.ShapeModel.differentiable_surface`),
projects each shape into a camera of the paper's view distribution with Π_v's silhouette gradients
(pixel-averaged depth d̄ and coverage c), and hands depth d̄ / c and mask c to the map networks'
step (both cycles and the adversarial terms of L_2D, Sec. 3.3 and App. B). The generators' loss
flows back through the networks into the depth maps, through Π_v into the vertices and through the
iso-surface link into the decoder, which an Adam step at ``decoder_lr`` moves; the discriminators
see detached fakes, as in ``train maps``. G_latent and the encoder stay as trained.

``shape_anchor = λ > 0`` adds λ times the prior's own autoencoder loss on its training shapes to
each decoder step (:class:`ShapeAnchor`), so the 2-D losses move the decoder only where the shape
data lets them; 0 (the default) is the plain link.

``link = false`` is the control at an equal budget: the same shapes, cameras and map-network steps
with the vertices detached, so the decoder never moves (training "separately", on G_shape's depth).

Tables: ``[init]`` (:class:`E2EInit`: the ``train maps`` and ``train shape`` runs to start from),
``[data]`` (the real reflectance maps, :class:`~ngp_mi.training.maps.MapsData`; its depth keys are
unused: the depth comes from G_shape) and ``[train]`` (:class:`E2ETrain`). Outputs under ``out``:
the map networks' checkpoints (``ckpt-*``, a ``train maps`` run for ``evaluate``, ``generate`` and
``export-model``), the shape prior's in ``shape/`` (a ``train shape`` run), ``log.jsonl``,
``images/``. Resumes exactly; runs under ``torchrun`` like ``train maps`` (gradients of the map
networks and of the decoder averaged over the processes).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ngp_mi.camera import ViewDistribution
from ngp_mi.data.views import derived_seed
from ngp_mi.models.maps import MapsModel
from ngp_mi.models.shape import ShapeModel, occupancy_loss
from ngp_mi.render.depth import depth_of_hits, project_depth
from ngp_mi.training import loop
from ngp_mi.training.maps import (MapsData, image_grid, maps_dataset, normal_step_batches, normal_step_source,
                                  prepare_data, require_coarse_pairs)
from ngp_mi.training.recipe import from_table, out_override, positive, read_tables, record
from ngp_mi.training.shape import ae_batch, run_shape_data
from ngp_mi.viz import save_png

TABLES = ("init", "data", "train")


@dataclasses.dataclass(frozen=True)
class E2EInit:
    maps_run: str  # a `train maps` run: the map networks (their newest checkpoint; optimisers start fresh)
    shape_run: str  # a `train shape` run: G_shape


@dataclasses.dataclass(frozen=True)
class E2ETrain:
    iterations: int
    batch_size: int  # shapes per step, one view each
    seed: int = 0
    out: str = "outputs/train/e2e"
    link: bool = True  # false: the control, vertices detached (the decoder never moves)
    decoder_lr: float = 1e-5
    shape_anchor: float = 0.0  # weight of the prior's own occupancy loss at each decoder step (0: off)
    anchor_batch: int = 8  # training shapes of the prior per anchor term
    extract_resolution: int = 32  # marching-cubes grid of G_shape(z_s) per step
    spp: int = 4  # Π_v samples per pixel, and of its silhouette term
    boundary_spp: int = 1
    log_every: int = 10
    image_every: int = 100
    checkpoint_every: int = 100
    device: str = "auto"

    def __post_init__(self) -> None:
        positive(self, "iterations", "batch_size", "extract_resolution", "spp", "boundary_spp", "log_every",
                 "image_every", "checkpoint_every", "anchor_batch")
        if not self.shape_anchor >= 0:
            raise ValueError(f"shape_anchor must be >= 0, got {self.shape_anchor}")
        if not self.decoder_lr > 0:
            raise ValueError(f"decoder_lr must be > 0, got {self.decoder_lr}")


@dataclasses.dataclass(frozen=True)
class E2ERecipe:
    init: E2EInit
    data: MapsData
    train: E2ETrain
    tables: dict[str, Any]

    @classmethod
    def read(cls, path: str | Path, overrides: Sequence[str] = ()) -> "E2ERecipe":
        tables = read_tables(path, overrides, required=TABLES, known=TABLES)
        return cls(*from_table(tables, "init", path, E2EInit), *from_table(tables, "data", path, MapsData),
                   *from_table(tables, "train", path, E2ETrain), tables)


def shape_depth_batch(shape: ShapeModel, batch: int, resolution: int, seed: int, link: bool,
                      train: E2ETrain) -> tuple[dict[str, torch.Tensor], int]:
    """A depth batch drawn from G_shape: ``batch`` latents of ``seed``, each shape projected by Π_v
    (silhouette gradients) into one camera of the paper's distribution. Returns the batch (depth d̄ / c,
    mask c, K, E, NOC bounds; differentiable in the decoder's weights when ``link``) and how many
    latents gave an empty shape and were replaced by the next."""
    generator = torch.Generator().manual_seed(seed)
    items: list[dict[str, torch.Tensor]] = []
    empty = 0
    while len(items) < batch:
        if empty > 4 * batch:
            raise RuntimeError(f"train e2e: {empty} latents in a row gave an empty shape; G_shape has collapsed")
        z = torch.randn(shape.config.z_dim, generator=generator)
        surface = shape.differentiable_surface(z, resolution=train.extract_resolution)
        if surface is None:
            empty += 1
            continue
        vertices, faces = surface
        vertices = vertices.float() if link else vertices.detach().float()
        camera = ViewDistribution().sample(1, seed=derived_seed(seed, len(items)), resolution=resolution)[0]
        maps = project_depth(vertices, faces, camera, silhouette_grad=True, spp=train.spp,
                             boundary_spp=train.boundary_spp, seed=seed + len(items))
        corners = vertices.detach().cpu().numpy()
        items.append({"depth": depth_of_hits(maps.depth, maps.mask)[0], "mask": maps.mask[0],
                      "K": torch.tensor(camera.K, dtype=torch.float32), "E": torch.tensor(camera.E, dtype=torch.float32),
                      "bounds": torch.tensor(np.stack([corners.min(0), corners.max(0)]), dtype=torch.float32)})
    return {key: torch.stack([item[key] for item in items]) for key in items[0]}, empty


class ShapeAnchor:
    """The anchor term λ_anchor · L_occ: the autoencoder's occupancy loss (IM-NET Eq. 2,
    :func:`~ngp_mi.models.shape.occupancy_loss`) of decoder(encoder(v), p) on the prior's own
    training shapes, added to L_2D's gradient at each decoder step.

    Without it nothing in the link ties the decoder to the shape data, and the 2-D losses pull the
    prior off its shapes (``bench/RESULTS.md``, bench_e2e). The encoder stays fixed, so the codes G_latent
    learned to generate keep their meaning; points are drawn at the prior's finest stage."""

    def __init__(self, shape_run: str | Path, weight: float, batch: int, seed: int, rank: int, world: int,
                 device: torch.device):
        recipe, self.data, _ = run_shape_data(shape_run)
        self.weight, self.device = weight, device
        self.resolution = recipe.train.stages[-1][0]
        self.points = recipe.train.points_per_shape
        self.batches = loop.SeededBatches(self.data, batch, seed, rank, world, repeat=True)

    def backward(self, shape: ShapeModel, step: int) -> float:
        """Adds λ ∇L_occ of ``step``'s batch to the decoder's gradients; returns L_occ."""
        voxels, points, occ = ae_batch(self.data, self.batches, self.resolution, step, self.points, self.device)
        with torch.no_grad():
            codes = shape.encoder(voxels)
        loss = occupancy_loss(shape.decoder(points, codes), occ)
        (self.weight * loss).backward()
        return loss.item()


def _decoder_step(shape: ShapeModel, world: int) -> bool:
    """The decoder's Adam step on the gradient left in it (L_2D's, plus the anchor's when on); False
    (and no step) when not finite."""
    parameters = list(shape.decoder.parameters())
    for p in parameters:
        if p.grad is None:  # every rank must reduce the same tensors
            p.grad = torch.zeros_like(p)
    if world > 1:
        loop.average_gradients(parameters)
    if not all(torch.isfinite(p.grad).all() for p in parameters):
        return False
    shape.opt_ae.step()
    return True


def train_e2e(config_path: str | Path, log=print, out: str | Path | None = None, overrides: Sequence[str] = ()) -> Path:
    """Train (or resume) as the recipe says; ``out`` replaces ``[train] out``. Returns the output folder."""
    overrides = [*overrides, *([out_override(out)] if out else [])]
    recipe = E2ERecipe.read(config_path, overrides)
    train = recipe.train
    device, rank, world = loop.start_processes(train.device)
    out = Path(train.out)
    model = MapsModel.from_run(recipe.init.maps_run, device)
    shape = ShapeModel.from_run(recipe.init.shape_run, device)
    for run, loaded in ((recipe.init.maps_run, model), (recipe.init.shape_run, shape)):
        if loaded is None:
            raise ValueError(f"[init] {run}: no readable checkpoint (train it first)")
    # G_shape's own shapes are the depth to decorate; coarse reconstructions only pair the real maps
    # for a G_n trained with normal_cycle_depth (or normal_steps_depth) = "coarse".
    data = recipe.data if model.config.reads_coarse_pairs else dataclasses.replace(recipe.data,
                                                                                               coarse_shapes=None)
    require_coarse_pairs(model.config, data)  # before any rendering
    maps_root, coarse_root = prepare_data(data, rank)
    maps_batches = loop.SeededBatches(maps_dataset(model.config, data, maps_root, coarse_root,
                                                   log if rank == 0 else None),
                                      train.batch_size, train.seed, rank, world)
    normal_batches = normal_step_source(maps_batches.dataset, train.batch_size, train.seed, rank, world)
    model.train()
    for network in (shape.encoder, shape.G_latent, shape.D_latent):
        network.requires_grad_(False)
    step, resumed_from = loop.resume(out, [model])
    shape_step, _ = loop.resume(out / "shape", [shape])
    for group in shape.opt_ae.param_groups:
        group["lr"] = train.decoder_lr
    if rank == 0:
        if resumed_from is not None:
            log(f"train e2e: resuming from {resumed_from} (step {step})")
            if shape_step != step:
                log(f"train e2e: the shape prior's newest checkpoint is of step {shape_step}, the maps' of {step}")
        log(f"train e2e: {world} process(es) on {device}, link {'on' if train.link else 'off (control)'}")
        out.mkdir(parents=True, exist_ok=True)
        record(out, config_path, overrides, recipe.tables)
    if world > 1:
        model.gradient_hook = loop.average_gradients
    anchor = (ShapeAnchor(recipe.init.shape_run, train.shape_anchor, train.anchor_batch, train.seed, rank, world, device)
              if train.link and train.shape_anchor > 0 else None)
    if anchor is not None and rank == 0:
        log(f"train e2e: anchored to {len(anchor.data)} training shapes of {recipe.init.shape_run} "
            f"(weight {train.shape_anchor})")

    log_file = loop.JsonLog(out, step) if rank == 0 else None
    bar = tqdm(total=train.iterations, initial=step, unit="it", disable=rank != 0, desc="train e2e")
    start, first, empty, skipped = time.perf_counter(), step, 0, 0
    while step < train.iterations:
        loop.reseed(train.seed, step, world, rank)
        shape.opt_ae.zero_grad(set_to_none=True)
        depth_batch, empty_now = shape_depth_batch(shape, train.batch_size, recipe.data.resolution,
                                                   derived_seed(train.seed, step * world + rank), train.link, train)
        empty += empty_now
        losses = model.optimize(loop.to_device(depth_batch, device), loop.to_device(maps_batches(step), device),
                                normal_step_batches(normal_batches, model.config, step, device))
        if anchor is not None:
            losses["anchor_occupancy"] = anchor.backward(shape, step)
        if train.link and not _decoder_step(shape, world):
            skipped += 1
            log(f"train e2e: step {step}: a non-finite gradient in the decoder; its step skipped")
        step += 1
        bar.update(1)
        if log_file is None:
            continue
        last = step == train.iterations
        if step % train.log_every == 0 or last:
            log_file.write({"step": step, "time": round(time.perf_counter() - start, 3),
                            "it_per_s": round((step - first) / (time.perf_counter() - start), 3), "world": world,
                            "empty_shapes": empty, "skipped_decoder_steps": skipped, **losses})
        if step % train.image_every == 0 or last:
            save_png(out / "images" / f"step-{step:08d}.png", image_grid(model.visuals))
        if step % train.checkpoint_every == 0 or last:
            loop.save(out / "shape", step, [shape], {"e2e": recipe.tables})
            loop.save(out, step, [model], recipe.tables)  # last: the maps' step is the run's step
    bar.close()
    if world > 1:
        loop.check_in_sync([model, shape], log_file, step, world)
    return out
