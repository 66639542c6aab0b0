"""Shipped models: export the inference networks of runs with a card; load them without code; the same images."""

import json

import pytest
import torch
import trimesh

from ngp_mi.camera import Camera
from ngp_mi.cli import main
from ngp_mi.lights import overhead_rig
from ngp_mi.models.pretrained import PRETRAINED_ROOT, available, load_model
from ngp_mi.pipeline import NGP, NGPScene


@pytest.fixture(scope="module")
def exported(tiny_model, tiny_maps_run, tiny_run):
    return tiny_model, tiny_maps_run, tiny_run[0]


def test_an_exported_model_draws_what_its_runs_draw(exported, tmp_path):
    folder, maps_run, shape_run = exported
    card = json.loads((folder / "card.json").read_text())
    assert card["family"] == "chair" and card["figures"] == {"iou_held_out": 0.5}
    assert card["maps"]["steps"] > 0 and card["shape"]["steps"] > 0 and card["maps"]["recipe"]["model"]
    assert set(card["configs"]) == {"maps", "specular", "shape"} and card["machine"]["torch"] == torch.__version__
    assert sorted(p.name for p in folder.iterdir()) == ["card.json", "maps.safetensors", "shape.safetensors"]
    # only what inference needs: no discriminators, cycle-only networks or optimiser states
    from safetensors import safe_open

    with safe_open(folder / "maps.safetensors", framework="pt") as f:
        assert {k.split(".")[1] for k in f.keys()} == {"G_n", "G_da", "E_da", "G_sp"}
    shipped, runs = NGP.pretrained(folder), NGP(maps_run, shape_run)
    mesh_path = tmp_path / "box.obj"
    trimesh.creation.box(extents=(0.6, 0.5, 0.4)).export(mesh_path)
    for ngp in (shipped, runs):
        ngp.image = NGPScene(ngp, 32).set_shape(mesh=mesh_path).set_camera(Camera.orbit(10, 20, 32)).render()["image"]
    assert torch.equal(shipped.image, runs.image)
    z = torch.randn(runs.shape_model.config.z_dim, generator=torch.Generator().manual_seed(0))
    assert torch.equal(shipped.shape_model.code_of(z), runs.shape_model.code_of(z))


def test_a_damaged_or_unknown_model_is_refused_by_name(exported, tmp_path):
    folder, _, _ = exported
    with pytest.raises(ValueError, match=r"--model 'no-such': not a shipped model"):
        load_model("no-such")
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in folder.iterdir():
        (broken / f.name).write_bytes(f.read_bytes())
    data = bytearray((broken / "maps.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (broken / "maps.safetensors").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"broken/maps.safetensors: its sha256 differs from card.json's"):
        load_model(broken)


def test_generate_takes_a_model_and_defaults_to_the_shipped_chair(exported, tmp_path, capsys):
    folder, maps_run, _ = exported
    assert main(["generate", "--model", str(folder), "--out", str(tmp_path / "g"), "--num", "1", "--views", "10,-30",
                 "--res", "32"]) == 0
    assert json.loads((tmp_path / "g" / "generate.json").read_text())["model"] == str(folder)
    assert main(["generate", "--model", str(folder), "--maps-run", str(maps_run), "--out", str(tmp_path / "x")]) == 1
    assert "not both" in capsys.readouterr().err
    code = main(["generate", "--out", str(tmp_path / "default"), "--num", "1", "--views", "10,-30", "--res", "32"])
    if "chair" in available():
        assert code == 0
    else:  # nothing shipped yet: the error says where shipped models live
        assert code == 1 and str(PRETRAINED_ROOT) in capsys.readouterr().err


def test_export_model_command(exported, tmp_path, capsys):
    _, maps_run, _ = exported
    assert main(["export-model", "--maps-run", str(maps_run), "--out", str(tmp_path / "m"), "--family", "chair"]) == 0
    assert "maps.safetensors" in capsys.readouterr().out
    maps, specular, shape, card = load_model(tmp_path / "m")
    assert shape is None and specular is not None and card["shape"] is None
    assert len(NGP.pretrained(tmp_path / "m").maps.lights) == len(overhead_rig())


def test_export_model_keeps_another_models_shape_prior_when_only_the_maps_are_retrained(exported, tmp_path, capsys):
    folder, maps_run, shape_run = exported
    assert main(["export-model", "--maps-run", str(maps_run), "--shape-from", str(folder), "--out",
                 str(tmp_path / "m")]) == 0
    _, _, kept, card = load_model(tmp_path / "m")
    _, _, original, original_card = load_model(folder)
    z = torch.randn(kept.config.z_dim, generator=torch.Generator().manual_seed(1))
    assert torch.equal(kept.code_of(z), original.code_of(z))
    assert card["shape"]["steps"] == original_card["shape"]["steps"]
    # the kept prior is named by facts that outlive the folder: its card's notes and its file's sha256
    assert card["shape"]["kept_from"] == {"model": str(folder), "notes": original_card["notes"],
                                          "sha256": original_card["files"]["shape.safetensors"]["sha256"]}
    assert card["files"]["shape.safetensors"]["sha256"] == card["shape"]["kept_from"]["sha256"]
    # exported again over itself (a maps re-ship in place), the prior keeps naming where it came from
    assert main(["export-model", "--maps-run", str(maps_run), "--shape-from", str(tmp_path / "m"), "--out",
                 str(tmp_path / "m"), "--notes", "re-shipped"]) == 0
    assert load_model(tmp_path / "m")[3]["shape"]["kept_from"] == card["shape"]["kept_from"]
    assert card["configs"]["shape"] == original_card["configs"]["shape"]
    assert main(["export-model", "--maps-run", str(maps_run), "--shape-from", str(folder), "--shape-run",
                 str(shape_run), "--out", str(tmp_path / "x")]) == 1
    assert "not both" in capsys.readouterr().err
    assert main(["export-model", "--maps-run", str(maps_run), "--shape-from", str(tmp_path / "none"), "--out",
                 str(tmp_path / "y")]) == 1
    assert "not a shipped model" in capsys.readouterr().err


def _perturbed_copy(folder, out, prefix):
    """A copy of model ``folder`` whose tensors under ``prefix`` are moved (its card's sha256 follows)."""
    import hashlib
    import shutil

    from safetensors.torch import load_file, save_file

    shutil.copytree(folder, out)
    weights = load_file(out / "maps.safetensors")
    save_file({k: v + 0.01 if k.startswith(prefix) and v.is_floating_point() else v for k, v in weights.items()},
              out / "maps.safetensors")
    card = json.loads((out / "card.json").read_text())
    card["files"]["maps.safetensors"]["sha256"] = hashlib.sha256((out / "maps.safetensors").read_bytes()).hexdigest()
    (out / "card.json").write_text(json.dumps(card))
    return out


def test_export_model_keeps_another_models_specular_stage_trained_on_the_same_maps(exported, tmp_path, capsys):
    folder, maps_run, _ = exported
    other = _perturbed_copy(folder, tmp_path / "other_stage", "specular.")
    assert main(["export-model", "--maps-run", str(maps_run), "--specular-from", str(other), "--out",
                 str(tmp_path / "m")]) == 0
    maps, specular, _, card = load_model(tmp_path / "m")
    kept_maps, kept, _, kept_card = load_model(other)
    run_maps, run_specular, _, _ = load_model(folder)
    from ngp_mi.models.pretrained import INFERENCE_NETWORKS

    def same(x, y, kind):
        return all(torch.equal(a, b) for name in INFERENCE_NETWORKS[kind]
                   for a, b in zip(getattr(x, name).state_dict().values(), getattr(y, name).state_dict().values()))

    assert same(specular, kept, "specular") and not same(specular, run_specular, "specular")
    assert same(maps, run_maps, "maps")
    kept_from = card["maps"]["specular_kept_from"]
    assert kept_from["sha256"] == kept_card["files"]["maps.safetensors"]["sha256"] and kept_from["model"] == str(other)
    assert card["maps"]["run"] == str(maps_run) and card["configs"]["specular"] == kept_card["configs"]["specular"]
    # re-exported over itself, the stage keeps naming where it came from
    assert main(["export-model", "--maps-run", str(maps_run), "--specular-from", str(tmp_path / "m"), "--out",
                 str(tmp_path / "m")]) == 0
    assert load_model(tmp_path / "m")[3]["maps"]["specular_kept_from"] == kept_from
    # a stage trained on other map networks is refused, naming why
    capsys.readouterr()
    other_maps = _perturbed_copy(folder, tmp_path / "other_maps", "maps.G_da.")
    assert main(["export-model", "--maps-run", str(maps_run), "--specular-from", str(other_maps), "--out",
                 str(tmp_path / "x")]) == 1
    assert "G_n and G_da differ from the run's" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_the_card_adds_up_resumed_training_time_and_carries_the_runs_measurements(exported, tmp_path):
    from ngp_mi.models.pretrained import training_seconds

    assert training_seconds([10.0, 20.0, 5.0, 15.0]) == 35.0  # killed at 20 s, resumed for 15 s more
    assert training_seconds([]) == 0.0
    _, maps_run, shape_run = exported
    main(["export-model", "--maps-run", str(maps_run), "--shape-run", str(shape_run), "--out", str(tmp_path / "m")])
    card = json.loads((tmp_path / "m" / "card.json").read_text())
    assert card["shape"]["figures"]["metrics.json"] == json.loads((shape_run / "metrics.json").read_text())


def test_the_shipped_models_load_with_their_cards_within_the_size_budget():
    """Every model in the package loads (sha256 checked), says what it is and what it measured, and
    all of them together stay within issue 16's 30 MB."""
    total = sum(f.stat().st_size for f in PRETRAINED_ROOT.rglob("*") if f.is_file())
    assert total <= 30e6, f"shipped models take {total / 1e6:.1f} MB"
    for name in available():
        maps, specular, shape, card = load_model(name)
        assert card["family"] == name and specular is not None and shape is not None
        # every shipped prior reconstructs a given shape (--coarse-shapes NAME): its encoder is there, in float16
        assert shape.has_encoder and card["files"]["shape.safetensors"]["float16"] == ["shape.encoder"]
        assert card["maps"]["steps"] > 0 and card["shape"]["steps"] > 0 and card["maps"]["training_seconds"] > 0
        assert "normal_error_deg" in card["maps"]["figures"]["eval/eval.json"]
        assert card["maps"]["recipe"]["data"]["source"] == name
