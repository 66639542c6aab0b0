"""ngp-mi train shape: outputs and metrics, exact resume, recipe errors, every preset."""

import json

import numpy as np
import pytest
import torch
from helpers import SHAPE_TINY, shape_recipe, without_encoder
from safetensors.torch import load_file, save_file

from ngp_mi.data.shapes import ShapeDataset
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


def test_an_encoder_is_trained_for_a_prior_exported_without_one(tiny_model, tiny_maps_run, tmp_path):
    from ngp_mi.cli import main
    from ngp_mi.models.pretrained import add_encoder, export_model, load_model, load_shape
    from ngp_mi.training.shape import autoencoder_iou

    old = without_encoder(tiny_model, tmp_path / "old")
    prior = load_shape(old)
    assert not prior.has_encoder
    with pytest.raises(ValueError, match="old: this shape prior was exported without its encoder"):
        prior.reconstruct(np.ones((32, 32, 32), bool))
    recipe = shape_recipe(tmp_path, "enc", gan_iterations=0, checkpoint_every=60)
    recipe.write_text(recipe.read_text().replace("[[16, 100], [32, 150]]", "[[16, 60], [32, 60]]")
                      + f'encoder_for = "{old}"\n')
    run = train_shape(recipe, log=lambda *_: None)
    trained = ShapeModel.from_run(run)
    for name in ("decoder", "G_latent"):  # the prior's G_shape is kept exactly
        a, b = getattr(trained, name).state_dict(), getattr(prior, name).state_dict()
        assert all(torch.equal(a[k], b[k]) for k in a)
    data = ShapeDataset(tmp_path / "data")
    random_encoder = ShapeModel(trained.config)
    random_encoder.decoder.load_state_dict(prior.decoder.state_dict())
    # 120 encoder steps find codes the fixed decoder reconstructs; a random encoder's codes do not
    assert autoencoder_iou(trained, data, 32) > autoencoder_iou(random_encoder, data, 32) + 0.2
    # exported, the model ships the encoder and its card keeps the prior's own facts beside the encoder run's
    new = export_model(tmp_path / "new", tiny_maps_run, run)
    card = json.loads((new / "card.json").read_text())
    assert card["shape"]["recipe"]["train"]["encoder_for"] == str(old)
    assert card["shape"]["decoder_and_G_latent"] == json.loads((old / "card.json").read_text())["shape"]
    assert load_shape(new).has_encoder and load_shape(new).reconstruct(data.voxels(0), 32).mesh is not None
    # a folder whose runs are gone takes the encoder in place; one with another decoder refuses it by name
    patched = without_encoder(tiny_model, tmp_path / "patched")
    assert main(["export-model", "--add-encoder", str(run), "--out", str(patched)]) == 0
    *_, shape, card = load_model(patched)  # sha256s checked
    assert shape.has_encoder and card["shape"]["decoder_and_G_latent"]["steps"] > 0
    # the encoder is stored in float16 (HALF_PRECISION): exactly the run's weights rounded, nothing else changed
    assert card["files"]["shape.safetensors"]["float16"] == ["shape.encoder"]
    stored = load_file(patched / "shape.safetensors")
    assert all((v.dtype == torch.float16) == k.startswith("shape.encoder.") for k, v in stored.items() if v.is_floating_point())
    rounded = ShapeModel(trained.config)
    rounded.load_state_dict(trained.state_dict())
    rounded.encoder.load_state_dict({k: v.half().float() if v.is_floating_point() else v
                                     for k, v in trained.encoder.state_dict().items()})
    voxels = data.all_voxels()[:2]
    assert torch.equal(shape.encode(voxels), rounded.encode(voxels))
    assert not torch.equal(shape.encode(voxels), trained.encode(voxels))
    assert torch.allclose(shape.encode(voxels), trained.encode(voxels), rtol=1e-2, atol=1e-2)
    # the folder itself as the source re-writes it unchanged (already rounded); its card keeps its facts
    before = dict(card["shape"])
    assert main(["export-model", "--add-encoder", str(patched), "--out", str(patched)]) == 0
    *_, again, card = load_model(patched)
    assert card["shape"] == before and torch.equal(again.encode(voxels), shape.encode(voxels))
    other = without_encoder(tiny_model, tmp_path / "other")
    tensors = load_file(other / "shape.safetensors")
    key = next(k for k in tensors if k.startswith("shape.decoder."))
    tensors[key] = tensors[key] + 1
    save_file(tensors, other / "shape.safetensors")
    with pytest.raises(ValueError, match="its decoder differs from .*other's"):
        add_encoder(other, run)
    # the old folder's prior kept for re-trained maps (--shape-from) stays without an encoder, not a random one
    assert not load_shape(export_model(tmp_path / "kept", tiny_maps_run, shape_from=old)).has_encoder


def test_encoder_for_needs_the_priors_model_and_no_gan(tiny_model, tmp_path):
    recipe = shape_recipe(tmp_path, "bad", gan_iterations=0)
    recipe.write_text(recipe.read_text().replace("gf = 16", "gf = 8") + f'encoder_for = "{tiny_model}"\n')
    with pytest.raises(ValueError, match=r"the recipe's model differs from that prior's \(gf: 8 here, 16 there\)"):
        train_shape(recipe, log=lambda *_: None)
    recipe = shape_recipe(tmp_path, "gan")
    recipe.write_text(recipe.read_text() + f'encoder_for = "{tiny_model}"\n')
    with pytest.raises(ValueError, match="keeps that prior's G_latent: gan_iterations must be 0, got 50"):
        train_shape(recipe, log=lambda *_: None)
