"""``ngp-mi train shape --config train/shape_<preset>.toml``: the IM-NET autoencoder, then the latent GAN.

The config (TOML) has three tables:

* ``[data]`` — the fields of :class:`~ngp_mi.data.shapes.ShapeDataConfig` (``source``, ``num_shapes``,
  ``voxel_resolution``, ``resolutions``, ``points``, …), ``cache_dir`` where the shape data is
  built (and reused), ``workers`` (processes that build it), and ``held_out``: the last shapes,
  kept out of training for the IoU metric.
* ``[model]`` — fields of :class:`~ngp_mi.models.shape.ShapeConfig`.
* ``[train]`` — ``stages`` (a list of ``[resolution, iterations]`` of the autoencoder, IM-NET's
  progressive 16³ → 32³ → 64³), ``gan_iterations``, ``batch_size``, ``points_per_shape`` (0: all
  points of the stage), ``gan_batch_size``, ``seed``, ``out``, ``log_every``, ``checkpoint_every``,
  ``device`` (``auto`` / ``cpu`` / ``cuda``), ``eval_samples`` and ``eval_resolution`` (the sample
  metrics).

One step counter runs through both phases (autoencoder steps first). Outputs under ``out``:
``log.jsonl`` (losses; metrics records), ``metrics.json`` (autoencoder IoU on held-out and training
shapes at the end of phase 1; coverage / MMD of generated shapes at the end, next to the same
metrics of the held-out real shapes as a reference), ``ckpt-*``. Killed and restarted, a run
resumes from its newest checkpoint and reproduces the uninterrupted run exactly on the CPU
(torch's generator is reseeded from (seed, step) before every step).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ngp_mi.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint
from ngp_mi.config import read_recipe, training_device
from ngp_mi.data.shapes import ShapeDataConfig, ShapeDataset, build_shape_dataset
from ngp_mi.eval.shape_metrics import chamfer_matrix, coverage_mmd
from ngp_mi.geometry.occupancy import surface_samples, voxel_iou
from ngp_mi.models.shape import ShapeConfig, ShapeModel

TRAIN_DEFAULTS = {"gan_iterations": 0, "batch_size": 16, "points_per_shape": 0, "gan_batch_size": 64, "seed": 0,
                  "out": "outputs/train/shape", "log_every": 10, "checkpoint_every": 500, "device": "auto",
                  "eval_samples": 16, "eval_resolution": 64}


def load_config(path: str | Path) -> dict[str, Any]:
    config = read_recipe(path, ("data", "model", "train"))
    checks = {"data": {f.name for f in dataclasses.fields(ShapeDataConfig)} | {"cache_dir", "held_out", "workers"},
              "model": {f.name for f in dataclasses.fields(ShapeConfig)},
              "train": set(TRAIN_DEFAULTS) | {"stages"}}
    for table, known in checks.items():
        unknown = set(config[table]) - known
        if unknown:
            raise ValueError(f"{path}: unknown [{table}] field(s) {sorted(unknown)}; known: {sorted(known)}")
    stages = config["train"].get("stages")
    if not stages or any(len(s) != 2 for s in stages):
        raise ValueError(f"{path}: [train] stages must be a list of [resolution, iterations], got {stages!r}")
    for resolution, _ in stages:
        if resolution not in config["data"].get("resolutions", ShapeDataConfig.resolutions):
            raise ValueError(f"{path}: stage resolution {resolution} is not among [data] resolutions")
    config["train"] = {**TRAIN_DEFAULTS, **config["train"]}
    return config


def data_config(data: dict[str, Any]) -> ShapeDataConfig:
    skip = ("cache_dir", "held_out", "workers")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k not in skip}
    return ShapeDataConfig(**values)


def model_config(model: dict[str, Any], data: ShapeDataConfig) -> ShapeConfig:
    return ShapeConfig(**{"voxel_resolution": data.voxel_resolution, **model})


def split_ids(dataset_ids: list[str], held_out: int) -> tuple[list[str], list[str]]:
    if held_out >= len(dataset_ids):
        raise ValueError(f"held_out = {held_out} leaves no training shape of {len(dataset_ids)}")
    return dataset_ids[:len(dataset_ids) - held_out], dataset_ids[len(dataset_ids) - held_out:]


def stage_at(stages: list[list[int]], step: int) -> int:
    """The autoencoder resolution of ``step``."""
    for resolution, iterations in stages:
        if step < iterations:
            return resolution
        step -= iterations
    return stages[-1][0]


def ae_batch(data: ShapeDataset, resolution: int, step: int, batch_size: int, points: int,
             seed: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Deterministic batch: shapes by a seeded permutation per epoch, a random subset of their points."""
    per_epoch = max(1, len(data) // batch_size)
    epoch, offset = divmod(step, per_epoch)
    order = torch.randperm(len(data), generator=torch.Generator().manual_seed(seed + epoch))
    chosen = order[offset * batch_size:(offset + 1) * batch_size].tolist()
    if len(chosen) < batch_size:  # fewer shapes than a batch: repeat
        chosen = (chosen * batch_size)[:batch_size]
    voxels, pts, occ = [], [], []
    for i in chosen:
        p, o = data.points(i, resolution)
        if 0 < points < len(p):
            pick = torch.randperm(len(p))[:points].numpy()
            p, o = p[pick], o[pick]
        voxels.append(data.voxel_tensor(i))
        pts.append(torch.from_numpy(p))
        occ.append(torch.from_numpy(o).float()[:, None])
    return tuple(torch.stack(t).to(device) for t in (voxels, pts, occ))


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


def train_shape(config_path: str | Path, log=print) -> Path:
    """Train (or resume training) as configured; returns the output folder."""
    from tqdm import tqdm

    config = load_config(config_path)
    train = config["train"]
    device = training_device(train["device"])
    out = Path(train["out"])
    seed = int(train["seed"])
    dcfg = data_config(config["data"])
    cache = Path(config["data"].get("cache_dir", "outputs/data/shape"))
    build_shape_dataset(dcfg, cache, progress=True, workers=int(config["data"].get("workers", 1)))
    all_ids = [r["id"] for r in ShapeDataset.index(cache)]
    train_ids, held_ids = split_ids(all_ids, int(config["data"].get("held_out", 0)))
    data = ShapeDataset(cache, ids=train_ids)  # every resolution's points; batches pick the stage's
    held = ShapeDataset(cache, ids=held_ids) if held_ids else None

    torch.manual_seed(seed)
    model = ShapeModel(model_config(config["model"], dcfg)).to(device)
    modules = model.networks()
    step = 0
    checkpoints = list_checkpoints(out)
    if checkpoints:
        state = load_checkpoint(checkpoints[-1], modules)
        model.load_optimizer_state(state)
        step = int(state["step"])
        log(f"train shape: resuming from {checkpoints[-1]} (step {step})")
    log(f"train shape: {len(train_ids)} training / {len(held_ids)} held-out shapes from {cache}, on {device}")

    stages = [list(s) for s in train["stages"]]
    ae_total = sum(it for _, it in stages)
    total = ae_total + int(train["gan_iterations"])
    out.mkdir(parents=True, exist_ok=True)
    metrics_path = out / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    codes = None
    bar = tqdm(total=total, initial=step, unit="it", desc="train shape", dynamic_ncols=True)
    start, first = time.perf_counter(), step

    def record(entry: dict[str, Any]) -> None:
        with open(out / "log.jsonl", "a") as f:
            f.write(json.dumps(entry) + "\n")

    def save_metrics() -> None:
        tmp = metrics_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(metrics, indent=1) + "\n")
        tmp.replace(metrics_path)

    while step < total:
        torch.manual_seed(seed * 1_000_003 + step)
        if step < ae_total:
            resolution = stage_at(stages, step)
            batch = ae_batch(data, resolution, step, int(train["batch_size"]), int(train["points_per_shape"]),
                             seed, device)
            losses = {"phase": "ae", "resolution": resolution, **model.ae_step(*batch)}
        else:
            if codes is None:
                codes = model.encode(data.all_voxels().to(device))
            pick = torch.randint(len(codes), (int(train["gan_batch_size"]),), device=codes.device)
            losses = {"phase": "gan", **model.gan_step(codes[pick])}
        step += 1
        bar.update(1)
        if step % train["log_every"] == 0 or step in (ae_total, total):
            record({"step": step, "time": round(time.perf_counter() - start, 3),
                    "it_per_s": round((step - first) / (time.perf_counter() - start), 3), **losses})
        if step == ae_total:
            iou = {"train": autoencoder_iou(model, data, dcfg.voxel_resolution)}
            if held is not None:
                iou["held_out"] = autoencoder_iou(model, held, dcfg.voxel_resolution)
            metrics["autoencoder_iou"] = {**iou, "grid": dcfg.voxel_resolution, "step": step}
            record({"step": step, "autoencoder_iou": iou})
            save_metrics()
            log(f"train shape: autoencoder IoU {json.dumps(iou)}")
        if step % train["checkpoint_every"] == 0 or step in (ae_total, total):
            save_checkpoint(out, step, modules, {**model.optimizer_state(), "config": json.dumps(config)})
    bar.close()
    if total > ae_total and "samples" not in metrics:
        reference = [data.surface(i) for i in range(len(data))]
        held_clouds = [held.surface(i) for i in range(len(held))] if held is not None else []
        metrics["samples"] = sample_metrics(model, reference, held_clouds, int(train["eval_samples"]),
                                            int(train["eval_resolution"]), seed + 1)
        record({"step": step, "samples": metrics["samples"]})
        save_metrics()
        log(f"train shape: samples {json.dumps(metrics['samples'])}")
    return out


def load_shape_model(run: str | Path, device: str | torch.device = "cpu") -> ShapeModel:
    """The shape model of the newest checkpoint of a ``train shape`` run."""
    checkpoints = list_checkpoints(run)
    if not checkpoints:
        raise ValueError(f"{run}: no checkpoint found (ckpt-*/weights.safetensors + state.pt)")
    state = torch.load(checkpoints[-1] / "state.pt", map_location="cpu", weights_only=True)
    config = json.loads(state["config"])
    model = ShapeModel(model_config(config["model"], data_config(config["data"])))
    load_checkpoint(checkpoints[-1], model.networks())
    return model.to(device).eval()
