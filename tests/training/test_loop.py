"""The trainers' shared loop: seeded batches, and a log that holds every step once after a resume."""

import json

import pytest
import torch

from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.training.loop import JsonLog, SeededBatches, linear_decay, resume, save


def test_batches_visit_every_item_once_per_epoch_and_ranks_split_them():
    data = list(range(24))
    ranks = [SeededBatches(data, 4, seed=3, rank=r, world=2) for r in range(2)]
    epoch = [i for step in range(3) for b in ranks for i in b.indices(step)]
    assert sorted(epoch) == data  # 3 steps x 2 ranks x 4 = one epoch
    assert ranks[0].indices(0) == SeededBatches(data, 4, seed=3, rank=0, world=2).indices(0)  # reproducible
    assert ranks[0].indices(3) != ranks[0].indices(0)  # the next epoch is another permutation


def test_a_dataset_smaller_than_a_batch_repeats_or_is_refused():
    assert sorted(set(SeededBatches([10, 11, 12], 8, seed=0, repeat=True).indices(5))) == [0, 1, 2]
    assert len(SeededBatches([10, 11, 12], 8, seed=0, repeat=True).indices(0)) == 8
    with pytest.raises(ValueError, match="smaller than one global batch"):
        SeededBatches([10, 11, 12], 8, seed=0)


def test_a_resumed_log_drops_the_steps_after_its_checkpoint(tmp_path):
    log = JsonLog(tmp_path)
    for step in range(1, 8):
        log.write({"step": step, "loss": 1.0 / step})
    log = JsonLog(tmp_path, resumed_step=5)  # killed after step 7, resumed from the checkpoint at 5
    for step in (6, 7):
        log.write({"step": step})
    steps = [json.loads(line)["step"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 8))


def test_a_resume_skips_a_damaged_checkpoint_and_clears_killed_writes(tmp_path):
    torch.manual_seed(0)
    model = MapsModel(MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,)))
    save(tmp_path, 3, [model], {})
    save(tmp_path, 6, [model], {})
    (tmp_path / "ckpt-00000006" / "state.pt").write_bytes(b"\x80\x02garbage")
    killed = tmp_path / ".ckpt-00000009.a1b2c3"  # what a checkpoint write killed by kill -9 leaves
    killed.mkdir()
    (killed / "weights.safetensors").write_bytes(b"partial")
    with pytest.warns(UserWarning, match=r"ckpt-00000006/state.pt: damaged .*using the older ckpt-00000003"):
        step, path = resume(tmp_path, [model])
    assert step == 3 and path.name == "ckpt-00000003" and not killed.exists()


def test_linear_decay_is_constant_then_falls_to_a_small_positive_rate():
    # 10 steps from 0.6 on: steps 0-5 at full rate, then 4/5 … 1/5 (CycleGAN's policy per step)
    assert [linear_decay(s, 10, 0.6) for s in range(10)] == pytest.approx([1] * 6 + [0.8, 0.6, 0.4, 0.2])
    assert all(linear_decay(s, 7, 1.0) == 1.0 for s in range(7))  # 1: constant
    assert linear_decay(0, 4, 0.0) == pytest.approx(0.8) and linear_decay(3, 4, 0.0) == pytest.approx(0.2)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="lr_decay_from"):
            linear_decay(0, 10, bad)
