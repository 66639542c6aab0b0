import math

import pytest
import torch
from helpers import maps_recipe

from ngp_mi.camera import Camera
from ngp_mi.eval.maps_eval import angular_error_deg, evaluate_maps
from ngp_mi.render.from_depth import normals_from_depth, smooth_depth
from ngp_mi.training.maps import train_maps


def test_angular_error_known_angles():
    truth = torch.tensor([0.0, 0.0, -1.0]).reshape(1, 3, 1, 1).expand(1, 3, 2, 2)
    a = math.radians(30)
    predicted = torch.tensor([math.sin(a), 0.0, -math.cos(a)]).reshape(1, 3, 1, 1).expand(1, 3, 2, 2) * 5
    mask = torch.tensor([[1.0, 1.0], [0.0, 1.0]]).reshape(1, 1, 2, 2)
    errors = angular_error_deg(predicted, truth, mask)
    assert errors.shape == (3,) and torch.allclose(errors, torch.full((3,), 30.0), atol=1e-4)


def test_smoothing_keeps_background_and_planes():
    camera = Camera.orbit(0.0, 0.0, 24)
    mask = torch.zeros(1, 1, 24, 24)
    mask[..., 4:20, 4:20] = 1
    plane = torch.linspace(1.5, 1.8, 24).reshape(1, 1, 1, 24).expand(1, 1, 24, 24) * mask  # a tilted plane
    smoothed = smooth_depth(plane, mask, 2.0)
    assert smoothed[mask == 0].abs().max() == 0
    inner = torch.zeros_like(mask, dtype=torch.bool)
    inner[..., 10:14, 10:14] = True  # at least 3 sigma from the mask edge
    assert torch.allclose(smoothed[inner], plane[inner], atol=1e-5)  # a linear function survives a symmetric blur
    normals = normals_from_depth(plane.double(), mask, camera)
    assert torch.isfinite(normals).all()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval")
    return train_maps(maps_recipe(tmp, "run", iterations=3), log=lambda *_: None), tmp / "data"


def test_evaluation_runs_and_reports_both_normal_methods(trained, tmp_path):
    run, data = trained
    result = evaluate_maps(run, data, tmp_path, coarse_sigma=1.5, latent_samples=3)
    errors = result["normal_error_deg"]
    for method in ("G_n", "from_coarse_depth"):
        assert 0 <= errors[method]["median"] <= 180 and math.isfinite(errors[method]["mean"])
    assert result["albedo_reconstruction_l1"] > 0 and result["albedo_diversity_l1"] >= 0
    assert 0 < result["albedo_single_colour_l1"] < 1 and result["appearance_diversity_ratio"] > 0
    assert (tmp_path / "eval.md").read_text().count("|") > 10 and (tmp_path / "eval.png").exists()
    # Smoothing removes detail: the baseline from the sharp depth is better. (At 32 px the parts are
    # a few pixels wide, so even the sharp depth's finite differences are off by ~20 deg; 0.01 deg at 128 px.)
    sharp = evaluate_maps(run, data, tmp_path / "sharp", coarse_sigma=0.0)
    assert sharp["normal_error_deg"]["from_coarse_depth"]["median"] < errors["from_coarse_depth"]["median"]


def test_a_coarse_dataset_pairs_by_shape_and_view(trained, tmp_path):
    """With the detailed views themselves as the "coarse" set the result equals the unsmoothed depth's;
    a coarse set that lacks a view is refused with the view named."""
    from ngp_mi.data.render_dataset import DatasetConfig, render_dataset

    run, data = trained
    sharp = evaluate_maps(run, data, tmp_path / "sharp", coarse_sigma=0.0, latent_samples=2)
    paired = evaluate_maps(run, data, tmp_path / "paired", coarse_data=data, latent_samples=2)
    assert paired["coarse_overlap"] == pytest.approx(1.0)
    for method in ("G_n", "from_coarse_depth"):
        assert paired["normal_error_deg"][method]["mean"] == pytest.approx(sharp["normal_error_deg"][method]["mean"])
    partial = tmp_path / "partial"
    render_dataset(DatasetConfig(source="chair", num_shapes=4, views=2, resolution=32, channels=("depth", "mask")),
                   partial, progress=False)
    with pytest.raises(ValueError, match=r"no coarse view for shape 'chair/00000\d' view [23]"):
        evaluate_maps(run, data, tmp_path / "bad", coarse_data=partial)


def test_residual_normals_start_from_the_depth_normals():
    """normal_residual: G_n's correction starts at 0, so an untrained N^g is exactly the
    finite-difference normals of the depth (and background stays 0)."""
    from ngp_mi.models.maps import MapsConfig, MapsModel, depth_to_net

    model = MapsModel(MapsConfig(ngf=4, blocks=1, nef=4, ndf=4, rf_maps=(16,), rf_albedo=(16,), normal_residual=True))
    camera = Camera.orbit(10.0, 30.0, 32)
    mask = torch.zeros(1, 1, 32, 32)
    mask[..., 8:24, 6:26] = 1
    depth = (1.8 + 0.01 * torch.arange(32.0).reshape(1, 1, 1, 32) + 0.005 * torch.arange(32.0).reshape(1, 1, 32, 1)) * mask
    expected = normals_from_depth(depth, mask, camera)
    got = model.generate_normals(depth_to_net(depth, mask), [camera])
    inside = mask[0, 0] > 0
    assert torch.allclose(got[0][:, inside], expected[0][:, inside], atol=2e-3)
    assert (got[0][:, ~inside] == 0).all()


def test_the_albedo_baselines_are_what_they_say():
    from ngp_mi.eval.maps_eval import mean_colour, single_colour_l1

    mask = torch.zeros(2, 1, 4, 4)
    mask[:, :, 1:3, 1:3] = 1
    albedo = torch.zeros(2, 3, 4, 4)
    albedo[0, :, 1:3, 1:3] = 0.5  # one flat colour: the single colour is exact
    albedo[1, 0, 1:3, 1:3] = torch.tensor([[0.0, 1.0], [1.0, 1.0]])  # red 0 / 1: the median 1 is off by 1 on 1 of 4
    errors = single_colour_l1(albedo, mask)
    assert errors.shape == (8,) and float(errors[:4].max()) == 0 and float(errors[4:].sum()) == pytest.approx(1 / 3)
    torch.testing.assert_close(mean_colour(albedo, mask)[1], torch.tensor([0.75, 0.0, 0.0]))


def test_a_model_folder_is_evaluated_as_the_run_it_was_exported_from(trained, tmp_path):
    """`evaluate maps --run` takes a model folder (or a shipped name): the same networks, the same figures;
    a folder that is neither is refused by name."""
    from ngp_mi.cli import main
    from ngp_mi.models.pretrained import export_model

    run, data = trained
    folder = export_model(tmp_path / "model", run)
    from_run = evaluate_maps(run, data, tmp_path / "a", latent_samples=2)
    from_folder = evaluate_maps(folder, data, tmp_path / "b", latent_samples=2)
    assert from_folder.pop("checkpoint") == str(folder) and "ckpt-" in from_run.pop("checkpoint")
    assert from_folder == from_run
    with pytest.raises(ValueError, match="'nowhere': not a shipped model"):
        evaluate_maps("nowhere", data, tmp_path / "c")
    assert main(["evaluate", "maps", "--run", str(folder), "--data", str(data), "--out", str(tmp_path / "d")]) == 0
    assert (tmp_path / "d" / "eval.json").exists()
