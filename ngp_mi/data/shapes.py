"""Training data of the shape prior: voxels and point–occupancy samples per shape, cached on disk.

For each shape (a procedural family's object, or a mesh file) one ``shapes/<id>.npz`` holds

* ``voxels``: the occupancy at the cell centres of a ``voxel_resolution``³ grid (bit-packed),
  the 3-D CNN encoder's input;
* ``points_R`` / ``occ_R`` for each progressive resolution R (IM-NET: 16³ → 32³ → 64³), points
  jittered in their cells, half of them (``near_fraction``) from cells on the voxel surface;
* ``surface``: points on the surface, for the Chamfer-based sample metrics.

Occupancy is exact for procedural solids (their signed distance) and the generalised winding
number for meshes (:mod:`ngp_mi.geometry.occupancy`, libigl's fast one), so open, non-watertight
meshes work.
Every file is written atomically (temp + rename): a rerun builds only missing shapes; a shape that
fails (unreadable mesh, …) is skipped with its reason in ``summary.json`` and the log.
``dataset.json`` keeps the settings; a resumed build with different ones is refused.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ngp_mi.atomic import atomic_path, write_json, write_text
from ngp_mi.geometry.occupancy import load_solid, sample_occupancy_points, surface_samples
from ngp_mi.geometry.sources import ShapeRef, resolve_shapes

log = logging.getLogger("ngp_mi.shapes")


@dataclasses.dataclass(frozen=True)
class ShapeDataConfig:
    source: str                                  # a family name, a mesh file or a folder of meshes
    num_shapes: int = 64
    seed: int = 0
    voxel_resolution: int = 64
    resolutions: tuple[int, ...] = (16, 32, 64)
    points: tuple[int, ...] = (4096, 8192, 32768)  # IM-NET's counts per resolution
    near_fraction: float = 0.5
    surface_points: int = 2048

    def __post_init__(self) -> None:
        if len(self.resolutions) != len(self.points):
            raise ValueError(f"shape data: resolutions {self.resolutions} and points {self.points} differ in length")
        if self.num_shapes < 1:
            raise ValueError(f"shape data: num_shapes must be >= 1, got {self.num_shapes}")

    def to_json(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def shape_refs(config: ShapeDataConfig) -> list[ShapeRef]:
    """The shapes of the configured source (a family or meshes; scene files are no solids)."""
    try:
        return resolve_shapes(config.source, config.num_shapes, config.seed, scenes=False)
    except ValueError as exc:
        raise ValueError(f"shape data: {exc}") from None


def shape_file(root: Path, shape_id: str) -> Path:
    return root / "shapes" / f"{shape_id.replace('/', '__')}.npz"


def sample_shape(config: ShapeDataConfig, ref: ShapeRef, index: int) -> dict[str, np.ndarray]:
    """All arrays of one shape (see the module docstring); deterministic in (seed, index)."""
    solid = load_solid(ref)
    mesh, inside, grid = solid.mesh, solid.inside, solid.grid
    rng = np.random.default_rng([config.seed, index, 7919])
    arrays: dict[str, np.ndarray] = {}
    grids = {r: grid(r) for r in {*config.resolutions, config.voxel_resolution}}
    voxels = grids[config.voxel_resolution]
    if not voxels.any():
        raise ValueError(f"{ref.id}: no voxel of the {config.voxel_resolution}³ grid is inside the shape "
                         "(open sheet or a shape thinner than a voxel)")
    arrays["voxels"] = np.packbits(voxels.ravel())
    for r, count in zip(config.resolutions, config.points):
        arrays[f"points_{r}"], arrays[f"occ_{r}"] = sample_occupancy_points(inside, grids[r], count, rng,
                                                                            config.near_fraction)
    arrays["surface"] = surface_samples(mesh, config.surface_points, rng)
    return arrays


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def _check_settings(out: Path, config: ShapeDataConfig) -> None:
    settings = out / "dataset.json"
    if settings.exists():
        old = json.loads(settings.read_text())
        changed = {k: (old.get(k), v) for k, v in config.to_json().items() if k != "num_shapes" and old.get(k) != v}
        if changed:
            raise ValueError(f"{settings}: this folder was built with other settings "
                             f"({', '.join(f'{k}: {a!r} → {b!r}' for k, (a, b) in changed.items())}); use a new folder")
    write_json(settings, config.to_json())


def _build_one(config: ShapeDataConfig, out: Path, index: int) -> str | None:
    """Write shape ``index``; returns None, or the reason it was skipped (runs in worker processes)."""
    ref = shape_refs(config)[index]
    try:
        _write_npz(shape_file(out, ref.id), sample_shape(config, ref, index))
    except Exception as exc:  # one bad shape must not end a long build
        return str(exc) or type(exc).__name__
    return None


def build_shape_dataset(config: ShapeDataConfig, out: str | Path, progress: bool = True,
                        strict: bool = False, workers: int = 1) -> dict[str, Any]:
    """Build (or finish building) the shape dataset in ``out`` with ``workers`` processes; returns the summary."""
    out = Path(out)
    _check_settings(out, config)
    items = shape_refs(config)
    summary: dict[str, Any] = {"total": len(items), "present": 0, "built": 0, "skipped": {}}
    start = time.perf_counter()
    todo = [i for i, item in enumerate(items) if not shape_file(out, item.id).exists()]
    summary["present"] = len(items) - len(todo)
    with tqdm(total=len(items), initial=summary["present"], unit="shape", disable=not progress, desc="shape data",
              dynamic_ncols=True) as bar:
        # "spawn": a forked child of a process whose torch / OpenMP threads ran can deadlock.
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) \
            if workers > 1 and len(todo) > 1 else None
        try:
            results = pool.map(_build_one, [config] * len(todo), [out] * len(todo), todo) if pool else \
                (_build_one(config, out, i) for i in todo)
            for index, reason in zip(todo, results):
                if reason is None:
                    summary["built"] += 1
                else:
                    summary["skipped"][items[index].id] = reason
                    log.warning("skipped %s: %s", items[index].id, reason)
                bar.update(1)
        finally:
            if pool:
                pool.shutdown()
    index_lines = [json.dumps({"id": item.id, "file": str(shape_file(out, item.id).relative_to(out)), "index": i})
                   for i, item in enumerate(items) if shape_file(out, item.id).exists()]
    summary["seconds"] = round(time.perf_counter() - start, 3)
    write_text(out / "index.jsonl", "".join(line + "\n" for line in index_lines))
    write_json(out / "summary.json", summary)
    log.info("shape data: %d built, %d present, %d skipped (%s)", summary["built"], summary["present"],
             len(summary["skipped"]), out / "summary.json")
    if strict and summary["skipped"]:
        raise RuntimeError(f"--strict: {len(summary['skipped'])} shape(s) skipped, see {out / 'summary.json'}")
    return summary


class ShapeDataset(torch.utils.data.Dataset):
    """Items of a shape dataset: ``voxels`` (1, V, V, V) float32, ``points`` (N, 3), ``occ`` (N, 1), ``surface``.

    ``resolution`` picks the point set (one of the built resolutions); ``ids`` restricts to a subset.
    Everything is loaded into memory once (a 64³ shape is about 0.5 MB).
    """

    def __init__(self, root: str | Path, resolution: int | None = None, ids: list[str] | None = None):
        self.root = Path(root)
        records = self.index(self.root)
        self.config = json.loads((self.root / "dataset.json").read_text())
        if ids is not None:
            wanted = set(ids)
            records = [r for r in records if r["id"] in wanted]
        if not records:
            raise ValueError(f"{self.root}: no shapes")
        self.ids = [r["id"] for r in records]
        self.resolution = resolution or max(self.config["resolutions"])
        if self.resolution not in self.config["resolutions"]:
            raise ValueError(f"{self.root}: no points at resolution {self.resolution}; built: {self.config['resolutions']}")
        self._arrays = [dict(np.load(self.root / r["file"])) for r in records]

    @staticmethod
    def index(root: str | Path) -> list[dict[str, Any]]:
        """The records of ``index.jsonl`` (id, file, index), without loading any shape."""
        index = Path(root) / "index.jsonl"
        if not index.exists():
            raise FileNotFoundError(f"{index}: not a shape dataset (build it with build_shape_dataset / train shape)")
        return [json.loads(line) for line in index.read_text().splitlines() if line.strip()]

    def __len__(self) -> int:
        return len(self.ids)

    def voxels(self, i: int) -> np.ndarray:
        v = self.config["voxel_resolution"]
        return np.unpackbits(self._arrays[i]["voxels"])[:v ** 3].reshape(v, v, v).astype(bool)

    def voxel_tensor(self, i: int) -> torch.Tensor:
        """The encoder's input: (1, V, V, V) float32."""
        return torch.from_numpy(self.voxels(i)).float()[None]

    def all_voxels(self) -> torch.Tensor:
        """(N, 1, V, V, V) float32 of every shape."""
        return torch.stack([self.voxel_tensor(i) for i in range(len(self))])

    def points(self, i: int, resolution: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        r = resolution or self.resolution
        return self._arrays[i][f"points_{r}"], self._arrays[i][f"occ_{r}"]

    def surface(self, i: int) -> np.ndarray:
        return self._arrays[i]["surface"]

    def __getitem__(self, i: int) -> dict[str, Any]:
        points, occ = self.points(i)
        return {"voxels": self.voxel_tensor(i), "points": torch.from_numpy(points),
                "occ": torch.from_numpy(occ).float()[:, None], "surface": torch.from_numpy(self.surface(i)),
                "index": i}
