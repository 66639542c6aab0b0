"""What the dataset renderer puts in a scene for each shape of a source (:mod:`ngp_mi.geometry.sources`).

``resolve_source(source, num_shapes, seed)`` (or :func:`source_items` of shapes already resolved)
returns :class:`SourceItem` s whose ``load()`` builds the Mitsuba shapes lazily (a bad mesh fails
when its turn comes, with its reason):

* ``chair`` / ``car`` — procedural objects ``seed, seed+1, …`` with their part materials;
* a folder of meshes or a ShapeNet-style tree (``geometry.loaders.find_meshes``), or one mesh
  file — normalised; parts get materials from a seeded palette;
* a Mitsuba scene file (``.xml``), or a folder of them. The file must contain at least one shape
  (with its BSDF) placed like a normalised object: centred at the origin within radius ≈ 0.5
  (the camera distribution looks at the origin from distance 2; the scene is not rescaled). Its
  emitters are used when the dataset asks for the scene's own lights; its sensors and integrator
  are ignored.

:func:`autoencoded_items` turns the shapes of a family or mesh source into NGP's *coarse* shapes
through a reconstruction the caller passes (the shape autoencoder's: voxelised, encoded, decoded
and extracted, what G_shape produces) for shapes whose detailed version is known
(``render-dataset --coarse-shapes RUN``; ``evaluate maps`` pairs their views by shape id).
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ngp_mi import backend
from ngp_mi.geometry.families import FAMILIES, Material, generate
from ngp_mi.geometry.loaders import load_mesh
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.sources import SCENE_SUFFIX, ShapeRef, resolve_shapes
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


def _procedural(ref: ShapeRef) -> SourceItem:
    def load() -> SceneContent:
        obj = generate(ref.origin, ref.seed)
        mesh = obj.mesh()
        shapes = mesh_parts_to_mitsuba(mesh, {k: m.to_mitsuba() for k, m in obj.materials.items()})
        return SceneContent(shapes, mesh.bounds, meta={
            "params": obj.params, "materials": {obj.part_names[k]: m.to_dict() for k, m in obj.materials.items()}})

    return SourceItem(ref.id, ref.kind, ref.origin, load)


def _mesh(ref: ShapeRef) -> SourceItem:
    def load() -> SceneContent:
        mesh = load_mesh(ref.path)
        materials = palette_materials(ref.id, mesh.part_ids)
        shapes = mesh_parts_to_mitsuba(mesh, {k: m.to_mitsuba() for k, m in materials.items()})
        return SceneContent(shapes, mesh.bounds, meta={
            "parts": len(materials), "materials": {str(k): m.to_dict() for k, m in materials.items()}})

    return SourceItem(ref.id, ref.kind, ref.origin, load)


def _scene(ref: ShapeRef) -> SourceItem:
    def load() -> SceneContent:
        mi = backend.mitsuba()
        try:
            scene = mi.load_file(str(ref.path))
        except Exception as exc:  # Mitsuba raises RuntimeError with the parser's message
            raise ValueError(f"{ref.path}: not a loadable Mitsuba scene ({exc})") from None
        shapes = {f"shape_{i}": shape for i, shape in enumerate(scene.shapes())}
        if not shapes:
            raise ValueError(f"{ref.path}: the scene contains no shapes")
        bbox = scene.bbox()
        bounds = np.array([list(bbox.min), list(bbox.max)], np.float64)
        emitters = {f"emitter_{i}": e for i, e in enumerate(scene.emitters())}
        return SceneContent(shapes, bounds, emitters, meta={"shapes": len(shapes), "emitters": len(emitters)})

    return SourceItem(ref.id, ref.kind, ref.origin, load)


_LOADERS = {"procedural": _procedural, "mesh": _mesh, "scene": _scene}


def source_items(refs: Sequence[ShapeRef]) -> list[SourceItem]:
    """The items of shapes :func:`~ngp_mi.geometry.sources.resolve_shapes` found."""
    return [_LOADERS[ref.kind](ref) for ref in refs]


def resolve_source(source: str, num_shapes: int, seed: int = 0) -> list[SourceItem]:
    """The first ``num_shapes`` items of ``source`` (:func:`~ngp_mi.geometry.sources.resolve_shapes`)."""
    return source_items(resolve_shapes(source, num_shapes, seed))


class Reconstruct(Protocol):
    """A shape's coarse version: given the shape's occupancy grid function (resolution → bool
    grid), the coarse mesh, or None when it is empty. ``meta`` goes into each item's record."""

    meta: dict[str, Any]

    def __call__(self, grid: Callable[[int], np.ndarray]) -> TriangleMesh | None: ...


def coarse_shapes_of(source: str, num_shapes: int, seed: int) -> list[ShapeRef]:
    """The shapes of ``source`` that have coarse versions: a family or meshes, not scenes."""
    if source not in FAMILIES and Path(source).suffix.lower() == SCENE_SUFFIX:
        raise ValueError(f"--coarse-shapes needs a family or mesh source, not a scene file: {source!r}")
    return resolve_shapes(source, num_shapes, seed, scenes=False)


def autoencoded_items(refs: Sequence[ShapeRef], reconstruct: Reconstruct) -> list[SourceItem]:
    """The shapes ``refs`` (:func:`coarse_shapes_of` a source) as ``reconstruct`` gives them (NGP's
    coarse shapes: the shape autoencoder's reconstructions, :class:`ngp_mi.models.shape.CoarseShapes`).

    Ids are the original shapes' ids, so the views of a dataset of these coarse shapes pair with
    the views of the detailed ones (same seed: same cameras). Every part gets one grey diffuse
    material (the coarse shape carries no parts). A shape that comes back empty fails when its
    turn comes, with that reason.
    """
    # Here, not at the top: occupancy imports torch (~3 s), which dataset workers otherwise go without.
    from ngp_mi.geometry.occupancy import load_solid

    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}

    def coarse(ref: ShapeRef) -> SourceItem:
        def load() -> SceneContent:
            mesh = reconstruct(load_solid(ref).grid)
            if mesh is None:
                raise ValueError(f"{ref.id}: the reconstruction ({reconstruct.meta}) is an empty shape")
            return SceneContent(mesh_parts_to_mitsuba(mesh, default_bsdf=grey), mesh.bounds,
                                meta={"coarse_of": ref.id, **reconstruct.meta, "faces": int(len(mesh.faces))})

        return SourceItem(ref.id, "autoencoded", ref.origin, load)

    return [coarse(ref) for ref in refs]
