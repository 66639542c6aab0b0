"""Triangle meshes with per-face part ids, validated and normalised to a common scale.

Scale convention: a normalised mesh has its bounding box centred at the origin and its farthest
vertex at :data:`NORMALIZED_RADIUS` = 0.5, i.e. it fits the sphere of unit *diameter* — the scale of
ShapeNet's ``model_normalized`` meshes (bounding-box diagonal at most 1) that the paper renders.
The paper's camera (ρ = 2, 39.6° horizontal field of view) sees ±0.72 around the origin, so a
mesh scaled to radius 1 would be cropped from most views.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class TriangleMesh:
    """An indexed triangle mesh.

    Attributes:
        vertices: (V, 3) float32 positions (world space).
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        part_ids: (F,) int32 part label per face (0 when the source has no parts).
        name: where the mesh came from, used in messages.
    """

    vertices: np.ndarray
    faces: np.ndarray
    part_ids: np.ndarray | None = None
    name: str = "mesh"

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices, dtype=np.float32)
        f = np.ascontiguousarray(self.faces, dtype=np.int32)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"{self.name}: vertices must be a non-empty (V, 3) array, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"{self.name}: faces must be a non-empty (F, 3) array, got shape {f.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{self.name}: {int((~np.isfinite(v)).any(1).sum())} vertices are not finite")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"{self.name}: face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        parts = np.zeros(len(f), np.int32) if self.part_ids is None else np.asarray(self.part_ids, np.int32)
        if parts.shape != (len(f),):
            raise ValueError(f"{self.name}: part_ids must have one entry per face ({len(f)}), got {parts.shape}")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "part_ids", parts)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3): minimum and maximum corner of the axis-aligned bounding box."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @staticmethod
    def concatenate(meshes: list["TriangleMesh"], name: str = "mesh") -> "TriangleMesh":
        """Merge meshes, giving the faces of the i-th input part id i."""
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return TriangleMesh(
            vertices=np.concatenate([m.vertices for m in meshes]),
            faces=np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]),
            part_ids=np.concatenate([np.full(len(m.faces), i, np.int32) for i, m in enumerate(meshes)]),
            name=name)


NORMALIZED_RADIUS = 0.5


def normalized_vertices(vertices: np.ndarray, name: str = "mesh", radius: float = NORMALIZED_RADIUS) -> np.ndarray:
    """Vertices with the bounding box centred at the origin and the farthest vertex at ``radius``,
    computed in float64: float32 loses a far-offset mesh's shape (0.06 units of rounding at 1e6) and
    overflows on a huge one (|v|² of 1e30). A result that is not finite, or an object that is a
    point, is refused with the reason."""
    v = np.asarray(vertices, np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: {int((~np.isfinite(v)).any(1).sum())} vertices are not finite")
    lo, hi = v.min(0), v.max(0)
    centred = v - (lo + hi) / 2
    with np.errstate(over="ignore"):  # coordinates near float64's limit: refused below, without a warning
        extent = float(np.sqrt((centred ** 2).sum(1).max()))
    if not extent > 0 or not np.isfinite(extent):
        raise ValueError(f"{name}: all vertices coincide (size {extent:g}); cannot normalise")
    out = centred * (radius / extent)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: coordinates up to {np.abs(v).max():g} cannot be normalised")
    return out


def normalize_mesh(mesh: TriangleMesh, radius: float = NORMALIZED_RADIUS) -> TriangleMesh:
    """Centre the bounding box at the origin and scale so the farthest vertex lies at ``radius``."""
    return dataclasses.replace(mesh, vertices=normalized_vertices(mesh.vertices, mesh.name, radius))


def face_areas(mesh: TriangleMesh) -> np.ndarray:
    """(F,) the area of each triangle."""
    a, b, c = (mesh.vertices[mesh.faces[:, i]].astype(np.float64) for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def drop_small_components(mesh: TriangleMesh, min_fraction: float) -> tuple[TriangleMesh, int]:
    """The mesh without its connected components (faces joined through shared vertices) whose area
    is below ``min_fraction`` of the whole surface's; returns it and how many were dropped. Unused
    vertices are removed. The largest component is always kept."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = mesh.faces
    n_vertices = len(mesh.vertices)
    # each face joins its three vertices: components of this graph are the mesh's pieces
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    count, label = connected_components(graph, directed=False)
    face_label = label[faces[:, 0]]
    area = np.bincount(face_label, weights=face_areas(mesh), minlength=count)
    keep = area >= min_fraction * area.sum()
    keep[np.argmax(area)] = True
    pieces = np.unique(face_label)
    dropped = int(np.count_nonzero(~keep[pieces]))
    if not dropped:
        return mesh, 0
    kept_faces = keep[face_label]
    used = np.zeros(n_vertices, bool)
    used[faces[kept_faces].ravel()] = True
    index = np.cumsum(used) - 1
    return TriangleMesh(mesh.vertices[used], index[faces[kept_faces]], mesh.part_ids[kept_faces],
                        name=mesh.name), dropped
