"""Where dataset shapes come from: a procedural family, a folder of meshes, or Mitsuba scene files.

``resolve_source(source, num_shapes, seed)`` returns :class:`SourceItem` s whose ``load()``
builds the Mitsuba shapes lazily (a bad mesh fails when its turn comes, with its reason):

* ``chair`` / ``car`` — procedural objects ``seed, seed+1, …`` with their part materials;
* a folder of meshes or a ShapeNet-style tree (``geometry.loaders.find_meshes``), or one mesh
  file — normalised; parts get materials from a seeded palette;
* a Mitsuba scene file (``.xml``), or a folder of them. The file must contain at least one shape
  (with its BSDF) placed like a normalised object: centred at the origin within radius ≈ 0.5
  (the camera distribution looks at the origin from distance 2; the scene is not rescaled). Its
  emitters are used when the dataset asks for the scene's own lights; its sensors and integrator
  are ignored.

:func:`autoencoded_items` turns the shapes of a family or mesh source into NGP's *coarse* shapes:
each is voxelised, encoded and decoded by a trained shape autoencoder (``ngp-mi train shape``)
and extracted by marching cubes — what G_shape produces, for shapes whose detailed version is
known (``render-dataset --coarse-shapes RUN``; ``evaluate maps`` pairs their views by shape id).
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ngp_mi import backend
from ngp_mi.geometry.families import FAMILIES, Material, generate
from ngp_mi.geometry.loaders import MESH_SUFFIXES, find_meshes, load_mesh
from ngp_mi.render.scene import mesh_parts_to_mitsuba


@dataclasses.dataclass
class SceneContent:
    """What a source item puts in a scene: shapes (with BSDFs), NOC bounds, optional emitters."""

    shapes: dict[str, Any]
    bounds: np.ndarray
    emitters: dict[str, Any] = dataclasses.field(default_factory=dict)
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class SourceItem:
    id: str
    kind: str  # "procedural" | "mesh" | "scene" | "autoencoded"
    origin: str
    load: Callable[[], SceneContent]


def palette_materials(shape_id: str, part_ids: np.ndarray) -> dict[int, Material]:
    """Deterministic materials for the parts of a user mesh (seeded by its id)."""
    rng = np.random.default_rng(zlib.crc32(shape_id.encode()))
    return {int(p): Material(tuple(float(x) for x in rng.uniform(0.1, 0.8, 3)), specular=float(rng.uniform(0.2, 0.6)),
                             roughness=float(rng.uniform(0.3, 0.9))) for p in np.unique(part_ids)}


def _procedural(family: str, seed: int) -> SourceItem:
    def load() -> SceneContent:
        obj = generate(family, seed)
        mesh = obj.mesh()
        shapes = mesh_parts_to_mitsuba(mesh, {k: m.to_mitsuba() for k, m in obj.materials.items()})
        return SceneContent(shapes, mesh.bounds, meta={
            "params": obj.params, "materials": {obj.part_names[k]: m.to_dict() for k, m in obj.materials.items()}})

    return SourceItem(f"{family}/{seed:06d}", "procedural", family, load)


def _mesh(shape_id: str, path: Path) -> SourceItem:
    def load() -> SceneContent:
        mesh = load_mesh(path)
        materials = palette_materials(shape_id, mesh.part_ids)
        shapes = mesh_parts_to_mitsuba(mesh, {k: m.to_mitsuba() for k, m in materials.items()})
        return SceneContent(shapes, mesh.bounds, meta={
            "parts": len(materials), "materials": {str(k): m.to_dict() for k, m in materials.items()}})

    return SourceItem(shape_id, "mesh", str(path), load)


def _scene(shape_id: str, path: Path) -> SourceItem:
    def load() -> SceneContent:
        mi = backend.mitsuba()
        try:
            scene = mi.load_file(str(path))
        except Exception as exc:  # Mitsuba raises RuntimeError with the parser's message
            raise ValueError(f"{path}: not a loadable Mitsuba scene ({exc})") from None
        shapes = {f"shape_{i}": shape for i, shape in enumerate(scene.shapes())}
        if not shapes:
            raise ValueError(f"{path}: the scene contains no shapes")
        bbox = scene.bbox()
        bounds = np.array([list(bbox.min), list(bbox.max)], np.float64)
        emitters = {f"emitter_{i}": e for i, e in enumerate(scene.emitters())}
        return SceneContent(shapes, bounds, emitters, meta={"shapes": len(shapes), "emitters": len(emitters)})

    return SourceItem(shape_id, "scene", str(path), load)


def resolve_source(source: str, num_shapes: int, seed: int = 0) -> list[SourceItem]:
    """The first ``num_shapes`` items of ``source`` (a family name, a mesh / scene file or folder)."""
    if num_shapes < 1:
        raise ValueError(f"num_shapes must be >= 1, got {num_shapes}")
    if source in FAMILIES:
        return [_procedural(source, seed + i) for i in range(num_shapes)]
    path = Path(source)
    if path.is_file():
        if path.suffix.lower() == ".xml":
            return [_scene(path.stem, path)]
        if path.suffix.lower() in MESH_SUFFIXES:
            return [_mesh(path.stem, path)]
        raise ValueError(f"{path}: not a mesh ({', '.join(MESH_SUFFIXES)}) or Mitsuba scene (.xml)")
    if path.is_dir():
        scenes = sorted(path.glob("*.xml"))
        if scenes:
            return [_scene(p.stem, p) for p in scenes[:num_shapes]]
        meshes = find_meshes(path)
        if not meshes:
            raise ValueError(f"{path}: no meshes ({', '.join(MESH_SUFFIXES)}) or scene files found")
        return [_mesh(m.id, m.path) for m in meshes[:num_shapes]]
    raise ValueError(f"--source {source!r}: not a family ({', '.join(sorted(FAMILIES))}), file or folder")


def autoencoded_items(source: str, num_shapes: int, seed: int, shape_run: str | Path,
                      resolution: int = 64) -> list[SourceItem]:
    """The shapes of ``source`` reconstructed by the shape autoencoder of ``shape_run``.

    Ids are the original shapes' ids, so the views of a dataset of these coarse shapes pair with
    the views of the detailed ones (same seed: same cameras). Every part gets one grey diffuse
    material (the coarse shape carries no parts). A shape the autoencoder turns empty fails when
    its turn comes, with that reason.
    """
    import torch

    from ngp_mi.data.shapes import shape_items
    from ngp_mi.train_shape import load_shape_model

    if source not in FAMILIES and Path(source).suffix.lower() == ".xml":
        raise ValueError(f"--coarse-shapes needs a family or mesh source, not a scene file: {source!r}")
    model = load_shape_model(shape_run)
    voxel_resolution = model.config.voxel_resolution
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}

    def coarse(item: Any) -> SourceItem:
        def load() -> SceneContent:
            _, _, grid = item.load()
            voxels = torch.from_numpy(grid(voxel_resolution)).float()[None, None]
            with torch.no_grad():
                code = model.encode(voxels.to(model.device))[0]
            extraction = model.extract(code, resolution)
            if extraction.mesh is None:
                raise ValueError(f"{item.id}: the autoencoder of {shape_run} reconstructs an empty shape")
            mesh = extraction.mesh
            return SceneContent(mesh_parts_to_mitsuba(mesh, default_bsdf=grey), mesh.bounds,
                                meta={"coarse_of": item.id, "shape_run": str(shape_run), "resolution": resolution,
                                      "faces": int(len(mesh.faces))})

        return SourceItem(item.id, "autoencoded", str(source), load)

    return [coarse(item) for item in shape_items(source, num_shapes, seed)]
