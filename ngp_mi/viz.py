"""Images people look at: sRGB conversion, PNG writing (atomic), labelled contact sheets."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw

from ngp_mi.atomic import atomic_path


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) on values clipped to [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_uint8(image: np.ndarray, srgb: bool = True) -> np.ndarray:
    """A linear float image (H, W[, C]) → uint8, through sRGB unless ``srgb`` is False."""
    image = linear_to_srgb(image) if srgb else np.clip(image, 0.0, 1.0)
    return np.round(image * 255.0).astype(np.uint8)


def save_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a uint8 (H, W[, C]) image as PNG, via a temporary file and a rename."""
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


def contact_sheet(images: Sequence[np.ndarray], labels: Sequence[str] | None = None, columns: int = 4,
                  pad: int = 4, label_height: int = 14, background: int = 32) -> np.ndarray:
    """Tile uint8 (H, W, 3) images of one size into a grid with a caption under each."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("contact_sheet images must share one size")
    rows = -(-len(images) // columns)
    cell_h = h + (label_height if labels else 0)
    sheet = Image.new("RGB", (columns * (w + pad) + pad, rows * (cell_h + pad) + pad), (background,) * 3)
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(images):
        x, y = pad + (i % columns) * (w + pad), pad + (i // columns) * (cell_h + pad)
        tile = image if image.ndim == 3 else np.repeat(image[..., None], 3, -1)
        sheet.paste(Image.fromarray(tile[..., :3]), (x, y))
        if labels:
            draw.text((x + 2, y + h + 1), labels[i], fill=(220, 220, 220))
    return np.asarray(sheet)
