"""Checkpoints: atomic, loaded without executing code, strict about modules."""

import json

import numpy as np
import pytest
import torch

from ngp_mi.models.checkpoint import (DamagedCheckpoint, list_checkpoints, load_checkpoint, newest_readable,
                                      save_checkpoint)
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




def _damage(file, how, seed=0):
    if how == "truncated":
        file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    else:
        file.write_bytes(np.random.default_rng(seed).integers(0, 256, 4096, dtype=np.uint8).tobytes())


@pytest.mark.parametrize("file, how", [("weights.safetensors", "truncated"), ("weights.safetensors", "random"),
                                       ("state.pt", "truncated"), ("state.pt", "random")])
def test_a_damaged_checkpoint_is_named_and_a_run_falls_back_to_the_newest_readable(tmp_path, file, how):
    torch.manual_seed(0)
    model = MapsModel(TINY_MAPS)
    recipe = {"model": {"ngf": 8, "blocks": 1, "nef": 8, "ndf": 8, "rf_maps": [16, 34], "rf_albedo": [16]}}
    save(tmp_path, 4, [model], recipe)
    older = {k: v.clone() for k, v in model.G_da.state_dict().items()}
    with torch.no_grad():
        next(model.G_da.parameters()).add_(1.0)
    save(tmp_path, 8, [model], recipe)
    _damage(tmp_path / "ckpt-00000008" / file, how)
    with pytest.raises(DamagedCheckpoint, match=rf"ckpt-00000008/{file}: damaged or not a checkpoint file") as error:
        load_checkpoint(tmp_path / "ckpt-00000008", model.networks())
    assert "weights_only=False" not in str(error.value)
    with pytest.warns(UserWarning, match=rf"ckpt-00000008/{file}: damaged .*using the older ckpt-00000004"):
        path, state = newest_readable(tmp_path)
    assert path.name == "ckpt-00000004" and state["step"] == 4
    with pytest.warns(UserWarning, match="using the older ckpt-00000004"):
        loaded = MapsModel.from_run(tmp_path)
    assert all(torch.equal(loaded.G_da.state_dict()[k], v) for k, v in older.items())
    _damage(tmp_path / "ckpt-00000004" / file, how)
    with pytest.raises(DamagedCheckpoint, match=r"no checkpoint reads: .*ckpt-00000008.*ckpt-00000004"):
        newest_readable(tmp_path)


def test_any_bytes_in_a_checkpoint_file_read_as_damaged(tmp_path):
    """Random contents reach the readers' errors of every kind (the weights-only unpickler's
    IndexError among them): each must come back as DamagedCheckpoint naming the file."""
    save_checkpoint(tmp_path, 1, {"net": torch.nn.Linear(3, 2)}, {})
    folder = tmp_path / "ckpt-00000001"
    for seed in range(60):
        for file in ("state.pt", "weights.safetensors"):
            original = (folder / file).read_bytes()
            _damage(folder / file, "random", seed)
            with pytest.raises(DamagedCheckpoint, match=file):
                load_checkpoint(folder, {"net": torch.nn.Linear(3, 2)})
            (folder / file).write_bytes(original)
