"""``ngp-mi train maps --config train/maps_<preset>.toml``: the map networks, then G_sp^real.

The recipe (TOML; :mod:`ngp_mi.training.recipe`) has these tables:

* ``[data]`` (:class:`MapsData`) — ``maps`` and ``depth``: ``render-dataset`` folders of real
  reflectance maps and of the depth maps to decorate; when absent, a dataset of ``source``
  (``num_shapes`` × ``views`` at ``resolution``) is rendered into ``cache_dir`` first (and reused).
  With ``coarse_shapes`` (a ``train shape`` run, or a model folder or shipped name whose prior has its
  encoder), the depth maps are those of the same shapes
  reconstructed by its autoencoder (``<cache_dir>-coarse``, marching cubes at
  ``coarse_resolution``): coarse shapes, as NGP decorates.
* ``[model]`` — fields of :class:`~ngp_mi.models.maps.MapsConfig`.
* ``[train]`` (:class:`MapsTrain`) — iterations, batch size, seed, output folder, how often to
  log, write image grids and checkpoints, the device (``"auto"``: CUDA when available) and the map
  stage's learning-rate schedule (``lr_decay_from``; the rate is logged as ``lr``).
* ``[encoder]`` (optional; :class:`EncoderStage`) — beyond the paper: after the map stage, E_da
  alone is trained for ``iterations`` more steps to invert the trained G_da (the exemplar handle's
  z_da = μ(E_da(I_da)) against I_da, :meth:`~ngp_mi.models.maps.MapsModel.optimize_encoder`), on
  ``num_shapes`` × ``views`` other shapes of ``[data] source`` rendered into ``<cache_dir>-encoder``.
* ``[specular]`` (optional; :class:`SpecularStage` and the fields of
  :class:`~ngp_mi.models.specular.SpecularConfig`) — the second stage, the realistic specular
  generator G_sp^real, trained for ``iterations`` more steps with the map networks fixed, as the
  paper orders it: ``real`` is a folder of real images (photographs or a ``render-dataset`` folder
  with path-traced images); when absent, ``num_shapes`` × ``views`` path-traced images
  (``real_spp``) of ``[data] source`` are rendered into ``<cache_dir>-real`` with other seeds than
  the maps (the domains stay unpaired). A run whose checkpoints predate the table resumes with its
  map networks and starts the stage.

Outputs under ``out``: ``recipe.json`` (the recipe with its command-line overrides), ``log.jsonl``
(losses per logged step; TensorBoard too if installed), ``images/step-*.png`` (every intermediate
map), ``ckpt-*`` (:mod:`ngp_mi.models.checkpoint`). Runs resume exactly (:mod:`ngp_mi.training.loop`).

Several processes (``torchrun --nproc_per_node N -m ngp_mi.cli train maps …``, gloo on CPU, NCCL
on GPUs) split every batch by rank and average gradients with ``torch.distributed.all_reduce``
before each optimiser step; rank 0 logs and checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch.utils.data import default_collate
from tqdm import tqdm

from ngp_mi.atomic import atomic_path, write_text

from ngp_mi.data.datasets import DepthDataset, ImageFolderDataset, ReflectanceMapDataset, WithCoarseDepth
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.models import pretrained
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel
from ngp_mi.training import loop
from ngp_mi.training.recipe import from_table, out_override, positive, read_tables, record
from ngp_mi.viz import contact_sheet, save_png

TABLES = ("data", "model", "train", "encoder", "specular")
# Runs started together on one data cache (recipe arms side by side): the first renders it, the others
# wait for it this long (seconds) and then find it complete, instead of failing on its lock.
CACHE_WAIT_SECONDS = 3 * 3600


@dataclasses.dataclass(frozen=True)
class MapsData:
    source: str = "chair"
    num_shapes: int = 16
    views: int = 8
    resolution: int = 64
    seed: int = 0
    cache_dir: str = "outputs/data/maps"
    maps: str | None = None    # a render-dataset folder of reflectance maps (with ``depth``: no rendering)
    depth: str | None = None   # a render-dataset folder of the depth maps to decorate
    coarse_shapes: str | None = None  # a `train shape` run or a model folder / shipped name (with an encoder):
                                      # decorate its autoencoder's coarse shapes
    coarse_resolution: int = 64

    def __post_init__(self) -> None:
        positive(self, "num_shapes", "views", "resolution", "coarse_resolution")
        if (self.maps is None) != (self.depth is None):
            raise ValueError("maps and depth go together (two render-dataset folders), or neither")


@dataclasses.dataclass(frozen=True)
class MapsTrain:
    iterations: int
    batch_size: int
    seed: int = 0
    out: str = "outputs/train/maps"
    log_every: int = 10
    image_every: int = 100
    checkpoint_every: int = 500
    device: str = "auto"
    # The map networks' learning rates fall linearly to near 0 over the map stage's iterations from this
    # fraction of them on (loop.linear_decay: CycleGAN's and BicycleGAN's schedule); 1: constant, the
    # paper's (it names none).
    lr_decay_from: float = 1.0

    def __post_init__(self) -> None:
        positive(self, "iterations", "batch_size", "log_every", "image_every", "checkpoint_every")
        try:  # the schedule's own check of its range, named by the recipe's table
            loop.linear_decay(0, self.iterations, self.lr_decay_from)
        except ValueError as error:
            raise ValueError(f"[train] {error}") from None


@dataclasses.dataclass(frozen=True)
class EncoderStage:
    """``[encoder]``: E_da refitted to the trained, fixed G_da (beyond the paper; off without the table).
    Its data are shapes the map stage never saw (seeds from ``[data] seed`` + ``SEED_OFFSET``): only
    E_da learns here, a network small enough to over-fit 200 shapes (bench/RESULTS.md), and
    rendering 2,000 takes seconds."""
    iterations: int
    lr: float = 1e-4
    batch_size: int = 16
    num_shapes: int = 2000
    views: int = 2
    cache_mib: int = 2048  # the views and their G_da condition held in memory when they fit; 0: read per batch

    SEED_OFFSET = 1000  # shapes data.seed + 1000 …: the `cpu` recipe's validation (600–) and test (500–) shapes lie below

    def __post_init__(self) -> None:
        positive(self, "iterations", "batch_size", "num_shapes", "views")
        if self.cache_mib < 0:
            raise ValueError(f"cache_mib must be >= 0, got {self.cache_mib!r}")
        if not 0 < self.lr <= 1:
            raise ValueError(f"lr must lie in (0, 1], got {self.lr!r}")


@dataclasses.dataclass(frozen=True)
class SpecularStage:
    iterations: int
    real: str | None = None  # a folder of real images; rendered from [data] source when absent
    real_spp: int = 64
    num_shapes: int = 16
    views: int = 8

    def __post_init__(self) -> None:
        positive(self, "iterations", "real_spp", "num_shapes", "views")


@dataclasses.dataclass(frozen=True)
class MapsRecipe:
    data: MapsData
    model: MapsConfig
    train: MapsTrain
    encoder: EncoderStage | None
    stage: SpecularStage | None
    specular: SpecularConfig | None
    tables: dict[str, Any]  # as read, overrides applied: stored in checkpoints and recipe.json

    def __post_init__(self) -> None:
        require_coarse_pairs(self.model, self.data)  # before any rendering

    @classmethod
    def read(cls, path: str | Path, overrides: Sequence[str] = ()) -> "MapsRecipe":
        tables = read_tables(path, overrides, required=("data", "model", "train"), known=TABLES)
        stage, specular = from_table(tables, "specular", path, SpecularStage, SpecularConfig) \
            if "specular" in tables else (None, None)
        encoder = from_table(tables, "encoder", path, EncoderStage)[0] if "encoder" in tables else None
        return cls(*from_table(tables, "data", path, MapsData), *from_table(tables, "model", path, MapsConfig),
                   *from_table(tables, "train", path, MapsTrain), encoder, stage, specular, tables)


def prepare_data(data: MapsData, rank: int) -> tuple[Path, Path]:
    """The (maps, depth) dataset folders, rendering a cached one from ``source`` when not given."""
    if data.maps is not None and data.depth is not None:
        return Path(data.maps), Path(data.depth)
    cache = Path(data.cache_dir)
    depth_cache = Path(f"{cache}-coarse") if data.coarse_shapes else cache
    if rank == 0:
        config = DatasetConfig(source=data.source, num_shapes=data.num_shapes, views=data.views,
                               resolution=data.resolution, channels=("depth", "normal", "albedo", "noc", "mask"),
                               seed=data.seed)
        render_dataset(config, cache, progress=False, wait=CACHE_WAIT_SECONDS)
        if data.coarse_shapes:  # the paper decorates G_shape's coarse shapes, not the detailed ones
            try:
                reconstruct = pretrained.coarse_shapes(data.coarse_shapes, data.coarse_resolution)
            except (ValueError, FileNotFoundError) as error:
                raise ValueError(f"[data] coarse_shapes = {data.coarse_shapes!r}: {error}") from error
            coarse = dataclasses.replace(config, channels=("depth", "mask"), coarse_shapes=data.coarse_shapes,
                                         coarse_resolution=data.coarse_resolution)
            render_dataset(coarse, depth_cache, progress=False, reconstruct=reconstruct,
                           wait=CACHE_WAIT_SECONDS)
    loop.barrier()
    return cache, depth_cache


def require_coarse_pairs(model: MapsConfig, data: MapsData) -> None:
    """``normal_cycle_depth`` or ``normal_steps_depth = "coarse"`` needs the real maps' reconstructions:
    ``[data] coarse_shapes``."""
    if model.reads_coarse_pairs and data.coarse_shapes is None:
        key = "normal_cycle_depth" if model.normal_cycle_depth == "coarse" else "normal_steps_depth"
        raise ValueError(f"[model] {key} = 'coarse' reads the real maps' coarse reconstructions: "
                         "set [data] coarse_shapes (a `train shape` run or a model such as \"chair\")")


def maps_dataset(model: MapsConfig, data: MapsData, maps_root: Path, depth_root: Path,
                 log: Callable[[str], None] | None = None) -> ReflectanceMapDataset | WithCoarseDepth:
    """The real maps; with ``normal_cycle_depth`` or ``normal_steps_depth = "coarse"``, each view with its
    shape's coarse depth (the ``[data] coarse_shapes`` folder; views of a shape without a reconstruction
    are left out)."""
    maps = ReflectanceMapDataset(maps_root)
    if not model.reads_coarse_pairs:
        return maps
    require_coarse_pairs(model, data)
    paired = WithCoarseDepth(maps, depth_root, drop_unpaired=True)
    if paired.dropped and log is not None:
        log(f"train maps: {paired.dropped} of {len(maps)} real views have no coarse view in {depth_root} "
            "(empty reconstruction) and are left out")
    return paired


def normal_step_source(maps: Any, batch_size: int, seed: int, rank: int = 0, world: int = 1) -> loop.SeededBatches:
    """What G_n's own steps (``[model] normal_steps``) draw from: the real maps in an order of their own."""
    return loop.SeededBatches(maps, batch_size, seed + 3 * 10 ** 6, rank, world)


def normal_step_batches(batches: loop.SeededBatches, model: MapsConfig, step: int,
                        device: torch.device | None = None) -> list[dict[str, Any]]:
    """The maps batches of G_n's own steps at ``step`` (``[model] normal_steps`` − 1 of them): a
    function of the step, so a resumed run repeats them."""
    extra = model.normal_steps - 1
    return [loop.to_device(batches(step * extra + j), device or torch.device("cpu")) for j in range(extra)]


def prepare_real_images(data: MapsData, stage: SpecularStage, rank: int) -> Path:
    """The real-image folder of the specular stage, rendering path-traced images when not given."""
    if stage.real is not None:
        return Path(stage.real)
    cache = Path(data.cache_dir + "-real")
    if rank == 0:
        render_dataset(DatasetConfig(source=data.source, num_shapes=stage.num_shapes, views=stage.views,
                                     resolution=data.resolution, channels=("mask",), real_spp=stage.real_spp,
                                     seed=data.seed + 1), cache, progress=False, wait=CACHE_WAIT_SECONDS)
    loop.barrier()
    return cache


def prepare_encoder_data(data: MapsData, stage: EncoderStage, rank: int) -> Path:
    """The encoder stage's maps (depth, albedo, mask), rendered from ``[data] source`` into
    ``<cache_dir>-encoder`` from seed ``data.seed + EncoderStage.SEED_OFFSET``."""
    cache = Path(data.cache_dir + "-encoder")
    if rank == 0:
        render_dataset(DatasetConfig(source=data.source, num_shapes=stage.num_shapes, views=stage.views,
                                     resolution=data.resolution, channels=("depth", "albedo", "mask"),
                                     seed=data.seed + EncoderStage.SEED_OFFSET), cache, progress=False,
                       wait=CACHE_WAIT_SECONDS)
    loop.barrier()
    return cache


class EncoderViews(torch.utils.data.Dataset):
    """The encoder stage's views held in memory with G_da's condition (albedo, mask, ``condition``;
    :meth:`~ngp_mi.models.maps.MapsModel.encoder_condition`), computed once when the stage starts:
    G_n and G_da are fixed in it, and reading each batch's EXR files and running G_n again took a
    third of its step (bench/RESULTS.md)."""

    def __init__(self, views: ReflectanceMapDataset, model: MapsModel, device: torch.device, chunk: int = 32):
        parts: dict[str, list[torch.Tensor]] = {"albedo": [], "mask": [], "condition": []}
        for start in range(0, len(views), chunk):
            batch = loop.to_device(default_collate([views[i] for i in range(start, min(start + chunk, len(views)))]),
                                   device)
            parts["albedo"].append(batch["albedo"])
            parts["mask"].append(batch["mask"])
            parts["condition"].append(model.encoder_condition(batch))
        self.tensors = {name: torch.cat(tensors) for name, tensors in parts.items()}

    @staticmethod
    def mebibytes(views: ReflectanceMapDataset) -> float:
        """What the views would take: albedo, mask and the condition (NOC and N), float32."""
        first = views[0]["mask"]
        return len(views) * (3 + 1 + 6) * first.shape[-2] * first.shape[-1] * 4 / 2 ** 20

    def __len__(self) -> int:
        return len(self.tensors["mask"])

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {name: tensor[index] for name, tensor in self.tensors.items()}


def encoder_batches_of(views: ReflectanceMapDataset, model: MapsModel, stage: EncoderStage, seed: int, rank: int,
                       world: int, device: torch.device, log: Callable[[str], None]) -> loop.SeededBatches:
    """The encoder stage's batches, from :class:`EncoderViews` when they fit in ``stage.cache_mib``
    (the same batches as from the folder: the same items in the same order)."""
    size = EncoderViews.mebibytes(views)
    if size > stage.cache_mib:
        log(f"train maps: [encoder] reads its {len(views)} views per batch ({size:.0f} MiB > cache_mib "
            f"{stage.cache_mib})")
        return loop.SeededBatches(views, stage.batch_size, seed, rank, world)
    start = time.perf_counter()
    cached = EncoderViews(views, model, device)
    log(f"train maps: [encoder] holds its {len(views)} views and their G_da condition in memory "
        f"({size:.0f} MiB, {time.perf_counter() - start:.0f} s)")
    return loop.SeededBatches(cached, stage.batch_size, seed, rank, world)


def image_grid(visuals: dict[str, torch.Tensor]) -> np.ndarray:
    """The first item of every visual (network range [−1, 1]) side by side, labelled."""
    tiles = []
    for tensor in visuals.values():
        image = ((tensor[0].detach().float().cpu().clamp(-1, 1) + 1) / 2).permute(1, 2, 0).numpy()
        image = np.repeat(image, 3, -1) if image.shape[-1] == 1 else image
        tiles.append((image * 255).round().astype(np.uint8))
    return contact_sheet(tiles, list(visuals), columns=len(tiles))


def seed_from_maps_run(source: str | Path, run: str | Path, iterations: int) -> None:
    """Start ``run`` from ``source``'s map networks at step ``iterations`` (its checkpoint there, and
    its log up to there), so that training ``run`` trains only the G_sp^real stage, whose networks
    start fresh as ``run``'s recipe builds them (switches of that stage compared, or a stage
    re-trained, on one set of map networks). Nothing happens when ``run`` already has that step."""
    source, run = Path(source), Path(run)
    checkpoint = source / f"ckpt-{iterations:08d}"
    if not checkpoint.is_dir():
        raise ValueError(f"--maps-from {source}: no checkpoint at step {iterations} ([train] iterations); its map "
                         f"stage must have reached it")
    if (run / checkpoint.name).exists():
        return  # seeded before (a resumed run)
    # without the stage's networks (saved untrained with every checkpoint), which would override the
    # recipe's own initialisation on resume
    stage_networks = {*SpecularModel.network_names, "G_sp_train"}
    tensors = {k: v for k, v in load_file(checkpoint / "weights.safetensors").items()
               if k.split(".", 1)[0] not in stage_networks}
    lines = [line for line in (source / "log.jsonl").read_text().splitlines(keepends=True)
             if line.strip() and json.loads(line)["step"] <= iterations]
    write_text(run / "log.jsonl", "".join(lines))
    with atomic_path(run / checkpoint.name, directory=True) as folder:
        shutil.copy2(checkpoint / "state.pt", folder / "state.pt")
        save_file(tensors, folder / "weights.safetensors")


# [model] fields a G_sp^real stage re-trained on a model's map networks may change: R_diff's own k_d
# scales the diffuse images the stage reads and NGP's image, and nothing in G_n, G_da or E_da
# (which read depth, NOC and albedo), so the stage can be trained for another energy split.
RESHADE_FIELDS = ("k_diff",)


def seed_from_model(source: str | Path, run: str | Path, iterations: int, recipe: "MapsRecipe") -> None:
    """Start ``run`` from the map networks of a model folder or shipped model (``export-model``'s
    output), as :func:`seed_from_maps_run` does from a run: a checkpoint at step ``iterations``
    holds the folder's G_n, G_da and E_da (the trained copies under ``ema`` too); the networks a model
    does not ship (the discriminators, G_depth) are built as the recipe builds them, and the G_sp^real
    stage, which reads only the shipped three, is trained alone. The recipe's ``[model]`` must be the
    card's (another k_d, say, would change the highlights the stage reads), except for
    :data:`RESHADE_FIELDS`: a stage for R_diff at another ``k_diff`` is what they are for. The card's
    facts of the map networks (run, steps, training time, figures) go to ``maps_from.json``
    (:data:`~ngp_mi.models.pretrained.MAPS_FROM_FACTS`), which ``export-model`` carries onto the new card."""
    run = Path(run)
    if (run / f"ckpt-{iterations:08d}").exists():
        return  # seeded before (a resumed run)
    shipped, _, _, card = pretrained.load_model(source)
    ours = dataclasses.asdict(recipe.model)
    differ = [f"{key} ({value!r} in the recipe, {theirs!r} in the card)" for key, value in ours.items()
              if key not in RESHADE_FIELDS and value != (theirs := getattr(shipped.config, key))]
    if differ:
        raise ValueError(f"--maps-from {source}: the recipe's [model] differs from the model's card.json in "
                         f"{', '.join(differ)}; set them to the card's (--set model.FIELD=VALUE)")
    torch.manual_seed(recipe.train.seed)
    model = MapsModel(recipe.model)
    for name in pretrained.INFERENCE_NETWORKS["maps"]:
        for target in (name, f"{name}_train") if recipe.model.ema else (name,):
            getattr(model, target).load_state_dict(getattr(shipped, name).state_dict())
    # before the checkpoint, which marks the run as seeded
    write_text(run / pretrained.MAPS_FROM_FACTS, json.dumps({"model": str(source), **card.get("maps", {})}, indent=1))
    loop.save(run, iterations, [model], recipe.tables)


def train_maps(config_path: str | Path, log=print, out: str | Path | None = None, overrides: Sequence[str] = (),
               maps_from: str | Path | None = None) -> Path:
    """Train (or resume training) as the recipe says; ``out`` replaces ``[train] out``. With
    ``maps_from`` (a run whose map stage reached ``[train] iterations``, or a model folder / shipped
    name) the run starts from its map networks there and trains the later stages only (E_da's
    ``[encoder]``, G_sp^real's ``[specular]``)
    (:func:`seed_from_maps_run`, :func:`seed_from_model`). Returns the output folder."""
    overrides = [*overrides, *([out_override(out)] if out else [])]
    recipe = MapsRecipe.read(config_path, overrides)
    train = recipe.train
    device, rank, world = loop.start_processes(train.device)
    out = Path(train.out)
    if maps_from is not None:
        if recipe.specular is None and recipe.encoder is None:
            raise ValueError(f"{config_path}: --maps-from trains the stages after the map stage ([encoder], "
                             "[specular]), and the recipe has neither")
        if rank == 0 and pretrained.is_training_run(maps_from):
            seed_from_maps_run(maps_from, out, train.iterations)
        elif rank == 0:
            seed_from_model(maps_from, out, train.iterations, recipe)
        loop.barrier()
    maps_root, depth_root = prepare_data(recipe.data, rank)
    maps = maps_dataset(recipe.model, recipe.data, maps_root, depth_root, log if rank == 0 else None)
    maps_batches = loop.SeededBatches(maps, train.batch_size, train.seed, rank, world)
    depth_batches = loop.SeededBatches(DepthDataset(depth_root), train.batch_size, train.seed + 10 ** 6, rank, world)
    normal_batches = normal_step_source(maps, train.batch_size, train.seed, rank, world)

    torch.manual_seed(train.seed)  # identical initial weights on every rank
    model = MapsModel(recipe.model).to(device)  # in place: the optimisers keep their parameters
    specular, real_batches = None, None
    if recipe.specular is not None:
        specular = SpecularModel(recipe.specular).to(device)
        real_root = prepare_real_images(recipe.data, recipe.stage, rank)
        real_batches = loop.SeededBatches(ImageFolderDataset(real_root, size=recipe.data.resolution, linear=True),
                                          train.batch_size, train.seed + 2 * 10 ** 6, rank, world)
    encoder_views, encoder_batches = None, None
    if recipe.encoder is not None:
        encoder_views = ReflectanceMapDataset(prepare_encoder_data(recipe.data, recipe.encoder, rank))
    models = [model] + ([specular] if specular is not None else [])
    # A checkpoint from before the [specular] table holds the map networks only: the stage starts fresh.
    step, resumed_from = loop.resume(out, [model], optional=models[1:])
    if rank == 0:
        if resumed_from is not None:
            log(f"train maps: resuming from {resumed_from} (step {step})")
        log(f"train maps: {world} process(es) on {device}")
        out.mkdir(parents=True, exist_ok=True)
        record(out, config_path, overrides, recipe.tables)
    if world > 1:
        for m in models:
            m.gradient_hook = loop.average_gradients

    maps_iterations = train.iterations
    encoder_end = maps_iterations + (recipe.encoder.iterations if recipe.encoder is not None else 0)
    iterations = encoder_end + (recipe.stage.iterations if specular is not None else 0)
    log_file = loop.JsonLog(out, step) if rank == 0 else None
    writer = loop.tensorboard(out) if rank == 0 else None
    bar = tqdm(total=iterations, initial=step, unit="it", disable=rank != 0, desc="train maps")
    start, first = time.perf_counter(), step
    while step < iterations:
        loop.reseed(train.seed, step, world, rank)
        # the later stages read the map networks as inference does (with [model] ema: the averages)
        model.train(step < maps_iterations)
        if step < maps_iterations:
            stage, visuals = "maps", model
            lr = model.scale_learning_rates(loop.linear_decay(step, maps_iterations, train.lr_decay_from))
            losses = model.optimize(loop.to_device(depth_batches(step), device),
                                    loop.to_device(maps_batches(step), device),
                                    normal_step_batches(normal_batches, model.config, step, device))
            losses["lr"] = lr
        elif step < encoder_end:
            stage, visuals = "encoder", model
            if encoder_batches is None:  # here, not before: G_da's condition is that of the final G_n
                encoder_batches = encoder_batches_of(encoder_views, model, recipe.encoder, train.seed + 4 * 10 ** 6,
                                                     rank, world, device, log if rank == 0 else lambda *_: None)
            losses = model.optimize_encoder(loop.to_device(encoder_batches(step), device), recipe.encoder.lr)
        else:
            stage, visuals = "specular", specular
            exemplars = (loop.to_device(maps_batches(step), device)
                         if specular.config.diffuse_input == "exemplar" else None)
            losses = specular.optimize(model, loop.to_device(depth_batches(step), device),
                                       real_batches(step).to(device), exemplars)
        step += 1
        bar.update(1)
        if log_file is None:
            continue
        last = step in (iterations, maps_iterations, encoder_end)
        if step % train.log_every == 0 or last:
            log_file.write({"step": step, "stage": stage, "time": round(time.perf_counter() - start, 3),
                            "it_per_s": round((step - first) / (time.perf_counter() - start), 3), "world": world,
                            **losses})
            if writer is not None:
                for key, value in losses.items():
                    writer.add_scalar(f"{stage}/{key}", value, step)
        if step % train.image_every == 0 or last:
            save_png(out / "images" / f"step-{step:08d}.png", image_grid(visuals.visuals))
        if step % train.checkpoint_every == 0 or last:
            loop.save(out, step, models, recipe.tables)
    bar.close()
    if world > 1:
        loop.check_in_sync(models, log_file, step, world)
    return out
