"""Shipped models: the inference networks of one family's NGP in one folder, weights only, with a card.

Layout of a model folder (``ngp_mi/pretrained/<name>/`` inside the package, or any folder)::

    maps.safetensors    G_n, G_da, E_da and, with the realistic specular stage, G_sp (prefixed by name)
    shape.safetensors   G_shape: the implicit decoder and the latent generator (optional)
    card.json           family, the models' configs, the recipes, steps, training time, machine,
                        the evaluation figures, and the sha256 of each weights file

Training keeps discriminators, the encoders used only by the cycles (G_depth, F_sp, the voxel
encoder) and optimiser states in its checkpoints; a shipped model drops them (a ``cpu`` model is a
few MB). Loading reads safetensors and JSON only: nothing is executed.
"""

from __future__ import annotations

import hashlib
import json
import platform
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from ngp_mi.atomic import atomic_path, write_json
from ngp_mi.models.base import config_from_dict
from ngp_mi.models.checkpoint import load_weights, module_tensors, newest_checkpoint, newest_readable
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.shape import CoarseShapes, ShapeConfig, ShapeModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel

PRETRAINED_ROOT = Path(__file__).resolve().parents[1] / "pretrained"
# G_shape's encoder reconstructs a given shape (NGP's coarse shapes, `render-dataset --coarse-shapes`); model
# folders exported before it was shipped hold the other two and load with ``has_encoder`` False.
INFERENCE_NETWORKS = {"maps": ("G_n", "G_da", "E_da"), "specular": ("G_sp",), "shape": ("encoder", "decoder", "G_latent")}
# Networks stored in float16 and loaded back as float32. The encoder only turns a given shape into the
# code of its coarse version (`--coarse-shapes`); rounded, its reconstructions keep their IoU (bench/RESULTS.md)
# and both families' encoders fit the 30 MB the shipped models may take. What the images depend on stays float32.
HALF_PRECISION = {"shape": ("encoder",)}
# In a `train maps` run whose map networks came from a model folder (`--maps-from FOLDER`): that card's
# facts of them, which `export-model` carries onto the new card as `maps.map_networks_from`.
MAPS_FROM_FACTS = "maps_from.json"


def available() -> list[str]:
    """Names of the models shipped in the package."""
    return sorted(p.name for p in PRETRAINED_ROOT.glob("*") if (p / "card.json").exists())


def resolve(name_or_path: str | Path) -> Path:
    """A shipped model's folder by name (``chair``, ``car``), or a model folder; the error lists what exists."""
    path = Path(name_or_path)
    if (path / "card.json").exists():
        return path
    if (PRETRAINED_ROOT / str(name_or_path) / "card.json").exists():
        return PRETRAINED_ROOT / str(name_or_path)
    shipped = ", ".join(available()) or f"none shipped in this install: {PRETRAINED_ROOT} holds no model"
    raise ValueError(f"--model {name_or_path!r}: not a shipped model ({shipped}) nor a folder with card.json; "
                     "`ngp-mi export-model` writes one from training runs")


def _tensors(model: Any, names: tuple[str, ...], prefix: str) -> dict[str, torch.Tensor]:
    """The weights of ``model``'s networks ``names`` as a model folder stores them (``HALF_PRECISION``)."""
    half = HALF_PRECISION.get(prefix, ())
    return {key: value.half() if key.split(".")[1] in half and value.dtype == torch.float32 else value
            for key, value in module_tensors({name: getattr(model, name) for name in names}, f"{prefix}.").items()}


def _file_facts(path: Path) -> dict[str, Any]:
    """A weights file's entry in the card: size, sha256 and the networks it holds in float16."""
    prefix = path.stem
    with safe_open(path, framework="pt") as f:
        keys = list(f.keys())
    half = [f"{prefix}.{name}" for name in HALF_PRECISION.get(prefix, ())
            if any(key.startswith(f"{prefix}.{name}.") for key in keys)]
    return {"bytes": path.stat().st_size, "sha256": _sha256(path), **({"float16": half} if half else {})}


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run_facts(run: Path) -> dict[str, Any]:
    """Steps, training time and recipe of a run (from its newest checkpoint and log); for a run whose
    map networks came from a model folder (``train maps --maps-from``), that card's facts of them."""
    path, state = newest_readable(run)
    facts: dict[str, Any] = {"run": str(run), "checkpoint": path.name, "steps": int(state["step"]),
                             "recipe": json.loads(state["config"]) if "config" in state else None}
    if (run / MAPS_FROM_FACTS).exists():
        facts["map_networks_from"] = json.loads((run / MAPS_FROM_FACTS).read_text())
    log = run / "log.jsonl"
    if log.exists():
        times = [json.loads(line).get("time") for line in log.read_text().splitlines() if line.strip()]
        seconds = training_seconds([t for t in times if t is not None])
        if seconds:
            facts["training_seconds"] = round(seconds, 1)
    # what `train shape`, `evaluate maps` and `compare --maps-checkpoint` (its per-method summary) measured
    for name, part in (("metrics.json", None), ("eval/eval.json", None), ("compare/results.json", "summary")):
        if (run / name).exists():
            measured = json.loads((run / name).read_text())
            facts.setdefault("figures", {})[name] = measured[part] if part else measured
    return facts


def _provenance(name_or_path: str | Path, card: dict[str, Any], file: str) -> dict[str, Any]:
    """Where a kept part came from, in facts that outlive the folder: a folder given by path is often a
    local copy (a shipped model before its re-export), so its notes and the part's sha256 name it too."""
    return {"model": str(name_or_path), "notes": card.get("notes", ""),
            "sha256": ((card.get("files") or {}).get(file) or {}).get("sha256")}


def training_seconds(times: list[float]) -> float:
    """Wall time of a run from its log's times, which restart from 0 in each resumed process: the
    sum of each process's last time."""
    total = 0.0
    for previous, current in zip(times, times[1:] + [None]):
        if current is None or current < previous:
            total += previous
    return total


def export_model(out: str | Path, maps_run: str | Path, shape_run: str | Path | None = None, family: str = "",
                 figures: dict[str, Any] | None = None, notes: str = "",
                 shape_from: str | Path | None = None, specular_from: str | Path | None = None) -> Path:
    """Write the inference networks of ``maps_run`` (and ``shape_run``) into the model folder ``out``.

    ``shape_from`` (a model folder or a shipped name, instead of ``shape_run``) keeps that model's
    G_shape and its card facts: the map networks and the shape prior train apart, so re-training
    the maps need not re-train the prior. ``specular_from`` keeps that model's G_sp^real instead of
    the run's stage: a stage trained on the same G_n and G_da (their weights must be equal, and the
    maps' configuration: G_sp^real reads their images), chosen over a re-trained one."""
    if shape_run and shape_from:
        raise ValueError("export-model: --shape-run or --shape-from, not both")
    out = Path(out)
    maps, specular = MapsModel.from_run(maps_run), SpecularModel.from_run(maps_run)
    specular_kept_from = None
    if specular_from:
        specular, specular_kept_from = _kept_specular(specular_from, maps, out)
    shape, shape_facts = None, None
    if shape_run:
        shape, shape_facts = ShapeModel.from_run(shape_run), _run_facts(Path(shape_run))
        kept = ((shape_facts.get("recipe") or {}).get("train") or {}).get("encoder_for")
        if kept:  # an encoder trained for another prior's G_shape: carry that prior's facts too
            shape_facts["decoder_and_G_latent"] = json.loads((resolve(kept) / "card.json").read_text())["shape"]
    elif shape_from:
        *_, shape, kept_card = load_model(shape_from)  # read (and sha-checked) before out is written
        if shape is None:
            raise ValueError(f"export-model --shape-from {shape_from}: that model has no G_shape (shape.safetensors)")
        kept_from = _provenance(shape_from, kept_card, "shape.safetensors")
        if resolve(shape_from).resolve() == out.resolve() and isinstance(kept_card["shape"].get("kept_from"), dict):
            kept_from = kept_card["shape"]["kept_from"]  # re-exported over itself: the prior came from where it did
        shape_facts = {**kept_card["shape"], "kept_from": kept_from}
    out.mkdir(parents=True, exist_ok=True)
    tensors = _tensors(maps, INFERENCE_NETWORKS["maps"], "maps")
    configs: dict[str, Any] = {"maps": maps.config_dict()["maps"]}
    if specular is not None:
        tensors.update(_tensors(specular, INFERENCE_NETWORKS["specular"], "specular"))
        configs["specular"] = specular.config_dict()["specular"]
    files = {"maps.safetensors": tensors}
    if shape is not None:
        # a prior kept from a folder that ships no encoder stays without one (its weights were never trained)
        files["shape.safetensors"] = _tensors(shape, _shape_networks(shape.has_encoder), "shape")
        configs["shape"] = shape.config_dict()["shape"]
    for name, data in files.items():
        with atomic_path(out / name) as tmp:
            save_file(data, tmp)
    maps_facts = _run_facts(Path(maps_run))
    if specular_kept_from:
        maps_facts["specular_kept_from"] = specular_kept_from
    card = {"family": family, "configs": configs, "maps": maps_facts, "shape": shape_facts,
            "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                        "torch": torch.__version__},
            "figures": figures or {}, "notes": notes,
            "files": {name: _file_facts(out / name) for name in files}}
    write_json(out / "card.json", card)
    return out


def _kept_specular(name_or_path: str | Path, maps: MapsModel, out: Path) -> tuple[SpecularModel, dict[str, Any]]:
    """G_sp^real of a model folder, for maps networks ``maps`` (a run's), with where it came from."""
    kept_maps, specular, _, card = load_model(name_or_path)  # read (and sha-checked) before out is written
    where = f"export-model --specular-from {name_or_path}"
    if specular is None:
        raise ValueError(f"{where}: that model has no G_sp^real stage")
    if kept_maps.config_dict()["maps"] != maps.config_dict()["maps"]:
        raise ValueError(f"{where}: its [model] configuration differs from the run's; G_sp^real reads the images "
                         "of the map networks it was trained on")
    ours, theirs = _tensors(maps, ("G_n", "G_da"), "maps"), _tensors(kept_maps, ("G_n", "G_da"), "maps")
    if ours.keys() != theirs.keys() or any(not torch.equal(ours[k], theirs[k]) for k in ours):
        raise ValueError(f"{where}: its G_n and G_da differ from the run's, so its G_sp^real was trained on other "
                         "maps")
    facts = {**_provenance(name_or_path, card, "maps.safetensors"), "stage": card["maps"]}
    if resolve(name_or_path).resolve() == out.resolve() and isinstance(card["maps"].get("specular_kept_from"), dict):
        facts = card["maps"]["specular_kept_from"]  # re-exported over itself: the stage came from where it did
    return specular, facts


def add_encoder(folder: str | Path, source: str | Path) -> Path:
    """Put the encoder of ``source`` into the model folder whose G_shape it was trained for; the maps and
    the rest of the card stay (for folders whose runs are gone). ``source`` is a ``train shape`` run with
    ``[train] encoder_for``, or a model folder with the same decoder (the folder itself re-writes its
    encoder as folders now store it, ``HALF_PRECISION``)."""
    folder = resolve(folder)
    card = json.loads((folder / "card.json").read_text())
    if "shape" not in card["configs"]:
        raise ValueError(f"{folder}: this model ships no shape prior to add an encoder to")
    kept, trained = _shape_of(folder, card["configs"]), load_shape_prior(source)
    trained.require_encoder()
    for name in ("decoder", "G_latent"):
        ours, theirs = getattr(trained, name).state_dict(), getattr(kept, name).state_dict()
        if ours.keys() != theirs.keys() or any(not torch.equal(ours[k], theirs[k]) for k in ours):
            raise ValueError(f"{source}: its {name} differs from {folder}'s, so its encoder was not trained for this "
                             "prior (train it with [train] encoder_for)")
    with atomic_path(folder / "shape.safetensors") as tmp:
        save_file(_tensors(trained, INFERENCE_NETWORKS["shape"], "shape"), tmp)
    if is_training_run(source):
        card["shape"] = {**_run_facts(Path(source)), "decoder_and_G_latent": card["shape"]}
    elif resolve(source).resolve() != folder.resolve():
        card["shape"] = {**json.loads((resolve(source) / "card.json").read_text())["shape"], "encoder_from": str(source)}
    card["files"]["shape.safetensors"] = _file_facts(folder / "shape.safetensors")
    write_json(folder / "card.json", card)
    return folder


def _shape_networks(has_encoder: bool) -> tuple[str, ...]:
    """The G_shape networks a model folder holds: the encoder only where it was trained."""
    return tuple(name for name in INFERENCE_NETWORKS["shape"] if has_encoder or name != "encoder")


def _load_into(model: Any, tensors: dict[str, torch.Tensor], prefix: str, names: tuple[str, ...], file: Path) -> None:
    own = {key[len(prefix) + 1:]: value.float() if value.dtype == torch.float16 else value  # HALF_PRECISION
           for key, value in tensors.items() if key.startswith(f"{prefix}.")}
    load_weights({name: getattr(model, name) for name in names}, own, file)


def load_model(name_or_path: str | Path) -> tuple[MapsModel, SpecularModel | None, ShapeModel | None, dict[str, Any]]:
    """The models of a shipped model folder (eval mode, CPU) and its card."""
    folder = resolve(name_or_path)
    card = json.loads((folder / "card.json").read_text())
    configs = card["configs"]
    for name, facts in card.get("files", {}).items():
        if (folder / name).exists() and _sha256(folder / name) != facts["sha256"]:
            raise ValueError(f"{folder / name}: its sha256 differs from card.json's (a damaged or replaced file)")
    weights = load_file(folder / "maps.safetensors")
    maps = MapsModel(config_from_dict(MapsConfig, configs["maps"]))
    _load_into(maps, weights, "maps", INFERENCE_NETWORKS["maps"], folder / "maps.safetensors")
    specular = None
    if "specular" in configs:
        specular = SpecularModel(config_from_dict(SpecularConfig, configs["specular"]))
        _load_into(specular, weights, "specular", INFERENCE_NETWORKS["specular"], folder / "maps.safetensors")
    shape = _shape_of(folder, configs) if "shape" in configs else None
    return maps.eval(), specular.eval() if specular is not None else None, shape, card


def _shape_of(folder: Path, configs: dict[str, Any]) -> ShapeModel:
    shape = ShapeModel(config_from_dict(ShapeConfig, configs["shape"]))
    tensors = load_file(folder / "shape.safetensors")
    # a folder exported before the encoder was shipped holds the other two
    shape.has_encoder = any(key.startswith("shape.encoder.") for key in tensors)
    _load_into(shape, tensors, "shape", _shape_networks(shape.has_encoder), folder / "shape.safetensors")
    shape.source = str(folder)
    return shape.eval()


def is_training_run(path: str | Path) -> bool:
    """Whether ``path`` is a ``train maps`` / ``train shape`` output folder (it holds ``recipe.json``)
    rather than a model folder or a shipped name."""
    return (Path(path) / "recipe.json").exists()


def load_shape_prior(run_or_model: str | Path) -> ShapeModel:
    """G_shape of a ``train shape`` run or of a model folder / shipped name."""
    if is_training_run(run_or_model):
        model = ShapeModel.from_run(run_or_model)
        if model is None:
            raise ValueError(f"{run_or_model}: no `train shape` checkpoint yet")
        return model
    return load_shape(run_or_model)


def load_map_networks(run_or_model: str | Path) -> tuple[MapsModel, str]:
    """The map networks of a ``train maps`` run's newest checkpoint or of a model folder / shipped
    name, and what they are (the checkpoint's path, or the folder's)."""
    if is_training_run(run_or_model):
        model = MapsModel.from_run(run_or_model)
        if model is None:
            raise ValueError(f"{run_or_model}: no `train maps` checkpoint yet")
        return model, str(newest_checkpoint(run_or_model))
    maps, *_ = load_model(run_or_model)
    return maps, str(resolve(run_or_model))


def load_ngp_networks(run_or_model: str | Path) -> tuple[MapsModel, SpecularModel | None]:
    """The map networks and G_sp^real (None when there is no such stage) of a ``train maps`` run's
    newest checkpoint or of a model folder / shipped name."""
    if is_training_run(run_or_model):
        maps, _ = load_map_networks(run_or_model)
        return maps, SpecularModel.from_run(run_or_model)
    maps, specular, *_ = load_model(run_or_model)
    return maps, specular


def trained_source(run_or_model: str | Path) -> str:
    """The ``[data] source`` the map networks of a ``train maps`` run (its newest checkpoint's recipe)
    or of a model folder / shipped name (its card's maps recipe, else its family) were trained on."""
    if is_training_run(run_or_model):
        return json.loads(newest_readable(run_or_model)[1]["config"]).get("data", {}).get("source", "chair")
    card = json.loads((resolve(run_or_model) / "card.json").read_text())
    return card.get("maps", {}).get("recipe", {}).get("data", {}).get("source") or card.get("family") or "chair"


def coarse_shapes(run_or_model: str | Path, resolution: int) -> CoarseShapes:
    """The ``reconstruct`` of ``render-dataset --coarse-shapes`` and ``[data] coarse_shapes``: a
    ``train shape`` run's or a model's G_shape, checked here for its encoder (not per shape, in the
    workers that load it again)."""
    load_shape_prior(run_or_model).require_encoder()
    return CoarseShapes(run_or_model, resolution, load=load_shape_prior)


def load_shape(name_or_path: str | Path) -> ShapeModel:
    """G_shape of a shipped model folder (eval mode, CPU): what ``render-dataset --coarse-shapes chair``
    reconstructs with (:class:`ngp_mi.models.shape.CoarseShapes`); the error names a folder without one."""
    folder = resolve(name_or_path)
    configs = json.loads((folder / "card.json").read_text())["configs"]
    if "shape" not in configs:
        raise ValueError(f"{folder}: this model ships no shape prior (card.json has no 'shape' config)")
    return _shape_of(folder, configs)
