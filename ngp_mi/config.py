"""What the training commands share: reading a TOML recipe and choosing the device."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Iterable

import torch


def read_recipe(path: str | Path, tables: Iterable[str]) -> dict[str, Any]:
    """A training recipe (TOML) that must have ``tables``; errors name the file."""
    path = Path(path)
    try:
        config = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the training config ({exc})") from None
    for table in tables:
        if table not in config:
            raise ValueError(f"{path}: missing table [{table}]")
    return config


def training_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` → the process's GPU (``cuda:LOCAL_RANK``) when CUDA works, else the CPU."""
    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"[train] device must be 'auto', 'cpu' or 'cuda', got {name!r}")
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise ValueError("[train] device = 'cuda' but torch sees no CUDA device")
    return torch.device("cuda", local_rank % torch.cuda.device_count())
