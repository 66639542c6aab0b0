"""ngp-mi evaluate shape: a prior's reconstructions of shapes it was or was not trained on."""

import json

import numpy as np
import pytest
from helpers import without_encoder

from ngp_mi.cli import main
from ngp_mi.eval.shape_eval import evaluate_shape


def test_evaluate_shape_agrees_with_training_and_writes_its_report(tiny_run, tmp_path, capsys):
    run, _ = tiny_run
    trained = json.loads((run / "metrics.json").read_text())["autoencoder_iou"]["train"]
    # the tiny recipe trains on chairs 0-5: the same IoU by another path (one shape at a time)
    result = evaluate_shape(run, tmp_path / "train", num_shapes=6, seed=0, resolution=32, log=lambda *_: None)
    assert result["iou"]["mean"] == pytest.approx(trained, abs=1e-6)
    assert main(["evaluate", "shape", "--run", str(run), "--num-shapes", "2", "--seed", "500", "--res", "32",
                 "--out", str(tmp_path / "held")]) == 0
    held = json.loads((tmp_path / "held" / "eval.json").read_text())
    assert [r["shape"] for r in held["per_shape"]] == ["chair/000500", "chair/000501"]
    assert all(0 <= r["iou"] <= 1 and 0 < r["chamfer_l2"] < 1 for r in held["per_shape"])
    assert np.isclose(held["chamfer_l2"]["mean"], np.mean([r["chamfer_l2"] for r in held["per_shape"]]))
    assert (tmp_path / "held" / "sheet.png").stat().st_size > 1000
    assert "| chair/000500 |" in (tmp_path / "held" / "eval.md").read_text()


def test_evaluate_shape_refuses_a_prior_without_its_encoder_by_name(tiny_model, tmp_path, capsys):
    old = without_encoder(tiny_model, tmp_path / "old")
    assert main(["evaluate", "shape", "--run", str(old), "--out", str(tmp_path / "e")]) == 1
    assert "old: this shape prior was exported without its encoder" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()  # refused before any work
    assert main(["evaluate", "maps", "--run", str(tmp_path)]) == 1
    assert "--data" in capsys.readouterr().err
