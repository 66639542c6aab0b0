"""Checkpoints that load without executing code, written atomically.

A checkpoint is a folder ``ckpt-<step:08d>/`` holding ``weights.safetensors`` (every module's
parameters and buffers, prefixed by the module's name) and ``state.pt`` (optimiser states and
plain values, read back with ``torch.load(weights_only=True)``). It is written under a temporary
name and renamed, so a job killed mid-write leaves either the previous checkpoint or the new one
(and a temporary ``.ckpt-*`` folder, which :func:`remove_temporaries` clears when the run resumes).

A checkpoint damaged afterwards (a truncated copy, a disk error) raises :class:`DamagedCheckpoint`
naming the file; :func:`newest_readable` (what loading a run and resuming use) then falls back to
the newest checkpoint that reads, with a warning.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path
from typing import Any, Callable

import torch
from safetensors.torch import load_file, save_file

from ngp_mi.atomic import atomic_path


def module_tensors(modules: dict[str, torch.nn.Module], prefix: str = "") -> dict[str, torch.Tensor]:
    """Every parameter and buffer of ``modules``, keyed ``<prefix><module name>.<key>``, on the CPU."""
    return {f"{prefix}{name}.{key}": value.detach().contiguous().cpu()
            for name, module in modules.items() for key, value in module.state_dict().items()}


def save_checkpoint(root: str | Path, step: int, modules: dict[str, torch.nn.Module], state: dict[str, Any],
                    keep: int = 3) -> Path:
    """Write ``root/ckpt-<step>``; keep the newest ``keep`` checkpoints."""
    root = Path(root)
    final = root / f"ckpt-{step:08d}"
    with atomic_path(final, directory=True) as tmp:
        save_file(module_tensors(modules), tmp / "weights.safetensors")
        torch.save({**state, "step": step}, tmp / "state.pt")
    for old in list_checkpoints(root)[:-keep]:
        shutil.rmtree(old)
    return final


class DamagedCheckpoint(ValueError):
    """A checkpoint file that cannot be read; the message names it."""


def _damaged(file: Path, exc: BaseException) -> DamagedCheckpoint:
    # The first sentence only: torch's weights-only error goes on to suggest weights_only=False.
    first = str(exc).strip().splitlines()[0].split(". ")[0] if str(exc).strip() else ""
    return DamagedCheckpoint(f"{file}: damaged or not a checkpoint file ({type(exc).__name__}: {first[:200]})")


def read_weights(path: str | Path) -> dict[str, torch.Tensor]:
    """A checkpoint's tensors; :class:`DamagedCheckpoint` when the file does not read."""
    file = Path(path) / "weights.safetensors"
    try:
        return load_file(file)
    except Exception as exc:  # a damaged file fails in whatever way its bytes lead the reader: all mean damaged
        raise _damaged(file, exc) from None


def remove_temporaries(root: str | Path) -> list[Path]:
    """Remove the temporary folders of checkpoint writes that were killed; returns them."""
    found = [p for p in Path(root).glob(".ckpt-*") if p.is_dir()]
    for tmp in found:
        shutil.rmtree(tmp, ignore_errors=True)
    return found


def list_checkpoints(root: str | Path) -> list[Path]:
    """Complete checkpoints under ``root``, oldest first."""
    root = Path(root)
    return sorted(p for p in root.glob("ckpt-*") if (p / "state.pt").exists() and (p / "weights.safetensors").exists())


def load_checkpoint(path: str | Path, modules: dict[str, torch.nn.Module]) -> dict[str, Any]:
    """Load weights into ``modules`` (strictly: every key must match) and return the state dict."""
    load_weights(modules, read_weights(path), path)
    return read_state(path)  # on the CPU: optimisers move state to their parameters


def load_weights(modules: dict[str, torch.nn.Module], tensors: dict[str, torch.Tensor], path: str | Path) -> None:
    """Load a checkpoint's ``tensors`` (read from ``path``) into ``modules``; every key must match."""
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


def _checkpoints_of(run: str | Path) -> list[Path]:
    checkpoints = list_checkpoints(run)
    if not checkpoints:
        raise ValueError(f"{run}: no checkpoint found (ckpt-*/weights.safetensors + state.pt)")
    return checkpoints


def newest_checkpoint(run: str | Path) -> Path:
    """The newest complete checkpoint of a training run; the error names the run."""
    return _checkpoints_of(run)[-1]


def read_state(path: str | Path) -> dict[str, Any]:
    """A checkpoint's ``state.pt`` (plain values only: ``weights_only``), on the CPU;
    :class:`DamagedCheckpoint` when the file does not read."""
    file = Path(path) / "state.pt"
    try:
        state = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # random bytes reach the weights-only unpickler's IndexError, EOFError, …
        raise _damaged(file, exc) from None
    if not isinstance(state, dict) or "step" not in state:
        raise DamagedCheckpoint(f"{file}: not a checkpoint state (no 'step' in it)")
    return state


def read_newest(run: str | Path) -> tuple[Path, dict[str, Any], dict[str, torch.Tensor]]:
    """The newest checkpoint of ``run`` whose files read: its path, state and tensors. A newer
    damaged one is skipped with a warning that names the file; when none reads, the error names each."""
    damaged: list[str] = []
    for path in reversed(_checkpoints_of(run)):
        try:
            state, tensors = read_state(path), read_weights(path)
        except DamagedCheckpoint as exc:
            damaged.append(str(exc))
            continue
        for reason in damaged:
            warnings.warn(f"{reason}; using the older {path.name} instead", stacklevel=3)
        return path, state, tensors
    raise DamagedCheckpoint(f"{run}: no checkpoint reads: " + "; ".join(damaged))


def newest_readable(run: str | Path) -> tuple[Path, dict[str, Any]]:
    """The path and state of :func:`read_newest`."""
    path, state, _ = read_newest(run)
    return path, state


def load_newest(run: str | Path, build: Callable[[dict[str, Any]], Any]) -> Any:
    """The model ``build(state)`` makes from the state of the run's newest checkpoint, with that
    checkpoint's weights loaded into its ``networks()``; None when ``build`` returns None (the run
    has no such model)."""
    path, state, tensors = read_newest(run)
    model = build(state)
    if model is not None:
        load_weights(model.networks(), tensors, path)
    return model
