"""What every trainer shares: seeded batches, the reseed rule, the JSON-lines log, checkpoints and resume,
several processes.

Exact resume: the data order is a seeded permutation per epoch (:class:`SeededBatches`) and torch's
generator is reseeded from (seed, step, rank) before every step (:func:`reseed`), so a run killed
and resumed from its newest checkpoint reproduces the uninterrupted one (bitwise on the CPU; on a
GPU up to the order of atomic float sums).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.distributed as dist
from torch.utils.data import default_collate

from ngp_mi.atomic import write_text
from ngp_mi.models.base import BaseModel
from ngp_mi.models.checkpoint import list_checkpoints, load_weights, read_newest, remove_temporaries, save_checkpoint
from ngp_mi.training.recipe import training_device


class SeededBatches:
    """Batches of a dataset: a seeded permutation per epoch, each batch split by rank.

    With ``repeat``, a dataset smaller than one batch is repeated to fill it; otherwise that is an error.
    """

    def __init__(self, dataset: Any, batch_size: int, seed: int, rank: int = 0, world: int = 1, repeat: bool = False):
        self.dataset, self.batch, self.seed, self.rank, self.world = dataset, batch_size, seed, rank, world
        self.size = len(dataset)
        self.per_epoch = self.size // (batch_size * world)
        if self.per_epoch == 0:
            if not repeat:
                raise ValueError(f"dataset of {self.size} items is smaller than one global batch ({batch_size} x {world})")
            self.per_epoch = 1

    def indices(self, step: int) -> list[int]:
        epoch, offset = divmod(step, self.per_epoch)
        order = torch.randperm(self.size, generator=torch.Generator().manual_seed(self.seed + epoch))
        start = (offset * self.world + self.rank) * self.batch
        chosen = order[start:start + self.batch].tolist()
        return (chosen * self.batch)[:self.batch] if len(chosen) < self.batch else chosen

    def __call__(self, step: int) -> dict[str, Any]:
        """The collated items of ``step``'s batch."""
        return default_collate([self.dataset[i] for i in self.indices(step)])


def linear_decay(step: int, iterations: int, decay_from: float) -> float:
    """The learning rate's factor for step ``step`` (0-based) of ``iterations``: 1 before
    ``decay_from`` × ``iterations``, then falling linearly to 1 / (n + 1) at the last step, n being the
    decaying steps (pix2pix / CycleGAN's "linear" policy, per step instead of per epoch, meant to let a
    GAN's generators settle; on issue 15's map stage it bought nothing over a constant rate of the same
    length, bench/RESULTS.md). A function of the step alone, so a resumed run sets the same rates.
    ``decay_from`` 1: constant."""
    if not 0.0 <= decay_from <= 1.0:
        raise ValueError(f"lr_decay_from = {decay_from}: a fraction of the iterations in [0, 1]")
    start = round(decay_from * iterations)
    return 1.0 - max(0, step - start + 1) / (iterations - start + 1)


def reseed(seed: int, step: int, world: int = 1, rank: int = 0) -> None:
    """Seed torch's generator for one step (the same rule in every trainer, so resumes are exact)."""
    torch.manual_seed(seed * 1_000_003 + step * world + rank)


class JsonLog:
    """``log.jsonl``: one JSON record per line. On resume, records past the resumed step (written
    after the checkpoint by the killed run) are dropped, so the log holds every step once."""

    def __init__(self, out: Path, resumed_step: int = 0):
        self.path = Path(out) / "log.jsonl"
        if resumed_step and self.path.exists():
            lines = self.path.read_text().splitlines()
            kept = [line for line in lines if line.strip() and json.loads(line).get("step", 0) <= resumed_step]
            if len(kept) != len(lines):
                write_text(self.path, "".join(line + "\n" for line in kept))

    def write(self, record: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")


def save(out: Path, step: int, models: Sequence[BaseModel], tables: dict[str, Any]) -> Path:
    """A checkpoint of every model's networks and optimisers, the recipe tables and the models' configs."""
    modules = {name: m for model in models for name, m in model.networks().items()}
    configs = {key: value for model in models for key, value in model.config_dict().items()}
    state = {name: s for model in models for name, s in model.optimizer_state().items()}
    return save_checkpoint(out, step, modules, {**state, "config": json.dumps(tables), "model_config": json.dumps(configs)})


def resume(out: Path, models: Sequence[BaseModel], optional: Sequence[BaseModel] = ()) -> tuple[int, Path | None]:
    """Load the newest readable checkpoint in ``out`` into ``models`` and ``optional`` models (one
    whose networks the checkpoint lacks — a stage added to the recipe later — starts fresh). Returns
    the step it holds and its path, or (0, None) without one. Temporaries of killed checkpoint
    writes are removed first."""
    remove_temporaries(out)
    if not list_checkpoints(out):
        return 0, None
    path, state, tensors = read_newest(out)
    saved = {key.split(".", 1)[0] for key in tensors}
    loaded = [m for m in models] + [m for m in optional if saved & set(m.networks())]
    load_weights({name: n for model in loaded for name, n in model.networks().items()}, tensors, path)
    for model in loaded:
        model.load_optimizer_state(state)
    return int(state["step"]), path


def start_processes(device_name: str) -> tuple[torch.device, int, int]:
    """(device, rank, world) of this process; under ``torchrun`` joins the process group (NCCL on
    GPUs, gloo on CPUs)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = training_device(device_name, int(os.environ.get("LOCAL_RANK", "0")))
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    rank = dist.get_rank() if dist.is_initialized() else 0
    return device, rank, world


def barrier() -> None:
    if dist.is_initialized():
        dist.barrier()


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def average_gradients(parameters: list[torch.Tensor]) -> None:
    """Mean of every gradient over the processes (what DistributedDataParallel does, per step)."""
    world = dist.get_world_size()
    for p in parameters:
        if p.grad is not None:
            dist.all_reduce(p.grad)
            p.grad /= world


def check_in_sync(models: Sequence[BaseModel], log: JsonLog | None, step: int, world: int) -> None:
    """Averaged gradients keep every rank's weights identical: check it at the end (rank 0 logs)."""
    parameters = [p for model in models for p in model.parameters()]
    checksum = torch.stack([p.detach().double().sum() for p in parameters]).sum().reshape(1)
    sums = [torch.zeros_like(checksum) for _ in range(world)]
    dist.all_gather(sums, checksum)
    if log is not None:
        in_sync = all(torch.equal(s, sums[0]) for s in sums)
        log.write({"step": step, "world": world, "ranks_in_sync": in_sync})
        if not in_sync:
            raise RuntimeError(f"ranks diverged: parameter checksums {[float(s) for s in sums]}")
    dist.barrier()


def tensorboard(out: Path) -> Any:
    """A TensorBoard writer in ``out/tensorboard`` when TensorBoard is installed (optional), else None."""
    out.mkdir(parents=True, exist_ok=True)
    try:  # TensorBoard is an optional package
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tensorboard"))
