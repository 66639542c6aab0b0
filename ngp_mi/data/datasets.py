"""torch Datasets over rendered dataset folders and image folders.

Maps are returned in physical units (depth in scene units, normals as unit vectors, albedo and
NOC in [0, 1]) as float32 CHW tensors; scaling to [−1, 1] happens at the network boundary.

* :class:`ReflectanceMapDataset` — the "real" reflectance maps (depth, normal, albedo, NOC, mask)
  and the camera of each view of a ``render-dataset`` folder.
* :class:`DepthDataset` — depth (+ mask) and camera only: the shapes to be decorated.
* :class:`WithCoarseDepth` — a dataset's views with the same shape's coarse depth of the same view
  (a ``render-dataset --coarse-shapes`` folder): ``coarse_depth`` and ``coarse_mask``.
* :class:`ImageFolderDataset` — the "real image" domain: the path-traced images of a dataset
  folder or a folder of photographs (PNG / JPEG / EXR), resized and randomly flipped as in the paper.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, BinaryIO, Sequence

import numpy as np
import torch
from PIL import Image
from torch.utils.data import Dataset

from ngp_mi.data.exr import read_exr
from ngp_mi.data.manifest import load_manifest
from ngp_mi.viz import linear_to_srgb

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


def _chw(array: np.ndarray) -> torch.Tensor:
    tensor = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
    return tensor[None] if tensor.ndim == 2 else tensor.permute(2, 0, 1).contiguous()


class ReflectanceMapDataset(Dataset):
    """Views of a ``render-dataset`` folder: a dict of maps plus ``K`` (3, 3), ``E`` (3, 4) and ids."""

    def __init__(self, root: str | Path, channels: Sequence[str] | None = None):
        self.root = Path(root)
        self.records = load_manifest(self.root)
        available = self.records[0]["channels"]
        self.channels = tuple(channels or available)
        missing = [c for c in self.channels if c not in available]
        if missing:
            raise ValueError(f"{self.root}: dataset has channels {available}, not {missing}")

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        maps = read_exr(self.root / record["files"]["maps"], self.channels)
        item: dict[str, Any] = {name: _chw(maps[name]) for name in self.channels}
        item["K"] = torch.tensor(record["K"], dtype=torch.float32)
        item["E"] = torch.tensor(record["E"], dtype=torch.float32)
        item["bounds"] = torch.tensor(record["bounds"], dtype=torch.float32)
        item["shape_id"], item["view"] = record["shape_id"], record["view"]
        return item


class DepthDataset(ReflectanceMapDataset):
    """Depth maps (and masks) with cameras: the coarse shapes NGP decorates."""

    def __init__(self, root: str | Path):
        super().__init__(root, channels=("depth", "mask"))


class WithCoarseDepth(Dataset):
    """The views of ``dataset`` with ``coarse_depth`` / ``coarse_mask``: the same shape and view in
    ``coarse_root`` (``render-dataset --coarse-shapes`` with the same source, seed, views and
    resolution), paired by (shape id, view). ``drop_unpaired``: leave out the views the coarse folder
    lacks (a shape whose reconstruction was empty is skipped there; ``dropped`` counts them) instead
    of failing on the first one."""

    def __init__(self, dataset: ReflectanceMapDataset, coarse_root: str | Path, drop_unpaired: bool = False):
        self.dataset, self.coarse = dataset, DepthDataset(coarse_root)
        coarse_index = {(r["shape_id"], r["view"]): i for i, r in enumerate(self.coarse.records)}
        self.pairs = []
        for i, record in enumerate(dataset.records):
            key = (record["shape_id"], record["view"])
            if key in coarse_index:
                self.pairs.append((i, coarse_index[key]))
            elif not drop_unpaired:
                raise ValueError(f"{coarse_root}: no coarse view for shape {key[0]!r} view {key[1]} of "
                                 f"{dataset.root} (render it with the same --source, --seed, --views and --res)")
        self.dropped = len(dataset) - len(self.pairs)
        if not self.pairs:
            raise ValueError(f"{coarse_root}: none of the views of {dataset.root} has a coarse view")
        self.records = [dataset.records[i] for i, _ in self.pairs]

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i, j = self.pairs[index]
        coarse = self.coarse[j]
        return {**self.dataset[i], "coarse_depth": coarse["depth"], "coarse_mask": coarse["mask"]}


def read_image(path: str | Path | BinaryIO, size: int | None = None, linear: bool = False) -> np.ndarray:
    """(H, W, 3) float32 of an image file (or an open binary file, e.g. an upload's bytes). PNG /
    JPEG are sRGB (resized to ``size``² when given) and returned as such unless ``linear``; EXR (an
    ``rgb`` layer, files only) is linear and returned as such unless ``linear=False`` (resize it
    with the caller's tensor ops)."""
    is_file = isinstance(path, (str, Path))
    name = Path(path) if is_file else Path(getattr(path, "name", None) or "uploaded image")
    if is_file and name.suffix.lower() == ".exr":
        channels = read_exr(name)
        rgb = channels.get("rgb")
        if rgb is None:
            raise ValueError(f"{name}: EXR image needs an 'rgb' layer, has {sorted(channels)}")
        return rgb if linear else linear_to_srgb(rgb)
    try:
        with Image.open(name if is_file else path) as im:
            im = im.convert("RGB")
            if size and im.size != (size, size):
                im = im.resize((size, size), Image.BILINEAR)
            image = np.asarray(im, dtype=np.float32) / 255.0
    except OSError as exc:
        raise ValueError(f"{name}: unreadable image ({exc})") from None
    if linear:
        image = np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)
    return image


class ImageFolderDataset(Dataset):
    """RGB images in [0, 1] as (3, H, W) float32, optionally resized and randomly flipped.

    ``root`` is a folder searched recursively (a dataset folder's ``real/`` images, or photos) or a
    ``render-dataset`` folder (its manifest's real images). PNG / JPEG are sRGB and returned as
    such unless ``linear=True``; EXR is linear and returned as such unless ``linear=False``.
    """

    def __init__(self, root: str | Path, size: int | None = None, flip: bool = True, linear: bool = False,
                 generator: torch.Generator | None = None):
        self.root = Path(root)
        if (self.root / "dataset.json").exists():
            self.files = [self.root / r["files"]["real_png"] for r in load_manifest(self.root) if "real_png" in r["files"]]
        elif self.root.is_dir():
            self.files = sorted(p for p in self.root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        else:
            raise ValueError(f"{self.root}: not a folder of images")
        if not self.files:
            raise ValueError(f"{self.root}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
        self.size, self.flip, self.linear, self.generator = size, flip, linear, generator

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> torch.Tensor:
        image = _chw(read_image(self.files[index], self.size, self.linear))
        if self.size and image.shape[-2:] != (self.size, self.size):
            image = torch.nn.functional.interpolate(image[None], size=(self.size, self.size), mode="bilinear",
                                                    align_corners=False)[0]
        if self.flip and torch.rand((), generator=self.generator) < 0.5:
            image = image.flip(-1)
        return image
