"""ngp-mi compare: outputs, the path-tracing ladder, and radiometric agreement of R_diff."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from ngp_mi.camera import Camera
from ngp_mi.eval.compare import CompareConfig, run_compare
from ngp_mi.eval.metrics import psnr
from ngp_mi.lights import overhead_rig
from ngp_mi.models.pretrained import export_model, trained_source
from ngp_mi.render.gbuffer import GBufferRenderer, maps_to_tensors
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render
from ngp_mi.render.shading import shade


def test_compare_writes_report_and_the_ladder_converges(tmp_path):
    config = CompareConfig(num_shapes=1, views=1, resolution=32, light_setups=("rig",), spp_ladder=(1, 16, 64),
                           reference_spp=256)
    summary = run_compare(config, tmp_path, log=lambda *_: None)
    for name in ("report.html", "results.json", "speed_accuracy.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert len(list((tmp_path / "images").glob("*.png"))) == 1
    ladder = [s for s in summary if s["kind"] == "path"]
    assert [s["spp"] for s in ladder] == [1, 16, 64]
    assert ladder[0]["psnr_linear"] < ladder[1]["psnr_linear"] < ladder[2]["psnr_linear"]
    assert {s["kind"] for s in summary} == {"reference", "path", "deferred", "effect"}
    report = (tmp_path / "report.html").read_text()
    assert "divided by π" in report and "R_BP" in report and "FID" in report
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert len(rows) == 1 + 3 + 4 and all(r["seconds"] > 0 for r in rows)


def test_r_diff_over_pi_equals_unshadowed_lambertian_radiance():
    """A convex diffuse sphere: no shadows, no specular, so R_diff(k_d=1)/pi must match Mitsuba."""
    camera = Camera.orbit(10.0, 20.0, 48)
    shapes = {"s": {"type": "sphere", "radius": 0.4, "bsdf": diffuse_bsdf((0.6, 0.4, 0.2))}}
    lights = overhead_rig()
    reference = render(build_scene(camera, shapes, lights, {"type": "direct_unshadowed"}, spp=64))
    maps = GBufferRenderer(shapes, np.array([[-0.4] * 3, [0.4] * 3]), camera, ("normal", "albedo", "mask")).render(camera)
    t = maps_to_tensors(maps)
    ours = shade(t["normal"], t["albedo"], t["mask"], lights, camera, k_d=1.0, mode="diffuse")[0].permute(1, 2, 0).numpy()
    interior = maps["mask"] > 0
    interior &= np.roll(interior, 1, 0) & np.roll(interior, -1, 0) & np.roll(interior, 1, 1) & np.roll(interior, -1, 1)
    assert psnr(reference, ours / math.pi, interior.astype(float)) > 45.0


def test_without_a_source_compare_scores_the_family_the_maps_trained_on(tmp_path, tiny_maps_run):
    """A car run (or a car model folder) compared without --source is scored on cars, not on the default chairs."""
    from ngp_mi.models.checkpoint import save_checkpoint

    assert trained_source(str(tiny_maps_run)) == "chair"  # the tiny recipe's family
    car_run = tmp_path / "car_run"
    save_checkpoint(car_run, 5, {"G": torch.nn.Linear(1, 1)}, {"config": json.dumps({"data": {"source": "car"}})})
    (car_run / "recipe.json").write_text("{}")
    assert trained_source(str(car_run)) == "car"
    folder = export_model(tmp_path / "model", tiny_maps_run, family="car")
    assert trained_source(folder) == "chair"  # the recipe's data source before the card's family
    card = json.loads((folder / "card.json").read_text())
    del card["maps"]["recipe"]["data"]["source"]
    (folder / "card.json").write_text(json.dumps(card))
    assert trained_source(folder) == "car"


def test_compare_scores_a_model_folder_as_the_run_it_was_exported_from(tmp_path, tiny_maps_run):
    """`compare --model DIR` (and a shipped name) loads the same map networks and G_sp^real as the run."""
    from ngp_mi.cli import main

    folder = export_model(tmp_path / "model", tiny_maps_run)
    config = CompareConfig(num_shapes=1, views=1, resolution=32, light_setups=("rig",), spp_ladder=(1,),
                           reference_spp=16)
    scores = {}
    for name, networks in (("run", tiny_maps_run), ("folder", folder)):
        summary = run_compare(dataclasses.replace(config, maps_checkpoint=str(networks)), tmp_path / name,
                              log=lambda *_: None)
        scores[name] = {s["method"]: s["psnr_linear"] for s in summary if s["kind"] == "neural"}
    assert "NGP: R_diff ⊕ G_sp^real" in scores["run"] and scores["folder"] == scores["run"]
    with pytest.raises(ValueError, match="'nowhere': not a shipped model"):
        run_compare(dataclasses.replace(config, maps_checkpoint="nowhere"), tmp_path / "x", log=lambda *_: None)
    assert main(["compare", "--out", str(tmp_path / "cli"), "--model", str(folder), "--num-shapes", "1", "--views",
                 "1", "--res", "32", "--lights", "rig", "--spp-ladder", "1", "--reference-spp", "16",
                 "--exemplar-steps", "3"]) == 0
    results = json.loads((tmp_path / "cli" / "results.json").read_text())
    assert results["config"]["maps_checkpoint"] == str(folder) and results["config"]["exemplar_steps"] == 3
    fitted = {s["method"] for s in results["summary"] if s["method"].endswith(", z_da fitted to the exemplar")}
    assert fitted == {"NGP w/o G_sp^real: R_diff on generated maps, z_da fitted to the exemplar",
                      "NGP: R_diff ⊕ G_sp^real, z_da fitted to the exemplar"}


def test_compare_with_trained_map_networks_and_fid(tmp_path, tiny_maps_run):
    run = tiny_maps_run  # maps + specular stage
    weights = tmp_path / "inception-2015-12-05.pt"
    torch.jit.save(torch.jit.script(_FakeInception()), str(weights))
    config = CompareConfig(num_shapes=1, views=2, resolution=32, light_setups=("rig", "rig+random"), spp_ladder=(4,),
                           reference_spp=64, maps_checkpoint=str(run), inception_weights=str(weights))
    summary = run_compare(config, tmp_path / "cmp", log=lambda *_: None)
    neural = {s["method"].split(":")[0]: s for s in summary if s["kind"] == "neural"}
    assert set(neural) == {"NGP-BP", "NGP w/o G_sp^real", "NGP", "NGP w/o G_n", "NGP w/o G_da", "NGP-plus"}
    assert all(math.isfinite(s["psnr_linear"]) for s in neural.values())
    assert neural["NGP-plus"]["images"] == 2 and neural["NGP"]["images"] == 4  # plus: only where lights are added
    assert all(math.isfinite(s["fid"]) and math.isfinite(s["kid"]) for s in summary if s["kind"] != "reference")
    report = (tmp_path / "cmp" / "report.html").read_text()
    assert "NGP-plus" in report and "<th>fid</th>" in report
    assert all("path_ms_at_equal_flip" in s and s["speedup"] > 0 for s in neural.values())
    assert "path tracing ms at equal FLIP" in report
    place = neural["NGP"]  # where G_sp^real's light goes, against the reference's excess over the diffuse image
    assert 0 <= place["specular_precision"] <= 1 and 0 <= place["specular_recall"] <= 1 and place["specular_added"] >= 0
    assert 0 <= place["specular_nyquist"] <= 1 and "<th>specular_nyquist</th>" in report
    assert 0 <= place["specular_colour_deg"] <= 90 and "<th>specular_colour_deg</th>" in report
    assert "specular_precision" not in neural["NGP w/o G_sp^real"] and "<th>specular_precision</th>" in report


class _FakeInception(torch.nn.Module):
    """The call signature of the TorchScript Inception (uint8 NCHW in, features out), 6-d features."""

    def forward(self, img: torch.Tensor, return_features: bool = False) -> torch.Tensor:
        x = img.float() / 255
        return torch.cat([x.mean((2, 3)), x.std((2, 3))], 1)


def test_fid_without_weights_names_the_file(tmp_path):
    from ngp_mi.eval.fid import InceptionFeatures

    with pytest.raises(FileNotFoundError, match="inception-2015-12-05.pt"):
        InceptionFeatures(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_text("not torchscript")
    with pytest.raises(ValueError, match="bad.pt: not a TorchScript module"):
        InceptionFeatures(tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="light setup must be one of"):
        run_compare(CompareConfig(light_setups=("rig", "sun")), tmp_path / "x", log=lambda *_: None)


def test_the_path_tracers_time_at_equal_flip_is_interpolated_on_the_ladder():
    from ngp_mi.eval.compare import add_equal_flip_times

    ladder = [{"method": f"path tracing {spp} spp", "kind": "path", "median_ms": ms, "flip": f}
              for spp, ms, f in ((1, 2.0, 0.4), (4, 8.0, 0.2), (16, 32.0, 0.1))]
    others = [{"method": m, "kind": "neural", "median_ms": 20.0, "flip": f}
              for m, f in (("between", 0.4 / 2 ** 0.5), ("worse", 0.5), ("better", 0.05), ("on a rung", 0.1))]
    out = {s["method"]: s for s in add_equal_flip_times(ladder + others)}
    assert out["between"]["path_ms_at_equal_flip"] == pytest.approx(4.0)  # time ∝ FLIP^-2 between these rungs
    assert out["between"]["speedup"] == pytest.approx(0.2)
    assert (out["worse"]["path_ms_at_equal_flip"], out["worse"]["equal_flip_note"]) == (2.0, "at most (lowest spp of the ladder)")
    assert out["better"]["equal_flip_note"] == "more than (highest spp)"
    assert out["on a rung"]["path_ms_at_equal_flip"] == pytest.approx(32.0)
    assert "path_ms_at_equal_flip" not in out["path tracing 4 spp"]


def test_report_cells_keep_small_shares_readable():
    """A share such as specular_nyquist (~0.001) keeps two significant digits instead of printing as 0."""
    from ngp_mi.eval.report import fmt

    assert [fmt(v) for v in (0.0, 0.00017, 0.0013, 0.197, 42.63, float("inf"), 3)] == [
        "0.000", "0.00017", "0.0013", "0.197", "42.6", "∞", "3"]
