"""Loading user meshes: single files, multi-part files, plain folders and ShapeNet-style trees.

Formats are read by trimesh (OBJ, PLY, OFF, STL, GLB / glTF, …). A file with several geometries
(OBJ groups, glTF nodes) becomes one :class:`TriangleMesh` whose faces carry the index of the
part they came from. Every mesh is validated and normalised in float64
(``geometry.mesh.normalized_vertices``);
a bad file raises :class:`MeshError` with the file and the reason, so that batch jobs can skip it
and report why.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from pathlib import Path

import numpy as np

from ngp_mi.geometry.mesh import TriangleMesh, normalized_vertices

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")
SHAPENET_MODEL = Path("models") / "model_normalized.obj"
DEGENERATE_AREA = 1e-12


class MeshError(ValueError):
    """A mesh file that cannot be used; ``str()`` names the file and the reason."""

    def __init__(self, path: str | Path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = str(path), reason


@dataclasses.dataclass(frozen=True)
class MeshSource:
    """A mesh on disk and the id it gets in datasets (``synset/model_id`` or a relative path)."""

    id: str
    path: Path


def load_mesh(path: str | Path, normalize: bool = True) -> TriangleMesh:
    """Read, merge, validate and (by default) normalise one mesh file.

    Faces of zero area are dropped (logged); a file with no faces left, non-finite vertices or
    that trimesh cannot parse raises :class:`MeshError`.
    """
    import trimesh  # here, not at the top: it takes over a second to import, and most jobs read no mesh file

    path = Path(path)
    if not path.is_file():
        raise MeshError(path, "no such file")
    if path.suffix.lower() == ".stl":
        check_binary_stl(path)
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many exception types for bad files
        raise MeshError(path, f"unreadable ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        parts = [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    elif isinstance(loaded, trimesh.Trimesh):
        parts = [loaded]
    else:
        raise MeshError(path, f"contains no triangles (trimesh read a {type(loaded).__name__})")
    parts = [p for p in parts if len(p.faces) > 0]
    if not parts:
        raise MeshError(path, "empty mesh: no faces")

    vertices, faces, part_ids, offset = [], [], [], 0
    for index, part in enumerate(parts):
        v = np.asarray(part.vertices, np.float64)
        vertices.append(v)
        faces.append(np.asarray(part.faces, np.int64) + offset)
        part_ids.append(np.full(len(part.faces), index, np.int32))
        offset += len(v)
    v, f, ids = np.concatenate(vertices), np.concatenate(faces), np.concatenate(part_ids)
    if not np.all(np.isfinite(v)):
        raise MeshError(path, f"{int((~np.isfinite(v)).any(1).sum())} vertices are not finite")
    if normalize:  # before anything is cast to float32 (TriangleMesh stores float32)
        try:
            v = normalized_vertices(v, str(path))
        except ValueError as exc:
            raise MeshError(path, str(exc).removeprefix(f"{path}: ")) from None
    corners = v[f]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    keep = area > DEGENERATE_AREA * max(1.0, float(np.ptp(v, axis=0).max()) ** 2)
    if not keep.any():
        raise MeshError(path, f"all {len(f)} faces are degenerate (zero area)")
    if not keep.all():
        log.info("%s: dropped %d degenerate faces of %d", path, int((~keep).sum()), len(f))
    try:
        mesh = TriangleMesh(v, f[keep], ids[keep], name=path.stem)
    except ValueError as exc:
        raise MeshError(path, str(exc)) from None
    return mesh


def check_binary_stl(path: Path) -> None:
    """A binary STL (80-byte header, triangle count, 50 bytes per triangle) whose size does not match
    its count is truncated (or padded): say so, instead of trimesh's "no faces"."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:5].lower() == b"solid" and b"facet" in head:
        return  # ASCII STL
    if size < 84:
        raise MeshError(path, f"truncated STL: {size} bytes, less than a binary STL's 84-byte header")
    count = int.from_bytes(head[80:84], "little")
    if size != 84 + 50 * count:
        raise MeshError(path, f"truncated binary STL: its header announces {count} triangles "
                              f"({84 + 50 * count} bytes), the file has {size} bytes")


def find_meshes(root: str | Path) -> list[MeshSource]:
    """Mesh files under ``root``, sorted by id.

    A ShapeNet-style tree (``<synset>/<model_id>/models/model_normalized.obj``) gives ids
    ``synset/model_id``; otherwise every file with a mesh suffix gives its path relative to
    ``root`` without the suffix — with it where two files would share an id (``a.obj`` and
    ``a.stl`` become ``a.obj`` and ``a.stl``), so every id names one file.
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder of meshes")
    shapenet = sorted(root.glob(f"*/*/{SHAPENET_MODEL.as_posix()}"))
    if shapenet:
        return [MeshSource(f"{p.parents[2].name}/{p.parents[1].name}", p) for p in shapenet]
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    stems = [p.relative_to(root).with_suffix("").as_posix() for p in files]
    shared = {s for s, n in collections.Counter(stems).items() if n > 1}
    return sorted((MeshSource(p.relative_to(root).as_posix() if s in shared else s, p) for s, p in zip(stems, files)),
                  key=lambda m: m.id)
