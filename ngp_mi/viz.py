"""Images people look at: sRGB conversion, PNG writing (atomic), labelled contact sheets and grids, GIFs.

Captions wrap to the width of their tile (a word wider than the tile breaks between letters), so
they stay legible and apart at every tile size. They are set in DejaVu Sans, the font matplotlib (a
dependency) ships, which has the Greek and mathematical glyphs of the captions (φ, Π_v, ⊕, ²).
Without it, Pillow's built-in font is used, which has none of them and almost no space between
words: captions are then written with the symbols' names (``φ`` → ``phi``, ``⊕`` → ``+``).
"""

from __future__ import annotations

import functools
import importlib.util
import unicodedata
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ngp_mi.atomic import atomic_path


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) on values clipped to [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_uint8(image: np.ndarray, srgb: bool = True) -> np.ndarray:
    """A linear float image (H, W[, C]) → uint8, through sRGB unless ``srgb`` is False."""
    image = linear_to_srgb(image) if srgb else np.clip(image, 0.0, 1.0)
    return np.round(image * 255.0).astype(np.uint8)


def chw_to_uint8(image: Any, srgb: bool = True) -> np.ndarray:
    """A (1, C, H, W) or (C, H, W) array (a CPU torch tensor too) → uint8 (H, W, C), through sRGB
    unless ``srgb`` is False."""
    array = np.asarray(image, dtype=np.float32)
    return to_uint8(np.moveaxis(array[0] if array.ndim == 4 else array, 0, -1), srgb)


def depth_to_uint8(depth: Any, mask: Any) -> np.ndarray:
    """A depth map (H, W) as grey (H, W, 3) uint8: the object's nearest point white, its farthest 0.2,
    the background black (the mask > 0 says which is which)."""
    d = np.asarray(depth, dtype=np.float32)
    on = np.asarray(mask) > 0
    shown = np.zeros_like(d)
    if on.any():
        near = d[on].min()
        shown[on] = 1 - 0.8 * (d[on] - near) / max(float(d[on].max() - near), 1e-6)
    return to_uint8(np.repeat(shown[..., None], 3, -1), srgb=False)


def save_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a uint8 (H, W[, C]) image as PNG, via a temporary file and a rename."""
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


LINE_HEIGHT = 14  # pixels per caption line (both fonts are at most 12 px high)


@functools.lru_cache(maxsize=1)
def caption_font() -> Any:
    """DejaVu Sans at 10 px from matplotlib's package data (found without importing matplotlib), or
    Pillow's built-in font when it is missing."""
    spec = importlib.util.find_spec("matplotlib")
    if spec is not None and spec.origin is not None:
        path = Path(spec.origin).parent / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
        if path.exists():
            return ImageFont.truetype(str(path), 10)
    return None  # Pillow's default
SYMBOL_NAMES = {"φ": "phi", "θ": "theta", "Π": "Pi", "π": "pi", "ρ": "rho", "α": "alpha", "μ": "mu", "σ": "sigma",
                "λ": "lambda", "Ω": "Omega", "⊕": "+", "→": "->", "−": "-", "…": "...", "×": "x", "≤": "<=",
                "≥": ">=", "²": "^2", "³": "^3", "·": "."}


def drawable(text: str, font: Any = "caption") -> str:
    """``text`` as the caption font draws it: unchanged in DejaVu Sans; for Pillow's built-in font
    (``font=None``), symbols by name and accents dropped."""
    if (caption_font() if font == "caption" else font) is not None:
        return text
    named = "".join(SYMBOL_NAMES.get(c, c) for c in text)
    plain = unicodedata.normalize("NFKD", named)
    return "".join(c for c in plain if c.isascii() or c == "°")


def wrap_label(draw: Any, text: str, width: float) -> list[str]:
    """``text`` (made :func:`drawable`) in lines no wider than ``width`` pixels: at spaces, and inside a
    word wider than that."""
    text = drawable(text)
    lines: list[str] = []
    line = ""
    for word in text.split():
        candidate = f"{line} {word}" if line else word
        if draw.textlength(candidate, font=caption_font()) <= width:
            line = candidate
            continue
        if line:
            lines.append(line)
        while len(word) > 1 and draw.textlength(word, font=caption_font()) > width:
            cut = max(1, max((k for k in range(1, len(word)) if draw.textlength(word[:k], font=caption_font()) <= width),
                             default=1))
            lines.append(word[:cut])
            word = word[cut:]
        line = word
    return lines + [line] if line else lines or [""]


def contact_sheet(images: Sequence[np.ndarray], labels: Sequence[str] | None = None, columns: int = 4,
                  pad: int = 4, label_height: int = LINE_HEIGHT, background: int = 32) -> np.ndarray:
    """Tile uint8 (H, W, 3) images of one size into a grid with a caption under each (wrapped to the tile)."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("contact_sheet images must share one size")
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    wrapped = [wrap_label(measure, text, w - 4) for text in labels] if labels else None  # antialiased glyphs bleed 1 px
    rows = -(-len(images) // columns)
    cell_h = h + (label_height * max(len(lines) for lines in wrapped) if wrapped else 0)
    sheet = Image.new("RGB", (columns * (w + pad) + pad, rows * (cell_h + pad) + pad), (background,) * 3)
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(images):
        x, y = pad + (i % columns) * (w + pad), pad + (i // columns) * (cell_h + pad)
        tile = image if image.ndim == 3 else np.repeat(image[..., None], 3, -1)
        sheet.paste(Image.fromarray(tile[..., :3]), (x, y))
        for j, line in enumerate(wrapped[i] if wrapped else ()):
            draw.text((x + 2, y + h + 1 + j * label_height), line, fill=(220, 220, 220), font=caption_font())
    return np.asarray(sheet)


def labelled_grid(rows: Sequence[Sequence[np.ndarray]], row_labels: Sequence[str], column_labels: Sequence[str],
                  pad: int = 4, background: int = 32, row_label_width: int = 96) -> np.ndarray:
    """A grid of uint8 images of one size: a header over each column and a label left of each row
    (what changes along a sweep), both wrapped to fit."""
    if not rows or not rows[0]:
        raise ValueError("labelled_grid needs at least one image")
    h, w = rows[0][0].shape[:2]
    columns = max(len(r) for r in rows)
    if len(row_labels) != len(rows) or len(column_labels) != columns:
        raise ValueError(f"labelled_grid: {len(rows)} rows x {columns} columns need as many labels, "
                         f"got {len(row_labels)} and {len(column_labels)}")
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    heads = [wrap_label(measure, text, w - 4) for text in column_labels]
    sides = [wrap_label(measure, text, row_label_width - 4) for text in row_labels]
    head_h = LINE_HEIGHT * max(len(lines) for lines in heads)
    cell_h = max(h, LINE_HEIGHT * max(len(lines) for lines in sides))
    sheet = Image.new("RGB", (row_label_width + columns * (w + pad) + pad, head_h + pad + len(rows) * (cell_h + pad)),
                      (background,) * 3)
    draw = ImageDraw.Draw(sheet)
    for c, lines in enumerate(heads):
        for j, line in enumerate(lines):
            draw.text((row_label_width + pad + c * (w + pad) + 2, pad // 2 + j * LINE_HEIGHT), line, fill=(220, 220, 220),
                      font=caption_font())
    for r, (row, lines) in enumerate(zip(rows, sides)):
        y = head_h + pad + r * (cell_h + pad)
        for j, line in enumerate(lines):
            draw.text((2, y + j * LINE_HEIGHT), line, fill=(220, 220, 220), font=caption_font())
        for c, image in enumerate(row):
            if image.shape[:2] != (h, w):
                raise ValueError("labelled_grid images must share one size")
            tile = image if image.ndim == 3 else np.repeat(image[..., None], 3, -1)
            sheet.paste(Image.fromarray(tile[..., :3]), (row_label_width + pad + c * (w + pad), y))
    return np.asarray(sheet)


def save_animation(path: str | Path, frames: Sequence[np.ndarray], fps: float = 12.0) -> Path:
    """Write uint8 frames (H, W, 3) as a looping animated GIF (imageio), atomically."""
    import imageio.v3 as iio  # only animations need it

    if not frames:
        raise ValueError("save_animation needs at least one frame")
    path = Path(path)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, np.stack([f[..., :3] for f in frames]), extension=".gif", duration=1000.0 / fps, loop=0)
    return path
