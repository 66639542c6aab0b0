"""``ngp-mi train shape --config train/shape_<preset>.toml``: the IM-NET autoencoder, then the latent GAN.

The recipe (TOML; :mod:`ngp_mi.training.recipe`) has three tables:

* ``[data]`` — the fields of :class:`~ngp_mi.data.shapes.ShapeDataConfig` (``source``, ``num_shapes``,
  ``voxel_resolution``, ``resolutions``, ``points``, …) and of :class:`ShapeCache`: ``cache_dir``
  where the shape data is built (and reused), ``workers`` (processes that build it), and
  ``held_out``: the last shapes, kept out of training for the IoU metric.
* ``[model]`` — fields of :class:`~ngp_mi.models.shape.ShapeConfig`.
* ``[train]`` (:class:`ShapeTrain`) — ``stages`` (a list of ``[resolution, iterations]`` of the
  autoencoder, IM-NET's progressive 16³ → 32³ → 64³), ``gan_iterations``, batch sizes, seed,
  output folder, logging and checkpoint periods, device, and the sample metrics' size;
  ``encoder_for`` (a model folder or shipped name) keeps that prior's decoder and G_latent and
  trains an encoder for them alone (priors exported without one cannot reconstruct shapes).

One step counter runs through both phases (autoencoder steps first). Outputs under ``out``:
``recipe.json``, ``log.jsonl`` (losses; metrics records), ``metrics.json`` (autoencoder IoU on
held-out and training shapes at the end of phase 1; coverage / MMD of generated shapes at the end,
next to the same metrics of the held-out real shapes as a reference), ``ckpt-*``. Runs resume
exactly (:mod:`ngp_mi.training.loop`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ngp_mi.atomic import write_json
from ngp_mi.data.shapes import ShapeDataConfig, ShapeDataset, build_shape_dataset
from ngp_mi.eval.shape_metrics import chamfer_matrix, coverage_mmd
from ngp_mi.geometry.occupancy import surface_samples, voxel_iou
from ngp_mi.models import pretrained
from ngp_mi.models.shape import ShapeConfig, ShapeModel
from ngp_mi.training import loop
from ngp_mi.training.recipe import from_table, out_override, positive, read_tables, record, training_device


@dataclasses.dataclass(frozen=True)
class ShapeCache:
    cache_dir: str = "outputs/data/shape"
    held_out: int = 0  # the last shapes: not trained on, scored by the autoencoder IoU
    workers: int = 1   # processes that build the shape data

    def __post_init__(self) -> None:
        positive(self, "held_out", minimum=0)
        positive(self, "workers")


@dataclasses.dataclass(frozen=True)
class ShapeTrain:
    stages: tuple[tuple[int, int], ...]  # (resolution, iterations) of the autoencoder, in order
    gan_iterations: int = 0
    batch_size: int = 16
    points_per_shape: int = 0  # 0: all points of the stage's resolution
    gan_batch_size: int = 64
    seed: int = 0
    out: str = "outputs/train/shape"
    log_every: int = 10
    checkpoint_every: int = 500
    device: str = "auto"
    eval_samples: int = 16
    eval_resolution: int = 64
    # A shipped model's name or a model folder: keep its G_shape (decoder and G_latent, fixed) and train
    # only an encoder for it, so a prior exported without one can reconstruct given shapes. "": off.
    encoder_for: str = ""

    def __post_init__(self) -> None:
        if self.encoder_for and self.gan_iterations:
            raise ValueError(f"[train] encoder_for = {self.encoder_for!r} keeps that prior's G_latent: "
                             f"gan_iterations must be 0, got {self.gan_iterations}")
        if not self.stages or any(r < 1 or n < 0 for r, n in self.stages):
            raise ValueError(f"stages must be a non-empty list of [resolution, iterations], got {self.stages!r}")
        positive(self, "batch_size", "gan_batch_size", "log_every", "checkpoint_every", "eval_resolution")
        positive(self, "gan_iterations", "points_per_shape", "eval_samples", minimum=0)


@dataclasses.dataclass(frozen=True)
class ShapeRecipe:
    data: ShapeDataConfig
    cache: ShapeCache
    model: ShapeConfig
    train: ShapeTrain
    tables: dict[str, Any]

    @classmethod
    def read(cls, path: str | Path, overrides: Sequence[str] = ()) -> "ShapeRecipe":
        tables = read_tables(path, overrides, required=("data", "model", "train"), known=("data", "model", "train"))
        return cls.from_tables(tables, path)

    @classmethod
    def from_tables(cls, tables: dict[str, Any], path: str | Path) -> "ShapeRecipe":
        """The recipe of parsed tables (a file's, or a run's ``recipe.json``); errors name ``path``."""
        data, cache = from_table(tables, "data", path, ShapeDataConfig, ShapeCache)
        (train,) = from_table(tables, "train", path, ShapeTrain)
        for resolution, _ in train.stages:
            if resolution not in data.resolutions:
                raise ValueError(f"{path}: stage resolution {resolution} is not among [data] resolutions {data.resolutions}")
        # the encoder reads the data's voxel grid
        model_table = {"voxel_resolution": data.voxel_resolution, **tables["model"]}
        (model,) = from_table({"model": model_table}, "model", path, ShapeConfig)
        return cls(data, cache, model, train, tables)


def split_ids(dataset_ids: list[str], held_out: int) -> tuple[list[str], list[str]]:
    if held_out >= len(dataset_ids):
        raise ValueError(f"held_out = {held_out} leaves no training shape of {len(dataset_ids)}")
    return dataset_ids[:len(dataset_ids) - held_out], dataset_ids[len(dataset_ids) - held_out:]


def stage_at(stages: Sequence[tuple[int, int]], step: int) -> int:
    """The autoencoder resolution of ``step``."""
    for resolution, iterations in stages:
        if step < iterations:
            return resolution
        step -= iterations
    return stages[-1][0]


def ae_batch(data: ShapeDataset, batches: loop.SeededBatches, resolution: int, step: int, points: int,
             device: torch.device) -> tuple[torch.Tensor, ...]:
    """Deterministic batch: shapes of ``batches`` (a dataset smaller than a batch is repeated), a
    random subset of ``points`` of each at the stage's resolution."""
    voxels, pts, occ = [], [], []
    for i in batches.indices(step):
        p, o = data.points(i, resolution)
        if 0 < points < len(p):
            pick = torch.randperm(len(p))[:points].numpy()
            p, o = p[pick], o[pick]
        voxels.append(data.voxel_tensor(i))
        pts.append(torch.from_numpy(p))
        occ.append(torch.from_numpy(o).float()[:, None])
    return tuple(torch.stack(t).to(device) for t in (voxels, pts, occ))


def run_shape_data(run: str | Path) -> tuple[ShapeRecipe, ShapeDataset, ShapeDataset | None]:
    """A ``train shape`` run's recipe and its training and held-out shapes (the split it trained with),
    read from the run's ``recipe.json`` and data cache."""
    run = Path(run)
    try:
        tables = json.loads((run / "recipe.json").read_text())["tables"]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{run}: not a `train shape` run (recipe.json: {exc})") from None
    recipe = ShapeRecipe.from_tables(tables, run / "recipe.json")
    cache = recipe.cache
    try:
        ids = [r["id"] for r in ShapeDataset.index(cache.cache_dir)]
    except FileNotFoundError:
        raise ValueError(f"{run}: its shape data {cache.cache_dir} is missing (`train shape` with the run's "
                         "recipe rebuilds it)") from None
    train_ids, held_ids = split_ids(ids, cache.held_out)
    return recipe, ShapeDataset(cache.cache_dir, ids=train_ids), (ShapeDataset(cache.cache_dir, ids=held_ids)
                                                                   if held_ids else None)


def autoencoder_iou(model: ShapeModel, data: ShapeDataset, resolution: int) -> float:
    """Mean voxel IoU of decode(encode(voxels)) against the voxels, at the voxel grid's cell centres."""
    if data.config["voxel_resolution"] != resolution:
        raise ValueError("autoencoder_iou: the IoU grid is the voxel grid")
    codes = model.encode(data.all_voxels().to(model.device))
    return float(np.mean([voxel_iou(model.occupancy_grid(c, resolution), data.voxels(i)) for i, c in enumerate(codes)]))


def sample_metrics(model: ShapeModel, reference: list[np.ndarray], held_out: list[np.ndarray], count: int,
                   resolution: int, seed: int) -> dict[str, Any]:
    """COV / MMD of ``count`` generated shapes against the training shapes' surface points.

    Also the same metrics of the held-out real shapes, and of as many generated shapes as there are
    held-out ones (coverage grows with the number of shapes matched, so only equal sizes compare).
    """
    rng = np.random.default_rng(seed)
    z = torch.randn(count, model.config.z_dim, generator=torch.Generator().manual_seed(seed))
    clouds, empty = [], 0
    for i in range(count):
        mesh = model.shape(z[i], resolution).mesh
        if mesh is None:
            empty += 1
            continue
        clouds.append(surface_samples(mesh, len(reference[0]), rng))
    result: dict[str, Any] = {"samples": count, "empty_samples": empty, "resolution": resolution}
    matrix = chamfer_matrix(clouds, reference) if clouds else None
    if matrix is not None:
        result.update(coverage_mmd(matrix))
    if held_out:  # what real, unseen shapes score; COV depends on the set size, so compare equal sizes
        result["held_out_real"] = {"shapes": len(held_out), **coverage_mmd(chamfer_matrix(held_out, reference))}
        if matrix is not None and len(matrix) >= len(held_out):
            result["first_samples_as_many"] = coverage_mmd(matrix[:len(held_out)])
    return result


def adopt_prior(model: ShapeModel, name_or_path: str) -> None:
    """Copy a model folder's decoder and G_latent into ``model``, whose config must be the same."""
    kept = pretrained.load_shape(name_or_path)
    differ = {f.name: (getattr(model.config, f.name), getattr(kept.config, f.name))
              for f in dataclasses.fields(model.config) if getattr(model.config, f.name) != getattr(kept.config, f.name)}
    if differ:
        raise ValueError(f"[train] encoder_for = {name_or_path!r}: the recipe's model differs from that prior's ("
                         + ", ".join(f"{k}: {a!r} here, {b!r} there" for k, (a, b) in differ.items())
                         + "); set them as it has them")
    model.decoder.load_state_dict(kept.decoder.state_dict())
    model.G_latent.load_state_dict(kept.G_latent.state_dict())


def train_shape(config_path: str | Path, log=print, out: str | Path | None = None, overrides: Sequence[str] = ()) -> Path:
    """Train (or resume training) as the recipe says; ``out`` replaces ``[train] out``. Returns the output folder."""
    overrides = [*overrides, *([out_override(out)] if out else [])]
    recipe = ShapeRecipe.read(config_path, overrides)
    train = recipe.train
    device = training_device(train.device)
    out = Path(train.out)
    cache = Path(recipe.cache.cache_dir)
    build_shape_dataset(recipe.data, cache, progress=True, workers=recipe.cache.workers)
    all_ids = [r["id"] for r in ShapeDataset.index(cache)]
    train_ids, held_ids = split_ids(all_ids, recipe.cache.held_out)
    data = ShapeDataset(cache, ids=train_ids)  # every resolution's points; batches pick the stage's
    held = ShapeDataset(cache, ids=held_ids) if held_ids else None
    batches = loop.SeededBatches(data, train.batch_size, train.seed, repeat=True)

    torch.manual_seed(train.seed)
    model = ShapeModel(recipe.model).to(device)
    step, resumed_from = loop.resume(out, [model])
    if resumed_from is not None:
        log(f"train shape: resuming from {resumed_from} (step {step})")
    if train.encoder_for:
        if resumed_from is None:
            adopt_prior(model, train.encoder_for)
        model.decoder.requires_grad_(False)  # the autoencoder's steps then move the encoder alone
        log(f"train shape: an encoder for {train.encoder_for}'s G_shape (decoder and G_latent fixed)")
    log(f"train shape: {len(train_ids)} training / {len(held_ids)} held-out shapes from {cache}, on {device}")
    record(out, config_path, overrides, recipe.tables)

    voxel_resolution = recipe.data.voxel_resolution
    ae_total = sum(it for _, it in train.stages)
    total = ae_total + train.gan_iterations
    metrics_path = out / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    log_file = loop.JsonLog(out, step)
    codes = None
    bar = tqdm(total=total, initial=step, unit="it", desc="train shape", dynamic_ncols=True)
    start, first = time.perf_counter(), step
    while step < total:
        loop.reseed(train.seed, step)
        if step < ae_total:
            resolution = stage_at(train.stages, step)
            batch = ae_batch(data, batches, resolution, step, train.points_per_shape, device)
            losses = {"phase": "ae", "resolution": resolution, **model.ae_step(*batch)}
        else:
            if codes is None:
                codes = model.encode(data.all_voxels().to(device))
            pick = torch.randint(len(codes), (train.gan_batch_size,), device=codes.device)
            losses = {"phase": "gan", **model.gan_step(codes[pick])}
        step += 1
        bar.update(1)
        if step % train.log_every == 0 or step in (ae_total, total):
            log_file.write({"step": step, "time": round(time.perf_counter() - start, 3),
                            "it_per_s": round((step - first) / (time.perf_counter() - start), 3), **losses})
        if step == ae_total:
            iou = {"train": autoencoder_iou(model, data, voxel_resolution)}
            if held is not None:
                iou["held_out"] = autoencoder_iou(model, held, voxel_resolution)
            metrics["autoencoder_iou"] = {**iou, "grid": voxel_resolution, "step": step}
            log_file.write({"step": step, "autoencoder_iou": iou})
            write_json(metrics_path, metrics)
            log(f"train shape: autoencoder IoU {json.dumps(iou)}")
        if step % train.checkpoint_every == 0 or step in (ae_total, total):
            loop.save(out, step, [model], recipe.tables)
    bar.close()
    if total > ae_total and "samples" not in metrics:
        reference = [data.surface(i) for i in range(len(data))]
        held_clouds = [held.surface(i) for i in range(len(held))] if held is not None else []
        metrics["samples"] = sample_metrics(model, reference, held_clouds, train.eval_samples, train.eval_resolution,
                                            train.seed + 1)
        log_file.write({"step": step, "samples": metrics["samples"]})
        write_json(metrics_path, metrics)
        log(f"train shape: samples {json.dumps(metrics['samples'])}")
    return out
