"""ngp-mi train maps: outputs, exact resume, checkpoint robustness, and 2-process training (gloo)."""

import math
import json
import shutil
from pathlib import Path

import pytest
import torch
from helpers import MAPS_TINY, maps_recipe, run_torchrun
from safetensors.torch import load_file

from ngp_mi.models.checkpoint import list_checkpoints, read_state
from ngp_mi.training.loop import linear_decay
from ngp_mi.training.maps import train_maps


def weights(run: Path) -> dict:
    return load_file(list_checkpoints(run)[-1] / "weights.safetensors")


def test_outputs_and_exact_resume(tmp_path):
    # 6 map steps, then 3 steps of the G_sp^real stage. Bitwise exactness holds on the CPU; CUDA's
    # atomic reductions (cuDNN, Dr.Jit's scatter-adds) reorder sums.
    straight = train_maps(maps_recipe(tmp_path, "straight", device='"cpu"'), log=lambda *_: None)
    records = [json.loads(line) for line in (straight / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == list(range(1, 10))
    assert [r["stage"] for r in records] == ["maps"] * 6 + ["specular"] * 3
    assert all(r["G"] > 0 and r["D"] > 0 for r in records) and "cyc_real" in records[-1]
    assert sorted(p.name for p in (straight / "images").iterdir()) == [f"step-0000000{i}.png" for i in (3, 6, 9)]
    assert [p.name for p in list_checkpoints(straight)] == ["ckpt-00000003", "ckpt-00000006", "ckpt-00000009"]
    assert {k.split(".")[0] for k in weights(straight)} >= {"G_n", "G_sp", "F_sp", "D_real", "D_dfr"}

    # killed after step 3 and resumed, killed again after step 7 (inside the specular stage) and resumed
    text = maps_recipe(tmp_path, "resumed", device='"cpu"').read_text()
    for name, cut_text in (("cut-3", text[:text.index("[specular]")].replace("iterations = 6", "iterations = 3")),
                           ("cut-7", text.replace("iterations = 3", "iterations = 1"))):
        (tmp_path / f"{name}.toml").write_text(cut_text)
        train_maps(tmp_path / f"{name}.toml", log=lambda *_: None)
    assert list_checkpoints(tmp_path / "resumed")[-1].name == "ckpt-00000007"
    resumed = train_maps(maps_recipe(tmp_path, "resumed", device='"cpu"'), log=lambda *_: None)
    a, b = weights(straight), weights(resumed)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_a_maps_only_run_resumes_into_the_specular_stage(tmp_path):
    text = maps_recipe(tmp_path, "old", iterations=2, device='"cpu"').read_text()
    maps_only = tmp_path / "maps-only.toml"
    maps_only.write_text(text[:text.index("[specular]")])
    run = train_maps(maps_only, log=lambda *_: None)
    assert "G_sp" not in {k.split(".")[0] for k in weights(run)}
    train_maps(maps_recipe(tmp_path, "old", iterations=2, device='"cpu"'), log=lambda *_: None)
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == ["maps"] * 2 + ["specular"] * 3
    assert "G_sp" in {k.split(".")[0] for k in weights(run)}


ENCODER_TABLE = "[encoder]\niterations = {}\nnum_shapes = 2\nviews = 2\nbatch_size = 2\nlr = 1e-3\n\n"


def with_encoder(recipe: Path, iterations: int = 2, specular: bool = True) -> Path:
    """``recipe`` with an [encoder] stage of ``iterations`` steps before its [specular] one (or instead)."""
    text = recipe.read_text()
    head, tail = text[:text.index("[specular]")], text[text.index("[specular]"):]
    out = recipe.with_name(f"{recipe.stem}-encoder-{iterations}-{specular}.toml")
    out.write_text(head + ENCODER_TABLE.format(iterations) + (tail if specular else ""))
    return out


def test_the_encoder_stage_trains_e_da_alone_between_the_stages_and_resumes_exactly(tmp_path):
    """[encoder]: after the map stage, E_da alone on other shapes (``<cache_dir>-encoder``), then
    G_sp^real; a run cut inside the stage resumes to the same weights; from a model folder
    (--maps-from) the stage moves the folder's E_da and nothing else of it."""
    from ngp_mi.models.pretrained import export_model

    recipe = with_encoder(maps_recipe(tmp_path, "straight", iterations=2, device='"cpu"'))
    straight = train_maps(recipe, log=lambda *_: None)
    records = [json.loads(line) for line in (straight / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == ["maps"] * 2 + ["encoder"] * 2 + ["specular"] * 3
    assert all(math.isfinite(r["encoder_l1"]) and r["lr"] == 1e-3 for r in records[2:4])
    cache = json.loads(recipe.read_text().split("cache_dir = ")[1].split("\n")[0])
    assert len(list(Path(cache + "-encoder").glob("**/*.exr"))) == 4  # 2 shapes x 2 views of other seeds

    cut = with_encoder(maps_recipe(tmp_path, "resumed", iterations=2, device='"cpu"'), iterations=1, specular=False)
    train_maps(cut, log=lambda *_: None)
    assert [p.name for p in list_checkpoints(tmp_path / "resumed")] == ["ckpt-00000002", "ckpt-00000003"]
    at_maps_end, after = (load_file(tmp_path / "resumed" / f"ckpt-0000000{i}" / "weights.safetensors") for i in (2, 3))
    assert not torch.equal(at_maps_end["E_da.mu.weight"], after["E_da.mu.weight"])
    assert all(torch.equal(at_maps_end[k], after[k]) for k in at_maps_end if not k.startswith("E_da."))
    resumed = train_maps(with_encoder(maps_recipe(tmp_path, "resumed", iterations=2, device='"cpu"')),
                         log=lambda *_: None)
    a, b = weights(straight), weights(resumed)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    folder = export_model(tmp_path / "model", straight)
    only = with_encoder(maps_recipe(tmp_path, "refit", iterations=2, device='"cpu"'), specular=False)
    out = train_maps(only, log=lambda *_: None, maps_from=folder)
    shipped = {k.removeprefix("maps."): v for k, v in load_file(folder / "maps.safetensors").items()
               if k.startswith("maps.")}
    refit = weights(out)
    assert [json.loads(line)["stage"] for line in (out / "log.jsonl").read_text().splitlines()] == ["encoder"] * 2
    moved = {k for k, v in shipped.items() if not torch.equal(refit[k], v)}
    assert moved and all(k.startswith("E_da.mu.") or k.startswith("E_da.features.") for k in moved)
    with pytest.raises(ValueError, match=r"\[encoder\] lr must lie in \(0, 1\]"):
        train_maps(only, log=lambda *_: None, overrides=["encoder.lr=0"])
    # the views held in memory with their condition (the default) step as the folder read per batch does
    lines = []
    per_batch = train_maps(only, log=lines.append, maps_from=folder, out=tmp_path / "per_batch",
                           overrides=["encoder.cache_mib=0"])
    assert any("reads its 4 views per batch" in line for line in lines)
    c, d = weights(out), weights(per_batch)
    assert all(torch.allclose(c[k], d[k], atol=1e-6) for k in c)
    assert not all(torch.equal(c[k], shipped[k]) for k in shipped)


def test_config_errors_name_the_table_and_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(MAPS_TINY.read_text().replace("real_spp = 8", "real_sp = 8"))
    with pytest.raises(ValueError, match=r"unknown \[specular\] field\(s\) \['real_sp'\]"):
        train_maps(bad, log=lambda *_: None)


def test_two_processes_with_gloo_stay_in_sync(tmp_path):
    cfg = maps_recipe(tmp_path, "ddp", iterations=3, device='"cpu"')  # two CPU processes, gloo, on any machine
    train_maps(maps_recipe(tmp_path, "warm", iterations=1), log=lambda *_: None)  # render the data once
    done = run_torchrun("maps", cfg, 29517)
    assert done.returncode == 0, done.stderr[-2000:]
    records = [json.loads(line) for line in (tmp_path / "ddp" / "log.jsonl").read_text().splitlines()]
    assert records[-1] == {"step": 6, "world": 2, "ranks_in_sync": True}  # 3 map steps, 3 specular steps
    assert all(r["world"] == 2 for r in records)


def test_the_specular_stage_trains_on_exemplar_maps_with_the_highlight_input(tmp_path):
    """[specular] diffuse_input = "exemplar" draws real-maps batches in the G_sp^real stage too, and
    highlight_input / ema build and save the stage's networks as the recipe says (issue 15)."""
    sets = ["specular.diffuse_input=exemplar", "specular.highlight_input=true", "specular.ema=0.9"]
    run = train_maps(maps_recipe(tmp_path, "exemplar", iterations=1, device='"cpu"'), log=lambda *_: None,
                     overrides=sets)
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    specular = [r for r in records if r["stage"] == "specular"]
    assert specular and all(math.isfinite(r["G"]) and math.isfinite(r["D"]) for r in specular)
    tensors = weights(run)
    assert tensors["G_sp.encoder.0.1.weight"].shape[1] == 7 and "G_sp_train.encoder.0.1.weight" in tensors


def test_with_ema_the_run_keeps_both_weights_and_the_exported_model_the_averages(tmp_path):
    """[model] ema (issue 15): a checkpoint holds the averaged generators and the trained ones, and
    `export-model` ships the averages."""
    from ngp_mi.models.pretrained import export_model

    run = train_maps(maps_recipe(tmp_path, "ema", iterations=2, device='"cpu"'), log=lambda *_: None,
                     overrides=["model.ema=0.5"])
    tensors = weights(run)
    for name in ("G_n", "G_da", "G_depth", "E_da"):
        key = next(k for k in tensors if k.startswith(f"{name}.") and k.endswith("weight"))
        trained = tensors[f"{name}_train.{key.split('.', 1)[1]}"]
        assert not torch.equal(tensors[key], trained), f"{name}'s average equals its trained weights"
    shipped = load_file(export_model(tmp_path / "model", run) / "maps.safetensors")
    assert not any("_train." in k for k in shipped)
    assert all(torch.equal(v, tensors[k.removeprefix("maps.")]) for k, v in shipped.items() if k.startswith("maps."))


def test_maps_from_trains_the_specular_stage_alone_on_another_runs_map_networks(tmp_path):
    from ngp_mi.cli import main

    recipe = maps_recipe(tmp_path, "source", iterations=2, device='"cpu"')
    source = train_maps(recipe, log=lambda *_: None)
    out = tmp_path / "stage"
    assert main(["train", "maps", "--config", str(recipe), "--out", str(out), "--maps-from", str(source),
                 "--set", "specular.highlight_input=true"]) == 0
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == ["maps"] * 2 + ["specular"] * 3  # the source's log up to step 2
    seeded = load_file(out / "ckpt-00000002" / "weights.safetensors")
    at_two = load_file(source / "ckpt-00000002" / "weights.safetensors")
    assert seeded.keys() == {k for k in at_two if not k.startswith(("G_sp.", "G_sp_train.", "F_sp.", "D_real.", "D_dfr."))}
    assert all(torch.equal(seeded[k], at_two[k]) for k in seeded)
    final = weights(out)
    assert all(torch.equal(final[k], at_two[k]) for k in seeded)  # the map networks stay fixed
    assert final["G_sp.encoder.0.1.weight"].shape[1] == 7  # the stage is built by this recipe
    with pytest.raises(ValueError, match="no checkpoint at step 4"):
        train_maps(maps_recipe(tmp_path, "source", iterations=4, device='"cpu"'), log=lambda *_: None,
                   out=tmp_path / "other", maps_from=source)


def test_maps_from_a_model_folder_trains_its_specular_stage_on_the_shipped_map_networks(tmp_path):
    """--maps-from takes a model folder (a shipped model's G_sp^real stage re-trained): the seeded
    checkpoint holds the folder's G_n, G_da, E_da (averaged and trained copies under ema), the stage
    trains on them unchanged; a recipe whose [model] is not the card's fails naming the field."""
    from ngp_mi.models.pretrained import export_model

    recipe = maps_recipe(tmp_path, "source", iterations=2, device='"cpu"')
    folder = export_model(tmp_path / "model", train_maps(recipe, log=lambda *_: None, overrides=["model.ema=0.5"]))
    shipped = {k.removeprefix("maps."): v for k, v in load_file(folder / "maps.safetensors").items()
               if k.startswith("maps.")}
    out = train_maps(recipe, log=lambda *_: None, out=tmp_path / "stage", maps_from=folder,
                     overrides=["model.ema=0.5"])
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == ["specular"] * 3
    assert [p.name for p in list_checkpoints(out)][0] == "ckpt-00000002"
    final = weights(out)
    for key, value in shipped.items():
        assert torch.equal(final[key], value), key  # the shipped networks, fixed through the stage
        name, rest = key.split(".", 1)
        assert torch.equal(final[f"{name}_train.{rest}"], value), key
    assert "G_sp.encoder.0.1.weight" in final
    card = json.loads((export_model(tmp_path / "re-trained", out) / "card.json").read_text())
    source_card = json.loads((folder / "card.json").read_text())
    assert card["maps"]["steps"] == 5 and card["maps"]["map_networks_from"]["model"] == str(folder)
    assert card["maps"]["map_networks_from"]["steps"] == source_card["maps"]["steps"] == 5
    with pytest.raises(ValueError, match=r"card\.json in k_d \(0\.5 in the recipe, 0\.\d+ in the card\)"):
        train_maps(recipe, log=lambda *_: None, out=tmp_path / "other", maps_from=folder,
                   overrides=["model.ema=0.5", "model.k_d=0.5"])
    # R_diff's own k_d may change (a stage for another energy split): the card then says the new one
    out = train_maps(recipe, log=lambda *_: None, out=tmp_path / "k_diff", maps_from=folder,
                     overrides=["model.ema=0.5", "model.k_diff=0.7"])
    assert json.loads((export_model(tmp_path / "k_diff-model", out) / "card.json").read_text())[
        "configs"]["maps"]["k_diff"] == 0.7


def test_coarse_shapes_from_a_model_folder(tmp_path):
    """[data] coarse_shapes takes a shipped model's name as render-dataset --coarse-shapes does: the
    depth folder holds its reconstructions (same ids, other depth); a folder without an encoder, or
    a name that is neither, fails naming the field before anything is rendered."""
    from helpers import without_encoder

    from ngp_mi.data.datasets import ReflectanceMapDataset
    from ngp_mi.models.pretrained import resolve
    from ngp_mi.training.maps import MapsData, prepare_data

    data = MapsData(num_shapes=1, views=1, resolution=32, cache_dir=str(tmp_path / "maps"), coarse_shapes="chair",
                    coarse_resolution=32)
    maps, depth = prepare_data(data, rank=0)
    assert depth == Path(f"{tmp_path / 'maps'}-coarse")
    detailed, coarse = ReflectanceMapDataset(maps)[0], ReflectanceMapDataset(depth)[0]
    assert coarse["mask"].sum() > 0 and not torch.equal(detailed["depth"], coarse["depth"])

    without_encoder(resolve("chair"), tmp_path / "old")
    for bad, message in ((str(tmp_path / "old"), "without its encoder"), ("no-such-model", "not a shipped model")):
        cache = tmp_path / f"bad-{len(message)}"
        with pytest.raises(ValueError, match=rf"\[data\] coarse_shapes = .*{message}"):
            prepare_data(MapsData(num_shapes=1, views=1, resolution=32, cache_dir=str(cache), coarse_shapes=bad), 0)
        assert not Path(f"{cache}-coarse").exists()


def test_the_normal_cycle_on_the_real_maps_coarse_reconstructions_trains(tmp_path):
    """[model] normal_cycle_depth = "coarse" pairs each real view with its shape's reconstruction by
    [data] coarse_shapes and trains; without coarse_shapes it fails naming both fields."""
    recipe = maps_recipe(tmp_path, "coarse", iterations=2, device='"cpu"')
    common = ['model.normal_cycle_depth="coarse"', "data.num_shapes=2", "data.views=2"]
    with pytest.raises(ValueError, match=r"normal_cycle_depth = 'coarse' .* set \[data\] coarse_shapes"):
        train_maps(recipe, log=lambda *_: None, overrides=common)
    run = train_maps(recipe, log=lambda *_: None, overrides=[*common, 'data.coarse_shapes="chair"',
                                                             "data.coarse_resolution=32"])
    maps_steps = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    maps_steps = [s for s in maps_steps if s["stage"] == "maps"]
    assert [s["step"] for s in maps_steps] == [1, 2] and all(math.isfinite(s["cyc_n"]) for s in maps_steps)


def test_normal_steps_log_g_ns_own_loss_and_resume_exactly(tmp_path):
    """[model] normal_steps = 3: each map step logs the mean of G_n's two extra steps (cyc_n_alone), and
    a run killed after step 2 and resumed ends with the straight run's weights (the extra batches
    are a function of the step)."""
    overrides = ['model.normal_cycle_depth="real"', "model.normal_steps=3"]
    straight = train_maps(maps_recipe(tmp_path, "straight", iterations=4, device='"cpu"'), log=lambda *_: None,
                          overrides=overrides)
    records = [json.loads(line) for line in (straight / "log.jsonl").read_text().splitlines()]
    maps_records = [r for r in records if r["stage"] == "maps"]
    assert len(maps_records) == 4 and all(math.isfinite(r["cyc_n_alone"]) and r["cyc_n_alone"] > 0
                                          for r in maps_records)
    text = maps_recipe(tmp_path, "resumed", iterations=4, device='"cpu"').read_text()
    (tmp_path / "cut.toml").write_text(text[:text.index("[specular]")].replace("iterations = 4", "iterations = 2"))
    train_maps(tmp_path / "cut.toml", log=lambda *_: None, overrides=overrides)
    resumed = train_maps(maps_recipe(tmp_path, "resumed", iterations=4, device='"cpu"'), log=lambda *_: None,
                         overrides=overrides)
    a, b = weights(straight), weights(resumed)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match=r"normal_steps_depth = 'coarse' .* set \[data\] coarse_shapes"):
        train_maps(maps_recipe(tmp_path, "coarse", iterations=1, device='"cpu"'), log=lambda *_: None,
                   overrides=["model.normal_steps=2", 'model.normal_steps_depth="coarse"'])


def test_lr_decay_sets_the_map_optimisers_rates_by_step_and_resumes_exactly(tmp_path):
    """[train] lr_decay_from = 0.5 over 4 map steps: the log's and the checkpoints' Adam rates are lr ×
    the schedule's factor (steps 2 and 3 decay), and a run killed after step 3 and resumed ends with
    the straight run's weights."""
    text = maps_recipe(tmp_path, "straight", iterations=4, device='"cpu"', checkpoint_every=1).read_text()
    (tmp_path / "maps-only.toml").write_text(text[:text.index("[specular]")])
    overrides = ["train.lr_decay_from=0.5"]
    straight = train_maps(tmp_path / "maps-only.toml", log=lambda *_: None, overrides=overrides)
    lr = json.loads(read_state(list_checkpoints(straight)[0])["model_config"])["maps"]["lr"]
    factors = [1.0, 1.0, 2 / 3, 1 / 3]
    assert factors == pytest.approx([linear_decay(s, 4, 0.5) for s in range(4)])
    records = [json.loads(line) for line in (straight / "log.jsonl").read_text().splitlines()]
    assert [r["lr"] for r in records] == pytest.approx([lr * f for f in factors])
    for checkpoint, factor in zip(list_checkpoints(straight), factors[1:]):  # the newest three: steps 2, 3, 4
        state = read_state(checkpoint)
        assert all(g["lr"] == pytest.approx(lr * factor) for name in ("opt_G", "opt_D")
                   for g in state[name]["param_groups"]), checkpoint.name

    # killed after step 3: the straight run's folder without its last checkpoint, resumed
    shutil.copytree(straight, tmp_path / "resumed")
    shutil.rmtree(list_checkpoints(tmp_path / "resumed")[-1])
    resumed = train_maps(tmp_path / "maps-only.toml", log=lambda *_: None, out=tmp_path / "resumed",
                         overrides=overrides)
    a, b = weights(straight), weights(resumed)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match=r"\[train\] lr_decay_from = 1.5"):
        train_maps(maps_recipe(tmp_path, "bad", iterations=1, device='"cpu"'), log=lambda *_: None,
                   overrides=["train.lr_decay_from=1.5"])
