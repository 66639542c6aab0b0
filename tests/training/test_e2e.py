"""ngp-mi train e2e: L_2D reaches G_shape's decoder through Π_v (and not with the link off), outputs,
exact resume, and two processes with gloo."""

import copy
import json
from pathlib import Path

import pytest
import torch
from helpers import ROOT, run_torchrun

from ngp_mi.models.shape import ShapeModel, occupancy_loss
from ngp_mi.training.e2e import E2ETrain, ShapeAnchor, shape_depth_batch, train_e2e
from ngp_mi.training.shape import run_shape_data


def e2e_recipe(tmp_path: Path, runs, name: str, **train) -> Path:
    """train/e2e_tiny.toml from the tiny runs, its real maps those of the tiny maps run (no rendering)."""
    maps_run, shape_run = runs
    text = (ROOT / "train" / "e2e_tiny.toml").read_text()
    text = text.replace('"outputs/train/maps_tiny"', f'"{maps_run}"').replace('"outputs/train/shape_tiny"',
                                                                               f'"{shape_run}"')
    text = text.replace('"outputs/data/maps_tiny"', f'"{Path(maps_run).parent / "data"}"')
    text = text.replace('"outputs/train/e2e_tiny"', f'"{tmp_path / name}"')
    for key, value in train.items():
        if f"\n{key} = " in text:
            text = text.replace(f"\n{key} = ", f"\n{key} = {value}\n# ", 1)
        else:
            text = text.replace("\n[train]\n", f"\n[train]\n{key} = {value}\n", 1)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def decoder(run) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in ShapeModel.from_run(run).decoder.state_dict().items()}


def test_the_depth_of_a_shape_batch_is_differentiable_in_the_decoder_only_with_the_link(runs):
    shape = ShapeModel.from_run(runs[1])
    train = E2ETrain(iterations=1, batch_size=2, extract_resolution=24, spp=2)
    for link in (True, False):
        shape.decoder.zero_grad(set_to_none=True)
        batch, empty = shape_depth_batch(shape, 2, 32, seed=3, link=link, train=train)
        assert batch["depth"].shape == batch["mask"].shape == (2, 1, 32, 32) and batch["K"].shape == (2, 3, 3)
        assert float(batch["mask"].detach().sum()) > 0 and empty >= 0 and torch.isfinite(batch["depth"]).all()
        assert batch["depth"].requires_grad == link
        if link:
            (batch["depth"] * batch["mask"].detach()).sum().backward()
            grads = [p.grad for p in shape.decoder.parameters()]
            assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.abs().sum() > 0 for g in grads)


def test_the_decoder_moves_with_the_link_and_stays_without_it(runs, tmp_path):
    before = decoder(runs[1])
    linked = train_e2e(e2e_recipe(tmp_path, runs, "linked", device='"cpu"'), log=lambda *_: None)
    control = train_e2e(e2e_recipe(tmp_path, runs, "control", link="false", device='"cpu"'), log=lambda *_: None)
    moved, kept = decoder(linked / "shape"), decoder(control / "shape")
    assert any(not torch.equal(moved[k], before[k]) for k in before)
    assert all(torch.equal(kept[k], before[k]) for k in before)
    records = [json.loads(line) for line in (linked / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3, 4]
    assert all(r["G"] > 0 and r["D"] > 0 and r["skipped_decoder_steps"] == 0 for r in records)
    assert (linked / "images" / "step-00000004.png").exists()
    from ngp_mi.pipeline import NGP  # the run is a maps run and a shape run for the rest of the tools

    ngp = NGP(linked, linked / "shape")
    assert ngp.shape_model is not None and ngp.maps is not None

    # killed after step 2 and resumed: the same weights as straight through
    train_e2e(e2e_recipe(tmp_path, runs, "resumed", iterations=2, device='"cpu"'), log=lambda *_: None)
    messages = []
    resumed = train_e2e(e2e_recipe(tmp_path, runs, "resumed", device='"cpu"'), log=messages.append)
    assert any("resuming from" in m and "(step 2)" in m for m in messages)
    again = decoder(resumed / "shape")
    # Π_v's silhouette gradients sum with Dr.Jit's atomic scatter-adds, whose order varies between
    # runs, and Adam turns rounding-sized gradient differences of near-idle weights into visible
    # ones: up to 1.2 % of what the steps moved in repeated runs here, so the bound is 3 % (a resume
    # that lost or repeated a step would differ by a whole step: about a quarter of it)
    moved_by = max(float((moved[k] - before[k]).abs().max()) for k in moved)
    assert max(float((again[k] - moved[k]).abs().max()) for k in moved) < 3e-2 * moved_by


def test_the_anchor_adds_the_weighted_occupancy_gradient_of_the_priors_training_shapes(runs):
    shape = ShapeModel.from_run(runs[1])
    recipe, train_shapes, held = run_shape_data(runs[1])
    anchor = ShapeAnchor(runs[1], weight=3.0, batch=2, seed=0, rank=0, world=1, device=torch.device("cpu"))
    assert len(anchor.data) == len(train_shapes) and anchor.resolution == recipe.train.stages[-1][0]
    assert held is None or not set(held.ids) & set(anchor.data.ids)  # never the held-out shapes
    shape.zero_grad(set_to_none=True)
    torch.manual_seed(7)  # the points' subset comes from the global generator, as in `train shape`
    loss = anchor.backward(shape, step=5)
    assert loss > 0 and all(p.grad is None for p in shape.encoder.parameters())  # the encoder stays fixed
    gradient = {name: p.grad.clone() for name, p in shape.decoder.named_parameters()}
    assert any(g.abs().sum() > 0 for g in gradient.values())

    # an independent check: the directional finite difference of 3 · L_occ on the same batch
    from ngp_mi.training.shape import ae_batch

    torch.manual_seed(7)
    voxels, points, occ = ae_batch(anchor.data, anchor.batches, anchor.resolution, 5, anchor.points, torch.device("cpu"))
    # in float64 (a copy of the decoder), so the difference quotient is not rounding
    decoder64 = copy.deepcopy(shape.decoder).double()
    codes, points, occ = shape.encoder(voxels).detach().double(), points.double(), occ.double()
    parameters = dict(decoder64.named_parameters())
    direction = {name: torch.randn(p.shape, generator=torch.Generator().manual_seed(i), dtype=torch.float64)
                 for i, (name, p) in enumerate(parameters.items())}

    def weighted(t: float) -> float:
        with torch.no_grad():
            for name, p in parameters.items():
                p.add_(t * direction[name])
            value = 3.0 * occupancy_loss(decoder64(points, codes), occ).item()
            for name, p in parameters.items():
                p.sub_(t * direction[name])
        return value

    # the decoder is piecewise linear (leaky ReLUs, IM-NET's leaky clamp): a step of 1e-5 crossed enough
    # kinks to move the quotient 2 % off on a prior trained at one thread; in float64 the step can be
    # 100x smaller, and both thread counts then agree within 0.1 %
    h = 1e-7
    numeric = (weighted(h) - weighted(-h)) / (2 * h)
    analytic = sum(float((gradient[name].double() * direction[name]).sum()) for name in parameters)
    assert numeric == pytest.approx(analytic, rel=5e-3, abs=1e-6)


def test_an_anchored_run_logs_its_term_and_a_control_has_none(runs, tmp_path):
    anchored = train_e2e(e2e_recipe(tmp_path, runs, "anchored", iterations=2, shape_anchor=1.0, device='"cpu"'),
                         log=lambda *_: None)
    control = train_e2e(e2e_recipe(tmp_path, runs, "control", iterations=1, shape_anchor=1.0, link="false",
                                   device='"cpu"'), log=lambda *_: None)
    records = [json.loads(line) for line in (anchored / "log.jsonl").read_text().splitlines()]
    assert all(r["anchor_occupancy"] > 0 and r["skipped_decoder_steps"] == 0 for r in records)
    assert all("anchor_occupancy" not in json.loads(line) for line in (control / "log.jsonl").read_text().splitlines())


def test_a_shape_run_without_its_recipe_or_data_is_named(runs, tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path}.*not a `train shape` run"):
        run_shape_data(tmp_path)
    recipe = json.loads((Path(runs[1]) / "recipe.json").read_text())
    recipe["tables"]["data"]["cache_dir"] = str(tmp_path / "gone")
    (tmp_path / "moved").mkdir()
    (tmp_path / "moved" / "recipe.json").write_text(json.dumps(recipe))
    with pytest.raises(ValueError, match="gone.*missing"):
        run_shape_data(tmp_path / "moved")


def test_a_run_that_does_not_exist_is_named(runs, tmp_path):
    with pytest.raises(ValueError, match="no readable checkpoint|no checkpoint|does not exist|not a directory"):
        train_e2e(e2e_recipe(tmp_path, (tmp_path / "none", runs[1]), "bad"), log=lambda *_: None)


def test_two_processes_with_gloo_stay_in_sync(runs, tmp_path):
    cfg = e2e_recipe(tmp_path, runs, "ddp", iterations=2, device='"cpu"')
    done = run_torchrun("e2e", cfg, 29519)
    assert done.returncode == 0, done.stderr[-2000:]
    records = [json.loads(line) for line in (tmp_path / "ddp" / "log.jsonl").read_text().splitlines()]
    assert records[-1] == {"step": 2, "world": 2, "ranks_in_sync": True}


def test_a_maps_run_with_the_coarse_normal_cycle_trains_end_to_end(runs, tmp_path):
    """A maps run trained with normal_cycle_depth = "coarse" keeps its real maps paired with their
    reconstructions under train e2e ([data] coarse_shapes); without coarse_shapes it fails by name."""
    from helpers import maps_recipe

    from ngp_mi.training.maps import train_maps

    coarse = ['model.normal_cycle_depth="coarse"', 'data.coarse_shapes="chair"', "data.coarse_resolution=32"]
    maps_run = train_maps(maps_recipe(tmp_path, "maps", iterations=2), log=lambda *_: None,
                          overrides=coarse)
    recipe = e2e_recipe(tmp_path, (maps_run, runs[1]), "e2e", iterations=2, device='"cpu"')
    with pytest.raises(ValueError, match=r"normal_cycle_depth = 'coarse' .* set \[data\] coarse_shapes"):
        train_e2e(recipe, log=lambda *_: None)
    recipe.write_text(recipe.read_text().replace("\n[data]", '\n[data]\ncoarse_shapes = "chair"\ncoarse_resolution = 32', 1))
    out = train_e2e(recipe, log=lambda *_: None)
    steps = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert steps[-1]["step"] == 2 and all(torch.isfinite(torch.tensor(s["cyc_n"])) for s in steps)
