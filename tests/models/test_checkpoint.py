"""Checkpoints: atomic, loaded without executing code, strict about modules."""

import json

import pytest
import torch

from ngp_mi.models.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularModel
from ngp_mi.training.loop import save


def test_checkpoints_are_atomic_and_load_without_code(tmp_path):
    net = torch.nn.Linear(3, 2)
    save_checkpoint(tmp_path, 5, {"net": net}, {"note": "x"})
    (tmp_path / ".ckpt-crashed").mkdir()  # a write that was killed
    (tmp_path / "ckpt-00000009").mkdir()  # an incomplete folder
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt-00000005"]
    state = torch.load(tmp_path / "ckpt-00000005" / "state.pt", weights_only=True)
    assert state == {"note": "x", "step": 5}
    other = torch.nn.Linear(3, 2)
    load_checkpoint(tmp_path / "ckpt-00000005", {"net": other})
    assert torch.equal(other.weight, net.weight)
    with pytest.raises(ValueError, match="does not fit module 'net'"):
        load_checkpoint(tmp_path / "ckpt-00000005", {"net": torch.nn.Linear(4, 2)})


TINY_MAPS = MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,))


def test_a_model_loads_itself_from_a_run_and_from_checkpoints_that_predate_stored_configs(tmp_path):
    torch.manual_seed(0)
    model = MapsModel(TINY_MAPS)
    recipe = {"model": {"ngf": 8, "blocks": 1, "nef": 8, "ndf": 8, "rf_maps": [16, 34], "rf_albedo": [16]}}
    save(tmp_path / "new", 4, [model], recipe)
    # the format before configs were stored: weights, optimisers and the recipe only
    save_checkpoint(tmp_path / "old", 4, model.networks(), {**model.optimizer_state(), "config": json.dumps(recipe)})
    for run in ("new", "old"):
        loaded = MapsModel.from_run(tmp_path / run)
        assert loaded.config == TINY_MAPS and not loaded.training
        assert all(torch.equal(a, b) for a, b in zip(loaded.G_da.parameters(), model.G_da.parameters()))
        assert SpecularModel.from_run(tmp_path / run) is None  # no G_sp^real stage in this run
    with pytest.raises(ValueError, match=r"nothing: no checkpoint found"):
        MapsModel.from_run(tmp_path / "nothing")


