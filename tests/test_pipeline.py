"""NGP inference (ngp_mi/pipeline.py): the variants' algebra and `ngp-mi generate` end to end."""

import dataclasses
import math

import pytest
import torch
import trimesh

from ngp_mi.camera import Camera
from ngp_mi.lights import DirectionalLight, PointLight, overhead_rig
from ngp_mi.models.maps import MapsConfig, MapsModel
from ngp_mi.models.specular import SpecularConfig, SpecularModel
from ngp_mi.pipeline import NGP, STAGES, NGPScene, at_training_distance, ngp_image, shade_maps
from ngp_mi.render.depth import project_depth
from ngp_mi.render.shading import PAPER_CONSTANTS, CameraLights, Constants, shade
from ngp_mi.training.loop import save


@pytest.fixture
def box_view(box_obj):
    return box_obj


@pytest.fixture
def ngp_and_box(runs, box_obj):
    from ngp_mi.geometry.loaders import load_mesh

    return NGP(runs[0]), load_mesh(box_obj)


def test_variants_compose_as_the_paper_says(ngp_and_box):
    ngp, mesh = ngp_and_box
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
    # a G_sp^real that reads the highlight (issue 15) gets R_BP's specular term with the car's k_s
    lit = SpecularModel(SpecularConfig(ngf=8, blocks=1, ndf=8, rf_image=(16,), highlight_input=True)).eval()
    highlight = shade(n, torch.zeros_like(a), m, CameraLights.from_lights(lights, [camera]), [camera], k_d=0.0,
                      k_s=0.4, alpha=4.0)[:, :1]
    assert highlight.max() > 0
    torch.testing.assert_close(ngp_image(maps, lit, *args, variant="ngp")["specular"],
                               lit.specular(n, base, m, highlight))
    # a signed G_sp^real (issue 15) may darken; NGP's image stays radiance, never negative
    signed = SpecularModel(SpecularConfig(ngf=8, blocks=1, ndf=8, rf_image=(16,), blend="signed")).eval()
    dark = ngp_image(maps, signed, *args, variant="ngp")
    assert (dark["specular"] < 0).any() and (dark["image"] >= 0).all()
    torch.testing.assert_close(dark["image"], (no_sp["image"] + dark["specular"]).clamp_min(0))


def test_k_diff_shades_r_diff_alone_and_leaves_r_bp_at_its_split(tmp_path):
    """[model] k_diff: NGP's R_diff, the training's diffuse images and G_sp^real's input use it; NGP-BP
    keeps R_BP's k_d / k_s; a negative one is refused; the viewer's R_BP sliders keep it."""
    with pytest.raises(ValueError, match="k_diff"):
        MapsConfig(k_diff=-0.5)
    torch.manual_seed(2)
    config = MapsConfig(ngf=8, blocks=1, nef=8, ndf=8, rf_maps=(16, 34), rf_albedo=(16,), k_diff=1.0)
    save(tmp_path / "run", 1, [MapsModel(config), SpecularModel(SpecularConfig(ngf=8, blocks=1, ndf=8, rf_image=(16,)))],
         {})
    maps, specular = MapsModel.from_run(tmp_path / "run"), SpecularModel.from_run(tmp_path / "run")
    assert maps.config.constants == Constants(0.8, 0.2, 4.0, 1.0) and maps.config.constants.diffuse_k_d == 1.0
    assert Constants(0.8, 0.2, 4.0).diffuse_k_d == 0.8  # the paper's: R_diff is R_BP's diffuse term
    camera = Camera.orbit(10.0, 30.0, 32)
    box = trimesh.creation.box(extents=(0.6, 0.5, 0.4))
    projected = project_depth(torch.as_tensor(box.vertices, dtype=torch.float32), box.faces, camera)
    lights = overhead_rig()
    args = (projected.depth, projected.mask, camera, box.bounds, torch.zeros(1, maps.config.latent_dim), lights)
    no_sp, bp, full = (ngp_image(maps, specular, *args, variant=v) for v in ("no_sp", "ngp_bp", "ngp"))
    n, a, m = no_sp["normal"], no_sp["albedo"], projected.mask
    torch.testing.assert_close(no_sp["image"], shade(n, a, m, lights, camera, mode="diffuse", k_d=1.0) / math.pi)
    torch.testing.assert_close(bp["image"], shade(n, a, m, lights, camera, k_d=0.8, k_s=0.2, alpha=4.0) / math.pi)
    base = shade(n, a, m, CameraLights.from_lights(lights, [camera]), [camera], k_d=1.0, mode="diffuse")
    torch.testing.assert_close(maps.render_diffuse(n, a, m, [camera]), base)
    torch.testing.assert_close(full["specular"], specular.specular(n, 2 * base - 1, m))


# ----------------------------------------------------------------------------- NGPScene: handles and stage caching

def _runs_of(scene):
    return dict(scene.stage_runs)


def _delta(before, scene):
    return {k: v - before[k] for k, v in scene.stage_runs.items() if v != before[k]}


def test_each_handle_re_runs_only_its_stages(runs, box_view):
    maps_run, shape_run = runs
    scene = NGPScene(NGP(maps_run, shape_run), resolution=32).set_shape(mesh=box_view)
    first = scene.render()["image"]
    assert _runs_of(scene) == {stage: 1 for stage in STAGES}
    before = _runs_of(scene)
    assert torch.equal(scene.render()["image"], first) and _delta(before, scene) == {}  # nothing changed, nothing runs
    scene.set_camera(theta=10.0, phi=-30.0).set_lights(overhead_rig()).set_shape(mesh=scene._shape[1]).render()
    assert _delta(before, scene) == {}  # the values it had: not a change
    scene.set_lights([DirectionalLight((0.3, 1.0, 0.5), (2.0, 1.5, 1.0)), PointLight((0.0, 1.0, 1.5), (4.0, 4.0, 4.0))])
    changed = scene.render()["image"]
    assert _delta(before, scene) == {"shade": 1, "blend": 1} and not torch.equal(changed, first)
    before = _runs_of(scene)
    scene.set_appearance(seed=5).render()
    assert _delta(before, scene) == {"albedo": 1, "specular": 1, "shade": 1, "blend": 1}
    before = _runs_of(scene)
    scene.set_camera(theta=15, phi=40).render()
    assert _delta(before, scene) == {stage: 1 for stage in STAGES if stage != "extract"}
    before = _runs_of(scene)
    scene.set_variant("ngp_bp").render()
    assert _delta(before, scene) == {"shade": 1, "blend": 1}  # R_BP instead of R_diff; no G_sp^real
    before = _runs_of(scene)
    scene.set_constants(Constants(0.6, 0.4, 8.0)).render()
    assert _delta(before, scene) == {"shade": 1, "blend": 1}
    before = _runs_of(scene)
    for seed in range(8):  # a latent of the tiny shape prior that gives a non-empty shape
        try:
            scene.set_shape(seed=seed).render()
            break
        except ValueError:
            continue
    assert _delta(before, scene)["extract"] >= 1 and _delta(before, scene)["blend"] == 1


def test_the_scene_renders_what_ngp_image_renders(ngp_and_box):
    ngp, mesh = ngp_and_box
    camera = Camera.orbit(12.0, 25.0, 32)
    z = ngp.appearance(seed=2)
    lights = [DirectionalLight((0.0, 1.0, 1.0), (1.5, 1.5, 1.5))]
    for variant in ("ngp", "ngp_bp", "no_gn", "no_gda"):
        scene = NGPScene(ngp, 32, variant).set_shape(mesh=mesh).set_camera(camera).set_appearance(z[0]).set_lights(lights)
        got = scene.render(maps=True)
        want = ngp.render(mesh, camera, z, lights, variant)
        for name in ("image", "normal", "albedo", "depth", "mask"):
            assert torch.allclose(got[name], want[name], atol=1e-6), (variant, name)


def test_camera_distance_and_focal_length_keep_the_networks_in_their_depth_range(runs, box_view):
    maps_run, _ = runs
    scene = NGPScene(NGP(maps_run), resolution=32).set_shape(mesh=box_view)
    near = scene.render(maps=True)
    far_mask = scene.set_camera(theta=10, phi=-30, distance=3.0).render(maps=True)["mask"]
    assert far_mask.sum() < 0.6 * near["mask"].sum()  # farther: smaller
    zoomed = scene.set_camera(theta=10, phi=-30, distance=3.0, focal_mm=75.0).render(maps=True)
    assert abs(float(zoomed["mask"].sum() - near["mask"].sum())) < 0.1 * float(near["mask"].sum())  # 75 mm at 3 = 50 at 2
    # what G_n reads from the far camera is the depth range of the training distance
    depth, mask = zoomed["depth"], zoomed["mask"]
    moved = at_training_distance(depth, mask, scene.camera)
    assert abs(float(moved[mask > 0].mean()) - float(near["depth"][near["mask"] > 0].mean())) < 0.05
    assert torch.equal(moved[mask == 0], depth[mask == 0])


def test_appearance_by_exemplar_interpolation_and_direct_editing(runs, box_view):
    maps_run, _ = runs
    ngp = NGP(maps_run)
    scene = NGPScene(ngp, resolution=32, variant="ngp_bp").set_shape(mesh=box_view)
    a = scene.set_appearance(seed=1).render(maps=True)
    assert torch.allclose(scene.interpolate_appearance(1, 2, 0.0).render()["image"], a["image"], atol=1e-6)
    exemplar = torch.full((1, 3, 32, 32), 0.7)
    with torch.no_grad():
        mu = ngp.maps.E_da(2 * exemplar - 1)[0]
    b = scene.set_appearance(exemplar=exemplar).render(maps=True)
    c = scene.set_appearance(mu[0]).render(maps=True)
    assert torch.allclose(b["albedo"], c["albedo"])
    edited = torch.zeros(1, 3, 32, 32)
    edited[:, 0] = 0.9  # paint the object red
    d = scene.set_appearance(albedo=edited).set_constants(Constants(0.8, 0.0, 4.0)).render(maps=True)
    assert torch.equal(d["albedo"], edited * d["mask"])
    expected = shade_maps(d["normal"], edited * d["mask"], d["mask"], d["depth"], scene.camera, scene.lights, "ngp_bp",
                          scene.constants)
    assert torch.allclose(d["image"], expected) and d["image"][:, 1:].max() == 0  # only red off a red albedo without k_s
    with pytest.raises(ValueError, match="exactly one of"):
        scene.set_appearance(seed=1, z_da=mu[0])
    with pytest.raises(ValueError, match=r"albedo must be \(1, 3, 32, 32\)"):
        scene.set_appearance(albedo=torch.zeros(1, 3, 16, 16))


def test_fit_appearance_starts_at_the_encoder_and_lowers_the_exemplar_error(ngp_and_box):
    """fit_appearance: 0 steps is μ(E_da(exemplar)); steps on the L1 to an exemplar that G_da itself painted
    from another z_da bring G_da's albedo closer to it, and leave G_da's weights alone."""
    from ngp_mi.pipeline import fit_appearance, generate_albedo, generate_normals

    ngp, mesh = ngp_and_box
    camera = Camera.orbit(15.0, 30.0, 32)
    view = ngp.render(mesh, camera, ngp.appearance(seed=5), overhead_rig(), "no_sp")
    depth, mask = view["depth"], view["mask"]
    exemplar = view["albedo"].detach()
    with torch.no_grad():
        mu = ngp.maps.E_da(2 * exemplar - 1)[0]
    weights = {k: v.clone() for k, v in ngp.maps.G_da.state_dict().items()}
    assert torch.equal(fit_appearance(ngp.maps, exemplar, depth, mask, camera, mesh.bounds, 0), mu)

    def error(z_da):
        with torch.no_grad():
            normal = generate_normals(ngp.maps, depth, mask, camera)
            albedo = generate_albedo(ngp.maps, depth, mask, camera, mesh.bounds, normal, z_da)
        return float(((albedo - exemplar).abs() * mask).sum() / (3 * mask.sum()))

    fitted = fit_appearance(ngp.maps, exemplar, depth, mask, camera, mesh.bounds, 40)
    assert not fitted.requires_grad and fitted.shape == mu.shape
    assert error(fitted) < error(mu)
    assert all(torch.equal(v, ngp.maps.G_da.state_dict()[k]) for k, v in weights.items())

    # the scene's handle: an exemplar seen on its own geometry gives the fitted code, and sets what G_da paints
    from ngp_mi.pipeline import ExemplarView

    exemplar_view = ExemplarView(exemplar, depth, mask, camera, mesh.bounds)
    assert torch.equal(ngp.appearance(view=exemplar_view, fit_steps=40), fitted)
    scene = NGPScene(ngp, resolution=32, variant="no_sp").set_shape(mesh=mesh).set_camera(camera=camera)
    shown = scene.set_appearance(exemplar_view=exemplar_view, fit_steps=40).render(maps=True)["albedo"]
    assert abs(float(((shown - exemplar).abs() * mask).sum() / (3 * mask.sum())) - error(fitted)) < 1e-5
    with pytest.raises(ValueError, match=r"depth must be \(1, 1, 32, 32\)"):
        ExemplarView(exemplar, depth[..., :16], mask, camera, mesh.bounds)
    with pytest.raises(ValueError, match="no object pixel"):
        ExemplarView(exemplar, depth, torch.zeros_like(mask), camera, mesh.bounds)
