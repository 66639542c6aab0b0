"""Π_v: depth / normal / NOC maps against independent computations, and their gradients."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import compiled_kernels, rss_mib, trimesh_depth

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.geometry.primitives import box, simple_chair
from ngp_mi.render.depth import project_depth, supersampled_depth_coverage


def test_box_front_face_is_exact():
    mesh = box((0.0, 0.0, 0.0), (0.6, 0.6, 0.6))
    cam = Camera.orbit(0.0, 0.0, 32)
    out = project_depth(torch.tensor(mesh.vertices), mesh.faces, cam)
    hit = out.mask[0, 0] > 0
    uv, _ = cam.project(np.array([[-0.3, 0.3, 0.3], [0.3, -0.3, 0.3]]))
    inside = np.zeros((32, 32), bool)
    inside[int(np.ceil(uv[0, 1] - 0.5)):int(np.floor(uv[1, 1] - 0.5)) + 1,
           int(np.ceil(uv[0, 0] - 0.5)):int(np.floor(uv[1, 0] - 0.5)) + 1] = True
    assert torch.equal(hit, torch.tensor(inside))  # pixel centres inside the projected face
    torch.testing.assert_close(out.depth[0, 0][hit], torch.full((int(hit.sum()),), 1.7), atol=1e-6, rtol=0)
    torch.testing.assert_close(out.normal[0, :, hit].T, torch.tensor([[0.0, 0.0, -1.0]]).expand(int(hit.sum()), 3))
    assert out.depth[0, 0][~hit].abs().max() == 0 and out.noc[0][:, ~hit].abs().max() == 0
    noc = out.noc[0][:, hit]
    torch.testing.assert_close(noc[2], torch.ones_like(noc[2]))  # front face: z = max
    assert noc[0].min() < 0.1 and noc[0].max() > 0.9  # x spans the box


def test_depth_agrees_with_trimesh_ray_casting():
    """An independent ray cast (trimesh, not Mitsuba) of the chair from an oblique view."""
    mesh = simple_chair()
    cam = Camera.orbit(17.0, -35.0, 40)
    out = project_depth(torch.tensor(mesh.vertices), mesh.faces, cam)
    z_ref = trimesh_depth(mesh, cam)
    ours = out.depth[0, 0].numpy()
    both = (z_ref > 0) & (ours > 0)
    assert both.sum() > 200
    assert (both == (z_ref > 0)).mean() > 0.99  # same silhouette up to edge pixels
    np.testing.assert_allclose(ours[both], z_ref[both], atol=2e-5)


def test_interior_per_pixel_derivative_matches_finite_differences():
    mesh = box((0.0, 0.0, 0.0), (0.6, 0.5, 0.4))
    cam = Camera.orbit(20.0, 35.0, 24)
    v0 = torch.tensor(mesh.vertices, dtype=torch.float64)
    vertex, axis, h = 7, 2, 1e-3  # the corner nearest the camera, moved in z: tilts the +x and +y faces
    ad = torch.zeros(24, 24, dtype=torch.float64)
    v = v0.clone().requires_grad_()
    out = project_depth(v, mesh.faces, cam)
    for p in range(24 * 24):
        (g,) = torch.autograd.grad(out.depth.reshape(-1)[p], v, retain_graph=True)
        ad.view(-1)[p] = g[vertex, axis]
    shift = torch.zeros_like(v0)
    shift[vertex, axis] = h
    fd = (project_depth(v0 + shift, mesh.faces, cam).depth - project_depth(v0 - shift, mesh.faces, cam).depth)[0, 0] / (2 * h)
    mask = out.mask[0, 0].bool()
    interior = mask & F.max_pool2d((~mask).float()[None, None], 3, 1, 1)[0, 0].eq(0)
    assert (ad[interior].abs() > 1e-3).sum() > 20  # the moved corner influences many pixels
    torch.testing.assert_close(ad[interior], fd[interior].double(), atol=2e-3, rtol=1e-3)
    assert ad[~mask].abs().max() == 0


# ----------------------------------------------------------------------------- silhouettes

RES, SUPER, PHASES = 24, 96, 8


def _supersampled(vertices, faces, cam, phase=(0.0, 0.0)):
    return supersampled_depth_coverage(vertices, faces, cam, SUPER, phase)


def _finite_difference(move, faces, cam, w, h):
    """Central difference of the loss, averaged over PHASES random grid phases (seed 0)."""
    rng = np.random.default_rng(0)
    fds = []
    for _ in range(PHASES):
        phase = rng.uniform(-0.5, 0.5, 2)
        fds.append((_loss(*_supersampled(move(h), faces, cam, phase), w)
                    - _loss(*_supersampled(move(-h), faces, cam, phase), w)).item() / (2 * h))
    return float(np.mean(fds))


def _silhouette_gradient(move, faces, cam, w, spp, seeds):
    grads = []
    for seed in seeds:
        s = torch.zeros((), dtype=torch.float64, requires_grad=True)
        out = project_depth(move(s), faces, cam, silhouette_grad=True, spp=spp, seed=seed)
        (g,) = torch.autograd.grad(_loss(out.depth, out.mask, w), s)
        grads.append(g.item())
    return float(np.mean(grads)), grads


def _weights(kind):
    y, x = torch.meshgrid(torch.linspace(0, 1, RES), torch.linspace(0, 1, RES), indexing="ij")
    if kind == "smooth":
        w = 1.0 + 0.6 * torch.sin(5.0 * x + 1.0) * torch.cos(3.0 * y)
    else:
        w = torch.rand(RES, RES, generator=torch.Generator().manual_seed(3))
    return w.double()[None, None]


def _loss(depth, mask, w):
    return (depth.double() * w).sum() + 0.5 * (mask.double() * w.flip(-1)).sum()


@pytest.mark.parametrize("motion", ["translate", "scale"])
def test_silhouette_gradient_matches_finite_differences(motion):
    """Smooth image weights on depth and coverage; AD at spp 256, seeds 0-3, within 2 % of FD.

    The translation moves the chair towards the camera and sideways. (A purely sideways move makes
    the loss a small difference of large boundary terms; its AD estimate is unbiased but needs
    many more samples: per-seed spread ~5 % of each boundary term at 1024 spp.)
    """
    mesh = simple_chair()
    cam = Camera.orbit(12.0, 40.0, RES)
    v0 = torch.tensor(mesh.vertices, dtype=torch.float64)
    direction = torch.tensor(-cam.forward + 0.3 * cam.R[0], dtype=torch.float64)
    move = (lambda s: v0 + s * direction) if motion == "translate" else (lambda s: v0 * (1 + s))
    w = _weights("smooth")
    fd = _finite_difference(move, mesh.faces, cam, w, h=5e-3)
    ad, grads = _silhouette_gradient(move, mesh.faces, cam, w, spp=256, seeds=range(4))
    assert ad == pytest.approx(fd, rel=0.02), (grads, fd)


def test_silhouette_derivative_lands_in_the_right_pixels():
    """The per-pixel derivative image of coverage and depth under a sideways move, AD vs FD.

    Forward-mode AD through the integrator (spp 4096) against a phase-averaged FD image with a
    0.025 px step: the image of a pixel-averaged map is piecewise linear in the motion with a
    kink whenever an edge crosses a pixel boundary, so larger steps blur FD across pixels.
    A boundary term splatted one pixel off would give an error near 100 %.
    """
    mi, dr = backend.mitsuba(), backend.drjit()
    from ngp_mi.render.depth import projector_for, silhouette_renderer
    from ngp_mi.render.scene import set_sensor_camera

    mesh = box((0.05, 0.02, 0.0), (0.5, 0.4, 0.45))
    cam = Camera.orbit(15.0, 30.0, RES)
    v0 = torch.tensor(mesh.vertices, dtype=torch.float64)
    direction = np.array([1.0, 0.0, 0.0])
    h, rng = 1.5e-3, np.random.default_rng(0)
    fd = np.zeros((2, RES, RES))
    for _ in range(PHASES):
        phase = rng.uniform(-0.5, 0.5, 2)
        plus = _supersampled(v0 + h * torch.tensor(direction), mesh.faces, cam, phase)
        minus = _supersampled(v0 - h * torch.tensor(direction), mesh.faces, cam, phase)
        fd += np.stack([(p - m)[0, 0].numpy() for p, m in zip(plus, minus)]) / (2 * h * PHASES)

    projector = projector_for(mesh.faces, len(mesh.vertices))
    renderer = silhouette_renderer(cam, 4096)
    set_sensor_camera(renderer.sensor, cam)
    renderer.integrator.set_camera(cam)
    s = mi.Float(0.0)
    dr.enable_grad(s)
    dr.set_grad(s, 1.0)
    projector.params[projector.key] = mi.Float(mesh.vertices.ravel()) + mi.Float(np.tile(direction, 8)) * s
    projector.params.update()
    image = renderer.integrator.render_forward(projector.scene, projector.params, renderer.sensor, seed=1, spp=4096)
    ad = image.numpy()[..., :2].transpose(2, 0, 1)
    for channel, name in enumerate(("depth", "coverage")):
        error = np.abs(ad[channel] - fd[channel]).sum() / np.abs(fd[channel]).sum()
        assert error < 0.1, f"{name}: relative L1 error of the derivative image {error:.3f}"
        assert ad[channel].sum() == pytest.approx(fd[channel].sum(), rel=0.03)


def test_silhouette_maps_are_pixel_averages():
    mesh = simple_chair()
    cam = Camera.orbit(10.0, -20.0, RES)
    v = torch.tensor(mesh.vertices)
    out = project_depth(v, mesh.faces, cam, silhouette_grad=True, spp=256)
    depth_ref, mask_ref = _supersampled(v, mesh.faces, cam)
    assert (out.mask.double() - mask_ref).abs().mean() < 0.01
    assert (out.depth.double() - depth_ref).abs().mean() < 0.02
    assert out.mask.min() >= 0 and out.mask.max() <= 1


# ----------------------------------------------------------------------------- batching, reuse, errors

def test_batch_of_views_equals_single_views():
    mesh = simple_chair()
    cams = [Camera.orbit(t, p, 20) for t, p in ((0, 0), (15, 60), (5, -80))]
    v = torch.tensor(mesh.vertices)
    batch = project_depth(v, mesh.faces, cams)
    for i, cam in enumerate(cams):
        single = project_depth(v, mesh.faces, cam)
        for name in ("depth", "mask", "normal", "noc"):
            torch.testing.assert_close(getattr(batch, name)[i], getattr(single, name)[0])


def test_new_vertices_reuse_kernels_and_memory_stays_flat():
    mesh = simple_chair()
    cams = [Camera.orbit(10, 20, 32), Camera.orbit(5, -40, 32)]
    v0 = torch.tensor(mesh.vertices)

    def step(i):
        v = (v0 * (1 + 0.01 * math.sin(i))).requires_grad_()
        out = project_depth(v, mesh.faces, cams, silhouette_grad=(i % 2 == 0), spp=4, seed=i)
        (out.depth.sum() + out.normal.sum()).backward()

    for i in range(6):
        step(i)
    launched, compiled = compiled_kernels(lambda: [step(i) for i in range(6, 10)])
    assert launched and not compiled, "a new vertex set recompiled a kernel"
    rss = rss_mib()
    for i in range(10, 70):
        step(i)
    assert rss_mib() - rss < 40, f"RSS grew by {rss_mib() - rss:.1f} MiB over 60 calls"


def test_bad_input_is_named():
    mesh = box((0, 0, 0), (0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match=r"vertices must be \(V, 3\)"):
        project_depth(torch.zeros(8, 2), mesh.faces, Camera.orbit(0, 0, 8))
    with pytest.raises(ValueError, match="non-finite"):
        project_depth(torch.full((8, 3), float("nan")), mesh.faces, Camera.orbit(0, 0, 8))
    with pytest.raises(ValueError, match="one resolution"):
        project_depth(torch.tensor(mesh.vertices), mesh.faces, [Camera.orbit(0, 0, 8), Camera.orbit(0, 0, 16)])


@pytest.mark.parametrize("silhouette_grad", [False, True])
def test_shading_the_projected_maps_reaches_the_vertices(silhouette_grad):
    """The README's example: Π_v then R_BP, a loss on the image, a gradient on the mesh."""
    from ngp_mi.lights import overhead_rig
    from ngp_mi.render.shading import shade

    mesh = simple_chair()
    cameras = [Camera.orbit(10.0, 30.0, 32), Camera.orbit(5.0, -50.0, 32)]
    vertices = torch.tensor(mesh.vertices, requires_grad=True)
    maps = project_depth(vertices, mesh.faces, cameras, silhouette_grad=silhouette_grad, spp=8)
    albedo = torch.full((2, 3, 32, 32), 0.5)
    image = shade(maps.normal, albedo, maps.mask, overhead_rig(), cameras, mode="blinn_phong",
                  k_d=0.8, k_s=0.2, alpha=4.0)
    (image.mean() + maps.depth.mean() + maps.noc.mean()).backward()
    assert image.shape == (2, 3, 32, 32) and image.max() > 0
    assert torch.isfinite(vertices.grad).all() and vertices.grad.abs().sum() > 0
