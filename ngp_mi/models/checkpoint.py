"""Checkpoints that load without executing code, written atomically.

A checkpoint is a folder ``ckpt-<step:08d>/`` holding ``weights.safetensors`` (every module's
parameters and buffers, prefixed by the module's name) and ``state.pt`` (optimiser states and
plain values, read back with ``torch.load(weights_only=True)``). It is written under a temporary
name and renamed, so a job killed mid-write leaves either the previous checkpoint or the new one.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Callable

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from ngp_mi.atomic import atomic_path


def save_checkpoint(root: str | Path, step: int, modules: dict[str, torch.nn.Module], state: dict[str, Any],
                    keep: int = 3) -> Path:
    """Write ``root/ckpt-<step>``; keep the newest ``keep`` checkpoints."""
    root = Path(root)
    final = root / f"ckpt-{step:08d}"
    with atomic_path(final, directory=True) as tmp:
        tensors = {f"{name}.{key}": value.detach().contiguous().cpu()
                   for name, module in modules.items() for key, value in module.state_dict().items()}
        save_file(tensors, tmp / "weights.safetensors")
        torch.save({**state, "step": step}, tmp / "state.pt")
    for old in list_checkpoints(root)[:-keep]:
        shutil.rmtree(old)
    return final


def list_checkpoints(root: str | Path) -> list[Path]:
    """Complete checkpoints under ``root``, oldest first."""
    root = Path(root)
    return sorted(p for p in root.glob("ckpt-*") if (p / "state.pt").exists() and (p / "weights.safetensors").exists())


def saved_modules(path: str | Path) -> set[str]:
    """Names of the modules a checkpoint holds weights for (read from the file's header only)."""
    with safe_open(Path(path) / "weights.safetensors", framework="pt") as f:
        return {key.split(".", 1)[0] for key in f.keys()}


def load_checkpoint(path: str | Path, modules: dict[str, torch.nn.Module]) -> dict[str, Any]:
    """Load weights into ``modules`` (strictly: every key must match) and return the state dict."""
    path = Path(path)
    tensors = load_file(path / "weights.safetensors")
    for name, module in modules.items():
        prefix = f"{name}."
        own = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
        try:
            missing, unexpected = module.load_state_dict(own, strict=False)
        except RuntimeError as exc:  # shape mismatches
            raise ValueError(f"{path}: checkpoint does not fit module {name!r} ({str(exc).splitlines()[-1].strip()})") from None
        if missing or unexpected:
            raise ValueError(f"{path}: checkpoint does not fit module {name!r} "
                             f"(missing {list(missing)[:3]}, unexpected {list(unexpected)[:3]})")
    return torch.load(path / "state.pt", map_location="cpu", weights_only=True)  # optimisers move state to their parameters


def newest_checkpoint(run: str | Path) -> Path:
    """The newest complete checkpoint of a training run; the error names the run."""
    checkpoints = list_checkpoints(run)
    if not checkpoints:
        raise ValueError(f"{run}: no checkpoint found (ckpt-*/weights.safetensors + state.pt)")
    return checkpoints[-1]


def read_state(path: str | Path) -> dict[str, Any]:
    """A checkpoint's ``state.pt`` (plain values only: ``weights_only``), on the CPU."""
    return torch.load(Path(path) / "state.pt", map_location="cpu", weights_only=True)


def load_newest(run: str | Path, build: Callable[[dict[str, Any]], Any]) -> Any:
    """The model ``build(state)`` makes from the state of the run's newest checkpoint, with that
    checkpoint's weights loaded into its ``networks()``; None when ``build`` returns None (the run
    has no such model)."""
    path = newest_checkpoint(run)
    model = build(read_state(path))
    if model is not None:
        load_checkpoint(path, model.networks())
    return model
