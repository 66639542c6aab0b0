"""Multi-channel OpenEXR files: linear float32 maps, written atomically.

A map of shape (H, W) is one channel (``depth``); a map of shape (H, W, 3) is written as three
channels ``name.R``, ``name.G``, ``name.B`` (OpenEXR's layer convention, read by Blender, Nuke,
OpenCV and ``OpenEXR`` itself) and read back as (H, W, 3).

A file may store only a rectangle of its image (OpenEXR's *data window* inside the *display
window*): the dataset renderer stores the object's bounding rectangle, since every map is 0 off
the object. :func:`read_exr` returns display-window arrays with zeros outside the data window
(OpenCV's ``imread`` returns only the stored rectangle).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import OpenEXR

from ngp_mi.atomic import atomic_path

COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,   # lossless; ~2x faster to write than zip, ~2x larger
    "zip": OpenEXR.ZIP_COMPRESSION,   # lossless, read everywhere: the default
    "zstd": OpenEXR.ZSTD_COMPRESSION,  # lossless, ~10 % smaller and faster; needs OpenEXR >= 3.4 to read
    "piz": OpenEXR.PIZ_COMPRESSION,
}


Window = tuple[int, int, int, int]  # x_min, y_min, x_max, y_max (inclusive), OpenEXR's convention


def nonzero_windows(masks: np.ndarray) -> list[Window]:
    """Per image of ``masks`` (N, H, W): the smallest rectangle holding its non-zero pixels.

    An image without any gets (0, 0, 0, 0): OpenEXR needs a non-empty data window (one zero pixel).
    """
    on = np.asarray(masks) != 0
    rows, cols = on.any(axis=2), on.any(axis=1)  # (N, H), (N, W): two passes for the whole batch
    windows = []
    for r, c in zip(rows, cols):
        r, c = np.flatnonzero(r), np.flatnonzero(c)
        windows.append((int(c[0]), int(r[0]), int(c[-1]), int(r[-1])) if len(r) else (0, 0, 0, 0))
    return windows


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray], compression: str = "zip",
              metadata: Mapping[str, str] | None = None, half: Iterable[str] = (),
              window: Window | None = None) -> Path:
    """Write maps to ``path`` through a temporary file and a rename (never a partial file).

    Channels are float32, except those named in ``half`` (16-bit float: 11-bit mantissa, relative
    error < 5e-4). ``window`` stores only that rectangle of the (H, W) image (the data window); the
    pixels outside it must be 0, which is what :func:`read_exr` returns for them.
    """
    half = set(half)
    path = Path(path)
    if compression not in COMPRESSIONS:
        raise ValueError(f"{path}: compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")
    if not channels:
        raise ValueError(f"{path}: no channels to write")
    shape = None
    data = {}
    for name, array in channels.items():
        array = np.ascontiguousarray(array, dtype=np.float16 if name in half else np.float32)
        if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3):
            raise ValueError(f"{path}: channel {name!r} must be (H, W) or (H, W, 3), got {array.shape}")
        if shape is not None and array.shape[:2] != shape:
            raise ValueError(f"{path}: channel {name!r} is {array.shape[:2]}, others are {shape}")
        shape = array.shape[:2]
        data[name] = array
    header = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    if window is not None:
        x0, y0, x1, y1 = window
        if not (0 <= x0 <= x1 < shape[1] and 0 <= y0 <= y1 < shape[0]):
            raise ValueError(f"{path}: window {window} is not inside the {shape[1]}x{shape[0]} image")
        data = {name: np.ascontiguousarray(a[y0:y1 + 1, x0:x1 + 1]) for name, a in data.items()}
        header["displayWindow"] = (np.array([0, 0], np.int32), np.array([shape[1] - 1, shape[0] - 1], np.int32))
        header["dataWindow"] = (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))
    header.update({str(k): str(v) for k, v in (metadata or {}).items()})
    with atomic_path(path) as tmp:
        OpenEXR.File(header, data).write(str(tmp))  # OpenEXR replaces the dict's values: pass our copy
    return path


def read_exr(path: str | Path, channels: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Read maps as float32 display-window arrays; ``channels`` selects some (error naming the missing ones).

    Pixels outside the file's data window are 0; a data window reaching outside the display
    window is clipped to it.
    """
    path = Path(path)
    try:
        file = OpenEXR.File(str(path))
        header = file.header()
        found = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in file.channels().items()}
    except Exception as exc:  # OpenEXR raises a bare Exception for unreadable or truncated files
        raise ValueError(f"{path}: not a readable OpenEXR file ({exc})") from None
    (dx0, dy0), (dx1, dy1) = (np.asarray(c, int) for c in header["dataWindow"])
    (sx0, sy0), (sx1, sy1) = (np.asarray(c, int) for c in header["displayWindow"])
    if (dx0, dy0, dx1, dy1) != (sx0, sy0, sx1, sy1):
        height, width = sy1 - sy0 + 1, sx1 - sx0 + 1
        # the stored rectangle's part inside the display window, in both coordinate systems
        x0, y0, x1, y1 = max(dx0, sx0), max(dy0, sy0), min(dx1, sx1), min(dy1, sy1)
        for name, stored in found.items():
            full = np.zeros((height, width, *stored.shape[2:]), np.float32)
            if x0 <= x1 and y0 <= y1:
                full[y0 - sy0:y1 - sy0 + 1, x0 - sx0:x1 - sx0 + 1] = stored[y0 - dy0:y1 - dy0 + 1, x0 - dx0:x1 - dx0 + 1]
            found[name] = full
    if channels is None:
        return found
    wanted = list(channels)
    missing = [c for c in wanted if c not in found]
    if missing:
        raise ValueError(f"{path}: missing channel(s) {missing}; the file has {sorted(found)}")
    return {c: found[c] for c in wanted}

