"""Where shapes come from: the one resolver of a ``--source`` for every job that reads shapes.

A source is

* a procedural family (``chair``, ``car``; :mod:`ngp_mi.geometry.families`): objects of seeds
  ``seed, seed+1, …``;
* a mesh file, a folder of meshes or a ShapeNet-style tree (:func:`~ngp_mi.geometry.loaders.find_meshes`);
* a Mitsuba scene file (``.xml``) or a folder of them (only where ``scenes`` allows: a scene is
  something to render, not a solid the shape prior can voxelise).

:func:`resolve_shapes` says what each shape is and where it is, and loads nothing: the dataset
renderer (:mod:`ngp_mi.data.sources`) loads them into Mitsuba scenes,
:func:`ngp_mi.geometry.occupancy.load_solid` as solids (a mesh and its occupancy) for the shape
prior's data (:mod:`ngp_mi.data.shapes`), so a bad file fails when its turn comes, with its reason.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ngp_mi.geometry.families import FAMILIES
from ngp_mi.geometry.loaders import MESH_SUFFIXES, find_meshes

SCENE_SUFFIX = ".xml"
KINDS = ("procedural", "mesh", "scene")


@dataclasses.dataclass(frozen=True)
class ShapeRef:
    """One shape of a source: its dataset id, its kind, and the family + seed or the file it comes from."""

    id: str
    kind: str  # one of KINDS
    origin: str  # the family name or the file path
    seed: int = 0  # procedural only
    path: Path | None = None  # meshes and scenes


def resolve_shapes(source: str, num_shapes: int, seed: int = 0, scenes: bool = True) -> list[ShapeRef]:
    """The first ``num_shapes`` shapes of ``source``; errors name the source and what it should be."""
    if num_shapes < 1:
        raise ValueError(f"num_shapes must be >= 1, got {num_shapes}")
    if source in FAMILIES:
        return [ShapeRef(f"{source}/{seed + i:06d}", "procedural", source, seed=seed + i) for i in range(num_shapes)]
    path = Path(source)
    wanted = f"a mesh ({', '.join(MESH_SUFFIXES)})" + (f" or Mitsuba scene ({SCENE_SUFFIX})" if scenes else "")
    if path.is_file():
        suffix = path.suffix.lower()
        if scenes and suffix == SCENE_SUFFIX:
            return [ShapeRef(path.stem, "scene", str(path), path=path)]
        if suffix in MESH_SUFFIXES:
            return [ShapeRef(path.stem, "mesh", str(path), path=path)]
        raise ValueError(f"{path}: not {wanted}")
    if path.is_dir():
        found = sorted(path.glob(f"*{SCENE_SUFFIX}")) if scenes else []
        if found:
            return [ShapeRef(p.stem, "scene", str(p), path=p) for p in found[:num_shapes]]
        meshes = find_meshes(path)
        if not meshes:
            raise ValueError(f"{path}: no meshes ({', '.join(MESH_SUFFIXES)})"
                             + (" or scene files" if scenes else "") + " found")
        return [ShapeRef(m.id, "mesh", str(m.path), path=m.path) for m in meshes[:num_shapes]]
    raise ValueError(f"--source {source!r}: not a family ({', '.join(sorted(FAMILIES))}), file or folder")

