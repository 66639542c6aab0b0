"""Recipes: TOML tables into dataclasses with every key, type and range checked; --set overrides; --out."""

import dataclasses
import json

import pytest
from helpers import MAPS_TINY, maps_recipe

from ngp_mi.cli import main
from ngp_mi.models.checkpoint import list_checkpoints, read_state
from ngp_mi.training.maps import MapsRecipe
from ngp_mi.training.recipe import from_table, parse_override


@dataclasses.dataclass(frozen=True)
class Train:
    iterations: int
    lr: float = 1.0
    stages: tuple[tuple[int, int], ...] = ((16, 1),)
    name: str | None = None

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")


def test_values_are_converted_to_the_field_types():
    (t,) = from_table({"train": {"iterations": 3, "lr": 2, "stages": [[16, 2], [32, 3]], "name": "x"}}, "train", "r.toml",
                      Train)
    assert t == Train(3, 2.0, ((16, 2), (32, 3)), "x") and isinstance(t.lr, float)


@pytest.mark.parametrize("table, message", [
    ({"iterations": "2"}, r"r.toml: \[train\] iterations must be an integer, got '2'"),
    ({"iterations": True}, r"iterations must be an integer, got True"),
    ({"iterations": 2, "lr": "fast"}, r"\[train\] lr must be a number, got 'fast'"),
    ({"iterations": 2, "stages": [[16]]}, r"\[train\] stages\[0\] must be a list of 2, got \[16\]"),
    ({}, r"r.toml: missing \[train\] iterations"),
    ({"iterations": -5}, r"r.toml: \[train\] iterations must be >= 1, got -5"),
    ({"iterations": 1, "log_evry": 1}, r"unknown \[train\] field\(s\) \['log_evry'\]"),
])
def test_errors_name_the_file_table_key_and_value(table, message):
    with pytest.raises(ValueError, match=message):
        from_table({"train": table}, "train", "r.toml", Train)


def test_overrides_parse_toml_values_and_bare_words():
    assert parse_override("train.iterations=500") == ("train", "iterations", 500)
    assert parse_override("model.rf_maps=[16, 34]") == ("model", "rf_maps", [16, 34])
    assert parse_override("train.out=outputs/x") == ("train", "out", "outputs/x")
    with pytest.raises(ValueError, match="TABLE.KEY=VALUE"):
        parse_override("iterations=5")


def test_every_table_of_the_maps_recipe_is_checked(tmp_path):
    for old, new, message in (("log_every = 1", "log_evry = 1", r"unknown \[train\] field\(s\) \['log_evry'\]"),
                              ("resolution = 32", "resolutoin = 32", r"unknown \[data\] field\(s\) \['resolutoin'\]"),
                              ("batch_size = 2", 'batch_size = "2"', r"\[train\] batch_size must be an integer"),
                              ("batch_size = 2", "batch_size = 0", r"\[train\] batch_size must be >= 1, got 0"),
                              ("iterations = 6", "iterations = -5", r"\[train\] iterations must be >= 1, got -5")):
        bad = tmp_path / "bad.toml"
        bad.write_text(MAPS_TINY.read_text().replace(old, new, 1))
        with pytest.raises(ValueError, match=message):
            MapsRecipe.read(bad)
    with pytest.raises(ValueError, match=r"--set trian.iterations=3: no table \[trian\]"):
        MapsRecipe.read(MAPS_TINY, ["trian.iterations=3"])
    with pytest.raises(ValueError, match=r"\[model\] ngf must be an integer, got 'eight'"):
        MapsRecipe.read(MAPS_TINY, ["model.ngf=eight"])


def test_train_command_with_out_and_overrides_records_them(tmp_path, capsys):
    recipe = maps_recipe(tmp_path, "unused")
    out = tmp_path / "elsewhere"
    sets = ["--set", "train.iterations=1", "--set", "specular.iterations=1", "--set", "train.device=cpu"]
    assert main(["train", "maps", "--config", str(recipe), "--out", str(out), *sets]) == 0
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == ["maps", "specular"] and not (tmp_path / "unused").exists()
    used = json.loads((out / "recipe.json").read_text())
    assert used["overrides"][:2] == ["train.iterations=1", "specular.iterations=1"]
    assert used["tables"]["train"]["iterations"] == 1 and used["tables"]["train"]["out"] == str(out)
    state = read_state(list_checkpoints(out)[-1])
    assert json.loads(state["config"]) == used["tables"] and set(json.loads(state["model_config"])) == {"maps", "specular"}
    assert main(["train", "maps", "--config", str(recipe), "--set", "train.iterations=abc"]) == 1
    assert "[train] iterations must be an integer, got 'abc'" in capsys.readouterr().err
