import math

import pytest
import torch

from ngp_mi.camera import Camera
from ngp_mi.eval.maps_eval import angular_error_deg, evaluate_maps, smooth_depth
from ngp_mi.render.maps import normals_from_depth


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
    from test_train_maps import config

    from ngp_mi.train_maps import train_maps

    tmp = tmp_path_factory.mktemp("eval")
    return train_maps(config(tmp, "run", iterations=3), log=lambda *_: None), tmp / "data"


def test_evaluation_runs_and_reports_both_normal_methods(trained, tmp_path):
    run, data = trained
    result = evaluate_maps(run, data, tmp_path, coarse_sigma=1.5, latent_samples=3)
    errors = result["normal_error_deg"]
    for method in ("G_n", "from_coarse_depth"):
        assert 0 <= errors[method]["median"] <= 180 and math.isfinite(errors[method]["mean"])
    assert result["albedo_reconstruction_l1"] > 0 and result["albedo_diversity_l1"] >= 0
    assert (tmp_path / "eval.md").read_text().count("|") > 10 and (tmp_path / "eval.png").exists()
    # Smoothing removes detail: the baseline from the sharp depth is better. (At 32 px the parts are
    # a few pixels wide, so even the sharp depth's finite differences are off by ~20 deg; 0.01 deg at 128 px.)
    sharp = evaluate_maps(run, data, tmp_path / "sharp", coarse_sigma=0.0)
    assert sharp["normal_error_deg"]["from_coarse_depth"]["median"] < errors["from_coarse_depth"]["median"]
