"""``ngp-mi train maps --config train/maps_<preset>.toml``: training of the map networks.

The config (TOML) has three tables:

* ``[data]`` — ``maps`` and ``depth``: ``render-dataset`` folders of real reflectance maps and of the
  depth maps to decorate; when absent, a dataset of ``source`` (``num_shapes`` × ``views`` at
  ``resolution``) is rendered into ``cache_dir`` first (and reused). With ``coarse_shapes`` (a
  ``train shape`` run), the depth maps are those of the same shapes reconstructed by its
  autoencoder (``<cache_dir>-coarse``, marching cubes at ``coarse_resolution``): coarse shapes,
  as NGP decorates.
* ``[model]`` — fields of :class:`~ngp_mi.models.maps.MapsConfig`.
* ``[train]`` — ``iterations``, ``batch_size``, ``seed``, ``out``, ``log_every``, ``image_every``,
  ``checkpoint_every``, ``device`` (``"auto"``: CUDA when available, else CPU; or ``"cpu"`` / ``"cuda"``).
* ``[specular]`` (optional) — the second stage, the realistic specular generator G_sp^real
  (:mod:`ngp_mi.models.specular`), trained for ``iterations`` more steps with the map networks
  fixed, as the paper orders it (maps first, then G_sp^real): ``real`` is a folder of real images
  (photographs or a ``render-dataset`` folder with path-traced images); when absent, ``num_shapes``
  × ``views`` path-traced images (``real_spp``) of ``[data] source`` are rendered into
  ``<cache_dir>-real`` with other seeds than the maps (the domains stay unpaired). Other keys are
  fields of :class:`~ngp_mi.models.specular.SpecularConfig`. A run whose checkpoints predate the
  table resumes with its map networks and starts the stage.

Outputs under ``out``: ``log.jsonl`` (losses per logged step; TensorBoard too if installed),
``images/step-*.png`` (every intermediate map), ``ckpt-*`` (see :mod:`ngp_mi.checkpoint`). A run
resumes from the newest checkpoint and reproduces the uninterrupted run exactly: the data order
is a seeded permutation per epoch, and torch's generator is reseeded from (seed, step, rank)
before every step. Resumes are bitwise exact on the CPU; on a GPU, atomic reductions (cuDNN's, Dr.Jit's
scatter-adds) reorder float sums, so a resumed run matches up to rounding.

Several processes (``torchrun --nproc_per_node N -m ngp_mi.cli train maps …``, gloo on CPU, NCCL
on GPUs) split every batch by rank and average gradients with ``torch.distributed.all_reduce``
before each optimiser step; rank 0 logs and checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import default_collate

from ngp_mi.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint, saved_modules
from ngp_mi.config import read_recipe, training_device
from ngp_mi.data.datasets import DepthDataset, ImageFolderDataset, ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel
from ngp_mi.viz import contact_sheet, save_png

NETWORKS = ("G_n", "G_da", "G_depth", "E_da", "D_n", "D_da", "D_df", "D_depth", "D_noc")
SPECULAR_NETWORKS = ("G_sp", "F_sp", "D_real", "D_dfr")
SPECULAR_DATA_KEYS = ("iterations", "real", "real_spp", "num_shapes", "views")


def load_config(path: str | Path) -> dict[str, Any]:
    config = read_recipe(path, ("data", "model", "train"))
    for table, known in (("model", {f.name for f in dataclasses.fields(MapsConfig)}),
                         ("specular", {f.name for f in dataclasses.fields(SpecularConfig)} | set(SPECULAR_DATA_KEYS))):
        unknown = set(config.get(table, {})) - known
        if unknown:
            raise ValueError(f"{path}: unknown [{table}] field(s) {sorted(unknown)}; known: {sorted(known)}")
    if "specular" in config and int(config["specular"].get("iterations", 0)) < 1:
        raise ValueError(f"{path}: [specular] iterations must be >= 1")
    return config


def model_config(config: dict[str, Any]) -> MapsConfig:
    values = dict(config["model"])
    for key in ("rf_maps", "rf_albedo"):
        if key in values:
            values[key] = tuple(values[key])
    return MapsConfig(**values)


def specular_config(config: dict[str, Any]) -> SpecularConfig | None:
    if "specular" not in config:
        return None
    values = {k: v for k, v in config["specular"].items() if k not in SPECULAR_DATA_KEYS}
    if "rf_image" in values:
        values["rf_image"] = tuple(values["rf_image"])
    return SpecularConfig(**values)


def prepare_data(data: dict[str, Any], rank: int) -> tuple[Path, Path]:
    """The (maps, depth) dataset folders, rendering a cached one from ``source`` when not given."""
    if "maps" in data and "depth" in data:
        return Path(data["maps"]), Path(data["depth"])
    cache = Path(data.get("cache_dir", "outputs/data/maps"))
    depth_cache = Path(f"{cache}-coarse") if "coarse_shapes" in data else cache
    if rank == 0:
        config = DatasetConfig(source=data.get("source", "chair"), num_shapes=data.get("num_shapes", 16),
                               views=data.get("views", 8), resolution=data.get("resolution", 64),
                               channels=("depth", "normal", "albedo", "noc", "mask"), seed=data.get("seed", 0))
        render_dataset(config, cache, progress=False)
        if "coarse_shapes" in data:  # the paper decorates G_shape's coarse shapes, not the detailed ones
            if not Path(data["coarse_shapes"]).is_dir():
                raise ValueError(f"[data] coarse_shapes = {data['coarse_shapes']!r}: no such `train shape` run "
                                 "(train it first: ngp-mi train shape --config train/shape_cpu.toml)")
            render_dataset(dataclasses.replace(config, channels=("depth", "mask"), coarse_shapes=data["coarse_shapes"],
                                               coarse_resolution=data.get("coarse_resolution", 64)),
                           depth_cache, progress=False)
    if dist.is_initialized():
        dist.barrier()
    return cache, depth_cache


def prepare_real_images(data: dict[str, Any], specular: dict[str, Any], rank: int) -> Path:
    """The real-image folder of the specular stage, rendering path-traced images when not given."""
    if "real" in specular:
        return Path(specular["real"])
    cache = Path(str(data.get("cache_dir", "outputs/data/maps")) + "-real")
    if rank == 0:
        render_dataset(DatasetConfig(source=data.get("source", "chair"), num_shapes=specular.get("num_shapes", 16),
                                     views=specular.get("views", 8), resolution=data.get("resolution", 64),
                                     channels=("mask",), real_spp=specular.get("real_spp", 64),
                                     seed=data.get("seed", 0) + 1), cache, progress=False)
    if dist.is_initialized():
        dist.barrier()
    return cache


class _Batches:
    """Deterministic batches: a seeded permutation per epoch, split by rank."""

    def __init__(self, dataset: torch.utils.data.Dataset, batch_size: int, seed: int, rank: int, world: int):
        self.dataset, self.batch, self.seed, self.rank, self.world = dataset, batch_size, seed, rank, world
        self.per_epoch = len(dataset) // (batch_size * world)
        if self.per_epoch == 0:
            raise ValueError(f"dataset of {len(dataset)} items is smaller than one global batch ({batch_size} x {world})")

    def __call__(self, step: int) -> dict[str, Any]:
        epoch, offset = divmod(step, self.per_epoch)
        order = torch.randperm(len(self.dataset), generator=torch.Generator().manual_seed(self.seed + epoch))
        start = (offset * self.world + self.rank) * self.batch
        return default_collate([self.dataset[int(i)] for i in order[start:start + self.batch]])


def _grid(visuals: dict[str, torch.Tensor]) -> np.ndarray:
    tiles = []
    for tensor in visuals.values():
        image = ((tensor[0].detach().float().cpu().clamp(-1, 1) + 1) / 2).permute(1, 2, 0).numpy()
        image = np.repeat(image, 3, -1) if image.shape[-1] == 1 else image
        tiles.append((image * 255).round().astype(np.uint8))
    return contact_sheet(tiles, list(visuals), columns=len(tiles))


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def average_gradients(parameters: list[torch.Tensor]) -> None:
    """Mean of every gradient over the processes (what DistributedDataParallel does, per step)."""
    world = dist.get_world_size()
    for p in parameters:
        if p.grad is not None:
            dist.all_reduce(p.grad)
            p.grad /= world


def train_maps(config_path: str | Path, log=print) -> Path:
    """Train (or resume training) as configured; returns the output folder."""
    from tqdm import tqdm

    config = load_config(config_path)
    train = config["train"]
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = training_device(train.get("device", "auto"), int(os.environ.get("LOCAL_RANK", "0")))
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    rank = dist.get_rank() if dist.is_initialized() else 0
    out = Path(train.get("out", "outputs/train/maps"))
    seed = int(train.get("seed", 0))
    maps_root, depth_root = prepare_data(config["data"], rank)
    maps_batches = _Batches(ReflectanceMapDataset(maps_root), train["batch_size"], seed, rank, world)
    depth_batches = _Batches(DepthDataset(depth_root), train["batch_size"], seed + 10 ** 6, rank, world)

    torch.manual_seed(seed)  # identical initial weights on every rank
    model = MapsModel(model_config(config)).to(device)  # in place: the optimisers keep their parameters
    modules = {name: getattr(model, name) for name in NETWORKS}
    optimizers = {"opt_G": model.opt_G, "opt_D": model.opt_D}
    spec_config = specular_config(config)
    specular, real_batches = None, None
    if spec_config is not None:
        specular = SpecularModel(spec_config).to(device)
        real_root = prepare_real_images(config["data"], config["specular"], rank)
        real_batches = _Batches(ImageFolderDataset(real_root, size=config["data"].get("resolution", 64), linear=True),
                                train["batch_size"], seed + 2 * 10 ** 6, rank, world)
        modules.update({name: getattr(specular, name) for name in SPECULAR_NETWORKS})
        optimizers.update(opt_sp_G=specular.opt_G, opt_sp_D=specular.opt_D)
    step = 0
    checkpoints = list_checkpoints(out)
    if checkpoints:
        # A checkpoint from before the [specular] table holds the map networks only: the stage starts fresh.
        saved = saved_modules(checkpoints[-1])
        state = load_checkpoint(checkpoints[-1], {k: m for k, m in modules.items() if k in saved or k in NETWORKS})
        for key, optimizer in optimizers.items():
            if key in state:
                optimizer.load_state_dict(state[key])
        step = int(state["step"])
        if rank == 0:
            log(f"train maps: resuming from {checkpoints[-1]} (step {step})")
    if rank == 0:
        log(f"train maps: {world} process(es) on {device}")
    if world > 1:
        model.gradient_hook = average_gradients
        if specular is not None:
            specular.gradient_hook = average_gradients

    maps_iterations = int(train["iterations"])
    iterations = maps_iterations + (int(config["specular"]["iterations"]) if specular is not None else 0)
    writer = _tensorboard(out) if rank == 0 else None
    bar = tqdm(total=iterations, initial=step, unit="it", disable=rank != 0, desc="train maps")
    start, first = time.perf_counter(), step
    while step < iterations:
        torch.manual_seed(seed * 1_000_003 + step * world + rank)
        depth_batch = to_device(depth_batches(step), device)
        if step < maps_iterations:
            stage, visuals = "maps", model
            losses = model.optimize(depth_batch, to_device(maps_batches(step), device))
        else:
            stage, visuals = "specular", specular
            losses = specular.optimize(model, depth_batch, real_batches(step).to(device))
        step += 1
        bar.update(1)
        if rank != 0:
            continue
        last = step == iterations or step == maps_iterations
        if step % train.get("log_every", 10) == 0 or last:
            record = {"step": step, "stage": stage, "time": round(time.perf_counter() - start, 3),
                      "it_per_s": round((step - first) / (time.perf_counter() - start), 3), "world": world, **losses}
            with open(out / "log.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")
            if writer is not None:
                for key, value in losses.items():
                    writer.add_scalar(f"{stage}/{key}", value, step)
        if step % train.get("image_every", 100) == 0 or last:
            save_png(out / "images" / f"step-{step:08d}.png", _grid(visuals.visuals))
        if step % train.get("checkpoint_every", 500) == 0 or last:
            save_checkpoint(out, step, modules, {**{k: o.state_dict() for k, o in optimizers.items()},
                                                 "config": json.dumps(config)})
    bar.close()
    if dist.is_initialized():
        # Averaged gradients keep every rank's weights identical: check it.
        parameters = [p for m in modules.values() for p in m.parameters()]
        checksum = torch.stack([p.detach().double().sum() for p in parameters]).sum().reshape(1)
        sums = [torch.zeros_like(checksum) for _ in range(world)]
        dist.all_gather(sums, checksum)
        if rank == 0:
            in_sync = all(torch.equal(s, sums[0]) for s in sums)
            with open(out / "log.jsonl", "a") as f:
                f.write(json.dumps({"step": step, "world": world, "ranks_in_sync": in_sync}) + "\n")
            if not in_sync:
                raise RuntimeError(f"ranks diverged: parameter checksums {[float(s) for s in sums]}")
        dist.barrier()
    return out


def _tensorboard(out: Path) -> Any:
    out.mkdir(parents=True, exist_ok=True)
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # TensorBoard is optional
        return None
    return SummaryWriter(str(out / "tensorboard"))
