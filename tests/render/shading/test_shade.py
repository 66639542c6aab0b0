"""R_diff / R_BP: backend agreement, gradcheck, repeated backward, extremes, and Mitsuba radiometry."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from helpers import BACKENDS, analytic_sphere, assert_backends_agree, random_inputs, shade_inputs

from ngp_mi.camera import Camera
from ngp_mi.lights import DirectionalLight, PointLight, overhead_rig
from ngp_mi.render.scene import build_scene, diffuse_bsdf, render
from ngp_mi.render.shading import CameraLights, shade


@pytest.mark.parametrize("mode", ["diffuse", "blinn_phong"])
@pytest.mark.parametrize("view", ["per_pixel", "constant"])
def test_backends_agree_in_value_and_gradient(mode, view):
    assert_backends_agree(mode, view, n=3, h=16, w=12)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode, view", [("blinn_phong", "per_pixel"), ("blinn_phong", "constant"),
                                        ("diffuse", "per_pixel")])
def test_gradcheck_float64(backend, mode, view):
    x, cams = random_inputs(n=2, h=3, w=4)
    names = list(x)
    x["mask"].requires_grad_(True)

    def f(*tensors):
        return shade_inputs(dict(zip(names, tensors)), cams, backend, mode, view)

    assert torch.autograd.gradcheck(f, tuple(x[k] for k in names), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("reduce", ["sum", "mean"])
def test_gradient_of_a_sum_or_mean_equals_the_dense_one(reduce):
    """Their upstream gradient is one broadcast value, which the Dr.Jit backward reads as such."""
    x, cams = random_inputs(n=2, h=4, w=5, dtype=torch.float32)
    out = shade_inputs(x, cams, "drjit")
    broadcast = torch.autograd.grad(getattr(out, reduce)(), list(x.values()), retain_graph=True, allow_unused=True)
    weight = torch.full_like(out, 1.0 if reduce == "sum" else 1.0 / out.numel())
    dense = torch.autograd.grad((out * weight).sum(), list(x.values()), allow_unused=True)
    for name, a, b in zip(x, broadcast, dense):
        assert (a is None) == (b is None), name
        if a is not None:
            torch.testing.assert_close(a, b, msg=name)
            assert a.abs().sum() > 0, name


@pytest.mark.parametrize("backend", BACKENDS)
def test_repeated_backward_over_one_graph(backend):
    """A second backward (retain_graph) must use the new upstream gradient, not the first one's."""
    x, cams = random_inputs(n=2, h=4, w=4)
    out = shade_inputs(x, cams, backend)
    w1, w2 = torch.rand_like(out), -3 * torch.rand_like(out)
    g1 = torch.autograd.grad((out * w1).sum(), [x["normal"], x["irradiance"]], retain_graph=True)
    g2 = torch.autograd.grad((out * w2).sum(), [x["normal"], x["irradiance"]], retain_graph=True)
    x_ref, _ = random_inputs(n=2, h=4, w=4)
    ref = shade_inputs(x_ref, cams, "torch")
    r2 = torch.autograd.grad((ref * w2).sum(), [x_ref["normal"], x_ref["irradiance"]])
    for a, b in zip(g2, r2):
        torch.testing.assert_close(a, b)
    assert not torch.allclose(g1[0], g2[0])


# ----------------------------------------------------------------------------- numerical extremes

def single_pixel(normal, light_dir, irradiance=1.0, alpha=4.0, mask=1.0, dtype=torch.float64):
    """One pixel, one camera-space directional light, constant view (0, 0, -1)."""
    t = lambda v, shape: torch.tensor(v, dtype=dtype).reshape(shape).requires_grad_(True)  # noqa: E731
    x = {
        "normal": t(normal, (1, 3, 1, 1)), "albedo": t([0.5, 0.5, 0.5], (1, 3, 1, 1)),
        "mask": t([mask], (1, 1, 1, 1)), "alpha": t([alpha], (1, 1, 1, 1)),
        "spec_albedo": t([1.0, 1.0, 1.0], (1, 3, 1, 1)),
        "directions": t(light_dir, (1, 1, 3)), "irradiance": t([irradiance] * 3, (1, 1, 3)),
    }
    return x


def shade_pixel(x, backend, mode="blinn_phong"):
    z = torch.zeros(1, 0, 3, dtype=x["normal"].dtype)
    lights = CameraLights(x["directions"], x["irradiance"], z, z)
    return shade(x["normal"], x["albedo"], x["mask"], lights, None, alpha=x["alpha"], spec_albedo=x["spec_albedo"],
                 k_d=0.8, k_s=0.2, mode=mode, view="constant", backend=backend)


V = [0.0, 0.0, -1.0]  # towards the viewer
EXTREMES = {
    # name: (normal, light direction, irradiance, alpha, mask, expected red value or None)
    "grazing light N.L=1e-7": ([0, 0, -1], [1, 0, -1e-7], 1.0, 4.0, 1.0, None),
    "light below surface N.L<0": ([0, 0, -1], [0, 0.6, 0.8], 1.0, 4.0, 1.0, 0.0),
    "N.H=0 with alpha 0.5": ([1, 0, 0], [0, 0, -1], 1.0, 0.5, 1.0, 0.0),
    "alpha 0, N.H>0": ([0, 0, -1], [0, 0, -1], 1.0, 0.0, 1.0, 0.8 * 0.5 + 0.2),
    "alpha 0, N.H=0 (0^0 := 0)": ([1, 0, 0], [0, 0, -1], 1.0, 0.0, 1.0, 0.0),
    "alpha 1e4 at N.H=1": ([0, 0, -1], [0, 0, -1], 1.0, 1e4, 1.0, 0.8 * 0.5 + 0.2),
    "alpha 1e4 off-peak": ([0, 0.3, -1], [0, 0, -1], 1.0, 1e4, 1.0, None),
    "zero-length normal": ([0, 0, 0], [0, 0, -1], 1.0, 4.0, 1.0, 0.0),
    "tiny normal 1e-30": ([0, 0, 1e-30], [0, 0, -1], 1.0, 4.0, 1.0, 0.0),
    "non-unit normal x7": ([0, 0, -7], [0, 0, -1], 1.0, 4.0, 1.0, 0.8 * 0.5 + 0.2),
    "light = -view": ([0, 0, -1], [0, 0, 1], 1.0, 4.0, 1.0, 0.0),
    "empty mask": ([0, 0, -1], [0, 0, -1], 1.0, 4.0, 0.0, 0.0),
    "irradiance 0": ([0, 0, -1], [0, 0, -1], 0.0, 4.0, 1.0, 0.0),
    "irradiance 1e6": ([0, 0, -1], [0, 0, -1], 1e6, 4.0, 1.0, 1e6 * (0.8 * 0.5 + 0.2)),
    "zero light direction": ([0, 0, -1], [0, 0, 0], 1.0, 4.0, 1.0, 0.0),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", list(EXTREMES))
def test_extremes_are_finite_with_documented_values(case, dtype, backend):
    normal, light, irradiance, alpha, mask, expected = EXTREMES[case]
    x = single_pixel(normal, light, irradiance, alpha, mask, dtype)
    out = shade_pixel(x, backend)
    out.sum().backward()
    assert torch.isfinite(out).all()
    for name, t in x.items():
        assert torch.isfinite(t.grad).all(), f"{name} gradient not finite: {t.grad}"
    if expected is not None:
        assert out[0, 0].item() == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_non_unit_normals_are_renormalised():
    x, cams = random_inputs(n=1, h=4, w=4, requires_grad=False)
    base = shade_inputs(x, cams, "drjit")
    x["normal"] = x["normal"] * 3.7
    torch.testing.assert_close(shade_inputs(x, cams, "drjit"), base)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_precision_inputs_compute_in_float32(half, backend):
    x, cams = random_inputs(n=1, h=4, w=4, dtype=torch.float32, requires_grad=False)
    for k in ("normal", "albedo", "alpha", "spec_albedo"):
        x[k] = x[k].to(half).requires_grad_(True)
    out = shade_inputs(x, cams, backend)
    assert out.dtype == torch.float32
    out.sum().backward()
    assert x["normal"].grad.dtype == half and torch.isfinite(x["normal"].grad.float()).all()
    ref = shade_inputs({k: v.detach().float() for k, v in x.items()}, cams, backend)
    torch.testing.assert_close(out, ref)


def test_bad_arguments_are_named():
    x, cams = random_inputs(n=1, h=4, w=4, requires_grad=False)
    with pytest.raises(ValueError, match="albedo must be"):
        shade(x["normal"], x["albedo"][:, :2], None, overhead_rig(), cams)
    with pytest.raises(ValueError, match="point lights need the depth"):
        shade(x["normal"], x["albedo"], None, [PointLight((0, 1, 0), 1.0)], cams)
    with pytest.raises(ValueError, match="mode must be one of"):
        shade(x["normal"], x["albedo"], None, overhead_rig(), cams, mode="phong")
    with pytest.raises(ValueError, match="camera is 4x4 but the maps are 5x4"):
        shade(torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5), None, overhead_rig(), cams)


# ----------------------------------------------------------------------------- independent checks

def test_blinn_phong_matches_a_direct_numpy_evaluation():
    """Eq. (1) evaluated per pixel in numpy, with world-space lights moved into camera space."""
    cam = Camera.orbit(12.0, -25.0, 6)
    g = np.random.default_rng(1)
    normal = g.normal(size=(3, 6, 6)) + np.array([0, 0, -2.0])[:, None, None]
    albedo = g.uniform(size=(3, 6, 6))
    lights = [DirectionalLight((0.2, 1.0, 0.3), (1.0, 0.5, 0.2)), DirectionalLight((-1.0, 0.5, 0.1), 0.7)]
    out = shade(torch.tensor(normal[None]), torch.tensor(albedo[None]), None, lights, cam,
                k_d=0.6, k_s=0.4, alpha=8.0).numpy()[0]
    expected = np.zeros((3, 6, 6))
    for j in range(6):
        for i in range(6):
            n = normal[:, j, i] / np.linalg.norm(normal[:, j, i])
            ray = np.array([(i + 0.5 - cam.cx) / cam.focal_px, (j + 0.5 - cam.cy) / cam.focal_px, 1.0])
            v = -ray / np.linalg.norm(ray)
            for light in lights:
                l_cam = cam.R @ np.array(light.direction)
                h = (l_cam + v) / np.linalg.norm(l_cam + v)
                specular = 0.4 * max(n @ h, 0) ** 8.0 if n @ l_cam > 0 else 0.0  # gated by N.L > 0
                term = 0.6 * max(n @ l_cam, 0) * albedo[:, j, i] + specular
                expected[:, j, i] += np.array(light.irradiance) * term
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-9)


def test_point_light_matches_inverse_square_law():
    cam = Camera.orbit(0.0, 0.0, 8)
    depth = torch.full((1, 1, 8, 8), 2.0, dtype=torch.float64)
    normal = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).reshape(1, 3, 1, 1).expand(1, 3, 8, 8)
    albedo = torch.ones(1, 3, 8, 8, dtype=torch.float64)
    light = PointLight((0.0, 0.0, 1.0), 3.0)  # world; the camera sits at z = 2 looking down -z
    out = shade(normal, albedo, None, [light], cam, depth=depth, k_d=1.0, mode="diffuse")
    # Pixel (3, 3) centre ray hits the plane z_cam = 2 at world (x, y, 0); distance to the light:
    ray = np.array([(3.5 - cam.cx) / cam.focal_px, (3.5 - cam.cy) / cam.focal_px, 1.0])
    p_world = cam.R.T @ (2.0 * ray - cam.t)
    d = np.array(light.position) - p_world
    r = np.linalg.norm(d)
    assert out[0, 0, 3, 3].item() == pytest.approx(3.0 * d[2] / r / r ** 2, rel=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_diffuse_shading_equals_mitsuba_direct_lighting(mi, backend):
    """On exact maps of a Lambertian sphere, R_diff(k_d=1) / π equals Mitsuba's direct lighting."""
    res, radius, albedo = 64, 0.5, (0.7, 0.5, 0.3)
    camera = Camera.orbit(15.0, 30.0, res)
    lights = [DirectionalLight((0.5, 0.8, 0.6), (1.0, 0.8, 0.6)), DirectionalLight((-0.7, 0.2, 0.4), 0.5)]
    # Mitsuba's direct integrator picks one emitter per sample; by linearity, render each light
    # alone (deterministic for a directional light) and sum.
    shapes = {"s": {"type": "sphere", "radius": radius, "bsdf": diffuse_bsdf(albedo)}}
    reference = sum(render(build_scene(camera, shapes, [light], integrator={"type": "direct"}, spp=64))
                    for light in lights)
    _, normal, hit = analytic_sphere(camera, radius)
    maps = lambda a: torch.tensor(np.ascontiguousarray(a), dtype=torch.float32)[None]  # noqa: E731
    ours = shade(maps(normal.transpose(2, 0, 1)), maps(np.broadcast_to(np.array(albedo)[:, None, None], (3, res, res))),
                 maps(hit[None].astype(np.float32)), lights, camera, k_d=1.0, mode="diffuse", backend=backend)
    ours = ours[0].numpy().transpose(1, 2, 0) / math.pi
    # Compare interior pixels (pixel-averaged reference vs pixel-centre maps differ at the silhouette).
    shifted = [np.roll(hit, s, a) for s in (1, -1) for a in (0, 1)]
    interior = hit & np.logical_and.reduce(shifted)
    background = ~hit & ~np.logical_or.reduce(shifted)
    err = np.abs(ours[interior] - reference[interior])
    assert interior.sum() > 500
    assert np.median(err) < 2e-4 and err.max() < 5e-3, (np.median(err), err.max())
    assert reference[background].max() == 0.0 and ours[background].max() == 0.0


def test_shared_lights_gradients_agree():
    """One camera-space light set for the whole batch (B = 1) with gradients, both backends."""
    grads = {}
    for backend in BACKENDS:
        x, _ = random_inputs(n=3, h=6, w=5, requires_grad=False)
        lights = CameraLights(x["directions"][:1].clone().requires_grad_(), x["irradiance"][:1].clone().requires_grad_(),
                              x["positions"][:1].clone().requires_grad_(), x["intensity"][:1].clone().requires_grad_())
        out = shade(x["normal"], x["albedo"], None, lights, None, depth=x["depth"], backend=backend)
        (out * torch.linspace(0, 1, out.numel(), dtype=out.dtype).reshape(out.shape)).sum().backward()
        grads[backend] = [t.grad for t in (lights.directions, lights.irradiance, lights.positions, lights.intensity)]
    for a, b in zip(grads["drjit"], grads["torch"]):
        assert a.shape == b.shape == (1, a.shape[1], 3)
        torch.testing.assert_close(a, b)




def test_cameras_with_other_intrinsics_in_one_batch():
    """Two focal lengths and principal points in one call: Dr.Jit reads one intrinsics row per image."""
    x, _ = random_inputs(n=2, h=5, w=8)
    zoomed = dataclasses.replace(Camera.orbit(10.0, 15.0, (8, 5)), focal_px=21.0, cx=3.5, cy=2.0)
    cams = [Camera.orbit(0.0, 0.0, (8, 5)), zoomed]
    values = {}
    for backend in BACKENDS:
        for t in x.values():
            t.grad = None
        out = shade_inputs(x, cams, backend)
        (out * torch.linspace(-1, 2, out.numel(), dtype=out.dtype).reshape(out.shape)).sum().backward()
        values[backend] = (out.detach(), {k: v.grad.clone() for k, v in x.items()})
    torch.testing.assert_close(values["drjit"][0], values["torch"][0])
    for name, g in values["torch"][1].items():
        torch.testing.assert_close(values["drjit"][1][name], g, msg=name)
    same = shade_inputs({k: v.detach() for k, v in x.items()}, [cams[0], cams[0]], "drjit")
    assert not torch.allclose(same[1], values["drjit"][0][1])  # the second image did use its own intrinsics


def test_empty_light_fields_that_require_grad():
    """No point lights, every CameraLights field requiring grad: the empty ones get no gradient."""
    cams = [Camera.orbit(10.0, 20.0 * i, 8) for i in range(2)]
    g = torch.Generator().manual_seed(3)
    normal = (torch.randn(2, 3, 8, 8, generator=g) - torch.tensor([0, 0, 1.5])[:, None, None]).requires_grad_()
    albedo = torch.rand(2, 3, 8, 8, generator=g)
    grads = {}
    for backend in BACKENDS:
        lights = CameraLights.from_lights(overhead_rig(), cams)
        for t in (lights.directions, lights.irradiance, lights.positions, lights.intensity):
            t.requires_grad_()
        shade(normal, albedo, None, lights, cams, backend=backend).sum().backward()
        grads[backend] = (lights.directions.grad, lights.irradiance.grad, lights.positions.grad, normal.grad.clone())
        normal.grad = None
    for a, b in zip(grads["drjit"][:2] + grads["drjit"][3:], grads["torch"][:2] + grads["torch"][3:]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert grads["drjit"][2] is None or not grads["drjit"][2].any()


TIES = {  # exact ties of max(x, 0): the gradient that flows is 0 in both backends
    "zero normal": dict(normal=[0.0, 0.0, 0.0], light_dir=[0.0, 0.0, -1.0]),
    "zero light direction": dict(normal=[0.0, 0.0, -1.0], light_dir=[0.0, 0.0, 0.0]),
    "N.L = 0 exactly": dict(normal=[0.0, 0.0, -1.0], light_dir=[1.0, 0.0, 0.0]),
}


@pytest.mark.parametrize("case", list(TIES))
def test_ties_have_the_same_gradient_in_both_backends(case):
    grads = {}
    for backend in BACKENDS:
        x = single_pixel(**TIES[case])
        out = shade_pixel(x, backend)
        out.sum().backward()
        grads[backend] = {k: v.grad for k, v in x.items() if v.grad is not None}
        assert all(torch.isfinite(g).all() for g in grads[backend].values())
    for name, g in grads["torch"].items():
        torch.testing.assert_close(grads["drjit"][name], g, msg=name)


@pytest.mark.parametrize("where", ["at the surface point", "at the camera over the background"])
def test_a_point_light_on_the_shaded_point_has_the_same_gradient_in_both_backends(where):
    cam = Camera.orbit(0.0, 0.0, 4)
    depth = torch.full((1, 1, 4, 4), 2.0 if where == "at the surface point" else 0.0, dtype=torch.float64)
    position = [0.25, 0.25, 2.0] if where == "at the surface point" else [0.0, 0.0, 0.0]  # camera space
    grads = {}
    for backend in BACKENDS:
        normal = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).reshape(1, 3, 1, 1).repeat(1, 1, 4, 4)
        normal.requires_grad_()
        lights = CameraLights(torch.zeros(1, 0, 3, dtype=torch.float64), torch.zeros(1, 0, 3, dtype=torch.float64),
                              torch.tensor([[position]], dtype=torch.float64, requires_grad=True),
                              torch.ones(1, 1, 3, dtype=torch.float64, requires_grad=True))
        out = shade(normal, torch.ones_like(normal), None, lights, cam, depth=depth, backend=backend)
        out.sum().backward()
        grads[backend] = (normal.grad, lights.positions.grad, lights.intensity.grad)
        assert torch.isfinite(out).all() and all(torch.isfinite(g).all() for g in grads[backend])
    for a, b in zip(*grads.values()):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6 * max(1.0, b.abs().max().item()))
