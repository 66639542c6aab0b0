"""``ngp-mi train maps --config train/maps_<preset>.toml``: training of the map networks.

The config (TOML) has three tables:

* ``[data]`` — ``maps`` and ``depth``: ``render-dataset`` folders of real reflectance maps and of the
  depth maps to decorate; when absent, a dataset of ``source`` (``num_shapes`` × ``views`` at
  ``resolution``) is rendered into ``cache_dir`` first (and reused).
* ``[model]`` — fields of :class:`~ngp_mi.models.maps.MapsConfig`.
* ``[train]`` — ``iterations``, ``batch_size``, ``seed``, ``out``, ``log_every``, ``image_every``,
  ``checkpoint_every``, ``device`` (``"auto"``: CUDA when available, else CPU; or ``"cpu"`` / ``"cuda"``).

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

from ngp_mi.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint
from ngp_mi.config import read_recipe, training_device
from ngp_mi.data.datasets import DepthDataset, ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.viz import contact_sheet, save_png

NETWORKS = ("G_n", "G_da", "G_depth", "E_da", "D_n", "D_da", "D_df", "D_depth", "D_noc")


def load_config(path: str | Path) -> dict[str, Any]:
    config = read_recipe(path, ("data", "model", "train"))
    fields = {f.name for f in dataclasses.fields(MapsConfig)}
    unknown = set(config["model"]) - fields
    if unknown:
        raise ValueError(f"{path}: unknown [model] field(s) {sorted(unknown)}; known: {sorted(fields)}")
    return config


def model_config(config: dict[str, Any]) -> MapsConfig:
    values = dict(config["model"])
    for key in ("rf_maps", "rf_albedo"):
        if key in values:
            values[key] = tuple(values[key])
    return MapsConfig(**values)


def prepare_data(data: dict[str, Any], rank: int) -> tuple[Path, Path]:
    """The (maps, depth) dataset folders, rendering a cached one from ``source`` when not given."""
    if "maps" in data and "depth" in data:
        return Path(data["maps"]), Path(data["depth"])
    cache = Path(data.get("cache_dir", "outputs/data/maps"))
    if rank == 0:
        render_dataset(DatasetConfig(source=data.get("source", "chair"), num_shapes=data.get("num_shapes", 16),
                                     views=data.get("views", 8), resolution=data.get("resolution", 64),
                                     channels=("depth", "normal", "albedo", "noc", "mask"), seed=data.get("seed", 0)),
                       cache, progress=False)
    if dist.is_initialized():
        dist.barrier()
    return cache, cache


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
    step = 0
    checkpoints = list_checkpoints(out)
    if checkpoints:
        state = load_checkpoint(checkpoints[-1], modules)
        model.opt_G.load_state_dict(state["opt_G"])
        model.opt_D.load_state_dict(state["opt_D"])
        step = int(state["step"])
        if rank == 0:
            log(f"train maps: resuming from {checkpoints[-1]} (step {step})")
    if rank == 0:
        log(f"train maps: {world} process(es) on {device}")
    if world > 1:
        model.gradient_hook = average_gradients

    iterations = int(train["iterations"])
    writer = _tensorboard(out) if rank == 0 else None
    bar = tqdm(total=iterations, initial=step, unit="it", disable=rank != 0, desc="train maps")
    start, first = time.perf_counter(), step
    while step < iterations:
        torch.manual_seed(seed * 1_000_003 + step * world + rank)
        losses = model.optimize(to_device(depth_batches(step), device), to_device(maps_batches(step), device))
        step += 1
        bar.update(1)
        if rank != 0:
            continue
        if step % train.get("log_every", 10) == 0 or step == iterations:
            record = {"step": step, "time": round(time.perf_counter() - start, 3),
                      "it_per_s": round((step - first) / (time.perf_counter() - start), 3), "world": world, **losses}
            with open(out / "log.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")
            if writer is not None:
                for key, value in losses.items():
                    writer.add_scalar(f"loss/{key}", value, step)
        if step % train.get("image_every", 100) == 0 or step == iterations:
            save_png(out / "images" / f"step-{step:08d}.png", _grid(model.visuals))
        if step % train.get("checkpoint_every", 500) == 0 or step == iterations:
            save_checkpoint(out, step, modules, {"opt_G": model.opt_G.state_dict(), "opt_D": model.opt_D.state_dict(),
                                                 "config": json.dumps(config)})
    bar.close()
    if dist.is_initialized():
        # Averaged gradients keep every rank's weights identical: check it.
        checksum = torch.stack([p.detach().double().sum() for p in model.parameters()]).sum().reshape(1)
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
