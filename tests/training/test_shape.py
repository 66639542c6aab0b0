"""ngp-mi train shape: outputs and metrics, exact resume, recipe errors, every preset."""

import json

import numpy as np
import pytest
import torch
from helpers import SHAPE_TINY, shape_recipe
from safetensors.torch import load_file

from ngp_mi.models.checkpoint import list_checkpoints
from ngp_mi.models.shape import ShapeModel
from ngp_mi.training.shape import ShapeRecipe, train_shape


def test_training_outputs_metrics_and_learns(tiny_run):
    run, _ = tiny_run
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    ae = [r for r in records if r.get("phase") == "ae"]
    gan = [r for r in records if r.get("phase") == "gan"]
    assert [r["resolution"] for r in ae][0] == 16 and ae[-1]["resolution"] == 32  # progressive
    assert gan and all(np.isfinite(r["gan_wasserstein"]) for r in gan)
    metrics = json.loads((run / "metrics.json").read_text())
    # The tiny preset (11 s) reaches IoU ~0.65 on its training shapes; an untrained decoder gives 0.
    assert metrics["autoencoder_iou"]["train"] > 0.3 and "held_out" in metrics["autoencoder_iou"]
    samples = metrics["samples"]
    assert samples["samples"] == 4 and {"coverage", "mmd"} <= set(samples) and "held_out_real" in samples


def test_training_resumes_exactly(tmp_path):
    straight = train_shape(shape_recipe(tmp_path, "straight", checkpoint_every=40, gan_iterations=10), log=lambda *_: None)
    cut = shape_recipe(tmp_path, "resumed", checkpoint_every=40, gan_iterations=10)
    text = cut.read_text().replace("stages = [[16, 100], [32, 150]]", "stages = [[16, 100], [32, 20]]")
    cut.with_name("cut.toml").write_text(text.replace("gan_iterations = 10", "gan_iterations = 0"))
    train_shape(cut.with_name("cut.toml"), log=lambda *_: None)  # stops at step 120 (checkpoint) ...
    resumed = train_shape(cut, log=lambda *_: None)               # ... and continues to the end
    a = load_file(list_checkpoints(straight)[-1] / "weights.safetensors")
    b = load_file(list_checkpoints(resumed)[-1] / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_bad_configs_name_the_field(tmp_path):
    bad = shape_recipe(tmp_path, "bad")
    bad.write_text(bad.read_text().replace("gf = 16", "gf = 16\nwidth = 3"))
    with pytest.raises(ValueError, match=r"unknown \[model\] field\(s\) \['width'\]"):
        train_shape(bad)
    bad.write_text(SHAPE_TINY.read_text().replace("stages = [[16, 100], [32, 150]]", "stages = [[64, 10]]"))
    with pytest.raises(ValueError, match="stage resolution 64"):
        train_shape(bad)


@pytest.mark.parametrize("preset", ["tiny", "cpu", "paper"])
def test_every_preset_config_loads_and_builds(preset):
    recipe = ShapeRecipe.read(SHAPE_TINY.with_name(f"shape_{preset}.toml"))
    data = recipe.data
    model = ShapeModel(recipe.model)
    assert model.encoder(torch.zeros(1, 1, *(data.voxel_resolution,) * 3)).shape == (1, model.config.code_dim)
