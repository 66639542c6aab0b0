"""What every trainable system declares, and how it is saved and loaded (as pytorch-CycleGAN-and-pix2pix's models).

A model names its networks (the modules a checkpoint holds), optimisers (saved with them so that
training resumes exactly), losses and visuals, and keeps its configuration, a frozen dataclass,
which new checkpoints store under ``model_config[config_key]``. :meth:`BaseModel.from_run`
rebuilds a model from a run folder without executing any code from it (safetensors weights,
``torch.load(weights_only=True)`` state).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Callable

import torch
from torch import nn

from ngp_mi.models.checkpoint import load_newest


def config_from_dict(config_class: type, values: dict[str, Any]) -> Any:
    """A config dataclass from JSON / TOML values: lists become tuples where the field is a tuple."""
    def tuples(value: Any) -> Any:
        return tuple(tuples(v) for v in value) if isinstance(value, list) else value

    fields = {f.name for f in dataclasses.fields(config_class)}
    unknown = set(values) - fields
    if unknown:
        raise ValueError(f"{config_class.__name__}: unknown field(s) {sorted(unknown)}; known: {sorted(fields)}")
    return config_class(**{k: tuples(v) for k, v in values.items()})


@torch.no_grad()
def update_moving_average(average: nn.Module, trained: nn.Module, decay: float) -> None:
    """θ̄ ← decay θ̄ + (1 − decay) θ for ``average``'s weights (Polyak averaging of a generator, as
    ProGAN and StyleGAN); its buffers are copied from ``trained``."""
    for a, t in zip(average.parameters(), trained.parameters()):
        a.lerp_(t, 1.0 - decay)
    for a, t in zip(average.buffers(), trained.buffers()):
        a.copy_(t)


class BaseModel(nn.Module):
    """Subclasses set the class attributes below and ``self.config``; see the module docstring."""

    network_names: tuple[str, ...] = ()
    optimizer_names: tuple[str, ...] = ()
    loss_names: tuple[str, ...] = ()
    visual_names: tuple[str, ...] = ()
    config_class: type
    config_key: str

    def __init__(self) -> None:
        super().__init__()
        self.visuals: dict[str, torch.Tensor] = {}
        # Called with each optimiser's parameters between backward and step (multi-process training
        # averages gradients there).
        self.gradient_hook: Callable[[list[torch.Tensor]], None] | None = None

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def networks(self) -> dict[str, nn.Module]:
        return {name: getattr(self, name) for name in self.network_names}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {name: getattr(self, name) for name in self.optimizer_names}

    def optimizer_state(self) -> dict[str, Any]:
        return {name: optimizer.state_dict() for name, optimizer in self.optimizers().items()}

    def load_optimizer_state(self, state: dict[str, Any]) -> None:
        """Restore the optimisers that ``state`` holds (a stage that starts later has none yet)."""
        for name, optimizer in self.optimizers().items():
            if name in state:
                optimizer.load_state_dict(state[name])

    def config_dict(self) -> dict[str, Any]:
        """``{config_key: config}`` for a checkpoint's ``model_config`` (merged over the run's models)."""
        return {self.config_key: dataclasses.asdict(self.config)}

    def optimizer_step(self, optimizer: torch.optim.Optimizer, loss: torch.Tensor) -> None:
        """Backward and step; :attr:`gradient_hook` sees the parameters in between."""
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.gradient_hook is not None:
            self.gradient_hook([p for group in optimizer.param_groups for p in group["params"]])
        optimizer.step()

    @classmethod
    def config_from_recipe(cls, recipe: dict[str, Any]) -> Any:
        """The config of a checkpoint written before configs were stored (from its training recipe)."""
        raise NotImplementedError

    @classmethod
    def config_from_state(cls, state: dict[str, Any]) -> Any:
        """The config a checkpoint's state describes, or None when the run has no such model."""
        if "model_config" in state:  # JSON text, like the recipe beside it
            values = json.loads(state["model_config"]).get(cls.config_key)
            return None if values is None else config_from_dict(cls.config_class, values)
        return cls.config_from_recipe(json.loads(state["config"]))

    @classmethod
    def from_run(cls, run: str | Path, device: str | torch.device = "cpu") -> Any:
        """The model of a run's newest checkpoint, in eval mode on ``device``; None when the run has none."""
        def build(state: dict[str, Any]) -> Any:
            config = cls.config_from_state(state)
            return None if config is None else cls(config)

        model = load_newest(run, build)
        return None if model is None else model.to(device).eval()
