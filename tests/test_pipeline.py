"""NGP inference (ngp_mi/pipeline.py): the variants' algebra and `ngp-mi generate` end to end."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
import trimesh

from ngp_mi.camera import Camera
from ngp_mi.cli import main
from ngp_mi.lights import DirectionalLight, overhead_rig, save_lights
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel
from ngp_mi.pipeline import NGP, ngp_image
from ngp_mi.render.depth import project_depth
from ngp_mi.render.shading import PAPER_CONSTANTS, CameraLights, Constants, shade
from ngp_mi.training.loop import save


@pytest.fixture(scope="module")
def runs(tiny_maps_run, tiny_run):
    return tiny_maps_run, tiny_run[0]


@pytest.fixture(scope="module")
def box_view(tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "box.obj"
    trimesh.creation.box(extents=(0.6, 0.5, 0.4)).export(path)
    return path


def test_variants_compose_as_the_paper_says(runs, box_view):
    maps_run, _ = runs
    ngp = NGP(maps_run)
    from ngp_mi.geometry.loaders import load_mesh

    mesh = load_mesh(box_view)
    camera = Camera.orbit(15.0, 30.0, 32)
    z = ngp.appearance(seed=3)
    rig = overhead_rig()
    added = [DirectionalLight((1.0, 0.5, 0.2), (2.0, 2.0, 2.0))]
    full = ngp.render(mesh, camera, z, rig, "ngp")
    diffuse_only = ngp.render(mesh, camera, z, rig, "no_sp")
    assert full["mask"].sum() > 50 and torch.isfinite(full["image"]).all() and (full["image"] >= 0).all()
    # ⊕ adds the realistic specular map, on the object only
    assert torch.allclose(full["image"] - diffuse_only["image"], full["specular"], atol=1e-6)
    assert (full["specular"] * (1 - full["mask"])).abs().max() == 0
    # NGP-plus without added lights is NGP under the rig; with them it adds exactly R_BP of those lights
    plain = ngp.render(mesh, camera, z, rig, "ngp_plus")
    assert torch.allclose(plain["image"], full["image"], atol=1e-6)
    plus = ngp.render(mesh, camera, z, rig, "ngp_plus", added)
    from ngp_mi.render.shading import shade

    extra = shade(full["normal"], full["albedo"], full["mask"], added, camera, mode="blinn_phong") / math.pi
    assert torch.allclose(plus["image"] - full["image"], extra, atol=1e-5) and extra.max() > 0
    white = ngp.render(mesh, camera, z, rig, "no_gda")
    assert torch.equal(white["albedo"], torch.ones_like(white["albedo"]))
    with pytest.raises(ValueError, match="variant must be one of"):
        ngp_image(ngp.maps, ngp.specular, full["depth"], full["mask"], camera, mesh.bounds, z, rig, "ngp_best")


def test_generate_writes_images_sheet_and_report(runs, box_view, tmp_path, capsys):
    maps_run, shape_run = runs
    lights = tmp_path / "lights.json"
    save_lights(lights, [DirectionalLight((0.0, 1.0, 1.0), (1.5, 1.5, 1.5))])
    code = main(["generate", "--maps-run", str(maps_run), "--shape-run", str(shape_run), "--out", str(tmp_path / "g"),
                 "--num", "2", "--views", "10,-30;15,40", "--res", "32", "--variant", "ngp-plus", "--add-lights", str(lights)])
    assert code == 0
    summary = json.loads((tmp_path / "g" / "generate.json").read_text())
    assert summary["variant"] == "ngp_plus" and len(summary["added_lights"]) == 1
    files = [tmp_path / "g" / r["file"] for r in summary["images"]]
    assert len(files) <= 4 and all(f.stat().st_size > 0 for f in files)
    assert (tmp_path / "g" / "sheet.png").exists() and "![sheet](sheet.png)" in (tmp_path / "g" / "report.md").read_text()
    # a user mesh and an exemplar albedo image instead of sampled latents
    from PIL import Image

    Image.fromarray(np.full((32, 32, 3), 180, np.uint8)).save(tmp_path / "albedo.png")
    assert main(["generate", "--maps-run", str(maps_run), "--mesh", str(box_view), "--out", str(tmp_path / "m"),
                 "--views", "5,0", "--res", "32", "--exemplar", str(tmp_path / "albedo.png")]) == 0
    assert [r["shape"] for r in json.loads((tmp_path / "m" / "generate.json").read_text())["images"]] == ["mesh"]
    assert main(["generate", "--maps-run", str(maps_run), "--out", str(tmp_path / "x")]) != 0
    assert "--shape-run" in capsys.readouterr().err


def test_a_model_trained_with_car_constants_is_shaded_with_them_everywhere(tmp_path):
    """k_d / k_s / α are the trained model's: R_diff, R_BP and G_sp^real's input all use k_d 0.6, k_s 0.4."""
    torch.manual_seed(1)
    tiny = MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,))
    car = dataclasses.replace(tiny, **dataclasses.asdict(PAPER_CONSTANTS["car"]))
    save(tmp_path / "car", 1, [MapsModel(car), SpecularModel(SpecularConfig(ngf=8, blocks=1, ndf=8, rf_image=(16,)))],
         {})
    maps, specular = MapsModel.from_run(tmp_path / "car"), SpecularModel.from_run(tmp_path / "car")
    assert maps.config.constants == Constants(0.6, 0.4, 4.0)
    camera = Camera.orbit(10.0, 30.0, 32)
    box = trimesh.creation.box(extents=(0.6, 0.5, 0.4))
    projected = project_depth(torch.as_tensor(box.vertices, dtype=torch.float32), box.faces, camera)
    z, lights = torch.zeros(1, maps.config.latent_dim), overhead_rig()
    args = (projected.depth, projected.mask, camera, box.bounds, z, lights)
    no_sp, bp, full = (ngp_image(maps, specular, *args, variant=v) for v in ("no_sp", "ngp_bp", "ngp"))
    n, a, m = no_sp["normal"], no_sp["albedo"], projected.mask
    torch.testing.assert_close(no_sp["image"], shade(n, a, m, lights, camera, mode="diffuse", k_d=0.6) / math.pi)
    torch.testing.assert_close(bp["image"], shade(n, a, m, lights, camera, k_d=0.6, k_s=0.4, alpha=4.0) / math.pi)
    base = 2 * shade(n, a, m, CameraLights.from_lights(lights, [camera]), [camera], k_d=0.6, mode="diffuse") - 1
    torch.testing.assert_close(full["specular"], specular.specular(n, base, m))
    torch.testing.assert_close(full["image"], no_sp["image"] + full["specular"])
    assert not torch.allclose(no_sp["image"], shade(n, a, m, lights, camera, mode="diffuse", k_d=0.8) / math.pi)
